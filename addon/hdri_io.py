"""Read equirectangular HDRI files (.exr via OpenEXR, .hdr Radiance RGBE in numpy) as float32 RGB.

Only reading lives here; validation of the map (shape, NaN/Inf/negative pixels) and down-sampling
to a light vector are in hdri.py. Every failure is an InputError that names the file.
"""

from __future__ import annotations

import os
import re

import numpy as np

from .errors import DependencyError, InputError

EXTENSIONS = (".exr", ".hdr", ".pic")
# The largest map read: 32768 x 16384 (the largest HDRIs published), 6.4 GB as float32 RGB. A
# header claiming more is refused before anything is allocated.
MAX_WIDTH, MAX_HEIGHT = 32768, 16384


def _check_size(path: str, width: int, height: int) -> None:
    if width < 1 or height < 1:
        raise InputError(f"The HDRI {path} claims a size of {width}x{height} pixels; the file "
                         "is damaged. Re-export it, or pick another HDRI.")
    if width > MAX_WIDTH or height > MAX_HEIGHT:
        raise InputError(f"The HDRI {path} claims {width}x{height} pixels, more than the "
                         f"{MAX_WIDTH}x{MAX_HEIGHT} this add-on reads (a damaged header, or a "
                         "map far larger than lighting needs). Re-export it at 8192x4096 or "
                         "less, or pick another HDRI.")


def read_hdri(path: str | os.PathLike) -> np.ndarray:
    """(H, W, 3) float32 linear radiance of an .exr or .hdr file, top row first."""
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise InputError(f"HDRI file not found: {path}. Check the path, or pick another HDRI.")
    ext = os.path.splitext(path)[1].lower()
    if ext not in EXTENSIONS:
        raise InputError(f"Cannot read {path}: HDRIs must be OpenEXR (.exr) or Radiance (.hdr) "
                         "files. Convert it, or pick another HDRI.")
    try:
        rgb = _read_exr(path) if ext == ".exr" else _read_rgbe(path)
    except InputError:
        raise
    except (OSError, ValueError, RuntimeError, IndexError, KeyError, TypeError) as err:
        raise InputError(f"Cannot read the HDRI {path}: the file is damaged or not a valid "
                         f"{ext} image ({err}).") from err
    return np.ascontiguousarray(rgb, dtype=np.float32)


def _read_exr(path: str) -> np.ndarray:
    try:
        import OpenEXR
    except ImportError as err:  # bundled with the extension; missing means a broken install
        raise DependencyError("The OpenEXR module is missing; reinstall the extension.") from err
    with OpenEXR.File(path, header_only=True) as f:
        (x0, y0), (x1, y1) = f.header()["dataWindow"]
    _check_size(path, int(x1) - int(x0) + 1, int(y1) - int(y0) + 1)
    with OpenEXR.File(path) as f:
        channels = f.channels()
        if "RGBA" in channels or "RGB" in channels:
            px = np.asarray(channels["RGBA" if "RGBA" in channels else "RGB"].pixels)
            rgb = px[..., :3]
        elif all(c in channels for c in "RGB"):
            rgb = np.stack([np.asarray(channels[c].pixels) for c in "RGB"], axis=-1)
        elif "Y" in channels:
            rgb = np.repeat(np.asarray(channels["Y"].pixels)[..., None], 3, axis=-1)
        else:
            raise InputError(f"The EXR {path} has no R, G, B (or Y) channels (it has "
                             f"{', '.join(sorted(channels))}); save the HDRI as RGB.")
    return rgb.astype(np.float32)


_RESOLUTION = re.compile(rb"^([-+])Y (\d+) ([-+])X (\d+)$")


def _read_rgbe(path: str) -> np.ndarray:
    with open(path, "rb") as f:
        data = f.read()
    header_end = data.find(b"\n\n")
    if not (data.startswith(b"#?") and header_end > 0):
        raise InputError(f"{path} is not a Radiance HDR file (missing '#?RADIANCE' header).")
    header = data[:header_end].split(b"\n")
    exposure = 1.0
    for line in header:
        if line.startswith(b"FORMAT=") and line.strip() != b"FORMAT=32-bit_rle_rgbe":
            raise InputError(f"{path} uses {line.decode(errors='replace')}; only RGBE Radiance "
                             "files are supported. Convert it to RGB.")
        if line.startswith(b"EXPOSURE="):
            exposure *= float(line[9:])  # pixels were multiplied by this: divide it back out
    if not (np.isfinite(exposure) and exposure > 0):
        raise InputError(f"{path} has an EXPOSURE of {exposure:g} in its header; the file is "
                         "damaged. Re-export it, or pick another HDRI.")
    eol = data.find(b"\n", header_end + 2)
    match = _RESOLUTION.match(data[header_end + 2:eol].strip())
    if not match:
        raise InputError(f"{path} has an unsupported Radiance resolution line; only standard "
                         "'-Y H +X W' images are supported.")
    height, width = int(match.group(2)), int(match.group(4))
    _check_size(path, width, height)
    # The smallest a scanline can be: run-length encoded, every run 127 long (2 bytes per run).
    least = height * (4 + 4 * 2 * -(-width // 127) if 8 <= width < 32768 else 4 * width)
    if len(data) - (eol + 1) < least:
        raise InputError(f"The HDRI {path} claims {width}x{height} pixels but holds only "
                         f"{len(data) - eol - 1} bytes of pixel data: it is truncated or its "
                         "header is damaged. Re-export it, or pick another HDRI.")
    rgbe = _decode_scanlines(np.frombuffer(data, np.uint8, offset=eol + 1), height, width)
    if match.group(1) == b"+":  # bottom row stored first
        rgbe = rgbe[::-1]
    if match.group(3) == b"-":
        rgbe = rgbe[:, ::-1]
    e = rgbe[..., 3].astype(np.int32)
    scale = np.where(e > 0, np.ldexp(1.0, e - 136), 0.0) / exposure
    return (rgbe[..., :3] + 0.5) * scale[..., None] * (e[..., None] > 0)


def _decode_scanlines(buf: np.ndarray, height: int, width: int) -> np.ndarray:
    """(height, width, 4) uint8 RGBE from flat or new-style run-length-encoded scanlines."""
    out = np.empty((height, width, 4), np.uint8)
    pos = 0
    for y in range(height):
        head = buf[pos:pos + 4]
        if 8 <= width < 32768 and len(head) == 4 and head[0] == 2 and head[1] == 2 \
                and not head[2] & 0x80:
            if (int(head[2]) << 8 | int(head[3])) != width:
                raise InputError("Radiance scanline width does not match the image width.")
            pos = _decode_rle_line(buf, pos + 4, out[y], width)
        else:  # flat scanline: width RGBE quadruples
            end = pos + 4 * width
            if end > len(buf):
                raise InputError("The Radiance file ends early (truncated pixel data).")
            out[y] = buf[pos:end].reshape(width, 4)
            pos = end
    return out


def _decode_rle_line(buf: np.ndarray, pos: int, row: np.ndarray, width: int) -> int:
    """Decode the four run-length-encoded channel planes of one scanline into ``row``."""
    n = len(buf)
    for ch in range(4):
        x = 0
        while x < width:
            if pos >= n:
                raise InputError("The Radiance file ends early (truncated run-length data).")
            count = int(buf[pos])
            if count > 128:  # a run of one repeated value
                count -= 128
                if x + count > width or pos + 1 >= n:
                    raise InputError("Bad run-length data in the Radiance file.")
                row[x:x + count, ch] = buf[pos + 1]
                pos += 2
            else:  # count literal values
                if count == 0 or x + count > width or pos + 1 + count > n:
                    raise InputError("Bad run-length data in the Radiance file.")
                row[x:x + count, ch] = buf[pos + 1:pos + 1 + count]
                pos += 1 + count
            x += count
    return pos
