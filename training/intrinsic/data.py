"""Intrinsic samples: a light-stage frame under a random light, with its exact buffers as targets.

The intrinsic model is supervised by what the light stage knows exactly per pixel: the surface
normal (camera frame: +X right, +Y up, +Z toward the camera, as the light vector), the height
toward the camera in pixels (relative to the subject's median), the albedo, the subject's matte
(sub-pixel coverage), the face-skin label and the light transport (``transfer``: visibility
times cosine toward each of the stage's 114 lights, projected on order-3 spherical harmonics; see
``transfer_matrix``). The picture itself is any light's weighted sum of the frame's 114
one-light-at-a-time transfers, so one rendered frame serves every lighting.

    .venv/bin/python -m training.intrinsic.data --res 128 --frames 1024 --jobs 2

writes ``cache/intrinsic/<split>_<res>/frame_NNNNNN.bin`` (git-ignored). A frame is a pure
function of (split, resolution, index, long hair): frames are the light stage's pool pairs' first
frames (``LightStageDataset.pair_scene``), so the build resumes and can be deleted at any time.
``--long-hair 0.5 --out cache/intrinsic-long`` gives half the identities with hair long hair
(``lightstage.assets.Curtain``), which the light stage's own identities lack.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import pathlib
import time

import numpy as np
import torch

from addon import intrinsic as render
from addon import lightvec
from addon.contract import PARSING_CLASSES

from ..data import lighting_sampling
from ..data.dataset import SPLITS, LightStageDataset, renderer_version
from ..lightstage import backdrops as backdrops_mod
from ..lightstage import layout, pairs, shading
from ..lightstage.scene import stage_dirs

ROOT = pathlib.Path(__file__).resolve().parents[2]
DEFAULT_OUT = ROOT / "cache" / "intrinsic"
MAGIC_FORMAT = 1
SKIN = PARSING_CLASSES.index("skin")
HAIR = PARSING_CLASSES.index("hair")
# Buffers in the order the network predicts them (channels of the target tensor).
TARGETS = ("normal", "height", "albedo", "matte", "face", "transfer", "hair")
TRANSFER = slice(9, 9 + render.TRANSFER_CHANNELS)  # the transfer's channels in the target


def transfer_matrix() -> np.ndarray:
    """(114, 16) float32: a pixel's transfer (addon.intrinsic's ``transfer`` buffer) is its 114
    stage lights' visibility x cosine times this. The light vector reaches the stage through
    ``layout.projection``; the transfer is that per-cell transport's least-squares fit on order-3
    SH (weighted by the cells' solid angles), so that transfer . light_sh(light) is the
    irradiance the stage gives for the light vector, to the fit's order."""
    yc = render.sh_basis(lightvec.directions().reshape(-1, 3).T.astype(np.float64),
                         render.TRANSFER_ORDER).T.astype(np.float64)  # (256, 16)
    om = lightvec.solid_angles().reshape(-1, 1).astype(np.float64)
    return (layout.projection() @ (om * yc) @ np.linalg.inv(yc.T @ (om * yc))).astype(np.float32)


_TRANSFER_MATRIX: list = []


def transfer(a: dict) -> np.ndarray:
    """(16, H, W) the frame's transfer (0 off the subject)."""
    if not _TRANSFER_MATRIX:
        _TRANSFER_MATRIX.append(transfer_matrix())
    return dense(a, a["diffuse"].astype(np.float32) @ _TRANSFER_MATRIX[0])


def folder_for(out, split: str, res: int) -> pathlib.Path:
    return pathlib.Path(out or DEFAULT_OUT) / f"{split}_{int(res)}"


def frame_path(folder: pathlib.Path, i: int) -> pathlib.Path:
    return folder / f"frame_{i:06d}.bin"


def render_frame(ds: LightStageDataset, i: int) -> dict:
    """Arrays of one frame: the transfer (float16) and the exact buffers of its foreground."""
    return frame_arrays(*ds.pair_scene(i), label=i)


def frame_arrays(scene, t: float, label=None) -> dict:
    """render_frame's arrays for any light-stage scene at time ``t`` (``label`` names it in
    errors)."""
    f = scene.frame(t)
    gb = f.gb
    pos = gb.position.reshape(-1, 3)[f.idx]
    nrm = gb.normal.reshape(-1, 3)[f.idx]
    z = pos[:, 2]
    height = (z - z.median()) * f.px_per_cm if len(z) else z
    for name in ("diffuse", "specular"):
        x = getattr(f.transfer, name)
        big = float(x.abs().max()) if x.numel() else 0.0
        if not bool(torch.isfinite(x).all()) or big > 6e4:
            raise ValueError(f"{name} transfer out of float16 range in frame {label}")
    return {"idx": f.idx.numpy().astype(np.int32),
            "diffuse": f.transfer.diffuse.numpy().astype(np.float16),
            "specular": f.transfer.specular.numpy().astype(np.float16),
            "albedo": f.albedo.numpy().astype(np.float32),
            "sss": f.sss.numpy().astype(np.float32),
            "mask": gb.mask.numpy(),
            "cover": (f.cover if f.cover is not None else gb.mask.float()).numpy(),
            "label": gb.label.numpy().astype(np.uint8),
            "backdrop": scene.backdrop.numpy(),
            "normal": nrm.numpy().astype(np.float32),
            "height": height.numpy().astype(np.float32),
            "px_per_cm": np.float64(f.px_per_cm)}


def load_frame(path: pathlib.Path) -> dict:
    return pairs.read_arrays(path)


def shade_inputs(a: dict, backdrop: torch.Tensor | None = None) -> shading.ShadeInputs:
    t = torch.from_numpy
    return shading.ShadeInputs(t(a["idx"]).long(), t(a["diffuse"]), t(a["specular"]),
                               t(a["albedo"]), t(a["sss"]), float(np.reshape(a["px_per_cm"], -1)[0]),
                               t(a["mask"]), t(a["backdrop"]) if backdrop is None else backdrop,
                               t(a["cover"]))


# A studio lamp (sample_light's ``studio``): one near-white lamp on the camera's side of the
# subject, from this range of azimuths and elevations (degrees; CroppedYale's flash positions and
# a film set's key lights span about the same), over a faint environment.
STUDIO_AZIMUTH = 130.0
STUDIO_ELEVATION = (-45.0, 90.0)


def studio_lamp(rng: np.random.Generator) -> np.ndarray:
    """(16, 16, 3) one near-white lamp (each channel within 10%) from the front, anywhere in
    STUDIO_AZIMUTH and STUDIO_ELEVATION (elevation uniform in its sine: uniform over the band)."""
    az = np.radians(rng.uniform(-STUDIO_AZIMUTH, STUDIO_AZIMUTH))
    lo, hi = np.sin(np.radians(STUDIO_ELEVATION))
    sin_el = rng.uniform(lo, hi)
    cos_el = np.sqrt(max(1.0 - sin_el * sin_el, 0.0))
    d = np.array([np.sin(az) * cos_el, sin_el, np.cos(az) * cos_el])
    return lighting_sampling.point_lamp(rng, d, (0.9, 1.1)).astype(np.float32)


def sample_light(rng: np.random.Generator, bank, pool, sky_flip: float = 0.0,
                 studio: float = 0.0) -> np.ndarray:
    """A lighting as the product meets it: an environment, one to three lamps, or both (so hard
    shadows and highlights are as common in training as soft light). ``sky_flip``: the share of
    environments turned upside down (their sky below): HDRIs are lit from above, so a network
    may read a face's up/down shading from that habit rather than from its shape. ``studio``:
    the share of lightings that are one near-white lamp from the front over a faint environment
    (studio_lamp), as a film set's key or a flash lights a face."""
    def env():
        e = lighting_sampling.sample_g(rng, bank, pool)
        return e[::-1].copy() if sky_flip and rng.random() < sky_flip else e

    if studio and rng.random() < studio:
        return (studio_lamp(rng) + rng.uniform(0.0, 0.1) * env()).astype(np.float32)
    kind = rng.random()
    if kind < 0.35:
        return env()
    lamps = lighting_sampling.sample_h(rng)
    if kind < 0.6:
        return (lamps + 0.02 * env()).astype(np.float32)
    return (rng.uniform(0.1, 1.0) * env() + lamps).astype(np.float32)


def dense(a: dict, values: np.ndarray, fill=0.0) -> np.ndarray:
    """(C, H, W) map of per-foreground-pixel values (N, C)."""
    h, w = a["mask"].shape
    out = np.full((values.shape[1], h * w), fill, np.float32)
    out[:, a["idx"]] = values.T
    return out.reshape(-1, h, w)


KEPT_TARGET = "_target"  # a kept frame's static_target, stored with its arrays (IntrinsicFrames)


def static_target(a: dict) -> np.ndarray:
    """(26, H, W) the frame's buffers stacked as the network's target (TARGETS), unflipped: the
    same for every sample of the frame, whatever its light."""
    normal = dense(a, a["normal"].astype(np.float32))
    height = dense(a, a["height"][:, None])
    albedo = dense(a, a["albedo"])
    matte = a["cover"].astype(np.float32)[None]
    face = (a["label"] == SKIN).astype(np.float32)[None]
    hair = (a["label"] == HAIR).astype(np.float32)[None]
    return np.concatenate([normal, height, albedo, matte, face, transfer(a), hair], 0)


def sample(a: dict, rng: np.random.Generator, bank, pool, photo_bank=None, photo_pool=None,
           sky_flip: float = 0.0, studio: float = 0.0) -> dict:
    """``image`` (3, H, W) linear radiance and ``target`` (len(TARGETS) buffers stacked: 3 normal,
    1 height, 3 albedo, 1 matte, 1 face, 16 transfer, 1 hair = 26 channels), ``fg`` (1, H, W)
    where the normal, height, albedo and transfer are defined. A random horizontal flip (normal x
    and the transfer's x-odd coefficients negated) doubles the poses."""
    h, w = a["mask"].shape
    backdrop = None
    if photo_bank is not None:
        backdrop = backdrops_mod.sample(rng, h, w, torch.from_numpy(a["backdrop"]), photo_bank,
                                        photo_pool)
    light = sample_light(rng, bank, pool, sky_flip, studio)
    wts = torch.from_numpy(layout.weights(light)).float()[None]
    img = shading.relight(shade_inputs(a, backdrop), wts, stage_dirs())[0].numpy()
    kept = a.get(KEPT_TARGET)
    target = static_target(a) if kept is None else kept
    fg = a["mask"].astype(np.float32)[None]
    if rng.random() < 0.5:
        img, target, fg = img[..., ::-1], target[..., ::-1].copy(), fg[..., ::-1]
        target[0] *= -1.0
        target[[TRANSFER.start + k for k in render.TRANSFER_X_ODD]] *= -1.0
    elif kept is not None:  # a kept frame's target stays as it is
        target = kept.copy()
    return {"image": np.ascontiguousarray(img, np.float32), "target": np.ascontiguousarray(target),
            "fg": np.ascontiguousarray(fg), "light": light}


class IntrinsicFrames:
    """Map-style dataset over a built frame folder: sample ``idx`` is a pure function of
    (seed, split, idx). Frames stay in memory once read (a 128-px frame is about 4 MB, 6 MB
    once sampled, with its target), unless ``keep_frames`` is False (many processes reading one
    cache share the system's file cache instead of each holding every frame)."""

    def __init__(self, split: str, res: int, seed: int = 0, cache_dir=None, data_root=None,
                 varied_backdrops: bool = True, length: int = 10 ** 7, sky_flip: float = 0.0,
                 studio: float = 0.0, keep_frames: bool = True):
        self.folder = folder_for(cache_dir, split, res)
        man = self.folder / "manifest.json"
        if not man.is_file():
            raise FileNotFoundError(f"No intrinsic frames at {self.folder}; build them with "
                                    f"`python -m training.intrinsic.data --split {split} --res {res}`.")
        info = json.loads(man.read_text())
        self.n = int(info["frames"])
        self.long_hair = float(info.get("long_hair", 0.0))  # share of identities with long hair
        self.split, self.seed, self.length = split, int(seed), int(length)
        self.sky_flip = float(sky_flip)  # share of environments upside down (sample_light)
        self.studio = float(studio)  # share of lightings that are a studio lamp (sample_light)
        root = pathlib.Path(data_root) if data_root else None
        from ..lightstage import assets
        root = root or assets.default_data_root()
        names, self.bank = lighting_sampling.environment_bank(root)
        self.pool = lighting_sampling.hdri_pool(names, split)
        self.photo_bank = self.photo_pool = None
        if varied_backdrops:
            pnames, self.photo_bank = backdrops_mod.photo_bank(root)
            self.photo_pool = backdrops_mod.pool_for(pnames, split)
        self._frames: dict[int, dict] = {}
        self.keep_frames = bool(keep_frames)

    def __len__(self) -> int:
        return self.length

    def frame(self, i: int) -> dict:
        if not self.keep_frames:
            return load_frame(frame_path(self.folder, i))
        if i not in self._frames:
            self._frames[i] = load_frame(frame_path(self.folder, i))
        return self._frames[i]

    def _sampled_frame(self, i: int) -> dict:
        """frame(i) for samples: a kept one holds its static_target beside its arrays, computed
        once rather than for every sample (frame's other readers need none)."""
        a = self.frame(i)
        if self.keep_frames and KEPT_TARGET not in a:
            a[KEPT_TARGET] = static_target(a)
        return a

    def preload(self, progress=print) -> None:
        """Read every frame into memory now (keep_frames): worker processes forked after this
        share them rather than each reading the files (``train.py --preload``); about 6 MB a
        frame at 128 px."""
        if not self.keep_frames:
            raise ValueError("preload needs keep_frames")
        t0 = time.perf_counter()
        for i in range(self.n):
            self._sampled_frame(i)
            if progress and ((i + 1) % 256 == 0 or i + 1 == self.n):
                progress(f"preloaded {i + 1}/{self.n} frames, {time.perf_counter() - t0:.0f} s")

    def __getitem__(self, idx: int) -> dict:
        rng = np.random.default_rng([self.seed, SPLITS[self.split], int(idx), 77])
        a = self._sampled_frame(int(rng.integers(self.n)))
        return sample(a, rng, self.bank, self.pool, self.photo_bank, self.photo_pool,
                      self.sky_flip, self.studio)

    def batch(self, indices) -> dict:
        items = [self[i] for i in indices]
        return {k: torch.from_numpy(np.stack([it[k] for it in items])) for k in items[0]}


# ---------------------------------------------------------------------------------- building

_ds = None


def _init(split, res, data_root, long_hair=0.0):
    global _ds
    torch.set_num_threads(1)
    _ds = LightStageDataset(split, res, data_root=data_root, long_hair=long_hair)


def _render(job):
    i, folder = job
    path = frame_path(folder, i)
    if not path.is_file():
        pairs.write_arrays(path, render_frame(_ds, i))
    return path.stat().st_size


def build(split: str, res: int, n: int, out=None, jobs: int = 1, data_root=None, progress=print,
          long_hair: float = 0.0):
    folder = folder_for(out, split, res)
    folder.mkdir(parents=True, exist_ok=True)
    cmd = f"python -m training.intrinsic.data --split {split} --res {res} --frames {n}"
    if long_hair:
        cmd += f" --long-hair {long_hair:g}" + (f" --out {out}" if out else "")
    info = {"format": MAGIC_FORMAT, "split": split, "resolution": int(res), "frames": int(n),
            "renderer": renderer_version(), "long_hair": float(long_hair), "command": cmd}
    old = folder / "manifest.json"
    if old.is_file():
        prev = json.loads(old.read_text())
        if (prev.get("renderer") != info["renderer"] or prev.get("format") != MAGIC_FORMAT
                or float(prev.get("long_hair", 0.0)) != info["long_hair"]):
            for p in folder.glob("frame_*.bin"):  # another renderer's frames: render them again
                p.unlink()
    t0, total = time.perf_counter(), 0
    work = [(i, folder) for i in range(n)]
    if jobs > 1:
        with multiprocessing.get_context("fork").Pool(jobs, _init,
                                                      (split, res, data_root, long_hair)) as pool:
            for k, size in enumerate(pool.imap(_render, work, chunksize=4), 1):
                total += size
                if progress and (k % 32 == 0 or k == n):
                    progress(f"{k}/{n} frames, {total / 1e9:.2f} GB, {time.perf_counter() - t0:.0f} s")
    else:
        _init(split, res, data_root, long_hair)
        for k, job in enumerate(work, 1):
            total += _render(job)
            if progress and (k % 32 == 0 or k == n):
                progress(f"{k}/{n} frames, {total / 1e9:.2f} GB, {time.perf_counter() - t0:.0f} s")
    tmp = folder / "manifest.json.tmp"
    tmp.write_text(json.dumps({**info, "bytes": int(total)}, indent=2))
    tmp.rename(folder / "manifest.json")
    return folder


def main(argv=None):
    ap = argparse.ArgumentParser(description="Render the intrinsic model's light-stage frames.")
    ap.add_argument("--split", default="train", choices=sorted(SPLITS))
    ap.add_argument("--res", type=int, default=128)
    ap.add_argument("--frames", type=int, default=1024)
    ap.add_argument("--jobs", type=int, default=1)
    ap.add_argument("--out", help=f"cache root (default {DEFAULT_OUT})")
    ap.add_argument("--data-root")
    ap.add_argument("--long-hair", type=float, default=0.0,
                    help="fraction of the identities with hair that wear it long (a curtain over "
                         "the ears to the shoulders; the light stage's own identities have none); "
                         "give such frames their own --out")
    a = ap.parse_args(argv)
    print(build(a.split, a.res, a.frames, a.out, a.jobs, a.data_root, long_hair=a.long_hair))


if __name__ == "__main__":
    main()
