"""The training samples: pairs of adjacent frames from the synthetic light stage (the sample API).

``LightStageDataset(split, resolution, seed)[idx]`` is a dict of float32 numpy arrays, channels
first, in absolute linear radiance (training applies addon/normalise itself):

* ``img_t_i`` frame t under L^i, ``img_t1_j`` frame t+1 under L^j, ``gt_t_k`` / ``gt_t1_k`` frames
  t and t+1 under L^k (3, H, W); ``light_i/j/k`` (16, 16, 3) light vectors (addon.lightvec);
* ``mask_t``, ``mask_t1`` (1, H, W) foreground coverage in [0, 1] (2 x 2 sub-samples, so
  silhouettes are anti-aliased like the images; 0 wherever the pixel centre misses the subject);
  ``parsing_t``, ``parsing_t1`` (K, H, W) in {0, 1}, channels in addon.contract.PARSING_CLASSES
  order (channel 0 = the pixel centre hits the subject: mask > 0);
* ``flow_fw`` (2, H, W) on frame t's pixels, displacement (dx, dy) in pixels to frame t+1;
  ``flow_bw`` the same from t+1 to t; ``valid_fw``, ``valid_bw`` (1, H, W): 1 where the point is
  visible in both frames.

Every sample is a pure function of (seed, split, idx). Identities are integers; an identity id
belongs to exactly one split (id % 16: 14 is val, 15 is test, the rest train), so held-out
performers are never seen in training (the paper holds out 4 of 36). Four HDRIs are held out of
training too (training/data/lighting_sampling.py). Within a split a sample picks one of
``identities`` ids of that split, a performance (seeded per identity and clip), a time, a camera, a
backdrop and a lighting triplet (training/data/lighting_sampling.py).

Backdrops: by default the stage's own matte wall (a smooth colour field); ``backdrops="varied"``
puts a photo crop, a chroma-key screen, a busy pattern or the wall behind the subject instead
(training/lightstage/backdrops.py), drawn from its own random stream so everything else in the
sample stays the same, and lit as the wall is. It works on cached pairs too.

Every sample carries every light's shadows, specular and subsurface: with the cache they cost
nothing extra at sample time. The selective-effects shortcut (``Scene.shade_selective``) is for
shading paid per image; the frontier benchmark measures its error and time.

Pools and the cache: with ``pool=P`` the frames come from a fixed pool of P frame pairs of the
split (pair p is a pure function of (split, resolution, p), whatever the seed), and a sample is a
pair drawn by its seed plus a fresh lighting triplet. Shading is linear in the lighting, so a pair's
transfer can be computed once: ``cache_dir`` points at a folder built by
``python -m training.data.build_cache`` and the pairs are read from there instead of rendered
(about 50x faster); the pool size is then the cache's. Cached samples equal the on-the-fly
samples of the same pool up to the cache's float16 transfer (tested).
"""

from __future__ import annotations

import dataclasses
import json
import pathlib
import warnings

import numpy as np
import torch

from addon.contract import PARSING_CLASSES
from addon.errors import InputError

from . import lighting_sampling
from ..lightstage import assets
from ..lightstage import backdrops as backdrops_mod
from ..lightstage import pairs
from ..lightstage.scene import Scene
from ..lightstage.subject import Performance, sample_camera, sample_identity

SPLITS = {"train": 0, "val": 1, "test": 2}
ID_MODULUS = 16
HELD_OUT = {"val": (14,), "test": (15,)}
CLIP_SECONDS = 60.0  # performance times are drawn from [0, CLIP_SECONDS)
CLIPS_PER_IDENTITY = 4
POOL_SALT = 0x9001
BACKDROP_SALT = 0xBDBD
BACKDROPS = ("wall", "varied")  # lightstage/backdrops.py
# What a rendered sample holds is versioned by hand: caches and the test set record RENDER_VERSION,
# so a stale one is noticed. Bump it with every change that alters samples (the renderer's look,
# the lighting sampling, the varied backdrops, the sample layout) and rewrite the golden probe
# (`python -m training.data.make_testset --write-probe`); tests/training/test_render_version.py
# renders the probe and fails when samples changed without a bump. (A hash of whole source files
# would make caches look stale after every edit, even one that changed no sample.)
RENDER_VERSION = 2


def renderer_version() -> str:
    """The light stage's sample version, as caches and the test set record it ("v1", ...)."""
    return f"v{RENDER_VERSION}"


def cache_folder(cache_dir, split: str, resolution: int) -> pathlib.Path:
    return pathlib.Path(cache_dir) / f"{split}_{int(resolution)}"


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
                 length: int = 100_000, data_root=None, cache_dir=None,
                 sampling: bool = True, identities: int | None = None, pool: int | None = None,
                 transport: bool = False, backdrops: str = "wall", long_hair: float = 0.0):
        if split not in SPLITS:
            raise InputError(f"Unknown split {split!r}; use one of {sorted(SPLITS)}.")
        if int(resolution) < 16:
            raise InputError(f"Resolution {resolution} is too small; use 16 pixels or more.")
        self.split, self.resolution, self.seed = split, int(resolution), int(seed)
        self.length = int(length)
        self.data_root = pathlib.Path(data_root) if data_root else assets.default_data_root()
        if backdrops not in BACKDROPS:
            raise InputError(f"Unknown backdrops {backdrops!r}; use one of {list(BACKDROPS)}.")
        self.backdrops = backdrops
        self.sampling = bool(sampling)
        self.transport = bool(transport)  # add the SH transport targets (lightstage/pairs.py)
        # Fraction of the identities with hair that wear it long (subject.sample_identity); 0 is
        # the light stage as its render version and the caches know it.
        self.long_hair = float(long_hair)
        if self.long_hair and cache_dir is not None:
            raise InputError("A light-stage cache holds the light stage's own identities; long "
                             "hair (long_hair > 0) renders on the fly, without cache_dir.")
        n_ids = identities or {"train": 448, "val": 32, "test": 32}[split]
        self.ids = identity_ids(split, n_ids)
        self.model = assets.load_head(self.data_root)
        names, self.bank = lighting_sampling.environment_bank(self.data_root)
        self.hdri_pool = lighting_sampling.hdri_pool(names, split)
        if backdrops == "varied":
            photo_names, self.photo_bank = backdrops_mod.photo_bank(self.data_root)
            self.photo_pool = backdrops_mod.pool_for(photo_names, split)
        self.cache = None
        if cache_dir is not None:
            self.cache = cache_folder(cache_dir, split, self.resolution)
            pool = self._open_cache(pool)
        if pool is not None and int(pool) < 1:
            raise InputError(f"A pool of {pool} frame pairs is empty; use 1 or more.")
        self.pool = None if pool is None else int(pool)

    def _open_cache(self, pool):
        man = self.cache / "manifest.json"
        build = (f"python -m training.data.build_cache --split {self.split} "
                 f"--res {self.resolution} --out {self.cache.parent}")
        if not man.is_file():
            raise InputError(f"No light-stage cache at {self.cache}; build it with `{build}`.")
        info = json.loads(man.read_text())
        if info.get("format") != pairs.FORMAT or info.get("identities") != len(self.ids):
            raise InputError(f"The cache at {self.cache} was built with another format or "
                             f"identity count; rebuild it with `{build}`.")
        n = int(info["pairs"])
        if pool is not None and int(pool) != n:
            raise InputError(f"The cache at {self.cache} holds {n} pairs, not pool={pool}.")
        missing = [p for p in range(n) if not pairs.pair_path(self.cache, p).is_file()]
        if missing:
            raise InputError(f"The cache at {self.cache} is incomplete ({len(missing)} of {n} "
                             f"pairs missing); finish it with `{build} --pairs {n}`.")
        if info.get("renderer") != renderer_version():
            warnings.warn(f"The cache at {self.cache} was rendered by another version of the light "
                          "stage; its samples differ from on-the-fly ones until it is rebuilt.")
        return n

    def __len__(self) -> int:
        return self.length

    def rng(self, idx: int) -> np.random.Generator:
        return np.random.default_rng([self.seed, SPLITS[self.split], int(idx)])

    def _draw_scene(self, rng: np.random.Generator):
        ident_id = self.ids[int(rng.integers(len(self.ids)))]
        clip = int(rng.integers(CLIPS_PER_IDENTITY))
        t = float(rng.integers(int(CLIP_SECONDS * 25))) / 25.0
        cam = sample_camera(rng, self.resolution)
        backdrop = int(rng.integers(2 ** 31))
        perf = Performance(ident_id * CLIPS_PER_IDENTITY + clip, self.model.expression_names)
        ident = sample_identity(ident_id, long_hair=self.long_hair)
        return Scene(ident, perf, cam, self.data_root, backdrop), t

    def pair_scene(self, p: int):
        """(scene, t) of pool pair ``p``: independent of the seed, so one cache serves all seeds."""
        return self._draw_scene(np.random.default_rng([POOL_SALT, SPLITS[self.split], int(p)]))

    def draw(self, idx: int):
        """(pair index or None, rng positioned after the scene draws)."""
        if not 0 <= int(idx) < self.length:
            raise IndexError(idx)
        rng = self.rng(idx)
        if self.pool is not None:
            return int(rng.integers(self.pool)), rng
        return None, rng

    def scene_for(self, idx: int):
        """(scene, t, lights) of sample ``idx``: everything random about it, drawn in one order."""
        p, rng = self.draw(idx)
        scene, t = self._draw_scene(rng) if p is None else self.pair_scene(p)
        lights = lighting_sampling.sample_triplet(rng, self.bank, self.sampling, self.hdri_pool)
        return scene, t, lights

    def __getitem__(self, idx: int) -> dict:
        torch_threads = torch.get_num_threads()
        p, rng = self.draw(idx)
        if self.cache is not None:
            rec = pairs.load(pairs.pair_path(self.cache, p))
        else:
            scene, t = self._draw_scene(rng) if p is None else self.pair_scene(p)
            rec = pairs.record_pair(scene, t)
        lights = lighting_sampling.sample_triplet(rng, self.bank, self.sampling, self.hdri_pool)
        if self.backdrops == "varied":  # its own random stream: the rest of the sample is unchanged
            brng = np.random.default_rng([self.seed, SPLITS[self.split], int(idx), BACKDROP_SALT])
            h, w = rec.frames[0].mask.shape
            bd = backdrops_mod.sample(brng, h, w, rec.frames[0].backdrop, self.photo_bank,
                                      self.photo_pool)
            rec = dataclasses.replace(rec, frames=tuple(dataclasses.replace(f, backdrop=bd)
                                                        for f in rec.frames))
        out = pairs.assemble(rec, lights, len(PARSING_CLASSES), with_transport=self.transport)
        assert torch.get_num_threads() == torch_threads
        return out


def make_dataset(split: str, resolution: int, seed: int, sampling: bool = True, **kwargs):
    """The light stage as training and evaluation build it: ``LightStageDataset``, with the
    lighting sampling off for the "w/o sampling" ablation (``sampling=False``)."""
    return LightStageDataset(split, resolution, seed, sampling=sampling, **kwargs)
