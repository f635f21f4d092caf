"""The light vector: the one lighting convention used everywhere (add-on, training, benchmarks).

A light vector is a float32 array of shape (16, 16, 3): a latitude-longitude map of distant lighting
in linear Rec.709 scene-referred radiance, expressed in the subject's frame, which is the camera's
frame (+X camera right, +Y up, +Z from the subject toward the camera).

* Row r spans polar angles (from +Y) [11.25 r, 11.25 (r+1)] degrees: row 0 touches the zenith.
* Column c is centred on azimuth (c - 8) * 22.5 degrees with azimuth = atan2(x, z): column 8 faces
  the camera, columns 9, 10, ... turn toward +X, column 0 is centred straight behind the subject.
* Each texel is the mean radiance over its solid-angle cell, so a uniform environment of radiance 1
  is all ones, and the irradiance on a unit normal n is sum_t L_t max(0, n . d_t) Omega_t.

Everything that needs cell geometry calls this module; nothing else writes these numbers down.
"""

from __future__ import annotations

import math

import numpy as np

from . import colour
from .errors import LightingError

ROWS = 16
COLS = 16
SHAPE = (ROWS, COLS, 3)
ROW_STEP = math.pi / ROWS  # 11.25 degrees of polar angle per row
COL_STEP = 2.0 * math.pi / COLS  # 22.5 degrees of azimuth per column
FRONT_COL = 8  # the column centred on the direction toward the camera


def polar_edges() -> np.ndarray:
    """Polar angles (radians from +Y) of the 17 row boundaries, zenith first."""
    return np.arange(ROWS + 1, dtype=np.float64) * ROW_STEP


def polar_centres() -> np.ndarray:
    """Polar angle (radians from +Y) of each row's centre line."""
    return (np.arange(ROWS, dtype=np.float64) + 0.5) * ROW_STEP


def azimuth_centres() -> np.ndarray:
    """Azimuth (radians, atan2(x, z)) of each column's centre."""
    return (np.arange(COLS, dtype=np.float64) - FRONT_COL) * COL_STEP


def angles_to_directions(theta: np.ndarray, phi: np.ndarray) -> np.ndarray:
    """Unit directions for polar angle theta (from +Y) and azimuth phi (atan2(x, z))."""
    theta = np.asarray(theta, dtype=np.float64)
    phi = np.asarray(phi, dtype=np.float64)
    s = np.sin(theta)
    return np.stack([s * np.sin(phi), np.cos(theta), s * np.cos(phi)], axis=-1)


def directions_to_angles(dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(theta, phi) of direction vectors (need not be unit length; zero vectors give theta=pi/2)."""
    d = np.asarray(dirs, dtype=np.float64)
    x, y, z = d[..., 0], d[..., 1], d[..., 2]
    theta = np.arctan2(np.hypot(x, z), y)  # robust near the poles, unlike arccos(y / |d|)
    phi = np.arctan2(x, z)
    return theta, phi


def directions() -> np.ndarray:
    """(16, 16, 3) float64 unit direction of every cell centre."""
    theta, phi = np.meshgrid(polar_centres(), azimuth_centres(), indexing="ij")
    return angles_to_directions(theta, phi)


def solid_angles() -> np.ndarray:
    """(16, 16) float64 solid angle of every cell (steradians); they sum to 4 pi."""
    e = polar_edges()
    band = np.cos(e[:-1]) - np.cos(e[1:])
    return np.repeat((band * COL_STEP)[:, None], COLS, axis=1)


def angles_to_cells(theta: np.ndarray, phi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Row and column index of the cells holding the given angles."""
    row = np.clip(np.floor(np.asarray(theta) / ROW_STEP).astype(np.int64), 0, ROWS - 1)
    col = np.floor(np.asarray(phi) / COL_STEP + FRONT_COL + 0.5).astype(np.int64) % COLS
    return row, col


def directions_to_cells(dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Row and column index of the cells holding the given directions."""
    return angles_to_cells(*directions_to_angles(dirs))


def zeros() -> np.ndarray:
    return np.zeros(SHAPE, dtype=np.float32)


def uniform(radiance=1.0) -> np.ndarray:
    """A uniform environment of the given radiance (scalar or RGB)."""
    return np.broadcast_to(np.asarray(radiance, dtype=np.float32), SHAPE).copy()


def validate(light, what: str = "light vector") -> np.ndarray:
    """Return ``light`` as a contiguous float32 (16, 16, 3) array, or raise LightingError."""
    arr = np.asarray(light)
    if arr.shape != SHAPE:
        raise LightingError(f"The {what} must have shape {SHAPE}, got {arr.shape}.")
    arr = arr.astype(np.float32)
    if not np.all(np.isfinite(arr)):
        raise LightingError(
            f"The {what} contains NaN or infinite values; check the HDRI or lamp settings "
            "that produced it.")
    if np.any(arr < 0):
        raise LightingError(
            f"The {what} contains negative radiance; lighting must be zero or positive.")
    return np.ascontiguousarray(arr)


# The smallest positive half float. A light whose every texel is below it relights footage of
# radiance up to about 1 to values that round to 0 in a half-float frame: a black frame.
DARKEST = 2.0 ** -24


def is_black(light) -> bool:
    """Whether ``light`` (a valid light vector) is too dark to show in a relit frame."""
    return not float(np.max(light)) >= DARKEST


def irradiance(light: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """Irradiance (..., 3) on unit normals (..., 3) from a light vector: sum L max(0, n.d) Omega."""
    d = directions().reshape(-1, 3)
    w = solid_angles().reshape(-1)
    cos = np.clip(np.asarray(normals, dtype=np.float64) @ d.T, 0.0, None)  # (..., 256)
    return (cos * w) @ np.asarray(light, dtype=np.float64).reshape(-1, 3)


def total_power(light: np.ndarray) -> np.ndarray:
    """sum_t L_t Omega_t per channel: the integral of radiance over the sphere (W/m2 per channel)."""
    return np.tensordot(solid_angles(), np.asarray(light, dtype=np.float64), axes=([0, 1], [0, 1]))


def rotate_azimuth(light: np.ndarray, degrees: float) -> np.ndarray:
    """Rotate lighting about +Y by ``degrees`` (right-handed: +Z turns toward +X).

    A light at azimuth a moves to azimuth a + degrees. Each row is resampled with periodic linear
    interpolation, which conserves each row's energy exactly and makes 360 degrees the identity.
    """
    light = np.asarray(light, dtype=np.float32)
    shift = (float(degrees) / math.degrees(COL_STEP)) % COLS
    whole = int(math.floor(shift))
    frac = shift - whole
    out = np.roll(light, whole, axis=1)
    if frac > 1e-9:
        out = (1.0 - frac) * out + frac * np.roll(out, 1, axis=1)
    return out.astype(np.float32)


def splat_direction(direction, irradiance_rgb) -> np.ndarray:
    """A light vector that delivers irradiance ``irradiance_rgb`` (W/m2 at normal incidence) from
    ``direction`` (camera frame), spread bilinearly over the nearest cell centres.

    The spread keeps moving lights smooth (no popping from texel to texel) and conserves
    sum_t L_t Omega_t = irradiance_rgb exactly.
    """
    theta, phi = directions_to_angles(np.asarray(direction, dtype=np.float64))
    e = np.broadcast_to(np.asarray(irradiance_rgb, dtype=np.float64), (3,))
    fr = float(theta) / ROW_STEP - 0.5  # fractional row between centres
    r0 = int(math.floor(fr))
    tr = fr - r0
    rows = [(min(max(r0, 0), ROWS - 1), 1.0 - tr), (min(max(r0 + 1, 0), ROWS - 1), tr)]
    fc = float(phi) / COL_STEP + FRONT_COL
    c0 = int(math.floor(fc))
    tc = fc - c0
    cols = [(c0 % COLS, 1.0 - tc), ((c0 + 1) % COLS, tc)]
    w = np.zeros((ROWS, COLS), dtype=np.float64)
    for r, wr in rows:
        for c, wc in cols:
            w[r, c] += wr * wc
    out = (w / solid_angles())[..., None] * e
    return out.astype(np.float32)


def to_preview(light: np.ndarray, exposure: float | None = None) -> np.ndarray:
    """An sRGB-encoded (16, 16, 3) float preview in [0, 1] for drawing in the UI.

    Exposure defaults to scaling the brightest texel to 1, so dim and bright maps both show detail.
    """
    light = np.nan_to_num(np.asarray(light, dtype=np.float64), nan=0.0, posinf=0.0, neginf=0.0)
    light = np.clip(light, 0.0, None)
    peak = float(light.max())
    scale = 1.0 / peak if exposure is None and peak > 0 else 2.0 ** (exposure or 0.0)
    return colour.linear_to_srgb(np.clip(light * scale, 0.0, 1.0))
