"""What each effect of the intrinsic renderer buys and costs, against the light stage's truth.

    .venv/bin/python -m bench.intrinsic_effects [--frames 24] [--model models/relight-portrait.onnx]
        [--cache cache/intrinsic-longval --out bench/results/intrinsic_effects_long_hair]

Held-out val frames (training/intrinsic/data.py, identities never trained on) are rendered under
a soft source light, then relit by ``addon.intrinsic.shade`` to seven target lights (targets)
and compared with the light stage's own render under each target (its shadows, GGX skin,
subsurface scattering). Two kinds of buffers: the light stage's exact ones, its light transport
included and its height's relief marched as it is (the renderer's own error), and, with
``--model``, the network's predictions from the camera-degraded picture, the mean of the
picture's and its mirror image's as the product's face crop takes them (the product's error;
its finer sampling of the box is left out: the cached frames are 128 pixels). Error: relative
RMSE over the subject after one least-squares gain (exposure is the artist's choice), so it
measures where the light falls. Effects: diffuse only,
+ cast shadows, + highlights, and "auto" (``intrinsic.plan``: shadows and highlights only for
compact, strong components). Shadow warmth: the median change of log(red / blue) from the
source frame over the face skin the target light darkens to under half (after one gain), the
relit frame's against the light stage's (a new shadow on skin is a little warm at its edges, from
light diffusing under the skin; too warm reads as a red-brown band). Time: the renderer's
milliseconds per 128 x 128 crop, median over the frames, on this machine. Writes
``bench/results/intrinsic_effects.{md,json}``. ``--cache``: another build's val frames (those
whose identities all wear long hair: training.intrinsic.data --long-hair 1); ``--no-hair-class``:
both kinds of buffers without the hair class (the renderer then lights nothing below the chin as
hair), to measure what the class buys.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import pathlib
import sys
import time

import numpy as np
import torch

from addon import intrinsic, lightvec
from training.data import lighting_sampling
from training.eval import report
from training.intrinsic import data
from training.lightstage import layout, shading
from training.lightstage.scene import stage_dirs

ROOT = pathlib.Path(__file__).resolve().parents[1]


def lamp(direction, power=3.0, fill=0.03) -> np.ndarray:
    d = np.asarray(direction, float)
    return (lightvec.splat_direction(d / np.linalg.norm(d), [power] * 3)
            + fill * lightvec.uniform()).astype(np.float32)


def source_light() -> np.ndarray:
    """The frames' own light before relighting: a soft world and a dim lamp above the camera."""
    return (0.7 * lightvec.uniform() + lamp([0.3, 0.5, 1.0], 1.0, 0.0)).astype(np.float32)


def targets(bank) -> dict:
    """Three lamps, a rim lamp behind the subject with a dim fill from the camera (the portrait
    lighting whose light lands on the silhouette), the softest and the most sun-like HDRI of the
    val split's bank (by the share of power in the brightest 3 x 3 cells), and a uniform world."""
    envs = [np.clip(lighting_sampling.environment(bank, i, 0.0), 0, None) for i in range(len(bank))]

    def peak_share(lv):
        p = (lv @ np.asarray(intrinsic.LUMA)) * lightvec.solid_angles()
        r, c = np.unravel_index(int(np.argmax(p)), p.shape)
        return float(p[max(r - 1, 0):r + 2, :].take(np.arange(c - 1, c + 2) % 16, axis=1).sum() / p.sum())

    shares = [peak_share(e) for e in envs]
    return {"key left": lamp([-1, 0.3, 0.5]), "key right": lamp([1, 0.2, 0.6]),
            "top": lamp([0, 1, 0.35]),
            "rim and fill": lamp([0.6, 0.5, -0.7]) + lamp([0, 0, 1], 0.4, 0.0),
            "softest HDRI": envs[int(np.argmin(shares))].astype(np.float32),
            "sunniest HDRI": envs[int(np.argmax(shares))].astype(np.float32),
            "uniform": lightvec.uniform().astype(np.float32)}


EFFECTS = {"diffuse only": dict(shadows=False, specular=False),
           "+ shadows": dict(shadows=True, specular=False),
           "+ highlights": dict(shadows=False, specular=True),
           "auto (both where called for)": dict(shadows=True, specular=True)}


def render(a: dict, light: np.ndarray) -> np.ndarray:
    w = torch.from_numpy(layout.weights(light)).float()[None]
    return shading.relight(data.shade_inputs(a), w, stage_dirs())[0].numpy()


def exact_buffers(a: dict) -> intrinsic.Buffers:
    return intrinsic.Buffers(data.dense(a, a["normal"]), data.dense(a, a["height"][:, None])[0],
                             data.dense(a, a["albedo"]), a["cover"].astype(np.float32),
                             (a["label"] == data.SKIN).astype(np.float32),
                             data.transfer(a), (a["label"] == data.HAIR).astype(np.float32))


def predicted_buffers(session, img: np.ndarray) -> intrinsic.Buffers:
    from addon import portrait

    return portrait.buffers(session, img, mirror=portrait.MIRROR)  # as the relighting passes


def error(out: np.ndarray, gt: np.ndarray, mask: np.ndarray) -> float:
    o, g = out[:, mask].astype(np.float64), gt[:, mask].astype(np.float64)
    gain = float((o * g).sum() / max((o * o).sum(), 1e-20))
    return float(np.sqrt(((gain * o - g) ** 2).mean()) / np.sqrt((g ** 2).mean()))


def darkened(src: np.ndarray, gt: np.ndarray, skin: np.ndarray) -> np.ndarray:
    """(h, w) bool: the skin that ``gt`` shows at under half of ``src``'s luminance, after one
    gain over the skin (where a new shadow falls)."""
    y_src, y_gt = intrinsic.luminance(src), intrinsic.luminance(gt)
    if not skin.any():
        return skin
    gain = np.median(y_src[skin]) / max(float(np.median(y_gt[skin])), 1e-12)
    return skin & (y_gt * gain < 0.5 * y_src)


def log_rb(x: np.ndarray) -> np.ndarray:
    """(h, w) log(red / blue) of a (3, h, w) image."""
    return np.log(np.maximum(x[0], 1e-8) / np.maximum(x[2], 1e-8))


def warmth(out: np.ndarray, src_rb: np.ndarray, where: np.ndarray) -> float | None:
    """The median change of log(red / blue) from the source (``src_rb``: its log_rb) to ``out``
    over ``where``; None when fewer than 20 pixels."""
    if where.sum() < 20:
        return None
    return float(np.median((log_rb(out) - src_rb)[where]))


def run(n_frames: int, model=None, cache=None, hair_class: bool = True) -> dict:
    torch.set_num_threads(1)
    ds = data.IntrinsicFrames("val", 128, 0, cache, varied_backdrops=False)
    lights = targets(ds.bank)
    session = None
    if model:
        from addon import api

        session = api.session(model, 1)
    rows: dict = {}
    source = source_light()
    for f in range(min(n_frames, ds.n)):
        a = ds.frame(f)
        src = render(a, source)
        src_rb = log_rb(src)
        kinds = {"exact buffers": exact_buffers(a)}
        if session is not None:
            kinds["network buffers"] = predicted_buffers(session, src)
        if not hair_class:
            kinds = {k: dataclasses.replace(b, hair=None) for k, b in kinds.items()}
        for lname, light in lights.items():
            gt = render(a, light)
            dark = darkened(src, gt, a["mask"] & (kinds["exact buffers"].face > 0.5))
            truth_warmth = warmth(gt, src_rb, dark)
            auto = intrinsic.plan(light)
            for kind, bufs in kinds.items():
                for ename, flags in EFFECTS.items():
                    p = intrinsic.Plan(auto.components, flags["shadows"] and bool(auto.components),
                                       flags["specular"] and bool(auto.components))
                    t0 = time.perf_counter()
                    # the light stage's height is exact: its relief is marched as it is
                    sh = intrinsic.shade(src, bufs, light, p,
                                         relief=1.0 if kind == "exact buffers" else None)
                    ms = (time.perf_counter() - t0) * 1000
                    out = src * sh.ratio + sh.highlight
                    r = rows.setdefault((kind, lname, ename),
                                        {"err": [], "ms": [], "components": len(auto.components),
                                         "warm": [], "warm_truth": []})
                    r["err"].append(error(out, gt, a["mask"]))
                    r["ms"].append(ms)
                    if truth_warmth is not None:
                        r["warm"].append(warmth(out, src_rb, dark))
                        r["warm_truth"].append(truth_warmth)
            r = rows.setdefault(("input (no relighting)", lname, "-"), {"err": [], "ms": [], "components": 0})
            r["err"].append(error(src, gt, a["mask"]))
            r["ms"].append(0.0)
    return {f"{k[0]} | {k[1]} | {k[2]}": {
        "rel_rmse": float(np.mean(v["err"])), "ms_median": float(np.median(v["ms"])),
        "components": v["components"], "frames": len(v["err"]),
        "shadow_warmth": float(np.mean(v["warm"])) if v.get("warm") else None,
        "shadow_warmth_truth": float(np.mean(v["warm_truth"])) if v.get("warm") else None}
        for k, v in rows.items()}


def markdown(res: dict, command: str, machine: str) -> str:
    lines = [f"Produced by `{command}` on {machine}.", "",
             "| buffers | target light | effects | relative RMSE (gain-fitted) "
             "| shadow warmth (light stage's) | renderer ms / crop | compact components |",
             "| --- | --- | --- | --- | --- | --- | --- |"]
    for k, v in res.items():
        kind, light, eff = k.split(" | ")
        w = ("-" if v.get("shadow_warmth") is None
             else f"{v['shadow_warmth']:+.3f} ({v['shadow_warmth_truth']:+.3f})")
        lines.append(f"| {kind} | {light} | {eff} | {v['rel_rmse']:.4f} | {w} "
                     f"| {v['ms_median']:.1f} | {v['components']} |")
    return "\n".join(lines) + "\n"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--frames", type=int, default=24)
    ap.add_argument("--model", help="an intrinsic .onnx: also measure with its predicted buffers")
    ap.add_argument("--out", default=str(ROOT / "bench" / "results" / "intrinsic_effects"))
    ap.add_argument("--cache", help="the val frames' cache root (default cache/intrinsic)")
    ap.add_argument("--no-hair-class", dest="hair_class", action="store_false",
                    help="the buffers without the hair class")
    a = ap.parse_args(argv)
    write_report(a.out, "intrinsic_effects", argv,
                 run(a.frames, a.model, a.cache, a.hair_class), markdown)


def write_report(out: str, module: str, argv, res: dict, markdown) -> None:
    """Print and write ``out``.md (``markdown(res, command, machine)``) and ``out``.json: the
    one-thread accuracy benches' results with the command that made them and the machine."""
    command = f"python -m bench.{module} " + " ".join(argv if argv is not None
                                                      else sys.argv[1:])
    machine = (f"{report.cpu_name()}, {os.cpu_count()} cores (one thread), load "
               f"{os.getloadavg()[0]:.1f}")
    md = markdown(res, command.strip(), machine)
    print(md)
    pathlib.Path(out + ".md").write_text(md)
    pathlib.Path(out + ".json").write_text(json.dumps({"command": command, "machine": machine,
                                                       "results": res}, indent=1) + "\n")


if __name__ == "__main__":
    main()
