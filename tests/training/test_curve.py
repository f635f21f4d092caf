"""training.run.train --curve: a run's log as a table, every loss term it trained, '-' for the
rest."""

import json

from training.run import validation


def test_curve_lists_val_rows_with_the_mean_terms_since_the_last_one(tmp_path):
    m = {"rmse": 0.1, "psnr": 20.0, "ssim": 0.85}
    rows = [{"val": {"model": {**m, "shading_corr": 0.5}, "identity": m, "irradiance_ratio": m},
             "step": 0, "minutes": 0.0},
            {"basic": 0.4, "transport": 0.2, "step": 1, "minutes": 0.1},
            {"basic": 0.2, "transport": 0.4, "step": 2, "minutes": 0.2},
            {"val": {"model": m, "identity": m, "irradiance_ratio": m}, "step": 2, "minutes": 0.2}]
    (tmp_path / "log.jsonl").write_text("\n".join(json.dumps(r) for r in rows))
    table = validation.curve(tmp_path).splitlines()
    head = [c.strip() for c in table[0].strip("|").split("|")]
    assert head[-6:] == ["basic", "latent", "parsing", "temporal", "transport", "adv"]
    first = [c.strip() for c in table[2].strip("|").split("|")]
    second = [c.strip() for c in table[3].strip("|").split("|")]
    assert first[3] == "0.500" and second[3] == "-"  # shading corr where logged
    assert second[-6:] == ["0.300", "-", "-", "-", "0.300", "-"]
    assert len(table) == 4
