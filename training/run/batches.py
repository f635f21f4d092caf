"""Batches for training: normalised samples stacked into tensors, down-sampled for the progressive
stages, and samples pre-rendered into a folder (``--render``, ``--cache``)."""

from __future__ import annotations

import json
import pathlib

import numpy as np
import torch
import torch.nn.functional as F

from addon.frames import write_atomic

from ..data.dataset import make_dataset, renderer_version
from ..model import warp
from ..model.units import IMAGE_KEYS, MASK_KEYS, TRANSPORT_KEYS, normalise_sample
from .recipe import git_commit


def collate(samples: list[dict], device="cpu") -> dict:
    return {k: torch.from_numpy(np.stack([s[k] for s in samples])).to(device) for k in samples[0]}


def _min_pool(x, f):
    return -F.max_pool2d(-x, f)


def downsample_batch(b: dict, factor: int) -> dict:
    """The batch at 1/factor resolution (progressive training): area-averaged images and labels,
    flows scaled, validity kept only where every source pixel was valid."""
    if factor == 1:
        return b
    out = dict(b)
    for k in IMAGE_KEYS + MASK_KEYS + tuple(k for k in TRANSPORT_KEYS if k in b):
        out[k] = F.avg_pool2d(b[k], factor)
    for k in ("flow_fw", "flow_bw"):
        out[k] = warp.downsample_flow(b[k], factor)
    for k in ("valid_fw", "valid_bw"):
        out[k] = _min_pool(b[k], factor)
    return out


# Samples are costly to render (~0.5 s at 128 px on one core) and a pure function of
# (seed, split, idx), so a renderer process can fill a folder while training reads what is there.
_HALF = ("img_t_i", "img_t1_j", "gt_t_k", "gt_t1_k", "flow_fw", "flow_bw")


def render_cache(folder, split: str, resolution: int, seed: int, start: int, count: int,
                 sampling: bool = True) -> None:
    """Render samples start..start+count-1 into ``folder`` (one .npz each, skipping those there)."""
    folder = pathlib.Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    ds = make_dataset(split, resolution, seed, sampling=sampling)
    (folder / "cache.json").write_text(json.dumps(
        {"split": split, "resolution": resolution, "seed": seed, "sampling": sampling,
         "dataset": "training.data.dataset.LightStageDataset", "git_commit": git_commit(),
         "renderer": renderer_version()}, indent=2))
    for idx in range(start, start + count):
        path = folder / f"{idx:07d}.npz"
        if path.exists():
            continue
        s = ds[idx]
        # half floats hold the radiance range here (< 65504) and halve the disk and reads
        s = {k: v.astype(np.float16) if k in _HALF else v for k, v in s.items()}

        def write(tmp, s=s):
            with open(tmp, "wb") as f:  # a file, so np.savez adds no .npz to the name
                np.savez(f, **s)
        write_atomic(path, write)  # readers never see a half-written file


class CachedSamples:
    """The samples rendered so far into a cache folder (the list is refreshed as it grows)."""

    def __init__(self, folder):
        self.folder = pathlib.Path(folder)
        self.refresh()

    def refresh(self):
        self.files = sorted(self.folder.glob("[0-9]*.npz"))  # render_cache's finished samples
        if not self.files:
            raise FileNotFoundError(f"no rendered samples in {self.folder} yet")

    def __len__(self):
        return len(self.files)

    def __getitem__(self, i):
        with np.load(self.files[i]) as z:
            return {k: z[k].astype(np.float32) for k in z.files}


class Batches:
    """Endless shuffled batches of normalised samples from a map-style dataset."""

    def __init__(self, dataset, batch: int, seed: int, device="cpu"):
        self.ds, self.batch, self.device = dataset, batch, device
        self.rng = np.random.default_rng(seed)
        self.order, self.pos = [], 0

    def __next__(self) -> dict:
        picks = []
        while len(picks) < self.batch:
            if self.pos >= len(self.order):
                if hasattr(self.ds, "refresh"):
                    self.ds.refresh()
                self.order, self.pos = self.rng.permutation(len(self.ds)), 0
            picks.append(normalise_sample(self.ds[int(self.order[self.pos])]))
            self.pos += 1
        return collate(picks, self.device)
