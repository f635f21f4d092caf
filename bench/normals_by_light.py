"""How the intrinsic network's normals depend on where the footage's light comes from.

    .venv/bin/python -m bench.normals_by_light [--frames 24] [--model models/relight-portrait.onnx]
        [--model ...]

Held-out val frames (training/intrinsic/data.py, identities never trained on) are rendered by
the light stage under one lamp (a little fill beside it) from above, level in front, below and
the side, each normalised as the product normalises a crop and run once (the product's mirrored
and finer passes left out: this is the network's own reading); per lamp, over the face skin, the
correlation of the network's up/down and left/right normal components with the light stage's
and the mean angle between the two. A network that reads the face's shape from its shading
scores alike under every lamp; one that leans on light coming from above (as the HDRIs it was
trained under do) reads the up/down shape of a face lit from below poorly. Writes
``bench/results/normals_by_light.{md,json}``.
"""

from __future__ import annotations

import argparse
import pathlib

import numpy as np
import torch

from training.intrinsic import data
from training.intrinsic.train import normalise_batch

from .intrinsic_effects import lamp, render, write_report

ROOT = pathlib.Path(__file__).resolve().parents[1]
# The lamps, in the light frame (+X right, +Y up, +Z toward the camera), with a fill of 0.05.
LAMPS = {"above": (0.0, 1.0, 0.6), "level": (0.0, 0.0, 1.0), "below": (0.0, -1.0, 0.6),
         "side": (-1.0, 0.0, 0.6)}
MIN_FACE = 50  # face-skin pixels a frame needs to count


def angles(pred: np.ndarray, truth: np.ndarray, sel: np.ndarray):
    """(predicted normals made unit, the truth's, the angle between them in degrees), each over
    ``sel`` (h, w) bool of the normals (3, h, w), in float64."""
    p, t = pred[:, sel].astype(np.float64), truth[:, sel].astype(np.float64)
    p = p / np.maximum(np.linalg.norm(p, axis=0), 1e-9)
    return p, t, np.degrees(np.arccos(np.clip((p * t).sum(0), -1.0, 1.0)))


def face_scores(pred: np.ndarray, truth: np.ndarray, face: np.ndarray) -> dict:
    """Over ``face`` (h, w) bool: the correlation of the normals' up/down (y) and left/right (x)
    components (3, h, w) with the truth's, and their mean angle in degrees."""
    p, t, deg = angles(pred, truth, face)
    return {"corr_y": float(np.corrcoef(p[1], t[1])[0, 1]),
            "corr_x": float(np.corrcoef(p[0], t[0])[0, 1]),
            "angle_deg": float(deg.mean())}


def face_frames(n_frames: int, cache=None):
    """Yield (frame, (h, w) bool face skin) of the first ``n_frames`` held-out val frames (of
    ``cache``'s build, default cache/intrinsic) that show at least MIN_FACE face-skin pixels."""
    ds = data.IntrinsicFrames("val", 128, 0, cache, varied_backdrops=False)
    for f in range(min(n_frames, ds.n)):
        a = ds.frame(f)
        face = a["label"] == data.SKIN
        if int(face.sum()) >= MIN_FACE:
            yield a, face


def run(models: list[str], n_frames: int = 24) -> dict:
    from addon import api

    torch.set_num_threads(1)
    sessions = {m: api.session(m, 1) for m in models}
    rows: dict = {}
    for a, face in face_frames(n_frames):
        truth = data.dense(a, a["normal"])
        for lname, d in LAMPS.items():
            img = normalise_batch(torch.from_numpy(render(a, lamp(d, 3.0, 0.05)))[None])[0]
            for m, sess in sessions.items():
                normal = sess.run_planar(img.numpy()).normal
                rows.setdefault((m, lname), []).append(face_scores(normal, truth, face))
    return {f"{m} | {lname}": {**{k: float(np.mean([r[k] for r in v])) for k in v[0]},
                               "frames": len(v)}
            for (m, lname), v in rows.items()}


def markdown(res: dict, command: str, machine: str) -> str:
    lines = [f"Produced by `{command}` on {machine}.", "",
             "| model | lamp | up/down correlation | left/right correlation | angle (deg) "
             "| frames |",
             "| --- | --- | --- | --- | --- | --- |"]
    for k, v in res.items():
        model, lname = k.split(" | ")
        lines.append(f"| {pathlib.Path(model).stem} | {lname} | {v['corr_y']:.3f} | "
                     f"{v['corr_x']:.3f} | {v['angle_deg']:.2f} | {v['frames']} |")
    return "\n".join(lines) + "\n"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--frames", type=int, default=24)
    ap.add_argument("--model", action="append", help="an intrinsic .onnx (repeat for several; "
                    "default: the shipped Portrait)")
    ap.add_argument("--out", default=str(ROOT / "bench" / "results" / "normals_by_light"))
    a = ap.parse_args(argv)
    models = a.model or [str(ROOT / "models" / "relight-portrait.onnx")]
    write_report(a.out, "normals_by_light", argv, run(models, a.frames), markdown)


if __name__ == "__main__":
    main()
