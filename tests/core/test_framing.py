"""Portrait framing on synthetic coarse maps: where the box lands, how it is smoothed over a clip,
and how pixels travel between the frame and the network's square (edges, fill, round trip)."""

import math
import tracemalloc

import numpy as np
import pytest

from addon import framing
from addon.framing import Box


def disc(shape, centre_xy, radius, scale_xy=(1.0, 1.0)):
    """Soft probability map of a disc given in full-frame pixels, on a coarse grid of ``shape``
    whose pixels are ``scale_xy`` full-frame pixels wide and tall; 0.5 exactly on the rim."""
    h, w = shape
    y = (np.arange(h) + 0.5)[:, None] * scale_xy[1]
    x = (np.arange(w) + 0.5)[None, :] * scale_xy[0]
    d = np.hypot(x - centre_xy[0], y - centre_xy[1])
    return (1.0 / (1.0 + np.exp((d - radius) / (0.5 * min(scale_xy))))).astype(np.float32)


def test_disc_in_wide_frame():
    frame = (1080, 1920)
    coarse = (72, 128)                        # 15 full-frame pixels per coarse pixel
    centre, radius = (1350.0, 450.0), 120.0   # off-centre, right half
    face = disc(coarse, centre, radius, (15.0, 15.0))
    matte = np.maximum(face, disc(coarse, (1350.0, 900.0), 400.0, (15.0, 15.0)))
    box = framing.find_portrait(face, matte, frame, margin=2.0)
    assert box is not None
    assert box.size == pytest.approx(2.0 * 2 * radius, rel=0.10)
    assert abs(box.cx - centre[0]) < 0.02 * frame[1]
    assert abs(box.cy - centre[1]) < 0.02 * frame[1]
    # Lifted for the hair, not pushed down.
    assert box.cy == pytest.approx(centre[1] - framing.LIFT * box.size, abs=0.01 * frame[1])


def test_vertical_frame_with_non_square_coarse_pixels():
    frame = (1920, 1080)
    coarse = (64, 64)                         # coarse pixels 16.875 wide, 30 tall
    centre, radius = (400.0, 700.0), 150.0
    scale = (frame[1] / 64, frame[0] / 64)
    face = disc(coarse, centre, radius, scale)
    box = framing.find_portrait(face, np.zeros_like(face), frame, margin=2.5)
    assert box is not None
    assert box.size == pytest.approx(2.5 * 2 * radius, rel=0.10)
    assert abs(box.cx - centre[0]) < 0.02 * frame[1]
    assert abs(box.cy + framing.LIFT * box.size - centre[1]) < 0.02 * frame[1]


def test_two_faces_the_bigger_wins():
    frame, coarse, s = (720, 1280), (90, 160), (8.0, 8.0)
    small = disc(coarse, (300.0, 300.0), 50.0, s)
    big = disc(coarse, (900.0, 350.0), 90.0, s)
    face = np.maximum(small, big)
    box = framing.find_portrait(face, face, frame)
    assert abs(box.cx - 900.0) < 0.02 * frame[1]
    assert box.size == pytest.approx(2.0 * 180.0, rel=0.10)


def test_no_face_uses_the_top_of_the_matte():
    frame, coarse = (720, 1280), (72, 128)    # 10 full-frame pixels per coarse pixel
    matte = np.zeros(coarse, np.float32)
    matte[30:72, 40:80] = 0.9                 # a person: 40 wide, from row 30 to the bottom
    face = np.zeros(coarse, np.float32)
    face[5, 5] = 1.0                          # a speck below min_face_px: ignored
    box = framing.find_portrait(face, matte, frame)
    assert box is not None
    head_rows = 0.6 * 40                      # the head: rows 30 .. 54
    assert box.cx == pytest.approx(600.0, abs=0.02 * frame[1])
    assert box.cy + framing.LIFT * box.size == pytest.approx((30 + head_rows / 2) * 10, abs=15)
    # The extent is calibrated for a face-like ellipse; a rectangle's comes out ~7% larger.
    assert box.size == pytest.approx(2.0 * 400, rel=0.15)


@pytest.mark.parametrize("value", [0.0, 0.4, np.nan])
def test_nothing_found_gives_none(value):
    empty = np.full((36, 64), value, np.float32)
    assert framing.find_portrait(empty, empty, (1080, 1920)) is None


@pytest.mark.parametrize("size", [96, 24])     # ~1.4 and ~5.6 frame pixels per crop pixel
def test_face_at_the_frame_edge_crops_with_edge_pixels(size):
    frame = (180, 320)
    coarse = (36, 64)
    face = disc(coarse, (10.0, 90.0), 30.0, (5.0, 5.0))   # cut by the left edge
    box = framing.find_portrait(face, face, frame)
    assert box is not None and box.size >= framing.MIN_SIDE
    assert box.cx - box.size / 2 < 0                      # reaches beyond the frame
    rng = np.random.default_rng(1)
    image = rng.random((*frame, 3)).astype(np.float32)
    image[:, 0] = 7.0                                      # the edge column, recognisable
    out = framing.crop(image, box, size)
    weight = framing.crop_weight(box, frame, size)
    assert out.shape == (size, size, 3) and out.dtype == np.float32
    assert weight.shape == (size, size) and weight.dtype == np.float32
    outside = weight == 0.0
    inside = weight == 1.0
    assert outside.any() and inside.any()
    if size == 24:
        # Area averaging blends the boundary's neighbours: look one crop pixel further out.
        outside[:, :-1] &= outside[:, 1:]
        assert outside.any()
    np.testing.assert_array_equal(out[outside], 7.0)       # replicated, never zeros or garbage
    assert out[inside].max() < 7.0
    assert np.all((weight >= 0) & (weight <= 1))


def test_crop_weight_marks_every_side():
    box = Box(50.0, 40.0, 200.0)                           # larger than the 80 x 100 frame
    weight = framing.crop_weight(box, (80, 100), 50)      # 4 frame pixels per crop pixel
    # Inside: x in [0, 100] -> crop columns 12.5..37.5; y in [0, 80] -> rows 15..35.
    assert weight[25, 25] == 1.0
    assert weight[25, 0] == 0.0 and weight[25, 49] == 0.0
    assert weight[0, 25] == 0.0 and weight[49, 25] == 0.0
    assert weight[25, 12] == pytest.approx(0.5) and weight[25, 37] == pytest.approx(0.5)
    assert weight.sum() == pytest.approx(80 * 100 / 16)   # covers exactly the frame's area


def smooth_image(h, w):
    y, x = np.mgrid[0:h, 0:w].astype(np.float32)
    return np.stack([np.sin(x / 37.0) * np.cos(y / 29.0), x / w, 0.5 + 0.3 * np.sin((x + y) / 53.0)],
                    axis=-1).astype(np.float32)


@pytest.mark.parametrize("side,size", [(120.0, 128), (200.0, 64), (90.5, 37)])
def test_crop_then_uncrop_round_trips(side, size):
    frame = (180, 320)
    image = smooth_image(*frame)
    box = Box(170.3, 95.7, side)
    back = framing.uncrop(framing.crop(image, box, size), box, frame, fill=0.0)
    # Compare inside the box, away from its border (where the round trip clamps).
    y0, y1 = int(box.cy - side / 2) + 4, int(box.cy + side / 2) - 4
    x0, x1 = int(box.cx - side / 2) + 4, int(box.cx + side / 2) - 4
    err = np.abs(back[y0:y1, x0:x1] - image[y0:y1, x0:x1])
    assert err.max() < 0.03
    assert err.mean() < 0.005


def test_crop_area_averages_when_shrinking():
    # A one-pixel checkerboard averages to 0.5; plain point sampling would alias to 0s and 1s.
    y, x = np.mgrid[0:256, 0:256]
    image = ((x + y) % 2).astype(np.float32)[..., None]
    out = framing.crop(image, Box(128.0, 128.0, 256.0), 32)
    np.testing.assert_allclose(out, 0.5, atol=1e-6)


@pytest.mark.parametrize("fill", [0.25, (0.1, 0.2, 0.3)])
def test_uncrop_fills_outside_the_box(fill):
    frame = (90, 160)
    box = Box(60.0, 40.0, 50.0)
    buf = np.ones((32, 32, 3), np.float32)
    out = framing.uncrop(buf, box, frame, fill)
    assert out.shape == (*frame, 3) and out.dtype == np.float32
    y, x = np.mgrid[0:90, 0:160] + 0.5
    inbox = (np.abs(x - box.cx) <= 25) & (np.abs(y - box.cy) <= 25)
    np.testing.assert_array_equal(out[inbox], 1.0)
    np.testing.assert_array_equal(out[~inbox], np.broadcast_to(np.float32(fill), (int((~inbox).sum()), 3)))


def test_uncrop_4k_stays_small():
    frame = (2160, 3840)
    buf = np.random.default_rng(0).random((256, 256, 3)).astype(np.float32)
    box = Box(1900.0, 900.0, 1700.0)
    tracemalloc.start()
    out = framing.uncrop(buf, box, frame, fill=0.0)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    full = 2160 * 3840 * 3 * 4
    assert out.shape == (*frame, 3)
    assert peak < 1.5 * full                               # the output plus small bands
    assert out[0, 0, 0] == 0.0 and out[900, 1900].min() >= 0.0


def test_full_frame_box_holds_the_frame():
    assert framing.full_frame_box((1080, 1920)).to_tuple() == (960.0, 540.0, 1920.0)
    assert framing.full_frame_box((1920, 1080)).to_tuple() == (540.0, 960.0, 1920.0)


def test_box_rejects_nonsense():
    with pytest.raises(ValueError):
        Box(float("nan"), 0.0, 10.0)
    with pytest.raises(ValueError):
        Box(0.0, 0.0, 0.0)


def mean_step(boxes):
    return float(np.mean(np.abs(np.diff([b.cx for b in boxes]))))


def test_smoothing_removes_jitter():
    rng = np.random.default_rng(3)
    n = 90
    boxes = [Box(500 + rng.normal(0, 3), 300 + rng.normal(0, 3), 200 * math.exp(rng.normal(0, 0.02)))
             for _ in range(n)]
    out = framing.smooth_boxes(boxes)
    assert len(out) == n
    assert mean_step(out) < mean_step(boxes) / 3
    assert abs(np.mean([b.cx for b in out]) - 500) < 1.5


def test_smoothing_fills_gaps_and_keeps_constants():
    box = Box(100.0, 80.0, 64.0)
    out = framing.smooth_boxes([box] * 20)
    for b in out:
        np.testing.assert_allclose(b.to_tuple(), box.to_tuple(), atol=1e-6)
    gaps = [None, None] + [box] * 5 + [None] * 4 + [box] * 5 + [None]
    out = framing.smooth_boxes(gaps)
    assert all(b is not None for b in out)
    for b in out:
        np.testing.assert_allclose(b.to_tuple(), box.to_tuple(), atol=1e-6)
    assert framing.smooth_boxes([None] * 5) == [None] * 5
    assert framing.smooth_boxes([]) == []


def test_smoothing_interpolates_a_gap_between_positions():
    boxes = [Box(100.0, 50.0, 40.0)] + [None] * 3 + [Box(140.0, 50.0, 40.0)]
    out = framing.smooth_boxes(boxes, window=1)            # window 1: interpolation only
    np.testing.assert_allclose([b.cx for b in out], [100, 110, 120, 130, 140])


def test_smoothing_a_cut_stays_between_the_positions():
    boxes = [Box(100.0, 200.0, 50.0)] * 30 + [Box(400.0, 100.0, 150.0)] * 30
    out = framing.smooth_boxes(boxes)
    cx = np.array([b.cx for b in out])
    cy = np.array([b.cy for b in out])
    size = np.array([b.size for b in out])
    assert cx.min() >= 100 - 1e-6 and cx.max() <= 400 + 1e-6
    assert cy.min() >= 100 - 1e-6 and cy.max() <= 200 + 1e-6
    assert size.min() >= 50 - 1e-6 and size.max() <= 150 + 1e-6
    assert cx[0] == pytest.approx(100) and cx[-1] == pytest.approx(400)


def test_smoothing_keeps_a_steady_pan():
    boxes = [Box(100.0 + 5 * i, 80.0, 60.0) for i in range(30)]
    out = framing.smooth_boxes(boxes)
    # Centred windows do not lag a linear move; near the clip's ends (two half-windows) they are
    # cut short and may.
    np.testing.assert_allclose([b.cx for b in out[8:-8]], [b.cx for b in boxes[8:-8]], atol=1e-6)


@pytest.mark.parametrize("frame,coarse", [((1, 1), (1, 1)), ((7, 5), (3, 2)), ((5, 9), (5, 9))])
def test_tiny_and_odd_sizes(frame, coarse):
    ones = np.ones(coarse, np.float32)
    box = framing.find_portrait(ones, ones, frame)
    assert box is not None and box.size >= framing.MIN_SIDE
    image = np.arange(frame[0] * frame[1] * 2, dtype=np.float32).reshape(*frame, 2)
    for size in (1, 3, 8):
        out = framing.crop(image, box, size)
        assert out.shape == (size, size, 2) and np.isfinite(out).all()
        assert out.min() >= image.min() and out.max() <= image.max()
        weight = framing.crop_weight(box, frame, size)
        assert weight.shape == (size, size) and np.all((weight >= 0) & (weight <= 1))
        back = framing.uncrop(out, box, frame, fill=-1.0)
        assert back.shape == (*frame, 2) and np.isfinite(back).all()
    # A box wholly outside the frame still crops to edge pixels.
    out = framing.crop(image, Box(-50.0, -50.0, 10.0), 4)
    np.testing.assert_array_equal(out, np.broadcast_to(image[0, 0], (4, 4, 2)))


def flood_fill_labels(mask):
    """Reference 8-connected labelling, pixel by pixel."""
    h, w = mask.shape
    labels = np.full((h, w), -1)
    n = 0
    for i, j in zip(*np.nonzero(mask)):
        if labels[i, j] >= 0:
            continue
        labels[i, j] = n
        todo = [(i, j)]
        while todo:
            a, b = todo.pop()
            for y in range(max(a - 1, 0), min(a + 2, h)):
                for x in range(max(b - 1, 0), min(b + 2, w)):
                    if mask[y, x] and labels[y, x] < 0:
                        labels[y, x] = n
                        todo.append((y, x))
        n += 1
    return labels, n


def test_components_match_a_flood_fill():
    for seed in range(60):
        rng = np.random.default_rng(seed)
        mask = rng.random(tuple(rng.integers(1, 14, size=2))) < rng.random()
        labels, areas = framing._components(mask)
        ref, n = flood_fill_labels(mask)
        assert len(areas) == n and areas.sum() == mask.sum()
        # The same partition: each (label, reference label) pair is one-to-one.
        assert len(set(zip(labels[mask].tolist(), ref[mask].tolist()))) == n
        assert np.all(labels[~mask] == -1)


def test_component_at_keeps_the_region_holding_the_weight():
    """The portrait is the matte's region under the face crop, not the biggest one."""
    mask = np.zeros((20, 40), bool)
    mask[2:18, 2:20] = True      # big region (a bright wall)
    mask[5:10, 30:36] = True     # small region holding the weight (the portrait)
    weight = np.zeros((20, 40))
    weight[6:9, 31:35] = 1.0
    keep = framing.component_at(mask, weight)
    assert keep[7, 32] and not keep[10, 10] and keep.sum() == 30
    assert not framing.component_at(np.zeros((4, 4), bool), np.ones((4, 4))).any()
