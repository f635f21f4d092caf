"""Minimal 8-bit PNG writer/reader (zlib only), so pictures need no imaging library."""

from __future__ import annotations

import pathlib
import struct
import zlib

import numpy as np


def _chunk(tag: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data))


def write_png(path, rgb: np.ndarray) -> None:
    """Write an (H, W, 3) or (H, W) uint8 array as a PNG (deterministic bytes for equal input)."""
    a = np.asarray(rgb)
    if a.dtype != np.uint8:
        raise TypeError("write_png takes uint8 pixels; encode to sRGB first")
    if a.ndim == 2:
        a = a[..., None]
    h, w, c = a.shape
    colour_type = {1: 0, 3: 2, 4: 6}[c]
    raw = b"".join(b"\x00" + a[y].tobytes() for y in range(h))
    png = (b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, colour_type, 0, 0, 0))
           + _chunk(b"IDAT", zlib.compress(raw, 9)) + _chunk(b"IEND", b""))
    pathlib.Path(path).write_bytes(png)


def read_png(path) -> np.ndarray:
    """Read a PNG written by write_png (8-bit, no interlace, filter type 0 only)."""
    data = pathlib.Path(path).read_bytes()
    pos, idat, ihdr = 8, b"", None
    while pos < len(data):
        n, tag = struct.unpack(">I4s", data[pos:pos + 8])
        body = data[pos + 8:pos + 8 + n]
        if tag == b"IHDR":
            ihdr = struct.unpack(">IIBBBBB", body)
        elif tag == b"IDAT":
            idat += body
        pos += 12 + n
    w, h, _, ct = ihdr[:4]
    c = {0: 1, 2: 3, 6: 4}[ct]
    raw = np.frombuffer(zlib.decompress(idat), np.uint8).reshape(h, w * c + 1)
    if np.any(raw[:, 0] != 0):
        raise ValueError("only unfiltered PNGs (as written by write_png) are supported")
    return raw[:, 1:].reshape(h, w, c).squeeze()


def to_srgb8(linear: np.ndarray, exposure: float = 1.0) -> np.ndarray:
    """Linear radiance (H, W, 3) -> 8-bit sRGB, clipped."""
    x = np.clip(np.nan_to_num(np.asarray(linear, np.float64) * exposure), 0.0, 1.0)
    s = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)
    return (s * 255.0 + 0.5).astype(np.uint8)
