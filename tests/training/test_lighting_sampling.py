"""Lighting sampling (paper sec. 4.3) on the shared HDRIs."""

import numpy as np
import pytest

from addon import hdri
from addon.hdri_io import read_hdri


@pytest.fixture(scope="module")
def bank(shared_data):
    from training.data import lighting_sampling
    return lighting_sampling.environment_bank(shared_data)


def test_bank_rotation_matches_direct_downsampling(bank, shared_data):
    from training.data import lighting_sampling
    names, b = bank
    i = names.index("blender/studio")
    img = read_hdri(shared_data / "hdri" / "blender" / "studio.exr")
    mean = hdri.downsample(img, max_width=256, repair=True).mean()
    for yaw in (0.0, 22.5 * 5, 22.5 / 8 * 37, 301.25):
        direct = hdri.downsample(img, yaw_degrees=yaw, max_width=256, repair=True) / mean
        np.testing.assert_allclose(lighting_sampling.environment(b, i, yaw), direct,
                                   rtol=1e-5, atol=1e-6)


def test_triplet_follows_the_paper_and_is_seeded(bank):
    from training.data import lighting_sampling
    _, b = bank
    for seed in range(5):
        li, lj, lk = lighting_sampling.sample_triplet(np.random.default_rng(seed), b)
        again = lighting_sampling.sample_triplet(np.random.default_rng(seed), b)
        np.testing.assert_array_equal(li, again[0])
        np.testing.assert_array_equal(lk, again[2])
        for lv in (li, lj, lk):
            assert lv.shape == (16, 16, 3) and lv.dtype == np.float32
            assert np.isfinite(lv).all() and lv.min() >= 0
    li, lj, lk = lighting_sampling.sample_triplet(np.random.default_rng(0), b, sampling=False)
    np.testing.assert_array_equal(li, lj)


def test_point_lights_are_one_to_three_coloured_lamps(bank):
    from training.data import lighting_sampling
    powers = [lighting_sampling.sample_h(np.random.default_rng(s)).sum() for s in range(20)]
    assert min(powers) > 0
    y = lighting_sampling.sample_h(np.random.default_rng(3))
    assert (y.reshape(-1, 3).max(1) > 0).sum() <= 3 * 4  # each lamp splats onto at most 4 texels
