"""The batch run: relight without the UI, on a workstation, in CI or as one chunk of a farm job.

One argument parser and one ``main()`` serve every way in: ``blender -b ... -P
scripts/relight_batch.py -- ...`` and plain python on the bpy module (the script only finds the
extension and calls ``main``), and ``blender -c relight ...``, the command-line command this
module registers. What to relight:

- ``--strip NAME``: a strip of the open .blend, as the panel's Relight Strip does;
- ``--demo``: the built-in demo clip;
- ``--input PATH``: a movie or an image sequence with no .blend. A strip is made for it with the
  Import Footage operator in an empty file, or in ``--lights-from FILE`` (opened, its lamps,
  world, camera and Relight settings used, never saved).

Every way writes a take of the strip, ``OUT/STRIP/v001`` (a new take when the lighting or
settings change, ops/relight_strip.py), with the frames named like the source's (shot.1001.exr
-> relit.1001.exr); the last line of a run names the take's folder.

Exit statuses are EXIT_STATUS below; ``--help`` lists them with the models and studio HDRIs."""

from __future__ import annotations

import argparse
import json
import math
import os
import pathlib
import re
import signal
import sys
import time
import traceback

import bpy

from ..addon.errors import Cancelled, RelightError
from . import bridge, import_footage, relight_strip

COMMAND = "relight"            # blender -c relight
NAME = "relight_batch"         # how messages start
ROOT = pathlib.Path(__file__).resolve().parents[1]   # the extension folder
DEMO_STUDIO = "sunset"  # the demo's lighting: one of Blender's bundled studio HDRIs
MAX_EXPOSURE = 128.0  # stops: 2^128 takes any light past float32's range
MAX_ROTATION = 36000.0  # degrees: a hundred turns is already more than anyone means

USAGE = """
  blender -b [scene.blend] -P scripts/relight_batch.py -- (--strip NAME | --input PATH | --demo) [options]
  blender -c relight [scene.blend] (--strip NAME | --input PATH | --demo) [options]
  python scripts/relight_batch.py [scene.blend] (--strip NAME | --input PATH | --demo) [options]"""

EXIT_STATUS = """exit status (one line on stderr says what happened; tracebacks only with --debug):
  0    done
  1    a problem with the input, lighting, model or output; the message says what to do
  2    bad arguments (unknown options, a non-finite or absurd --exposure or --rotation, ...)
  3    an unexpected error, a bug: rerun with --debug for the traceback and report it
  130  cancelled with Ctrl-C; finished frames are kept, run again to resume
  143  stopped by SIGTERM (a farm manager), the same as Ctrl-C"""

EXAMPLES = """examples:
  blender -c relight --input shot/ --studio sunset --out relit/      (shot.1001.exr -> relit/shot/v001/relit.1001.exr)
  blender -c relight --input take.mov --lights-from lights.blend --out relit/
  blender -b scene.blend -P scripts/relight_batch.py -- --strip "Take 1" --frames 1-50"""


class BatchError(Exception):
    """A failure with a message for the user (exit status 1)."""


def script_args(argv: list[str]) -> list[str]:
    """The script's own arguments: after "--" under Blender, else everything after argv[0]."""
    return argv[argv.index("--") + 1:] if "--" in argv else argv[1:]


def frame_range(text: str) -> tuple[int, int]:
    m = re.fullmatch(r"\s*(-?\d+)\s*(?:-\s*(-?\d+)\s*)?", text)
    if not m:
        raise argparse.ArgumentTypeError(f"'{text}' is not a frame range like 1-250")
    start = int(m.group(1))
    end = int(m.group(2)) if m.group(2) is not None else start
    if end < start:
        raise argparse.ArgumentTypeError(f"the frame range {text} ends before it starts")
    return start, end


def bounded_float(name: str, unit: str, limit: float):
    """An argparse type: a finite number within +-``limit``."""
    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"'{text}' is not a number of {unit}") from None
        if not math.isfinite(value) or abs(value) > limit:
            raise argparse.ArgumentTypeError(f"{name} must be a finite number of {unit} between "
                                             f"{-limit:g} and {limit:g}, got '{text}'")
        return value
    return parse


def installed_lists(models: str = "") -> str:
    """The help's list of the presets in the models folder and of the studio HDRIs."""
    folder = bridge.models_dir(bpy.context, str(pathlib.Path(models).resolve()) if models else "")
    cards, problems = bridge.scan_models(folder)
    lines = [f"presets (--preset) in {folder}:"]
    lines += [f"  {c.preset:<12} {c.summary}" for c in cards] or ["  (none installed)"]
    lines += [f"  unusable: {p}" for p in problems]
    studios = bridge.builtin_hdri_names()
    lines += ["studio HDRIs (--studio): " + (", ".join(studios) or "(none in this Blender)")]
    return "\n".join(lines)


def build_parser(prog: str = NAME, lists: str = "") -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog=prog, usage=USAGE, formatter_class=argparse.RawDescriptionHelpFormatter,
        description="Relight portrait footage headless: a strip of a .blend, or a movie or "
                    "image sequence with no .blend (--input).",
        epilog="\n\n".join(part for part in (EXAMPLES, EXIT_STATUS, lists) if part))
    p.add_argument("blend", nargs="?", help="the .blend file to open")
    what = p.add_argument_group("what to relight (one of)")
    what.add_argument("--strip", help="name of the movie or image strip of the .blend")
    what.add_argument("--input", metavar="PATH",
                      help="a movie, an image of a numbered sequence, or a folder holding one: "
                           "relit with no .blend; frames keep their numbers "
                           "(shot.1001.exr -> OUT/<clip>/v001/relit.1001.exr)")
    what.add_argument("--demo", action="store_true", help="relight the built-in demo clip")
    footage = p.add_argument_group("footage given with --input")
    footage.add_argument("--input-colorspace", metavar="NAME",
                         help="its colour space as Blender names it, e.g. 'ACEScg' or "
                              "'Filmic Log' (default: Blender's choice for the file: sRGB for "
                              "movies and 8-bit images, Linear Rec.709 for EXR)")
    footage.add_argument("--start-frame", type=int, metavar="N",
                         help="scene frame of its first frame (default: the first file's number "
                              "for an image sequence, the scene's start frame for a movie)")
    footage.add_argument("--lights-from", metavar="FILE",
                         help="a .blend whose lamps, world, camera and Relight settings light "
                              "the footage (opened, never saved); alone it lights with what the "
                              "file holds, or add --scene-lights or --world")
    light = p.add_argument_group("lighting (default: the .blend's Relight panel)")
    one = light.add_mutually_exclusive_group()
    one.add_argument("--hdri", metavar="PATH", help="light with this equirectangular HDRI")
    one.add_argument("--studio", metavar="NAME", help="light with a studio HDRI bundled with "
                                                      "Blender (listed below)")
    one.add_argument("--scene-lights", action="store_true", help="light with the scene's lamps")
    one.add_argument("--world", action="store_true", help="light with the scene's world HDRI")
    light.add_argument("--rotation", type=bounded_float("--rotation", "degrees", MAX_ROTATION),
                       metavar="DEG", help="turn the lighting (degrees)")
    light.add_argument("--exposure", type=bounded_float("--exposure", "stops", MAX_EXPOSURE),
                       metavar="EV", help="scale the lighting by 2^EV")
    light.add_argument("--exposure-mode", choices=["keep", "physical"],
                       help="keep the footage's exposure, or let the light's brightness set it "
                            "(default: the .blend's setting)")
    out = p.add_argument_group("run")
    out.add_argument("--preset", help="quality preset (model) to use, listed below")
    out.add_argument("--exr-compression", choices=["none", "rle", "zips", "zip", "piz"],
                     help="compression of the relit EXRs, all lossless (default: the .blend's "
                          "setting, PIZ in a new file)")
    out.add_argument("--models", metavar="DIR", help="folder of models (default: preferences)")
    out.add_argument("--out", metavar="DIR", help="output folder: DIR/STRIP/v001, v002, ... one "
                                                  "take per lighting (default: the .blend's "
                                                  "setting)")
    out.add_argument("--frames", type=frame_range, metavar="A-B",
                     help="scene frames to relight (one farm chunk)")
    out.add_argument("--matte", action="store_true", help="also write the portrait matte")
    out.add_argument("--background", choices=["network", "keep", "relit"],
                     help="what stands behind the relit subject: the network's output, the "
                          "footage's own background as it was, or relit as a wall facing the "
                          "camera (default: the .blend's setting)")
    out.add_argument("--keep-background", action="store_true",
                     help="the same as --background keep")
    out.add_argument("--overwrite", action="store_true",
                     help="replace the strip's latest take instead of making a new one when the "
                          "lighting or settings changed (the same ones resume their take)")
    out.add_argument("--save", action="store_true", help="save the .blend with the relit strip")
    out.add_argument("--progress", choices=["text", "json"], default="text",
                     help="json: one JSON object per line on stdout (state, frame, total, fps, "
                          "eta) and nothing else there; other messages go to stderr")
    out.add_argument("--debug", action="store_true", help="show tracebacks of unexpected errors")
    return p


def parse_args(argv: list[str], prog: str = NAME) -> argparse.Namespace:
    """The options in ``argv`` (the script's own, see script_args); SystemExit(2) with a message
    for bad ones, SystemExit(0) after --help."""
    argv = _join_negative_ranges(argv)
    lists = ""
    if "-h" in argv or "--help" in argv:
        known, _ = build_parser(prog).parse_known_args(
            [a for a in argv if a not in ("-h", "--help")])
        lists = installed_lists(known.models or "")
    p = build_parser(prog, lists)
    args = p.parse_args(argv)
    modes = [m for m in ("--strip", "--input", "--demo")
             if getattr(args, m[2:].replace("-", "_"))]
    if len(modes) != 1:
        p.error("give either --strip NAME or --demo, or --input PATH"
                + (f" (not {' and '.join(modes)})" if modes else ""))
    if args.keep_background and args.background not in (None, "keep"):
        p.error(f"--keep-background is --background keep; it contradicts --background "
                f"{args.background}: give one of them")
    for flag in ("input_colorspace", "start_frame", "lights_from"):
        if getattr(args, flag) is not None and not args.input:
            p.error(f"--{flag.replace('_', '-')} goes with --input PATH")
    if args.input:
        if args.blend:
            p.error("with --input, give the .blend that holds the lights as --lights-from FILE")
        if args.save:
            p.error("--save needs a .blend to save into; --input makes none (relight a strip of "
                    "a .blend with --strip NAME to add the result to it)")
        if not args.out:
            p.error("--input needs --out DIR for the relit frames")
        if (args.scene_lights or args.world) and not args.lights_from:
            p.error(f"--{'scene-lights' if args.scene_lights else 'world'} with --input needs "
                    "--lights-from FILE, the .blend that holds them")
        if not (args.hdri or args.studio or args.lights_from):
            p.error("--input needs lighting: --hdri PATH, --studio NAME or --lights-from FILE")
    return args


def _join_negative_ranges(argv: list[str]) -> list[str]:
    """'--frames -10-5' as '--frames=-10-5': argparse takes a value that starts with '-' and is
    not a plain number for an option (scene frames may be negative, and farm chunks say so)."""
    out = []
    for arg in argv:
        if out and out[-1] == "--frames" and re.fullmatch(r"-\d+\s*-\s*-?\d+", arg):
            out[-1] = f"--frames={arg}"
        else:
            out.append(arg)
    return out


# ---- setting up the scene ---------------------------------------------------------------------

def open_blend(path: str) -> None:
    blend = pathlib.Path(path).resolve()
    if not blend.is_file():
        raise BatchError(f"The .blend file {blend} does not exist.")
    bpy.ops.wm.open_mainfile(filepath=str(blend))


def call(op, **kwargs) -> None:
    """Run an operator; its error report becomes a BatchError with the operator's message."""
    try:
        op(**kwargs)
    except RuntimeError as err:
        raise BatchError(re.sub(r"^Error:\s*", "", str(err).strip())) from None


def demo_frames() -> pathlib.Path:
    """The first frame of the built-in demo clip (a synthetic portrait made by the project)."""
    folder = ROOT / "demo"
    frames = sorted(p for p in folder.rglob("*") if p.suffix.lower() in (".png", ".exr")
                    and re.search(r"\d+$", p.stem)) if folder.is_dir() else []
    if not frames:
        raise BatchError(f"The demo clip is missing: {folder} holds no numbered PNG or EXR frames. "
                         "Make it with `.venv/bin/python -m training.make_demo_clip`.")
    return frames[0]


def demo_preflight(args) -> pathlib.Path:
    """The demo's first frame, or one BatchError naming everything the demo still lacks."""
    missing = []
    try:
        first = demo_frames()
    except BatchError as err:
        missing.append(str(err))
    folder = bridge.models_dir(bpy.context, args.models or "")
    if not bridge.model_cards(folder):
        missing.append(f"No trained model is installed in {folder}: it needs an .onnx model "
                       "with its .json card (made by the training, see README.md).")
    if missing:
        raise BatchError("cannot run the demo yet:\n  - " + "\n  - ".join(missing))
    return first


def set_up_demo(args) -> str:
    first = demo_preflight(args)
    bpy.ops.wm.read_homefile(use_empty=True)
    call(bpy.ops.relight.import_footage, filepath=str(first), frame_start=1)
    scene = bpy.context.scene
    info = ROOT / "demo" / "clip.json"
    fps = json.loads(info.read_text()).get("fps") if info.is_file() else None
    if fps:
        scene.render.fps, scene.render.fps_base = int(round(fps)), round(fps) / fps
    if not (args.hdri or args.scene_lights or args.world or args.studio):
        args.studio = DEMO_STUDIO
    if args.rotation is None:  # show animated light: the studio turns once around the head
        bpy.context.preferences.edit.keyframe_new_interpolation_type = 'LINEAR'
        strip = scene.sequence_editor.active_strip
        for frame, turn in ((strip.frame_final_start, 0.0), (strip.frame_final_end - 1, 1.0)):
            scene.relight.rotation = turn * 2.0 * math.pi
            scene.relight.keyframe_insert("rotation", frame=frame)

    if args.out is None:
        args.out = str(ROOT / "out" / "demo")
    return bpy.context.scene.sequence_editor.active_strip.name


def first_footage_file(path: pathlib.Path) -> pathlib.Path:
    """The file Import Footage is given: the movie, or the first image of the sequence that
    the image or folder holds."""
    from ..addon import frames

    if path.is_dir():
        return pathlib.Path(frames.list_sequence(path)[0])
    if not path.is_file():
        raise BatchError(f"The footage {path} does not exist.")
    if not is_image(path):
        return path  # a movie
    return import_footage.sequence_files(path)[0]  # one image stands for its whole sequence


def is_image(path: pathlib.Path) -> bool:
    """Whether Import Footage takes ``path`` for an image of a sequence (else for a movie)."""
    from ..addon import frames

    return path.suffix.lower() in frames.IMAGE_EXTS


def set_up_input(args) -> str:
    """A strip for --input in an empty file, or in --lights-from FILE (which is never saved);
    its name."""
    from ..addon import frames

    first = first_footage_file(pathlib.Path(args.input).resolve())
    if args.lights_from:
        open_blend(args.lights_from)
    else:
        bpy.ops.wm.read_homefile(use_empty=True)
    scene = bpy.context.scene
    if args.start_frame is not None:
        start = args.start_frame
    elif not is_image(first):
        start = scene.frame_start  # a movie
    else:
        start = (frames.frame_number(first) or (None, scene.frame_start))[1]
    call(bpy.ops.relight.import_footage, filepath=str(first), frame_start=start)
    strip = scene.sequence_editor.active_strip
    if args.input_colorspace:
        settings = strip.colorspace_settings
        try:
            settings.name = args.input_colorspace
        except TypeError:
            names = [i.identifier for i in settings.bl_rna.properties["name"].enum_items]
            raise BatchError(f"There is no colour space named '{args.input_colorspace}'; this "
                             f"Blender has: {', '.join(names)}.") from None
    if args.lights_from and not (args.hdri or args.studio or args.scene_lights or args.world):
        use_file_lighting(scene)
    return strip.name


def use_file_lighting(scene) -> None:
    """--lights-from alone: the file's own Relight lighting where it set one, else what the
    file holds (lamps, its world, or both)."""
    settings = scene.relight
    if settings.is_property_set("light_source"):
        return
    lamps = any(obj.type == 'LIGHT' for obj in scene.objects)
    settings.light_source = ('WORLD_AND_LAMPS' if lamps and scene.world else
                             'LAMPS' if lamps else 'WORLD')


def apply_settings(scene, args) -> None:
    s = scene.relight
    if args.hdri:
        s.light_source, s.hdri_path = 'HDRI_FILE', str(pathlib.Path(args.hdri).resolve())
    elif args.scene_lights:
        s.light_source = 'LAMPS'
    elif args.world:
        s.light_source = 'WORLD'
    elif args.studio:
        s.light_source = 'BUILTIN'
        try:
            s.builtin_hdri = args.studio
        except TypeError:
            raise BatchError(f"There is no studio HDRI named '{args.studio}'; choose one of "
                             f"{', '.join(bridge.builtin_hdri_names())}.") from None
    if args.rotation is not None:
        s.rotation = math.radians(args.rotation)
    if args.exposure is not None:
        s.exposure = args.exposure
    apply_exposure_mode(s, args.exposure_mode)
    if args.preset:
        s.preset = args.preset
    if args.exr_compression:
        s.exr_compression = args.exr_compression.upper()
    if args.out:
        s.output_dir = str(pathlib.Path(args.out).resolve()) + "/"
    s.use_frame_range = args.frames is not None
    if args.frames:
        s.frame_start, s.frame_end = args.frames
    s.write_matte = args.matte or s.write_matte
    if args.background or args.keep_background:
        s.background = (args.background or "keep").upper()
    s.overwrite = args.overwrite


def apply_exposure_mode(settings, mode: str | None) -> None:
    """--exposure-mode keep|physical into the Relight settings' exposure mode."""
    if mode is not None:
        settings.exposure_mode = mode.upper()


# ---- the run ----------------------------------------------------------------------------------

def relight(strip: str, models: str) -> None:
    """Run the relight operator. Its failure is raised as the exception that ended it (the
    operator keeps it: a RelightError for the user, a Cancelled, or a bug), so main() can
    choose the exit status and show a bug's traceback only with --debug."""
    relight_strip.last_error = None
    try:
        done = bpy.ops.relight.relight_strip(strip=strip, models_dir=models, show_traceback=False)
    except RuntimeError as err:
        if relight_strip.last_error is not None:
            raise relight_strip.last_error from None
        raise BatchError(re.sub(r"^Error:\s*", "", str(err).strip())) from None
    if relight_strip.last_error is not None:
        raise relight_strip.last_error
    if done != {'FINISHED'}:
        raise BatchError(f"the relight operator ended with {sorted(done)}")


def run_frames(scene, strip) -> list[int]:
    """The scene frames this run relit: the strip's, or their overlap with --frames."""
    s = scene.relight
    return bridge.frames_to_run(strip, (s.frame_start, s.frame_end) if s.use_frame_range else None)


def run(args, progress: "Progress") -> None:
    if args.blend:
        open_blend(args.blend)
    if args.models:
        args.models = str(pathlib.Path(args.models).resolve())
    if args.demo:
        strip = set_up_demo(args)
    elif args.input:
        strip = set_up_input(args)
    else:
        strip = args.strip
    apply_settings(bpy.context.scene, args)
    started = time.perf_counter()
    relight(strip, args.models or "")
    scene = bpy.context.scene
    source = scene.sequence_editor.strips[strip]
    out = pathlib.Path(relight_strip.last_result.out_dir)
    names = relight_strip.last_published
    where = f"{out} ({names[0]} to {names[-1]})" if len(names) > 1 else f"{out / names[0]}"
    if args.save:
        if not bpy.data.filepath:
            raise BatchError("--save needs a .blend file to save into; open one first.")
        bpy.ops.wm.save_mainfile()
    seconds = time.perf_counter() - started
    progress.done(len(run_frames(scene, source)), out, seconds)
    progress.say(f"{NAME}: done in {seconds:.1f} s; relit frames are in {where}")


class Progress:
    """How a run reports. Text (the default): the operator prints progress lines on stdout and
    failures go to stderr. JSON: one object per line on stdout, nothing else there: everything
    else written to the process's stdout (Blender's own lines too) goes to stderr meanwhile."""

    def __init__(self, mode: str = "text"):
        self.json = mode == "json"
        self.stream = None
        self.started = None     # perf_counter at the first progress report
        self.first = 0          # frames already done then (resumed)
        self.last = (0, 0)      # (done, total) last reported

    def open(self) -> None:
        if not self.json:
            return
        sys.stdout.flush()
        self.stream = os.fdopen(os.dup(1), "w", encoding="utf-8", buffering=1)
        os.dup2(2, 1)
        relight_strip.progress_sink, relight_strip.log_sink = self.frame, self.log

    def close(self) -> None:
        if self.stream is None:
            return
        relight_strip.progress_sink = relight_strip.log_sink = None
        sys.stdout.flush()
        if not bpy.app.binary_path:
            # The bpy module: the caller's process goes on, so it gets its stdout back. Blender
            # exits after the run, and what it prints on the way out stays on stderr.
            os.dup2(self.stream.fileno(), 1)
        self.stream.close()
        self.stream = None

    def emit(self, state: str, **fields) -> None:
        self.stream.write(json.dumps({"state": state, **fields}) + "\n")
        self.stream.flush()

    def rates(self, done: int, total: int) -> dict:
        elapsed = time.perf_counter() - self.started if self.started is not None else 0.0
        fps = (done - self.first) / elapsed if elapsed > 0 and done > self.first else None
        eta = (total - done) / fps if fps else (0.0 if done >= total else None)
        return {"frame": done, "total": total, "fps": None if fps is None else round(fps, 3),
                "eta": None if eta is None else round(eta, 1)}

    def frame(self, done, total=None, *_):
        """The pipeline's on_progress: ``done`` of ``total`` frames finished (resumed ones too)."""
        done, total = int(done), int(total or 0)
        if self.started is None:
            self.started, self.first, self.last = time.perf_counter(), done, (done, total)
            self.emit("started", **self.rates(done, total))
        elif (done, total) != self.last:
            self.last = (done, total)
            self.emit("frame", **self.rates(done, total))

    def log(self, message: str) -> None:
        print(f"relight: {message}", file=sys.stderr, flush=True)

    def say(self, line: str) -> None:
        print(line, file=sys.stderr if self.json else sys.stdout, flush=True)

    def done(self, total: int, out: pathlib.Path, seconds: float) -> None:
        if not self.json:
            return
        if self.started is None:
            self.frame(total, total)
        self.emit("done", **self.rates(total, total), output=str(out), seconds=round(seconds, 3))

    def end(self, state: str, code: int, message: str) -> None:
        """The run stopped: 'failed' or 'cancelled', with its exit status."""
        if self.json and self.stream is not None:
            fields = self.rates(*self.last) if self.started is not None else {
                "frame": 0, "total": None, "fps": None, "eta": None}
            self.emit(state, **fields, exit=code, message=message)


# ---- exit statuses ----------------------------------------------------------------------------

def _stop(signum, frame):
    """SIGTERM (a farm manager stopping the job) cancels like Ctrl-C: the run stops at once,
    keeps its finished frames and releases its output folder."""
    _stop.signum = signum
    raise KeyboardInterrupt


_stop.signum = signal.SIGINT


def _wants_json(argv: list[str]) -> bool:
    return any(a == "--progress=json" or (a == "--progress" and argv[i + 1:i + 2] == ["json"])
               for i, a in enumerate(argv))


def main(argv=None, prog: str = NAME) -> int:
    """Relight as ``argv`` says (sys.argv by default; Blender's own arguments before "--" are
    skipped) and return the exit status (EXIT_STATUS)."""
    own = script_args(sys.argv if argv is None else list(argv))
    try:
        args = parse_args(own, prog=prog)
    except SystemExit as stop:  # --help (0) or bad arguments (2): argparse has said why
        code = stop.code if isinstance(stop.code, int) else (0 if stop.code is None else 2)
        if code and _wants_json(own):
            print(json.dumps({"state": "failed", "frame": 0, "total": None, "fps": None,
                              "eta": None, "exit": code, "message": "bad arguments"}),
                  flush=True)
        return code
    _stop.signum = signal.SIGINT
    # Ctrl-C raises KeyboardInterrupt here, under Blender too (which has its own handler).
    handlers = (signal.signal(signal.SIGINT, signal.default_int_handler),
                signal.signal(signal.SIGTERM, _stop))
    progress = Progress(args.progress)
    progress.open()
    try:
        return _run_reporting(args, progress)
    finally:
        progress.close()
        signal.signal(signal.SIGINT, handlers[0])
        signal.signal(signal.SIGTERM, handlers[1])


def _run_reporting(args, progress: Progress) -> int:
    try:
        run(args, progress)
    except BatchError as err:
        return _failed(progress, 1, str(err))
    except KeyboardInterrupt:
        return _cancelled(progress)
    except Cancelled:
        return _cancelled(progress)
    except RelightError as err:
        return _failed(progress, 1, str(err))
    except Exception as err:  # noqa: BLE001 - the last line of defence: one clear line
        if args.debug:
            traceback.print_exception(err)
        text = f"unexpected error ({type(err).__name__}: {' '.join(str(err).split())})"
        print(f"{NAME}: {text}; "
              + ("this is a bug, please report it with the traceback above" if args.debug else
                 "rerun with --debug for the traceback and report it"), file=sys.stderr)
        progress.end("failed", 3, text)
        return 3
    return 0


def _failed(progress: Progress, code: int, message: str) -> int:
    print(f"{NAME}: error: {message}", file=sys.stderr)
    progress.end("failed", code, message)
    return code


def _cancelled(progress: Progress) -> int:
    code = 128 + int(_stop.signum)
    print(f"{NAME}: cancelled, run again to resume", file=sys.stderr)
    progress.end("cancelled", code, "cancelled; finished frames are kept, run again to resume")
    return code


# ---- blender -c relight -----------------------------------------------------------------------

def cli_command(argv: list[str]) -> int:
    """``blender -c relight ARGS``: Blender hands over ARGS; the exit status is main()'s."""
    return main([COMMAND, *argv], prog=f"blender -c {COMMAND}")


_cli_handle = None
classes = ()  # no operator here: a command-line command


def register():
    global _cli_handle
    _cli_handle = bpy.utils.register_cli_command(COMMAND, cli_command)


def unregister():
    global _cli_handle
    if _cli_handle is not None:
        bpy.utils.unregister_cli_command(_cli_handle)
        _cli_handle = None
