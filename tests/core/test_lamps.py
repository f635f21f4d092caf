"""Lamps to light vectors: the paper's point-light projection, Blender's lamp units, skipping."""

import math

import numpy as np
import pytest

from addon import lamps, lightvec
from addon.errors import LightingError


def _sphere_normals(n=20000):
    """Evenly spread unit normals (Fibonacci lattice): each stands for the same area."""
    i = np.arange(n) + 0.5
    y = 1 - 2 * i / n
    r = np.sqrt(1 - y * y)
    a = math.pi * (1 + 5 ** 0.5) * i
    return np.stack([r * np.cos(a), y, r * np.sin(a)], axis=1)


def _point_light_irradiance(normals, position, intensity, radius):
    """Exact irradiance on a sphere of ``radius`` at the origin from an isotropic point source."""
    to_lamp = np.asarray(position, float) - radius * normals
    d = np.linalg.norm(to_lamp, axis=1)
    return intensity * np.clip(np.sum(normals * to_lamp, axis=1), 0, None) / d ** 3


@pytest.mark.parametrize("k", [1.05, 1.2, 2.0, 4.0, 10.0, 150.0])
def test_near_field_gain_is_the_least_squares_scale(k):
    # Independent check: least-squares scale of the clamped cosine against the exact shading,
    # by quadrature over the sphere instead of the closed form.
    n = _sphere_normals(400_000)
    truth = _point_light_irradiance(n, [0, 0, k], 1.0, 1.0)
    cos = np.clip(n[:, 2], 0, None) / k ** 2
    assert lamps.near_field_gain(k) == pytest.approx(truth @ cos / (cos @ cos), rel=0.01)


def test_near_field_gain_is_smooth_across_the_series_switch():
    assert lamps.near_field_gain(100 - 1e-9) == pytest.approx(lamps.near_field_gain(100 + 1e-9),
                                                              rel=1e-10)
    assert lamps.near_field_gain(1.0) == pytest.approx(3.0)
    assert lamps.near_field_gain(1e12) == pytest.approx(1.0)


def test_point_light_to_the_right_lights_the_right():
    light = lamps.project_point_light([3.0, 0.0, 0.0], [1.0, 2.0, 3.0])
    assert light[:, 9:16].sum() > 0 and light[:, 1:8].sum() == 0
    assert light.dtype == np.float32 and light.shape == lightvec.SHAPE


def test_far_point_light_gives_inverse_square_irradiance():
    pos = np.array([20.0, 30.0, 40.0])
    light = lamps.project_point_light(pos, [5.0, 5.0, 5.0], subject_radius=0.1)
    e = lightvec.irradiance(light, pos / np.linalg.norm(pos))
    assert e[0] == pytest.approx(5.0 / (pos @ pos), rel=0.03)  # 16x16 quadrature error only


def test_point_light_is_linear_in_colour():
    a = lamps.project_point_light([0.5, 1.0, 1.5], [1.0, 0.5, 0.25], subject_radius=0.5)
    b = lamps.project_point_light([0.5, 1.0, 1.5], [3.0, 1.5, 0.75], subject_radius=0.5)
    np.testing.assert_allclose(b, 3.0 * a, rtol=1e-6)


@pytest.mark.parametrize("k,bound", [(1.2, 0.94), (2.0, 0.64), (4.0, 0.34), (10.0, 0.15),
                                     (100.0, 0.045)])
def test_point_light_error_is_the_unavoidable_one(k, bound):
    """Relative RMSE of the sphere's shading over the hemisphere facing the lamp: what a distant
    light cannot avoid for a lamp at k radii (measured 0.933, 0.630, 0.334, 0.144, 0.040 for this
    direction; the 16x16 cells alone cost 2-4% for a far lamp, up to 10% straight overhead)."""
    d = np.array([0.22, 0.11, 0.97]) / np.linalg.norm([0.22, 0.11, 0.97])
    n = _sphere_normals()
    n = n[n @ d > 0]
    truth = _point_light_irradiance(n, k * d, 1.0, 1.0)
    fitted = lightvec.irradiance(lamps.project_point_light(k * d, [1, 1, 1]), n)[:, 0]
    err = np.linalg.norm(fitted - truth) / np.linalg.norm(truth)
    # The naive conversion (inverse square at the centre) in the same 16x16 cells does worse.
    far = lightvec.irradiance(lightvec.splat_direction(d, [1 / k ** 2] * 3), n)[:, 0]
    err_far = np.linalg.norm(far - truth) / np.linalg.norm(truth)
    assert err < bound and err < err_far


@pytest.mark.parametrize("position", [[0, 0, 0], [0.1, 0.2, 0.3], [0, 0.999, 0]])
def test_point_light_inside_the_subject_is_a_clear_error(position):
    with pytest.raises(LightingError, match="inside the subject radius"):
        lamps.project_point_light(position, [1, 1, 1], subject_radius=1.0)


@pytest.mark.parametrize("bad", [dict(position=[np.nan, 0, 2]), dict(color=[1, -1, 1]),
                                 dict(color=[np.inf, 1, 1]), dict(subject_radius=0.0)])
def test_point_light_bad_input_is_a_clear_error(bad):
    args = dict(position=[0, 0, 2], color=[1, 1, 1], subject_radius=1.0) | bad
    with pytest.raises(LightingError):
        lamps.project_point_light(**args)


def test_point_light_at_huge_distance_is_finite():
    assert np.all(lamps.project_point_light([0, 0, 1e300], [1e30] * 3) == 0)
    light = lamps.project_point_light([0, 0, 1e6], [1e12] * 3)
    assert np.all(np.isfinite(light)) and light.sum() > 0
    assert not np.any(lamps.project_point_light([0, 0, 2], [0, 0, 0]))


def _lamp(kind, pos=(0.0, 0.0, 4.0), **kw):
    p = np.asarray(pos, float)
    return lamps.Lamp(kind, tuple(p), tuple(-p / np.linalg.norm(p)), (1.0, 1.0, 1.0), 100.0, **kw)


def test_strength_is_colour_energy_and_exposure():
    lamp = lamps.Lamp('POINT', (0, 0, 4), (0, 0, -1), (1.0, 0.5, 0.25), 10.0, exposure=2.0)
    np.testing.assert_allclose(lamp.strength(), [40.0, 20.0, 10.0])


def test_point_lamp_units():
    # P / (4 pi) W/sr, projected: the same as project_point_light with that intensity.
    light = lamps.lamp_to_light(_lamp('POINT'), 1.0)
    expected = lamps.project_point_light([0, 0, 4], [100 / (4 * math.pi)] * 3)
    np.testing.assert_allclose(light, expected)


def test_spot_masks_but_does_not_concentrate():
    wide = lamps.lamp_to_light(_lamp('SPOT', spot_size=math.radians(120)), 1.0)
    np.testing.assert_allclose(wide, lamps.lamp_to_light(_lamp('POINT'), 1.0), rtol=1e-6)
    # A spot aimed away from the subject gives nothing; a half-covering cone about a fraction.
    away = lamps.Lamp('SPOT', (0, 0, 4), (0, 0, 1), (1, 1, 1), 100.0, spot_size=math.radians(30))
    assert not lamps.lamp_to_light(away, 1.0).any()
    edge = lamps.lamp_to_light(_lamp('SPOT', pos=(0, 0, 1.5), spot_size=math.radians(40)), 1.0)
    ratio = edge.sum() / lamps.lamp_to_light(_lamp('POINT', pos=(0, 0, 1.5)), 1.0).sum()
    assert 0.05 < ratio < 0.95


def test_spot_mask_follows_cycles_smoothstep():
    size, blend = math.radians(60), 0.5
    cos_half = math.cos(size / 2)
    assert lamps.spot_mask(1.0, size, blend) == 1.0
    assert lamps.spot_mask(cos_half - 1e-9, size, blend) == 0.0
    mid = cos_half + 0.5 * (1 - cos_half) * blend
    assert lamps.spot_mask(mid, size, blend) == pytest.approx(0.5)
    assert lamps.spot_mask(cos_half + 1e-6, size, 0.0) == 1.0


@pytest.mark.parametrize("angle_deg", [0.0, 0.4, 10.0, 60.0])
def test_sun_delivers_its_irradiance_at_normal_incidence(angle_deg):
    sun = lamps.Lamp('SUN', (0, 0, 0), (0, 0, -1), (1, 1, 1), 3.0,
                     sun_angle=math.radians(angle_deg))
    light = lamps.lamp_to_light(sun, 1.0)
    e = lightvec.irradiance(light, np.array([0.0, 0.0, 1.0]))
    # The representation's cells cost up to 2% on a normal facing the lamp.
    assert e[0] == pytest.approx(3.0, rel=0.02)
    spread = (light[..., 0] > 0).sum()
    assert spread > 4 if angle_deg >= 10 else spread <= 4


@pytest.mark.parametrize("shape", lamps.AREA_SHAPES)
def test_far_area_lamp_is_a_point_of_its_power(shape):
    # Far away, a one-sided Lambertian panel of power P facing the subject has intensity P / pi.
    area = lamps.lamp_to_light(_lamp('AREA', pos=(0, 0, 100), area_shape=shape, size=1.0,
                                     size_y=0.5), 1.0)
    point = lamps.project_point_light([0, 0, 100], [100 / math.pi] * 3)
    np.testing.assert_allclose(area.sum(), point.sum(), rtol=0.01)


def test_area_lamp_normalize_and_facing():
    on = lamps.lamp_to_light(_lamp('AREA', size=2.0), 1.0)
    off = lamps.lamp_to_light(_lamp('AREA', size=2.0, normalize=False), 1.0)
    np.testing.assert_allclose(off, 4.0 * on, rtol=1e-5)  # power per m2 times 4 m2
    back = lamps.Lamp('AREA', (0, 0, 4), (0, 0, 1), (1, 1, 1), 100.0, size=1.0)
    assert not lamps.lamp_to_light(back, 1.0).any()  # panels emit from their front only


def test_near_area_lamp_spreads_over_its_solid_angle():
    near = lamps.lamp_to_light(_lamp('AREA', pos=(0, 0, 1.5), size=3.0), 1.0)
    assert (near[..., 0] > 0).sum() > 20  # a big close panel is a broad light


@pytest.mark.parametrize("bad,match", [
    (dict(kind='LASER'), "Unknown lamp type"), (dict(energy=-1.0), "negative energy"),
    (dict(energy=math.nan), "finite"), (dict(kind='AREA', size=0.0), "positive size"),
    (dict(kind='AREA', size=1.0, area_shape='STAR'), "shape"),
])
def test_lamp_bad_input_is_a_clear_error(bad, match):
    kw = dict(kind='POINT', position=(0, 0, 4), direction=(0, 0, -1), color=(1, 1, 1),
              energy=10.0) | bad
    with pytest.raises(LightingError, match=match):
        lamps.lamp_to_light(lamps.Lamp(**kw), 1.0)


def test_negligible_lamps_are_skipped_and_the_cost_is_measured():
    key = _lamp('POINT', pos=(1.0, 1.0, 4.0))
    dim = lamps.Lamp('POINT', (-3, 0, 1), (1, 0, 0), (1, 1, 1), 0.05)
    off = lamps.Lamp('SUN', (0, 0, 0), (0, -1, 0), (1, 1, 1), 0.0)
    light, skipped = lamps.lamps_to_light([key, dim, off], 1.0)
    assert skipped == [1, 2]
    full = lamps.lamp_to_light(key, 1.0) + lamps.lamp_to_light(dim, 1.0)
    n = _sphere_normals(4000)
    err = np.linalg.norm(lightvec.irradiance(light, n) - lightvec.irradiance(full, n)) \
        / np.linalg.norm(lightvec.irradiance(full, n))
    assert 0 < err < 1e-3  # measured 9.5e-4, the dim lamp's share of the power (9.5e-4)
    assert lamps.lamps_to_light([key, dim], 1.0, rel_threshold=0.0)[1] == []


def test_blackbody_is_normalised_and_ordered():
    for t in (1000, 2700, 6500, 12000, 40000):
        r, g, b = lamps.blackbody_rgb(t)
        assert 0.2126 * r + 0.7152 * g + 0.0722 * b == pytest.approx(1.0)
        assert min(r, g, b) >= 0
    assert lamps.blackbody_rgb(2700)[0] > 1 > lamps.blackbody_rgb(2700)[2]  # warm
    assert lamps.blackbody_rgb(12000)[2] > 1 > lamps.blackbody_rgb(12000)[0]  # cool
    assert lamps.blackbody_rgb(40000) == lamps.blackbody_rgb(12000)  # Blender's range
    with pytest.raises(LightingError):
        lamps.blackbody_rgb(-5)
