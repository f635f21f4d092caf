"""ONNX export round trip, int8 quantisation, the model card, and the card's metrics."""

import hashlib
import json

import numpy as np
import onnx
import pytest
import torch

import standin
from addon import contract
from training.eval import evaluate, metrics, predictors
from training.run import export
from training.model import network

torch.set_num_threads(1)
TINY = network.NetConfig(widths=(8, 8, 16, 16), blocks=(1, 1, 1, 1), expand=2, code=8,
                         light_embed=16)


@pytest.fixture(scope="module")
def net():
    return standin.perturbed_net(TINY, 0)


@pytest.fixture(scope="module")
def onnx_path(net, tmp_path_factory):
    return export.export_onnx(net, tmp_path_factory.mktemp("m") / "tiny.onnx")


def test_export_uses_contract_names_opset_and_dynamic_size(onnx_path):
    m = onnx.load(str(onnx_path))
    assert max(o.version for o in m.opset_import if o.domain in ("", "ai.onnx")) >= 17
    assert [i.name for i in m.graph.input] == [contract.INPUT_IMAGE, contract.INPUT_LIGHT]
    assert [o.name for o in m.graph.output] == [contract.OUTPUT_RELIT,
                                                contract.OUTPUT_SOURCE_LIGHT,
                                                contract.OUTPUT_PARSING]
    dims = m.graph.input[0].type.tensor_type.shape.dim
    assert dims[2].dim_param and dims[3].dim_param  # H and W are symbolic


def test_onnx_matches_torch_within_the_stated_tolerance(net, onnx_path):
    report = export.verify(net, onnx_path, sizes=((32, 32), (64, 96)))
    assert report["max_abs_diff"][contract.OUTPUT_RELIT] <= export.TOLERANCE["atol"] * 10


def test_verify_catches_a_model_that_differs(net, onnx_path):
    other = network.RelightNet(TINY).eval()  # fresh weights: not what was exported
    with pytest.raises(AssertionError, match="differs"):
        export.verify(other, onnx_path, sizes=((32, 32),))


def test_card_has_every_required_key_and_the_file_checksum(net, onnx_path):
    cost = export.measure_cost(onnx_path, sizes=(32,), threads=1, repeats=2)
    card = export.make_card("tiny", "draft", onnx_path, net, {"recipe": {}},
                            {"model": {"rmse": 0.1}}, {"cpu": cost}, working_size=64)
    assert set(contract.REQUIRED_CARD_KEYS) <= set(card)
    assert card["sha256"] == hashlib.sha256(onnx_path.read_bytes()).hexdigest()
    assert card["stride"] == TINY.stride
    assert card["classes"][0] == contract.FOREGROUND_CLASS
    assert cost["per_size"]["32"]["ms"] > 0
    path = export.write_card(card, onnx_path)
    assert json.loads(path.read_text())["onnx"] == "tiny.onnx"
    engine = pytest.importorskip("addon.engine")
    loaded = engine.load_card(onnx_path)  # the engine accepts what export writes
    assert loaded.stride == TINY.stride and loaded.sha256 == card["sha256"]


def test_int8_quantisation_stays_close_to_fp32(net, onnx_path, tmp_path):
    feeds = export.calibration_feeds([standin.sample(64, i) for i in range(4)], TINY.stride)
    q = export.quantize_int8(onnx_path, tmp_path / "tiny-int8.onnx", feeds)
    ops = {n.op_type for n in onnx.load(str(q)).graph.node}
    assert "QuantizeLinear" in ops and "DequantizeLinear" in ops
    a = export.session(onnx_path).run(None, feeds[0])[0]
    b = export.session(q).run(None, feeds[0])[0]
    assert np.abs(a - b).mean() < 0.05 * np.abs(a).mean()


# ---- held-out metrics (training/eval/evaluate.py)

def test_metrics_of_a_perfect_prediction():
    s = standin.sample(48, 0)
    mask = s["mask_t"][0] > 0.5
    m = metrics.image_metrics(s["gt_t_k"], s["gt_t_k"], mask)
    assert m["rmse"] == 0.0 and m["psnr"] >= 199 and m["ssim"] == pytest.approx(1.0)


def test_metrics_only_see_the_portrait_region():
    s = standin.sample(48, 0)
    mask = s["mask_t"][0] > 0.5
    pred = s["gt_t_k"].copy()
    pred[:, ~mask] = 100.0  # garbage outside the portrait
    assert metrics.image_metrics(pred, s["gt_t_k"], mask)["rmse"] == 0.0
    pred = s["gt_t_k"] * 0.5
    worse = metrics.image_metrics(pred, s["gt_t_k"], mask)
    assert 0.05 < worse["rmse"] < 1 and worse["ssim"] < 1


def test_irradiance_ratio_baseline_is_exact_for_a_scaled_light():
    s = standin.sample(48, 0)
    s["light_k"] = s["light_i"] * 3.0
    s["gt_t_k"] = s["img_t_i"] * 3.0
    mask = s["mask_t"][0] > 0.5
    m = metrics.image_metrics(metrics.baseline_irradiance_ratio(s), s["gt_t_k"], mask)
    assert m["rmse"] < 1e-6
    assert metrics.image_metrics(metrics.baseline_identity(s), s["gt_t_k"], mask)["rmse"] > 0.1


def test_evaluate_runs_onnx_and_torch_predictors_alike(net, onnx_path):
    ds = standin.StandinDataset(resolution=64, n=2)
    a = evaluate.evaluate(predictors.onnx_predictor(export.session(onnx_path), TINY.stride), ds)
    b = evaluate.evaluate(predictors.torch_predictor(net), ds, baselines=False)
    assert a["samples"] == 2 and set(a) >= {"model", "identity", "irradiance_ratio"}
    assert a["model"]["rmse"] == pytest.approx(b["model"]["rmse"], abs=1e-4)
    assert 0 <= a["model"]["foreground_iou"] <= 1


def test_the_true_source_diagnostic_feeds_the_decoder_the_sample_light():
    """evaluate --true-source: the decoder gets the sample's light; given the encoder's own
    estimate as the sample's light it reproduces the plain prediction."""
    import dataclasses

    net = standin.perturbed_net(dataclasses.replace(TINY, relight="ratio"), 0)
    s = standin.sample(32, 0)
    plain, extras = predictors.torch_predictor(net)(s)
    echoed, _ = predictors.torch_predictor(net, true_source=True)(
        {**s, "light_i": extras["source_light"]})
    assert np.allclose(echoed, plain, rtol=1e-4, atol=1e-6)
    other, _ = predictors.torch_predictor(net, true_source=True)(
        {**s, "light_i": extras["source_light"] * np.array([2.0, 1.0, 0.5], np.float32)})
    assert np.isfinite(other).all() and not np.allclose(other, plain, rtol=1e-3)


def test_empty_mask_is_refused():
    s = standin.sample(32, 0)
    with pytest.raises(ValueError, match="empty"):
        metrics.image_metrics(s["gt_t_k"], s["gt_t_k"], np.zeros((32, 32), bool))


def test_every_resize_in_the_graph_is_bilinear(onnx_path):
    """Nearest up-sampling in the decoder left 8-pixel blocks in the first Draft's relit images
    (the 1/32 features copied, never smoothed by the skips); every resize must interpolate."""
    modes = [a.s for n in onnx.load(str(onnx_path)).graph.node if n.op_type == "Resize"
             for a in n.attribute if a.name == "mode"]
    assert modes and all(m == b"linear" for m in modes)


def test_shading_correlation_scores_the_spatial_pattern_of_the_change():
    s = standin.sample(32, seed=3)
    mask = s["mask_t"][0] > 0.5
    inp = s["img_t_i"]
    yy, xx = np.mgrid[0:32, 0:32] / 32.0
    shade = (0.3 + xx)[None].astype(np.float32)           # light from the right
    gt = inp * shade
    assert metrics.shading_correlation(gt * 1.7, inp, gt, mask) == pytest.approx(1.0)   # level free
    assert metrics.shading_correlation(inp / shade, inp, gt, mask) == pytest.approx(-1.0, abs=0.02)
    assert metrics.shading_correlation(inp * 2.0, inp, gt, mask) == 0.0  # a global change
    assert metrics.shading_correlation(inp, inp, gt, mask) == 0.0        # no change
    other = inp * (0.3 + yy)[None].astype(np.float32)     # light from below: unrelated pattern
    assert abs(metrics.shading_correlation(other, inp, gt, mask)) < 0.3


def test_lateral_response_tells_a_light_blind_model_from_one_that_follows_the_lamp():
    ds = standin.StandinDataset("test", 32, n=3)
    xx = np.mgrid[0:32, 0:32][1] / 31.0

    def follows(s):  # brighter on the side the lamp's energy is (light vector columns < 8: left)
        light = np.asarray(s["light_k"])
        side = light[:, 8:].sum() - light[:, :8].sum()   # > 0: the lamp is on the right
        shade = 1.0 + 2.0 * (xx if side > 0 else 1.0 - xx)
        return s["img_t_i"] * shade[None], {}

    def blind(s):
        return s["img_t_i"] * 3.0, {}

    assert evaluate.lateral_response(blind, ds) == pytest.approx(1.0)
    assert evaluate.lateral_response(follows, ds) > 1.5


def test_error_breakdown_splits_the_error_by_region_and_level():
    """training.eval.evaluate.error_breakdown: a prediction off by one colour gain everywhere has
    all its error in level (the fit removes it); a patch of wrong pixels puts its error in its
    class."""
    rng = np.random.default_rng(0)
    h = w = 24
    mask = np.zeros((h, w), bool)
    mask[4:20, 4:20] = True
    parsing = np.zeros((9, h, w), np.float32)
    parsing[0] = mask
    parsing[1] = mask  # skin ...
    parsing[1, 4:10] = 0
    parsing[2, 4:10] = mask[4:10]  # ... and hair on top
    gt = rng.uniform(0.2, 1.0, (3, h, w)).astype(np.float32)
    sample = {"mask_t": mask[None].astype(np.float32), "gt_t_k": gt, "parsing_t": parsing}
    ds = [sample, sample]
    exact = evaluate.error_breakdown(lambda s: (s["gt_t_k"], {}), ds)
    assert exact["rmse_pooled"] == 0.0 and exact["level_fit_rmse"] == 0.0
    tinted = evaluate.error_breakdown(
        lambda s: (s["gt_t_k"] * np.array([1.3, 0.8, 1.1], np.float32)[:, None, None], {}), ds)
    assert tinted["rmse_pooled"] > 0.05 and tinted["level_fit_rmse"] < 1e-6
    # the fit's gain is 1 / tint: brightness and colour split in log space, no spread (a bias)
    g = -np.log([1.3, 0.8, 1.1])
    level = tinted["level_gain"]
    assert level["log_brightness_mean"] == pytest.approx(g.mean(), abs=1e-6)
    assert level["log_colour_mean"] == pytest.approx(g - g.mean(), abs=1e-6)
    assert level["log_brightness_sd"] < 1e-6 and max(level["log_colour_sd"]) < 1e-6
    assert exact["level_gain"]["log_brightness_mean"] == pytest.approx(0.0, abs=1e-9)
    shares = tinted["regions"]
    assert abs(shares["skin"]["pixel_share"] + shares["hair"]["pixel_share"] - 1.0) < 1e-9
    assert abs(shares["skin"]["pixel_share"] - 10 / 16) < 1e-9

    def hair_wrong(s):
        p = s["gt_t_k"].copy()
        p[:, 6:9, 8:12] = 0.0  # inside the hair, away from the outline
        return p, {}
    bad = evaluate.error_breakdown(hair_wrong, ds)["regions"]
    assert bad["hair"]["error_share"] == 1.0 and bad["skin"]["error_share"] == 0.0
    assert bad["edge (2 px)"]["error_share"] == 0.0
    assert abs(bad["edge (2 px)"]["pixel_share"] - (256 - 144) / 256) < 1e-9
    # after the level fit the tint leaves no error anywhere; the wrong patch's stays mostly in
    # the hair (the fit's gain, pulled by it, moves the skin a little), and the classes' shares
    # of what the fit leaves add up to all of it
    assert max(r["rmse_level_fit"] for r in shares.values()) < 1e-6
    assert bad["hair"]["rmse_level_fit"] > 5 * bad["skin"]["rmse_level_fit"]
    assert bad["hair"]["level_fit_share"] > 0.9
    assert sum(r["level_fit_share"] for k, r in bad.items() if not k.startswith("edge")) == \
        pytest.approx(1.0, abs=1e-9)


def test_level_fit_rmse_forgives_an_overall_level_and_tint_only():
    s = standin.sample(48, 0)
    mask = s["mask_t"][0] > 0.5
    gt = s["gt_t_k"]
    tinted = gt * np.array([1.4, 0.9, 0.7], np.float32)[:, None, None]
    assert metrics.image_metrics(tinted, gt, mask)["rmse"] > 0.03
    assert metrics.level_fit_rmse(tinted, gt, mask) < 1e-6
    flat = np.broadcast_to(gt[:, mask].mean(1)[:, None, None], gt.shape)  # no spatial pattern
    assert metrics.level_fit_rmse(flat, gt, mask) > 0.03


def test_update_card_rewrites_only_the_metrics_of_the_card_that_describes_the_file(tmp_path):
    """evaluate --update-card: re-measuring a shipped model (a new test set) replaces the card's
    metrics it measures and nothing else (an intrinsic card's buffer figures stay, and its
    indentation), and refuses a card written for another file or a missing card."""
    onnx_path = tmp_path / "m.onnx"
    onnx_path.write_bytes(b"model bytes")
    with pytest.raises(SystemExit, match="no card"):
        evaluate.update_card(onnx_path, {"rmse": 1})
    card = {"name": "m", "sha256": hashlib.sha256(b"model bytes").hexdigest(),
            "training": {"recipe": {"command": "x"}}, "metrics": {"rmse": 0.5}}
    (tmp_path / "m.json").write_text(json.dumps(card))
    evaluate.update_card(onnx_path, {"rmse": 0.25, "render_version": "v2"})
    assert json.loads((tmp_path / "m.json").read_text()) == {
        **card, "metrics": {"rmse": 0.25, "render_version": "v2"}}
    card["metrics"]["val_buffers"] = {"normal_deg": 11.0}
    (tmp_path / "m.json").write_text(json.dumps(card))
    evaluate.update_card(onnx_path, {"rmse": 0.2})
    assert json.loads((tmp_path / "m.json").read_text())["metrics"] == {
        "rmse": 0.2, "val_buffers": {"normal_deg": 11.0}}
    # A card keeps its own indentation, so its diff is the figures that changed.
    (tmp_path / "m.json").write_text(json.dumps(card, indent=1) + "\n")
    evaluate.update_card(onnx_path, {"rmse": 0.2})
    assert (tmp_path / "m.json").read_text() == json.dumps(
        {**card, "metrics": {"rmse": 0.2, "val_buffers": {"normal_deg": 11.0}}}, indent=1) + "\n"
    onnx_path.write_bytes(b"other bytes")
    with pytest.raises(SystemExit, match="sha256 differs"):
        evaluate.update_card(onnx_path, {"rmse": 0.1})


def test_paired_difference_is_the_mean_change_over_the_same_samples_with_its_error():
    a = [{"rmse": 0.1}, {"rmse": 0.2}, {"rmse": 0.3}]
    b = [{"rmse": 0.1}, {"rmse": 0.1}, {"rmse": 0.4}]
    d, se = metrics.paired_difference(a, b)
    assert d == pytest.approx(0.0)
    assert se == pytest.approx(np.std([0, -0.1, 0.1], ddof=1) / 3 ** 0.5)
    assert metrics.paired_difference(a, a) == (0.0, 0.0)
    with pytest.raises(SystemExit):  # --compare needs --onnx
        evaluate.main(["--run", "runs/x", "--compare", "m.onnx"])
