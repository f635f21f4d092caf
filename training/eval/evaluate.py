"""Held-out accuracy: RMSE, PSNR and SSIM on the portrait region, as in the paper (sec. 5.1).

    python -m training.eval.evaluate --run runs/draft-01         # the fixed test set (64 samples)
    python -m training.eval.evaluate --onnx models/relight-draft.onnx

How values are "normalised to [0, 1]" (the paper's images are display images): each prediction and
its ground truth (absolute linear radiance) are divided by the ground truth's 99th-percentile
channel value inside the portrait mask, clipped to [0, 1] and sRGB-encoded. RMSE and SSIM are taken
over the mask's pixels only (SSIM: 11x11 Gaussian window, sigma 1.5, per channel, the map averaged
over the mask); PSNR = 20 log10(1 / RMSE). Each figure is the mean over the held-out samples.

``shading_corr`` asks whether the light acts where it should: the Pearson correlation, over the
portrait region, between the predicted and the true change of log luminance from the input to the
relit frame, each with its mean over the region removed (so a global change of level
scores 0, the right spatial pattern of light and shadow scores 1, the opposite -1).

``rmse_level_fit`` is the RMSE after the prediction is scaled per channel by the least-squares
gain toward the truth (level_fit_rmse): what is left when the overall level and colour, which a
single image leaves ambiguous (albedo against light power, skin tone against the light's tint),
are set right. ``error_breakdown`` (``--breakdown``) says which regions the error lives in.

``lateral_response`` is a blunter check of the same: each sample relit by one lamp from the
camera's left and by one from its right (90 degrees off the view axis, at eye height); the
image-left over image-right mean luminance of the portrait under the first, divided by the same
under the second (median over samples). 1 means the side of the light makes no difference.

``background`` asks whether the backdrop is kept: held-out samples with varied backdrops (photos,
chroma-key screens, busy patterns; training/lightstage/backdrops.py) whose background is a matte
plane lit by the light, so relit it changes by one factor per channel. RMSE over the pixels the
subject does not cover, normalised with the portrait's white level as above. A model that repaints
the backdrop scores worse than the irradiance-ratio baseline there. ``model_keep`` and
``model_relit`` score the product's background choices "keep" and "relit" (addon/pipeline.py).

Baselines: ``identity`` outputs the input unchanged; ``irradiance_ratio`` scales the input per
channel by total_power(L^k) / total_power(L^i) with the true source light (an oracle on lighting).
"""

from __future__ import annotations

import argparse
import json
import math
import pathlib

import numpy as np

from addon import lightvec

from .facetemplate import applied as template_applied
from .facetemplate import flag_path as template_flag_path
from .metrics import (LUMA, baseline_identity, baseline_irradiance_ratio, erode4, image_metrics,
                      level_fit_rmse, level_gain, mean_metrics, paired_difference,
                      shading_correlation, to_unit, white_level)
from .predictors import onnx_file_predictor, torch_predictor


def lateral_response(predict, dataset, n: int = 16) -> float:
    """Median over samples of balance(left lamp) / balance(right lamp) (see module doc)."""
    out = []
    for idx in range(min(n, len(dataset))):
        s = dataset[idx]
        mask = np.asarray(s["mask_t"])[0] > 0.5
        half = mask.shape[1] // 2
        left, right = mask.copy(), mask.copy()
        left[:, half:], right[:, :half] = False, False
        if not left.any() or not right.any():
            continue
        bal = []
        for direction in ((-1.0, 0.0, 0.0), (1.0, 0.0, 0.0)):
            lamp = lightvec.splat_direction(direction, (1.0, 1.0, 1.0))
            relit, _ = predict({**s, "light_k": lamp})
            lum = (LUMA[:, None, None] * np.asarray(relit, np.float64)).sum(0)
            bal.append(lum[left].mean() / max(lum[right].mean(), 1e-12))
        out.append(bal[0] / max(bal[1], 1e-12))
    return float(np.median(out)) if out else float("nan")


def background_error(predict, n: int = 16, resolution: int = 128, data_root=None) -> dict:
    """RMSE over the background of ``n`` held-out samples with varied backdrops (module doc):
    the model as the product composes it under each background choice of addon/pipeline.py
    ("network": its own output; "keep": the source's background by its foreground matte; "relit":
    the same times pipeline.wall_gain with its own source-light estimate), and both baselines."""
    from addon.pipeline import wall_gain

    from ..data.dataset import LightStageDataset
    from ..data.make_testset import TEST_SEED

    ds = LightStageDataset("test", resolution, seed=TEST_SEED, length=n, data_root=data_root,
                           backdrops="varied")
    err: dict[str, list] = {}
    for idx in range(n):
        s = ds[idx]
        cover = np.asarray(s["mask_t"])[0]
        bg = cover == 0
        if not bg.any():
            continue
        gt = np.asarray(s["gt_t_k"], np.float32)
        white = white_level(gt, cover > 0.5)
        g = to_unit(gt, white)[:, bg]
        src = np.asarray(s["img_t_i"], np.float32)
        pred, extras = predict(s)
        images = {"model": pred, "identity": baseline_identity(s),
                  "irradiance_ratio": baseline_irradiance_ratio(s)}
        if "foreground" in extras:
            m = np.clip(np.asarray(extras["foreground"], np.float32), 0, 1)[None]
            images["model_keep"] = pred * m + src * (1 - m)
            if "source_light" in extras:
                gain = wall_gain(s["light_k"], extras["source_light"])[:, None, None]
                images["model_relit"] = pred * m + src * gain * (1 - m)
        for name, img in images.items():
            p = to_unit(np.nan_to_num(img, nan=0.0, posinf=white, neginf=0.0), white)[:, bg]
            err.setdefault(name, []).append(float(np.sqrt(np.mean((p - g) ** 2))))
    out = {k: float(np.mean(v)) for k, v in err.items()}
    out["samples"] = len(err.get("model", []))
    return out


def evaluate(predict, dataset, n: int | None = None, baselines: bool = True,
             per_sample: bool = False) -> dict:
    """``predict(sample) -> (relit (3,H,W) absolute, extras dict)`` over the first n samples.
    ``per_sample`` also returns every sample's metrics (for paired comparisons of models)."""
    n = len(dataset) if n is None else min(n, len(dataset))
    rows = {"model": [], "identity": [], "irradiance_ratio": []}
    fg_iou = []
    for idx in range(n):
        s = dataset[idx]
        mask = np.asarray(s["mask_t"])[0] > 0.5
        gt = np.asarray(s["gt_t_k"], np.float32)
        pred, extras = predict(s)
        rows["model"].append({**image_metrics(pred, gt, mask),
                              "shading_corr": shading_correlation(pred, s["img_t_i"], gt, mask),
                              "rmse_level_fit": level_fit_rmse(pred, gt, mask)})
        if "foreground" in extras:
            fg = extras["foreground"] > 0.5
            fg_iou.append(float((fg & mask).sum() / max((fg | mask).sum(), 1)))
        if baselines:
            for name, base in (("identity", baseline_identity(s)),
                               ("irradiance_ratio", baseline_irradiance_ratio(s))):
                rows[name].append({**image_metrics(base, gt, mask),
                                   "shading_corr": shading_correlation(base, s["img_t_i"], gt,
                                                                       mask),
                                   "rmse_level_fit": level_fit_rmse(base, gt, mask)})
    out = {name: mean_metrics(r) for name, r in rows.items() if r}
    if fg_iou:
        out["model"]["foreground_iou"] = float(np.mean(fg_iou))
    out["samples"] = n
    if per_sample:
        out["per_sample"] = rows
    return out


def error_breakdown(predict, dataset, n: int | None = None, edge_px: int = 2) -> dict:
    """Where the model's RMSE lives, over the first n samples (same normalisation as
    image_metrics): per parsing class of the target frame, the share of portrait pixels, the
    RMSE inside the class and the share of all squared error; the same for a band of ``edge_px``
    pixels inside the portrait's outline (overlapping the classes); and ``level_fit_rmse``, the
    RMSE left after each sample's prediction is scaled per channel by the least-squares gain
    toward the truth (linear, over the portrait): the part of the error a right overall level and
    colour would remove is ``rmse - level_fit_rmse`` (per region too: ``rmse_level_fit`` and
    ``level_fit_share``, where the card's figure lives); and ``level_gain``, the mean and standard
    deviation over the samples of the log of that gain (brightness: the mean of the three
    channels; colour: each channel less that mean). A mean far from 0 would be a bias that one
    fixed correction removes; a spread is a per-image guess that no fixed correction can."""
    from addon.contract import PARSING_CLASSES

    n = len(dataset) if n is None else min(n, len(dataset))
    names = list(PARSING_CLASSES[1:]) + [f"edge ({edge_px} px)"]
    sq = dict.fromkeys(names, 0.0)
    fit_region = dict.fromkeys(names, 0.0)
    count = dict.fromkeys(names, 0)
    total_sq, total_px, fit_sq = 0.0, 0, 0.0
    log_gains = []
    for idx in range(n):
        s = dataset[idx]
        mask = np.asarray(s["mask_t"])[0] > 0.5
        if not mask.any():
            continue
        gt = np.asarray(s["gt_t_k"], np.float64)
        pred, _ = predict(s)
        pred = np.nan_to_num(np.asarray(pred, np.float64), nan=0.0, posinf=0.0, neginf=0.0)
        w = white_level(gt, mask)
        g = to_unit(gt, w)
        err = ((to_unit(pred, w) - g) ** 2).mean(0)
        gain = level_gain(pred, gt, mask)
        fit = ((to_unit(pred * gain[:, None, None], w) - g) ** 2).mean(0)
        log_gains.append(np.log(np.maximum(gain, 1e-6)))
        total_sq += float(err[mask].sum())
        fit_sq += float(fit[mask].sum())
        total_px += int(mask.sum())
        label = np.argmax(np.asarray(s["parsing_t"])[1:], axis=0)  # class channels after fg
        inner = mask.copy()
        for _ in range(edge_px):
            inner = erode4(inner)
        regions = {name: mask & (label == i) for i, name in enumerate(PARSING_CLASSES[1:])}
        regions[names[-1]] = mask & ~inner
        for name, sel in regions.items():
            sq[name] += float(err[sel].sum())
            fit_region[name] += float(fit[sel].sum())
            count[name] += int(sel.sum())
    out = {name: {"pixel_share": count[name] / max(total_px, 1),
                  "rmse": math.sqrt(sq[name] / count[name]) if count[name] else float("nan"),
                  "error_share": sq[name] / max(total_sq, 1e-30),
                  "rmse_level_fit": math.sqrt(fit_region[name] / count[name]) if count[name]
                  else float("nan"),
                  "level_fit_share": fit_region[name] / max(fit_sq, 1e-30)} for name in names}
    lg = np.array(log_gains).reshape(-1, 3)
    bright, colour_ = lg.mean(1), lg - lg.mean(1, keepdims=True)
    level = {"log_brightness_mean": float(bright.mean()) if len(lg) else float("nan"),
             "log_brightness_sd": float(bright.std()) if len(lg) else float("nan"),
             "log_colour_mean": colour_.mean(0).tolist(), "log_colour_sd": colour_.std(0).tolist()}
    return {"regions": out, "rmse_pooled": math.sqrt(total_sq / max(total_px, 1)),
            "level_fit_rmse": math.sqrt(fit_sq / max(total_px, 1)), "level_gain": level,
            "samples": n}


def heldout_dataset(resolution: int, seed: int = 12345, split: str = "test"):
    """The fixed test set (training.data.make_testset: stored, rebuilt bit-identically) for the
    default test split and seed; other splits or seeds are rendered on the fly."""
    from ..data import make_testset

    if split == "test" and seed == make_testset.TEST_SEED:
        return make_testset.TestSet(resolution)
    from ..data.dataset import make_dataset

    return make_dataset(split, resolution, seed)


def dataset_id(ds) -> dict:
    """What the metrics were measured on: the fixed test set's content sha256 where it is one."""
    from ..data import make_testset

    if isinstance(ds, make_testset.TestSet):
        return {"testset": "training.data.make_testset", "samples_in_set": len(ds),
                "testset_sha256": make_testset.content_sha256(ds.arrays),
                "render_version": make_testset.renderer_version()}
    return {"dataset": type(ds).__name__}


def card_metrics(predict, ds, n: int, resolution: int) -> dict:
    """A model card's ``metrics``: evaluate's figures on ``n`` held-out samples, the lateral
    response, the painted background, what the figures mean and what they were measured on."""
    metrics = evaluate(predict, ds, n)
    metrics["model"]["lateral_response"] = lateral_response(predict, ds)
    metrics["background"] = background_error(predict, resolution=resolution)
    metrics.update(split="test", resolution=resolution,
                   definition="\n\n".join(__doc__.split("\n\n")[2:6]), **dataset_id(ds))
    return metrics


def update_card(onnx_path, metrics: dict) -> pathlib.Path:
    """Write ``metrics`` into the card beside ``onnx_path`` (re-measuring a shipped model on
    today's test set; its training record stays as it was). The card must describe that file."""
    import hashlib

    onnx_path = pathlib.Path(onnx_path)
    card_path = onnx_path.with_suffix(".json")
    if not card_path.is_file():
        raise SystemExit(f"--update-card: no card at {card_path}; export the model with "
                         "training.run.export, which writes one")
    text = card_path.read_text()
    card = json.loads(text)
    digest = hashlib.sha256(onnx_path.read_bytes()).hexdigest()
    if card.get("sha256") != digest:
        raise SystemExit(f"--update-card: {card_path} describes another file than {onnx_path} "
                         "(sha256 differs); re-export the model instead")
    # Figures this module does not measure (an intrinsic card's buffers against the light
    # stage, from its export) stay.
    card["metrics"] = {**card.get("metrics", {}), **metrics}
    # The card keeps its own indentation (exports write 1 space, older cards 2), so its diff
    # shows the figures that changed.
    second = text.split("\n", 2)[1] if text.count("\n") > 1 else ""
    indent = len(second) - len(second.lstrip(" ")) or 2
    card_path.write_text(json.dumps(card, indent=indent) + "\n")
    return card_path


def main(argv=None):
    p = argparse.ArgumentParser(description="held-out RMSE / PSNR / SSIM on the portrait region")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--run", help="a training run folder (see --checkpoint)")
    src.add_argument("--onnx", help="an exported model")
    p.add_argument("--n", type=int, default=64)
    p.add_argument("--resolution", type=int, default=128)
    p.add_argument("--split", default="test")
    p.add_argument("--seed", type=int, default=12345)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--checkpoint", default="checkpoint.pt",
                   help="with --run: checkpoint.pt (last) or best.pt (best on val)")
    p.add_argument("--raw", action="store_true",
                   help="with --run: the raw training weights of a run trained with --ema "
                        "(checkpoint.pt keeps them beside the average), not the average")
    p.add_argument("--true-source", action="store_true",
                   help="with --run: give the decoder the true source light instead of the "
                        "encoder's estimate (a diagnostic)")
    p.add_argument("--breakdown", action="store_true",
                   help="only where the error lives: per parsing class, the outline, and what "
                        "a right overall level and colour would remove (error_breakdown)")
    p.add_argument("--compare", metavar="ONNX",
                   help="with --onnx: also evaluate this model on the same samples and print the "
                        "paired difference (this one minus --onnx) of each figure with its "
                        "standard error over the samples (is a new model better beyond the test "
                        "set's sampling noise?)")
    p.add_argument("--update-card", action="store_true",
                   help="with --onnx: write the figures into the model's card (its metrics; "
                        "after the test set changed, e.g. a new light stage render version)")
    p.add_argument("--face-template", metavar="NPZ",
                   help="with --onnx: the Portrait network's normals' vertical low band over the "
                        "face skin taken from this face template instead of the product's, or "
                        "from none with 'none' (addon/facetemplate.py; an experiment, not the "
                        "card's figures)")
    a = p.parse_args(argv)
    if a.face_template and (not a.onnx or a.update_card):
        p.error("--face-template needs --onnx (and not --update-card: its figures are not the "
                "product's)")
    if a.face_template:
        with template_applied(template_flag_path(a.face_template, p.error)):
            return _main(p, a)
    return _main(p, a)


def _main(p, a):
    if a.raw and not a.run:
        p.error("--raw needs --run (an exported model holds one set of weights)")
    if a.true_source and not a.run:
        p.error("--true-source needs --run (an ONNX model always uses its own estimate)")
    if a.compare and (not a.onnx or a.breakdown or a.update_card):
        p.error("--compare needs --onnx (and neither --breakdown nor --update-card)")
    if a.update_card and (not a.onnx or a.breakdown or a.split != "test" or a.seed != 12345):
        p.error("--update-card needs --onnx and the fixed test set (default --split and --seed)")
    ds = heldout_dataset(a.resolution, a.seed, a.split)
    if a.run:
        import torch

        from ..model.checkpoint import load_checkpoint
        torch.set_num_threads(a.threads)
        net, _ = load_checkpoint(f"{a.run}/{a.checkpoint}", raw=a.raw)
        predict = torch_predictor(net, a.true_source)
    else:
        predict, _ = onnx_file_predictor(a.onnx, a.threads)
    if a.breakdown:
        b = error_breakdown(predict, ds, a.n)
        lv = b["level_gain"]
        print(f"{b['samples']} samples: RMSE pooled over pixels {b['rmse_pooled']:.4f}, "
              f"after a per-sample level and colour fit {b['level_fit_rmse']:.4f}")
        print(f"that fit's log gain: brightness {lv['log_brightness_mean']:+.3f} mean, "
              f"{lv['log_brightness_sd']:.3f} sd; colour (R, G, B less brightness) mean "
              + " ".join(f"{v:+.3f}" for v in lv["log_colour_mean"]) + ", sd "
              + " ".join(f"{v:.3f}" for v in lv["log_colour_sd"]))
        print("region          pixels  RMSE    share of squared error  after the fit: RMSE, share")
        for name, r in b["regions"].items():
            print(f"{name:14s}  {r['pixel_share']:6.1%}  {r['rmse']:.4f}  {r['error_share']:6.1%}"
                  f"                  {r['rmse_level_fit']:.4f}  {r['level_fit_share']:6.1%}")
        print(json.dumps({**b, **dataset_id(ds)}))
        return
    if a.compare:
        other, _ = onnx_file_predictor(a.compare, a.threads)
        base = evaluate(predict, ds, a.n, baselines=False, per_sample=True)
        new = evaluate(other, ds, a.n, baselines=False, per_sample=True)
        print(f"{a.compare} minus {a.onnx}, {base['samples']} samples (mean ± standard error):")
        rows = {}
        for key in ("rmse", "psnr", "ssim", "shading_corr", "rmse_level_fit"):
            d = paired_difference(base["per_sample"]["model"], new["per_sample"]["model"], key)
            rows[key] = {"mean": d[0], "se": d[1], "base": base["model"][key],
                         "other": new["model"][key]}
            print(f"  {key:15s} {base['model'][key]:8.4f} -> {new['model'][key]:8.4f}   "
                  f"{d[0]:+.4f} ± {d[1]:.4f}")
        print(json.dumps({"compare": rows, **dataset_id(ds)}))
        return
    if a.update_card:
        metrics = card_metrics(predict, ds, a.n, a.resolution)
        print(json.dumps(metrics, indent=2))
        print("card:", update_card(a.onnx, metrics))
        return
    res = {**evaluate(predict, ds, a.n), "lateral_response": lateral_response(predict, ds),
           "background": background_error(predict, resolution=a.resolution)}
    print(json.dumps({**res, **dataset_id(ds)}, indent=2))


if __name__ == "__main__":
    main()
