"""Training speed on this machine (``--measure-speed``): steps per second for fp32, bf16 autocast
and channels-last."""

from __future__ import annotations

import argparse
import json
import time

import torch

from ..model import losses, network
from .trainer import Trainer


def measure_speed(args, batch_fn) -> list[dict]:
    """Training steps per second for fp32 / bf16 / channels-last on this machine."""
    rows = []
    for bf16, cl in ((False, False), (True, False), (False, True), (True, True)):
        torch.manual_seed(0)
        a = argparse.Namespace(**{**vars(args), "bf16": bf16, "channels_last": cl})
        trainer = Trainer(network.build(args.preset), losses.Switches(), a)
        b = batch_fn()
        trainer.step(b, args.lr, adv_on=True)  # warm-up
        t0 = time.perf_counter()
        for _ in range(args.speed_steps):
            trainer.step(b, args.lr, adv_on=True)
        dt = (time.perf_counter() - t0) / args.speed_steps
        rows.append({"bf16": bf16, "channels_last": cl, "s_per_step": round(dt, 3),
                     "pairs_per_s": round(args.batch / dt, 2)})
        print(json.dumps(rows[-1]), flush=True)
    return rows
