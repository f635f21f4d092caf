"""Varied backdrops: what real footage has behind a performer and the stage's plain wall lacks.

The stage's own backdrop (Scene._backdrop) is a smooth, muted colour field. Networks trained only
on it learnt that a background is smooth, and on real footage repainted busy rooms into blotches and
left halos around green screens (the footage sheets showed it). ``LightStageDataset(backdrops="varied")``
replaces it, per sample, by one of:

* ``photo``: a crop of one of the CC0 HDRIs' horizon band (rooms, streets, trees), tone-mapped to an
  albedo, often defocused (a portrait lens at a wide aperture). A split draws from its own maps
  (training never the four held-out ones; lighting_sampling.hdri_pool);
* ``screen``: a green or blue chroma-key cloth with soft folds;
* ``pattern``: a busy room stand-in: shelves, frames and posters (random rectangles) over a wall;
* ``wall``: the stage's own smooth wall (so the plain case stays in the mix).

Every kind is an albedo in [0.01, 0.95] on the same matte plane facing the camera, so it is lit as
the stage's wall is (shading.relight: unshadowed, far behind the subject): under two lightings a
background pixel changes by one per-channel factor, and a network that learns this keeps the
backdrop's detail instead of painting a new one. The subject's pixels are untouched, and silhouette
pixels blend subject and backdrop by coverage as before, so no fringe of the old wall remains.
"""

from __future__ import annotations

import functools

import numpy as np
import torch
import torch.nn.functional as tf

from addon import colour
from addon.hdri_io import read_hdri

from . import shading

KINDS = ("photo", "screen", "pattern", "wall")
SHARES = (0.45, 0.15, 0.2, 0.2)
ALBEDO = (0.01, 0.95)
BAND = (0.3, 0.62)  # rows of an equirectangular map holding the scenery (above/below: sky, floor)
WIDTH = 512  # the bank's maps are reduced to this width once


def _tone_map(rgb: np.ndarray) -> np.ndarray:
    """HDR radiance to a plausible albedo: log luminance from its 2nd-98th percentile to 0.02-0.6,
    hue and saturation kept."""
    lum = np.maximum(rgb @ np.array(colour.REC709_LUMA, np.float32), 1e-6)
    log = np.log(lum)
    lo, hi = np.percentile(log, [2, 98])
    mapped = 0.02 + 0.58 * np.clip((log - lo) / max(hi - lo, 1e-3), 0, 1)
    out = np.clip(rgb, 0, None) / lum[..., None] * mapped[..., None]
    return np.clip(out, *ALBEDO).astype(np.float32)


@functools.lru_cache(maxsize=2)
def photo_bank(data_root) -> tuple[tuple[str, ...], tuple[torch.Tensor, ...]]:
    """(names as lighting_sampling names them, (3, h, WIDTH) albedo bands), one per HDRI."""
    from ..data import lighting_sampling

    names, bands = [], []
    for p in lighting_sampling.hdri_paths(data_root):
        img = np.nan_to_num(read_hdri(p).astype(np.float32), nan=0.0, posinf=0.0, neginf=0.0)
        h = img.shape[0]
        band = img[int(BAND[0] * h): int(BAND[1] * h)]
        t = torch.from_numpy(_tone_map(band)).permute(2, 0, 1)[None]
        out_h = max(8, round(t.shape[2] * WIDTH / t.shape[3]))
        t = tf.interpolate(t, size=(out_h, WIDTH), mode="bilinear", align_corners=False,
                           antialias=True)[0]
        names.append(f"{p.parent.name}/{p.stem}")
        bands.append(t.contiguous())
    return tuple(names), tuple(bands)


def _blur(img: torch.Tensor, sigma: float) -> torch.Tensor:
    """Gaussian blur renormalised at the borders (the frame edge stays as bright as the rest)."""
    if sigma < 0.3:
        return img
    ones = torch.ones_like(img[:1])
    return shading.gaussian_blur(img, sigma) / shading.gaussian_blur(ones, sigma)


def _noise(rng: np.random.Generator, h: int, w: int, cells: int) -> torch.Tensor:
    """A smooth (1, h, w) field in [0, 1] from a cells x cells random grid."""
    g = torch.from_numpy(rng.random((1, 1, cells, cells)).astype(np.float32))
    return tf.interpolate(g, size=(h, w), mode="bicubic", align_corners=False)[0].clamp(0, 1)


def photo(rng: np.random.Generator, h: int, w: int, band: torch.Tensor) -> torch.Tensor:
    bh, bw = band.shape[1:]
    cw = int(bw * rng.uniform(0.12, 0.45))
    ch = min(bh, max(4, round(cw * h / w)))
    cw = min(bw, max(4, round(ch * w / h)))
    x0 = int(rng.integers(0, bw - cw + 1))
    y0 = int(rng.integers(0, bh - ch + 1))
    crop = band[:, y0:y0 + ch, x0:x0 + cw]
    if rng.random() < 0.5:
        crop = crop.flip(2)
    img = tf.interpolate(crop[None], size=(h, w), mode="bilinear", align_corners=False,
                         antialias=True)[0]
    gain = float(np.exp(rng.normal(0.0, 0.3)))
    sigma = float(rng.uniform(0.0, 3.0)) * h / 128 if rng.random() < 0.6 else 0.0
    return _blur(img * gain, sigma)


def screen(rng: np.random.Generator, h: int, w: int) -> torch.Tensor:
    base = np.array([0.03, 0.40, 0.06]) if rng.random() < 0.7 else np.array([0.02, 0.08, 0.45])
    base = base * np.exp(rng.normal(0.0, 0.12, 3)) * rng.uniform(0.7, 1.2)
    folds = 0.8 + 0.3 * _noise(rng, h, w, int(rng.integers(3, 7)))
    return torch.from_numpy(base.astype(np.float32))[:, None, None] * folds


def pattern(rng: np.random.Generator, h: int, w: int) -> torch.Tensor:
    wall = torch.from_numpy(rng.uniform(0.15, 0.8, 3).astype(np.float32))[:, None, None]
    img = wall * (0.85 + 0.3 * _noise(rng, h, w, 4)).expand(3, h, w).clone()
    for _ in range(int(rng.integers(6, 30))):
        y0, x0 = int(rng.integers(0, h)), int(rng.integers(0, w))
        rh = int(rng.integers(2, max(3, h // 3)))
        rw = int(rng.integers(2, max(3, w // 3)))
        paint = torch.from_numpy(rng.uniform(0.02, 0.9, 3).astype(np.float32))[:, None, None]
        img[:, y0:y0 + rh, x0:x0 + rw] = paint
    sigma = float(rng.uniform(0.0, 2.5)) * h / 128
    return _blur(img, sigma)


def sample(rng: np.random.Generator, h: int, w: int, wall: torch.Tensor, bank,
           pool) -> torch.Tensor:
    """(3, h, w) albedo of one backdrop; ``wall``: the stage's own; ``bank``: photo_bank's bands;
    ``pool``: the bank indices this split may use."""
    kind = KINDS[int(rng.choice(len(KINDS), p=SHARES))]
    if kind == "photo" and len(pool):
        img = photo(rng, h, w, bank[int(pool[int(rng.integers(len(pool)))])])
    elif kind == "screen":
        img = screen(rng, h, w)
    elif kind == "pattern":
        img = pattern(rng, h, w)
    else:
        img = wall
    return img.clamp(*ALBEDO).contiguous()


def pool_for(names, split: str) -> np.ndarray:
    """The photo bank's indices a split draws from: the HDRIs its lighting may use."""
    from ..data import lighting_sampling

    return np.unique(lighting_sampling.hdri_pool(names, split))
