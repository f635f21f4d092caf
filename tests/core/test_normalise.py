import numpy as np
import pytest

from addon import lightvec, normalise


def test_light_scale_of_uniform_is_its_radiance():
    assert normalise.light_scale(lightvec.uniform(3.0)) == pytest.approx(3.0)


def test_normalise_light_is_scale_invariant_and_zero_safe():
    rng = np.random.default_rng(0)
    light = rng.random((16, 16, 3)).astype(np.float32)
    a, ka = normalise.normalise_light(light)
    b, kb = normalise.normalise_light(light * 1e5)
    np.testing.assert_allclose(a, b, rtol=1e-5)
    assert kb == pytest.approx(ka * 1e5)
    z, kz = normalise.normalise_light(lightvec.zeros())
    assert kz == 0.0 and not z.any()


def test_exposure_scale_is_robust():
    rng = np.random.default_rng(0)
    frame = rng.random((64, 64, 3)).astype(np.float32)
    s = normalise.exposure_scale([frame])
    assert normalise.exposure_scale([frame * 4]) == pytest.approx(4 * s, rel=1e-5)
    bad = frame.copy()
    bad[0, 0] = np.nan
    bad[1, 1] = np.inf
    bad[2, 2] = -5
    assert np.isfinite(normalise.exposure_scale([bad]))
    assert normalise.exposure_scale([np.zeros((8, 8, 3), np.float32)]) == 1.0
    assert normalise.exposure_scale([]) == 1.0


def test_sample_frames_cover_the_clip_independent_of_chunks():
    assert normalise.sample_frame_indices(1) == [0]
    idx = normalise.sample_frame_indices(1000)
    assert idx[0] == 0 and idx[-1] == 999 and len(idx) == 16
    assert normalise.sample_frame_indices(0) == []
