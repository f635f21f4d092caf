"""Relight headless: a strip of a .blend, or a movie or image sequence with no .blend; on a
workstation, in CI, or as one chunk of a render-farm job.

    blender -b scene.blend -P scripts/relight_batch.py -- --strip NAME \\
        [--hdri PATH | --scene-lights | --world | --studio NAME] [--preset P] [--out DIR] [--frames A-B]
    blender -b -P scripts/relight_batch.py -- --input shot/ (--hdri PATH | --studio NAME |
        --lights-from lights.blend) --out DIR              (no .blend: shot.1001.exr -> relit.1001.exr)
    blender -c relight --input shot.mov --studio sunset --out DIR   (the installed extension's command)
    python scripts/relight_batch.py [scene.blend] --strip NAME ...   (the bpy module)
    python scripts/relight_batch.py --demo                           (the built-in demo clip)

Without a lighting option the lighting set in the .blend's Relight panel is used. --frames takes
scene frames; outputs do not depend on how a clip is split, so chunks may run anywhere, in any
order, at the same time (chunks of one run share the output folder; another run is refused
while one is writing there). --progress json prints one JSON object per line on stdout.

Exit status, with one line on stderr saying what happened (tracebacks only with --debug):
  0    done
  1    a problem with the input, lighting, model or output; the message says what to do
  2    bad arguments (unknown options, a non-finite or absurd --exposure or --rotation, ...)
  3    an unexpected error, a bug: rerun with --debug for the traceback and report it
  130  cancelled with Ctrl-C (143: stopped by SIGTERM); finished frames are kept, run again
       to resume

This file only finds the extension and calls its batch run (ops/batch.py), the same code that
`blender -c relight` runs, so both take the same options and give the same exit statuses.
"""

from __future__ import annotations

import importlib
import importlib.util
import pathlib
import sys

EXT_ID = "portrait_relight"
HERE = pathlib.Path(__file__).resolve().parent


class LaunchError(Exception):
    """The extension cannot be found or loaded (exit status 1)."""


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
        raise LaunchError(f"The Portrait Relight extension is not enabled, and {root} is not the "
                          "extension folder. Install and enable the extension, or run this "
                          "script from the extension's own scripts/ folder.")
    spec = importlib.util.spec_from_file_location(
        EXT_ID, root / "__init__.py", submodule_search_locations=[str(root)])
    module = importlib.util.module_from_spec(spec)
    sys.modules[EXT_ID] = module
    spec.loader.exec_module(module)
    module.register()
    return module


def main(argv=None) -> int:
    try:
        import bpy  # noqa: F401  (Blender, or the bpy module)
    except ImportError:
        print("relight_batch: error: needs Blender (blender -b -P ...) or the bpy module "
              "(pip install bpy)", file=sys.stderr)
        return 1
    try:
        ext = load_extension()
    except LaunchError as err:
        print(f"relight_batch: error: {err}", file=sys.stderr)
        return 1
    batch = getattr(ext.ops, "batch", None)
    if batch is None:
        print(f"relight_batch: error: the enabled extension ({ext.__name__}) is older than this "
              "script; update it, or run the script that came with it", file=sys.stderr)
        return 1
    return batch.main(sys.argv if argv is None else argv)


if __name__ == "__main__":
    sys.exit(main())
