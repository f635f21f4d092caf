"""Full-resolution transfer (tests/reference.py: addon/detail.py's method in numpy; the shipped
graphs equal it, tests/core/test_onnx_graph.py), measured against a synthetic ground truth.

The scene: a textured albedo (pixel-level texture the working resolution cannot see) with a
sharp-edged disc, lit by a smooth gradient; the target lighting is another gradient that also
changes exactly at the disc's edge. The "network" is perfect at the working resolution (the
area-averaged ground truth), so every error below is the transfer's own."""

import numpy as np
import pytest

from addon import detail
from tests import reference


def scene(h=192, w=256, seed=0):
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:h, 0:w].astype(np.float32) / max(h, w)
    tex = 0.6 + 0.3 * rng.random((h, w, 1)).astype(np.float32)
    disc = ((x - 0.5) ** 2 + (y - 0.4) ** 2 < 0.09)[..., None]
    albedo = np.where(disc, np.float32([0.8, 0.55, 0.45]), np.float32([0.1, 0.3, 0.2])) * tex
    shade_in = (0.3 + 0.7 * x)[..., None] * np.ones(3, np.float32)
    shade_out = (1.2 - 0.9 * x)[..., None] * np.float32([1.0, 0.9, 1.1]) * np.where(disc, 1, 0.25)
    return (albedo * shade_in).astype(np.float32), (albedo * shade_out).astype(np.float32)


def rel_rmse(a, b):
    return float(np.sqrt(np.mean((a - b) ** 2)) / np.sqrt(np.mean(b ** 2)))


def low(inp, truth, factor):
    h, w = inp.shape[0] // factor, inp.shape[1] // factor
    return detail.resize(inp, h, w), detail.resize(truth, h, w)


@pytest.mark.parametrize("factor,bound", [(2, 0.025), (4, 0.04)])
def test_transfer_beats_the_alternatives(factor, bound):
    inp, truth = scene()
    il, rl = low(inp, truth, factor)
    h, w = inp.shape[:2]
    guided = rel_rmse(reference.transfer(inp, il, rl), truth)
    plain = rel_rmse(reference.upsample_only(rl, h, w), truth)
    ratio = rel_rmse(reference.ratio_transfer(inp, il, rl), truth)
    assert guided < bound
    # measured: x2 1.8% (ratio 5.9%, plain 12.5%); x4 3.4% (ratio 6.8%, plain 15.2%)
    assert guided < 0.6 * ratio and guided < 0.25 * plain


def test_no_halo_at_a_lighting_edge():
    # 1-D step: the light changes exactly where the albedo does. Overshoot past the truth's
    # range would be a halo.
    w = 128
    albedo = np.where(np.arange(w) < 61, 0.2, 0.8).astype(np.float32)
    inp = np.repeat(np.tile(albedo[None, :, None], (16, 1, 3)), 1, axis=0)
    light_out = np.where(np.arange(w) < 61, 3.0, 0.5).astype(np.float32)
    truth = inp * light_out[None, :, None]
    il, rl = low(inp, truth, 4)
    out = reference.transfer(inp, il, rl)
    assert out.min() >= truth.min() - 0.02 and out.max() <= truth.max() + 0.02
    far = np.r_[0:52, 70:w]  # away from the edge's own low-res pixel, the result is exact
    np.testing.assert_allclose(out[:, far], truth[:, far], rtol=0.02)


def test_dark_noisy_pixels_do_not_blow_up():
    rng = np.random.default_rng(3)
    h, w = 64, 96
    inp = np.abs(rng.normal(0.0, 1e-4, (h, w, 3))).astype(np.float32)  # near-black, noisy
    truth = np.full((h, w, 3), 0.5, np.float32)  # a new light fills the shadow
    il, rl = low(inp, truth, 4)
    out = reference.transfer(inp, il, rl)
    assert np.all(np.isfinite(out))
    assert abs(out.mean() - 0.5) < 0.01 and out.max() < 0.6 and out.min() > 0.4


def test_non_finite_low_res_values_do_not_spread():
    inp, truth = scene(64, 64)
    il, rl = low(inp, truth, 2)
    rl[3, 3] = np.nan
    out = reference.transfer(inp, il, rl)
    assert np.all(np.isfinite(out))


def test_same_resolution_is_identity_and_odd_sizes_work():
    inp, truth = scene(17, 9)
    np.testing.assert_array_equal(reference.transfer(inp, inp, truth), truth)
    il, rl = detail.resize(inp, 5, 3), detail.resize(truth, 5, 3)
    assert reference.transfer(inp, il, rl).shape == (17, 9, 3)
    one = np.ones((1, 1, 3), np.float32)
    assert reference.transfer(np.ones((3, 2, 3), np.float32), one, 2 * one).shape == (3, 2, 3)


def test_area_resize_keeps_means_exact():
    rng = np.random.default_rng(0)
    x = rng.random((108, 192, 3)).astype(np.float32)
    for h, w in [(54, 96), (29, 51), (1, 1)]:
        y = detail.resize(x, h, w)
        assert y.shape == (h, w, 3)
        np.testing.assert_allclose(y.mean(axis=(0, 1)), x.mean(axis=(0, 1)), rtol=2e-3)
    np.testing.assert_allclose(detail.resize(np.full((30, 40, 3), 7.0, np.float32), 11, 13), 7.0,
                               rtol=1e-6)
    block = detail.resize(x, 54, 96)  # exact factor 2: plain 2x2 means
    np.testing.assert_allclose(block, x.reshape(54, 2, 96, 2, 3).mean(axis=(1, 3)), rtol=1e-5)


@pytest.mark.parametrize("h,w,size,want", [(1080, 1920, 512, (288, 512)),
                                           (1920, 1080, 512, (512, 288)),
                                           (100, 80, 512, (100, 80)), (1, 1, 512, (1, 1)),
                                           (4320, 7680, 384, (216, 384))])
def test_working_shape(h, w, size, want):
    assert detail.working_shape(h, w, size) == want


@pytest.mark.parametrize("shape,big", [((3, 7, 9), (20, 31)), ((8, 72, 128), (198, 352)),
                                       ((2, 5, 5), (5, 12)), ((3, 7, 9), (131, 9)),
                                       ((2, 6, 7), (13, 200)), ((1, 1, 1), (3, 4))])
def test_enlarge_planar_is_resize_channels_first(shape, big):
    x = np.random.default_rng(1).random(shape).astype(np.float32)
    want = detail.resize(x.transpose(1, 2, 0), *big).transpose(2, 0, 1)
    got = detail.enlarge_planar(x, *big)
    assert got.shape == (shape[0],) + big and got.flags.c_contiguous
    np.testing.assert_allclose(got, want, atol=1e-6)
    with pytest.raises(ValueError):
        detail.enlarge_planar(x, shape[1] - 1, big[1])


@pytest.mark.parametrize("hw", [(1080, 1920), (720, 1280), (512, 512), (2160, 3840), (192, 168)])
@pytest.mark.parametrize("f", [0.188, 0.3, 0.58, 0.9])
def test_block_scale_gives_whole_grids_with_block_paths(hw, f):
    got = detail.block_scale(*hw, f)
    if got is None:  # only where no ratio of small blocks lies near f
        candidates = [(q, p) for p in range(5, detail.MAX_BLOCK + 1) if not (hw[0] % p or hw[1] % p)
                      for q in range(4, p) if abs(np.log(q / (p * f))) <= np.log1p(0.1)]
        assert not candidates
        return
    q, p = got
    assert 4 <= q < p <= detail.MAX_BLOCK and abs(q / p / f - 1) <= 0.1
    gh, gw = hw[0] * q // p, hw[1] * q // p
    assert (gh * p, gw * p) == (hw[0] * q, hw[1] * q)  # whole numbers of pixels
    assert detail.area_blocks(hw[0], gh) is not None and detail.area_blocks(hw[1], gw) is not None
    assert (detail.upsample_blocks(gh, hw[0]) is not None
            and detail.upsample_blocks(gw, hw[1]) is not None)


def test_block_scale_is_the_nearest_and_none_without_one():
    assert detail.block_scale(1080, 1920, 0.188) == (11, 60)  # 0.1833: 2.5% under
    assert detail.block_scale(1081, 1919, 0.3) is None  # coprime sides
    assert detail.block_scale(1080, 1920, 1.0) is None
    assert detail.block_scale(1080, 1920, 0.0) is None
