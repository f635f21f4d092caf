"""The schedule of a run, as fractions of its budget (time or steps): the learning rate, and the
progressive resolutions (low resolution first)."""

from __future__ import annotations

import math


def parse_stages(text: str) -> list[tuple[float, int]]:
    """"0.4:4,0.75:2,1:1" -> [(0.4, 4), (0.75, 2), (1.0, 1)]: down-sampling factor until each
    fraction of the time budget (progressive training, low resolution first)."""
    stages = []
    for part in text.split(","):
        frac, factor = part.split(":")
        stages.append((float(frac), int(factor)))
    if stages[-1][0] < 1.0:
        raise ValueError("the last progressive stage must reach fraction 1")
    return stages


def factor_at(stages, frac: float) -> int:
    for until, factor in stages:
        if frac < until:
            return factor
    return stages[-1][1]


def lr_at(base: float, frac: float, step: int = 0, warmup: int = 0) -> float:
    """Cosine decay over the time budget to 5% of the base rate; with ``warmup`` steps, a linear
    ramp from base / warmup up to the cosine over the first ones (for runs continued with
    ``--init``, which start with fresh optimiser moments and a fresh critic)."""
    cosine = base * (0.05 + 0.95 * 0.5 * (1.0 + math.cos(math.pi * min(frac, 1.0))))
    return cosine * min(1.0, (step + 1) / warmup) if warmup > 0 else cosine
