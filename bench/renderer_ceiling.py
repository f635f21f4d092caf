"""How far the intrinsic renderer's design can go on the card's test set, and what stops it.

    .venv/bin/python -m bench.renderer_ceiling [--n 64] [--model models/relight-portrait.onnx]

The card's ``rmse_level_fit`` (training/eval/evaluate.py: the fixed test set of held-out
identities, each relit frame scaled per channel by its least-squares gain toward the truth, then
display-normalised RMSE over the portrait) measured for a ladder of relightings of the same 64
frames, each step replacing an estimate with the light stage's truth:

* ``input unchanged`` and ``the product``: the input as it is, and the model as the card
  measures it (addon.relight_image: framing, buffers, renderer);
* ``renderer, network buffers (no framing)``: addon.intrinsic.shade on the network's buffers of
  the whole 128-pixel frame (the mean with the mirror image's, as the face crop takes them);
* ``renderer, exact buffers``: the same renderer on the light stage's own normals, height,
  albedo, matte, face skin and light transport (the height's relief marched as it is, not
  raised as the network's is: intrinsic.shade's ``relief``): what a perfect network would score;
* ``renderer, network buffers (no framing), exact X``: the network's buffers with one of them
  (normals, height, albedo, matte and face skin, transfer) the light stage's, over the subject
  it renders (the matte and face skin whole): which buffer the gap between the two rows above
  waits on, so training knows where its effort pays;
* ``, the true source shading`` (and ``per channel``): either renderer given the light stage's
  own diffuse irradiance of the footage in place of its estimate from the footage
  (intrinsic.shade's ``source``; luminance, or with its colour): what the estimate costs. On
  the network's buffers the estimate can beat the truth: fitted on the same predicted normals
  as the target is rendered on, their errors partly cancel in the ratio;
  ``, the true source light colour``: the shading estimated as the product does, but the
  footage's light colour per pixel (its irradiance over the irradiance's luminance) the light
  stage's, in place of source_chroma's estimate (intrinsic.shade's ``source_colour``): what
  reading the light's colour from one image costs;
* ``ratio of the true diffuse shading``: the footage times the light stage's own target over
  source diffuse irradiance (subsurface diffusion included), the source's taken as luminance
  (the footage keeps its colour; the renderer divides out only a strong colour gradient,
  addon.intrinsic.source_chroma); ``per channel``: the source's colour divided out too;
  ``per channel, specular exact``: and the source's specular reflection taken out of the
  footage and the target's added (what is left is the backdrop blended into the silhouette's
  pixels).

The light stage's buffers come from rendering each test sample's scene again
(training.intrinsic.data.frame_arrays); its pictures are checked against the stored test set's.
Writes ``bench/results/renderer_ceiling.{md,json}``.
"""

from __future__ import annotations

import argparse
import dataclasses
import pathlib

import numpy as np
import torch

from addon import intrinsic
from training.data.dataset import LightStageDataset
from training.data.make_testset import TEST_SEED, load_testset
from training.eval.metrics import level_fit_rmse
from training.intrinsic import data
from training.lightstage import layout, shading

from .intrinsic_effects import exact_buffers, predicted_buffers, render, write_report

ROOT = pathlib.Path(__file__).resolve().parents[1]
# The scene rendered again must give the stored test set's pictures (its transfer is kept in
# float16, as the intrinsic cache keeps it): largest difference over the picture's peak.
MATCH = 2e-3
TRUE_SOURCE = (", the true source shading", ", the true source shading per channel",
               ", the true source light colour")
NETWORK = "renderer, network buffers (no framing)"
# The buffers made exact one at a time in the network's: Buffers fields each stands for.
EXACT_ONE = {"normals": ("normal",), "height": ("height",), "albedo": ("albedo",),
             "matte and face skin": ("matte", "face"), "transfer": ("transfer",)}
STEPS = ("input unchanged", "the product",
         *(f"{b}{t}" for b in (NETWORK, "renderer, exact buffers") for t in ("", *TRUE_SOURCE)),
         *(f"{NETWORK}, exact {k}" for k in EXACT_ONE),
         "ratio of the true diffuse shading",
         "ratio of the true diffuse shading, per channel",
         "ratio of the true diffuse shading, per channel, specular exact")


def stage_parts(a: dict, light: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(diffuse irradiance after subsurface diffusion, specular radiance), each (3, H, W), of
    the light stage's frame ``a`` under ``light`` (shading.terms; the specular of silhouette
    pixels weighted by their coverage as the pictures are)."""
    s = data.shade_inputs(a)
    irr, spec = shading.terms(s, torch.from_numpy(layout.weights(light)).float()[None])
    h, wd = s.mask.shape
    spec = spec.view(3, h, wd) * (1.0 if s.cover is None else s.cover[None])
    return irr.view(3, h, wd).numpy(), spec.numpy()


def with_exact(net: intrinsic.Buffers, exact: intrinsic.Buffers, fields,
               cover: np.ndarray) -> intrinsic.Buffers:
    """The network's buffers ``net`` with ``fields`` (Buffers field names) taken from the light
    stage's ``exact``: the matte and face skin whole (the light stage says where the subject is
    not, too), the others where the subject is (``cover`` > 0; beyond it the light stage has no
    normals, height, albedo or transport, and the network's stay)."""
    on = cover > 0
    got = {}
    for f in fields:
        e, n = getattr(exact, f), getattr(net, f)
        got[f] = e if f in ("matte", "face") or n is None else np.where(on, e, n).astype(
            np.float32)
    return dataclasses.replace(net, **got)


def ladder(sample: dict, a: dict, product=None, session=None) -> dict:
    """{step: rmse_level_fit} for one test sample (``sample``: the stored test set's, ``a``:
    its light-stage frame)."""
    src, gt = sample["img_t_i"], sample["gt_t_k"]
    mask = sample["mask_t"][0] > 0.5
    light = sample["light_k"]
    e_s, s_s = stage_parts(a, sample["light_i"])
    e_t, s_t = stage_parts(a, light)
    fg = e_s > 1e-8
    per_channel = np.where(fg, e_t / np.maximum(e_s, 1e-8), 1.0)
    e_lum = intrinsic.luminance(e_s)[None]
    lum = np.where(fg & (e_lum > 1e-8), e_t / np.maximum(e_lum, 1e-8), 1.0)
    tint = np.where(fg & (e_lum > 1e-8), e_s / np.maximum(e_lum, 1e-8), 1.0).astype(np.float32)
    outs = {"input unchanged": src,
            "ratio of the true diffuse shading": src * lum,
            "ratio of the true diffuse shading, per channel": src * per_channel,
            "ratio of the true diffuse shading, per channel, specular exact":
                (src - s_s) * per_channel + s_t}
    if product is not None:
        outs["the product"] = product(sample)[0]
    exact = exact_buffers(a)
    kinds = {"renderer, exact buffers": exact}
    if session is not None:
        kinds[NETWORK] = net = predicted_buffers(session, src)
    for name, bufs in kinds.items():
        for suffix, source, colour in (("", None, None), (TRUE_SOURCE[0], e_lum[0], None),
                                       (TRUE_SOURCE[1], e_s, None), (TRUE_SOURCE[2], None, tint)):
            # the light stage's height is exact: its relief is marched as it is
            sh = intrinsic.shade(src, bufs, light, source=source, source_colour=colour,
                                 relief=1.0 if bufs is exact else None)
            outs[name + suffix] = src * sh.ratio + sh.highlight
    if session is not None:
        cover = np.asarray(a["cover"], np.float32)
        for k, fields in EXACT_ONE.items():
            sh = intrinsic.shade(src, with_exact(net, exact, fields, cover), light)
            outs[f"{NETWORK}, exact {k}"] = src * sh.ratio + sh.highlight
    return {k: level_fit_rmse(v, gt, mask) for k, v in outs.items()}


def run(n: int = 64, model: str | None = None) -> dict:
    torch.set_num_threads(1)
    ts = load_testset(128)
    n = min(n, len(ts["img_t_i"]))
    ds = LightStageDataset("test", 128, seed=TEST_SEED, length=len(ts["img_t_i"]))
    product = session = None
    if model:
        from addon import api
        from training.eval.predictors import onnx_file_predictor

        product, _ = onnx_file_predictor(model, 1)
        session = api.session(model, 1)
    rows: dict = {}
    for i in range(n):
        sample = {k: v[i] for k, v in ts.items()}
        scene, t, _ = ds.scene_for(i)
        a = data.frame_arrays(scene, t, i)
        for key, light in (("img_t_i", sample["light_i"]), ("gt_t_k", sample["light_k"])):
            off = float(np.abs(render(a, light) - sample[key]).max()) / max(
                float(sample[key].max()), 1e-12)
            if off > MATCH:
                raise RuntimeError(f"test sample {i} rendered again differs from the stored "
                                   f"test set by {off:.2g} of its peak: rebuild the test set "
                                   "(python -m training.data.make_testset)")
        for k, v in ladder(sample, a, product, session).items():
            rows.setdefault(k, []).append(v)
    return {"samples": n, "model": model,
            "rmse_level_fit": {k: float(np.mean(rows[k])) for k in STEPS if k in rows}}


def markdown(res: dict, command: str, machine: str) -> str:
    lines = [f"Produced by `{command}` on {machine}.", "",
             f"The card's test set ({res['samples']} samples of held-out identities); model: "
             f"{res['model'] or 'none'}.", "",
             "| relighting | rmse_level_fit |", "| --- | --- |"]
    lines += [f"| {k} | {v:.4f} |" for k, v in res["rmse_level_fit"].items()]
    return "\n".join(lines) + "\n"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--n", type=int, default=64, help="test samples (of the stored 64)")
    ap.add_argument("--model", help="an intrinsic .onnx: also the product and its buffers")
    ap.add_argument("--out", default=str(ROOT / "bench" / "results" / "renderer_ceiling"))
    a = ap.parse_args(argv)
    write_report(a.out, "renderer_ceiling", argv, run(a.n, a.model), markdown)


if __name__ == "__main__":
    main()
