"""Blender lamps to light vectors, in Blender's own units as Cycles interprets them.

A light vector holds *distant* lighting, so a lamp near the subject cannot be reproduced exactly:
its light falls off with the inverse square across the subject and lights less than a hemisphere.
Every lamp here is fitted so that a Lambertian sphere of the subject's radius is shaded as closely as
possible (least squares over the sphere) by non-negative distant light. For a point source that
optimum is a single direction (the NNLS fit puts no weight elsewhere: a distant light cannot make
shading fall off faster than the cosine), scaled by ``near_field_gain``. The error left over is
unavoidable and grows as the lamp comes closer (README, "Lighting conversion against Cycles").

Units (checked against Cycles renders in tests/blender/test_cycles_referee.py):
* point / spot: radiant intensity colour * energy * 2^exposure / (4 pi) W/sr; a spot's cone only
  masks, it does not concentrate the power;
* sun: irradiance colour * energy * 2^exposure W/m2 at normal incidence;
* area (normalize on): radiance colour * energy * 2^exposure / (pi A).
Positions and directions are in the light frame (the camera's frame), relative to the subject's
centre, in metres.
"""

from __future__ import annotations

import math

import numpy as np

from . import lightvec
from .errors import LightingError

# Beyond this many subject radii the closed form of near_field_gain cancels badly in float64;
# its series 1 + 3/(4k) + 1/(4k^3) is exact there to better than 1e-10.
_SERIES_FROM = 100.0


def near_field_gain(k: float) -> float:
    """Least-squares scale of a point light at ``k`` subject radii seen as a distant light.

    A point source of intensity I at distance k R from the centre of a Lambertian sphere of radius R
    gives irradiance E(u) = I (k u - 1) / (R^2 (k^2 + 1 - 2 k u)^{3/2}) for u = cos(angle from the
    lamp) > 1/k. The distant light g I / (k R)^2 along the lamp direction whose shading g I u /
    (k R)^2 is closest to E in L2 over the sphere has g = (3 / 8) [F(k^2 - 1) - F((k - 1)^2)] with
    F(w) = -2 a b w^{-1/2} - 2 (a + b) w^{1/2} + 2/3 w^{3/2}, a = k^2 - 1, b = k^2 + 1.
    g is 1 for a far lamp, 1.08 at 10 radii, 1.88 at 1.2 radii and 3 at the surface (k = 1).
    """
    k = float(k)
    if not k >= 1.0:
        raise LightingError(f"near_field_gain needs a lamp outside the sphere (k >= 1), got {k}.")
    if k > _SERIES_FROM:
        return 1.0 + 0.75 / k + 0.25 / k / k / k
    a, b = k * k - 1.0, k * k + 1.0
    ra, rc = math.sqrt(a), k - 1.0  # square roots of the two limits of w
    f_a = -2.0 * b * ra - 2.0 * (a + b) * ra + (2.0 / 3.0) * a * ra
    # a b / sqrt(w) at w = (k - 1)^2 is (k + 1) b: finite even as k -> 1.
    f_c = -2.0 * (k + 1.0) * b - 2.0 * (a + b) * rc + (2.0 / 3.0) * rc ** 3
    return 0.375 * (f_a - f_c)


def _vec3(value, what: str) -> np.ndarray:
    v = np.asarray(value, dtype=np.float64)
    if v.shape != (3,) or not np.all(np.isfinite(v)):
        raise LightingError(f"The {what} must be three finite numbers, got {value!r}.")
    return v


def _colour(value, what: str = "lamp colour") -> np.ndarray:
    c = _vec3(value, what)
    if np.any(c < 0):
        raise LightingError(f"The {what} must not be negative, got {tuple(c)}.")
    return c


def _subject_radius(value) -> float:
    r = float(value)
    if not (math.isfinite(r) and r > 0):
        raise LightingError(f"The subject radius must be a positive number of metres, got {value!r}.")
    return r


def _finite_light(light: np.ndarray, what: str) -> np.ndarray:
    if not np.all(np.isfinite(light)):
        raise LightingError(f"The {what} is too bright to represent (radiance overflows float32); "
                            "lower its energy or exposure.")
    return light


def project_point_light(position, color, subject_radius: float = 1.0) -> np.ndarray:
    """The paper's lighting of a point light outside the subject sphere (sec. 4.3) as a light vector.

    ``position``: the lamp relative to the subject's centre (light frame, same unit as
    ``subject_radius``); it must lie outside the sphere. ``color``: radiant intensity per channel
    (W/sr), so the irradiance it gives at distance d is color / d^2. The lamp is projected onto the
    sphere with the Lambertian model: the returned light vector is the distant light that shades the
    sphere closest (least squares) to the point light, bilinearly splatted so that a moving lamp
    moves smoothly. Raises LightingError inside the sphere or for non-finite input.
    """
    p = _vec3(position, "point light position")
    intensity = _colour(color, "point light colour")
    radius = _subject_radius(subject_radius)
    dist = math.hypot(*p)  # no overflow for huge positions, unlike a squared norm
    if not dist > radius:
        raise LightingError(
            f"A lamp is {dist:.3g} m from the subject's centre, inside the subject radius "
            f"({radius:.3g} m). Move the lamp away from the subject or lower the subject radius.")
    gain = near_field_gain(dist / radius)
    irr = intensity * (gain / dist) / dist  # divided twice so that huge distances underflow to 0
    return _finite_light(lightvec.splat_direction(p / dist, irr), "point light")
