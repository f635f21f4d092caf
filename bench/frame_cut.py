"""What a frame's edge through the subject does to the network's normals, and what the product
puts beyond it.

    .venv/bin/python -m bench.frame_cut [--frames 32] [--model models/relight-portrait.onnx]
        [--yale]

A face that fills its frame (a tight photo, a head cut by the top of a phone video) reaches the
network with its box reaching past the frame's edge; addon.portrait.crop_planar makes the crop
black there, like a dark backdrop. Held-out val frames (training/intrinsic/data.py, identities
never trained on), rendered under a soft light, are cut as training.intrinsic.train.frame_cut
cuts them (every sample; each side crosses the subject near its face box's edge with its
chance), and the network's normals over the face skin left in the frame are scored against the
light stage's, per band of distance to the nearest cut edge (working-size pixels): mean angle
and mean up/down bias (the network's normal y minus the truth's; negative: it reads the face as
facing down), for the uncut frame and for each way of filling the crop beyond the edge:

* ``black``: the product's (crop_planar);
* ``edge copies``: the frame's edge pixels repeated outward (framing.crop without the black);
* ``edge copies, blurred``: those, blurred by a Gaussian of BLUR pixels beyond the edge;

and ``black, the face template``: the product's black crop with the product's face template
held over the face skin left in the frame (addon.facetemplate.held), which replaces the
normals' up/down low band there.

``--yale`` also relights CroppedYale's tune subjects (training/eval/yale.py, PAIRS pairs each)
through addon.relight_image with each fill in the product's crop: the scale-invariant PSNR over
all pairs and the left/right and top/bottom balance correlation with the real photographs.
CroppedYale's crops cut every side of the face close to it. Writes
``bench/results/frame_cut.{md,json}``.
"""

from __future__ import annotations

import argparse
import contextlib
import pathlib

import numpy as np
import torch

from addon import framing, intrinsic, portrait

from .intrinsic_effects import render, source_light, write_report
from .normals_by_light import angles

ROOT = pathlib.Path(__file__).resolve().parents[1]
FILLS = ("black", "edge copies", "edge copies, blurred")
TEMPLATE = "black, the face template"
BLUR = 6.0  # working-size pixels
BANDS = ((0, 4), (4, 8), (8, 16), (16, None))  # distance to the nearest cut edge, pixels
MIN_BAND = 5  # face pixels a band needs in a frame to count there
PAIRS = 36


def fill(rep: np.ndarray, valid: np.ndarray, how: str) -> np.ndarray:
    """(3, h, w) crop beyond the frame's edge, from ``rep`` (the crop with the frame's edge
    pixels repeated outward, as framing.crop makes it) and ``valid`` (h, w) (the share of each
    pixel inside the frame)."""
    if how == "black":
        return rep * valid
    if how == "edge copies":
        return rep
    if how == "edge copies, blurred":
        return rep * valid + intrinsic.gaussian_blur(rep, BLUR) * (1.0 - valid)
    raise ValueError(f"unknown fill {how!r}; one of {FILLS}")


@contextlib.contextmanager
def product_fill(how: str):
    """Within this context the product's face crop (portrait.crop_planar) is filled with
    ``how`` beyond the frame's edge; "black" leaves the product's own crop in place."""
    if how not in FILLS:
        raise ValueError(f"unknown fill {how!r}; one of {FILLS}")
    if how == "black":
        yield
        return
    original = portrait.crop_planar

    def crop_planar(x, box, size):
        valid = framing.crop_weight(box, x.shape[1:], size)
        rep = np.stack([framing.crop(x[c], box, size) for c in range(x.shape[0])])
        return fill(rep, valid, how).astype(np.float32), valid

    portrait.crop_planar = crop_planar
    try:
        yield
    finally:
        portrait.crop_planar = original


def repeat_edges(img: np.ndarray, inside: np.ndarray) -> np.ndarray:
    """(3, h, w) ``img`` with the pixels outside the rectangle ``inside`` (h, w) bool replaced by
    copies of its nearest edge pixels: the crop of a frame cut there."""
    rows, cols = np.nonzero(inside.any(1))[0], np.nonzero(inside.any(0))[0]
    t, b, left, r = rows[0], rows[-1], cols[0], cols[-1]
    h, w = inside.shape
    core = img[:, t:b + 1, left:r + 1]
    return np.pad(core, ((0, 0), (t, h - 1 - b), (left, w - 1 - r)), mode="edge")


def edge_distance(inside: np.ndarray) -> np.ndarray:
    """(h, w) distance in pixels (pixel centres) from each pixel of the rectangle ``inside`` to
    its nearest side that cuts the frame (a side on the picture's own border cuts nothing);
    infinite where no side cuts."""
    h, w = inside.shape
    rows, cols = np.nonzero(inside.any(1))[0], np.nonzero(inside.any(0))[0]
    yy, xx = np.mgrid[:h, :w].astype(np.float64)
    d = np.full((h, w), np.inf)
    if rows[0] > 0:
        d = np.minimum(d, yy - rows[0] + 0.5)
    if rows[-1] < h - 1:
        d = np.minimum(d, rows[-1] - yy + 0.5)
    if cols[0] > 0:
        d = np.minimum(d, xx - cols[0] + 0.5)
    if cols[-1] < w - 1:
        d = np.minimum(d, cols[-1] - xx + 0.5)
    return d


def band_scores(pred: np.ndarray, truth: np.ndarray, sel: np.ndarray) -> tuple[float, float]:
    """(mean angle in degrees, mean up/down bias) of the normals ``pred`` against ``truth``
    (3, h, w) over ``sel`` (h, w) bool."""
    p, t, deg = angles(pred, truth, sel)
    return float(deg.mean()), float((p[1] - t[1]).mean())


def templated(session, res, valid: np.ndarray) -> np.ndarray:
    """(3, h, w) the normals of the network's result ``res`` on a crop with the product's face
    template held over the face skin inside the frame (``valid``), as addon.portrait.buffers
    holds them (portrait.templated)."""
    return portrait.templated(portrait.result_buffers(session, res, valid),
                              session.card.working_size).normal


def band_name(lo, hi) -> str:
    return f"{lo}+ px" if hi is None else f"{lo}-{hi} px"


def synthetic(model: str, n_frames: int) -> dict:
    from addon import api
    from training.intrinsic import data
    from training.intrinsic.train import frame_cut, normalise_batch

    torch.set_num_threads(1)
    ds = data.IntrinsicFrames("val", 128, 0, varied_backdrops=False)
    session = api.session(model, 1)
    source = source_light()
    gen = torch.Generator().manual_seed(0)
    acc: dict = {}
    for f in range(min(n_frames, ds.n)):
        a = ds.frame(f)
        face = a["label"] == data.SKIN
        if int(face.sum()) < 50:
            continue
        img = normalise_batch(torch.from_numpy(render(a, source))[None])[0]
        target = torch.zeros(1, 9, *face.shape)
        target[:, 8] = torch.from_numpy(face.astype(np.float32))
        batch = {"image": img[None], "target": target, "fg": torch.ones(1, 1, *face.shape)}
        inside = frame_cut(batch, gen, 1.0)["inside"][0, 0].numpy() > 0.5
        if inside.all():
            continue  # no side of this sample landed on the subject
        x = img.numpy()
        rep = repeat_edges(x, inside)
        preds = {"uncut": session.run_planar(x, mirror=portrait.MIRROR).normal}
        for how in FILLS:
            res = session.run_planar(fill(rep, inside.astype(np.float32), how),
                                     mirror=portrait.MIRROR)
            preds[how] = res.normal
            if how == "black":
                preds[TEMPLATE] = templated(session, res, inside.astype(np.float32))
        truth = data.dense(a, a["normal"])
        dist = edge_distance(inside)
        for lo, hi in BANDS:
            sel = face & inside & (dist >= lo) & (dist < (np.inf if hi is None else hi))
            if int(sel.sum()) < MIN_BAND:
                continue
            for name, n in preds.items():
                ang, bias = band_scores(n, truth, sel)
                acc.setdefault((name, band_name(lo, hi)), []).append((ang, bias, int(sel.sum())))
    out = {}
    order = {name: i for i, name in enumerate(("uncut", FILLS[0], TEMPLATE, *FILLS[1:]))}
    for (name, band), v in sorted(acc.items(), key=lambda kv: order[kv[0][0]]):
        v = np.array(v)
        out[f"{name} | {band}"] = {"angle_deg": float(np.average(v[:, 0], weights=v[:, 2])),
                                   "up_down_bias": float(np.average(v[:, 1], weights=v[:, 2])),
                                   "frames": len(v), "pixels": int(v[:, 2].sum())}
    return out


def yale_fills(model: str) -> dict:
    from training.eval import yale

    out = {}
    for how in FILLS:
        with product_fill(how):
            res = yale.run([model], n_pairs=PAIRS, split="tune", progress=lambda *_: None)
        name = next(iter(res["balance_correlation"]))
        bc = res["balance_correlation"][name]
        out[how] = {"psnr_all": res["results"]["scale_invariant"][name]["all"]["psnr"],
                    "left_right": bc["left_right"], "top_bottom": bc["top_bottom"],
                    "pairs": bc["pairs"], "subjects": bc["subjects"]}
    return out


def markdown(res: dict, command: str, machine: str) -> str:
    lines = [f"Produced by `{command}` on {machine}.", "",
             f"Model: {res['model']}. Held-out val frames cut by the frame's edge; the network's "
             "normals over the face skin left in the frame, by distance to the nearest cut "
             "edge.", "",
             "| crop beyond the edge | distance | angle (deg) | up/down bias | frames |",
             "| --- | --- | --- | --- | --- |"]
    for k, v in res["synthetic"].items():
        name, band = k.split(" | ")
        lines.append(f"| {name} | {band} | {v['angle_deg']:.2f} | {v['up_down_bias']:+.3f} | "
                     f"{v['frames']} |")
    if res.get("yale"):
        lines += ["", f"CroppedYale tune subjects through addon.relight_image ({PAIRS} pairs "
                  "each), the product's crop filled each way:", "",
                  "| crop beyond the edge | PSNR all (dB, scale-invariant) | left/right | "
                  "top/bottom | pairs |", "| --- | --- | --- | --- | --- |"]
        for how, v in res["yale"].items():
            lines.append(f"| {how} | {v['psnr_all']:.2f} | {v['left_right']:.3f} | "
                         f"{v['top_bottom']:.3f} | {v['pairs']} |")
    return "\n".join(lines) + "\n"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--frames", type=int, default=32)
    ap.add_argument("--model", default=str(ROOT / "models" / "relight-portrait.onnx"))
    ap.add_argument("--yale", action="store_true", help="also relight CroppedYale's tune "
                    "subjects with each fill")
    ap.add_argument("--out", default=str(ROOT / "bench" / "results" / "frame_cut"))
    a = ap.parse_args(argv)
    res = {"model": pathlib.Path(a.model).name, "synthetic": synthetic(a.model, a.frames)}
    if a.yale:
        res["yale"] = yale_fills(a.model)
    write_report(a.out, "frame_cut", argv, res, markdown)


if __name__ == "__main__":
    main()
