"""Checkpoints: a network's weights with its configuration, the run's recipe and the step, in one
file that rebuilds the network (``best.pt``, ``checkpoint.pt`` in a run folder)."""

from __future__ import annotations

import torch

from . import network


def save_checkpoint(path, net, recipe, step, extra=None):
    torch.save({"state_dict": net.state_dict(), "config": net.cfg.to_dict(), "recipe": recipe,
                "step": step, **(extra or {})}, path)


def load_checkpoint(path, map_location="cpu", raw: bool = False):
    """A checkpoint's network (eval mode) and the checkpoint. ``raw``: the raw training weights
    that a run with --ema keeps beside the average in checkpoint.pt, instead of the average."""
    ck = torch.load(path, map_location=map_location, weights_only=False)
    cfg = network.NetConfig(**{k: tuple(v) if isinstance(v, list) else v
                               for k, v in ck["config"].items()})
    net = network.RelightNet(cfg)
    if raw and "raw_state_dict" not in ck:
        raise SystemExit(f"{path} holds one set of weights (no --ema average): leave out --raw")
    net.load_state_dict(ck["raw_state_dict"] if raw else ck["state_dict"])
    return net.eval(), ck
