"""Relight a strip headless: on a workstation, in CI, or as one chunk of a render-farm job.

    blender -b scene.blend -P scripts/relight_batch.py -- --strip NAME \\
        [--hdri PATH | --scene-lights | --studio NAME] [--preset P] [--out DIR] [--frames A-B]
    python scripts/relight_batch.py [scene.blend] --strip NAME ...      (the bpy module)
    python scripts/relight_batch.py --demo                              (the built-in demo clip)

Without a lighting option the lighting set in the .blend's Relight panel is used. --frames takes
scene frames; outputs do not depend on how a clip is split, so chunks may run anywhere, in any
order, at the same time (chunks of one run share the output folder; another run is refused
while one is writing there).

Exit status, with one line on stderr saying what happened (tracebacks only with --debug):
  0    done
  1    a problem with the input, lighting, model or output; the message says what to do
  2    bad arguments (unknown options, a non-finite or absurd --exposure or --rotation, ...)
  3    an unexpected error, a bug: rerun with --debug for the traceback and report it
  130  cancelled with Ctrl-C (143: stopped by SIGTERM); finished frames are kept, run again
       to resume
"""

from __future__ import annotations

import argparse
import importlib
import json
import math
import importlib.util
import pathlib
import re
import signal
import sys
import time
import traceback

EXT_ID = "portrait_relight"
HERE = pathlib.Path(__file__).resolve().parent
DEMO_STUDIO = "sunset"  # the demo's lighting: one of Blender's bundled studio HDRIs


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


MAX_EXPOSURE = 128.0  # stops: 2^128 takes any light past float32's range
MAX_ROTATION = 36000.0  # degrees: a hundred turns is already more than anyone means


def parse_args(argv: list[str]) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog="relight_batch", description=__doc__.split("\n\n")[0],
                                epilog="Exit status: 0 done, 1 input/lighting/model/output "
                                       "problem (the message says what to do), 2 bad "
                                       "arguments, 3 unexpected error (rerun with --debug), "
                                       "130 cancelled with Ctrl-C (143 by SIGTERM; run again "
                                       "to resume).")
    p.add_argument("blend", nargs="?", help="the .blend file to open (with the bpy module)")
    p.add_argument("--strip", help="name of the movie or image strip to relight")
    p.add_argument("--demo", action="store_true", help="relight the built-in demo clip")
    light = p.add_mutually_exclusive_group()
    light.add_argument("--hdri", metavar="PATH", help="light with this equirectangular HDRI")
    light.add_argument("--scene-lights", action="store_true", help="light with the scene's lamps")
    light.add_argument("--world", action="store_true", help="light with the scene's world HDRI")
    light.add_argument("--studio", metavar="NAME", help="light with a bundled studio HDRI")
    p.add_argument("--rotation", type=bounded_float("--rotation", "degrees", MAX_ROTATION),
                   metavar="DEG", help="turn the lighting (degrees)")
    p.add_argument("--exposure", type=bounded_float("--exposure", "stops", MAX_EXPOSURE),
                   metavar="EV", help="scale the lighting by 2^EV")
    p.add_argument("--preset", help="quality preset (model) to use")
    p.add_argument("--models", metavar="DIR", help="folder of models (default: preferences)")
    p.add_argument("--out", metavar="DIR", help="output folder (default: the .blend's setting)")
    p.add_argument("--frames", type=frame_range, metavar="A-B", help="scene frames to relight")
    p.add_argument("--matte", action="store_true", help="also write the portrait matte")
    p.add_argument("--background", choices=["network", "keep", "relit"],
                   help="what stands behind the relit subject: the network's output, the "
                        "footage's own background as it was, or relit as a wall facing the camera "
                        "(default: the .blend's setting)")
    p.add_argument("--keep-background", action="store_true",
                   help="the same as --background keep")
    p.add_argument("--overwrite", action="store_true", help="redo frames an earlier run made")
    p.add_argument("--save", action="store_true", help="save the .blend with the relit strip")
    p.add_argument("--debug", action="store_true", help="show tracebacks of unexpected errors")
    args = p.parse_args(argv)
    if bool(args.strip) == bool(args.demo):
        p.error("give either --strip NAME or --demo")
    if args.keep_background and args.background not in (None, "keep"):
        p.error(f"--keep-background is --background keep; it contradicts --background "
                f"{args.background}: give one of them")
    return args


def enabled_extension():
    import bpy

    for name in bpy.context.preferences.addons.keys():
        if name == EXT_ID or name.endswith("." + EXT_ID):
            return importlib.import_module(name)
    return None


def load_extension():
    """The extension package: the installed, enabled copy if there is one, else the extension
    folder that holds this script (loaded under its id, as Blender would; no sys.path edits)."""
    import bpy

    ext = enabled_extension()
    if ext is None and not bpy.app.binary_path:
        # The bpy module starts without the user's preferences; Blender itself has them loaded.
        bpy.ops.wm.read_userpref()
        ext = enabled_extension()
    if ext is not None:
        return ext
    if EXT_ID in sys.modules:
        return sys.modules[EXT_ID]
    root = HERE.parent
    if not (root / "blender_manifest.toml").is_file():
        raise BatchError(f"The Portrait Relight extension is not enabled, and {root} is not the "
                         "extension folder. Install and enable the extension, or run this script "
                         "from the extension's own scripts/ folder.")
    spec = importlib.util.spec_from_file_location(
        EXT_ID, root / "__init__.py", submodule_search_locations=[str(root)])
    module = importlib.util.module_from_spec(spec)
    sys.modules[EXT_ID] = module
    spec.loader.exec_module(module)
    module.register()
    return module


def open_blend(path: str) -> None:
    import bpy

    blend = pathlib.Path(path).resolve()
    if not blend.is_file():
        raise BatchError(f"The .blend file {blend} does not exist.")
    bpy.ops.wm.open_mainfile(filepath=str(blend))


def demo_frames() -> pathlib.Path:
    """The first frame of the built-in demo clip (a synthetic portrait made by the project)."""
    folder = HERE.parent / "demo"
    frames = sorted(p for p in folder.rglob("*") if p.suffix.lower() in (".png", ".exr")
                    and re.search(r"\d+$", p.stem)) if folder.is_dir() else []
    if not frames:
        raise BatchError(f"The demo clip is missing: {folder} holds no numbered PNG or EXR frames. "
                         "Make it with `.venv/bin/python -m training.make_demo_clip`.")
    return frames[0]


def demo_preflight(ext, args) -> pathlib.Path:
    """The demo's first frame, or one BatchError naming everything the demo still lacks."""
    import bpy

    missing = []
    try:
        first = demo_frames()
    except BatchError as err:
        missing.append(str(err))
    folder = ext.ops.bridge.models_dir(bpy.context, args.models or "")
    if not ext.ops.bridge.model_cards(folder):
        missing.append(f"No trained model is installed in {folder}: it needs an .onnx model "
                       "with its .json card (made by the training, see README.md).")
    if missing:
        raise BatchError("cannot run the demo yet:\n  - " + "\n  - ".join(missing))
    return first


def set_up_demo(ext, args) -> str:
    import bpy

    first = demo_preflight(ext, args)
    bpy.ops.wm.read_homefile(use_empty=True)
    call(bpy.ops.relight.import_footage, filepath=str(first), frame_start=1)
    scene = bpy.context.scene
    info = HERE.parent / "demo" / "clip.json"
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
        args.out = str(HERE.parent / "out" / "demo")
    return bpy.context.scene.sequence_editor.active_strip.name


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
            raise BatchError(f"There is no studio HDRI named '{args.studio}'.") from None
    if args.rotation is not None:
        s.rotation = math.radians(args.rotation)
    if args.exposure is not None:
        s.exposure = args.exposure
    if args.preset:
        s.preset = args.preset
    if args.out:
        s.output_dir = str(pathlib.Path(args.out).resolve()) + "/"
    s.use_frame_range = args.frames is not None
    if args.frames:
        s.frame_start, s.frame_end = args.frames
    s.write_matte = args.matte or s.write_matte
    if args.background or args.keep_background:
        s.background = (args.background or "keep").upper()
    s.overwrite = args.overwrite


def call(op, **kwargs) -> None:
    """Run an operator; its error report becomes a BatchError with the operator's message."""
    try:
        op(**kwargs)
    except RuntimeError as err:
        raise BatchError(re.sub(r"^Error:\s*", "", str(err).strip())) from None


def relight(ext, strip: str, models: str) -> None:
    """Run the relight operator. Its failure is raised as the exception that ended it (the
    operator keeps it: a RelightError for the user, a Cancelled, or a bug), so main() can
    choose the exit status and show a bug's traceback only with --debug."""
    import bpy

    module = ext.ops.relight_strip
    module.last_error = None
    try:
        done = bpy.ops.relight.relight_strip(strip=strip, models_dir=models, show_traceback=False)
    except RuntimeError as err:
        if module.last_error is not None:
            raise module.last_error from None
        raise BatchError(re.sub(r"^Error:\s*", "", str(err).strip())) from None
    if module.last_error is not None:
        raise module.last_error
    if done != {'FINISHED'}:
        raise BatchError(f"the relight operator ended with {sorted(done)}")


def run(args) -> None:
    import bpy

    if args.blend:
        open_blend(args.blend)
    ext = load_extension()
    if args.models:
        args.models = str(pathlib.Path(args.models).resolve())
    strip = set_up_demo(ext, args) if args.demo else args.strip
    apply_settings(bpy.context.scene, args)
    started = time.perf_counter()
    relight(ext, strip, args.models or "")
    scene = bpy.context.scene
    out = ext.ops.bridge.output_dir(scene, scene.sequence_editor.strips[strip],
                                    scene.relight.output_dir)
    print(f"relight_batch: done in {time.perf_counter() - started:.1f} s; relit frames are in "
          f"{out / 'relit'}", flush=True)
    if args.save:
        if not bpy.data.filepath:
            raise BatchError("--save needs a .blend file to save into; open one first.")
        bpy.ops.wm.save_mainfile()


def _stop(signum, frame):
    """SIGTERM (a farm manager stopping the job) cancels like Ctrl-C: the run stops at once,
    keeps its finished frames and releases its output folder."""
    _stop.signum = signum
    raise KeyboardInterrupt


_stop.signum = signal.SIGINT


def main(argv=None) -> int:
    args = parse_args(script_args(sys.argv if argv is None else argv))
    # Ctrl-C raises KeyboardInterrupt here, under Blender too (which has its own handler).
    signal.signal(signal.SIGINT, signal.default_int_handler)
    signal.signal(signal.SIGTERM, _stop)
    try:
        try:
            import bpy  # noqa: F401  (Blender, or the bpy module)
        except ImportError:
            print("relight_batch: error: needs Blender (blender -b -P ...) or the bpy module "
                  "(pip install bpy)", file=sys.stderr)
            return 1
        run(args)
    except BatchError as err:
        print(f"relight_batch: error: {err}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        return _cancelled()
    except Exception as err:  # noqa: BLE001 - the last line of defence: one clear line
        if _relight_error(err, "Cancelled"):
            return _cancelled()
        if _relight_error(err, "RelightError"):
            print(f"relight_batch: error: {err}", file=sys.stderr)
            return 1
        if args.debug:
            traceback.print_exception(err)
        print(f"relight_batch: unexpected error ({type(err).__name__}: {_one_line(err)}); "
              + ("this is a bug, please report it with the traceback above" if args.debug else
                 "rerun with --debug for the traceback and report it"), file=sys.stderr)
        return 3
    return 0


def _one_line(err: BaseException) -> str:
    return " ".join(str(err).split())


def _relight_error(err: BaseException, name: str) -> bool:
    """Whether ``err`` is the extension's error class ``name`` (addon/errors.py), by name: the
    script may run beside an installed copy of the extension with classes of its own."""
    return any(c.__name__ == name and c.__module__.endswith("addon.errors")
               for c in type(err).__mro__)


def _cancelled() -> int:
    print("relight_batch: cancelled, run again to resume", file=sys.stderr)
    return 128 + int(_stop.signum)


if __name__ == "__main__":
    sys.exit(main())
