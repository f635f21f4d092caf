"""Equirectangular HDRIs to light vectors: solid-angle-correct down-sampling with rotation.

Blender's world convention (Z up): an equirectangular image's column u (0..1, left to right) and
row v (0 at the top) map to the world direction with azimuth atan2(y, x) = pi - 2 pi u (so the
image centre u = 0.5 faces world +X and u = 0.25 faces +Y) and elevation pi/2 - pi v.
``tests/blender`` pins this against a Cycles render.
"""

from __future__ import annotations

import math

import numpy as np

from . import lightvec
from .errors import InputError, LightingError

# Default frame when no scene camera exists: a viewer on world -Y looking toward +Y (Blender's
# front view), so light-frame X = world X, Y = world Z, Z = world -Y.
MIN_WIDTH = 128  # working width never goes below this (see downsample)
FRONT_VIEW_WORLD_TO_FRAME = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])


def world_to_frame_from_camera(camera_rotation: np.ndarray) -> np.ndarray:
    """World->light-frame matrix for a camera whose world rotation (3x3, columns = camera local
    X, Y, Z axes in world space) is given. Blender cameras look down local -Z with +Y up, which is
    exactly the light frame, so this is the transpose."""
    r = np.asarray(camera_rotation, dtype=np.float64)
    return r.T


def yaw_world(degrees: float) -> np.ndarray:
    """Rotation of world directions about world +Z (Blender's world mapping rotation Z)."""
    a = math.radians(degrees)
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def pixel_row_solid_angles(height: int, width: int) -> np.ndarray:
    """(height,) solid angle of one pixel in each row of an equirectangular image."""
    e = np.linspace(0.0, math.pi, height + 1)  # polar angle from world +Z, top row first
    return (np.cos(e[:-1]) - np.cos(e[1:])) * (2.0 * math.pi / width)


def pixel_directions(height: int, width: int, rows: slice | None = None,
                     offset: float = 0.0) -> np.ndarray:
    """(h, width, 3) world directions of pixel centres (Blender convention), top row first;
    ``offset``: the points taken that many pixels right of and below the centres."""
    rows = rows or slice(0, height)
    v = (np.arange(rows.start, rows.stop, dtype=np.float64) + 0.5 + offset) / height
    u = (np.arange(width, dtype=np.float64) + 0.5 + offset) / width
    elev = math.pi / 2 - math.pi * v
    azim = math.pi - 2.0 * math.pi * u
    ce, se = np.cos(elev)[:, None], np.sin(elev)[:, None]
    return np.stack(np.broadcast_arrays(ce * np.cos(azim)[None, :], ce * np.sin(azim)[None, :], se),
                    axis=-1)


# Negative texels no deeper than this share of the image's mean radiance are rounding from the
# file's compression (Blender's bundled studio HDRIs undershoot by up to 1.4% of their mean, in
# 1 to 826 texels each), not damage: they count as black without a word. Web HDRIs checked
# undershoot by 10% to several thousand times their mean (ringing beside a sun): those are said.
ROUNDING = 0.02


def damaged_texels(image: np.ndarray) -> int:
    """How many values of an HDRI are NaN, infinite, or negative beyond ROUNDING (counted for a
    warning; check_equirect's repair makes all of them black, the rounding too)."""
    img = np.asarray(image, np.float32)
    finite = np.isfinite(img)
    mean = float(img[finite].mean()) if finite.any() else 0.0
    return int(np.count_nonzero(~finite) + np.count_nonzero(img < -ROUNDING * max(mean, 0.0)))


def check_equirect(image: np.ndarray, what: str = "HDRI", repair: bool = False) -> np.ndarray:
    """Validate an (H, W, C>=3) equirectangular radiance image; return float32 RGB (H, W, 3).

    Raises InputError for the wrong shape and LightingError for NaN/Inf/negative pixels unless
    ``repair`` is set, in which case those pixels become 0 (counted in the message of nothing;
    the caller decides whether to warn)."""
    img = np.asarray(image)
    if img.ndim == 2:
        img = img[..., None]
    if img.ndim != 3 or img.shape[2] not in (1, 3, 4):
        raise InputError(f"The {what} must be an image with 1, 3 or 4 channels, got shape "
                         f"{np.shape(image)}.")
    h, w = img.shape[:2]
    if h < 2 or abs(w - 2 * h) > 1:
        raise InputError(
            f"The {what} is {w}x{h} pixels; an equirectangular (latitude-longitude) map is twice "
            "as wide as it is tall. Convert it to equirectangular, or pick another HDRI.")
    rgb = img[..., :3] if img.shape[2] >= 3 else np.repeat(img, 3, axis=2)
    rgb = rgb.astype(np.float32)
    bad = ~np.isfinite(rgb) | (rgb < 0)
    if bad.any():
        if not repair:
            n_nan = int(np.isnan(rgb).any(axis=2).sum())
            n_inf = int(np.isinf(rgb).any(axis=2).sum())
            n_neg = int((rgb < 0).any(axis=2).sum())
            raise LightingError(
                f"The {what} has {n_nan} NaN, {n_inf} infinite and {n_neg} negative pixels. "
                "Fix the file, or enable 'Repair HDRI' to treat those pixels as black.")
        rgb = np.where(bad, 0.0, rgb).astype(np.float32)
    return rgb


# Pixels are binned by a point this many pixels off their centre. In the front view a map's pixel
# centres can lie exactly on a cell's edge (a width a multiple of the cells' 16 columns), and
# there the last bit of the trigonometry decides the cell: numpy's vectorised sin, cos and
# arctan2 round differently with an array's alignment in memory, so the same HDRI gave light
# vectors that differed by several per cent in a tenth of the cells from one call to the next
# (two processes of one farm run could disagree on the lighting). The offset is far beyond that
# rounding and far below a pixel.
BIN_OFFSET = 1e-6


def _block_reduce(rgb: np.ndarray, max_width: int) -> tuple[np.ndarray, np.ndarray]:
    """Area-weighted box reduction by an integer factor; returns (image, per-row pixel solid angle).

    Only factors that divide both sides are used, so no pixel is dropped and energy is exact."""
    h, w = rgb.shape[:2]
    omega = pixel_row_solid_angles(h, w)
    f = 1
    # Never reduce below half the requested width: a map whose sides share no small factor is
    # binned at full size instead (slower, never less accurate).
    for cand in range(max(1, math.ceil(w / max_width)), max(1, (2 * w) // max_width) + 1):
        if h % cand == 0 and w % cand == 0:
            f = cand
            break
    if f == 1:
        return rgb.astype(np.float64), omega
    weighted = rgb.astype(np.float64) * omega[:, None, None]
    summed = weighted.reshape(h // f, f, w // f, f, 3).sum(axis=(1, 3))
    omega_blk = omega.reshape(h // f, f).sum(axis=1) * f
    return summed / omega_blk[:, None, None], omega_blk


def downsample(image: np.ndarray, world_to_frame: np.ndarray | None = None,
               yaw_degrees: float = 0.0, strength: float = 1.0, max_width: int = 1024,
               repair: bool = False) -> np.ndarray:
    """Down-sample an equirectangular HDRI (Blender world convention) to a light vector.

    Every (pre-reduced) pixel is binned into the light-vector cell that holds its direction in the
    light frame, weighted by its solid angle; each cell is the weighted mean of its pixels, so a
    uniform map gives exactly ``strength`` everywhere and total power is conserved to the binning
    error (Blender's studio.exr seen from a tilted camera: 3.5% at max_width 128, 0.4% at 256,
    0.16% at 512; bench/light_conversion.py).

    ``world_to_frame``: 3x3 matrix taking world directions into the light frame (see
    ``world_to_frame_from_camera``); defaults to the front view. ``yaw_degrees`` turns the HDRI
    about world Z first (counter-clockwise seen from above); a world Mapping node (Point) with Z
    rotation +a turns it by -a (tests/blender/test_cycles_referee.py). ``max_width`` trades
    accuracy for time: the map is first box-reduced to at most that width.
    """
    if not math.isfinite(float(strength)):
        raise LightingError(f"The HDRI strength is {strength}; set it to a number.")
    if not math.isfinite(float(yaw_degrees)) or (
            world_to_frame is not None and not np.all(np.isfinite(world_to_frame))):
        raise LightingError("The lighting's rotation (or the camera's orientation) is not a "
                            "finite number; set the rotation to a number of degrees.")
    rgb = check_equirect(image, repair=repair)
    width = max(int(max_width), MIN_WIDTH)
    # Small maps are enlarged (exactly: nearest neighbour) to the working width, large ones box-
    # reduced to it: every pixel lands whole in one cell, so the working width bounds the
    # energy error of one dominant pixel (worst per-cell coverage error over 150 random pitches
    # and yaws: 3.5% at 1024, 9.3% at 512).
    if rgb.shape[1] > width:
        src, omega = _block_reduce(rgb, width)
    else:
        src = upsample_small(rgb, width).astype(np.float64)
        omega = pixel_row_solid_angles(*src.shape[:2])
    h, w = src.shape[:2]
    m = (FRONT_VIEW_WORLD_TO_FRAME if world_to_frame is None
         else np.asarray(world_to_frame, dtype=np.float64)) @ yaw_world(yaw_degrees)
    acc = np.zeros((lightvec.ROWS * lightvec.COLS, 3), dtype=np.float64)
    wsum = np.zeros(lightvec.ROWS * lightvec.COLS, dtype=np.float64)
    chunk = max(1, 65536 // w)
    for r0 in range(0, h, chunk):
        rs = slice(r0, min(h, r0 + chunk))
        d = pixel_directions(h, w, rs, BIN_OFFSET) @ m.T
        row, col = lightvec.directions_to_cells(d)
        idx = (row * lightvec.COLS + col).reshape(-1)
        om = np.broadcast_to(omega[rs, None], row.shape).reshape(-1)
        wsum += np.bincount(idx, weights=om, minlength=acc.shape[0])
        vals = src[rs].reshape(-1, 3) * om[:, None]
        for ch in range(3):
            acc[:, ch] += np.bincount(idx, weights=vals[:, ch], minlength=acc.shape[0])
    # MIN_WIDTH guarantees several pixel centres per cell even at the poles after any rotation.
    assert np.all(wsum > 0), "every light cell must catch at least one HDRI pixel"
    # Checked after the cast: a float64 mean above 3.4e38 only overflows in float32.
    out = ((acc / wsum[:, None]).reshape(lightvec.SHAPE) * float(strength)).astype(np.float32)
    if not np.all(np.isfinite(out)):
        raise LightingError("The HDRI is too bright to represent (radiance overflows); "
                            "lower its strength.")
    return out


def upsample_small(image: np.ndarray, min_width: int = 2 * MIN_WIDTH) -> np.ndarray:
    """Nearest-neighbour enlargement of a small map (exact: every pixel keeps its radiance)."""
    h, w = image.shape[:2]
    if w >= min_width:
        return image
    f = math.ceil(min_width / w)
    return np.repeat(np.repeat(image, f, axis=0), f, axis=1)
