"""Which of a candidate network's buffers carry its gain or its loss: a model relit through the
product with some of its buffers taken from another network's (both networks run on every pass),
on the synthetic test set and on CroppedYale's tune subjects.

    .venv/bin/python -m training.eval.buffer_swap --onnx models/relight-portrait.onnx \\
        --other models/research/portrait-gpu.onnx [--swap normal --swap albedo,transfer ...]
        [--pairs 36] [--out bench/results/buffer_swap]

Each ``--swap`` (comma-separated fields of the network's output: normal, height, albedo,
transfer, parsing) is one variant; by default each field alone, albedo with transfer, and all
but the parsing. For every variant, and for the two models as they are: the synthetic test
set's ``rmse_level_fit`` (training/eval/evaluate.py's figure, through ``addon.relight_image``;
its held-out identities) and, with ``training.eval.yale --split tune``'s machinery, CroppedYale's
tune subjects: scale-invariant PSNR and the left/right and top/bottom balance correlations, each
variant's gain paired with ``--onnx``'s on the same pairs. The tune subjects are the ones
choices are made on; the test subjects stay unseen. A training diagnostic: a candidate whose
albedo helps real faces while its normals cost their up/down balance says which of its outputs
to keep training and which to hold. Writes ``<out>.md`` and ``<out>.json``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import pathlib
import sys

import numpy as np

from addon import contract, engine
from addon.errors import InputError

from . import evaluate, report, yale
from .predictors import product_predictor

ROOT = pathlib.Path(__file__).resolve().parents[2]
FIELDS = ("normal", "height", "albedo", "transfer", "parsing")
DEFAULT_SWAPS = (("normal",), ("height",), ("albedo",), ("transfer",), ("albedo", "transfer"),
                 ("normal", "height", "albedo", "transfer"))


class BuffersFrom(engine.IntrinsicSession):
    """An intrinsic model (``base``, an engine.IntrinsicSession) whose ``fields`` of every pass's
    output (engine.IntrinsicResult's) are another's (``other``), run on the same image; the card
    is the base's, named for the swap."""

    def __init__(self, base: engine.IntrinsicSession, other: engine.IntrinsicSession, fields):
        fields = tuple(fields)
        unknown = [f for f in fields if f not in FIELDS]
        if not fields or unknown:
            raise InputError(f"Swap which buffers? {', '.join(unknown) or 'none given'}: give "
                             f"some of {', '.join(FIELDS)}.")
        if "parsing" in fields and other.card.classes != base.card.classes:
            raise InputError(f"{other.card.name} parses {list(other.card.classes)}, "
                             f"{base.card.name} {list(base.card.classes)}: their parsing "
                             "cannot be swapped.")
        if "transfer" in fields and ((contract.OUTPUT_TRANSFER in base.outputs)
                                     != (contract.OUTPUT_TRANSFER in other.outputs)):
            raise InputError("Only one of the two models predicts the light transport: its "
                             "transfer cannot be swapped.")
        if other.card.stride != base.card.stride:
            raise InputError(f"{other.card.name} and {base.card.name} pad to different strides.")
        super().__init__(base.session, dataclasses.replace(
            base.card, name=f"{base.card.name}, {other.card.name}'s {'+'.join(fields)}"),
            base.providers)
        self.base, self.other, self.fields = base, other, fields

    def run_planar(self, image: np.ndarray, mirror: bool = False) -> engine.IntrinsicResult:
        mine = self.base.run_planar(image, mirror=mirror)
        theirs = self.other.run_planar(image, mirror=mirror)
        return dataclasses.replace(mine, **{f: getattr(theirs, f) for f in self.fields})


def synthetic(models: dict, threads: int = 1) -> dict:
    """{name: the synthetic test set's rmse_level_fit} for each model (a path or a loaded
    session), relit and measured as the card is (training.eval.evaluate)."""
    ds = evaluate.heldout_dataset(128)
    return {name: evaluate.evaluate(product_predictor(model, threads), ds,
                                    baselines=False)["model"]["rmse_level_fit"]
            for name, model in models.items()}


def shown(path) -> str:
    """A model's path as the report names it: relative to the repository where it lies in it."""
    p = pathlib.Path(path).resolve()
    return str(p.relative_to(ROOT)) if p.is_relative_to(ROOT) else str(path)


def run(onnx: str, other: str, swaps=DEFAULT_SWAPS, n_pairs: int = 36, threads: int = 1,
        data_root=None, progress=print) -> dict:
    def load(path):
        s = engine.new_session(path, providers=["CPUExecutionProvider"], threads=threads,
                               spin=False)
        if not isinstance(s, engine.IntrinsicSession):
            raise InputError(f"{path} is not an intrinsic model: it has no buffers to swap.")
        return s

    base, cand = load(onnx), load(other)
    variants = [BuffersFrom(base, cand, f) for f in swaps]
    models = {base.card.name: onnx, cand.card.name: other} | {v.card.name: v for v in variants}
    progress("synthetic test set ...")
    syn = synthetic(models, threads)
    progress("CroppedYale tune subjects ...")
    data_root = pathlib.Path(data_root) if data_root else yale.default_root().parents[1]
    real = yale.run([onnx, other], data_root / "yale" / "CroppedYale", data_root, n_pairs,
                    threads=threads, progress=progress, split="tune", sessions=variants)
    psnr = {m: real["results"]["scale_invariant"][m]["all"]["psnr"] for m in models}
    return {"onnx": shown(onnx), "other": shown(other), "swaps": [list(f) for f in swaps],
            "pairs_per_subject": n_pairs, "rmse_level_fit": syn, "yale_tune_psnr": psnr,
            "balance_correlation": {m: real["balance_correlation"][m] for m in models},
            "seconds": real["seconds"]}


def markdown(res: dict, command: str, machine: str) -> str:
    lines = [f"Produced by `{command}` on {machine}.", "",
             f"`{res['onnx']}` relit through the product with some of its buffers taken from "
             f"`{res['other']}`'s network (both run on every pass). Synthetic: the card's test "
             "set (held-out identities), rmse_level_fit. Real: CroppedYale's tune subjects, "
             f"{res['pairs_per_subject']} pairs each (training.eval.yale --split tune): "
             "scale-invariant PSNR and the balance correlations with the truth's; the paired "
             "gain over the first row on the same pairs, with its 5th-95th percentile over "
             "resampled subjects.", "",
             "| relit with | rmse_level_fit | PSNR (dB) | left/right | top/bottom | "
             "top/bottom paired gain |", "|---|---|---|---|---|---|"]
    for m, rmse in res["rmse_level_fit"].items():
        c = res["balance_correlation"][m]
        gain = (f"{c['top_bottom_gain']:+.3f} ({c['top_bottom_gain_90'][0]:+.3f} to "
                f"{c['top_bottom_gain_90'][1]:+.3f})" if "top_bottom_gain" in c else "-")
        lines.append(f"| {m} | {rmse:.4f} | {res['yale_tune_psnr'][m]:.2f} | "
                     f"{c['left_right']:.3f} | {c['top_bottom']:.3f} | {gain} |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--onnx", default=str(ROOT / "models" / "relight-portrait.onnx"))
    p.add_argument("--other", required=True, help="the network whose buffers are swapped in")
    p.add_argument("--swap", action="append", default=[],
                   help=f"comma-separated fields ({', '.join(FIELDS)}); repeat for several")
    p.add_argument("--pairs", type=int, default=36, help="pairs per CroppedYale tune subject")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--data", help="the shared data folder (default ../shared/data)")
    p.add_argument("--out", default=str(ROOT / "bench" / "results" / "buffer_swap"))
    a = p.parse_args(argv)
    swaps = [tuple(s.split(",")) for s in a.swap] or list(DEFAULT_SWAPS)
    try:
        res = run(a.onnx, a.other, swaps, a.pairs, a.threads, a.data,
                  progress=lambda msg: print(msg, file=sys.stderr))
    except InputError as e:
        print(f"buffer_swap: {e}", file=sys.stderr)
        return 2
    m = report.machine()
    command = "python -m training.eval.buffer_swap " + " ".join(
        argv if argv is not None else sys.argv[1:])
    md = markdown(res, command, f"{report.cpu_name()}, one thread per network")
    print(md)
    pathlib.Path(a.out + ".md").write_text(md)
    pathlib.Path(a.out + ".json").write_text(json.dumps(
        {"command": command, "machine": report.machine_line(m), **res}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
