"""The blend of a frame's change of light with its neighbours' (addon/temporal.py)."""

import numpy as np
import pytest

from addon import lightvec, temporal


def coeffs(value, shape=(3, 4, 6), b=0.0):
    return (np.full(shape, value, np.float32), np.full(shape, b, np.float32))


def test_context_adds_the_neighbours_inside_the_clip():
    assert temporal.context_frames([0, 1, 2], 10) == [0, 1, 2, 3]
    assert temporal.context_frames([5], 10) == [4, 5, 6]
    assert temporal.context_frames([9, 3], 10) == [2, 3, 4, 8, 9]
    assert temporal.context_frames([], 10) == []


def turned(degrees):
    t = np.radians(degrees)
    return lightvec.splat_direction([np.cos(t) - 0.3 * np.sin(t), 0.0, np.sin(t) + 0.3 * np.cos(t)],
                                    10.0)


def alike(a, b):
    return temporal.alike(temporal.signature(a), temporal.signature(b))


def test_similar_lights_shade_alike():
    key = turned(0.0)
    assert alike(key, key * 1.04)
    assert not alike(key, key * 1.2)          # a flash
    assert alike(key, turned(2.0))             # an animated lamp, 2 deg a frame
    assert not alike(key, turned(10.0))
    assert not alike(key, lightvec.splat_direction([-1, 0, 0.3], 10.0))
    assert alike(lightvec.zeros(), lightvec.zeros())
    assert not alike(key, lightvec.zeros())


def test_blend_weights_and_missing_neighbours():
    a, b = temporal.blend(coeffs(2.0, b=1.0), coeffs(1.0), coeffs(5.0, b=3.0))
    np.testing.assert_allclose(a, 0.25 * 1 + 0.5 * 2 + 0.25 * 5)
    np.testing.assert_allclose(b, 0.5 * 1 + 0.25 * 3)
    a, _ = temporal.blend(coeffs(2.0), None, coeffs(5.0))  # the first frame: 2/3 and 1/3
    np.testing.assert_allclose(a, (2 * 2 + 5) / 3, rtol=1e-6)
    a, b = temporal.blend(coeffs(2.0, b=1.0), None, None)
    assert (a == 2).all() and (b == 1).all()


def test_blend_applies_on_the_frames_subject_only():
    mask = np.zeros((4, 6), np.float32)
    mask[:, 3:] = 1.0
    mask[:, 2] = 0.5
    a, _ = temporal.blend(coeffs(2.0), coeffs(4.0), coeffs(4.0), mask=mask)
    np.testing.assert_allclose(a[:, :, :2], 2.0)   # no subject here: its own change
    np.testing.assert_allclose(a[:, :, 2], 2.5)
    np.testing.assert_allclose(a[:, :, 3:], 3.0)


def test_neighbours_on_another_grid_are_resampled_and_placeholders_skipped():
    a, _ = temporal.blend(coeffs(2.0), coeffs(4.0, shape=(3, 8, 12)), None)
    assert a.shape == (3, 4, 6)
    np.testing.assert_allclose(a, (2 * 2 + 4) / 3, rtol=1e-6)
    # a frame with no portrait has a 1x1 placeholder: it is not blended, nor blended into
    a, _ = temporal.blend(coeffs(2.0), coeffs(1.0, shape=(3, 1, 1)), None)
    assert (a == 2).all()
    a, _ = temporal.blend(coeffs(1.0, shape=(3, 1, 1)), coeffs(2.0), coeffs(2.0))
    assert a.shape == (3, 1, 1) and (a == 1).all()


@pytest.mark.parametrize("value", [0.0, 1e4])
def test_blend_of_extreme_values_stays_finite(value):
    a, b = temporal.blend(coeffs(value, b=value), coeffs(value), coeffs(0.0, b=value))
    assert np.isfinite(a).all() and np.isfinite(b).all()
