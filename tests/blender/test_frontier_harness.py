"""bench/frontier.py end to end with its Cycles part (bench/light_conversion.py), on the toy model
installed as a model; the panel then shows the figures the harness wrote into the card."""

import json

import pytest

from conftest import load_extension


@pytest.fixture(scope="module")
def run(shared_data, tmp_path_factory):
    from onnx_fixtures import write_toy_model

    from bench import frontier

    tmp = tmp_path_factory.mktemp("frontier")
    write_toy_model(tmp / "models")
    result = frontier.main(["--quick", "--models", str(tmp / "models"), "--out",
                            str(tmp / "results"), "--write-cards", "--no-cache",
                            "--skip", "untrained", "lightstage"])
    return tmp, result


def test_conversion_rows_have_referee_error_and_timing(run):
    _, result = run
    rows = [r for r in result["rows"] if r.group == "lighting conversion"]
    assert [r.settings["hdri_width"] for r in rows] == [128, 256]
    for r in rows:
        assert 0 < r.error < 0.1  # the synthetic sky against Cycles (bench/light_conversion.py)
        assert 0 < r.p10 <= r.ms <= r.p90 and r.runs == 3
    assert any(r.frontier for r in rows)


def test_panel_shows_the_frontier_figures_of_the_card(run):
    tmp, _ = run
    load_extension()
    from portrait_relight.ops import bridge

    (card,) = bridge.model_cards(tmp / "models")
    front = json.loads((tmp / "models" / "toy.json").read_text())["frontier"]
    assert card.ms_per_frame == front["ms_per_frame"]
    assert card.held_out_error == (front["rmse"], "RMSE")
    assert card.summary.startswith(f"{front['ms_per_frame']:.0f} ms/frame (64 px, CPU), "
                                   "held-out RMSE")
