"""Fixtures shared by the tests of tests/core."""

import pytest

from tests.onnx_fixtures import write_toy_model


@pytest.fixture(scope="module")
def toy(tmp_path_factory):
    """The toy ONNX model (tests/onnx_fixtures.py) with its card, one per test module."""
    return str(write_toy_model(tmp_path_factory.mktemp("model")))
