"""The repository root loaded as the extension package ``portrait_relight``, as Blender loads it.

The root is the extension (manifest and __init__.py at the top) and its modules import each
other relatively (``from ..addon import ...``), so code that drives Blender (the Cycles
benchmarks here, tests/blender) imports it as a package named by the extension id, with
importlib and no sys.path edits. Its ``addon`` is a second copy of the top-level ``addon`` that
tests/core and training import.
"""

from __future__ import annotations

import importlib
import importlib.util
import pathlib
import sys

ROOT = pathlib.Path(__file__).resolve().parents[1]
EXT_ID = "portrait_relight"  # the id in blender_manifest.toml


def load_extension():
    """The extension package (loaded once per process)."""
    if EXT_ID in sys.modules:
        return sys.modules[EXT_ID]
    spec = importlib.util.spec_from_file_location(
        EXT_ID, ROOT / "__init__.py", submodule_search_locations=[str(ROOT)])
    module = importlib.util.module_from_spec(spec)
    sys.modules[EXT_ID] = module
    spec.loader.exec_module(module)
    return module


def submodule(name: str):
    """``portrait_relight.<name>`` (e.g. "addon.lamps", "ops.scene_light"), the package loaded."""
    load_extension()
    return importlib.import_module(f"{EXT_ID}.{name}")
