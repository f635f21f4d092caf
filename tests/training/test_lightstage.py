"""The synthetic light stage: linearity, determinism, splits, flow, hard cases (small sizes)."""

import math

import numpy as np
import pytest
import torch

from addon import lightvec
from training.lightstage import layout

RES = 48


def test_layout_has_114_distinct_lights_and_conserves_power():
    d = layout.directions()
    assert d.shape == (114, 3)
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-12)
    cos = d @ d.T - 2 * np.eye(114)
    assert np.degrees(np.arccos(cos.max())) > 15.0  # no two lights closer than 15 degrees
    np.testing.assert_allclose(layout.projection().sum(axis=0), 1.0, atol=1e-12)
    rng = np.random.default_rng(0)
    light = rng.uniform(0, 3, lightvec.SHAPE)
    np.testing.assert_allclose(layout.weights(light).sum(axis=0), lightvec.total_power(light),
                               rtol=1e-12)


def test_a_lamp_on_the_right_drives_lights_on_the_right():
    light = lightvec.splat_direction([1.0, 0.0, 0.0], [1.0, 1.0, 1.0])
    w = layout.weights(light)[:, 0]
    assert layout.directions()[np.argmax(w), 0] > 0.9


@pytest.fixture(scope="module")
def scene(shared_data):
    from training.lightstage.scene import Scene
    from training.lightstage.subject import Performance, sample_camera, sample_identity
    from training.lightstage import assets

    torch.set_num_threads(1)
    m = assets.load_head(shared_data)
    cam = sample_camera(np.random.default_rng(5), RES)
    return Scene(sample_identity(3), Performance(1, m.expression_names), cam, shared_data, 9)


def test_image_under_a_light_vector_is_the_weighted_sum_of_olat_images(scene):
    f = scene.frame(0.4)
    rng = np.random.default_rng(1)
    light = rng.uniform(0, 2, lightvec.SHAPE).astype(np.float32)
    light[3, 9] = 40.0  # a bright sun makes the specular and shadow terms matter
    img = scene.shade(f, [light])[0].double()
    olat = scene.shade_weights(f, torch.ones(114, 1, 3) * torch.eye(114)[:, :, None]).double()
    w = torch.from_numpy(layout.weights(light))  # (114, 3)
    total = torch.einsum("jc,jchw->chw", w, olat)
    assert img.abs().max() > 0.1
    np.testing.assert_allclose(img.numpy(), total.numpy(), rtol=1e-4, atol=1e-5 * float(img.max()))


def test_shadows_darken_the_side_away_from_a_side_light(scene):
    f = scene.frame(0.0)
    right = scene.shade(f, [lightvec.splat_direction([1, 0, 0.2], [3, 3, 3])])[0]
    olat_vis = f.transfer.diffuse
    assert float(olat_vis.max()) <= 1.0 + 1e-6 and float(olat_vis.min()) >= 0.0
    m = f.gb.mask
    xs = torch.nonzero(m)[:, 1].float()
    cx = float(xs.mean())
    lum = right.sum(0)
    assert float(lum[m & (torch.arange(RES)[None, :] > cx + 3)].mean()) > \
        2.0 * float(lum[m & (torch.arange(RES)[None, :] < cx - 3)].mean())


def test_all_zero_light_is_black_and_a_huge_texel_stays_finite(scene):
    f = scene.frame(1.0)
    black = scene.shade(f, [lightvec.zeros()])
    assert float(black.abs().max()) == 0.0
    sun = lightvec.zeros()
    sun[2, 8] = 1e5
    img = scene.shade(f, [sun])
    assert torch.isfinite(img).all() and float(img.max()) > 0


def _warp(img, flow):
    """Sample img (C, H, W) at x + flow (bilinear, border clamp)."""
    c, h, w = img.shape
    ys, xs = np.meshgrid(np.arange(h), np.arange(w), indexing="ij")
    gx = (xs + 0.5 + flow[0]) / w * 2 - 1
    gy = (ys + 0.5 + flow[1]) / h * 2 - 1
    grid = torch.from_numpy(np.stack([gx, gy], -1)[None]).float()
    return torch.nn.functional.grid_sample(torch.from_numpy(img)[None], grid, align_corners=False,
                                           padding_mode="border")[0].numpy()


@pytest.fixture(scope="module")
def dataset(shared_data):
    from training.data.dataset import LightStageDataset
    torch.set_num_threads(1)
    return LightStageDataset("train", RES, seed=11, length=50, data_root=shared_data)


def test_samples_follow_the_api(dataset):
    from addon.contract import PARSING_CLASSES
    s = dataset[0]
    k = len(PARSING_CLASSES)
    shapes = {"img_t_i": (3, RES, RES), "img_t1_j": (3, RES, RES), "gt_t_k": (3, RES, RES),
              "gt_t1_k": (3, RES, RES), "light_i": (16, 16, 3), "light_j": (16, 16, 3),
              "light_k": (16, 16, 3), "mask_t": (1, RES, RES), "mask_t1": (1, RES, RES),
              "parsing_t": (k, RES, RES), "parsing_t1": (k, RES, RES), "flow_fw": (2, RES, RES),
              "flow_bw": (2, RES, RES), "valid_fw": (1, RES, RES), "valid_bw": (1, RES, RES)}
    assert set(s) == set(shapes)
    for key, shape in shapes.items():
        assert s[key].shape == shape and s[key].dtype == np.float32, key
        assert np.isfinite(s[key]).all(), key
    np.testing.assert_array_equal(s["parsing_t"][0], s["mask_t"][0] > 0)
    # Every foreground pixel carries exactly one semantic class; the background none.
    np.testing.assert_array_equal(s["parsing_t"][1:].sum(0), s["parsing_t"][0])
    assert s["mask_t"].mean() > 0.05
    # Anti-aliased silhouettes: coverage in quarters, fractional along the outline only.
    m = s["mask_t"][0]
    assert m.min() >= 0 and m.max() <= 1
    np.testing.assert_array_equal(m * 4, np.round(m * 4))
    edge = (m > 0) & (m < 1)
    assert 0 < edge.sum() < 0.2 * (m > 0).sum()


def test_samples_are_deterministic(dataset, shared_data):
    from training.data.dataset import LightStageDataset
    a = dataset[7]
    b = LightStageDataset("train", RES, seed=11, length=50, data_root=shared_data)[7]
    c = LightStageDataset("train", RES, seed=12, length=50, data_root=shared_data)[7]
    for key in a:
        np.testing.assert_array_equal(a[key], b[key])
    assert not np.array_equal(a["img_t_i"], c["img_t_i"])


def test_held_out_identities_never_reach_training(dataset, shared_data):
    from training.data.dataset import LightStageDataset, split_of_identity
    train = set(dataset.ids)
    for split in ("val", "test"):
        held = LightStageDataset(split, RES, data_root=shared_data, length=10)
        assert not train & set(held.ids)
        assert all(split_of_identity(i) == split for i in held.ids)
    assert all(split_of_identity(i) == "train" for i in train)


def test_flow_warps_frame_t1_onto_frame_t_where_visible(dataset):
    s = dataset[3]
    for src, dst, fl, valid, mask in (("gt_t_k", "gt_t1_k", "flow_fw", "valid_fw", "mask_t"),
                                      ("gt_t1_k", "gt_t_k", "flow_bw", "valid_bw", "mask_t1")):
        warped = _warp(s[dst], s[fl])
        sel = (s[valid][0] > 0) & (s[mask][0] > 0)
        # Stay away from silhouettes, where bilinear warping mixes in the background.
        er = torch.nn.functional.max_pool2d(torch.from_numpy(1 - s[mask])[None], 3, 1, 1)[0, 0] == 0
        sel &= er.numpy()
        assert sel.sum() > 100
        err = np.abs(warped - s[src])[:, sel].mean()
        still = np.abs(s[dst] - s[src])[:, sel].mean()
        scale = s[src][:, sel].mean()
        assert err < 0.08 * scale, (err, scale)
        assert err <= still + 1e-6  # following the flow is never worse than standing still


@pytest.mark.parametrize("case", ["degenerate_identity", "extreme_expression", "back_view",
                                  "grazing_view"])
def test_hard_cases_give_finite_images_and_flows(shared_data, case):
    from dataclasses import replace

    from training.lightstage import assets
    from training.lightstage.scene import Scene
    from training.lightstage.subject import Camera, Performance, sample_identity

    torch.set_num_threads(1)
    m = assets.load_head(shared_data)
    ident = sample_identity(2)
    perf = Performance(3, m.expression_names)
    if case == "degenerate_identity":
        ident = replace(ident, shape=np.full(100, 8.0, np.float32))
    elif case == "extreme_expression":
        perf = Performance(3, m.expression_names, intensity=3.0)
    else:
        perf = Performance(3, m.expression_names, head_range=0.0)
        perf.yaw = lambda t: 180.0 if case == "back_view" else 88.0
    cam = Camera(focal=RES * 1.5, cx=RES / 2, cy=RES / 2, distance=70.0, height=RES, width=RES)
    sc = Scene(ident, perf, cam, shared_data, 1)
    f0, f1 = sc.frame(0.5), sc.frame(0.54)
    img = sc.shade(f0, [lightvec.uniform(1.0)])
    fl, valid = sc.flow(f0, f1)
    assert torch.isfinite(img).all() and torch.isfinite(fl).all()
    assert f0.gb.mask.sum() > 50
    assert 0.0 <= float(img.min()) and float(img.max()) < 50.0
    assert math.isfinite(float(valid.sum()))


def test_selective_effects_are_exact_with_every_light_and_close_with_the_strongest(scene):
    """The 'simulate only what the scene calls for' shortcut: all lights -> the full sum exactly;
    the strongest lights carrying 90% of the power -> a small error with fewer shadow maps."""
    f = scene.frame(0.2)
    rng = np.random.default_rng(4)
    light = rng.uniform(0, 0.5, lightvec.SHAPE).astype(np.float32)
    light[4, 10] = 600.0  # a sun carrying most of the power, as in a sunny HDRI
    full = scene.shade(f, [light])
    exact, n_all = scene.shade_selective(f, [light], energy=1.0 + 1e-9)
    np.testing.assert_allclose(exact.numpy(), full.numpy(), rtol=1e-4, atol=1e-6)
    fast, n = scene.shade_selective(f, [light], energy=0.9)
    assert n < 40 and n_all == 114
    m = f.gb.mask
    rel = float(((fast - full)[0][:, m] ** 2).mean().sqrt() / full[0][:, m].mean())
    assert rel < 0.15, rel
    black, n0 = scene.shade_selective(f, [lightvec.zeros()])
    assert n0 == 0 and float(black.abs().max()) == 0.0
