"""An exponential moving average of the generator's weights (``--ema DECAY``)."""

from __future__ import annotations

import copy

import torch


class WeightAverage:
    """An exponential moving average of the generator's weights (``--ema DECAY``): with batch 8 the
    weights after any one step carry that step's noise, and a val-selected checkpoint picks the
    luckiest of them (the "dip" of continued runs, models/README.md). The average is what gets
    validated, chosen as ``best.pt`` and exported; the raw weights keep training. Early in a run
    from scratch the decay is held at (1 + n) / (10 + n) so the average is not dominated by the
    random start; a run from ``--init`` starts its average at the loaded weights."""

    def __init__(self, net, decay: float, warm: bool):
        self.decay, self.warm, self.updates = float(decay), warm, 0
        self.net = copy.deepcopy(net).eval()
        for p in self.net.parameters():
            p.requires_grad_(False)

    @torch.no_grad()
    def update(self, net):
        self.updates += 1
        d = self.decay if self.warm else min(self.decay, (1 + self.updates) / (10 + self.updates))
        for a, b in zip(self.net.parameters(), net.parameters()):
            a.lerp_(b.detach(), 1.0 - d)
        for a, b in zip(self.net.buffers(), net.buffers()):
            a.copy_(b)
