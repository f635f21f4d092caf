"""The paper's ablation table (its Table 2) on our held-out synthetic test set.

    .venv/bin/python -m training.eval.ablation                  # models/research/ablation-*.onnx
    .venv/bin/python -m training.eval.ablation --out bench/results  # also ablation.md, .json

Each variant is one training run of the Draft network with one part of the method switched off
(training/model/losses.py Switches.ablation; ``--steps`` budget, so every run saw the same number of
steps whatever the machine's load), exported with training/run/export.py into models/research/.
"full" is the shipped Draft's recipe: the paper's losses plus the transport supervision of the ratio
head (``--transport-loss``), without which the network did not learn the light's direction; "w/o
transport supervision" is therefore the paper's own full recipe. Rows: full, w/o structure, w/o
temporal, w/o parsing, w/o sampling, w/o transport supervision, then the two baselines (output =
input; input scaled by the ratio of total irradiance, which is given the true source light).
``shading corr`` and ``lateral response`` say whether the light acts where it should
(training/eval/evaluate.py; both baselines change the whole image alike, so their lateral response
is 1). Metrics are training/eval/evaluate.py's (portrait region, values normalised to [0, 1]), on
the fixed test set of training/data/make_testset.py.

Besides the means, each variant's RMSE difference to the full model is given with its paired
standard error over the test samples: that is the test set's sampling noise only. Each variant is
one seed, so the training noise (seed to seed) is not in it, and differences of the size of the
checkpoint-to-checkpoint wobble of the val curves (``python -m training.run.train --curve RUN``) say
nothing.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import time

from . import evaluate, metrics, predictors

ROOT = pathlib.Path(__file__).resolve().parents[2]
VARIANTS = ("full", "no_structure", "no_temporal", "no_parsing", "no_sampling", "no_transport")
LABELS = {"full": "full (ours)", "no_structure": "w/o structure", "no_temporal": "w/o temporal",
          "no_parsing": "w/o parsing", "no_sampling": "w/o sampling",
          "no_transport": "w/o transport supervision (= the paper's full recipe)"}
PAPER = {"full": (0.0349, 30.6110, 0.9584), "no_temporal": (0.0404, 28.6403, 0.9510),
         "no_parsing": (0.0680, 23.6189, 0.9170), "no_sampling": (0.0616, 24.5142, 0.9223),
         "no_structure": (0.0549, 25.5496, 0.9021)}  # the paper's "w/o content" row


def model_paths(folder) -> dict:
    folder = pathlib.Path(folder)
    return {v: folder / f"ablation-{v}.onnx" for v in VARIANTS
            if (folder / f"ablation-{v}.onnx").is_file()}


def run(paths: dict, dataset, n: int, threads: int) -> dict:
    """Per-variant metrics and per-sample rows; the baselines come with the first variant."""
    out, baselines = {}, None
    for name, path in paths.items():
        predict, card = predictors.onnx_file_predictor(path, threads)
        res = evaluate.evaluate(predict, dataset, n, baselines=baselines is None, per_sample=True)
        rows = res.pop("per_sample")
        if baselines is None:
            baselines = {k: {"mean": res[k], "rows": rows[k]}
                         for k in ("identity", "irradiance_ratio")}
        recipe = card.get("training", {}).get("recipe", {})
        out[name] = {"mean": res["model"], "rows": rows["model"], "onnx": str(path),
                     "lateral_response": evaluate.lateral_response(predict, dataset),
                     "steps": recipe.get("steps"),
                     "exported_step": recipe.get("exported_checkpoint", {}).get("step"),
                     "command": recipe.get("command")}
    return {"variants": out, "baselines": baselines or {}}


paired = metrics.paired_difference  # mean of b - a over the same samples, its standard error


def table(result: dict) -> str:
    v, base = result["variants"], result["baselines"]
    lines = ["| variant | RMSE | PSNR dB | SSIM | shading corr | lateral response | "
             "RMSE - full (± s.e.) | steps (exported) | paper RMSE / PSNR / SSIM |",
             "|---|---|---|---|---|---|---|---|---|"]
    corr = lambda m: f"{m['shading_corr']:.3f}" if "shading_corr" in m else ""  # noqa: E731
    full = v.get("full")
    for name in VARIANTS:
        if name not in v:
            continue
        m = v[name]["mean"]
        diff = "" if full is None or name == "full" else \
            "{:+.4f} ± {:.4f}".format(*paired(full["rows"], v[name]["rows"]))
        paper = "{:.4f} / {:.2f} / {:.4f}".format(*PAPER[name]) if name in PAPER else ""
        lines.append(f"| {LABELS[name]} | {m['rmse']:.4f} | {m['psnr']:.2f} | {m['ssim']:.3f} | "
                     f"{corr(m)} | {v[name]['lateral_response']:.1f} | {diff} | "
                     f"{v[name]['steps']} ({v[name]['exported_step']}) | "
                     f"{paper} |")
    for key, label in (("identity", "output = input"),
                       ("irradiance_ratio", "irradiance ratio (true source light)")):
        if key in base:
            m = base[key]["mean"]
            diff = "" if full is None else \
                "{:+.4f} ± {:.4f}".format(*paired(full["rows"], base[key]["rows"]))
            lines.append(f"| {label} | {m['rmse']:.4f} | {m['psnr']:.2f} | {m['ssim']:.3f} | "
                         f"{corr(m)} | 1.0 | {diff} | | |")
    return "\n".join(lines)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--models", default=str(ROOT / "models" / "research"),
                   help="folder with ablation-<variant>.onnx and their cards")
    p.add_argument("--n", type=int, default=64, help="test samples (the fixed set holds 64)")
    p.add_argument("--resolution", type=int, default=128)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--out", help="folder for ablation.md and ablation.json")
    a = p.parse_args(argv)
    paths = model_paths(a.models)
    if not paths:
        raise SystemExit(f"No ablation-<variant>.onnx in {a.models}: train the variants and export "
                         "them (see models/README.md, 'Ablations').")
    t0 = time.perf_counter()
    ds = evaluate.heldout_dataset(a.resolution)
    result = run(paths, ds, a.n, a.threads)
    md = table(result)
    ident = evaluate.dataset_id(ds)
    head = (f"Held-out test set: {min(a.n, len(ds))} samples at {a.resolution} px "
            f"({json.dumps(ident)}); `python -m training.eval.ablation`, "
            f"{time.perf_counter() - t0:.0f} s.")
    print(head + "\n\n" + md)
    if a.out:
        out = pathlib.Path(a.out)
        out.mkdir(parents=True, exist_ok=True)
        (out / "ablation.md").write_text(head + "\n\n" + md + "\n")
        slim = {"dataset": ident, "samples": min(a.n, len(ds)),
                "variants": {k: {kk: vv for kk, vv in v.items() if kk != "rows"}
                             for k, v in result["variants"].items()},
                "baselines": {k: v["mean"] for k, v in result["baselines"].items()}}
        (out / "ablation.json").write_text(json.dumps(slim, indent=2))


if __name__ == "__main__":
    main()
