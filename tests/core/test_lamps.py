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
