"""Property-based tests (hypothesis) of the light-vector code: lightvec, hdri, lamps, normalise.

Documented behaviour for hard inputs: any valid input gives a finite, non-negative light vector;
lamps inside the subject (or at its centre) and non-finite or negative inputs raise LightingError;
lamps at huge distances give finite (possibly all-zero) light; the normalised light the engine feeds
the network stays finite in float16 for radiance from 1e-6 to 1e6.
"""

import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from addon import hdri, lamps, lightvec, normalise
from addon.errors import LightingError

FAST = settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.too_slow])

unit = st.floats(-1.0, 1.0, allow_nan=False)
direction = st.tuples(unit, unit, unit).filter(lambda v: math.hypot(*v) > 1e-3)
magnitude = st.floats(1e-6, 1e6)  # the dynamic range the engine must survive
rgb = st.tuples(magnitude, magnitude, magnitude)


@st.composite
def light_vectors(draw):
    """Random lights: a log-uniform field from 1e-6 to 1e6, often with one or a few hot texels."""
    seed = draw(st.integers(0, 2 ** 32 - 1))
    rng = np.random.default_rng(seed)
    light = 10.0 ** rng.uniform(-6, 6, lightvec.SHAPE)
    light *= rng.random(lightvec.SHAPE) < draw(st.floats(0.0, 1.0))  # sparsity: 0 = all black
    return light.astype(np.float32)


@st.composite
def equirect(draw):
    h = draw(st.integers(2, 24))
    seed = draw(st.integers(0, 2 ** 32 - 1))
    rng = np.random.default_rng(seed)
    img = (10.0 ** rng.uniform(-6, 3, (h, 2 * h, 3))).astype(np.float32)
    if draw(st.booleans()):  # a sun up to 1e6
        img[rng.integers(h), rng.integers(2 * h)] = draw(magnitude)
    return img


@FAST
@given(direction, rgb)
def test_splat_is_finite_non_negative_and_conserves_power(d, e):
    light = lightvec.splat_direction(d, e)
    assert light.dtype == np.float32 and np.all(np.isfinite(light)) and light.min() >= 0
    np.testing.assert_allclose(lightvec.total_power(light), e, rtol=1e-5)


@FAST
@given(equirect(), st.floats(-720, 720), st.floats(-90, 90))
def test_hdri_downsampling_is_finite_and_conserves_power(img, yaw, pitch):
    a = math.radians(pitch)
    tilt = np.array([[1, 0, 0], [0, math.cos(a), -math.sin(a)], [0, math.sin(a), math.cos(a)]])
    light = hdri.downsample(img, tilt @ hdri.FRONT_VIEW_WORLD_TO_FRAME, yaw_degrees=yaw)
    assert np.all(np.isfinite(light)) and light.min() >= 0
    h, w = img.shape[:2]
    truth = (img.astype(np.float64) * hdri.pixel_row_solid_angles(h, w)[:, None, None]).sum((0, 1))
    # Each pixel lands whole in the cell holding its centre, so a cell's pixels cover a little more
    # or less than its exact solid angle. When one pixel dominates a small map (enlarged to the
    # default 1024-pixel working width) that mismatch shows whole: the worst cell's coverage is off
    # by up to 3.5% at 1024 over 150 random pitches and yaws (9.3% at 512), and a drawn map with
    # yaw 3 deg came to 3.00003%. tests/core/test_lightvec.py covers realistic maps at 1%.
    np.testing.assert_allclose(lightvec.total_power(light), truth, rtol=0.05)


@FAST
@given(light_vectors(), st.integers(-3, 3))
def test_rotating_by_whole_turns_is_the_identity(light, turns):
    np.testing.assert_allclose(lightvec.rotate_azimuth(light, 360.0 * turns), light,
                               rtol=1e-6, atol=0)


@FAST
@given(light_vectors(), st.floats(-1000, 1000))
def test_rotation_keeps_each_rows_power(light, degrees):
    r = lightvec.rotate_azimuth(light, degrees)
    assert np.all(np.isfinite(r)) and r.min() >= 0
    np.testing.assert_allclose(r.astype(np.float64).sum(axis=1),
                               light.astype(np.float64).sum(axis=1), rtol=1e-5)


@FAST
@given(equirect(), st.floats(1e-3, 1e3))
def test_hdri_is_linear_in_intensity(img, c):
    a = hdri.downsample(img)
    b = hdri.downsample(img * np.float32(c))
    np.testing.assert_allclose(b, a * c, rtol=1e-4, atol=1e-30)


lamp_kinds = st.sampled_from(["POINT", "SPOT", "SUN", "AREA"])


@st.composite
def lamps_outside(draw):
    kind = draw(lamp_kinds)
    d = np.array(draw(direction))
    d = d / np.linalg.norm(d)
    dist = draw(st.floats(1.01, 1e4))
    return lamps.Lamp(kind, tuple(d * dist), tuple(-d), draw(st.tuples(*[st.floats(0, 1)] * 3)),
                      draw(st.floats(0.0, 1e6)), exposure=draw(st.floats(-10, 10)),
                      sun_angle=draw(st.floats(0, math.pi)),
                      spot_size=draw(st.floats(0.01, math.pi)),
                      spot_blend=draw(st.floats(0, 1)), size=draw(st.floats(0.01, 5)),
                      size_y=draw(st.floats(0.01, 5)),
                      area_shape=draw(st.sampled_from(lamps.AREA_SHAPES)))


@FAST
@given(lamps_outside(), st.floats(1e-3, 1e3))
def test_any_lamp_outside_is_finite_non_negative_and_linear(lamp, c):
    light = lamps.lamp_to_light(lamp, 1.0)
    assert light.shape == lightvec.SHAPE and np.all(np.isfinite(light)) and light.min() >= 0
    brighter = lamps.lamp_to_light(lamps.Lamp(**{**lamp.__dict__, "energy": lamp.energy * c}), 1.0)
    np.testing.assert_allclose(brighter, light * np.float32(c), rtol=1e-4, atol=1e-30)


@FAST
@given(lamp_kinds, direction)
def test_zero_energy_lamps_give_no_light_and_are_skipped(kind, d):
    lamp = lamps.Lamp(kind, tuple(3 * np.array(d) / np.linalg.norm(d)), d, (1, 1, 1), 0.0, size=1)
    assert not lamps.lamp_to_light(lamp, 1.0).any()
    light, skipped = lamps.lamps_to_light([lamp], 1.0)
    assert skipped == [0] and not light.any()


@FAST
@given(st.sampled_from(["POINT", "SPOT", "AREA"]), direction, st.floats(0.0, 0.999))
def test_lamps_inside_the_subject_or_at_its_centre_raise(kind, d, frac):
    pos = tuple(frac * np.array(d) / np.linalg.norm(d))
    with pytest.raises(LightingError, match="inside the subject radius"):
        lamps.lamp_to_light(lamps.Lamp(kind, pos, (0, 0, -1), (1, 1, 1), 10.0, size=0.1), 1.0)


@FAST
@given(st.sampled_from(["POINT", "SPOT", "AREA"]), direction, st.floats(1e6, 1e300))
def test_lamps_at_huge_distances_are_finite(kind, d, dist):
    d = np.array(d) / np.linalg.norm(d)
    lamp = lamps.Lamp(kind, tuple(d * dist), tuple(-d), (1, 1, 1), 1e6, size=1.0)
    light = lamps.lamp_to_light(lamp, 1.0)
    assert np.all(np.isfinite(light)) and light.min() >= 0


@FAST
@given(light_vectors())
def test_normalised_light_is_safe_in_float16(light):
    """What the engine feeds the network: light / k with k its mean radiance. Any light from
    1e-6 to 1e6 stays finite in float16 and keeps its shape (texels that float16 cannot hold below
    6e-8 of the mean flush to zero, as they would in the network's own half-precision path)."""
    norm, k = normalise.normalise_light(light)
    assert np.all(np.isfinite(norm)) and norm.min() >= 0
    if k == 0:
        assert not light.any() and not norm.any()
        return
    half = norm.astype(np.float16)
    assert np.all(np.isfinite(half)) and float(half.max()) < 65504
    # The mean radiance of the normalised light is 1 by construction.
    assert normalise.light_scale(norm) == pytest.approx(1.0, rel=1e-4)
    big = norm > 1e-3
    np.testing.assert_allclose(half[big].astype(np.float64), norm[big], rtol=1e-3)
    np.testing.assert_allclose(norm.astype(np.float64) * k, light, rtol=1e-4, atol=1e-30)


@FAST
@given(st.lists(st.tuples(direction, st.floats(1e-6, 1e6)), min_size=1, max_size=5),
       st.floats(1e-4, 1e-1))
def test_skipping_costs_at_most_the_threshold(suns, threshold):
    """lamps_to_light skips lamps below ``threshold`` of the total power: the power it drops is at
    most threshold x (number of lamps) of the total."""
    ls = [lamps.Lamp("SUN", (0, 0, 0), d, (1, 1, 1), e) for d, e in suns]
    light, skipped = lamps.lamps_to_light(ls, 1.0, rel_threshold=threshold)
    full = sum(lamps.light_power(lamps.lamp_to_light(x, 1.0)) for x in ls)
    dropped = full - lamps.light_power(light)
    assert -1e-4 * full <= dropped <= threshold * len(ls) * full + 1e-4 * full
    assert len(skipped) < len(ls)  # the brightest lamp is never skipped


def test_all_zero_light_and_bad_texels():
    norm, k = normalise.normalise_light(lightvec.zeros())
    assert k == 0 and not norm.any()
    bad = lightvec.uniform(1.0)
    bad[0, 0, 0] = np.nan
    with pytest.raises(LightingError):
        lightvec.validate(bad)

