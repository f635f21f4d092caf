"""Fixtures for tests that run the extension on the bpy module.

The repository root is the extension package (manifest and __init__.py at the top), whose modules
import each other relatively (``from ..addon import ...``). Tests load that root as a package
named by its extension id, ``portrait_relight``, exactly as Blender would load it
(bench/extension.py, which the Cycles benchmarks use too): ``portrait_relight.ops``,
``portrait_relight.addon`` ... Note that ``portrait_relight.addon`` and the top-level ``addon``
that tests/core uses are two copies of the same code: catch errors from the one the code under
test raises.
"""

import pathlib

import bpy
import numpy as np
import pytest

from bench.extension import load_extension  # noqa: F401  (tests import it from here)

ROOT = pathlib.Path(__file__).resolve().parents[2]


@pytest.fixture(scope="session")
def extension():
    """The extension, registered for the whole session (classes survive read_homefile)."""
    ext = load_extension()
    ext.register()
    yield ext
    ext.unregister()


@pytest.fixture(autouse=True)
def empty_file():
    """Every test starts from an empty file, as in a fresh Blender session."""
    bpy.ops.wm.read_homefile(use_empty=True)
    yield


def write_png_sequence(folder: pathlib.Path, count: int = 8, size=(64, 64), start: int = 1,
                       prefix: str = "frame_") -> list[pathlib.Path]:
    """A tiny 8-bit PNG sequence (a bright disc on a dark ground, drifting) via Blender itself."""
    folder.mkdir(parents=True, exist_ok=True)
    h, w = size
    yy, xx = np.mgrid[0:h, 0:w]
    paths = []
    for i in range(count):
        disc = ((yy - h / 2) ** 2 + (xx - w / 2 - i) ** 2 < (min(h, w) / 3) ** 2)
        rgba = np.ones((h, w, 4), np.float32)
        rgba[..., :3] = np.where(disc[..., None], [0.8, 0.6, 0.5], [0.1, 0.1, 0.12])
        paths.append(_save_png(folder / f"{prefix}{start + i:04d}.png", rgba))
    return paths


def _save_png(path: pathlib.Path, rgba: np.ndarray) -> pathlib.Path:
    img = bpy.data.images.new(path.stem, rgba.shape[1], rgba.shape[0], alpha=True)
    img.pixels.foreach_set(np.ascontiguousarray(rgba[::-1]).ravel())
    img.filepath_raw = str(path)
    img.file_format = 'PNG'
    img.save()
    bpy.data.images.remove(img)
    return path


def write_movie(path: pathlib.Path, count: int = 8, size=(64, 64), fps: int = 25) -> pathlib.Path:
    """A tiny H.264 movie with PyAV (frames of rising grey)."""
    import av

    path.parent.mkdir(parents=True, exist_ok=True)
    with av.open(str(path), "w") as container:
        stream = container.add_stream("libx264", rate=fps)
        stream.width, stream.height, stream.pix_fmt = size[1], size[0], "yuv420p"
        for i in range(count):
            frame = np.full(size + (3,), 30 + 20 * i, np.uint8)
            for packet in stream.encode(av.VideoFrame.from_ndarray(frame, format="rgb24")):
                container.mux(packet)
        for packet in stream.encode():
            container.mux(packet)
    return path


@pytest.fixture(scope="session")
def toy_models(tmp_path_factory) -> pathlib.Path:
    """A models folder holding the toy ONNX model of tests/onnx_fixtures.py and its card."""
    from onnx_fixtures import write_toy_model

    folder = tmp_path_factory.mktemp("models")
    write_toy_model(folder)
    return folder


def write_hdri(path: pathlib.Path, size=(32, 64), sun=(4, 40)) -> pathlib.Path:
    """A small equirectangular EXR: dim uniform sky plus one bright texel (a sun)."""
    import OpenEXR

    rgb = np.full(size + (3,), 0.2, np.float32)
    rgb[sun] = 50.0
    path.parent.mkdir(parents=True, exist_ok=True)
    with OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION}, {"RGB": rgb}) as f:
        f.write(str(path))
    return path


def footage_scene(tmp_path: pathlib.Path, count: int = 8, frame_start: int = 1):
    """An empty file with one imported 64x64 PNG strip, lit by a small HDRI file, writing into
    tmp_path/out; returns the strip."""
    files = write_png_sequence(tmp_path / "footage", count=count)
    bpy.ops.relight.import_footage(filepath=str(files[0]), frame_start=frame_start)
    settings = bpy.context.scene.relight
    settings.light_source = 'HDRI_FILE'
    settings.hdri_path = str(write_hdri(tmp_path / "sky.exr"))
    settings.output_dir = str(tmp_path / "out") + "/"
    return bpy.context.scene.sequence_editor.active_strip
