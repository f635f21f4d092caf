"""A contact sheet of the synthetic light stage, to look at.

    .venv/bin/python -m training.data.contact_sheet [--out demo/lightstage_sheet.png] [--size 96]

Rows: 16 of the 114 OLAT images of one frame (every 7th light, auto-exposed each); the same frame
under six HDRIs and two point-light sets; parsing labels, forward flow and its valid mask, the
mask; eight consecutive 25 fps frames of the performance under one HDRI; the same frame under that
HDRI in front of the varied training backdrops (``--backdrops varied``: photo crops, chroma-key
screens, busy patterns, the stage's wall).
"""

from __future__ import annotations

import argparse
import pathlib

import numpy as np
import torch

from addon.contract import PARSING_CLASSES

from . import lighting_sampling
from ..lightstage import assets, backdrops
from ..lightstage.png import to_srgb8, write_png
from ..lightstage.scene import Scene
from ..lightstage.subject import FPS, Performance, sample_camera, sample_identity

ROOT = pathlib.Path(__file__).resolve().parents[2]
PALETTE = np.array([[0, 0, 0], [230, 180, 150], [90, 60, 30], [40, 20, 10], [60, 120, 255],
                    [220, 40, 60], [255, 255, 230], [170, 120, 200], [60, 180, 90]], np.uint8)


def _img(x: torch.Tensor, exposure=None) -> np.ndarray:
    a = x.permute(1, 2, 0).numpy()
    if exposure is None:
        p = float(np.percentile(a.mean(2), 95))
        exposure = 0.7 / p if p > 0 else 1.0
    return to_srgb8(a, exposure)


def _flow_rgb(flow: torch.Tensor, valid: torch.Tensor) -> np.ndarray:
    f = flow.numpy()
    mag = np.hypot(f[0], f[1])
    s = max(float(mag.max()), 1e-6)
    rgb = np.stack([0.5 + 0.5 * f[0] / s, 0.5 + 0.5 * f[1] / s, 0.5 + 0 * f[0]], -1)
    rgb *= (0.3 + 0.7 * valid[0].numpy())[..., None]
    return (np.clip(rgb, 0, 1) * 255).astype(np.uint8)


def sheet(size: int = 96, identity: int = 33, data_root=None) -> np.ndarray:
    root = pathlib.Path(data_root) if data_root else assets.default_data_root()
    model = assets.load_head(root)
    names, bank = lighting_sampling.environment_bank(root)
    rng = np.random.default_rng(identity)
    cam = sample_camera(rng, size)
    scene = Scene(sample_identity(identity), Performance(identity, model.expression_names), cam,
                  root, backdrop_seed=identity)
    f = scene.frame(1.0)
    olat = scene.shade_weights(f, torch.ones(114, 1, 3) * torch.eye(114)[:, :, None])
    row1 = [_img(olat[j]) for j in range(0, 114, 7)][:8]
    row2 = [_img(olat[j]) for j in range(0, 114, 7)][8:16]
    envs = [lighting_sampling.environment(bank, names.index(n), 40.0 * i) for i, n in enumerate(
        ("blender/studio", "blender/city", "blender/forest", "blender/sunset", "pmndrs/lobby",
         "pmndrs/warehouse"))]
    envs += [lighting_sampling.sample_h(np.random.default_rng(s)) + 0.05 for s in (1, 2)]
    lit = scene.shade(f, envs)
    row3 = [_img(x) for x in lit]
    f1 = scene.frame(1.0 + 1 / FPS)
    fl, valid = scene.flow(f, f1)
    par = PALETTE[f.gb.label.numpy()]
    row4 = [par, _flow_rgb(fl, valid), (np.repeat(valid[0].numpy()[..., None], 3, 2) * 255)
            .astype(np.uint8), (np.repeat(f.gb.mask.numpy()[..., None], 3, 2) * 255).astype(np.uint8)]
    seq = [scene.shade(scene.frame(1.0 + n * 3 / FPS), [envs[0]])[0] for n in range(4)]
    seq_exposure = 0.7 / float(np.percentile(seq[0].mean(0).numpy(), 95))
    row4 += [_img(x, exposure=seq_exposure) for x in seq]
    _, photos = backdrops.photo_bank(root)
    brng = np.random.default_rng(identity)
    h, w = f.gb.mask.shape
    walls = [backdrops.photo(brng, h, w, photos[names.index(n)]) for n in
             ("blender/interior", "pmndrs/apartment", "blender/city")]
    walls += [backdrops.screen(brng, h, w) for _ in range(2)]
    walls += [backdrops.pattern(brng, h, w) for _ in range(2)] + [scene.backdrop]
    row5 = []
    for wall in walls:
        scene.backdrop = wall.clamp(*backdrops.ALBEDO)
        row5.append(_img(scene.shade(f, [envs[0]])[0], exposure=seq_exposure))
    rows = [np.concatenate(r, 1) for r in (row1, row2, row3, row4, row5)]
    return np.concatenate(rows, 0)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", default=str(ROOT / "demo" / "lightstage_sheet.png"))
    ap.add_argument("--size", type=int, default=96)
    ap.add_argument("--identity", type=int, default=33)
    a = ap.parse_args(argv)
    torch.set_num_threads(2)
    out = pathlib.Path(a.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    write_png(out, sheet(a.size, a.identity))
    print(f"wrote {out} (classes: {', '.join(PARSING_CLASSES[1:])})")


if __name__ == "__main__":
    main()
