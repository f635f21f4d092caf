"""Blender lamps to light vectors, in Blender's own units as Cycles interprets them.

A light vector holds *distant* lighting, so a lamp near the subject cannot be reproduced exactly:
its light falls off with the inverse square across the subject and lights less than a hemisphere.
Every lamp here is fitted so that a Lambertian sphere of the subject's radius is shaded as closely
as possible (least squares over the sphere) by non-negative distant light. For a point source that
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
from dataclasses import dataclass

import numpy as np

from . import colour, lightvec
from .errors import LightingError

KINDS = ("POINT", "SUN", "SPOT", "AREA")
AREA_SHAPES = ("SQUARE", "RECTANGLE", "DISK", "ELLIPSE")


@dataclass(frozen=True)
class Lamp:
    """A Blender lamp in the light frame (the camera's frame), relative to the subject's centre."""

    kind: str  # 'POINT' | 'SUN' | 'SPOT' | 'AREA'
    position: tuple[float, float, float]  # metres
    direction: tuple[float, float, float]  # unit vector the lamp emits along (its local -Z)
    color: tuple[float, float, float]  # linear RGB, already times the blackbody colour if used
    energy: float  # W (point/spot/area) or W/m2 (sun), as in Blender's UI
    exposure: float = 0.0  # stops
    radius: float = 0.0  # point/spot shadow_soft_size (m)
    sun_angle: float = 0.0  # radians, the sun disc's angular diameter
    spot_size: float = math.pi  # radians, full cone angle
    spot_blend: float = 0.0
    area_shape: str = "SQUARE"
    size: float = 0.0  # area size along its local X (m)
    size_y: float = 0.0  # area size along its local Y (RECTANGLE, ELLIPSE)
    normalize: bool = True  # area: energy is the total power (else power per m2)
    axis_x: tuple[float, float, float] | None = None  # the lamp's local X (area rectangles)

    def strength(self) -> np.ndarray:
        """colour x energy x 2^exposure, per channel: what every lamp type scales with."""
        scale = float(self.energy) * 2.0 ** float(self.exposure)
        return _colour(self.color) * scale


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
        raise LightingError(
            f"The subject radius must be a positive number of metres, got {value!r}.")
    return r


def _finite_light(light: np.ndarray, what: str) -> np.ndarray:
    if not np.all(np.isfinite(light)):
        raise LightingError(f"The {what} is too bright to represent (radiance overflows float32); "
                            "lower its energy or exposure.")
    return light


def project_point_light(position, color, subject_radius: float = 1.0) -> np.ndarray:
    """The paper's point light outside the subject sphere (sec. 4.3) as a light vector.

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


def fibonacci_sphere(n: int) -> np.ndarray:
    """(n, 3) evenly spread unit vectors, each standing for the same area of the sphere."""
    i = np.arange(n, dtype=np.float64) + 0.5
    y = 1.0 - 2.0 * i / n
    r = np.sqrt(np.clip(1.0 - y * y, 0.0, None))
    a = math.pi * (1.0 + math.sqrt(5.0)) * i
    return np.stack([r * np.cos(a), y, r * np.sin(a)], axis=1)


_FIT_NORMALS = fibonacci_sphere(2048)  # for the numeric fits (spot cones): 1% accurate, ~0.1 ms


def spot_mask(cos_angle, spot_size: float, spot_blend: float):
    """Cycles' spot cone: 1 inside, 0 outside, smoothstep over the blend; cos_angle is measured
    from the spot's axis. The cone only masks: a spot is not brighter than a point lamp."""
    c = np.asarray(cos_angle, dtype=np.float64)
    cos_half = math.cos(min(float(spot_size), math.pi) / 2.0)
    smooth = (1.0 - cos_half) * float(spot_blend)
    if smooth <= 0.0:
        return (c > cos_half).astype(np.float64)
    t = np.clip((c - cos_half) / smooth, 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def _spot_factor(lamp: Lamp, pos: np.ndarray, radius: float) -> float:
    """The mask of a spot as the sphere sees it: its mean over the sphere, weighted like the
    least-squares fit of a point lamp (exact point-lamp shading times the cosine toward it)."""
    axis = _unit(lamp.direction, "spot direction")
    if lamp.spot_size >= math.pi and lamp.spot_blend <= 0:
        return 1.0
    n = _FIT_NORMALS
    to_lamp = pos - radius * n
    dist = np.linalg.norm(to_lamp, axis=1)
    shading = np.clip(np.sum(n * to_lamp, axis=1), 0.0, None) / dist ** 3
    weight = shading * np.clip(n @ (pos / np.linalg.norm(pos)), 0.0, None)
    mask = spot_mask(np.sum(-to_lamp * axis, axis=1) / dist, lamp.spot_size, lamp.spot_blend)
    total = weight.sum()
    return float((weight * mask).sum() / total) if total > 0 else 0.0


def _unit(value, what: str) -> np.ndarray:
    v = _vec3(value, what)
    norm = math.hypot(*v)
    if not norm > 0:
        raise LightingError(f"The {what} must not be the zero vector.")
    return v / norm


def _sun(lamp: Lamp) -> np.ndarray:
    """A sun: irradiance = strength at normal incidence, spread uniformly over its disc."""
    toward = -_unit(lamp.direction, "sun direction")
    e = lamp.strength()
    half = min(max(float(lamp.sun_angle), 0.0), math.pi) / 2.0
    if half < math.radians(0.5):  # far below a cell (11.25 degrees): one direction is exact enough
        return lightvec.splat_direction(toward, e)
    # Cycles' sun has radiance e / (pi sin^2 half) over the cone; each of n equal solid-angle
    # samples carries that radiance times 2 pi (1 - cos half) / n, which integrates back to e.
    n = 64
    i = np.arange(n) + 0.5
    cos_t = 1.0 - (1.0 - math.cos(half)) * i / n  # equal solid angle rings
    sin_t = np.sqrt(1.0 - cos_t ** 2)
    a = math.pi * (1.0 + math.sqrt(5.0)) * i
    u, v = _basis(toward)
    ring = np.cos(a)[:, None] * u + np.sin(a)[:, None] * v
    dirs = cos_t[:, None] * toward + sin_t[:, None] * ring
    w = np.full(n, 2.0 * (1.0 - math.cos(half)) / (n * math.sin(half) ** 2))
    out = np.zeros(lightvec.SHAPE, dtype=np.float64)
    for d, wi in zip(dirs, w):
        out += lightvec.splat_direction(d, e * wi)
    return out.astype(np.float32)


def _basis(axis: np.ndarray, x_hint=None) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors completing ``axis`` to a right-handed frame (x, y, axis)."""
    if x_hint is not None:
        x = np.asarray(x_hint, dtype=np.float64)
        x = x - axis * (x @ axis)
    if x_hint is None or not np.linalg.norm(x) > 1e-9:
        x = np.cross([0.0, 1.0, 0.0] if abs(axis[1]) < 0.9 else [1.0, 0.0, 0.0], axis)
    x = x / np.linalg.norm(x)
    return x, np.cross(axis, x)


def _area_patches(lamp: Lamp, n: int = 8) -> tuple[np.ndarray, float]:
    """Centres (k, 2) in the lamp's local X/Y of equal patches covering its shape; its area."""
    sx = float(lamp.size)
    sy = float(lamp.size_y) if lamp.area_shape in ("RECTANGLE", "ELLIPSE") else sx
    if not (math.isfinite(sx) and math.isfinite(sy) and sx > 0 and sy > 0):
        raise LightingError(f"An area lamp needs a positive size, got {sx} x {sy} m.")
    g = (np.arange(n) + 0.5) / n - 0.5
    xy = np.stack(np.meshgrid(g * sx, g * sy, indexing="ij"), axis=-1).reshape(-1, 2)
    if lamp.area_shape in ("DISK", "ELLIPSE"):
        xy = xy[(xy[:, 0] / sx) ** 2 + (xy[:, 1] / sy) ** 2 <= 0.25]
        area = math.pi * sx * sy / 4.0
    else:
        area = sx * sy
    return xy, area


def _area(lamp: Lamp, pos: np.ndarray, radius: float) -> np.ndarray:
    """An area lamp as many small one-sided Lambertian emitters, each projected like a point."""
    if lamp.area_shape not in AREA_SHAPES:
        raise LightingError(f"Unknown area lamp shape {lamp.area_shape!r}; use one of "
                            f"{', '.join(AREA_SHAPES)}.")
    emit = _unit(lamp.direction, "area lamp direction")
    ax, ay = _basis(-emit, lamp.axis_x)  # local Z is -emit; Blender lamps emit along local -Z
    xy, area = _area_patches(lamp)
    radiance = lamp.strength() / (math.pi * (area if lamp.normalize else 1.0))
    patch_area = area / len(xy)
    out = np.zeros(lightvec.SHAPE, dtype=np.float64)
    for px, py in xy:
        q = pos + px * ax + py * ay
        dist = math.hypot(*q)
        cos_e = float(-q @ emit) / dist if dist > 0 else 0.0
        if cos_e <= 0 or dist <= radius:  # the subject is behind this patch, or the patch is inside
            continue
        out += project_point_light(q, radiance * patch_area * cos_e, radius)
    return out.astype(np.float32)


def lamp_to_light(lamp: Lamp, subject_radius: float) -> np.ndarray:
    """One lamp as a (16, 16, 3) float32 light vector for a subject of ``subject_radius`` metres at
    the origin of the light frame. Raises LightingError for lamps it cannot represent (inside the
    subject, negative or non-finite energy, unknown type)."""
    if lamp.kind not in KINDS:
        raise LightingError(f"Unknown lamp type {lamp.kind!r}; use one of {', '.join(KINDS)}.")
    if not (math.isfinite(float(lamp.energy)) and math.isfinite(float(lamp.exposure))):
        raise LightingError("A lamp's energy and exposure must be finite numbers.")
    if lamp.energy < 0:
        raise LightingError(f"A lamp has negative energy ({lamp.energy}); negative light cannot be "
                            "represented. Use a positive energy.")
    radius = _subject_radius(subject_radius)
    if lamp.energy == 0:
        return lightvec.zeros()
    if lamp.kind == "SUN":
        return _finite_light(_sun(lamp), "sun lamp")
    pos = _vec3(lamp.position, "lamp position")
    intensity = lamp.strength() / (4.0 * math.pi)
    if math.hypot(*pos) <= radius:
        return project_point_light(pos, intensity, radius)  # raises the inside-subject error
    if lamp.kind == "AREA":
        return _finite_light(_area(lamp, pos, radius), "area lamp")
    if lamp.kind == "SPOT":
        intensity = intensity * _spot_factor(lamp, pos, radius)
    return project_point_light(pos, intensity, radius)


def light_power(light: np.ndarray) -> float:
    """Luminance of a light vector's total power: how much a lamp contributes, as one number."""
    return float(lightvec.total_power(light) @ np.array(colour.REC709_LUMA))


def lamps_to_light(lamps, subject_radius: float,
                   rel_threshold: float = 1e-3) -> tuple[np.ndarray, list[int]]:
    """The sum of ``lamps`` as one light vector, and the indices of the lamps skipped.

    A lamp is skipped when its energy is zero or its contribution (luminance of its total power)
    is below ``rel_threshold`` of all lamps together, so the skipped lamps together change the total
    power by at most ``rel_threshold`` times their count."""
    lights, powers = [], []
    for lamp in lamps:
        light = lamp_to_light(lamp, subject_radius)
        lights.append(light)
        powers.append(light_power(light))
    total = float(sum(powers))
    out = np.zeros(lightvec.SHAPE, dtype=np.float64)
    skipped = []
    for i, (light, power) in enumerate(zip(lights, powers)):
        if power <= 0 or power < rel_threshold * total:
            skipped.append(i)
        else:
            out += light
    return _finite_light(out.astype(np.float32), "sum of the lamps"), skipped


# Wyman, Sloan & Shirley (2013) multi-lobe fit of the CIE 1931 2-degree colour matching functions:
# (weight, mean nm, sigma below, sigma above) per lobe.
_CMF = (
    ((1.056, 599.8, 37.9, 31.0), (0.362, 442.0, 16.0, 26.7), (-0.065, 501.1, 20.4, 26.2)),
    ((0.821, 568.8, 46.9, 40.5), (0.286, 530.9, 16.3, 31.1)),
    ((1.217, 437.0, 11.8, 36.0), (0.681, 459.0, 26.0, 13.8)),
)
_XYZ_TO_REC709 = np.array([[3.2404542, -1.5371385, -0.4985314],
                           [-0.9692660, 1.8760108, 0.0415560],
                           [0.0556434, -0.2040259, 1.0572252]])
_NM = np.arange(360.0, 831.0, 1.0)
_CMF_TABLE = np.stack([
    sum(w * np.exp(-0.5 * ((_NM - mu) / np.where(_NM < mu, s1, s2)) ** 2)
        for w, mu, s1, s2 in lobes)
    for lobes in _CMF])


def blackbody_rgb(kelvin: float) -> tuple[float, float, float]:
    """Linear Rec.709 colour of a black body, normalised to luminance 1 like Blender's.

    Computed from Planck's law and the CIE 1931 observer and clamped to Blender's range
    (800-12000 K). It matches Blender's ``Light.temperature_color`` within 2% from 2000 K up
    (tests/blender); below that Blender maps the out-of-gamut reds differently (6% at 1000 K).
    The bridge uses Blender's own value where it has one."""
    t = float(kelvin)
    if not math.isfinite(t) or t <= 0:
        raise LightingError(f"A temperature must be a positive number of kelvin, got {kelvin!r}.")
    t = min(max(t, 800.0), 12000.0)
    lam = _NM * 1e-9
    planck = 1.0 / (lam ** 5 * np.expm1(1.4387769e-2 / (lam * t)))
    xyz = _CMF_TABLE @ planck
    rgb = np.clip(_XYZ_TO_REC709 @ (xyz / xyz[1]), 0.0, None)
    rgb = rgb / (rgb @ np.array(colour.REC709_LUMA))
    return (float(rgb[0]), float(rgb[1]), float(rgb[2]))
