"""training/eval/ablation.py: the ablation table from exported variants, with paired differences."""

import json

import numpy as np
import pytest
import torch

import standin
from training.eval import ablation
from training.run import export
from training.model import network

torch.set_num_threads(1)
TINY = network.NetConfig(widths=(8, 8, 16, 16), blocks=(1, 1, 1, 1), expand=2, code=8,
                         light_embed=16)


def _export(folder, name, seed, recipe=None):
    net = standin.perturbed_net(TINY, seed)  # different weights per variant: metrics differ
    path = export.export_onnx(net, folder / f"ablation-{name}.onnx")
    card = {"stride": TINY.stride, "training": {"recipe": recipe or {}}}
    path.with_suffix(".json").write_text(json.dumps(card))
    return path


@pytest.fixture(scope="module")
def result(tmp_path_factory):
    folder = tmp_path_factory.mktemp("research")
    _export(folder, "full", 0, {"steps": 1500, "exported_checkpoint": {"step": 1200}})
    _export(folder, "no_temporal", 1)
    (folder / "unrelated.onnx").write_bytes(b"")  # not an ablation variant: ignored
    paths = ablation.model_paths(folder)
    assert list(paths) == ["full", "no_temporal"]
    return ablation.run(paths, standin.StandinDataset("test", 64, n=3), 3, threads=1)


def test_every_variant_and_both_baselines_are_measured(result):
    v, b = result["variants"], result["baselines"]
    assert set(v) == {"full", "no_temporal"} and set(b) == {"identity", "irradiance_ratio"}
    for rows in [v["full"]["rows"], v["no_temporal"]["rows"], b["identity"]["rows"]]:
        assert len(rows) == 3 and all(np.isfinite(r["rmse"]) for r in rows)
    assert v["full"]["steps"] == 1500 and v["full"]["exported_step"] == 1200
    # different weights give different errors: the table is not one model measured twice
    assert v["full"]["mean"]["rmse"] != v["no_temporal"]["mean"]["rmse"]


def test_paired_difference_is_the_difference_of_the_means(result):
    v = result["variants"]
    d, se = ablation.paired(v["full"]["rows"], v["no_temporal"]["rows"])
    assert d == pytest.approx(v["no_temporal"]["mean"]["rmse"] - v["full"]["mean"]["rmse"])
    assert se >= 0 and np.isfinite(se)
    assert ablation.paired(v["full"]["rows"], v["full"]["rows"]) == (0.0, 0.0)


def test_table_has_a_row_per_variant_and_baseline_with_the_papers_figures(result):
    md = ablation.table(result)
    lines = md.splitlines()
    assert len(lines) == 2 + 2 + 2  # header, rule, two variants, two baselines
    assert lines[2].startswith("| full (ours) |") and "0.0349" in lines[2]
    assert lines[3].startswith("| w/o temporal |") and "±" in lines[3]
    assert lines[4].startswith("| output = input |")


def test_a_folder_without_variants_says_what_to_do(tmp_path):
    with pytest.raises(SystemExit, match="train the variants"):
        ablation.main(["--models", str(tmp_path)])
