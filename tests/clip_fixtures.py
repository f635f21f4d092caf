"""Tiny generated clips for tests: movies written with PyAV, PNG and EXR sequences."""

from __future__ import annotations

import pathlib

import av
import numpy as np
import OpenEXR


def ramp_frames(n: int, height: int = 48, width: int = 64, seed: int = 0) -> list[np.ndarray]:
    """uint8 RGB frames: a textured gradient whose brightness steps with the frame number, so a
    decoded frame tells which source frame it was."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:height, 0:width]
    base = (40 + 100 * x / max(width - 1, 1) + 40 * y / max(height - 1, 1))[..., None]
    tex = rng.integers(-8, 9, size=(height, width, 3))
    tint = np.array([1.0, 0.85, 0.7])
    return [np.clip(base * tint + tex + 6 * i, 0, 255).astype(np.uint8) for i in range(n)]


def write_movie(path, frames_rgb, fps: int = 25, codec: str = "libx264") -> pathlib.Path:
    """A movie (near-lossless H.264 in yuv444p by default; 'png' in .mov is exactly lossless)."""
    path = pathlib.Path(path)
    h, w = frames_rgb[0].shape[:2]
    with av.open(str(path), "w") as c:
        s = c.add_stream(codec, rate=fps)
        s.width, s.height = w, h
        if codec == "libx264":
            s.pix_fmt = "yuv444p"
            s.options = {"crf": "0", "g": "4"}
        else:
            s.pix_fmt = "rgb24"
        for f in frames_rgb:
            for p in s.encode(av.VideoFrame.from_ndarray(np.ascontiguousarray(f),
                                                         format="rgb24")):
                c.mux(p)
        for p in s.encode():
            c.mux(p)
    return path


def write_png(path, pixels: np.ndarray) -> None:
    """PNG from uint8/uint16 arrays of shape (H, W), (H, W, 3) or (H, W, 4)."""
    px = np.ascontiguousarray(pixels)
    deep = px.dtype == np.uint16
    fmt = {(2, False): "gray", (2, True): "gray16le", (3, False): "rgb24", (3, True): "rgb48le",
           (4, False): "rgba", (4, True): "rgba64le"}[(px.ndim if px.ndim == 2 else px.shape[2],
                                                      deep)]
    out_fmt = {"gray16le": "gray16be", "rgb48le": "rgb48be", "rgba64le": "rgba64be"}.get(fmt, fmt)
    frame = av.VideoFrame.from_ndarray(px, format=fmt)
    cc = av.CodecContext.create("png", "w")
    cc.width, cc.height, cc.pix_fmt = px.shape[1], px.shape[0], out_fmt
    packets = cc.encode(frame.reformat(format=out_fmt)) + cc.encode(None)
    pathlib.Path(path).write_bytes(b"".join(bytes(p) for p in packets))


def _write_sequence(folder, frames, prefix: str, start: int, ext: str, write) -> list[str]:
    """Numbered files prefix####.ext from ``start``, one per frame, each written by ``write``."""
    folder = pathlib.Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    out = []
    for i, f in enumerate(frames):
        p = folder / f"{prefix}{start + i:04d}.{ext}"
        write(p, f)
        out.append(str(p))
    return out


def write_png_sequence(folder, frames, prefix: str = "shot_", start: int = 1) -> list[str]:
    return _write_sequence(folder, frames, prefix, start, "png", write_png)


def write_exr_float(path, pixels: np.ndarray) -> None:
    """A float32 RGB EXR written directly (keeps NaN/Inf/negative values as they are)."""
    px = np.ascontiguousarray(pixels, dtype=np.float32)
    with OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage},
                      {"RGB": px}) as f:
        f.write(str(path))


def write_exr_sequence(folder, frames, prefix: str = "plate.", start: int = 1001) -> list[str]:
    return _write_sequence(folder, frames, prefix, start, "exr", write_exr_float)
