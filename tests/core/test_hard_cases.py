"""The hard-case catalogue (tests/HARD_CASES.md) for the engine and the pipeline, with the toy
models: cases no other test covers, plus the check that the catalogue names only real tests.

Expectations, as the catalogue states them: every written frame (relit, matte, source light) is
finite and within the half-float range; brightness follows light transport (twice the light,
exactly twice the output: the pipeline divides the light by its mean radiance k before the
network and multiplies by k after, so a power-of-two scale is exact in binary floating point);
bad input is a RelightError whose message says what to do.
"""

from __future__ import annotations

import os
import pathlib
import re

import numpy as np
import onnx
import pytest
from onnx import helper

from addon import (api, colour, contract, engine, frames, hdri, lamps, lightvec, outline,
                   pipeline)
from addon.errors import LightingError, OutputError
from tests.clip_fixtures import ramp_frames, write_exr_sequence, write_png
from tests.onnx_fixtures import card_fields, graph_model, save_model

ROOT = pathlib.Path(__file__).resolve().parents[2]
CATALOGUE = ROOT / "tests" / "HARD_CASES.md"
HALF_MAX = 65504.0
UNIFORM = lightvec.uniform(1.0)[None]


# ---- models -------------------------------------------------------------------------------

def build_broken_model() -> onnx.ModelProto:
    """A model that returns NaN, +Inf and -Inf: relit R = x / 0 (NaN where x = 0, +Inf
    elsewhere), G = -x / 0, B = log(x - 0.5); source light = light / 0; parsing = NaN or 1."""
    nodes = [
        helper.make_node("Split", ["image", "split3"], ["r", "g", "b"], axis=1),
        helper.make_node("Div", ["r", "zero"], ["r_out"]),
        helper.make_node("Neg", ["g"], ["g_neg"]),
        helper.make_node("Div", ["g_neg", "zero"], ["g_out"]),
        helper.make_node("Sub", ["b", "half"], ["b_sub"]),
        helper.make_node("Log", ["b_sub"], ["b_out"]),
        helper.make_node("Concat", ["r_out", "g_out", "b_out"], ["relit"], axis=1),
        helper.make_node("Div", ["target_light", "zero"], ["source_light"]),
        helper.make_node("Concat", ["b_out", "r_out"], ["par_in"], axis=1),
        helper.make_node("Sigmoid", ["par_in"], ["parsing"]),
    ]
    return graph_model(nodes, {"split3": np.array([1, 1, 1], np.int64), "zero": np.float32(0.0),
                          "half": np.float32(0.5)}, "broken")


def build_sqrt_light_model() -> onnx.ModelProto:
    """relit = image * sqrt(mean light): a network that is NOT linear in the light by itself, so
    the pipeline's light normalisation alone must make the output scale with the light."""
    nodes = [
        helper.make_node("ReduceMean", ["target_light", "axes"], ["mean"], keepdims=1),
        helper.make_node("Sqrt", ["mean"], ["gain"]),
        helper.make_node("Mul", ["image", "gain"], ["relit"]),
        helper.make_node("Mul", ["target_light", "zero"], ["z"]),
        helper.make_node("Add", ["z", "one"], ["source_light"]),
        helper.make_node("ReduceMean", ["image", "axes_c"], ["lum"], keepdims=1),
        helper.make_node("Concat", ["lum", "lum"], ["par_in"], axis=1),
        helper.make_node("Sigmoid", ["par_in"], ["parsing"]),
    ]
    return graph_model(nodes, {"axes": np.array([1, 2, 3], np.int64), "zero": np.float32(0.0),
                          "one": np.float32(1.0), "axes_c": np.array([1], np.int64)},
                  "sqrt_light")


def build_negative_model() -> onnx.ModelProto:
    """relit = image - 0.3: negative radiance wherever the image is darker than 0.3."""
    nodes = [
        helper.make_node("Sub", ["image", "offset"], ["relit"]),
        helper.make_node("Mul", ["target_light", "zero"], ["z"]),
        helper.make_node("Add", ["z", "one"], ["source_light"]),
        helper.make_node("ReduceMean", ["image", "axes_c"], ["lum"], keepdims=1),
        helper.make_node("Mul", ["lum", "zero"], ["flat"]),
        helper.make_node("Add", ["flat", "one"], ["fg"]),
        helper.make_node("Concat", ["fg", "fg"], ["parsing"], axis=1),
    ]
    return graph_model(nodes, {"offset": np.float32(0.3), "zero": np.float32(0.0),
                          "one": np.float32(1.0), "axes_c": np.array([1], np.int64)},
                  "negative")


@pytest.fixture(scope="module")
def broken(tmp_path_factory):
    return str(save_model(build_broken_model(), tmp_path_factory.mktemp("broken"), "broken", card_fields()))


@pytest.fixture(scope="module")
def negative(tmp_path_factory):
    return str(save_model(build_negative_model(), tmp_path_factory.mktemp("negative"), "negative",
                     card_fields()))


@pytest.fixture(scope="module")
def sqrt_light(tmp_path_factory):
    return str(save_model(build_sqrt_light_model(), tmp_path_factory.mktemp("sqrt"), "sqrt_light",
                     card_fields()))


def is_intrinsic(model) -> bool:
    return engine.load_card(model).contract == contract.INTRINSIC_CONTRACT


def shipped_models() -> list[str]:
    """Real trained models in models/ with their cards (none until training has shipped one)."""
    return sorted(str(p) for p in (ROOT / "models").glob("*.onnx")
                  if p.with_suffix(".json").is_file())


# ---- helpers ------------------------------------------------------------------------------

def image_clip(files, space="Linear Rec.709"):
    files = tuple(str(f) for f in files)
    return pipeline.ClipSpec("images", str(pathlib.Path(files[0]).parent), files, 0, len(files),
                             space, 0.0)


def opts(model, **kw):
    kw.setdefault("working_size", 16)
    kw.setdefault("threads", 1)
    kw.setdefault("background", "network")  # the network's own output unless a test says
    kw.setdefault("exposure_mode", "physical")  # the light's own level: scaling is what's checked
    return pipeline.RelightOptions(model, **kw)


def relight(model, files, out, lights=UNIFORM, space="Linear Rec.709", **kw):
    return pipeline.relight_clip(image_clip(files, space), lights, out, opts(model, **kw))


def written(res) -> list[np.ndarray]:
    """Every array a run wrote: relit and matte frames, source lights."""
    arrays = [frames.read_exr(f) for f in res.relit_files + res.matte_files]
    arrays += [np.load(pipeline.source_path(res.out_dir, i)) for i in range(len(res.relit_files))]
    return arrays


def assert_safe(arrays) -> None:
    for a in arrays:
        assert np.all(np.isfinite(a)), "a written file holds NaN or Inf"
        assert np.abs(a).max() <= np.finfo(np.float32).max


def one_frame(folder, px) -> list[str]:
    return write_exr_sequence(pathlib.Path(folder), [np.asarray(px, np.float32)])


# ---- frames -------------------------------------------------------------------------------

def _frames():
    rng = np.random.default_rng(3)
    tex = rng.random((24, 40, 3)).astype(np.float32)
    nan_frame = np.full((24, 40, 3), np.nan, np.float32)
    nan_frame[::3, ::2] = np.inf
    nan_frame[1::3, ::2] = -1.0
    return {
        "black": np.zeros((24, 40, 3), np.float32),
        "white": np.ones((24, 40, 3), np.float32),
        "saturated_red": np.stack([np.ones((24, 40)), 0 * tex[..., 1], 0 * tex[..., 2]], -1),
        "hdr_1e4": 1e4 * tex + 1.0,
        "all_nan_inf_negative": nan_frame,
    }


@pytest.mark.parametrize("name", list(_frames()))
@pytest.mark.parametrize("detail", [True, False])
def test_black_white_saturated_and_non_finite_frames(toy, tmp_path, name, detail):
    """Expectation: finite output that is the toy's physics (uniform light 2 doubles the input
    over the clip's exposure s, the toy's source radiance; NaN/Inf/negative pixels count as 0),
    and a warning for replaced pixels."""
    px = _frames()[name].astype(np.float32)
    res = relight(toy, one_frame(tmp_path / "in", px), tmp_path / "out", 2 * UNIFORM,
                  detail_transfer=detail, write_matte=True)
    assert_safe(written(res))
    out = frames.read_exr(res.relit_files[0])
    clean = np.where(np.isfinite(px) & (px > 0), px, 0.0)
    want = np.minimum(2 * clean / res.exposure_scale, HALF_MAX)
    if detail:  # the guided transfer keeps every pixel
        np.testing.assert_allclose(out, want, rtol=2e-3, atol=1e-6)
    else:  # plain upsampling of the working-size result: local means, within the input's range
        np.testing.assert_allclose(out.mean((0, 1)), want.mean((0, 1)), rtol=2e-2, atol=1e-6)
        assert out.min() >= 0 and out.max() <= want.max() * 1.001
    if name == "all_nan_inf_negative":
        assert res.exposure_scale == 1.0 and not out.any()
        assert any("NaN, infinite or negative" in w for w in res.warnings)


def test_8bit_white_and_black_movie_frames(toy, tmp_path):
    """Clipped 8-bit code values (0 and 255 in every channel) through the sRGB curve."""
    black_white = [np.zeros((16, 24, 3), np.uint8), np.full((16, 24, 3), 255, np.uint8)]
    (tmp_path / "png").mkdir()
    files = []
    for i, f in enumerate(black_white):
        files.append(str(tmp_path / "png" / f"bw_{i + 1:04d}.png"))
        write_png(files[-1], f)
    res = relight(toy, files, tmp_path / "out", UNIFORM, space="sRGB")
    black, white = (frames.read_exr(f) for f in res.relit_files)
    assert not black.any()
    np.testing.assert_allclose(white, 1.0 / res.exposure_scale, rtol=2e-3)


# ---- sizes --------------------------------------------------------------------------------

@pytest.mark.parametrize("h,w", [(1, 1), (1, 7), (5, 3), (33, 17)])
def test_tiny_and_odd_frames_with_a_real_stride(toy, tmp_path, h, w):
    """The toy needs its stride 8: the engine pads and crops, at working size and at full size."""
    px = np.random.default_rng(h + w).random((h, w, 3)).astype(np.float32) + 0.1
    for working in (4, 64):
        res = relight(toy, one_frame(tmp_path / f"in{working}", px), tmp_path / f"o{working}",
                      3 * UNIFORM, working_size=working)
        out = frames.read_exr(res.relit_files[0])
        assert out.shape == (h, w, 3)
        np.testing.assert_allclose(out, 3 * px / res.exposure_scale, rtol=4e-3)


@pytest.mark.parametrize("h,w", [(2160, 3840), (4320, 7680)], ids=["4K", "8K"])
def test_4k_and_8k_frames(toy, tmp_path, h, w):
    """One 4K / 8K half-float EXR frame through the whole pipeline (toy at working size 64):
    finite, full size, the toy's physics (light 2 doubles the input over s) to half precision."""
    y = np.linspace(0.05, 1.0, h, dtype=np.float32)[:, None, None]
    x = np.linspace(0.2, 1.0, w, dtype=np.float32)[None, :, None]
    px = (y * x * np.array([1.0, 0.8, 0.6], np.float32)).astype(np.float16)
    (tmp_path / "in").mkdir()
    src = str(tmp_path / "in" / "plate.0001.exr")
    frames.write_exr(src, px, "rle")
    del y, x
    res = relight(toy, [src], tmp_path / "out", 2 * UNIFORM, working_size=64,
                  exr_compression="rle")
    out = frames.read_exr(res.relit_files[0])
    assert out.shape == (h, w, 3) and np.all(np.isfinite(out))
    rows = slice(None, None, 97)  # a sample of rows keeps the comparison cheap
    want = 2 * px[rows].astype(np.float32) / np.float32(res.exposure_scale)
    np.testing.assert_allclose(out[rows], want, rtol=3e-3, atol=1e-4)


# ---- the network path ---------------------------------------------------------------------

def _extreme_lights() -> dict:
    one_texel = lightvec.zeros()
    one_texel[6, 9] = 1e5
    coloured = lightvec.uniform((1.0, 0.0, 0.0))
    coloured[3:8, 6:10] = (0.0, 0.0, 40.0)
    return {"one_texel_1e5": one_texel, "very_coloured": coloured,
            "tiny_1e-6": lightvec.uniform(1e-6), "hot_1e6": lightvec.uniform(1e6),
            "one_texel_1e30": one_texel * 1e25}


NETWORKS = ["toy", "sqrt_light"] + [f"shipped:{p}" for p in shipped_models()]


def _network(name, request):
    return name.split(":", 1)[1] if name.startswith("shipped:") else request.getfixturevalue(name)


@pytest.mark.parametrize("background", ["network", "relit"])
@pytest.mark.parametrize("net", NETWORKS)
@pytest.mark.parametrize("light", list(_extreme_lights()))
def test_extreme_lights_are_finite_and_scale_with_the_light(net, light, background, request,
                                                            tmp_path):
    """Twice the light gives exactly twice the output (bit for bit, where nothing clamps and
    outside half-float subnormals), for any network, because the pipeline feeds it light / k and
    multiplies by k after; three times the light gives three times the output within half-float
    rounding (rtol 2^-10). With the background kept and relit too: the wall's gain is linear in
    the light (three times within 2^-8 there: the composite's coefficient sum m a + (1 - m) g
    rounds in float32 before the half output, which a saturated colour can make visible)."""
    model = _network(net, request)
    px = np.concatenate([np.zeros((8, 24, 3)), np.ones((8, 24, 3)),
                         np.random.default_rng(1).random((16, 24, 3))]).astype(np.float32)
    files = one_frame(tmp_path / "in", px)
    base = _extreme_lights()[light]
    outs = {}
    for c in (1, 2, 3):
        res = relight(model, files, tmp_path / f"out{c}", (c * base)[None], working_size=16,
                      background=background)
        assert_safe(written(res))
        outs[c] = frames.read_exr(res.relit_files[0])
        assert outs[c].min() >= 0, "negative radiance reached a file"
    ok = np.abs(outs[3]) < HALF_MAX  # values that clamp cannot scale
    if is_intrinsic(model):
        # Nor can the outline's refit of them (addon.outline.apply): it mixes a fade pixel's
        # relit value, already clamped to half float, with the footage, so it comes out below
        # the maximum yet not scaled. Such pixels lie within the refit's reach of ones that
        # clamp outright: its windows (outline.RADIUS and outline.COLOUR_RADIUS grid samples
        # each way) and the enlargement's one sample more, at this frame's two pixels a grid
        # sample (a 16 x 12 grid), 8 pixels.
        reach = 2 * (outline.RADIUS + outline.COLOUR_RADIUS + 1)
        clamped = np.pad(~ok.all(-1), reach)
        h, w = ok.shape[:2]
        near = np.zeros((h, w), bool)
        for dy in range(2 * reach + 1):
            for dx in range(2 * reach + 1):
                near |= clamped[dy:dy + h, dx:dx + w]
        ok &= ~near[..., None]
        assert ok.any()
        # In absolute units the subject's change is linear in the light while the footage
        # beyond the portrait stays as it was: the output is affine in the light's power.
        np.testing.assert_allclose((outs[3] - 2 * outs[2] + outs[1])[ok], 0.0,
                                   atol=2 ** -8 * float(np.abs(outs[3][ok]).max()) + 2 ** -20)
        # Keeping the footage's exposure, a stronger light of the same shape gives the same
        # frame: the light sets direction, colour and contrast.
        keep = [frames.read_exr(relight(model, files, tmp_path / f"keep{c}", (c * base)[None],
                                        working_size=16, background=background,
                                        exposure_mode="keep").relit_files[0]) for c in (1, 3)]
        np.testing.assert_allclose(keep[1], keep[0], rtol=2 ** -9, atol=2 ** -20)
        return
    # Half-float subnormals (below 2^-14) have a fixed step of 2^-24, so there doubling can be
    # one step off; everywhere else it is exact.
    np.testing.assert_allclose(outs[2][ok], 2 * outs[1][ok], rtol=0, atol=2 ** -24)
    normal = ok & (np.abs(outs[1]) >= 2 ** -14)
    np.testing.assert_array_equal(outs[2][normal], 2 * outs[1][normal])
    # Tripling a subnormal rounded by half a step can land two steps from its own rounding.
    np.testing.assert_allclose(outs[3][ok], 3 * outs[1][ok],
                               rtol=2 ** -10 if background == "network" else 2 ** -8,
                               atol=2 ** -23)


@pytest.mark.parametrize("net", NETWORKS)
def test_black_light_is_refused_by_a_run_and_black_in_relight_image(net, request, tmp_path):
    """A run whose light is black on every frame (all zero; 2^-100, an exposure of -100; just
    below the smallest half float) is a LightingError saying what to set, before anything is
    written. Below the run the maths keeps its defined answer: no light, a black image, the
    network not run. Intrinsic presets keep the footage's exposure, so for them only a light of
    exactly zero is black; a faint one relights by its direction like any other."""
    model = _network(net, request)
    files = one_frame(tmp_path / "in", np.ones((8, 8, 3)))
    for n, light in enumerate((lightvec.zeros(), lightvec.uniform(2.0 ** -100),
                               lightvec.uniform(lightvec.DARKEST / 2))):
        if is_intrinsic(model) and light.any():
            res = relight(model, files, tmp_path / f"faint{n}", light[None])
            assert frames.read_exr(res.relit_files[0]).any()
            continue
        with pytest.raises(LightingError, match="lighting is black.*add a lamp with energy"):
            relight(model, files, tmp_path / "out", light[None], write_matte=True)
        assert not (tmp_path / "out").exists()
    assert not api.relight_image(np.ones((8, 8, 3), np.float32), lightvec.zeros(),
                                 model=model, threads=1).any()
    # Just bright enough to show: a run, and a frame that is not black.
    res = relight(model, files, tmp_path / "out", lightvec.uniform(4 * lightvec.DARKEST)[None])
    assert frames.read_exr(res.relit_files[0]).any()


# ---- NaN and Inf never reach a written frame ----------------------------------------------

@pytest.mark.parametrize("detail,working,matte", [
    (True, 8, True),    # network at low resolution, guided transfer to full resolution
    (False, 8, True),   # low resolution, plain upsampling
    (True, 64, False),  # the network at full resolution (no transfer)
    (False, 64, True),
])
def test_a_network_that_returns_nan_and_inf_never_reaches_a_file(broken, tmp_path, detail,
                                                                 working, matte):
    px = np.random.default_rng(2).random((20, 30, 3)).astype(np.float32)
    px[:5] = 0.0  # 0 / 0 = NaN in the broken model's red channel
    res = relight(broken, one_frame(tmp_path / "in", px), tmp_path / "out", UNIFORM,
                  detail_transfer=detail, working_size=working, write_matte=matte)
    arrays = written(res)
    assert_safe(arrays)
    assert arrays[0].min() >= 0 and arrays[0].max() <= HALF_MAX  # -Inf becomes 0, not -65504
    if matte:
        m = frames.read_exr(res.matte_files[0])
        assert m.min() >= 0 and m.max() <= 1


@pytest.mark.parametrize("detail,working", [(True, 8), (False, 8), (True, 64)])
def test_negative_radiance_is_written_as_zero_and_reported_once(negative, tmp_path, detail,
                                                                working):
    px = np.random.default_rng(4).random((24, 32, 3)).astype(np.float32) * 0.6
    files = write_exr_sequence(tmp_path / "in", [px, px])
    res = relight(negative, files, tmp_path / "out", UNIFORM, detail_transfer=detail,
                  working_size=working)
    for f in res.relit_files:
        out = frames.read_exr(f)
        assert out.min() == 0 and out.max() > 0
        if working == 64:  # the network at full size: max(image / s - 0.3, 0) (s: exposure)
            want = np.maximum(px / np.float32(res.exposure_scale) - np.float32(0.3), 0)
            np.testing.assert_allclose(out, want, rtol=2e-3, atol=1e-4)
    warned = [w for w in res.warnings if "below 0" in w]
    assert len(warned) == 1 and "on 2 frame(s)" in warned[0], res.warnings


def test_hdri_sun_of_1e5_and_more_is_finite_end_to_end(toy, tmp_path):
    """An HDRI with a sun of 1e5 (and 1e9) gives a finite light vector; the relit frame is finite,
    values beyond the half range are clamped to 65504 and the run says so."""
    files = one_frame(tmp_path / "in", np.full((8, 8, 3), 0.5))
    for sun in (1e5, 1e9):
        sky = np.full((64, 128, 3), 0.1, np.float32)
        sky[31, 96] = sun  # u = 0.75 on the horizon: toward the front-view camera
        light = hdri.downsample(sky)
        assert np.all(np.isfinite(light)) and light.max() > 1.0
        res = relight(toy, files, tmp_path / f"out{sun:g}", light[None])
        out = frames.read_exr(res.relit_files[0])
        assert np.all(np.isfinite(out)) and out.max() <= HALF_MAX
    assert out.max() == HALF_MAX and any("half-float range" in w for w in res.warnings)


@pytest.mark.filterwarnings("ignore:overflow encountered in cast")  # the overflow is the case
def test_hdri_that_overflows_or_has_bad_texels_is_a_clear_error():
    sky = np.full((32, 64, 3), 1.0, np.float32)
    sky[:, :] = 3e38  # every texel near float32's maximum: the cell means overflow
    with pytest.raises(LightingError, match="too bright"):
        hdri.downsample(sky, strength=10.0)
    bad = np.ones((32, 64, 3), np.float32)
    bad[3, 3] = -1.0
    bad[4, 4] = np.inf
    with pytest.raises(LightingError, match="Repair HDRI"):
        hdri.downsample(bad)


def test_lamps_far_away_or_dark_are_finite_through_the_pipeline(toy, tmp_path):
    """A lamp 1e12 radii away or at 0 W gives a finite, non-negative light; alone it leaves the
    subject black, which a run refuses; beside a faint fill it changes nothing visible."""
    files = one_frame(tmp_path / "in", np.full((8, 8, 3), 0.5))
    far = lamps.lamp_to_light(lamps.Lamp("POINT", (0.0, 0.0, 1e12), (0, 0, -1), (1, 1, 1), 1e3),
                              1.0)
    zero = lamps.lamp_to_light(lamps.Lamp("SUN", (0, 0, 5), (0, 0, -1), (1, 1, 1), 0.0), 1.0)
    for light in (far, zero):
        assert np.all(np.isfinite(light)) and light.min() >= 0 and lightvec.is_black(light)
        with pytest.raises(LightingError, match="lighting is black"):
            relight(toy, files, tmp_path / "alone", light[None])
    fill = lightvec.uniform(1e-3)
    res = relight(toy, files, tmp_path / "out", np.stack([far + zero + fill]))
    out = frames.read_exr(res.relit_files[0])
    ref = frames.read_exr(relight(toy, files, tmp_path / "ref", fill[None]).relit_files[0])
    assert np.all(np.isfinite(out)) and out.max() > 0
    np.testing.assert_array_equal(out, ref)
    with pytest.raises(LightingError, match="inside the subject"):
        lamps.lamp_to_light(lamps.Lamp("POINT", (0, 0, 0), (0, 0, -1), (1, 1, 1), 10.0), 1.0)


# ---- never overwrite without being asked --------------------------------------------------

def _stamp(folder) -> dict:
    return {p.name: (p.stat().st_mtime_ns, p.read_bytes()) for p in sorted(folder.rglob("*"))
            if p.is_file()}


def test_identical_rerun_changes_nothing(toy, tmp_path):
    files = write_exr_sequence(tmp_path / "in", [np.full((8, 8, 3), v, np.float32)
                                                 for v in (0.2, 0.4, 0.6)])
    relight(toy, files, tmp_path / "out")
    before = _stamp(tmp_path / "out")
    res = relight(toy, files, tmp_path / "out")
    assert res.written == 0 and res.resumed == 3
    assert _stamp(tmp_path / "out") == before


def test_overwrite_never_reaches_source_footage(toy, tmp_path):
    """Footage that lives where the run would write (even through a symlink, even with
    overwrite on) is refused before anything is written or deleted."""
    lin = [colour.to_linear(f, colour.lookup("sRGB")) for f in ramp_frames(2, 8, 8)]
    src = write_exr_sequence(tmp_path / "out" / "relit", lin, prefix="relit_", start=0)
    before = _stamp(tmp_path / "out")
    with pytest.raises(OutputError, match="source footage"):
        relight(toy, src, tmp_path / "out", overwrite=True)
    assert _stamp(tmp_path / "out") == before
    plates = write_exr_sequence(tmp_path / "plates", lin)
    (tmp_path / "linked").mkdir()
    os.symlink(tmp_path / "plates", tmp_path / "linked" / "relit")
    before = _stamp(tmp_path / "plates")
    with pytest.raises(OutputError, match="source footage"):
        relight(toy, plates, tmp_path / "linked", overwrite=True)
    assert _stamp(tmp_path / "plates") == before


def test_output_in_the_footage_folder_leaves_the_footage_alone(toy, tmp_path):
    files = write_exr_sequence(tmp_path / "shot", [np.full((8, 8, 3), 0.3, np.float32)] * 2)
    before = {f: pathlib.Path(f).read_bytes() for f in files}
    res = relight(toy, files, tmp_path / "shot")
    assert res.written == 2
    assert {f: pathlib.Path(f).read_bytes() for f in files} == before


def test_a_corrupt_run_record_is_another_run(toy, tmp_path):
    files = one_frame(tmp_path / "in", np.full((8, 8, 3), 0.3))
    relight(toy, files, tmp_path / "out")
    (tmp_path / "out" / pipeline.RUN_FILE).write_text("{not json")
    before = _stamp(tmp_path / "out" / "relit")
    with pytest.raises(OutputError, match="already holds"):
        relight(toy, files, tmp_path / "out")
    assert _stamp(tmp_path / "out" / "relit") == before


# ---- the catalogue names only tests that exist --------------------------------------------

TEST_REF = re.compile(r"`(tests/[\w/]+\.py)::(\w+)`")


def catalogue_rows() -> list[tuple[str, str, list[tuple[str, str]]]]:
    """(case, expectation, [(file, test)]) for each row of the table in HARD_CASES.md."""
    rows = []
    for line in CATALOGUE.read_text(encoding="utf-8").splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) != 4 or cells[0] in ("#", "") or set(cells[0]) <= set("-: "):
            continue
        rows.append((cells[1], cells[2], TEST_REF.findall(cells[3])))
    return rows


def test_catalogue_names_only_tests_that_exist():
    rows = catalogue_rows()
    assert len(rows) >= 30
    missing = []
    for case, expectation, refs in rows:
        assert refs, f"catalogue row '{case}' names no test"
        assert expectation, f"catalogue row '{case}' states no expectation"
        for path, name in refs:
            text = (ROOT / path).read_text(encoding="utf-8") if (ROOT / path).is_file() else ""
            if not re.search(rf"^\s*def {name}\(", text, re.M):
                missing.append(f"{path}::{name}")
    assert not missing, f"HARD_CASES.md names tests that do not exist: {missing}"


def test_catalogue_covers_the_design_list():
    text = CATALOGUE.read_text(encoding="utf-8").lower()
    for word in ("black", "white", "saturated", "nan", "1x1", "4k", "8k", "1e5", "all-zero",
                 "zero energy", "inside the unit sphere", "centre", "huge distance", "fp16",
                 "missing", "corrupt", "cancel", "existing output", "very coloured",
                 "twice the light", "source footage"):
        assert word in text, f"HARD_CASES.md does not mention '{word}'"
