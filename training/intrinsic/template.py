"""Build the face template that addon/facetemplate.py lays over the network's normals: the
light stage's near-frontal heads' exact normals, each frame and its mirror image resampled to a
grid set by its face skin's own extent (centre, square root of its area) and averaged, weighted
by the sub-pixel matte.

    .venv/bin/python -m training.intrinsic.template [--cache cache/intrinsic/val_128 ...] \
        [--out models/face-template/template.npz]

The frames are the validation builds' (training.intrinsic.data --split val; held-out
identities, so no training identity shapes it). Writes the .npz (``normal`` (3, T, T),
``reach``) and a .json card beside it: the command, the frames it used, and the ICT-FaceKit
licence notice the template, derived from its heads, carries.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import sys

import numpy as np

from addon import facetemplate

from . import data

ROOT = pathlib.Path(__file__).resolve().parents[2]
DEFAULT_CACHES = (ROOT / "cache" / "intrinsic" / "val_128",
                  ROOT / "cache" / "intrinsic-longval" / "val_128")
DEFAULT_OUT = ROOT / "models" / "face-template" / "template.npz"
SIZE = 64          # the template's grid, T x T
REACH = 1.3        # face sizes each way from the face skin's centre
MAX_TURN = 0.15    # the face skin's mean sideways normal above which a head counts as turned
NOTICE = ROOT.parent / "shared" / "data" / "heads" / "LICENSE-ict-facekit.txt"


def resample(field: np.ndarray, frame: tuple[float, float, float], size: int = SIZE,
             reach: float = REACH) -> np.ndarray:
    """(C, size, size) of an (C, H, W) ``field`` at the template's grid about the face skin's
    ``frame`` (facetemplate.skin_frame's), bilinear (facetemplate.bilinear_weights, the weights
    the product lays the template back with); 0 beyond the field."""
    cy, cx, s = frame
    step = 2.0 * reach * s / size  # field pixels from one grid sample to the next
    first = (0.5 / size * 2.0 - 1.0) * reach * s - 0.5  # the first sample, less the centre
    wy, _ = facetemplate.bilinear_weights(size, cy + first, step, field.shape[1])
    wx, _ = facetemplate.bilinear_weights(size, cx + first, step, field.shape[2])
    return np.matmul(np.matmul(wy, np.asarray(field, np.float32)), wx.T)


def mirrored(normal: np.ndarray, face: np.ndarray, matte: np.ndarray):
    """The frame's buffers flipped left to right (the normals' x negated)."""
    n = normal[:, :, ::-1].copy()
    n[0] *= -1.0
    return n, face[:, ::-1].copy(), matte[:, ::-1].copy()


def template_from(frames, size: int = SIZE, reach: float = REACH,
                  max_turn: float = MAX_TURN) -> tuple[np.ndarray, int]:
    """((3, size, size) the matte-weighted mean normals, how many frames it took) over
    ``frames``, an iterable of ((3, H, W) normal, (H, W) face skin, (H, W) matte): each
    near-frontal frame (the face skin's mean sideways normal within ``max_turn``) and its
    mirror image, at the grid of its own face skin (resample)."""
    total = np.zeros((3, size, size), np.float64)
    weight = np.zeros((size, size), np.float64)
    used = 0
    for normal, face, matte in frames:
        skin = (face > 0.5) & (matte > 0.5)
        if skin.sum() < facetemplate.MIN_SKIN or abs(float(normal[0][skin].mean())) > max_turn:
            continue
        for n, f, m in ((normal, face, matte), mirrored(normal, face, matte)):
            got = resample(np.concatenate([n, m[None]], 0), facetemplate.skin_frame(f, m),
                           size, reach)
            total += got[:3] * got[3]
            weight += got[3]
        used += 1
    if used == 0:
        raise ValueError("no near-frontal face among the frames: build the val caches first "
                         "(python -m training.intrinsic.data --split val --res 128 --frames 96)")
    return (total / np.maximum(weight, 1e-6)).astype(np.float32), used


def cache_frames(folders):
    """(normal, face, matte) of every frame in the cache ``folders`` (their exact buffers)."""
    for folder in folders:
        for path in sorted(pathlib.Path(folder).glob("frame_*.bin")):
            t = data.static_target(data.load_frame(path))
            yield t[0:3], t[8], t[7]


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--cache", action="append", help="a val cache folder (repeatable; default "
                   "cache/intrinsic/val_128 and cache/intrinsic-longval/val_128, those there)")
    p.add_argument("--out", default=str(DEFAULT_OUT))
    a = p.parse_args(argv)
    folders = [pathlib.Path(c) for c in a.cache] if a.cache else [
        f for f in DEFAULT_CACHES if f.is_dir()]
    missing = [str(f) for f in folders if not f.is_dir()]
    if not folders or missing:
        print("template: no val cache at " + (", ".join(missing) or ", ".join(
            str(f) for f in DEFAULT_CACHES)) + "; build one with python -m "
            "training.intrinsic.data --split val --res 128 --frames 96", file=sys.stderr)
        return 2
    try:
        normal, used = template_from(cache_frames(folders))
    except ValueError as e:
        print(f"template: {e}", file=sys.stderr)
        return 2
    out = pathlib.Path(a.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(out, normal=normal.astype(np.float16), reach=np.float32(REACH))
    card = {"what": "face template: the light stage's near-frontal val heads' mean normals, "
                    "on a grid set by the face skin's centre and size (addon/facetemplate.py)",
            "command": " ".join(["python -m training.intrinsic.template",
                                 *(argv if argv is not None else sys.argv[1:])]),
            "frames": used, "caches": [str(f.relative_to(ROOT)) if f.is_relative_to(ROOT)
                                       else str(f) for f in folders],
            "size": SIZE, "reach": REACH, "max_turn": MAX_TURN,
            "licence": "derived from ICT-FaceKit (MIT): " + (
                NOTICE.read_text() if NOTICE.is_file() else
                "Copyright (c) 2020 USC Institute for Creative Technologies; MIT License")}
    out.with_suffix(".json").write_text(json.dumps(card, indent=2) + "\n")
    print(f"wrote {out} and {out.with_suffix('.json')} from {used} frames")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
