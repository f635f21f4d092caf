"""The bridge between Blender data (strips, scene settings, preferences) and addon/.

Everything here reads Blender data and returns plain Python values; nothing here relights."""

from __future__ import annotations

import dataclasses
import pathlib

import bpy

from ..addon import engine
from ..addon.errors import InputError, ModelError, OutputError

# The extension's top-level package: "bl_ext.<repo>.portrait_relight" when installed.
PACKAGE = __package__.rpartition(".")[0]
BUNDLED_MODELS = pathlib.Path(__file__).resolve().parents[1] / "models"
FOOTAGE_TYPES = {'MOVIE', 'IMAGE'}
LINEAR = "Linear Rec.709"  # the colour space of the relit EXR frames (scene linear)


@dataclasses.dataclass(frozen=True)
class Job:
    """One relight run, gathered from the scene: everything the pipeline call needs."""
    strip_name: str
    clip: object                 # addon.pipeline.ClipSpec
    scene_frames: tuple          # scene frames to relight now (whole strip, or one farm chunk)
    clip_frames: tuple           # the same frames as 0-based indices into the clip
    out_dir: pathlib.Path        # the strip's folder of takes (addon/takes.py)
    model: engine.ModelCard
    options: object              # addon.pipeline.RelightOptions
    light_args: dict             # keyword arguments for ops.scene_light.light_schedule
    channel: int                 # the source strip's channel; results go above it
    frame_start: int             # the source strip's first visible scene frame
    frame_count: int             # its visible length
    numbers: tuple = ()          # the source's frame number of each clip frame (file names)
    digits: int = 4              # the zero padding of those numbers


def addon_prefs(context):
    """The add-on preferences, or None when the package runs without being enabled (tests)."""
    addon = context.preferences.addons.get(PACKAGE)
    return getattr(addon, "preferences", None) if addon else None


def models_dir(context, override: str = "") -> pathlib.Path:
    prefs = addon_prefs(context)
    chosen = override or (prefs.models_dir if prefs else "")
    return pathlib.Path(bpy.path.abspath(chosen)) if chosen else BUNDLED_MODELS


def scan_models(folder: pathlib.Path) -> tuple[list[engine.ModelCard], list[str]]:
    """(usable models sorted by expected time, a message for each unusable one) in ``folder``."""
    folder = pathlib.Path(folder)
    cards, problems = [], []
    for path in sorted(folder.glob("*.onnx")) if folder.is_dir() else ():
        try:
            cards.append(engine.load_card(path))
        except ModelError as err:
            problems.append(str(err))
    cards.sort(key=lambda c: (c.ms_per_frame is None, c.ms_per_frame or 0.0, c.preset))
    return cards, problems


def model_cards(folder: pathlib.Path) -> list[engine.ModelCard]:
    return scan_models(folder)[0]


def default_card(cards: list[engine.ModelCard]) -> engine.ModelCard | None:
    """The model an empty preset means: the one whose card is marked recommended (Portrait: its
    light reads as light on real faces), else the fastest of ``cards`` (scan_models' order)."""
    return next((c for c in cards if c.recommended), cards[0] if cards else None)


def preset_label(card: engine.ModelCard) -> str:
    """A preset as the panel shows it: its name, whether it is the recommended one, its time per
    frame and its held-out error, e.g. "Portrait (recommended): 22 ms per frame, held-out
    error 0.0634"."""
    ms, _ = card.timing
    error, _ = card.held_out_error
    time = f"{ms:.0f} ms per frame" if ms is not None else "time not measured"
    err = f"held-out error {error:.3g}" if error is not None else "error not measured"
    return f"{card.title}{' (recommended)' if card.recommended else ''}: {time}, {err}"


def choose_model(context, preset: str, override_dir: str = "") -> engine.ModelCard:
    folder = models_dir(context, override_dir)
    cards, problems = scan_models(folder)
    if not cards:
        if problems:
            raise ModelError(problems[0])
        raise ModelError(f"No relighting model is installed in {folder}. Install a model "
                         "(an .onnx file with its .json card) or set the models folder in the "
                         "add-on preferences.")
    for card in cards:
        if card.preset == preset:
            return card
    if not preset:
        return default_card(cards)
    raise ModelError(f"No model for the quality preset '{preset}' in {folder}; available: "
                     f"{', '.join(c.preset for c in cards)}.")


def builtin_hdri_names() -> list[str]:
    from . import scene_light  # another helper's module; imported lazily so the panel never breaks
    return sorted(scene_light.builtin_hdris())


def check_footage_strip(strip) -> None:
    """InputError unless ``strip`` is a movie or image strip that plays at normal speed."""
    if strip is None:
        raise InputError("No active strip: click a movie or image strip in the sequencer first.")
    if strip.type not in FOOTAGE_TYPES:
        kind = strip.type.lower().replace("_", " ")
        raise InputError(f"The strip '{strip.name}' is a {kind} strip, not footage. Select a movie "
                         "or image-sequence strip to relight.")
    if strip.use_reverse_frames or strip.strobe > 1.0 or len(strip.retiming_keys) > 0:
        raise InputError(f"The strip '{strip.name}' is reversed, strobed or retimed. Relight the "
                         "footage at normal speed, then apply those effects to the relit strip.")


def free_channel(strips, lowest: int, start: int, end: int) -> int:
    """The lowest channel >= ``lowest`` with no strip overlapping frames [start, end)."""
    channel = lowest
    while any(s.channel == channel and s.frame_final_start < end and s.frame_final_end > start
              for s in strips):
        channel += 1
    return channel


def content_index(strip, scene_frame: int) -> int:
    """0-based index into the strip's footage of what it shows at ``scene_frame``."""
    return int(scene_frame - round(strip.frame_start)) + int(strip.animation_offset_start)


def image_files(strip) -> list[str]:
    folder = bpy.path.abspath(strip.directory)
    return [str(pathlib.Path(folder) / e.filename) for e in strip.elements]


def source_numbering(strip) -> tuple[tuple[int, ...], int]:
    """(the frame number of each visible frame, the digits to pad them to): an image sequence's
    own numbers (shot.0998.exr: 998, 4 digits; files without numbers count up from the strip's
    first frame), a movie's scene frames. Relit files take these names (relit.0998.exr)."""
    from ..addon import numbered

    first = content_index(strip, strip.frame_final_start)
    count = int(strip.frame_final_duration)
    if strip.type == 'IMAGE':
        numbers, digits = numbered.sequence_numbering(image_files(strip), round(strip.frame_start))
        return tuple(numbers[first:first + count]), digits
    start = int(strip.frame_final_start)
    return tuple(range(start, start + count)), numbered.MOVIE_DIGITS


def clip_spec(strip, scene):
    """The visible part of a footage strip as an addon.pipeline.ClipSpec.

    A trimmed strip gives only its visible frames; colour space and fps come from the strip, and
    its first visible scene frame lets messages name frames as the timeline shows them."""
    from ..addon.pipeline import ClipSpec

    check_footage_strip(strip)
    first = content_index(strip, strip.frame_final_start)
    count = int(strip.frame_final_duration)
    if first < 0:
        raise InputError(f"The strip '{strip.name}' starts before its footage does; trim it so "
                         "every visible frame shows footage.")
    colorspace = strip.colorspace_settings.name
    if strip.type == 'MOVIE':
        path = bpy.path.abspath(strip.filepath)
        return ClipSpec(kind="movie", path=path, files=(), first=first, count=count,
                        colorspace=colorspace, fps=float(strip.fps),
                        scene_start=int(strip.frame_final_start))
    files = image_files(strip)
    if first + count > len(files):
        raise InputError(f"The strip '{strip.name}' shows {first + count - len(files)} frames "
                         "past the end of its image sequence; trim it to the images it has.")
    fps = scene.render.fps / scene.render.fps_base
    return ClipSpec(kind="images", path=str(pathlib.Path(files[0]).parent), files=tuple(files),
                    first=first, count=count, colorspace=colorspace, fps=float(fps),
                    scene_start=int(strip.frame_final_start))


def frames_to_run(strip, frame_range: tuple[int, int] | None) -> list[int]:
    """Scene frames to relight: the strip's visible frames, or their overlap with a farm chunk."""
    start, end = strip.frame_final_start, strip.frame_final_end - 1
    if frame_range is None:
        return list(range(start, end + 1))
    a, b = frame_range
    if a > b:
        raise InputError(f"The frame range {a}-{b} is empty: its start is after its end.")
    frames = list(range(max(a, start), min(b, end) + 1))
    if not frames:
        raise InputError(f"The frames {a}-{b} do not overlap the strip '{strip.name}', which shows "
                         f"frames {start}-{end}.")
    return frames


def output_dir(scene, strip, folder: str) -> pathlib.Path:
    """<output folder>/<folder for the strip's name>: one folder per strip, holding its takes
    (v001, v002, ...: addon/takes.py), so runs never mix (addon.pipeline.folder_name: readable,
    and distinct for distinct names)."""
    from ..addon.pipeline import folder_name

    if not folder:
        raise OutputError("No output folder is set; choose one in the Relight panel.")
    base = pathlib.Path(bpy.path.abspath(folder))
    if folder.startswith("//") and not bpy.data.filepath:
        raise OutputError("The output folder is relative to the .blend file, which is not saved "
                          "yet. Save the file or choose an absolute output folder.")
    return base / folder_name(strip.name)


ORT_PROVIDERS = {
    'CUDA': ["CUDAExecutionProvider", "CPUExecutionProvider"],
    'COREML': ["CoreMLExecutionProvider", "CPUExecutionProvider"],
    'DIRECTML': ["DmlExecutionProvider", "CPUExecutionProvider"],
    'CPU': ["CPUExecutionProvider"],
}


def light_args(scene, settings) -> dict:
    """Keyword arguments for scene_light.light_schedule from ``Scene.relight``."""
    import math

    hdri = bpy.path.abspath(settings.hdri_path) if settings.hdri_path else ""
    if settings.light_source == 'HDRI_FILE' and not hdri:
        raise InputError("The lighting is set to an HDRI file, but no file is chosen.")
    return dict(source=settings.light_source, hdri_path=hdri or None,
                hdri_builtin=settings.builtin_hdri if settings.light_source == 'BUILTIN' else None,
                rotation_deg=math.degrees(settings.rotation), exposure=settings.exposure,
                subject=settings.subject, camera=settings.camera or scene.camera,
                subject_radius=settings.subject_radius)


def gather_job(context, strip, *, models_override: str = "") -> Job:
    """Validate the strip and the settings and gather one run; RelightError on bad input."""
    from ..addon.pipeline import RelightOptions

    scene = context.scene
    settings = scene.relight
    clip = clip_spec(strip, scene)
    chunk = (settings.frame_start, settings.frame_end) if settings.use_frame_range else None
    scene_frames = frames_to_run(strip, chunk)
    first_visible = strip.frame_final_start
    out_dir = output_dir(scene, strip, settings.output_dir)
    model = choose_model(context, settings.preset, models_override)
    numbers, digits = source_numbering(strip)
    prefs = addon_prefs(context)
    options = RelightOptions(
        model_path=str(model.onnx_path), detail_transfer=settings.detail_transfer,
        write_matte=settings.write_matte, overwrite=settings.overwrite, takes=True,
        background=settings.background.lower(), exposure_mode=settings.exposure_mode.lower(),
        exr_compression=settings.exr_compression.lower(),
        providers=ORT_PROVIDERS.get(prefs.provider) if prefs else None,
        threads=(prefs.threads or None) if prefs else None)
    return Job(strip_name=strip.name, clip=clip, scene_frames=tuple(scene_frames),
               clip_frames=tuple(f - first_visible for f in scene_frames), out_dir=out_dir,
               model=model, options=options, light_args=light_args(scene, settings),
               channel=strip.channel, frame_start=first_visible,
               frame_count=int(strip.frame_final_duration), numbers=numbers, digits=digits)
