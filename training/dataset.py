"""The training samples: pairs of adjacent frames from the synthetic light stage (the sample API).

``LightStageDataset(split, resolution, seed)[idx]`` is a dict of float32 numpy arrays, channels
first, in absolute linear radiance (training applies addon/normalise itself):

* ``img_t_i`` frame t under L^i, ``img_t1_j`` frame t+1 under L^j, ``gt_t_k`` / ``gt_t1_k`` frames
  t and t+1 under L^k (3, H, W); ``light_i/j/k`` (16, 16, 3) light vectors (addon.lightvec);
* ``mask_t``, ``mask_t1`` (1, H, W) foreground; ``parsing_t``, ``parsing_t1`` (K, H, W) in {0, 1},
  channels in addon.contract.PARSING_CLASSES order (channel 0 = foreground);
* ``flow_fw`` (2, H, W) on frame t's pixels, displacement (dx, dy) in pixels to frame t+1;
  ``flow_bw`` the same from t+1 to t; ``valid_fw``, ``valid_bw`` (1, H, W): 1 where the point is
  visible in both frames.

Every sample is a pure function of (seed, split, idx). Identities are integers; an identity id
belongs to exactly one split (id % 16: 14 is val, 15 is test, the rest train), so held-out
performers are never seen in training (the paper holds out 4 of 36). Within a split a sample picks
one of ``identities`` ids of that split, a performance (seeded per identity and clip), a time, a
camera, a backdrop and a lighting triplet (training/lighting_sampling.py).
"""

from __future__ import annotations

import pathlib

import numpy as np
import torch

from addon.contract import PARSING_CLASSES
from addon.errors import InputError

from . import lighting_sampling
from .lightstage import assets
from .lightstage.scene import Scene, next_time
from .lightstage.subject import Performance, sample_camera, sample_identity

SPLITS = {"train": 0, "val": 1, "test": 2}
ID_MODULUS = 16
HELD_OUT = {"val": (14,), "test": (15,)}
CLIP_SECONDS = 60.0  # performance times are drawn from [0, CLIP_SECONDS)
CLIPS_PER_IDENTITY = 4


def split_of_identity(identity_id: int) -> str:
    r = int(identity_id) % ID_MODULUS
    for split, residues in HELD_OUT.items():
        if r in residues:
            return split
    return "train"


def identity_ids(split: str, count: int) -> list[int]:
    """The first ``count`` identity ids that belong to ``split``."""
    out, i = [], 0
    while len(out) < count:
        if split_of_identity(i) == split:
            out.append(i)
        i += 1
    return out


class LightStageDataset:
    """Map-style dataset of synthetic light-stage samples (no DataLoader needed)."""

    def __init__(self, split: str = "train", resolution: int = 128, seed: int = 0,
                 length: int = 100_000, data_root=None, cache_dir=None, effects="auto",
                 sampling: bool = True, identities: int | None = None):
        if split not in SPLITS:
            raise InputError(f"Unknown split {split!r}; use one of {sorted(SPLITS)}.")
        if int(resolution) < 16:
            raise InputError(f"Resolution {resolution} is too small; use 16 pixels or more.")
        self.split, self.resolution, self.seed = split, int(resolution), int(seed)
        self.length = int(length)
        self.data_root = pathlib.Path(data_root) if data_root else assets.default_data_root()
        self.cache_dir = cache_dir
        self.effects = effects
        self.sampling = bool(sampling)
        n_ids = identities or {"train": 448, "val": 32, "test": 32}[split]
        self.ids = identity_ids(split, n_ids)
        self.model = assets.load_head(self.data_root)
        self.bank = lighting_sampling.environment_bank(self.data_root)[1]

    def __len__(self) -> int:
        return self.length

    def rng(self, idx: int) -> np.random.Generator:
        return np.random.default_rng([self.seed, SPLITS[self.split], int(idx)])

    def scene_for(self, idx: int):
        """(scene, t, lights) of sample ``idx``: everything random about it, drawn in one order."""
        if not 0 <= int(idx) < self.length:
            raise IndexError(idx)
        rng = self.rng(idx)
        ident_id = self.ids[int(rng.integers(len(self.ids)))]
        clip = int(rng.integers(CLIPS_PER_IDENTITY))
        t = float(rng.integers(int(CLIP_SECONDS * 25))) / 25.0
        cam = sample_camera(rng, self.resolution)
        backdrop = int(rng.integers(2 ** 31))
        lights = lighting_sampling.sample_triplet(rng, self.bank, self.sampling)
        perf = Performance(ident_id * CLIPS_PER_IDENTITY + clip, self.model.expression_names)
        scene = Scene(sample_identity(ident_id), perf, cam, self.data_root, backdrop)
        return scene, t, lights

    def __getitem__(self, idx: int) -> dict:
        torch_threads = torch.get_num_threads()
        scene, t, (li, lj, lk) = self.scene_for(idx)
        f0 = scene.frame(t)
        f1 = scene.frame(next_time(t))
        a = scene.shade(f0, [li, lk])
        b = scene.shade(f1, [lj, lk])
        flow_fw, valid_fw = scene.flow(f0, f1)
        flow_bw, valid_bw = scene.flow(f1, f0)
        k = len(PARSING_CLASSES)
        out = {
            "img_t_i": a[0], "gt_t_k": a[1], "img_t1_j": b[0], "gt_t1_k": b[1],
            "mask_t": f0.gb.mask[None].float(), "mask_t1": f1.gb.mask[None].float(),
            "parsing_t": scene.parsing(f0, k), "parsing_t1": scene.parsing(f1, k),
            "flow_fw": flow_fw, "flow_bw": flow_bw, "valid_fw": valid_fw, "valid_bw": valid_bw,
        }
        out = {key: np.ascontiguousarray(v.numpy(), dtype=np.float32) for key, v in out.items()}
        out.update(light_i=li.astype(np.float32), light_j=lj.astype(np.float32),
                   light_k=lk.astype(np.float32))
        assert torch.get_num_threads() == torch_threads
        return out
