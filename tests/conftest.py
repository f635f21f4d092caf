"""Shared fixtures. Tests that need ../shared/data skip with a stated reason where it is absent."""

import os
import pathlib
import sys

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
SHARED_DATA = pathlib.Path(os.environ.get("RELIGHT_SHARED_DATA", ROOT.parent / "shared" / "data"))

# The repository root is the extension package's parent directory layout: make `addon`, `training`
# and `bench` importable as top-level packages in tests.
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))


@pytest.fixture(scope="session")
def shared_data() -> pathlib.Path:
    if not (SHARED_DATA / "README.md").is_file():
        pytest.skip(f"needs the shared data folder ({SHARED_DATA}), which is absent on this machine")
    return SHARED_DATA


@pytest.fixture(scope="module")
def toy(tmp_path_factory):
    """The toy ONNX model (tests/onnx_fixtures.py) with its card, one per test module."""
    from tests.onnx_fixtures import write_toy_model

    return str(write_toy_model(tmp_path_factory.mktemp("model")))
