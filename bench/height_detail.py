"""How much of a face's fine relief the network's shadows' height holds, against the light stage's.

    .venv/bin/python -m bench.height_detail [--frames 24] [--model models/relight-portrait.onnx]
        [--cache cache/intrinsic-longval --out bench/results/height_detail_long_hair]

Held-out val frames (training/intrinsic/data.py, identities never trained on) are rendered under
the effects bench's soft source light and read by the network as the product's face crop reads them
(the picture and its mirror image, the face template held over the mean and the face skin's
normals' detail raised, portrait.templated; the finer sampling of the box is left out: the cached
frames are 128 pixels). Over the face skin, per frame: the standard deviation of the shadows'
height (``intrinsic.shadow_height``) less its Gaussian blur of ``intrinsic.SHADOW_DETAIL_SIGMA``
pixels (the relief that casts the small shadows: the nose, the brows over the eye sockets, the
lips), over the same of the exact buffers' height; and the blurred height's range (5th to 95th
percentile), over the exact one's (the face's coarser shape). Rows: the network's height as drawn
(``relief`` 1) and as the renderer marches it (``intrinsic.SHADOW_DETAIL``, chosen on CroppedYale's
real faces, which the network draws flatter still); then, as drawn, the network's normals over the
exact height and the exact normals over the network's height. shadow_height gives the height the
normals' slopes, so the two say which of the network's buffers the flat relief comes from. Median
and the 10th-90th percentiles over the frames.
Writes ``bench/results/height_detail.{md,json}``.
"""

from __future__ import annotations

import argparse
import dataclasses
import pathlib

import numpy as np
import torch

from addon import intrinsic, portrait
from training.intrinsic.train import normalise_batch

from .intrinsic_effects import exact_buffers, predicted_buffers, render, source_light, write_report
from .normals_by_light import face_frames

ROOT = pathlib.Path(__file__).resolve().parents[1]


def relief(height: np.ndarray, face: np.ndarray) -> tuple[float, float]:
    """(the standard deviation over ``face`` of ``height`` less its blur of
    SHADOW_DETAIL_SIGMA, the blurred height's 5th-to-95th percentile range there)."""
    low = intrinsic.gaussian_blur(height, intrinsic.SHADOW_DETAIL_SIGMA)
    lo, hi = np.percentile(low[face], [5, 95])
    return float((height - low)[face].std()), float(hi - lo)


def run(model: str, n_frames: int = 24, cache=None) -> dict:
    from addon import api

    torch.set_num_threads(1)
    session = api.session(model, 1)
    rows: dict = {}
    for a, face in face_frames(n_frames, cache):
        exact = exact_buffers(a)
        d_exact, r_exact = relief(intrinsic.shadow_height(exact, 1.0), face)
        img = normalise_batch(torch.from_numpy(render(a, source_light()))[None])[0].numpy()
        bufs = portrait.templated(predicted_buffers(session, img), session.card.working_size)
        for name, b, k in (("as drawn", bufs, 1.0), ("as marched", bufs, intrinsic.SHADOW_DETAIL),
                           ("its normals, the exact height", dataclasses.replace(
                               exact, normal=bufs.normal), 1.0),
                           ("the exact normals, its height", dataclasses.replace(
                               bufs, normal=exact.normal), 1.0)):
            d, r = relief(intrinsic.shadow_height(b, k), face)
            rows.setdefault(name, []).append((d / d_exact, r / r_exact, d, d_exact))
    out = {}
    for name, v in rows.items():
        v = np.array(v)
        out[name] = {"detail": float(np.median(v[:, 0])),
                     "detail_10_90": [float(x) for x in np.percentile(v[:, 0], [10, 90])],
                     "range": float(np.median(v[:, 1])),
                     "detail_px": float(np.median(v[:, 2])),
                     "exact_detail_px": float(np.median(v[:, 3])), "frames": len(v)}
    return {"model": str(model), "detail": intrinsic.SHADOW_DETAIL,
            "sigma": intrinsic.SHADOW_DETAIL_SIGMA, "rows": out}


def markdown(res: dict, command: str, machine: str) -> str:
    lines = [f"Produced by `{command}` on {machine}.", "",
             f"Model: {pathlib.Path(res['model']).name}. The shadows' height over the face skin "
             f"against the light stage's exact height: its detail finer than a Gaussian of "
             f"{res['sigma']:g} pixels (standard deviation, the network's over the exact one's) "
             f"and its coarser shape's range; the renderer marches the detail "
             f"{res['detail']:g} times as drawn.", "",
             "| the network's shadows' height | detail over exact (median, 10-90%) | detail (px) "
             "| exact detail (px) | coarse range over exact | frames |",
             "| --- | --- | --- | --- | --- | --- |"]
    for name, v in res["rows"].items():
        lo, hi = v["detail_10_90"]
        lines.append(f"| {name} | {v['detail']:.2f} ({lo:.2f}-{hi:.2f}) | {v['detail_px']:.2f} "
                     f"| {v['exact_detail_px']:.2f} | {v['range']:.2f} | {v['frames']} |")
    return "\n".join(lines) + "\n"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--frames", type=int, default=24)
    ap.add_argument("--model", default=str(ROOT / "models" / "relight-portrait.onnx"))
    ap.add_argument("--out", default=str(ROOT / "bench" / "results" / "height_detail"))
    ap.add_argument("--cache", help="the val frames' cache root (default cache/intrinsic)")
    a = ap.parse_args(argv)
    write_report(a.out, "height_detail", argv, run(a.model, a.frames, a.cache), markdown)


if __name__ == "__main__":
    main()
