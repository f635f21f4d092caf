"""The options of a training run (``python -m training.run.train``): every argument a run records
in its recipe, and the network overrides they make."""

from __future__ import annotations

import argparse

from ..model import network

DESCRIPTION = "Train one preset of the relighting network on the synthetic light stage."


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=DESCRIPTION)
    p.add_argument("--preset", default="standard", choices=sorted(network.PRESETS))
    p.add_argument("--minutes", type=float, default=100.0, help="wall-clock training budget")
    p.add_argument("--max-steps", type=int, default=0, help="stop early after this many steps")
    p.add_argument("--steps", type=int, default=0,
                   help="a step budget instead of --minutes: the learning-rate schedule, "
                        "progressive stages and the adversarial/temporal starts become fractions "
                        "of it, so runs compare fairly on a loaded machine (ablations)")
    p.add_argument("--val-every-steps", type=int, default=250,
                   help="steps between val metrics when --steps is given")
    p.add_argument("--init", metavar="CKPT",
                   help="start from this checkpoint's weights (same architecture), e.g. to train "
                        "a shipped model further: runs/final-t2500/checkpoint.pt. The schedule "
                        "starts anew: continue with a lower --lr and --progressive 1:1 (a 1e-3 "
                        "restart at 64 px undid a trained Draft within two steps)")
    p.add_argument("--widths", help="override the preset's four encoder widths, e.g. 12,16,32,48")
    p.add_argument("--blocks", help="override the preset's four block counts, e.g. 1,1,1,1")
    p.add_argument("--out", default="runs/latest")
    p.add_argument("--ablation", default="full",
                   choices=["full", "no_structure", "no_temporal", "no_parsing", "no_sampling",
                            "basic_only"])
    p.add_argument("--transport-loss", action="store_true",
                   help="supervise the ratio head's SH transport with the light stage's (not in "
                        "the paper; an experiment)")
    p.add_argument("--backdrops", default="wall", choices=["wall", "varied"],
                   help="what stands behind the training subjects: the stage's smooth wall, or "
                        "photos, chroma-key screens and busy patterns as well "
                        "(training/lightstage/backdrops.py); validation keeps the wall")
    p.add_argument("--resolution", type=int, default=128, help="light-stage render size")
    p.add_argument("--batch", type=int, default=4)
    p.add_argument("--seed", type=int, default=0, help="torch and data seed")
    p.add_argument("--optim", default="adam", choices=["adam", "rmsprop"],
                   help="network optimiser; the paper's is rmsprop at 5e-5 (the critic always is)")
    p.add_argument("--lr", type=float, default=1e-3)
    p.add_argument("--ema", type=float, default=0.0, metavar="DECAY",
                   help="validate, choose best.pt and export an exponential moving average of "
                        "the weights with this decay per step (e.g. 0.999); 0: the raw weights")
    p.add_argument("--warmup-steps", type=int, default=0,
                   help="ramp the learning rate up linearly over these first steps (for runs "
                        "continued with --init, whose optimiser starts afresh)")
    p.add_argument("--progressive", default="0.3:2,1:1",
                   help="fraction:downsample stages (low resolution first)")
    p.add_argument("--adv-start", type=float, default=0.3,
                   help="fraction of the budget after which adversarial training starts")
    p.add_argument("--temporal-start", type=float, default=0.5,
                   help="fraction of the budget after which the temporal term is on: from the "
                        "start it drove the first Draft to a blurred, input-independent output "
                        "(a smooth image is temporally consistent) before it learnt to relight")
    p.add_argument("--n-critic", type=int, default=1)
    p.add_argument("--critic-width", type=int, default=32)
    p.add_argument("--bf16", action="store_true", help="bf16 autocast")
    p.add_argument("--channels-last", action="store_true")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--cpu", action="store_true", help="ignore a GPU")
    p.add_argument("--log-every", type=int, default=20)
    p.add_argument("--save-every", type=int, default=200)
    p.add_argument("--cache", help="read rendered samples from this folder (see --render)")
    p.add_argument("--data-cache", metavar="DIR",
                   help="light-stage pair cache root (python -m training.data.build_cache), e.g. "
                        "cache/lightstage: about 50x faster than rendering")
    p.add_argument("--overfit", type=int, default=0, metavar="N",
                   help="train on the first N samples only and report metrics on them")
    p.add_argument("--val-n", type=int, default=16, help="val samples for the logged curves")
    p.add_argument("--val-every", type=float, default=5.0, help="minutes between val metrics")
    p.add_argument("--render", metavar="FOLDER",
                   help="render training samples into FOLDER instead of training")
    p.add_argument("--start", type=int, default=0, help="first sample index for --render")
    p.add_argument("--count", type=int, default=1000, help="samples for --render")
    p.add_argument("--curve", metavar="RUN",
                   help="print a run's val curve (model vs baselines) and loss terms, then exit")
    p.add_argument("--measure-speed", action="store_true")
    p.add_argument("--speed-steps", type=int, default=5)
    return p


def net_overrides(args) -> dict:
    """Width / depth overrides of the preset (the extra points of the accuracy/time frontier)."""
    out = {}
    for key in ("widths", "blocks"):
        text = getattr(args, key, None)
        if text:
            vals = tuple(int(v) for v in text.split(","))
            if len(vals) != 4 or min(vals) < 1:
                raise SystemExit(f"--{key} takes four positive integers, e.g. 16,24,48,64")
            out[key] = vals
    return out
