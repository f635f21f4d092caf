"""Lighting sampling of the paper (sec. 4.3): environments G, point lights H, and the triplet.

* G: the CC0 HDRIs in ``../shared/data/hdri`` down-sampled to light vectors with
  ``addon.hdri.downsample`` at a random yaw, each normalised to a mean radiance of 1 and then given
  a random intensity (log-uniform 0.25..4) and a random colour cast (per-channel gain
  exp(N(0, 0.15))). Down-sampling an HDRI is slow (tens of ms), so each map is down-sampled once at
  eight sub-column yaw offsets; a whole-column turn is then an exact roll of the columns.
* H: one to three point lights of uniformly random colour, at a uniformly random direction and a
  distance from the subject's centre uniform in (1, 2.5] (outside the unit sphere, at most 1.5 away
  from it), projected onto the sphere by ``addon.lamps.project_point_light``; their irradiance at
  the subject's centre is uniform in 0.5..4 (times the colour).
* The triplet: L^i = X^i, L^j = b1 L^i + (1 - b1) X^j, L^k = b2 L^j + (1 - b2) X^k + Y with
  X ~ G, Y ~ H, b1, b2 ~ Beta(0.5, 0.5). With ``sampling=False`` (the paper's "w/o sampling"
  ablation: only the discrete environment maps) L^i = L^j = X^i and L^k = X^k.
* Held-out lighting: four of the 26 HDRIs (``HELD_OUT_HDRIS``) never light a training sample; in
  the val and test splits half of the environment draws come from them, so held-out metrics also
  measure unseen lighting. Blender's own studio maps stay in training: the add-on offers them as
  presets.
"""

from __future__ import annotations

import functools
import pathlib

import numpy as np

from addon import hdri, lightvec
from addon.hdri_io import read_hdri
from addon.lamps import project_point_light

SUB_STEPS = 8  # yaw offsets per 22.5-degree column that are down-sampled exactly
# One indoor, two outdoor and one workshop map that training never sees (see the docstring).
HELD_OUT_HDRIS = ("pmndrs/lobby", "pmndrs/park", "pmndrs/venice", "pmndrs/workshop")


def hdri_paths(data_root) -> list[pathlib.Path]:
    paths = sorted((pathlib.Path(data_root) / "hdri").glob("*/*.exr"))
    if not paths:
        from addon.errors import InputError
        raise InputError(f"No HDRIs found under {pathlib.Path(data_root) / 'hdri'}; the light "
                         "stage needs ../shared/data/hdri/*/*.exr.")
    return paths


@functools.lru_cache(maxsize=2)
def environment_bank(data_root) -> tuple[tuple[str, ...], np.ndarray]:
    """(names, (n_hdri, SUB_STEPS, 16, 16, 3) float32): each HDRI at each sub-column yaw, mean 1."""
    names, bank = [], []
    for p in hdri_paths(data_root):
        img = read_hdri(p)
        rows = []
        for s in range(SUB_STEPS):
            lv = hdri.downsample(img, yaw_degrees=s * 22.5 / SUB_STEPS, max_width=256,
                                    repair=True)  # a few CC0 maps hold tiny negative pixels
            rows.append(lv / max(float(np.mean(lv)), 1e-6))
        names.append(f"{p.parent.name}/{p.stem}")
        bank.append(np.stack(rows))
    return tuple(names), np.stack(bank).astype(np.float32)


def environment(bank: np.ndarray, index: int, yaw_degrees: float) -> np.ndarray:
    """HDRI ``index`` of the bank turned by ``yaw_degrees`` (to 1/8 of a column, exactly)."""
    step = int(round(yaw_degrees / (22.5 / SUB_STEPS))) % (lightvec.COLS * SUB_STEPS)
    whole, sub = divmod(step, SUB_STEPS)
    # In the default front view, hdri.downsample's yaw of 22.5 degrees is exactly a roll of the
    # light vector by one column, so whole columns compose with the sub-column maps (tested).
    return np.roll(bank[index, sub], whole, axis=1)


def hdri_pool(names, split: str) -> np.ndarray:
    """Bank indices a split draws environments from (uniformly): training only the seen maps;
    val/test the seen and the held-out maps repeated so that each group gets half the draws."""
    held = [i for i, n in enumerate(names) if n in HELD_OUT_HDRIS]
    seen = [i for i, n in enumerate(names) if n not in HELD_OUT_HDRIS]
    if split == "train" or not held:
        return np.array(seen, np.int64)
    return np.array(seen * len(held) + held * len(seen), np.int64)


def sample_g(rng: np.random.Generator, bank: np.ndarray, pool=None) -> np.ndarray:
    index = int(rng.integers(len(bank))) if pool is None else int(pool[rng.integers(len(pool))])
    lv = environment(bank, index, float(rng.uniform(0, 360)))
    gain = np.exp(rng.uniform(np.log(0.25), np.log(4.0))) * np.exp(rng.normal(0, 0.15, 3))
    return (lv * gain).astype(np.float32)


def point_lamp(rng: np.random.Generator, d: np.ndarray, tint=(0.0, 1.0)) -> np.ndarray:
    """(16, 16, 3) a point lamp in the unit direction ``d`` at a random distance (1 to 2.5
    subject radii), its colour each channel uniform in ``tint`` times a random gain, scaled by
    the distance squared so the gain sets the irradiance it gives the subject."""
    dist = rng.uniform(1.0, 2.5)
    if dist <= 1.0:  # uniform() may return the lower bound; keep strictly outside
        dist = 1.0 + 1e-6
    colour = rng.uniform(*tint, 3) * rng.uniform(0.5, 4.0)
    return project_point_light(d * dist, colour * dist * dist, subject_radius=1.0)


def sample_h(rng: np.random.Generator) -> np.ndarray:
    out = np.zeros(lightvec.SHAPE, np.float32)
    for _ in range(int(rng.integers(1, 4))):
        d = rng.normal(size=3)
        d /= max(np.linalg.norm(d), 1e-9)
        out += point_lamp(rng, d)
    return out


def sample_triplet(rng: np.random.Generator, bank: np.ndarray, sampling: bool = True, pool=None):
    """(L^i, L^j, L^k) float32 (16, 16, 3) each; environments from bank indices ``pool``."""
    xi = sample_g(rng, bank, pool)
    if not sampling:
        return xi, xi.copy(), sample_g(rng, bank, pool)
    xj, xk = sample_g(rng, bank, pool), sample_g(rng, bank, pool)
    y = sample_h(rng)
    b1, b2 = rng.beta(0.5, 0.5, 2)
    lj = b1 * xi + (1 - b1) * xj
    lk = b2 * lj + (1 - b2) * xk + y
    return xi, lj.astype(np.float32), lk.astype(np.float32)
