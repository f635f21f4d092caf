"""The per-clip pipeline: footage + one light vector per frame in, half-float EXR frames out.

One function, ``relight_clip``, serves the modal operator (on_progress / should_cancel), the
batch script and render-farm chunks (``frames``). Per frame:

    decode -> linear (colour.py) -> / s -> area-resize to the working size -> network (light / k)
    -> full-resolution transfer (detail.py) -> * k -> [0, 65504], half -> EXR

Frames stay channels-first (3, H, W) from the decoder to the EXR file (see detail.py), and so do
the per-frame stage functions below (what relight_image and the benchmarks run too).

``s`` is one exposure scale per clip from fixed sample frames over the whole clip, so chunks and
resumed runs agree bit for bit; ``k`` is the target light's mean radiance (k == 0: black frame,
network not run; a run whose light is black on every frame is refused before anything is
written). Decoding runs in a worker thread and writing in another while onnxruntime
runs, so the three overlap. Intrinsic presets (Portrait) frame the portrait first and blend each
frame's change of light with its neighbours' (temporal.py), inferring the neighbours just outside
the frames asked for, so the result never depends on how a clip is chunked.

With ``RelightOptions.takes`` (the strip runs), ``out_dir`` is the strip's folder of takes and
the run writes into the take that holds its identity, or a new one (takes.py).

Outputs (i = 0-based clip frame index): relit/relit_{i:06d}.exr, matte/matte_{i:06d}.exr (optional),
source_light/source_{i:06d}.npy, and relight_run.json (the run's identity). A frame is finished
when its relit file exists: it is renamed into place last, after its matte and source light.
Files are written under a temporary name first (frames.partial_path); a run sweeps away those
that a killed process of this machine left behind (see sweep_partials). A run holds its folder
(runlock.FolderLock): processes of one run (farm chunks) share it, another run is refused.
"""

from __future__ import annotations

import functools
import hashlib
import json
import os
import pathlib
import queue
import re
import threading
from dataclasses import dataclass, field

import numpy as np

from . import (blas, colour, contract, detail, engine, framing, frames, intrinsic, lightvec,
               normalise, outline, portrait, runlock, takes, temporal)
from .errors import Cancelled, InputError, LightingError, OutputError
from .frames import ClipInfo, probe_clip  # noqa: F401  (part of this module's API)

RUN_FILE = "relight_run.json"
BOXES_FILE = "relight_boxes.json"  # intrinsic models: the clip's smoothed portrait boxes
FRAMING_STEP = 3  # frames between two framing passes (a head moves little in 3 frames at 25 fps)
RUN_FORMAT = "relight-run/3"
EXPOSURE_MODES = ("keep", "physical")
DEFAULT_EXPOSURE_MODE = "keep"
GAIN_SAMPLES = 8  # frames, evenly spaced over the clip, that set its exposure gain


@dataclass(frozen=True)
class ClipSpec:
    kind: str                  # 'movie' | 'images'
    path: str                  # movie file; for 'images' the folder
    files: tuple[str, ...]     # for 'images': ordered absolute file paths, one per source frame
    first: int                 # 0-based index within the source of the first frame to relight
    count: int                 # number of frames to relight
    colorspace: str            # Blender colour-space name of the strip
    fps: float
    scene_start: int | None = None  # the scene frame showing clip frame 0, to name frames by


def frame_name(clip: ClipSpec, i: int) -> str:
    """How a message names 0-based clip frame ``i``: by its scene frame when the clip knows it."""
    if clip.scene_start is not None:
        return f"scene frame {clip.scene_start + int(i)}"
    return f"clip frame {int(i)} (0-based)"


def source_frame_name(clip: ClipSpec):
    """frame_name for an index into the source (the movie, or the image strip's files)."""
    return lambda index: frame_name(clip, int(index) - clip.first)


# What stands behind the relit subject: "network" its own output (the models repaint backgrounds),
# "keep" the source's background as it was, "relit" the source's background brightened and tinted
# by the change of light on a matte wall facing the camera (wall_gain, with the network's own
# estimate of the source light). "keep" and "relit" composite by the network's foreground matte.
BACKGROUNDS = ("network", "keep", "relit")
DEFAULT_BACKGROUND = "relit"


@dataclass(frozen=True)
class RelightOptions:
    model_path: str            # the .onnx; its card is the same stem + '.json'
    working_size: int | None = None   # network working resolution (long side); None = card
    detail_transfer: bool = True
    write_matte: bool = False
    providers: tuple[str, ...] | None = None
    threads: int | None = None
    overwrite: bool = False    # replace another run's output in out_dir instead of refusing
    # out_dir is a strip's folder of takes (addon/takes.py): the run writes into the take that
    # holds it, else a new take (overwrite: the latest take); RunResult.out_dir names the take.
    takes: bool = False
    # Blend each frame's change of light with its neighbours' (addon/temporal.py): steadier
    # shadow edges; a light that jumps still changes on its frame. Intrinsic presets only.
    temporal: bool = True
    exr_compression: str = "none"     # see frames.COMPRESSIONS; not part of the run identity
    # What stands behind the relit subject (BACKGROUNDS): the network's own output, or the
    # source's background composited in by the network's foreground matte, as it was or relit as
    # a wall facing the camera (the default: the models repaint backgrounds; training/evaluate.py
    # measures it).
    background: str = DEFAULT_BACKGROUND
    # "keep": the subject keeps the footage's overall exposure (one gain for the clip; the light
    # sets direction, colour and contrast, and an animated light still brightens and dims it);
    # "physical": absolute units, for scenes lit to scale (exposure_gain).
    exposure_mode: str = DEFAULT_EXPOSURE_MODE


@dataclass
class RunResult:
    out_dir: str
    relit_files: list[str]
    matte_files: list[str]
    written: int
    resumed: int
    exposure_scale: float
    warnings: list[str] = field(default_factory=list)
    model: str = ""            # the card's name
    provider: str = ""         # the onnxruntime execution provider that ran it


# Device names Windows reserves in every folder, with or without an extension.
_RESERVED = {"con", "prn", "aux", "nul", *(f"{d}{i}" for d in ("com", "lpt") for i in range(10))}
_HASHED = re.compile(r"_[0-9a-f]{8}$")


def folder_name(name: str) -> str:
    """The folder a strip called ``name`` writes into: the name itself where it is a plain,
    lower-case ASCII name (letters, digits, '.', '_', '-' inside), else a readable slug of it plus
    8 hex digits of the sha256 of the exact name. Distinct names never share a folder, even on
    file systems that ignore case (Windows, macOS): '顔' and '名前', or 'a/b', 'a b' and 'a_b',
    would otherwise all share one, and Overwrite on one strip deleted another's frames."""
    slug = re.sub(r"[^A-Za-z0-9._-]+", "_", name).strip("._-")
    plain = (slug and slug == name and name == name.lower() and not _HASHED.search(name)
             and name.split(".")[0] not in _RESERVED)
    if plain:
        return name
    folder = f"{slug or 'strip'}_{hashlib.sha256(name.encode('utf-8')).hexdigest()[:8]}"
    if folder.split(".")[0].lower() in _RESERVED:  # 'con.mov_...' is still 'con' to Windows
        folder = folder.replace(".", "_", 1)
    return folder


def relit_path(out_dir, i) -> str:
    return os.path.join(str(out_dir), "relit", f"relit_{int(i):06d}.exr")


def matte_path(out_dir, i) -> str:
    return os.path.join(str(out_dir), "matte", f"matte_{int(i):06d}.exr")


def source_path(out_dir, i) -> str:
    return os.path.join(str(out_dir), "source_light", f"source_{int(i):06d}.npy")


class Log:
    """Collects warnings (each once) and passes every message to the caller's ``log``."""

    def __init__(self, sink=None):
        self.sink = sink
        self.warnings: list[str] = []

    def info(self, msg: str) -> None:
        if self.sink:
            self.sink(msg)

    def warn(self, msg: str) -> None:
        if msg not in self.warnings:
            self.warnings.append(msg)
            self.info("Warning: " + msg)


# ---- checks and identity ------------------------------------------------------------------

def _check_clip(clip: ClipSpec) -> ClipInfo:
    if clip.kind not in ("movie", "images"):
        raise InputError(f"Unknown clip kind '{clip.kind}'; expected 'movie' or 'images'.")
    if clip.count < 1 or clip.first < 0:
        raise InputError(f"The clip range (first {clip.first}, {clip.count} frames) is empty or "
                         "negative; check the strip's trim.")
    if clip.kind == "images":
        if not clip.files:
            raise InputError("The image strip lists no files.")
        frames.check_sequence(clip.files[clip.first:clip.first + clip.count])
        info = probe_clip(list(clip.files[clip.first:clip.first + clip.count]))
        total = len(clip.files)
    else:
        info = probe_clip(clip.path)
        total = info.frame_count
    if clip.first + clip.count > total:
        raise InputError(f"The strip asks for source frames {clip.first}..{clip.first + clip.count - 1}"
                         f" but the footage has {total}; the file is shorter than the strip.")
    return info


def _check_lights(lights, count: int) -> np.ndarray:
    arr = np.asarray(lights)
    if arr.ndim != 4 or arr.shape[1:] != lightvec.SHAPE or arr.shape[0] not in (1, count):
        raise LightingError(f"Lights must have shape (1 or {count}, 16, 16, 3) for a clip of "
                            f"{count} frames, got {arr.shape}.")
    return np.stack([lightvec.validate(x, f"light vector of frame {i}")
                     for i, x in enumerate(arr)])


def black_lights(lights: np.ndarray, contract_name: str) -> list[bool]:
    """Per light vector: whether a frame relit by it comes out black. Presets that follow the
    light's brightness need light above lightvec.DARKEST; intrinsic presets keep the footage's
    exposure (the light sets direction and colour), so only a light of exactly zero is black."""
    if contract_name == contract.INTRINSIC_CONTRACT:
        return [not float(np.max(x)) > 0 for x in lights]
    return [lightvec.is_black(x) for x in lights]


def _check_not_black(clip: ClipSpec, lights: np.ndarray, contract_name: str,
                     selected: list[int], out: Log) -> None:
    """Refuse lighting that is black on every frame of the clip (every frame would be black: a
    scene without lamps or world, lamps at 0 W, an exposure of -100); warn about the frames to
    relight where an animated light goes black (a fade to black is a choice, not an error)."""
    dark = black_lights(lights, contract_name)
    if all(dark):
        raise LightingError(
            f"The lighting is black (its brightest value is {float(np.max(lights)):.3g}; a "
            f"half-float frame shows nothing below {lightvec.DARKEST:.3g}), so every frame would "
            "come out black. Light the subject: add a lamp with energy or a world HDRI, pick a "
            "studio HDRI, or raise the exposure.")
    black = [i for i in selected if dark[min(i, len(dark) - 1)]]
    if black:
        out.warn(f"The lighting is black on {len(black)} of the frames to relight (the first is "
                 f"{frame_name(clip, black[0])}); they come out black.")


def _check_frames(frames_sel, count: int) -> list[int]:
    sel = list(range(count)) if frames_sel is None else sorted(set(int(i) for i in frames_sel))
    bad = [i for i in sel if not 0 <= i < count]
    if bad:
        raise InputError(f"Frames {bad[:5]} are outside the clip (0..{count - 1}).")
    if not sel:
        raise InputError("No frames to relight: the frame range is empty.")
    return sel


def _file_stamp(path) -> list:
    """What identifies a source file wherever it is reached from (a symlink, another mount point
    of the same share on a farm machine): its name, size and modification time, the time in
    whole microseconds (network file systems report finer digits differently)."""
    st = os.stat(path)
    return [os.path.basename(path), st.st_size, st.st_mtime_ns // 1000]


def _source_files(clip: ClipSpec) -> list[str]:
    if clip.kind == "movie":
        return [clip.path]
    return list(clip.files[clip.first:clip.first + clip.count])


@functools.lru_cache(maxsize=1)
def engine_sha256() -> str:
    """sha256 over the engine's source (every module of this package, by name and content) and
    the extension's manifest beside it (its version and bundled wheels, onnxruntime's among
    them): what turns a model's outputs into frames. A run's identity holds it, so a take
    begun before an update of the extension is not finished by the updated one, whose frames
    may differ (a renderer change shows as a jump part way through the clip): the run goes to
    a new take, and a plain output folder is refused with the reason."""
    here = pathlib.Path(__file__).resolve().parent
    digest = hashlib.sha256()
    for path in [*sorted(here.glob("*.py")), here.parent / "blender_manifest.toml"]:
        if path.is_file():
            digest.update(path.name.encode() + b"\0" + path.read_bytes() + b"\0")
    return digest.hexdigest()


# What an artist reads for an identity's keys when a folder holds another run.
IDENTITY_WORDS = {"engine_sha256": "the version of the extension that made it",
                  "model_sha256": "the model", "lights_sha256": "the lighting",
                  "source": "the footage", "range": "the frame range",
                  "colorspace": "the footage's colour space", "settings": "the settings",
                  "format": "the format of its record"}


def run_identity(clip: ClipSpec, lights: np.ndarray, options: RelightOptions,
                 card: engine.ModelCard, working: int) -> dict:
    """What makes two runs produce the same frames (the chunk and resume state do not). The
    footage counts by its files (_file_stamp), not by the path it was reached through; the
    engine by its source (engine_sha256)."""
    src = hashlib.sha256(json.dumps([_file_stamp(f) for f in _source_files(clip)]).encode())
    light_hash = hashlib.sha256(str(lights.shape).encode() + lights.tobytes()).hexdigest()
    return {
        "format": RUN_FORMAT,
        "source": {"kind": clip.kind, "files_sha256": src.hexdigest()},
        "range": {"first": clip.first, "count": clip.count},
        "colorspace": clip.colorspace,
        "lights_sha256": light_hash,
        "model_sha256": card.sha256,
        "engine_sha256": engine_sha256(),
        "settings": {"working_size": working, "detail_transfer": options.detail_transfer,
                     "write_matte": options.write_matte, "background": options.background,
                     "exposure_mode": options.exposure_mode, "temporal": options.temporal},
    }


def _read_run(out_dir: str) -> dict | None:
    p = os.path.join(out_dir, RUN_FILE)
    if not os.path.isfile(p):
        return None
    try:
        with open(p, encoding="utf-8") as f:
            return json.load(f)
    except (OSError, json.JSONDecodeError):
        return {}  # unreadable: treated as another run


def _write_text(path: str, text: str) -> None:
    frames.write_atomic(path, lambda tmp: pathlib.Path(tmp).write_text(text, encoding="utf-8"))


_OUTPUT_NAME = re.compile(r"^(relit_\d{6}\.exr|matte_\d{6}\.exr|source_\d{6}\.npy)$")


def sweep_partials(out_dir: str) -> list[str]:
    """Remove the temporary files that writers of this run's own folders left when they were
    killed mid-write (only names this pipeline writes, only from dead processes of this
    machine; a concurrent chunk's file in progress is kept). Returns the removed paths."""
    removed = []
    for folder, pattern in ((out_dir, re.compile(re.escape(RUN_FILE) + "$")),
                            (os.path.join(out_dir, "relit"), _OUTPUT_NAME),
                            (os.path.join(out_dir, "matte"), _OUTPUT_NAME),
                            (os.path.join(out_dir, "source_light"), _OUTPUT_NAME)):
        removed += frames.sweep_stale_partials(folder, pattern)
    return removed


def _clear_outputs(out_dir: str) -> None:
    """Remove a previous run's frames (only files this pipeline names; nothing else)."""
    for sub, prefix, ext in (("relit", "relit_", ".exr"), ("matte", "matte_", ".exr"),
                             ("source_light", "source_", ".npy")):
        d = pathlib.Path(out_dir, sub)
        if d.is_dir():
            for p in d.iterdir():
                if p.name.startswith(prefix) and p.name.endswith(ext):
                    p.unlink()


def _check_not_source(clip: ClipSpec, out_dir: str) -> None:
    outs = {os.path.realpath(os.path.join(out_dir, s)) for s in ("relit", "matte",
                                                                   "source_light")}
    for f in _source_files(clip):
        if os.path.realpath(os.path.dirname(f)) in outs or os.path.realpath(f) == os.path.realpath(
                os.path.join(out_dir, RUN_FILE)):
            raise OutputError(f"The output folder {out_dir} would write where the source footage "
                              f"lives ({f}); choose another output folder.")


def _create_folder(out_dir: str) -> None:
    try:
        for sub in ("relit", "matte", "source_light"):
            os.makedirs(os.path.join(out_dir, sub), exist_ok=True)
    except OSError as err:
        raise OutputError(f"Cannot create the output folder {out_dir} ({err}); choose a folder "
                          "you can write to.") from err
    if not os.access(out_dir, os.W_OK):
        raise OutputError(f"The output folder {out_dir} is not writable; choose another.")


def prepare_output(out_dir: str, identity: dict, overwrite: bool) -> dict | None:
    """Create the folders; return the stored run record when resuming, else None. Refuses a
    folder holding another run (or unknown relit frames) unless ``overwrite``. Called under the
    folder's setup lock (runlock.FolderLock)."""
    _create_folder(out_dir)
    stored = _read_run(out_dir)
    if stored is not None and stored.get("identity") == identity:
        return stored
    has_frames = any(pathlib.Path(out_dir, "relit").glob("relit_*.exr"))
    if stored is None and not has_frames:
        return None
    if not overwrite:
        what = "another relight run" if stored else "relit frames from an unknown run"
        diff = ""
        if stored and isinstance(stored.get("identity"), dict):
            keys = [k for k in identity if stored["identity"].get(k) != identity[k]]
            diff = f" (it differs in: {', '.join(IDENTITY_WORDS.get(k, k) for k in keys)})"
        raise OutputError(f"The output folder {out_dir} already holds {what}{diff}. Choose "
                          "another folder, or enable Overwrite to replace it.")
    _clear_outputs(out_dir)
    return None


# ---- per-frame stages (also timed one by one by bench/pipeline_1080p.py) --------------------

@dataclass(frozen=True)
class Plan:
    """Everything a frame needs that is fixed for the run."""
    space: colour.ColourSpace
    scale: float               # s, exposure scale
    size: tuple[int, int]      # full (width, height)
    working: tuple[int, int]   # working (height, width)
    detail_transfer: bool
    write_matte: bool
    compression: str
    background: str = "network"


def linearise(pixels: np.ndarray, plan: Plan) -> tuple[np.ndarray, int, float]:
    """Channels-first code values (3, H, W) -> exposure-normalised linear (3, H, W); NaN/Inf/
    negative become 0. Returns (image, number of values replaced, an upper bound of the
    image's values)."""
    gain = 1.0 / plan.scale
    lin = colour.to_linear_planar(pixels, plan.space, gain)
    if (np.issubdtype(pixels.dtype, np.integer) and plan.space.matrix is None
            and plan.space.curve != "ocio"):
        # Code values through a curve: finite, non-negative, bounded by the table's top.
        lut = colour.integer_lut(plan.space, 8 * pixels.dtype.itemsize)
        return lin, 0, float(lut[-1]) * gain
    mask = ~np.isfinite(lin) | (lin < 0)  # floats and gamut matrices can give these
    bad = int(np.count_nonzero(mask))
    if bad:
        lin[mask] = 0.0
    return lin, bad, float(lin.max()) if lin.size else 0.0


def shrink_planar(x_full: np.ndarray, plan: Plan, fullres: detail.FullRes) -> np.ndarray:
    return fullres.shrink_planar(x_full, *plan.working)


def infer_planar(session: engine.RelightSession, x_low: np.ndarray, light: np.ndarray):
    """(relit_low (3, h, w), source_light, foreground (h, w), k) in normalised units; k == 0:
    nothing run."""
    light_n, k = normalise.normalise_light(light)
    if k <= 0:
        return None, np.zeros(lightvec.SHAPE, np.float32), None, 0.0
    res = session.run_planar(x_low, light_n)
    fg = res.parsing[session.card.foreground_channel]
    return res.relit, res.source_light, fg, k


def coefficients_planar(x_low: np.ndarray, relit_low, k: float, plan: Plan,
                        fullres: detail.FullRes):
    """Working-resolution (a, b), each (3, h, w), with out = up(a) * x_full + up(b) in
    scene-linear units, finite; None for a black frame. The network's relit output comes back to
    scene linear by k alone (contract.RELIT_SCALE: image / s is the scene under lights / s, so a
    decoder fed light / k renders relit / k; training.model.units.normalise_sample)."""
    if relit_low is None:
        return None
    gain = k
    if plan.detail_transfer and x_low.shape[1:] != (plan.size[1], plan.size[0]):
        return fullres.coefficients_planar(x_low, relit_low, gain)
    b = np.nan_to_num(np.asarray(relit_low, np.float32) * np.float32(gain), nan=0.0,
                      posinf=1e30, neginf=-1e30)  # plain upsampling: a = 0
    return np.zeros_like(b), b


def finish_planar(x_full: np.ndarray, ab, x_max: float,
                  fullres: detail.FullRes) -> tuple[np.ndarray, int, float]:
    """(the full-resolution half-float frame (3, H, W), within [0, 65504]; how many values were
    clamped to the half maximum; the most negative value that was raised to 0, 0.0 if none was):
    radiance is never negative, though the network's output and the detail transfer's
    extrapolation can be (a little in normal use, hugely when the light overflows it)."""
    if ab is None:
        return np.zeros(x_full.shape, np.float16), 0, 0.0
    y, may_clamp, lowest = fullres.finish_planar(x_full, *ab, x_max)
    return y, _count_clamped(y) if may_clamp else 0, lowest


def _count_clamped(y: np.ndarray) -> int:
    """Values at +-65504 (half bits 0x7BFF once the sign is masked)."""
    return int(np.count_nonzero((y.view(np.uint16) & 0x7FFF) == 0x7BFF))


def background_coefficients(ab, fg, plan: Plan, gain=None):
    """(a, b) of coefficients_planar with the source's own background composited in by the
    foreground matte ``fg`` (h, w), at the working resolution: finishing is linear in (a, b), so
    m (up(a) x + up(b)) + (1 - m) s g x becomes up(m a + (1 - m) s g) x + up(m b), which costs
    nothing at full resolution (exact where the matte or a is flat; across the silhouette the
    blend follows the bilinearly enlarged matte, as the written matte does). ``gain``: per
    channel (3,) for background "relit", 1 when None."""
    a, b = ab
    m = np.clip(np.nan_to_num(np.asarray(fg, np.float32), nan=0.0), 0.0, 1.0)[None]
    g = np.ones(3, np.float32) if gain is None else np.asarray(gain, np.float32)
    back = (np.float32(plan.scale) * g)[:, None, None]
    return m * a + (1.0 - m) * back, m * b


def with_background(ab, fg, light: np.ndarray, source: np.ndarray, plan: Plan):
    """The frame's (a, b) under ``plan.background``: unchanged for "network" or a black frame
    (``ab`` None), else background_coefficients, with wall_gain(light, source) for "relit"
    (``source``: the network's source-light estimate in the footage's units)."""
    if plan.background == "network" or ab is None:
        return ab
    gain = wall_gain(light, source) if plan.background == "relit" else None
    return background_coefficients(ab, fg, plan, gain)


_TO_CAMERA = np.array([0.0, 0.0, 1.0])


def wall_gain(target: np.ndarray, source: np.ndarray) -> np.ndarray:
    """(3,) how much brighter, per channel, a matte wall facing the camera is under ``target``
    than under ``source`` (absolute light vectors): the kept background's change of light for
    background "relit". A source channel near 0 (1% of the mean of the three) is floored there;
    a source with no light on the wall at all falls back to the ratio of total power."""
    e_t = lightvec.irradiance(target, _TO_CAMERA)
    e_s = lightvec.irradiance(source, _TO_CAMERA)
    if not np.all(np.isfinite(e_s)) or float(np.mean(e_s)) <= 1e-12:
        e_t, e_s = lightvec.total_power(target), lightvec.total_power(source)
        if not np.all(np.isfinite(e_s)) or float(np.mean(e_s)) <= 1e-12:
            return np.zeros(3, np.float32)
    gain = e_t / np.maximum(e_s, 0.01 * float(np.mean(e_s)))
    return np.nan_to_num(gain, nan=0.0, posinf=65504.0).astype(np.float32)


def matte_full(fg, plan: Plan, fullres: detail.FullRes) -> np.ndarray:
    w, h = plan.size
    if fg is None:
        return np.zeros((h, w), np.float16)
    return fullres.upsample_half_planar(np.asarray(fg, np.float32)[None], h, w, 0.0, 1.0)[0]


def _save_npy(path: str, arr: np.ndarray) -> None:
    def save(tmp):
        with open(tmp, "wb") as f:  # a file, so np.save adds no .npy to the name
            np.save(f, arr)
    frames.write_atomic(path, save)


def write_frame(out_dir: str, i: int, relit: np.ndarray, matte, source: np.ndarray,
                plan: Plan) -> None:
    """Write one frame's files, relit (half (3, H, W)) last."""
    _save_npy(source_path(out_dir, i), np.nan_to_num(source).astype(np.float32))
    if plan.write_matte:
        frames.write_exr_planes(matte_path(out_dir, i), matte, plan.compression)
    frames.write_exr_planes(relit_path(out_dir, i), relit, plan.compression)


# ---- exposure -----------------------------------------------------------------------------

def clip_exposure(clip: ClipSpec, plan: Plan, fullres: detail.FullRes) -> float:
    """s from normalise.sample_frame_indices over the whole clip (never the chunk)."""
    idx = normalise.sample_frame_indices(clip.count)
    probe = Plan(plan.space, 1.0, plan.size, plan.working, False, False, plan.compression)
    lows = [shrink_planar(linearise(d.pixels, probe)[0], probe, fullres).transpose(1, 2, 0)
            for d in frames.iter_frames(clip.kind, clip.path, clip.files,
                                        [clip.first + i for i in idx], plan.size, planar=True,
                                        name=source_frame_name(clip))]
    return normalise.exposure_scale(lows)


# ---- portrait framing (intrinsic models) ----------------------------------------------------

def portrait_boxes(clip: ClipSpec, plan: Plan, session, out_dir: str, identity: dict,
                   fullres: detail.FullRes, should_cancel=None) -> tuple[list, list[int]]:
    """(the portrait's box in every frame of the clip, the frames where none was found). Boxes
    are smoothed over the whole clip (never the chunk, so farm chunks agree), and a frame where
    none was found takes its neighbours' framing: a face missed for a frame is still relit,
    and where there really is no subject the network's matte is empty there and the frame comes
    out unchanged. Kept in BOXES_FILE so a resumed run frames exactly as the first did."""
    path = os.path.join(out_dir, BOXES_FILE)
    if os.path.isfile(path):
        try:
            stored = json.loads(pathlib.Path(path).read_text(encoding="utf-8"))
            if stored.get("identity") == identity and len(stored["boxes"]) == clip.count:
                return ([None if b is None else framing.Box(*b) for b in stored["boxes"]],
                        [int(i) for i in stored["missing"]])
        except (OSError, ValueError, TypeError, KeyError):
            pass  # unreadable: framed again below
    # Every FRAMING_STEP-th frame (and the last) is framed; smoothing interpolates the others.
    probe = sorted(set(range(0, clip.count, FRAMING_STEP)) | {clip.count - 1})
    raw: list = [None] * clip.count
    prior = None
    for d in frames.iter_frames(clip.kind, clip.path, clip.files,
                                [clip.first + i for i in probe], plan.size, planar=True,
                                name=source_frame_name(clip)):
        if should_cancel and should_cancel():
            raise Cancelled("Cancelled while framing the portrait; nothing was written, run "
                            "again to start.")
        # the portrait is followed from the last framed frame's box, when it had one
        prior = raw[d.index - clip.first] = portrait.find_box(
            session, linearise(d.pixels, plan)[0], fullres, prior)
    boxes = framing.smooth_boxes(raw)
    missing = [i for i in probe if raw[i] is None]
    _write_text(path, json.dumps(
        {"identity": identity, "framed": probe, "found": len(probe) - len(missing),
         "missing": missing, "boxes": [None if b is None else list(b.to_tuple()) for b in boxes]}))
    return boxes, missing


def exposure_gain(clip: ClipSpec, lights: np.ndarray, plan: Plan, session, fullres,
                  boxes, mode: str) -> float:
    """The clip's exposure gain under ``mode`` (EXPOSURE_MODES), from GAIN_SAMPLES frames evenly
    spaced over the whole clip (never the chunk, so farm chunks agree): "keep", the subject's
    luminance summed over those frames is the footage's (the subject's for intrinsic presets,
    the frame's for the end-to-end ones); "physical", absolute units (the
    end-to-end networks' own level; for intrinsic presets skin of albedo
    intrinsic.SKIN_ALBEDO under the target's irradiance, portrait.clip_gain)."""
    if mode == "physical" and boxes is None:
        return 1.0
    n = min(GAIN_SAMPLES, clip.count)
    idx = sorted({int(round(v)) for v in np.linspace(0, clip.count - 1, n)})
    stats = []
    for d in frames.iter_frames(clip.kind, clip.path, clip.files, [clip.first + i for i in idx],
                                plan.size, planar=True, name=source_frame_name(clip)):
        i = d.index - clip.first
        x_full = linearise(d.pixels, plan)[0]
        light = lights[min(i, len(lights) - 1)]
        if boxes is not None:
            stats.append(portrait.relight_frame(session, x_full, light, boxes[i], exposure=1.0,
                                                fullres=fullres, scale=plan.scale,
                                                outline_fit=False))
            continue
        x_low = shrink_planar(x_full, plan, fullres)
        relit_low, source, fg, k = infer_planar(session, x_low, light)
        ab = coefficients_planar(x_low, relit_low, k, plan, fullres)
        if ab is None:
            continue
        ab = with_background(ab, fg, light, source * np.float32(plan.scale), plan)
        stats.append(frame_luminance(x_low, ab, plan.scale))
    return portrait.clip_gain(stats, mode, plan.scale)


def frame_luminance(x_low: np.ndarray, ab, scale: float):
    """The frame's luminance summed in the footage and in the relit frame out = a x_low + b,
    both in the footage's units (x_low is the footage / scale), as a portrait.FrameResult for
    clip_gain. The whole frame, not the network's matte: the end-to-end networks relight the
    whole picture, and a gain that stopped at an uncertain matte would draw its outline."""
    x_lum = intrinsic.luminance(x_low) * np.float32(scale)
    out_lum = intrinsic.luminance(ab[0] * x_low + ab[1])
    return portrait.FrameResult(None, None, None, True, None, float(x_lum.sum()),
                                float(out_lum.sum()))


def scaled(ab, gain: float):
    """(a, b) times the clip's exposure gain."""
    if ab is None or gain == 1.0:
        return ab
    return ab[0] * np.float32(gain), ab[1] * np.float32(gain)


# ---- the run ------------------------------------------------------------------------------

_DONE = object()


class _Worker(threading.Thread):
    """A thread that runs ``fn`` and keeps its exception for the main thread to raise."""

    def __init__(self, fn, name):
        super().__init__(name=name, daemon=True)
        self.fn, self.error = fn, None

    def run(self):
        try:
            self.fn()
        except BaseException as err:  # re-raised in the main thread by _raise_if_failed
            self.error = err


def _raise_if_failed(*workers):
    for w in workers:
        if w.error is not None:
            raise w.error


@blas.one_thread()  # the run's threads too: numpy's BLAS on one thread (addon/blas.py)
def relight_clip(clip: ClipSpec, lights: np.ndarray, out_dir: str, options: RelightOptions,
                 frames: range | None = None, on_progress=None, should_cancel=None,
                 log=None) -> RunResult:
    """Relight ``frames`` (0-based clip indices; None = all) of ``clip`` into ``out_dir``.

    Raises InputError / LightingError / ModelError / OutputError with a message for the user,
    and Cancelled when ``should_cancel()`` turns true (finished frames are kept; run again to
    resume)."""
    out = Log(log)
    out_dir = str(out_dir)
    if options.exposure_mode not in EXPOSURE_MODES:
        raise InputError(f"Unknown exposure mode {options.exposure_mode!r}; use one of "
                         f"{', '.join(EXPOSURE_MODES)}.")
    if options.background not in BACKGROUNDS:
        raise InputError(f"Unknown background {options.background!r}; use one of "
                         f"{', '.join(BACKGROUNDS)}.")
    info = _check_clip(clip)
    lights = _check_lights(lights, clip.count)
    selected = _check_frames(frames, clip.count)
    _check_not_black(clip, lights, engine.load_card(options.model_path).contract, selected, out)
    space = colour.lookup(clip.colorspace)
    if space.is_data:
        out.warn(f"The strip's colour space is {clip.colorspace}; its values are relit as if "
                 "they were linear light.")
    if info.has_alpha:
        out.warn("The footage has an alpha channel; it is ignored (the relit frames are "
                 "opaque).")
    if info.channels in (1, 2):
        out.warn("The footage is greyscale; it is relit as grey RGB.")
    # No spinning: idle onnxruntime threads would take the core from the decode/write threads.
    session = engine.new_session(options.model_path, options.providers, options.threads,
                                 spin=False, working_size=options.working_size)
    working = session.card.working_size
    identity = run_identity(clip, lights, options, session.card, working)
    run = hashlib.sha256(json.dumps(identity, sort_keys=True).encode()).hexdigest()
    if options.takes:
        out_dir = takes.choose_take(out_dir, run, options.overwrite, out.warn, should_cancel)
    _check_not_source(clip, out_dir)
    _create_folder(out_dir)
    # Held until the run ends, however it ends: another run cannot write here meanwhile.
    with runlock.FolderLock(out_dir, run, note=out.warn, should_cancel=should_cancel) as lock:
        stored = prepare_output(out_dir, identity, options.overwrite)
        swept = sweep_partials(out_dir)
        if swept:
            out.info(f"Removed {len(swept)} unfinished file(s) that an interrupted run left.")
        plan = Plan(space, 1.0, (info.width, info.height),
                    detail.working_shape(info.height, info.width, working),
                    options.detail_transfer, options.write_matte, options.exr_compression)
        fullres = detail.FullRes(threads=1)
        scale = (float(stored["exposure_scale"]) if stored is not None
                 else clip_exposure(clip, plan, fullres))
        plan = Plan(space, scale, plan.size, plan.working, plan.detail_transfer, plan.write_matte,
                    plan.compression, options.background)
        boxes, missing = None, []
        todo = [i for i in selected if not os.path.isfile(relit_path(out_dir, i))]
        if isinstance(session, engine.IntrinsicSession) and (todo or stored is None):
            boxes, missing = portrait_boxes(clip, plan, session, out_dir, identity, fullres,
                                            should_cancel)
        if stored is not None:
            gain = float(stored["exposure_gain"])
        else:
            gain = exposure_gain(clip, lights, plan, session, fullres, boxes,
                                 options.exposure_mode)
            _write_text(os.path.join(out_dir, RUN_FILE), json.dumps(
                {"identity": identity, "exposure_scale": scale, "exposure_gain": gain,
                 "model": session.card.name, "providers": session.providers,
                 "source_path": os.path.realpath(clip.path)}, indent=2))
        lock.end_setup()  # what the folder holds is settled: other chunks of this run may start
        out.info(f"Relighting {len(selected)} frames at {plan.working[1]}x{plan.working[0]} with "
                 f"{session.card.name} on {session.providers[0]}; exposure scale {scale:.6g}, "
                 f"{options.exposure_mode} exposure (gain {gain:.6g}).")

        resumed = len(selected) - len(todo)
        if resumed:
            out.info(f"Resuming: {resumed} of {len(selected)} frames are already done.")
        missed = len(set(missing) & set(todo))
        if missed:
            out.warn(f"No portrait was found in {missed} frame(s); they are framed like their "
                     "neighbours (a frame with no subject comes out unchanged). The subject's "
                     "face must be visible and at least a few pixels across.")
        written = _run_frames(clip, lights, out_dir, plan, session, fullres, todo, resumed,
                              len(selected), on_progress, should_cancel, out, boxes, gain,
                              options.temporal)
    return RunResult(out_dir, [relit_path(out_dir, i) for i in selected],
                     [matte_path(out_dir, i) for i in selected] if options.write_matte else [],
                     written, resumed, scale, out.warnings, session.card.name,
                     session.providers[0])


def _run_frames(clip, lights, out_dir, plan, session, fullres, todo, resumed, total,
                on_progress, should_cancel, out: Log, boxes=None, gain: float = 1.0,
                steady: bool = False) -> int:
    """Decode, linearise and shrink (worker thread) -> network and low-resolution coefficients
    (this thread) -> full-resolution finish and write (worker thread), each frame channels-first.
    ``steady``: each frame's coefficients are blended with its neighbours' (addon/temporal.py),
    which are decoded and inferred too where the run does not relight them.

    Any thread's failure stops the other two; this thread then raises the first failure (a
    worker's is raised with its own traceback). Frames written before it stay finished, so a
    rerun resumes after them."""
    stop = threading.Event()
    decoded: queue.Queue = queue.Queue(maxsize=2)
    results: queue.Queue = queue.Queue(maxsize=2)
    # each key written by one thread
    counts = {"bad_in": 0, "clamped": 0, "written": 0, "negative": 0, "lowest": 0.0}
    # Only the intrinsic path's coefficients are the change of light alone (a ratio and a
    # highlight); the end-to-end models' also carry the frame's content, which would ghost.
    steady = steady and boxes is not None
    wanted = set(todo)
    infer = temporal.context_frames(todo, clip.count) if steady else list(todo)

    def produce():
        try:
            for d in frames.iter_frames(clip.kind, clip.path, clip.files,
                                        [clip.first + i for i in infer], plan.size, planar=True,
                                        name=source_frame_name(clip)):
                if stop.is_set():
                    return
                x_full, bad, x_max = linearise(d.pixels, plan)
                counts["bad_in"] += bad
                low = None if boxes is not None else shrink_planar(x_full, plan, fullres)
                _put(decoded, (d.index - clip.first, x_full, x_max, low), stop)
        finally:
            _put(decoded, _DONE, stop, force=True)

    def consume():
        try:
            while True:
                item = results.get()
                if item is _DONE:
                    return
                i, x_full, x_max, ab, fg, source, edge = item
                relit, clamped, lowest = finish_planar(x_full, ab, x_max, fullres)
                matte = matte_full(fg, plan, fullres) if plan.write_matte else None
                if edge is not None:
                    relit = outline.apply(edge[0], x_full, relit, plan.scale, fullres)
                    if matte is not None:
                        matte = outline.refine_matte(edge[1], x_full, matte)
                write_frame(out_dir, i, relit, matte, source, plan)
                counts["clamped"] += clamped
                if lowest < 0:
                    counts["negative"] += 1
                    counts["lowest"] = min(counts["lowest"], lowest)
                counts["written"] += 1
        except BaseException:
            stop.set()  # the decoder stops too; this thread's error is raised by the caller
            raise

    reported = [-1]

    def progress():  # called from this (the caller's) thread only, once per new count
        done = resumed + counts["written"]
        if on_progress and done != reported[0]:
            reported[0] = done
            on_progress(done, total, f"{done} of {total} frames")

    # frame -> (x_full, x_max, ab, fg, source, light's signature, the outline's fits of the
    # change and the matte): this frame and its neighbours
    window = {}

    def emit(i):
        x_full, x_max, ab, fg, source, sig, edge = window[i]
        if steady and ab is not None:
            near = []
            for j in (i - 1, i + 1):
                other = window.get(j)
                near.append(other[2] if other is not None and other[2] is not None
                            and temporal.alike(sig, other[5]) else None)
            ab = temporal.blend(ab, *near, mask=fg)
        _put(results, (i, x_full, x_max, ab, fg, source, edge), stop, alive=writer)
        _raise_if_failed(writer)

    reader, writer = _Worker(produce, "relight-decode"), _Worker(consume, "relight-write")
    reader.start()
    writer.start()
    cancelled = False
    try:
        while True:
            progress()
            if should_cancel and should_cancel():
                cancelled = True
                break
            item = _get(decoded, reader, writer)
            if item is _DONE:
                break
            i, x_full, x_max, x_low = item
            light = lights[min(i, len(lights) - 1)]
            if boxes is not None:  # intrinsic: framing, buffers, renderer (addon/portrait.py)
                res = portrait.relight_frame(session, x_full, light, boxes[i], exposure=gain,
                                             fullres=fullres, matte_fit=plan.write_matte)
                s = np.float32(plan.scale)  # x_full is the footage / s
                ab, fg, edge = (res.a * s, res.b * s), res.matte, (res.outline, res.matte_outline)
                source = np.zeros(lightvec.SHAPE, np.float32)
            else:
                relit_low, source, fg, k = infer_planar(session, x_low, light)
                ab = coefficients_planar(x_low, relit_low, k, plan, fullres)
                source = source * np.float32(plan.scale)  # the source light in footage units
                ab = scaled(with_background(ab, fg, light, source, plan), gain)
                edge = None
            window[i] = (x_full, x_max, ab, fg, source,
                         temporal.signature(light) if steady else None, edge)
            # A frame goes out once its following neighbour is in (or there is none).
            if steady and i - 1 in wanted and i - 1 in window:
                emit(i - 1)
            if i in wanted and (not steady or i + 1 >= clip.count):
                emit(i)
            for j in [j for j in window if not steady or j < i - 1]:
                del window[j]
    finally:
        stop.set()
        _drain(decoded)
        _put(results, _DONE, threading.Event(), alive=writer)  # the writer finishes its queue
        writer.join()
        reader.join()  # it stops at its next frame (stop is set and nobody reads its queue)
    _raise_if_failed(writer, reader)
    progress()
    if counts["bad_in"]:
        out.warn(f"{counts['bad_in']} input values were NaN, infinite or negative and were "
                 "treated as 0.")
    if counts["clamped"]:
        out.warn(f"{counts['clamped']} output values exceeded the half-float range (65504) or "
                 "were not finite, and were clamped; lower the light or the exposure.")
    if counts["negative"]:
        out.warn(f"Relit values below 0 (down to {counts['lowest']:.3g}) on "
                 f"{counts['negative']} frame(s) were set to 0: light cannot be negative. Small "
                 "ones are the network's error; large ones mean the light is far brighter than "
                 "the footage, so lower the light or the exposure.")
    if cancelled:
        raise Cancelled(f"Cancelled after {resumed + counts['written']} of {total} frames; the "
                        "finished frames are kept, run again to resume.")
    return counts["written"]


def _put(q: queue.Queue, item, stop: threading.Event, force=False, alive=None) -> None:
    """Put with a timeout loop, giving up when ``stop`` is set (unless ``force``: then make
    room by dropping what nobody will read) or when the ``alive`` consumer has ended."""
    while True:
        if stop.is_set() and not force:
            return
        if alive is not None and not alive.is_alive():
            return
        try:
            q.put(item, timeout=0.1)
            return
        except queue.Full:
            if force and stop.is_set():
                _drain(q)


def _get(q: queue.Queue, producer: _Worker, consumer: _Worker):
    """The next item, or _DONE once the producer has ended; raises a worker's failure as soon
    as it is seen (a failed writer must not leave this thread waiting on the decoder)."""
    while True:
        try:
            return q.get(timeout=0.1)
        except queue.Empty:
            _raise_if_failed(consumer)
            if not producer.is_alive() and q.empty():
                _raise_if_failed(producer)
                return _DONE


def _drain(q: queue.Queue) -> None:
    try:
        while True:
            q.get_nowait()
    except queue.Empty:
        pass
