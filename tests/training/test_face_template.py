"""The face template: built from the light stage's exact buffers (training/intrinsic/template.py),
laid over the face skin and taken as the normals' low band there (addon/facetemplate.py), and
swapped for experiments (training/eval/facetemplate.py)."""

import json

import numpy as np
import pytest

from addon import facetemplate, intrinsic, portrait
from training.eval import facetemplate as experiment
from training.intrinsic import template


def sphere(h=96, w=96, cy=50.0, cx=44.0, r=24.0):
    """(3, h, w) a sphere's normals (camera frame: +Y up, +Z toward the camera) inside a disc,
    toward the camera outside it, and the disc (h, w)."""
    y, x = np.mgrid[0:h, 0:w].astype(np.float32) + 0.5
    dx, dy = (x - cx) / r, -(y - cy) / r
    inside = dx * dx + dy * dy < 1.0
    dz = np.sqrt(np.clip(1.0 - dx * dx - dy * dy, 0.0, None))
    n = np.stack([np.where(inside, dx, 0.0), np.where(inside, dy, 0.0), np.where(inside, dz, 1.0)])
    return n.astype(np.float32), inside


def buffers(normal, face, matte=None):
    h, w = face.shape
    matte = np.ones((h, w), np.float32) if matte is None else matte
    return intrinsic.Buffers(normal, np.zeros((h, w), np.float32),
                             np.full((3, h, w), 0.5, np.float32), matte,
                             face.astype(np.float32))


def sphere_template(size=64, reach=1.3):
    """The template of a sphere face: its normals on the grid of its own disc (skin_frame)."""
    n, disc = sphere(256, 256, 128.0, 128.0, 64.0)
    cy, cx, s = facetemplate.skin_frame(disc.astype(np.float32), np.ones_like(disc, np.float32))
    g = ((np.arange(size) + 0.5) / size * 2.0 - 1.0) * reach * s
    iy = np.clip(np.round(cy + g - 0.5).astype(int), 0, 255)
    ix = np.clip(np.round(cx + g - 0.5).astype(int), 0, 255)
    return facetemplate.Template(n[:, iy][:, :, ix], reach)


def test_the_skin_frame_is_the_skin_s_centre_and_the_root_of_its_area():
    _, disc = sphere()
    cy, cx, s = facetemplate.skin_frame(disc.astype(np.float32), np.ones(disc.shape, np.float32))
    assert (cy, cx) == pytest.approx((50.0, 44.0), abs=0.2)
    assert s == pytest.approx(np.sqrt(np.pi) * 24.0, rel=0.02)
    assert facetemplate.skin_frame(np.zeros((20, 20), np.float32),
                                   np.ones((20, 20), np.float32)) is None


def test_a_template_lands_on_the_face_wherever_and_however_large_it_is():
    """Laid on a sphere's own skin frame, a sphere's template gives that sphere's normals (where
    the grid reaches), for a face off centre and at another size than the template's."""
    t = sphere_template()
    n, disc = sphere(96, 96, 40.0, 58.0, 20.0)
    frame = facetemplate.skin_frame(disc.astype(np.float32), np.ones(disc.shape, np.float32))
    got, inside = facetemplate.laid(t, frame, disc.shape)
    core = disc & inside
    y, x = np.mgrid[0:96, 0:96] + 0.5
    core &= (x - 58.0) ** 2 + (y - 40.0) ** 2 < 16.0 ** 2  # away from the rim's steep normals
    assert core.sum() > 500
    assert np.abs(got[:, core] - n[:, core]).max() < 0.08
    far = ~inside
    assert far.any() and np.all(got[:, far] == 0.0)


@pytest.mark.parametrize("hw, sigma", [((96, 96), 6.0), ((72, 128), 3.375), ((96, 80), 1.0)])
def test_the_template_s_low_band_is_the_blur_of_the_laid_template(hw, sigma):
    """laid_low, whose blur is taken into the template's bilinear weights (or, for a blur of a
    few taps, applied to the laid template), gives the laid template blurred as gaussian_blur
    blurs it, edges and all, and the same reach; here for a face near the crop's edge, so the
    blur's edge samples and the grid's unreached pixels both count."""
    t = sphere_template()
    frame = (hw[0] * 0.3, hw[1] * 0.75, min(hw) * 0.4)
    shape, inside = facetemplate.laid(t, frame, hw)
    got, reach = facetemplate.laid_low(t, frame, hw, sigma)
    assert (~inside).any() and np.array_equal(reach, inside)
    want = intrinsic.gaussian_blur(shape, sigma)
    assert got.shape == want.shape == (3,) + hw
    assert np.abs(got - want).max() < 1e-5
    assert np.abs(got - shape).max() > 0.05  # a blur that did something


def test_held_takes_the_template_s_low_band_and_keeps_the_network_s_detail():
    """On a flat face (every normal toward the camera) with fine sideways ripples, the held
    normals' vertical low band over the skin turns like the sphere's (up at its top) while the
    sideways component stays the network's, ripples and all; with every axis the sideways low
    band turns like the sphere's too. Everything but the normals is left as it was."""
    t = sphere_template()
    _, disc = sphere()
    flat = np.zeros((3, 96, 96), np.float32)
    flat[2] = 1.0
    ripple = 0.05 * np.sin(np.arange(96, dtype=np.float32) * 2.5)[None, :]
    flat[0] += ripple[0]
    b = buffers(intrinsic.unit_normals(flat), disc)

    def low(n):
        return np.stack([intrinsic.gaussian_blur(np.ascontiguousarray(c), 4.0) for c in n])

    got = facetemplate.held(b, t, sigma=4.0)
    every = facetemplate.held(b, t, sigma=4.0, axes=facetemplate.AXES["xyz"])
    for name in ("height", "albedo", "matte", "face"):
        assert getattr(got, name) is getattr(b, name)
    for g in (got, every):
        assert np.all(np.diff(low(g.normal)[1, 36:64, 44]) < 0)  # up at the top
        np.testing.assert_allclose(np.linalg.norm(g.normal, axis=0), 1.0, atol=1e-5)
    assert np.all(np.diff(low(every.normal)[0, 50, 30:60]) > 0)  # turns left to right
    assert np.abs(low(got.normal)[0, 50, 30:60]).max() < 0.02  # the network's: flat
    side = got.normal[0, 50, 36:52]
    assert np.corrcoef(side, ripple[0, 36:52])[0, 1] > 0.9


def test_a_turned_head_takes_less_of_the_frontal_template_and_a_far_turned_one_none():
    """The share of the template falls from 1 at TURN[0] (either way) to 0 at TURN[1]; on a flat
    face turned sideways the held normals' vertical low band moves toward the template's by
    that share: fully when frontal, half way between, not at all when turned far."""
    lo, hi = facetemplate.TURN
    assert facetemplate.turned_share(0.0) == 1.0
    assert facetemplate.turned_share(-lo) == pytest.approx(1.0)
    assert facetemplate.turned_share(0.5 * (lo + hi)) == pytest.approx(0.5)
    assert facetemplate.turned_share(-0.5 * (lo + hi)) == pytest.approx(0.5)
    assert facetemplate.turned_share(hi) == 0.0 and facetemplate.turned_share(-1.0) == 0.0
    t = sphere_template()
    _, disc = sphere()

    def lift(sideways):
        """How far the held face's vertical low band turns up at its top, relative to frontal."""
        flat = np.zeros((3, 96, 96), np.float32)
        flat[0], flat[2] = sideways, np.sqrt(1.0 - sideways ** 2)
        got = facetemplate.held(buffers(flat, disc), t, sigma=4.0)
        return float(got.normal[1, 36, 44] - got.normal[1, 64, 44])

    frontal = lift(0.0)
    assert frontal > 0.2
    assert lift(0.5 * (lo + hi)) == pytest.approx(0.5 * frontal, rel=0.15)
    far = buffers(np.zeros((3, 96, 96), np.float32), disc)
    far.normal[0], far.normal[2] = hi + 0.05, np.sqrt(1.0 - (hi + 0.05) ** 2)
    assert facetemplate.held(far, t, sigma=4.0) is far


def test_held_leaves_a_crop_without_face_skin_as_it_was():
    t = sphere_template()
    n, _ = sphere()
    b = buffers(n, np.zeros((96, 96), bool))
    assert facetemplate.held(b, t) is b


def test_load_says_how_to_build_a_missing_template_and_refuses_another_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="python -m training.intrinsic.template"):
        facetemplate.load(tmp_path / "none.npz")
    bad = tmp_path / "bad.npz"
    np.savez(bad, something=np.zeros(3))
    with pytest.raises(ValueError, match="not a face template"):
        facetemplate.load(bad)
    wrong = tmp_path / "wrong.npz"
    np.savez(wrong, normal=np.zeros((3, 8, 4)), reach=1.0)
    with pytest.raises(ValueError, match=r"\(3, T, T\)"):
        facetemplate.load(wrong)
    good = tmp_path / "good.npz"
    np.savez(good, normal=np.zeros((3, 8, 8), np.float16), reach=np.float32(1.3))
    t = facetemplate.load(good)
    assert t.normal.dtype == np.float32 and t.reach == pytest.approx(1.3)


def turned(n, by):
    """The normals turned about the vertical axis by ``by`` radians (a head turned sideways)."""
    c, s = np.cos(by), np.sin(by)
    return np.stack([c * n[0] + s * n[2], n[1], -s * n[0] + c * n[2]]).astype(np.float32)


def test_the_template_is_the_mean_face_on_its_own_skin_s_grid_left_right_symmetric():
    """Spheres of different sizes and places give one template: a sphere's normals on the grid
    of its disc, x antisymmetric (each frame counts with its mirror image), toward the camera at
    the centre and up at the top; a turned head is left out."""
    frames = []
    for cy, cx, r in ((48.0, 40.0, 20.0), (60.0, 70.0, 28.0)):
        n, disc = sphere(128, 128, cy, cx, r)
        frames.append((n, disc.astype(np.float32), np.ones(disc.shape, np.float32)))
    n, disc = sphere(128, 128, 64.0, 64.0, 24.0)
    frames.append((turned(n, 0.6), disc.astype(np.float32), np.ones(disc.shape, np.float32)))
    got, used = template.template_from(frames, size=32, reach=1.3)
    assert used == 2
    assert got.shape == (3, 32, 32)
    np.testing.assert_allclose(got[0], -got[0][:, ::-1], atol=1e-5)
    assert got[2, 16, 16] > 0.95
    assert got[1, 12, 16] > 0.3 and got[1, 20, 16] < -0.3  # the top faces up, the bottom down
    alone, _ = template.template_from(frames[:1], size=32, reach=1.3)
    inner = (slice(None), slice(11, 21), slice(11, 21))  # within the rim's steep normals
    np.testing.assert_allclose(got[inner], alone[inner], atol=0.02)  # size and place aside


def test_no_frontal_face_is_a_clear_error():
    n, disc = sphere(64, 64, 32.0, 32.0, 12.0)
    frames = [(turned(n, 0.8), disc.astype(np.float32), np.ones(disc.shape, np.float32))]
    with pytest.raises(ValueError, match="training.intrinsic.data --split val"):
        template.template_from(frames)


def test_main_writes_a_template_the_product_loads_with_its_card(tmp_path, monkeypatch, capsys):
    """main: the .npz training/eval/facetemplate.py loads and a card beside it with the command, the
    frames and the heads' licence notice; no cache is exit 2 with what to build."""
    n, disc = sphere(128, 128, 60.0, 64.0, 22.0)
    frames = [(n, disc.astype(np.float32), np.ones(disc.shape, np.float32))]
    monkeypatch.setattr(template, "cache_frames", lambda folders: iter(frames))
    cache = tmp_path / "val_128"
    cache.mkdir()
    out = tmp_path / "face.npz"
    assert template.main(["--cache", str(cache), "--out", str(out)]) == 0
    t = facetemplate.load(out)
    assert t.normal.shape == (3, template.SIZE, template.SIZE)
    assert t.reach == pytest.approx(template.REACH)
    card = json.loads(out.with_suffix(".json").read_text())
    assert card["frames"] == 1 and "--out" in card["command"]
    assert "ICT-FaceKit" in card["licence"] and "MIT" in card["licence"]
    assert template.main(["--cache", str(tmp_path / "none"), "--out", str(out)]) == 2
    assert "training.intrinsic.data --split val" in capsys.readouterr().err


def test_the_product_holds_every_pass_to_its_shipped_template(monkeypatch, tmp_path):
    """portrait.FACE_TEMPLATE: the shipped template (models/face-template/, which loads) by
    default; a relighting pass's buffers are facetemplate.held's, the vertical component's,
    the low band's width scaled with the crop's size (SIGMA at the working size), the framing
    passes' and the coarse pass's not, and a relit frame's face crop takes it once.
    experiment.applied swaps in another template, or none (the network's normals as they are),
    and then steps aside; a missing file is refused before anything runs."""
    from addon import engine, framing
    from tests.core.test_portrait import RIGHT_LAMP, chw, frame, write_standin

    assert portrait.FACE_TEMPLATE == facetemplate.SHIPPED and portrait.FACE_TEMPLATE_AXES == "y"
    shipped = facetemplate.load(facetemplate.SHIPPED)
    assert shipped.normal.shape == (3, template.SIZE, template.SIZE)
    sess = engine.new_session(write_standin(tmp_path, "template"),
                              providers=["CPUExecutionProvider"], threads=1, spin=False)
    x = chw(frame(96, 160, (110.0, 48.0), 20.0))
    box = framing.Box(110.0, 48.0, 64.0)
    size = sess.card.working_size
    calls, held = [], facetemplate.held

    def spied(bufs, t, sigma=facetemplate.SIGMA, axes=facetemplate.AXES["y"]):
        calls.append((t.normal.shape, sigma, axes))
        return held(bufs, t, sigma, axes)

    monkeypatch.setattr(facetemplate, "held", spied)
    for n in (size, 2 * size):
        portrait.buffers(sess, *portrait.crop_planar(x, box, n))
    assert calls == [(shipped.normal.shape, pytest.approx(facetemplate.SIGMA), (1,)),
                     (shipped.normal.shape, pytest.approx(2 * facetemplate.SIGMA), (1,))]
    calls.clear()
    portrait.find_box(sess, x)  # framing reads the face and the matte only: no shape to hold
    portrait.find_box(sess, x, prior=box)
    assert calls == []
    # A relit frame holds it once, on the face crop's buffers (the mean of its passes); the
    # coarse pass over the whole frame (this box does not hold it) takes none.
    portrait.relight_frame(sess, x, RIGHT_LAMP, box)
    assert calls == [(shipped.normal.shape, pytest.approx(facetemplate.SIGMA), (1,))]
    other = tmp_path / "t.npz"
    np.savez(other, normal=np.tile(np.array([0.0, 0.6, 0.8], np.float32)[:, None, None],
                                   (1, 16, 16)), reach=np.float32(1.3))
    calls.clear()
    with experiment.applied(other, "xyz"):
        portrait.buffers(sess, *portrait.crop_planar(x, box, size))
    with experiment.applied(None):
        plain = portrait.buffers(sess, *portrait.crop_planar(x, box, size))
    assert calls == [((3, 16, 16), pytest.approx(facetemplate.SIGMA), (0, 1, 2))]
    assert portrait.FACE_TEMPLATE == facetemplate.SHIPPED and portrait.FACE_TEMPLATE_AXES == "y"
    crop, level = portrait.crop_planar(x, box, size)[0], intrinsic.INPUT_LEVEL
    fed = portrait.lifted(crop * np.float32(intrinsic.exposure_scale(crop, level)), level)
    np.testing.assert_array_equal(plain.normal, sess.run_planar(fed).normal)  # the network's
    with pytest.raises(FileNotFoundError, match="python -m training.intrinsic.template"):
        with experiment.applied(tmp_path / "none.npz"):
            pass
    assert portrait.FACE_TEMPLATE == facetemplate.SHIPPED


@pytest.mark.parametrize("module", ["evaluate", "yale_normals"])
def test_an_experiment_runs_under_another_template_or_none(module, tmp_path, monkeypatch, capsys):
    """training.eval.evaluate and yale_normals --face-template: the run goes with the product's
    passes taking that template (or none, with 'none') and with the product's after it; a
    missing template is refused with what to build."""
    import importlib

    mod = importlib.import_module(f"training.eval.{module}")
    seen = []
    monkeypatch.setattr(mod, "_main", lambda p, a: seen.append(portrait.FACE_TEMPLATE))
    path = tmp_path / "t.npz"
    np.savez(path, normal=np.zeros((3, 8, 8), np.float32), reach=np.float32(1.3))
    mod.main(["--onnx", "m.onnx", "--face-template", str(path)])
    mod.main(["--onnx", "m.onnx", "--face-template", "none"])
    mod.main(["--onnx", "m.onnx"])
    assert seen == [str(path), None, facetemplate.SHIPPED]
    assert portrait.FACE_TEMPLATE == facetemplate.SHIPPED
    with pytest.raises(SystemExit):
        mod.main(["--onnx", "m.onnx", "--face-template", str(tmp_path / "none.npz")])
    assert "python -m training.intrinsic.template" in capsys.readouterr().err


def test_evaluate_keeps_another_template_off_the_card(tmp_path, capsys):
    """evaluate --face-template never with --update-card: the card's figures are the product's."""
    from training.eval import evaluate

    path = tmp_path / "t.npz"
    np.savez(path, normal=np.zeros((3, 8, 8), np.float32), reach=np.float32(1.3))
    with pytest.raises(SystemExit):
        evaluate.main(["--onnx", "m.onnx", "--face-template", str(path), "--update-card"])
    assert "not the product's" in capsys.readouterr().err


def test_the_pose_bench_reads_each_variant_as_named_and_restores_the_product_s(monkeypatch):
    """bench.face_template_pose.read: 'no template' reads without the template, 'template on
    every head' with it at any turn, 'the product' with the product's fade; the product's
    TURN is back after each, even when a read fails."""
    from bench import face_template_pose as bench

    seen = []

    def buffers(session, img, shape=True):
        seen.append((shape, facetemplate.turned_share(0.5)))
        if session == "fail":
            raise RuntimeError("failed")
        return "bufs"

    monkeypatch.setattr(portrait, "buffers", buffers)
    product = facetemplate.TURN
    for v in bench.VARIANTS:
        assert bench.read(None, None, v) == "bufs"
        assert facetemplate.TURN == product
    assert seen == [(False, 0.0), (True, 1.0), (True, 0.0)]
    with pytest.raises(RuntimeError):
        bench.read("fail", None, "template on every head")
    assert facetemplate.TURN == product
