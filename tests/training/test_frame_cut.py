"""bench.frame_cut's pieces: the crop of a cut frame, its fills beyond the edge, the distance to
the cut and the scores; its "black" is the product's own crop."""

import numpy as np
import pytest

from addon import framing, portrait
from bench import frame_cut


def cut_top_left(h=32, w=40, top=6, left=9):
    inside = np.zeros((h, w), bool)
    inside[top:, left:] = True
    return inside


def test_edge_distance_counts_only_the_sides_that_cut():
    inside = cut_top_left()
    d = frame_cut.edge_distance(inside)
    assert d[6, 30] == pytest.approx(0.5) and d[16, 35] == pytest.approx(10.5)
    assert d[20, 9] == pytest.approx(0.5)  # the left cut, nearer than the top one there
    assert d[31, 39] == pytest.approx(min(31 - 6, 39 - 9) + 0.5)  # bottom/right: the picture's own
    assert np.isinf(frame_cut.edge_distance(np.ones((8, 8), bool))).all()


def test_repeat_edges_copies_the_nearest_edge_pixel_outward():
    inside = cut_top_left()
    img = np.random.default_rng(0).random((3, 32, 40)).astype(np.float32)
    rep = frame_cut.repeat_edges(img, inside)
    np.testing.assert_array_equal(rep[:, inside], img[:, inside])
    np.testing.assert_array_equal(rep[:, 0, 20], img[:, 6, 20])    # above the top cut
    np.testing.assert_array_equal(rep[:, 15, 0], img[:, 15, 9])    # left of the left cut
    np.testing.assert_array_equal(rep[:, 2, 3], img[:, 6, 9])      # the corner


def test_fills_keep_the_frame_and_differ_only_beyond_it():
    inside = cut_top_left()
    img = np.random.default_rng(1).random((3, 32, 40)).astype(np.float32)
    rep = frame_cut.repeat_edges(img, inside)
    valid = inside.astype(np.float32)
    black = frame_cut.fill(rep, valid, "black")
    copies = frame_cut.fill(rep, valid, "edge copies")
    blurred = frame_cut.fill(rep, valid, "edge copies, blurred")
    for f in (black, copies, blurred):
        np.testing.assert_allclose(f[:, inside], img[:, inside], atol=1e-6)
    assert (black[:, ~inside] == 0).all()
    np.testing.assert_array_equal(copies, rep)
    assert blurred[:, ~inside].std() < 0.5 * copies[:, ~inside].std()
    with pytest.raises(ValueError):
        frame_cut.fill(rep, valid, "grey")
    with pytest.raises(ValueError), frame_cut.product_fill("grey"):
        pass


def test_black_is_the_products_own_crop_and_the_context_steps_aside():
    rng = np.random.default_rng(2)
    x = rng.random((3, 48, 40)).astype(np.float32)
    box = framing.Box(cx=20.0, cy=18.0, size=70.0)  # past the frame on every side
    want, want_valid = portrait.crop_planar(x, box, 32)
    rep = np.stack([framing.crop(x[c], box, 32) for c in range(3)])
    np.testing.assert_allclose(frame_cut.fill(rep, want_valid, "black"), want, atol=1e-6)
    original = portrait.crop_planar
    with frame_cut.product_fill("black"):
        assert portrait.crop_planar is original
        got, valid = portrait.crop_planar(x, box, 32)
        np.testing.assert_allclose(got, want, atol=1e-6)
        np.testing.assert_array_equal(valid, want_valid)
    with frame_cut.product_fill("edge copies"):
        got, _ = portrait.crop_planar(x, box, 32)
        assert (got[:, want_valid == 0] > 0).all()  # the frame's own pixels, not black
    assert portrait.crop_planar is original


def test_band_scores_read_the_angle_and_the_up_down_bias():
    rng = np.random.default_rng(3)
    n = rng.normal(0, 0.3, (3, 10, 10))
    n[2] = 1.0
    truth = n / np.linalg.norm(n, axis=0)
    sel = np.ones((10, 10), bool)
    assert frame_cut.band_scores(truth, truth, sel) == pytest.approx((0.0, 0.0), abs=1e-4)
    down = truth.copy()
    down[1] -= 0.3
    ang, bias = frame_cut.band_scores(down, truth, sel)
    assert ang > 5.0 and bias < -0.1


def test_the_template_row_holds_the_face_skin_inside_the_frame_only():
    """frame_cut.templated: the network's normals with the product's face template held over
    the face skin that is inside the frame (and its detail raised, portrait.deepened); a crop
    whose face skin lies all beyond the edge keeps the network's normals."""
    from types import SimpleNamespace

    from addon import engine, facetemplate, intrinsic

    h = w = 64
    yy, xx = np.mgrid[:h, :w] + 0.5
    skin = (((yy - 32) ** 2 + (xx - 30) ** 2) < 18 ** 2).astype(np.float32)
    normal = np.zeros((3, h, w), np.float32)
    normal[2] = 1.0
    res = engine.IntrinsicResult(normal, np.zeros((h, w), np.float32),
                                 np.full((3, h, w), 0.5, np.float32),
                                 np.stack([np.ones((h, w), np.float32), skin,
                                           np.zeros((h, w), np.float32)]))
    session = SimpleNamespace(card=SimpleNamespace(classes=("foreground", "skin", "hair"),
                                                working_size=h))
    inside = np.ones((h, w), np.float32)
    got = frame_cut.templated(session, res, inside)
    tpl = facetemplate.cached(facetemplate.SHIPPED)
    want = portrait.deepened(facetemplate.held(intrinsic.Buffers(
        normal, res.height, res.albedo, np.ones((h, w), np.float32), skin), tpl),
        portrait.NORMAL_DETAIL, portrait.NORMAL_DETAIL_SIGMA).normal
    np.testing.assert_allclose(got, want, atol=1e-6)
    assert np.abs(got[1] - normal[1]).max() > 0.05  # the template turned the face
    np.testing.assert_array_equal(frame_cut.templated(session, res, 0.0 * inside), normal)
