"""bench/frontier.py's pieces: the Pareto frontier, the plot, and the network group end to end on
the toy model (the whole harness, Cycles included, runs in
tests/blender/test_frontier_harness.py)."""

import json
import time

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from PIL import Image

from bench import frontier
from tests.onnx_fixtures import write_toy_model
from training.eval import report


def read_rgb(path) -> np.ndarray:
    """A PNG as (H, W, 3) uint8 (decoded by Pillow, independently of matplotlib's writer)."""
    with Image.open(path) as im:
        return np.asarray(im.convert("RGB"))


def colour_pixels(img: np.ndarray, hex_colour: str, tol: int = 8) -> int:
    """How many pixels are within ``tol`` (per channel, 0-255) of ``hex_colour``."""
    rgb = np.array([int(hex_colour[i:i + 2], 16) for i in (1, 3, 5)])
    return int((np.abs(img.astype(int) - rgb) <= tol).all(-1).sum())


def _rows(points):
    return [frontier.Row("network", "k", f"p{i}", e, t) for i, (t, e) in enumerate(points)]


@settings(max_examples=50, deadline=None)
@given(st.lists(st.tuples(st.floats(0.1, 1e4), st.floats(0.0, 1.0)), min_size=1, max_size=12))
def test_frontier_is_exactly_the_undominated_points(points):
    rows = _rows(points)
    frontier.mark_frontier(rows)
    front = [r for r in rows if r.frontier]
    assert front, "the fastest of the most accurate points is always on the frontier"
    for r in rows:
        dominated = any(o.ms <= r.ms and o.error <= r.error and (o.ms < r.ms or o.error < r.error)
                        for o in rows)
        assert r.frontier == (not dominated)
    # along the frontier, more time buys less error
    front.sort(key=lambda r: (r.ms, r.error))
    assert all(b.error <= a.error for a, b in zip(front, front[1:]))


def test_frontier_ignores_rows_without_an_error_and_keeps_groups_apart():
    rows = _rows([(1.0, 0.5), (10.0, 0.1)]) + [
        frontier.Row("network", "untrained", "u", None, 0.01),
        frontier.Row("light stage", "effects", "e", 0.9, 100.0)]
    frontier.mark_frontier(rows)
    assert [r.frontier for r in rows] == [True, True, False, True]


def test_each_hdri_has_its_own_conversion_frontier():
    rows = [frontier.Row("lighting conversion", m, f"{m} {w}", e, t)
            for m, w, e, t in (("a", 128, 0.01, 1.0), ("a", 512, 0.008, 5.0),
                               ("b", 128, 0.03, 10.0), ("b", 512, 0.02, 30.0))]
    frontier.mark_frontier(rows)
    assert all(r.frontier for r in rows)  # across maps, "a" would hide every point of "b"


def test_network_frames_come_back_in_the_pipelines_units(tmp_path):
    """The benchmark runs the pipeline's own stages, so the network's output comes back to
    scene linear by the light's k exactly as in a real run (the toy: light 2 doubles)."""
    from addon import detail, engine, lightvec

    card = engine.load_card(write_toy_model(tmp_path))
    made = frontier.card_for(card.onnx_path, card.stride, 64, "toy", "toy", card.classes)
    x = np.random.default_rng(0).random((3, 24, 40)).astype(np.float32)
    f = frontier.Frame(x, float(x.max()), 4.0, lightvec.uniform(2.0), None, None)
    fullres = detail.FullRes(threads=1)
    for c in (card, made):
        y = frontier.relight_frame(frontier.open_session(c, 1, frontier.CPU), f, 16, True,
                                   fullres).astype(np.float32)
        np.testing.assert_allclose(y, 2.0 * x, rtol=2e-3, atol=1e-4)


@pytest.fixture(scope="module")
def quick_run(shared_data, tmp_path_factory):
    """The harness on the toy model (as an installed model) without the Cycles part."""
    tmp = tmp_path_factory.mktemp("frontier")
    write_toy_model(tmp / "models")
    result = frontier.main(["--quick", "--models", str(tmp / "models"), "--out",
                            str(tmp / "results"), "--write-cards",
                            "--no-cache", "--skip", "conversion"])
    return tmp, result


def test_quick_run_measures_every_network_knob(quick_run):
    tmp, result = quick_run
    rows = result["rows"]
    kinds = {r.kind for r in rows}
    assert {"preset x resolution", "detail transfer off", "precision",
            "untrained width/depth (time only)", "baseline", "effects"} <= kinds
    sizes = {r.settings["working"] for r in rows if r.kind == "preset x resolution"}
    assert sizes == {16, 32, 64}  # the quick sizes and full (the 64 px test set)
    for r in rows:
        if r.ms is not None:
            assert 0 < r.p10 <= r.ms <= r.p90 and r.runs >= 3
        if r.kind.startswith("untrained"):
            assert r.error is None and "time only" in r.note  # never presented as accuracy
    toy = [r for r in rows if r.kind == "preset x resolution"]
    assert all(0 < r.error < 1 for r in toy)
    precisions = {r.settings["precision"]: r for r in rows if r.kind == "precision"}
    assert 0 < precisions["fp16"].error < 1 and precisions["fp16"].ms > 0
    assert precisions["int8"].ms is None and "no convolution" in precisions["int8"].note
    untrained = {r.settings["precision"] for r in rows if r.kind.startswith("untrained")}
    assert untrained == {"fp32", "int8", "fp16"}
    assert any(r.frontier for r in rows if r.group == "network")


def test_quick_run_writes_table_plot_and_card(quick_run):
    tmp, result = quick_run
    md = (tmp / "results" / "frontier.md").read_text()
    m = result["info"]["machine"]
    assert m["cpu"] in md and f"{m['cores']} cores" in md and m["date"] in md
    assert "| preset x resolution | toy fp32 16 |" in md
    png = read_rgb(tmp / "results" / "frontier.png")
    panels = {r.group for r in result["rows"] if r.error is not None and r.ms
              and r.group != "reference"}
    assert panels == {"network", "light stage"}  # --skip conversion; the baselines take no time
    w, h = report.PANEL_PIXELS
    assert png.shape == (h, w * len(panels), 3)
    assert colour_pixels(png, report.HIGHLIGHT) > 50  # the frontier's line and rings
    assert colour_pixels(png, "#1f77b4") > 20  # the first knob's points (tab10's blue)
    assert (png == 255).all(-1).mean() > 0.5  # mostly white: a plot, not noise
    data = json.loads((tmp / "results" / "frontier.json").read_text())
    assert len(data["rows"]) == len(result["rows"])
    assert "toy fp32 full" in md
    card = json.loads((tmp / "models" / "toy.json").read_text())
    front = card["frontier"]
    assert front["working_size"] == 64 and front["ms_per_frame"] > 0 and 0 < front["rmse"] < 1
    assert card["metrics"] == {} and "per_size" not in card["cost"]  # other keys untouched
    assert result["cards"] == [str(tmp / "models" / "toy.json")]


def test_interleaved_timing_warms_up_then_goes_round_robin():
    """Every setting is warmed up, then each round runs every setting once (order shuffled with
    a fixed seed), so no setting pays the session's start-up cost alone."""
    def settings_and_calls():
        calls, started = [], set()

        def setting(i):
            def run(r):
                calls.append((i, r))
                if i not in started:  # the first call of each setting is slow (a cold start)
                    started.add(i)
                    time.sleep(0.2)
            return run
        return [setting(i) for i in range(3)], calls

    fns, calls = settings_and_calls()
    out = frontier.interleaved_times(fns, repeats=4, warmup=2, seed=7, rewarm=False)
    rounds = [calls[k:k + 3] for k in range(0, len(calls), 3)]
    assert len(rounds) == 6
    for n, rnd in enumerate(rounds):
        assert sorted(i for i, _ in rnd) == [0, 1, 2] and {r for _, r in rnd} == {n - 2}
    assert len({tuple(i for i, _ in rnd) for rnd in rounds}) > 1  # the order is shuffled
    assert all(s["runs"] == 4 and s["p90"] < 40 for s in out)  # the cold start is not timed
    fns, again = settings_and_calls()
    frontier.interleaved_times(fns, repeats=4, warmup=2, seed=7, rewarm=False)
    assert again == calls  # the same seed, the same order


def test_rewarm_times_each_run_right_after_a_run_of_the_same_setting():
    calls = []

    def setting(i):
        return lambda r: calls.append((i, r))

    out = frontier.interleaved_times([setting(i) for i in range(3)], repeats=2, warmup=1, seed=3)
    warm, timed = calls[:3], calls[3:]
    assert sorted(i for i, _ in warm) == [0, 1, 2]
    assert len(timed) == 2 * 3 * 2
    pairs = [timed[k:k + 2] for k in range(0, len(timed), 2)]
    assert all(a == b for a, b in pairs)  # the untimed re-warm, then the timed run
    assert all(s["runs"] == 2 for s in out)


def test_quick_run_without_a_research_folder_skips_the_trained_points(quick_run):
    """tmp/models/research does not exist: the group is absent, the table says why, the run
    goes on (and the untrained draft, which then has no trained point, is kept)."""
    tmp, result = quick_run
    assert not any(r.kind.startswith("width/depth (trained") for r in result["rows"])
    md = (tmp / "results" / "frontier.md").read_text()
    assert "not measured: trained width/depth point(s) ablation-full, width-narrow, width-deep" \
        in md


def _export_research_point(folder, name, steps, **overrides):
    """A tiny untrained draft-family network exported as training/run/export.py would a trained one:
    the ONNX file and a card from export.make_card, its recipe saying how it trained."""
    from training.run import export
    from training.model import network

    net = network.build("draft", **overrides).eval()
    path = export.export_onnx(net, folder / f"{name}.onnx")
    recipe = {"args": {"preset": "draft", "steps": steps, "ablation": "full"},
              "net": net.cfg.to_dict(), "exported_checkpoint": {"file": "best.pt", "step": 15}}
    export.write_card(export.make_card(name, "draft", path, net, {"recipe": recipe}, {}, {}, 32),
                      path)
    return net


@pytest.fixture(scope="module")
def research_run(shared_data, tmp_path_factory):
    from training.model import network

    tmp = tmp_path_factory.mktemp("frontier-research")
    write_toy_model(tmp / "models")
    nets = {"ablation-full": _export_research_point(tmp / "research", "ablation-full", 20),
            "width-narrow": _export_research_point(tmp / "research", "width-narrow", 20,
                                                   widths=(8, 12, 24, 32))}
    (tmp / "research" / "width-deep.onnx").write_bytes(b"not a model")  # and no card
    result = frontier.main(["--quick", "--models", str(tmp / "models"), "--research",
                            str(tmp / "research"), "--out", str(tmp / "results"), "--no-cache",
                            "--threads", "1", "--skip", "lightstage", "conversion"])
    params = {k: network.parameter_count(n) for k, n in nets.items()}
    return tmp, result, params


def test_research_points_are_measured_like_the_presets(research_run):
    tmp, result, params = research_run
    rows = {r.settings["model"]: r for r in result["rows"] if r.kind == frontier.TRAINED_KIND}
    assert set(rows) == {"ablation-full", "width-narrow"}  # width-deep is unusable: skipped
    for name, r in rows.items():
        assert 0 < r.error <= 1 and r.extra["psnr"] > 0  # held-out accuracy, not time only
        assert 0 < r.p10 <= r.ms <= r.p90 and r.runs == 3
        s = r.settings
        assert s["working"] == 32 and s["full"] == 64 and s["precision"] == "fp32"
        assert s["parameters"] == params[name] and s["gflop_at_working"] > 0
        assert s["training"]["step_budget"] == 20 and s["training"]["checkpoint_step"] == 15
        assert "trained 20 steps (best.pt at step 15)" in r.note
    narrow, full = rows["width-narrow"], rows["ablation-full"]
    assert narrow.settings["widths"] == [8, 12, 24, 32] and full.settings["blocks"] == [1, 1, 1, 1]
    assert narrow.settings["gflop_at_working"] < full.settings["gflop_at_working"]
    md = (tmp / "results" / "frontier.md").read_text()
    assert f"| {frontier.TRAINED_KIND} | width-narrow fp32 32 |" in md
    assert "not measured: trained width/depth point(s) width-deep (model or card unusable" in md


def test_untrained_rows_only_for_configs_without_a_trained_point(research_run):
    """The quick untrained point is the Draft config, which ablation-full trained: not repeated
    as a time-only row."""
    _, result, _ = research_run
    assert not any(r.kind.startswith("untrained") for r in result["rows"])
    assert {r.kind for r in result["rows"]} >= {"preset x resolution", frontier.TRAINED_KIND}


def test_variant_labels_become_flat_file_names():
    # "standard narrow (widths/2)" once made the int8 export write into a missing sub-folder
    stem = frontier.file_stem("standard narrow (widths/2)")
    assert "/" not in stem and " " not in stem and stem.startswith("standard_narrow")
