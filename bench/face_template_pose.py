"""What the face template does to the normals of heads turned or pitched away from the camera.

    .venv/bin/python -m bench.face_template_pose [--frames 96] [--model models/relight-portrait.onnx]

Held-out val frames (training/intrinsic/data.py, identities never trained on) are rendered by
the light stage under one lamp (a little fill beside it) from above, level in front and the side
(bench.normals_by_light's lamps) and read as the product's relighting passes read a crop
(addon.portrait.buffers, without the mirror image): without the face template, with it held over
every head (addon.facetemplate.TURN set beyond any turn) and as the product holds it (faded out
as the head turns). Per band of the head's turn (the light stage's mean sideways normal over the
face skin) and of its pitch (the mean up/down normal): the correlation of the vertical normal
component with the truth's, and the mean angle, over the face skin; and how the mean up/down
normal each reads follows the truth's (bias, slope, correlation). The template is a frontal
face's; a turned head it does not describe should not pay for it, and a template's own pitch
replaces the head's. Writes ``bench/results/face_template_pose.{md,json}``.
"""

from __future__ import annotations

import argparse
import pathlib

import numpy as np

from training.intrinsic import data

from .intrinsic_effects import lamp, render, write_report
from .normals_by_light import LAMPS, face_frames, face_scores

ROOT = pathlib.Path(__file__).resolve().parents[1]
BANDS = ((0.0, 0.1), (0.1, 0.15), (0.15, 0.2), (0.2, 1.0))  # |mean sideways normal| of the truth
PITCH_BANDS = ((-1.0, -0.02), (-0.02, 0.02), (0.02, 0.06), (0.06, 1.0))  # its mean up/down normal
LAMP_NAMES = ("above", "level", "side")
VARIANTS = ("no template", "template on every head", "the product")


def read(session, img: np.ndarray, variant: str):
    """The buffers of one linear image as the relighting passes read it, under ``variant``."""
    from addon import facetemplate, portrait

    if variant == "no template":
        return portrait.buffers(session, img, shape=False)
    kept = facetemplate.TURN
    if variant == "template on every head":
        facetemplate.TURN = (1e9, 2e9)  # beyond any turn
    try:
        return portrait.buffers(session, img, shape=True)
    finally:
        facetemplate.TURN = kept


def run(model: str, n_frames: int = 96) -> dict:
    import torch

    from addon import api

    torch.set_num_threads(1)
    session = api.session(model, 1)
    rows = []
    for a, face in face_frames(n_frames):
        truth = data.dense(a, a["normal"])
        turn = abs(float(truth[0][face].mean()))
        pitch = float(truth[1][face].mean())
        for lname in LAMP_NAMES:
            img = render(a, lamp(LAMPS[lname], 3.0, 0.05)).astype(np.float32)
            for v in VARIANTS:
                normal = read(session, img, v).normal
                s = face_scores(normal, truth, face)
                n = normal[:, face] / np.maximum(np.linalg.norm(normal[:, face], axis=0), 1e-9)
                rows.append((turn, pitch, v, s["corr_y"], s["angle_deg"], float(n[1].mean())))
    out = {"turn": {}, "pitch": {}, "pitch_reading": {}}
    for key, col, bands in (("turn", 0, BANDS), ("pitch", 1, PITCH_BANDS)):
        for lo, hi in bands:
            for v in VARIANTS:
                sel = [r for r in rows if lo <= r[col] < hi and r[2] == v]
                if sel:
                    out[key][f"{lo:+.2f} to {hi:+.2f} | {v}"] = {
                        "corr_y": float(np.mean([r[3] for r in sel])),
                        "angle_deg": float(np.mean([r[4] for r in sel])), "readings": len(sel)}
    for v in VARIANTS:
        got = np.array([(r[1], r[5]) for r in rows if r[2] == v])
        out["pitch_reading"][v] = {"bias": float((got[:, 1] - got[:, 0]).mean()),
                                   "slope": float(np.polyfit(got[:, 0], got[:, 1], 1)[0]),
                                   "corr": float(np.corrcoef(got.T)[0, 1]), "readings": len(got)}
    return out


def markdown(res: dict, command: str, machine: str) -> str:
    lines = [f"Produced by `{command}` on {machine}.", ""]
    for key, what in (("turn", "head turn (mean sideways normal)"),
                      ("pitch", "head pitch (mean up/down normal)")):
        lines += [f"| {what} | normals | up/down correlation | angle (deg) | readings |",
                  "| --- | --- | --- | --- | --- |"]
        for k, v in res[key].items():
            band, variant = k.split(" | ")
            lines.append(f"| {band} | {variant} | {v['corr_y']:.3f} | {v['angle_deg']:.2f} | "
                         f"{v['readings']} |")
        lines.append("")
    lines += ["The mean up/down normal over the face skin as each reads it, against the truth's:",
              "", "| normals | bias | slope | correlation | readings |",
              "| --- | --- | --- | --- | --- |"]
    for v, r in res["pitch_reading"].items():
        lines.append(f"| {v} | {r['bias']:+.3f} | {r['slope']:.2f} | {r['corr']:.2f} | "
                     f"{r['readings']} |")
    return "\n".join(lines) + "\n"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--frames", type=int, default=96)
    ap.add_argument("--model", default=str(ROOT / "models" / "relight-portrait.onnx"))
    ap.add_argument("--out", default=str(ROOT / "bench" / "results" / "face_template_pose"))
    a = ap.parse_args(argv)
    write_report(a.out, "face_template_pose", argv, run(a.model, a.frames), markdown)


if __name__ == "__main__":
    main()
