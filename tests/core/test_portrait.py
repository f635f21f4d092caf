"""Intrinsic models end to end with a stand-in network: the engine session, framing
(portrait.find_box), one frame (portrait.relight_frame, addon.api.relight_image) and whole clips
(pipeline.relight_clip: boxes file, resume, frames without a portrait).

The stand-in (built here with onnx.helper, opset 17) sees a "portrait" wherever the image is
skin-coloured: parsing (foreground, skin) = sigmoid(K (r - b - T)), so a grey background is never
the subject at any exposure; normals bulge like a sphere filling the crop (the crop is centred
on the face, so a side lamp lights that side of the face); height 0; albedo 0.5.
"""

import dataclasses
import hashlib
import json
import multiprocessing
import os
import pathlib

import numpy as np
import onnx
import pytest
from onnx import TensorProto, helper, numpy_helper

from addon import (api, contract, detail, engine, framing, frames, intrinsic, lightvec, outline,
                   pipeline, portrait)
from addon.errors import InputError, ModelError
from tests.clip_fixtures import write_exr_sequence
from tests.core.test_intrinsic_render import normals_of

OPSET = 17
K, T = 400.0, 0.04          # parsing = sigmoid(K (r - b - T))
BULGE = 0.7                 # normals: (BULGE u, -BULGE v, sqrt(1 - ...)) over the padded input
SKIN = np.array([0.8, 0.55, 0.45], np.float32)
GREY = 0.2
HALF = 2.0 ** -11           # relative rounding of a half float
RIGHT_LAMP = lightvec.splat_direction([1.0, 0.0, 0.35], 10.0) + lightvec.uniform(0.05)


# ---- the stand-in model --------------------------------------------------------------------

def _c(name, value):
    return numpy_helper.from_array(np.asarray(value, np.float32), name)


def build_standin(normal_name: str = contract.OUTPUT_NORMAL,
                  transfer: int = 0, hair: bool = False) -> onnx.ModelProto:
    """The stand-in intrinsic network; ``normal_name`` renames its normal output (to break the
    contract); ``transfer``: that many channels of a ``transfer`` output, each the unoccluded
    transfer of a camera-facing normal (a sixteenth of the light let through); ``hair``: a third
    parsing class, hair, everywhere but the skin-coloured disc."""
    n = helper.make_node
    nodes = [
        n("Slice", [contract.INPUT_IMAGE, "i0", "i1", "ax1"], ["r"]),
        n("Slice", [contract.INPUT_IMAGE, "i2", "i3", "ax1"], ["b"]),
        n("Sub", ["r", "b"], ["chroma"]),
        n("Sub", ["chroma", "t"], ["chroma_t"]),
        n("Mul", ["chroma_t", "k"], ["logit"]),
        n("Sigmoid", ["logit"], ["p"]),
        n("Sub", ["one", "p"], ["not_p"]),
        n("Concat", ["p", "p"] + (["not_p"] if hair else []), [contract.OUTPUT_PARSING], axis=1),
        # A plane of zeros and ones of the input's size ([N, 1, H, W]).
        n("Mul", ["r", "zero"], [contract.OUTPUT_HEIGHT]),
        n("Add", [contract.OUTPUT_HEIGHT, "one"], ["ones"]),
        n("Mul", [contract.INPUT_IMAGE, "zero"], ["zeros3"]),
        n("Add", ["zeros3", "half"], [contract.OUTPUT_ALBEDO]),
    ]
    for axis, name in ((3, "u"), (2, "v")):  # pixel centres in (-1, 1) across the input
        nodes += [n("CumSum", ["ones", f"axis{axis}"], [f"{name}_count"]),
                  n("ReduceSum", ["ones", f"axes{axis}"], [f"{name}_len"], keepdims=1),
                  n("Sub", [f"{name}_count", "half"], [f"{name}_centre"]),
                  n("Div", [f"{name}_centre", f"{name}_len"], [f"{name}_unit"]),
                  n("Mul", [f"{name}_unit", "two_bulge"], [f"{name}_scaled"]),
                  n("Sub", [f"{name}_scaled", "bulge"], [f"{name}_n"])]
    nodes += [
        n("Neg", ["v_n"], ["ny"]),
        n("Mul", ["u_n", "u_n"], ["uu"]),
        n("Mul", ["v_n", "v_n"], ["vv"]),
        n("Add", ["uu", "vv"], ["rr"]),
        n("Sub", ["one", "rr"], ["zz"]),
        n("Sqrt", ["zz"], ["nz"]),
        n("Concat", ["u_n", "ny", "nz"], [normal_name], axis=1),
    ]
    inits = [numpy_helper.from_array(np.array([v], np.int64), name) for name, v in
             (("i0", 0), ("i1", 1), ("i2", 2), ("i3", 3), ("ax1", 1))]
    inits += [numpy_helper.from_array(np.array(a, np.int64), name) for name, a in
              (("axis3", 3), ("axis2", 2), ("axes3", [3]), ("axes2", [2]))]
    inits += [_c("t", T), _c("k", K), _c("zero", 0.0), _c("one", 1.0), _c("half", 0.5),
              _c("bulge", BULGE), _c("two_bulge", 2 * BULGE)]
    f = TensorProto.FLOAT
    outs = [(normal_name, 3), (contract.OUTPUT_HEIGHT, 1), (contract.OUTPUT_ALBEDO, 3),
            (contract.OUTPUT_PARSING, 3 if hair else 2)]
    if transfer:
        nodes += [n("Concat", [contract.OUTPUT_HEIGHT] * transfer, ["zeros_t"], axis=1),
                  n("Add", ["zeros_t", "facing"], [contract.OUTPUT_TRANSFER])]
        facing = intrinsic.TRANSFER_BAND * intrinsic.sh_basis(np.array([0.0, 0.0, 1.0]), 3)
        inits.append(_c("facing", np.resize(facing, transfer).reshape(1, transfer, 1, 1)))
        outs.append((contract.OUTPUT_TRANSFER, transfer))
    outputs = [helper.make_tensor_value_info(name, f, ["N", c, "H", "W"]) for name, c in outs]
    graph = helper.make_graph(
        nodes, "intrinsic_standin",
        [helper.make_tensor_value_info(contract.INPUT_IMAGE, f, ["N", 3, "H", "W"])], outputs, inits)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", OPSET)],
                              producer_name="tests/core/test_portrait.py")
    model.ir_version = 8
    onnx.checker.check_model(model)
    return model


def write_standin(folder, name="standin", normal_name=contract.OUTPUT_NORMAL,
                  transfer: int = 0, hair: bool = False) -> str:
    """The stand-in and its card (contract relight-intrinsic/1, stride 16, working size 32)."""
    folder = pathlib.Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / f"{name}.onnx"
    path.write_bytes(build_standin(normal_name, transfer, hair).SerializeToString())
    classes = list(contract.INTRINSIC_CLASSES) + (["hair"] if hair else [])
    shapes = {contract.OUTPUT_NORMAL: 3, contract.OUTPUT_HEIGHT: 1, contract.OUTPUT_ALBEDO: 3,
              contract.OUTPUT_PARSING: len(classes)}  # what the card promises
    if transfer:
        shapes[contract.OUTPUT_TRANSFER] = contract.TRANSFER_CHANNELS
    card = {
        "contract": contract.INTRINSIC_CONTRACT, "name": name, "preset": "standin",
        "onnx": path.name, "sha256": engine.file_sha256(path),
        "inputs": [{"name": contract.INPUT_IMAGE, "shape": ["N", 3, "H", "W"], "dtype": "float32"}],
        "outputs": [{"name": k, "shape": ["N", c, "H", "W"]} for k, c in shapes.items()],
        "stride": 16, "working_size": 32,
        "colour": {"space": "linear Rec.709 scene-referred, channels first"},
        "classes": classes,
        "training": {"data": "none: a stand-in built by tests/core/test_portrait.py"},
        "metrics": {}, "cost": {"cpu": {"provider": "CPUExecutionProvider", "per_size": {}}},
    }
    path.with_suffix(".json").write_text(json.dumps(card, indent=1), encoding="utf-8")
    return str(path)


@pytest.fixture(scope="module")
def model(tmp_path_factory):
    return write_standin(tmp_path_factory.mktemp("standin"))


@pytest.fixture(scope="module")
def session(model):
    return engine.new_session(model, providers=["CPUExecutionProvider"], threads=1, spin=False)


@pytest.fixture(scope="module")
def shipped():
    """The shipped Portrait network (a learned one: its passes differ) and the demo's first
    frame, (3, H, W) linear."""
    root = pathlib.Path(__file__).resolve().parents[2]
    sess = engine.new_session(root / "models" / "relight-portrait.onnx",
                              providers=["CPUExecutionProvider"], threads=1, spin=False)
    from training.lightstage.png import read_png
    src = read_png(root / "demo" / "frames" / "frame_0001.png").astype(np.float32) / 255.0
    return sess, np.ascontiguousarray(src.transpose(2, 0, 1) ** 2.2)


# ---- frames --------------------------------------------------------------------------------

def frame(h, w, centre=None, radius=0.0, seed=0):
    """(H, W, 3) linear: a grey textured background and, if ``centre`` (x, y), a disc of skin
    with a little texture."""
    rng = np.random.default_rng(seed)
    img = np.empty((h, w, 3), np.float32)
    img[...] = GREY * (1.0 + 0.2 * rng.random((h, w, 1)))
    if centre is not None:
        yy, xx = np.mgrid[0:h, 0:w] + 0.5
        disc = np.hypot(xx - centre[0], yy - centre[1]) < radius
        img[disc] = SKIN * (1.0 + 0.1 * rng.random((int(disc.sum()), 1)))
    return img


def away_from(shape_hw, centre, distance):
    """Pixels whose centre is farther than ``distance`` from ``centre`` (x, y)."""
    yy, xx = np.mgrid[0:shape_hw[0], 0:shape_hw[1]] + 0.5
    return np.hypot(xx - centre[0], yy - centre[1]) > distance


def within(shape_hw, centre, distance):
    return ~away_from(shape_hw, centre, distance)


def chw(hwc):
    return np.ascontiguousarray(hwc.transpose(2, 0, 1))


def apply(x, res):
    """(3, H, W) float32 of a FrameResult applied to ``x`` at full resolution, as the pipeline
    and relight_image do (half-float output)."""
    y = detail.FullRes(threads=1).finish_planar(x, res.a, res.b, float(x.max(initial=0.0)))[0]
    return outline.apply(res.outline, x, y).astype(np.float32)


def margin(h, w, size=32):
    """How far the change may spread past the disc: the coarse pass's pixels (it runs at
    portrait.COARSE times the working size), enlarged bilinearly, reach 2.5 of them."""
    return 2.5 * max(h, w) / portrait.coarse_size(size)


# ---- the session -----------------------------------------------------------------------------

def test_intrinsic_card_gives_an_intrinsic_session_with_the_buffers(session):
    """new_session returns an IntrinsicSession whose buffers have the contract's shapes, at odd
    sizes too (padding to the stride is cropped away)."""
    assert isinstance(session, engine.IntrinsicSession)
    assert session.card.contract == contract.INTRINSIC_CONTRACT
    res = session.run_planar(chw(frame(21, 35, (17.0, 10.0), 8.0)))
    assert res.normal.shape == (3, 21, 35) and res.height.shape == (21, 35)
    assert res.albedo.shape == (3, 21, 35) and res.parsing.shape == (2, 21, 35)
    np.testing.assert_allclose(np.linalg.norm(res.normal, axis=0), 1.0, atol=1e-5)
    assert res.parsing[0, 10, 17] > 0.99 and res.parsing[0, 1, 1] < 1e-6


def test_a_model_with_the_transfer_gives_it_and_relights_with_it(tmp_path, monkeypatch):
    """The optional transfer output: the card lists it after the four buffers, the session
    returns it with the others, and the frame path renders with it (here every pixel lets only a
    camera-facing normal's light through, so a lamp from the side lights the disc less than
    the stand-in's bulging normals alone would: those normals as they are, without the face
    template's shape). Sixteen channels or it is refused."""
    monkeypatch.setattr(portrait, "FACE_TEMPLATE", None)
    path = write_standin(tmp_path, "with_transfer", transfer=contract.TRANSFER_CHANNELS)
    sess = engine.new_session(path, providers=["CPUExecutionProvider"], threads=1, spin=False)
    res = sess.run_planar(chw(frame(21, 35, (17.0, 10.0), 8.0)))
    assert res.transfer.shape == (contract.TRANSFER_CHANNELS, 21, 35)
    x = chw(frame(96, 96, (48.0, 48.0), 30.0))
    plain = engine.new_session(write_standin(tmp_path, "plain"), providers=["CPUExecutionProvider"],
                               threads=1, spin=False)
    assert plain.run_planar(x[:, :32, :32]).transfer is None
    box = portrait.find_box(sess, x)
    out = {}
    for name, s in (("with", sess), ("plain", plain)):
        r = portrait.relight_frame(s, x, RIGHT_LAMP, box, exposure=1.0)
        y = apply(x, r)
        assert np.isfinite(y).all()
        out[name] = float(y[:, within((96, 96), (48.0, 48.0), 20.0)].mean())
    assert out["with"] < 0.95 * out["plain"], out
    bad = write_standin(tmp_path, "bad_transfer", transfer=9)
    card = json.loads(pathlib.Path(bad).with_suffix(".json").read_text())
    with pytest.raises(ModelError, match="shape"):
        engine.new_session(bad, providers=["CPUExecutionProvider"], threads=1).run_planar(
            x[:, :32, :32])
    card["outputs"].insert(0, card["outputs"].pop())  # the transfer listed first
    pathlib.Path(bad).with_suffix(".json").write_text(json.dumps(card))
    with pytest.raises(ModelError, match="outputs"):
        engine.new_session(bad, providers=["CPUExecutionProvider"], threads=1)


def test_a_model_with_the_hair_class_gives_the_renderer_its_hair(tmp_path, session):
    """A card that lists a third class, hair: the buffers carry that channel as ``hair`` (zeroed
    beyond the frame's edge, as the matte), the frame path relights with it; a model without
    the class gives none."""
    path = write_standin(tmp_path, "with_hair", hair=True)
    sess = engine.new_session(path, providers=["CPUExecutionProvider"], threads=1, spin=False)
    x = chw(frame(32, 32, (16.0, 16.0), 10.0))
    bufs = portrait.buffers(sess, x)
    np.testing.assert_allclose(bufs.hair, 1.0 - bufs.matte, atol=1e-6)
    valid = np.ones((32, 32), np.float32)
    valid[:, :8] = 0.0
    assert portrait.buffers(sess, x, valid).hair[:, :8].max() == 0.0
    assert portrait.buffers(session, x).hair is None
    big = chw(frame(96, 96, (48.0, 48.0), 30.0))
    r = portrait.relight_frame(sess, big, RIGHT_LAMP, portrait.find_box(sess, big), exposure=1.0)
    assert np.isfinite(apply(big, r)).all()


def test_the_mirrored_pass_is_the_mean_of_the_image_s_and_its_mirror_s_buffers(tmp_path,
                                                                              shipped):
    """run_planar(mirror=True): each buffer is the mean of the image's and the mirror image's
    mirrored back, the normal's x and the transfer's x-odd coefficients negated; so mirroring
    the image mirrors the result exactly. The face crop's passes use it; the framing passes
    and the coarse pass over the whole frame do not. The finer sampling's pass alone is fed
    brighter (FINER_LEVEL)."""
    sess, full = shipped  # a learned network: its two passes differ
    x = np.ascontiguousarray(full[:, :128, :128])
    flip = np.ascontiguousarray(x[:, :, ::-1])
    a, b, m = sess.run_planar(x), sess.run_planar(flip), sess.run_planar(x, mirror=True)
    odd = list(contract.TRANSFER_X_ODD)
    nb, tb = b.normal[:, :, ::-1].copy(), b.transfer[:, :, ::-1].copy()
    nb[0] *= -1
    tb[odd] *= -1
    n = a.normal + nb
    n /= np.linalg.norm(n, axis=0, keepdims=True)
    assert np.abs(a.parsing - b.parsing[:, :, ::-1]).max() > 0.5  # the passes differ
    np.testing.assert_allclose(m.normal, n, atol=1e-5)
    np.testing.assert_allclose(m.height, 0.5 * (a.height + b.height[:, ::-1]), atol=1e-5)
    np.testing.assert_allclose(m.albedo, 0.5 * (a.albedo + b.albedo[:, :, ::-1]), atol=1e-6)
    np.testing.assert_allclose(m.parsing, 0.5 * (a.parsing + b.parsing[:, :, ::-1]), atol=1e-6)
    np.testing.assert_allclose(m.transfer, 0.5 * (a.transfer + tb), atol=1e-5)
    mm = sess.run_planar(flip, mirror=True)
    back = mm.normal[:, :, ::-1].copy()
    back[0] *= -1
    np.testing.assert_allclose(back, m.normal, atol=1e-5)
    # which passes mirror: every relighting pass, no framing pass
    sess = engine.new_session(write_standin(tmp_path, "mirror"),
                              providers=["CPUExecutionProvider"], threads=1, spin=False)
    seen = []

    class Spy:
        card = sess.card

        def run_planar(self, image, mirror=False):
            level = float(np.quantile(intrinsic.luminance(image), intrinsic.INPUT_QUANTILE))
            seen.append((mirror, image.shape[1], level))
            return sess.run_planar(image, mirror=mirror)

    wide = chw(frame(96, 160, (110.0, 48.0), 20.0))
    box = portrait.find_box(Spy(), wide)
    assert seen and not any(m for m, *_ in seen)
    seen.clear()
    portrait.relight_frame(Spy(), wide, RIGHT_LAMP, box)
    # the coarse pass, the face crop, its finer sampling (in a second thread: in any order)
    size, finer = sess.card.working_size, round(sess.card.working_size * portrait.ZOOM)
    assert len(seen) == 3
    coarse = [p for p in seen if p[1] not in (size, finer)]
    by_size = {n: (m, level) for m, n, level in seen}
    assert len(coarse) == 1 and coarse[0][0] is False
    assert by_size[size][0] is portrait.MIRROR and by_size[finer][0] is portrait.MIRROR
    # each pass normalised to its level: the finer sampling brighter (FINER_LEVEL); the lift
    # keeps the level (up to the quantile's interpolation between two pixels, which a curve
    # moves a little)
    assert portrait.FINER_LEVEL > intrinsic.INPUT_LEVEL
    np.testing.assert_allclose([coarse[0][2], by_size[size][1], by_size[finer][1]],
                               [intrinsic.INPUT_LEVEL] * 2 + [portrait.FINER_LEVEL], rtol=1e-3)


def test_the_finer_pass_in_a_second_thread_gives_the_frame_the_passes_in_turn_give(tmp_path,
                                                                                    monkeypatch):
    """relight_frame with the finer sampling's pass in the second thread
    (PARALLEL_PASSES) gives the same frame, to the bit, as with its passes one after
    another."""
    sess = engine.new_session(write_standin(tmp_path), providers=["CPUExecutionProvider"],
                              threads=1, spin=False)
    wide = chw(frame(96, 160, (110.0, 48.0), 20.0))
    box = portrait.find_box(sess, wide)
    assert box is not None
    got = {}
    for parallel in (True, False):
        monkeypatch.setattr(portrait, "PARALLEL_PASSES", parallel)
        got[parallel] = portrait.relight_frame(sess, wide, RIGHT_LAMP, box)
    for field in ("a", "b", "matte"):
        np.testing.assert_array_equal(getattr(got[True], field), getattr(got[False], field))


def test_a_pass_failing_in_the_second_thread_fails_the_frame_and_the_next_frame_runs(tmp_path):
    """The finer sampling's pass raising in the second thread: relight_frame raises that
    error (no pass left running), and the next frame relights as before."""
    sess = engine.new_session(write_standin(tmp_path), providers=["CPUExecutionProvider"],
                              threads=1, spin=False)
    finer = round(sess.card.working_size * portrait.ZOOM)
    broken = {"on": True}

    class Failing:
        card = sess.card

        def run_planar(self, image, mirror=False):
            if broken["on"] and image.shape[1] == finer:
                raise ModelError("the finer pass failed")
            return sess.run_planar(image, mirror=mirror)

    wide = chw(frame(96, 160, (110.0, 48.0), 20.0))
    box = portrait.find_box(sess, wide)
    with pytest.raises(ModelError, match="finer pass failed"):
        portrait.relight_frame(Failing(), wide, RIGHT_LAMP, box)
    broken["on"] = False
    again = portrait.relight_frame(Failing(), wide, RIGHT_LAMP, box)
    np.testing.assert_array_equal(again.a, portrait.relight_frame(sess, wide, RIGHT_LAMP, box).a)


def _relight_in_child(sess, frame_chw, box, out):
    out.put(float(portrait.relight_frame(sess, frame_chw, RIGHT_LAMP, box).a.sum()))


@pytest.mark.skipif("fork" not in multiprocessing.get_all_start_methods(),
                    reason="no fork on this platform")
def test_a_process_forked_after_a_relit_frame_relights_with_its_own_second_thread(tmp_path):
    """relight_frame in a process forked from one that had already relit a frame (its second
    thread does not exist in the child): the frame comes out, the same as the parent's, rather
    than waiting for ever on a pass handed to a thread that is not there."""
    sess = engine.new_session(write_standin(tmp_path), providers=["CPUExecutionProvider"],
                              threads=1, spin=False)
    wide = chw(frame(96, 160, (110.0, 48.0), 20.0))
    box = portrait.find_box(sess, wide)
    parent = float(portrait.relight_frame(sess, wide, RIGHT_LAMP, box).a.sum())
    ctx = multiprocessing.get_context("fork")
    out = ctx.Queue()
    child = ctx.Process(target=_relight_in_child, args=(sess, wide, box, out))
    child.start()
    child.join(60)
    if child.is_alive():
        child.kill()
        pytest.fail("the forked process never finished its frame")
    assert child.exitcode == 0
    assert out.get(timeout=5) == parent


def test_the_lift_raises_shadows_keeps_the_level_and_every_pixel_s_colour():
    """portrait.lifted: each pixel's luminance over the level to the power INPUT_LIFT, its
    colour kept; the level and black stay where they are, and the order of the tones too."""
    rng = np.random.default_rng(5)
    x = rng.random((3, 16, 20), dtype=np.float32) * np.float32(1.5)
    x[:, 0, 0] = 0.0
    level = 0.6
    y = portrait.lifted(x, level)
    assert y.dtype == np.float32 and y.shape == x.shape
    lx, ly = intrinsic.luminance(x), intrinsic.luminance(y)
    ok = lx > 1e-3
    np.testing.assert_allclose(ly[ok], level * (lx[ok] / level) ** portrait.INPUT_LIFT, rtol=1e-4)
    np.testing.assert_allclose((y / ly)[:, ok], (x / lx)[:, ok], rtol=1e-4)  # chromaticity
    assert (y[:, 0, 0] == 0).all()
    order = np.argsort(lx.ravel())
    assert (np.diff(ly.ravel()[order]) >= -1e-6).all()
    grey = np.full((3, 2, 2), level, np.float32)
    np.testing.assert_allclose(portrait.lifted(grey, level), grey, rtol=1e-6)
    assert portrait.INPUT_LIFT < 1.0  # shadows come up
    dark = np.full((3, 1, 1), 0.1 * level, np.float32)
    assert float(portrait.lifted(dark, level)[0, 0, 0]) > 1.5 * 0.1 * level
    assert portrait.lifted(x, level, power=1.0) is x


def test_every_pass_feeds_the_network_its_lifted_crop(tmp_path):
    """portrait.buffers: the network's input is the crop normalised to the pass's level, then
    lifted (INPUT_LIFT), for the framing, coarse, face and finer passes alike."""
    sess = engine.new_session(write_standin(tmp_path, "lift"),
                              providers=["CPUExecutionProvider"], threads=1, spin=False)
    fed = []

    class Spy:
        card = sess.card

        def run_planar(self, image, mirror=False):
            fed.append(image.copy())
            return sess.run_planar(image, mirror=mirror)

    wide = chw(frame(96, 160, (110.0, 48.0), 20.0))
    crop, valid = portrait.crop_planar(wide, framing.Box(110.0, 48.0, 64.0), 32)
    for level in (None, portrait.FINER_LEVEL):
        fed.clear()
        portrait.buffers(Spy(), crop, valid, level=level)
        lv = intrinsic.INPUT_LEVEL if level is None else level
        want = portrait.lifted(crop * np.float32(intrinsic.exposure_scale(crop, lv)), lv)
        np.testing.assert_allclose(fed[0], want, rtol=1e-6, atol=1e-7)
        assert np.abs(fed[0] - crop * np.float32(intrinsic.exposure_scale(crop, lv))).max() > 1e-3


def test_the_face_crop_keeps_its_own_albedo_and_averages_the_rest_with_the_finer_pass(shipped):
    """portrait.face_buffers: the finer sampling, fed brighter, clips the highlights its albedo
    would read, so the albedo is the crop's own pass's; the other buffers are the mean of the
    two passes (mean_buffers of the crop's and the finer pass shrunk to the crop), the face
    template held once, on the mean (portrait.templated)."""
    sess, x = shipped
    box = portrait.find_box(sess, x)
    size = sess.card.working_size
    crop, valid, got = portrait.face_buffers(sess, x, box, size)
    own = portrait.buffers(sess, crop, valid, mirror=portrait.MIRROR, shape=False)
    finer = portrait.buffers(sess, *portrait.crop_planar(x, box, round(size * portrait.ZOOM)),
                             mirror=portrait.MIRROR, level=portrait.FINER_LEVEL, shape=False)
    mean = portrait.mean_buffers(own, portrait.shrunk(finer, size))
    held = portrait.templated(mean, size)
    np.testing.assert_array_equal(got.albedo, own.albedo)
    assert np.abs(mean.albedo - own.albedo).max() > 1e-3  # the mean's albedo would differ
    for name in ("normal", "height", "matte", "face", "transfer"):
        np.testing.assert_allclose(getattr(got, name), getattr(held, name), atol=1e-6)
    assert np.degrees(np.arccos(np.clip((got.normal * own.normal).sum(0), -1, 1))).max() > 1.0
    # The template moved the mean's normals (this frame's face is one it holds).
    assert np.degrees(np.arccos(np.clip((held.normal * mean.normal).sum(0), -1, 1))).max() > 1.0


def test_the_face_skin_s_normal_detail_is_raised_and_the_rest_kept(monkeypatch):
    """portrait.deepened: over the face skin the normals' detail finer than the Gaussian (a bump,
    a nose drawn too flat) is raised the given times, so the normals there turn further from the
    camera; far from the skin and on a flat face nothing changes; the normals stay unit.
    templated applies it after the face template, and without a template keeps the buffers."""
    s = 64
    yy, xx = np.mgrid[:s, :s].astype(np.float64)
    height = 3.0 * np.exp(-((xx - 32) ** 2 + (yy - 30) ** 2) / (2 * 2.5 ** 2))
    n = normals_of(height).astype(np.float32)
    face = np.zeros((s, s), np.float32)
    face[16:48, 16:48] = 1.0
    ones = np.ones((s, s), np.float32)
    bufs = intrinsic.Buffers(n, height.astype(np.float32), np.full((3, s, s), 0.5, np.float32),
                             ones, face)
    got = portrait.deepened(bufs, 1.3, 6.0)
    np.testing.assert_allclose(np.linalg.norm(got.normal, axis=0), 1.0, atol=1e-5)
    side = (slice(27, 34), slice(33, 37))  # the bump's side
    assert (np.abs(got.normal[0][side]) > np.abs(n[0][side]) + 0.01).all()
    far = np.ones((s, s), bool)
    far[8:56, 8:56] = False
    np.testing.assert_allclose(got.normal[:, far], n[:, far], atol=1e-6)
    flat = dataclasses.replace(bufs, normal=np.stack([0 * ones, 0 * ones, ones]))
    np.testing.assert_allclose(portrait.deepened(flat, 1.3, 6.0).normal, flat.normal, atol=1e-6)
    assert portrait.deepened(bufs, 1.0, 6.0) is bufs
    monkeypatch.setattr(portrait, "FACE_TEMPLATE", None)  # no shape prior: the network's
    assert portrait.templated(bufs, 2 * s) is bufs
    assert portrait.NORMAL_DETAIL > 1.0


def test_a_finer_sampling_s_buffers_are_shrunk_to_the_crop_and_averaged():
    """portrait.shrunk: buffers of the same box at a larger size come back at the crop's size,
    area-averaged, the normals unit, the height in the crop's pixels; mean_buffers averages
    (the normals renormalised) and keeps the transfer only where both have one."""
    rng = np.random.default_rng(0)
    n = rng.normal(size=(3, 40, 40)).astype(np.float32)
    n[2] = np.abs(n[2]) + 1.0
    n /= np.linalg.norm(n, axis=0, keepdims=True)
    big = intrinsic.Buffers(n, np.full((40, 40), 10.0, np.float32),
                            np.full((3, 40, 40), 0.4, np.float32), np.ones((40, 40), np.float32),
                            np.zeros((40, 40), np.float32), np.ones((16, 40, 40), np.float32))
    small = portrait.shrunk(big, 32)
    assert small.normal.shape == (3, 32, 32) and small.transfer.shape == (16, 32, 32)
    np.testing.assert_allclose(np.linalg.norm(small.normal, axis=0), 1.0, atol=1e-5)
    np.testing.assert_allclose(small.height, 8.0, atol=1e-5)  # 10 px of 40 are 8 of 32
    np.testing.assert_allclose(small.albedo, 0.4, atol=1e-6)
    flat = intrinsic.Buffers(np.broadcast_to(np.float32([0, 0, 1])[:, None, None],
                                             (3, 32, 32)).copy(), np.zeros((32, 32), np.float32),
                             np.full((3, 32, 32), 0.2, np.float32), np.zeros((32, 32), np.float32),
                             np.ones((32, 32), np.float32), None)
    m = portrait.mean_buffers(small, flat)
    np.testing.assert_allclose(np.linalg.norm(m.normal, axis=0), 1.0, atol=1e-5)
    np.testing.assert_allclose(m.height, 4.0, atol=1e-5)
    np.testing.assert_allclose(m.albedo, 0.3, atol=1e-6)
    np.testing.assert_allclose(m.matte, 0.5) and np.testing.assert_allclose(m.face, 0.5)
    assert m.transfer is None
    assert np.all(m.normal[2] > small.normal[2] - 1e-6)  # pulled toward the camera-facing one


def test_shrunk_buffers_are_exact_area_means_of_every_channel():
    """portrait.shrunk takes all channels through one shrink: each (albedo, matte, face, the
    transfer's coefficients, the height times the size ratio) equals detail.resize's exact area
    means of the same channel, and the normals are those means renormalised."""
    rng = np.random.default_rng(1)
    n = rng.normal(size=(3, 40, 40)).astype(np.float32)
    n[2] = np.abs(n[2]) + 1.0
    n /= np.linalg.norm(n, axis=0, keepdims=True)
    big = intrinsic.Buffers(n, rng.random((40, 40), np.float32) * 10,
                            rng.random((3, 40, 40), np.float32), rng.random((40, 40), np.float32),
                            rng.random((40, 40), np.float32), rng.normal(size=(16, 40, 40))
                            .astype(np.float32), rng.random((40, 40), np.float32))

    def area(a):  # (C, 40, 40) or (40, 40) -> (C, 32, 32)
        hwc = np.moveaxis(a.reshape((-1,) + a.shape[-2:]), 0, -1)
        return detail.resize(hwc, 32, 32).transpose(2, 0, 1)

    small = portrait.shrunk(big, 32)
    for got, full in ((small.albedo, big.albedo), (small.matte, big.matte),
                      (small.face, big.face), (small.transfer, big.transfer),
                      (small.hair, big.hair)):
        np.testing.assert_allclose(got, area(full).reshape(got.shape), atol=1e-5)
    np.testing.assert_allclose(small.height, 0.8 * area(big.height)[0], atol=1e-5)
    mean_n = area(big.normal)
    np.testing.assert_allclose(small.normal, mean_n / np.linalg.norm(mean_n, axis=0), atol=1e-5)
    assert portrait.shrunk(dataclasses.replace(big, transfer=None), 32).transfer is None
    plain = portrait.shrunk(dataclasses.replace(big, hair=None), 32)
    assert plain.hair is None
    np.testing.assert_array_equal(plain.transfer, small.transfer)
    both = portrait.mean_buffers(small, dataclasses.replace(small, hair=1.0 - small.hair))
    np.testing.assert_allclose(both.hair, 0.5, atol=1e-6)
    assert portrait.mean_buffers(small, plain).hair is None


def test_the_shared_full_resolution_graphs_are_built_once():
    """shared_fullres() without the caller's graphs keeps one FullRes and returns it again
    (building one costs more than relighting a small frame), and the caller's when given."""
    first = portrait.shared_fullres()
    assert portrait.shared_fullres() is first and portrait.shared_fullres(None) is first
    own = detail.FullRes(threads=1)
    assert portrait.shared_fullres(own) is own


def test_a_model_without_a_normal_output_is_refused(tmp_path):
    """A relight-intrinsic/1 model whose outputs lack 'normal' is a ModelError, not a crash."""
    path = write_standin(tmp_path, "no_normal", normal_name="normals")
    with pytest.raises(ModelError, match="normal"):
        engine.new_session(path, providers=["CPUExecutionProvider"], threads=1)


# ---- framing ---------------------------------------------------------------------------------

@pytest.mark.parametrize("h, w, centre, radius", [(180, 320, (210.0, 80.0), 25.0),
                                                    (320, 180, (70.0, 120.0), 25.0)])
def test_find_box_finds_the_disc(session, h, w, centre, radius):
    """A disc in a wide 16:9 and in a vertical frame: the box is centred on it (lifted by
    framing.LIFT for the hair) and about MARGIN times its diameter."""
    box = portrait.find_box(session, chw(frame(h, w, centre, radius)))
    assert box is not None
    assert abs(box.cx - centre[0]) < 0.03 * box.size
    assert abs(box.cy + framing.LIFT * box.size - centre[1]) < 0.03 * box.size
    assert box.size == pytest.approx(portrait.MARGIN * 2 * radius, rel=0.15)


class Counting:
    """A session that counts its network passes."""

    def __init__(self, session):
        self.inner, self.calls, self.card = session, 0, session.card

    def run_planar(self, x, **kw):
        self.calls += 1
        return self.inner.run_planar(x, **kw)


def test_find_box_follows_a_prior_box_with_one_network_pass(session):
    """From a nearby frame's box the crop around it is searched directly (one network pass, no
    coarse pass) and gives the box a search of the whole frame gives."""
    h, w, centre, radius = 180, 320, (210.0, 80.0), 25.0
    x = chw(frame(h, w, centre, radius))
    counting = Counting(session)
    full = portrait.find_box(counting, x)
    assert counting.calls == 2
    moved = framing.Box(full.cx - 6.0, full.cy + 4.0, full.size * 1.1)  # a few frames before
    counting.calls = 0
    tracked = portrait.find_box(counting, x, prior=moved)
    assert counting.calls == 1
    assert abs(tracked.cx - full.cx) < 0.03 * full.size
    assert abs(tracked.cy - full.cy) < 0.03 * full.size
    assert tracked.size == pytest.approx(full.size, rel=0.1)


def test_a_prior_box_without_the_portrait_falls_back_to_the_whole_frame(session):
    """A prior box where the portrait no longer is (it moved away, or left the frame) is not
    followed: the whole frame is searched; with no portrait anywhere the answer is None."""
    h, w, centre, radius = 180, 320, (240.0, 90.0), 25.0
    x = chw(frame(h, w, centre, radius))
    stale = framing.Box(60.0, 80.0, 110.0)  # the left of the frame, grey background only
    got = portrait.find_box(session, x, prior=stale)
    want = portrait.find_box(session, x)
    assert got == want and abs(got.cx - centre[0]) < 0.03 * got.size
    assert portrait.find_box(session, chw(frame(h, w)), prior=want) is None


def test_the_followed_portrait_stays_the_subject_when_a_larger_one_comes_in(session):
    """Two faces: a search of the whole frame picks the larger; a run that has been following
    the smaller keeps it (the subject does not jump to whoever comes nearer the camera)."""
    h, w = 180, 320
    img = frame(h, w, (80.0, 90.0), 20.0)
    big = frame(h, w, (240.0, 90.0), 32.0, seed=1)
    img[:, 160:] = big[:, 160:]
    x = chw(img)
    assert portrait.find_box(session, x).cx > 160
    small = portrait.find_box(session, chw(frame(h, w, (80.0, 90.0), 20.0)))
    assert portrait.find_box(session, x, prior=small).cx < 160


@pytest.mark.parametrize("kind", ["black", "grey"])
def test_no_portrait_gives_none_and_an_unchanged_frame(session, kind):
    """A black (or grey, skinless) frame has no box; relight_frame(..., None) returns the frame
    unchanged with found=False and an empty matte."""
    x = chw(np.zeros((45, 80, 3), np.float32) if kind == "black" else frame(45, 80))
    assert portrait.find_box(session, x) is None
    res = portrait.relight_frame(session, x, RIGHT_LAMP, None)
    assert not res.found and res.plan is None
    assert np.all(res.a == 1.0) and not res.b.any() and not res.matte.any()
    np.testing.assert_allclose(apply(x, res), x, rtol=HALF, atol=0)


def test_relight_frame_changes_the_portrait_and_keeps_the_background(session):
    """Under a lamp from the right the disc's right half gains on its left half; pixels outside
    the matte keep the footage exactly."""
    h, w, centre, radius = 90, 160, (90.0, 45.0), 20.0
    x = chw(frame(h, w, centre, radius, seed=1))
    box = portrait.find_box(session, x)
    res = portrait.relight_frame(session, x, RIGHT_LAMP, box)
    assert res.found and res.matte.max() > 0.99
    y = apply(x, res)
    assert y.shape == x.shape and np.all(np.isfinite(y))
    outside = away_from((h, w), centre, radius + margin(h, w))
    np.testing.assert_allclose(y[:, outside], x[:, outside], rtol=HALF, atol=0)
    inner = within((h, w), centre, radius - 3)
    yy, xx = np.mgrid[0:h, 0:w] + 0.5
    left, right = inner & (xx < centre[0] - 4), inner & (xx > centre[0] + 4)
    gain = intrinsic.luminance(y) / intrinsic.luminance(x)
    assert gain[right].mean() > 1.5 * gain[left].mean()
    # The mirrored lamp favours the other side.
    mirrored = lightvec.splat_direction([-1.0, 0.0, 0.35], 10.0) + lightvec.uniform(0.05)
    y = apply(x, portrait.relight_frame(session, x, mirrored, box))
    gain = intrinsic.luminance(y) / intrinsic.luminance(x)
    assert gain[left].mean() > 1.5 * gain[right].mean()


def test_grid_shape_snaps_to_block_ratios_near_the_box_scale():
    """The grid puts the box at about the working size; where the frame allows, at a ratio the
    full-resolution stages shrink and enlarge by exact blocks; never above the frame's size."""
    box = framing.Box(1400.0, 430.0, 680.0)  # 128 / 680 = 0.188
    assert portrait.grid_shape(1080, 1920, box, 128) == (198, 352)  # 11/60
    assert detail.upsample_blocks(198, 1080) is not None
    assert portrait.grid_shape(1081, 1919, box, 128) == (203, 361)  # no ratio: the plain scale
    # A close-up (128 / 1250 = 0.102) and a 4K frame: no ratio of four or more grid samples a
    # block lies within 10%, so blocks of fewer: 1/10 and 1/16, exact blocks both ways.
    assert portrait.grid_shape(1080, 1920, framing.Box(960.0, 540.0, 1250.0), 128) == (108, 192)
    assert portrait.grid_shape(2160, 3840, framing.Box(1900.0, 900.0, 2000.0), 128) == (135, 240)
    assert detail.upsample_blocks(108, 1080) is not None
    assert detail.upsample_blocks(135, 2160) is not None
    assert portrait.grid_shape(90, 160, framing.Box(45.0, 45.0, 60.0), 128) == (90, 160)


# ---- addon.api.relight_image -----------------------------------------------------------------

@pytest.mark.parametrize("h, w", [(37, 53), (53, 37), (1, 1), (2, 1), (1, 7)])
def test_relight_image_any_size(model, h, w):
    """Odd and tiny sizes come back (H, W, 3) float32 and finite, with or without a portrait."""
    for img in (frame(h, w, (w / 2, h / 2), 0.3 * min(h, w) + 0.5), np.zeros((h, w, 3), np.float32),
                np.broadcast_to(SKIN, (h, w, 3))):
        out = api.relight_image(img, RIGHT_LAMP, model=model, threads=1)
        assert out.shape == (h, w, 3) and out.dtype == np.float32
        assert np.all(np.isfinite(out)) and out.min() >= 0.0


def test_relight_image_takes_bad_pixels_as_zero(model):
    """NaN, Inf and negative pixels: finite output, those pixels black, the portrait relit as if
    they were 0."""
    img = frame(48, 64, (32.0, 24.0), 12.0)
    bad = img.copy()
    bad[0, :8] = np.nan
    bad[1, :8] = np.inf
    bad[2, :8] = -np.inf
    bad[3, :8] = -1.0
    out = api.relight_image(bad, RIGHT_LAMP, model=model, threads=1)
    assert out.shape == img.shape and np.all(np.isfinite(out))
    assert not out[:4, :8].any()
    clean = img.copy()
    clean[:4, :8] = 0.0
    np.testing.assert_array_equal(out, api.relight_image(clean, RIGHT_LAMP, model=model, threads=1))


def test_relight_image_is_the_frame_path(model, session):
    """relight_image is find_box + relight_frame on the image."""
    img = frame(60, 90, (40.0, 30.0), 14.0, seed=2)
    x = chw(img)
    want = apply(x, portrait.relight_frame(session, x, RIGHT_LAMP, portrait.find_box(session, x)))
    got = api.relight_image(img, RIGHT_LAMP, model=model, threads=1)
    np.testing.assert_array_equal(got, want.transpose(1, 2, 0))
    assert np.abs(got - img).max() > 0.05


def test_a_working_size_in_place_of_the_card_s_runs_the_network_on_crops_of_that_size(
        model, monkeypatch):
    """relight_image(working_size=...) frames and relights at that size (the crops the network
    sees), a valid relit frame; a size that is not a positive whole number is refused."""
    img = frame(60, 90, (40.0, 30.0), 14.0, seed=2)
    seen = []
    run = engine.IntrinsicSession.run_planar
    monkeypatch.setattr(engine.IntrinsicSession, "run_planar",
                        lambda self, x, **kw: seen.append(x.shape[1:]) or run(self, x, **kw))
    card = engine.load_card(model).working_size
    for size in (card // 2, card + 16):
        seen.clear()
        out = api.relight_image(img, RIGHT_LAMP, model=model, threads=1, working_size=size)
        assert (size, size) in seen and (card, card) not in seen
        assert np.all(np.isfinite(out)) and np.abs(out - img).max() > 0.05
    for bad in (0, -32, 12.5, "64", True):
        with pytest.raises(InputError, match="working size"):
            api.relight_image(img, RIGHT_LAMP, model=model, threads=1, working_size=bad)


def test_a_clip_run_relights_at_the_working_size_its_options_ask_for(model, tmp_path,
                                                                     monkeypatch):
    """RelightOptions.working_size reaches Portrait's crops, as it sets the end-to-end presets'
    working shape, and is part of the run's identity."""
    seen = []
    run = engine.IntrinsicSession.run_planar
    monkeypatch.setattr(engine.IntrinsicSession, "run_planar",
                        lambda self, x, **kw: seen.append(x.shape[1:]) or run(self, x, **kw))
    files = write_exr_sequence(tmp_path / "src", clip_frames())
    size = engine.load_card(model).working_size + 16
    res = pipeline.relight_clip(image_clip(files), RIGHT_LAMP[None], tmp_path / "out",
                                pipeline.RelightOptions(model, threads=1, working_size=size))
    assert res.written == N and (size, size) in seen
    stored = json.loads((tmp_path / "out" / pipeline.RUN_FILE).read_text())
    assert stored["identity"]["settings"]["working_size"] == size


@pytest.mark.parametrize("centre", [(8.0, 30.0), (90.0, 4.0), (92.0, 60.0)])
def test_a_disc_touching_the_frame_edge(model, centre):
    """A portrait cut by the frame's edge: finite, relit, and the footage unchanged outside the
    disc (the crop's padding beyond the frame is not taken for the subject)."""
    h, w, radius = 64, 96, 14.0
    img = frame(h, w, centre, radius, seed=3)
    out = api.relight_image(img, RIGHT_LAMP, model=model, threads=1)
    assert out.shape == img.shape and np.all(np.isfinite(out))
    outside = away_from((h, w), centre, radius + margin(h, w))
    np.testing.assert_allclose(out[outside], img[outside], rtol=HALF, atol=0)
    assert np.abs(out - img)[within((h, w), centre, radius - 2)].max() > 0.05


# ---- the pipeline ----------------------------------------------------------------------------

H, W, N = 48, 80, 4


def clip_frames(absent=()):
    """N frames of a disc drifting right; frames in ``absent`` have no disc."""
    return [frame(H, W, None if i in absent else (34.0 + 2 * i, 24.0), 11.0, seed=10 + i)
            for i in range(N)]


def image_clip(files):
    files = tuple(str(f) for f in files)
    return pipeline.ClipSpec("images", str(pathlib.Path(files[0]).parent), files, 0, len(files),
                             "Linear Rec.709", 0.0)


def run(model, files, out):
    return pipeline.relight_clip(image_clip(files), RIGHT_LAMP[None], out,
                                 pipeline.RelightOptions(model, threads=1, write_matte=True))


def sha(path):
    return hashlib.sha256(pathlib.Path(path).read_bytes()).hexdigest()


def test_clip_writes_every_frame_and_resumes_bit_identically(model, tmp_path):
    """Every frame and the boxes file are written; after deleting one relit frame a rerun writes
    exactly that frame, framed from the stored boxes, bit-identical to the first run's."""
    src = clip_frames()
    files = write_exr_sequence(tmp_path / "src", src)
    out = tmp_path / "out"
    res = run(model, files, out)
    assert res.written == N and res.resumed == 0 and not res.warnings
    assert all(os.path.isfile(p) for p in res.relit_files + res.matte_files)
    boxes_path = out / pipeline.BOXES_FILE
    stored = json.loads(boxes_path.read_text(encoding="utf-8"))
    # Every FRAMING_STEP-th frame and the last are framed; the others are interpolated.
    framed = sorted(set(range(0, N, pipeline.FRAMING_STEP)) | {N - 1})
    assert stored["framed"] == framed and stored["found"] == len(framed)
    assert len(stored["boxes"]) == N
    for i, b in enumerate(stored["boxes"]):  # each box on its frame's disc
        assert abs(b[0] - (34.0 + 2 * i)) < 0.1 * b[2] and b[2] > 2 * 11.0
    for i, p in enumerate(res.relit_files):
        y = frames.read_exr(p)
        assert y.shape == (H, W, 3) and np.all(np.isfinite(y))
        assert np.abs(y - src[i]).max() > 0.05  # relit, not copied
    first = [sha(p) for p in res.relit_files]
    boxes_bytes, boxes_stamp = boxes_path.read_bytes(), boxes_path.stat().st_mtime_ns

    os.remove(res.relit_files[2])
    again = run(model, files, out)
    assert (again.written, again.resumed) == (1, N - 1)
    assert [sha(p) for p in again.relit_files] == first
    assert boxes_path.read_bytes() == boxes_bytes  # not framed again: read back
    assert boxes_path.stat().st_mtime_ns == boxes_stamp


def test_a_frame_without_a_portrait_warns_and_is_written_unchanged(model, tmp_path):
    """A frame with no disc: the run warns that no portrait was found, that frame comes out as its
    input (within half-float rounding) and the others are relit."""
    gone = pipeline.FRAMING_STEP  # a frame the framing pass looks at
    src = clip_frames(absent=(gone,))
    files = write_exr_sequence(tmp_path / "src", src)
    res = run(model, files, tmp_path / "out")
    assert res.written == N
    assert any("No portrait was found in 1 frame" in m for m in res.warnings), res.warnings
    stored = json.loads((tmp_path / "out" / pipeline.BOXES_FILE).read_text(encoding="utf-8"))
    assert stored["missing"] == [gone] and stored["found"] == len(stored["framed"]) - 1
    assert stored["boxes"][gone] is not None  # framed like its neighbours
    out = [frames.read_exr(p) for p in res.relit_files]
    np.testing.assert_allclose(out[gone], src[gone], rtol=2.0 ** -10, atol=0)
    assert frames.read_exr(res.matte_files[gone]).max() < 1e-2  # no subject seen there
    for i in sorted(set(range(N)) - {gone}):
        assert np.abs(out[i] - src[i]).max() > 0.05


def test_keep_exposure_is_one_gain_for_the_clip_and_physical_follows_the_light(model, tmp_path):
    """Keep (the default): one gain for the whole clip, so the frame under three times the lamp
    is about three times as bright on the subject, and the clip's subject keeps the footage's
    luminance; physical: the gain is the absolute one, and a brighter lamp brightens it."""
    src = [clip_frames()[0]] * 2
    files = write_exr_sequence(tmp_path / "src", src)
    lights = np.stack([RIGHT_LAMP, 3.0 * RIGHT_LAMP])
    disc = within((H, W), (34.0, 24.0), 8.0)

    def relit(mode, lamps, out):
        res = pipeline.relight_clip(image_clip(files), lamps, tmp_path / out,
                                    pipeline.RelightOptions(model, threads=1,
                                                            exposure_mode=mode))
        gain = json.loads((tmp_path / out / pipeline.RUN_FILE).read_text())["exposure_gain"]
        return [frames.read_exr(p) for p in res.relit_files], gain

    keep, gain = relit("keep", lights, "keep")
    ratio = keep[1][disc].mean() / keep[0][disc].mean()
    assert 2.5 < ratio < 3.5, ratio
    both = (keep[0][disc].mean() + keep[1][disc].mean()) / (2 * src[0][disc].mean())
    assert 0.8 < both < 1.25, both  # the subject keeps the footage's luminance over the clip
    one, g1 = relit("physical", lights[:1], "physical1")
    two, g2 = relit("physical", 2 * lights[:1], "physical2")
    assert g1 == g2 and g1 != gain  # the absolute gain does not depend on the light
    # Inside the outline's fade (addon.outline) a pixel keeps part of the footage, which does
    # not double with the light: the disc's core only.
    core = within((H, W), (34.0, 24.0), 6.0)
    np.testing.assert_allclose(two[0][core], 2 * one[0][core], rtol=1e-2)


def test_frames_blend_with_their_neighbours_and_chunks_still_equal_one_run(model, tmp_path):
    """Temporal blend on (the default): interior frames differ from relighting each frame alone,
    and a run split in two chunks (each infers the neighbour just outside it) writes the whole
    run's frames bit for bit."""
    files = write_exr_sequence(tmp_path / "src", clip_frames())
    whole = run(model, files, tmp_path / "whole")
    alone = pipeline.relight_clip(image_clip(files), RIGHT_LAMP[None], tmp_path / "alone",
                                  pipeline.RelightOptions(model, threads=1, write_matte=True,
                                                          temporal=False))
    changed = [np.abs(frames.read_exr(a) - frames.read_exr(b)).max()
               for a, b in zip(whole.relit_files, alone.relit_files)]
    assert min(changed) > 1e-3, changed  # the disc drifts: each frame takes its neighbours'
    for chunk in ((0, 1), (2, 3)):
        pipeline.relight_clip(image_clip(files), RIGHT_LAMP[None], tmp_path / "chunked",
                              pipeline.RelightOptions(model, threads=1, write_matte=True),
                              frames=list(chunk))
    assert [sha(pipeline.relit_path(tmp_path / "chunked", i)) for i in range(N)] == \
        [sha(p) for p in whole.relit_files]


def test_a_light_that_jumps_is_never_blended_across(model, tmp_path):
    """A light twice as strong every other frame (a strobe): no frame takes its neighbours'
    change, so the run equals relighting each frame alone."""
    files = write_exr_sequence(tmp_path / "src", clip_frames())
    lights = np.stack([RIGHT_LAMP * (1.0 + i % 2) for i in range(N)])

    def relit(temporal, out):
        res = pipeline.relight_clip(image_clip(files), lights, tmp_path / out,
                                    pipeline.RelightOptions(model, threads=1, temporal=temporal))
        return [sha(p) for p in res.relit_files]

    assert relit(True, "blend") == relit(False, "alone")
