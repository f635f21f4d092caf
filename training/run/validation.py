"""Validation during a run and its curve: val metrics of the model and both baselines on held-out
identities (training/eval/evaluate.py's), never the test set."""

from __future__ import annotations

import json
import pathlib

import numpy as np

from ..eval import evaluate, predictors
from ..data.dataset import make_dataset

VAL_SEED = 777  # val samples (held-out identities) for the curves logged during training


def validation_samples(resolution: int, n: int) -> list:
    """The first n samples of the val split (held-out identities, rendered once, kept in memory)."""
    if n <= 0:
        return []
    ds = make_dataset("val", resolution, VAL_SEED)
    return [ds[i] for i in range(n)]


def validate(net, samples) -> dict:
    """Val RMSE / PSNR / SSIM of the model and both baselines (training.eval.evaluate's metrics)."""
    was_training = net.training
    net.eval()
    try:
        res = evaluate.evaluate(predictors.torch_predictor(net), samples)
    finally:
        net.train(was_training)
    return {name: {k: round(v, 4) for k, v in res[name].items()}
            for name in ("model", "identity", "irradiance_ratio")}


def curve(run) -> str:
    """A run's log as a markdown table: val metrics of the model and both baselines over time,
    the model's shading correlation, and the mean training loss terms since the previous val row
    ("-" for a term the run did not train)."""
    rows = [json.loads(line) for line in open(pathlib.Path(run) / "log.jsonl")]
    terms = ("basic", "latent", "parsing", "temporal", "transport", "adv")
    out = ["| step | min | model RMSE / PSNR / SSIM | shading corr | identity | irradiance ratio | "
           + " | ".join(terms) + " |", "|" + "---|" * (6 + len(terms))]
    pending = []
    for r in rows:
        if "val" not in r:
            pending.append(r)
            continue
        v = r["val"]
        cell = lambda m: f"{m['rmse']:.4f} / {m['psnr']:.2f} / {m['ssim']:.3f}"  # noqa: E731
        means = [f"{np.mean([p[k] for p in pending if k in p]):.3f}"
                 if any(k in p for p in pending) else "-" for k in terms]
        corr = v["model"].get("shading_corr")
        out.append(f"| {r['step']} | {r['minutes']} | {cell(v['model'])} | "
                   f"{'-' if corr is None else f'{corr:.3f}'} | {cell(v['identity'])} | "
                   f"{cell(v['irradiance_ratio'])} | " + " | ".join(means) + " |")
        pending = []
    return "\n".join(out)
