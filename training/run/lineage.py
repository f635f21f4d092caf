"""Lineage: a run started from another run's checkpoint (``--init``) records that checkpoint and,
nested in it, the whole chain back to a run from scratch, so a model trained further several times
reproduces from its card alone (training.run.reproduce)."""

from __future__ import annotations

import pathlib

import torch


def load_init(net, path) -> dict:
    """Start from a checkpoint's weights (continue or fine-tune a run; the schedule starts anew).
    The architecture must be the same: another preset or width is a clear error."""
    ck = torch.load(path, map_location="cpu", weights_only=False)
    if ck.get("config") != net.cfg.to_dict():
        raise SystemExit(f"--init {path}: its network ({ck.get('config')}) is not the one this run "
                         f"builds ({net.cfg.to_dict()}); use the same --preset/--widths/--blocks.")
    net.load_state_dict(ck["state_dict"])
    recipe = ck.get("recipe") or {}
    return {"checkpoint": str(path), "step": ck.get("step"), "recipe": recipe.get("command"),
            "render_version": samples_version(recipe), "git_commit": recipe.get("git_commit"),
            "init": resolve_lineage(recipe.get("init"))}


def samples_version(recipe: dict) -> str:
    """The light stage render version a run's samples had (training.data.dataset.RENDER_VERSION).
    Runs recorded before the field was kept all trained on v1 samples: v2 came with it."""
    return recipe.get("render_version") or "v1"


def resolve_lineage(init: dict | None) -> dict | None:
    """The whole chain of runs a checkpoint was trained from: ``init`` (the recipe's record of the
    checkpoint a run started from) with that checkpoint's own ``init`` nested in it, and so on back
    to a run from scratch, so a model trained further several times can be reproduced from its
    card alone. Records written before the chain was kept (one level) are completed from the
    parent checkpoints where they are on disk; where one is not, the chain stops there."""
    if not init or "init" in init:
        return init
    path = pathlib.Path(init.get("checkpoint") or "")
    if not path.is_file():
        return init
    parent = (torch.load(path, map_location="cpu", weights_only=False).get("recipe") or {})
    return {**init, "init": resolve_lineage(parent.get("init"))}
