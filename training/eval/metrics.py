"""Image metrics of the held-out evaluation and the two baselines, on (3, H, W) absolute linear
images and a portrait mask. What they mean and how values are normalised: training/eval/evaluate.py.
"""

from __future__ import annotations

import math

import numpy as np

from addon import colour, lightvec

WHITE_PERCENTILE = 99.0
LUMA = np.array(colour.REC709_LUMA)  # Rec.709 luminance weights
_SSIM_C1, _SSIM_C2 = 0.01 ** 2, 0.03 ** 2


def srgb_encode(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)


def to_unit(img: np.ndarray, white: float) -> np.ndarray:
    return srgb_encode(np.asarray(img, np.float64) / white)


def white_level(gt: np.ndarray, mask: np.ndarray) -> float:
    """gt (3,H,W) absolute, mask (H,W) bool -> the level that maps to 1."""
    vals = gt[:, mask].reshape(-1) if mask.any() else gt.reshape(-1)
    w = float(np.percentile(vals, WHITE_PERCENTILE)) if vals.size else 0.0
    return w if np.isfinite(w) and w > 1e-12 else 1.0


def _gauss_kernel(size=11, sigma=1.5) -> np.ndarray:
    x = np.arange(size) - size // 2
    g = np.exp(-(x ** 2) / (2 * sigma ** 2))
    return g / g.sum()


def _blur(img: np.ndarray) -> np.ndarray:
    """Separable Gaussian blur of (C,H,W) with reflected borders."""
    g = _gauss_kernel()
    r = len(g) // 2
    out = np.pad(img, ((0, 0), (r, r), (0, 0)), mode="reflect")
    out = sum(g[i] * out[:, i:i + img.shape[1]] for i in range(len(g)))
    out = np.pad(out, ((0, 0), (0, 0), (r, r)), mode="reflect")
    return sum(g[i] * out[:, :, i:i + img.shape[2]] for i in range(len(g)))


def ssim_map(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Per-pixel SSIM (C,H,W) of two images in [0, 1]."""
    mu_a, mu_b = _blur(a), _blur(b)
    saa = _blur(a * a) - mu_a ** 2
    sbb = _blur(b * b) - mu_b ** 2
    sab = _blur(a * b) - mu_a * mu_b
    return (((2 * mu_a * mu_b + _SSIM_C1) * (2 * sab + _SSIM_C2))
            / ((mu_a ** 2 + mu_b ** 2 + _SSIM_C1) * (saa + sbb + _SSIM_C2)))


def image_metrics(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray) -> dict:
    """pred, gt (3,H,W) absolute linear; mask (H,W) bool (the portrait region)."""
    if not mask.any():
        raise ValueError("the portrait mask is empty; nothing to measure")
    w = white_level(gt, mask)
    p, g = to_unit(np.nan_to_num(pred, nan=0.0, posinf=w, neginf=0.0), w), to_unit(gt, w)
    rmse = float(np.sqrt(np.mean((p[:, mask] - g[:, mask]) ** 2)))
    psnr = 20.0 * math.log10(1.0 / max(rmse, 1e-10))
    ssim = float(np.mean(ssim_map(p, g)[:, mask]))
    return {"rmse": rmse, "psnr": psnr, "ssim": ssim}


def level_gain(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """(3,) per-channel least-squares gain of ``pred`` toward ``gt`` over the mask (linear)."""
    p = np.nan_to_num(np.asarray(pred, np.float64)[:, mask], nan=0.0, posinf=0.0, neginf=0.0)
    g = np.asarray(gt, np.float64)[:, mask]
    return (p * g).sum(1) / np.maximum((p * p).sum(1), 1e-12)


def level_fit_rmse(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray) -> float:
    """The RMSE left when the prediction's overall level and colour are right: ``pred`` scaled
    per channel by level_gain first. A single image cannot tell a darker face under a brighter
    light from a lighter face under a dimmer one, nor a skin tone from a light's tint, so part of
    any relit level is a guess; this figure leaves that part out."""
    pred = np.nan_to_num(np.asarray(pred, np.float64), nan=0.0, posinf=0.0, neginf=0.0)
    return image_metrics(pred * level_gain(pred, gt, mask)[:, None, None], gt, mask)["rmse"]


def shading_correlation(pred: np.ndarray, inp: np.ndarray, gt: np.ndarray,
                        mask: np.ndarray) -> float:
    """Correlation of the predicted and true spatial change of log luminance (see module doc),
    over the portrait pixels the input shows (luminance above 1% of the white level: the log of
    a near-black input is noise); relit values are floored at 0.1% of white."""
    lum = lambda x: (LUMA[:, None] * np.asarray(x, np.float64)[:, mask]).sum(0)  # noqa: E731
    white = white_level(gt, mask)
    li = lum(inp)
    seen = li > 0.01 * white
    if seen.sum() < 2:
        return 0.0
    floor = 1e-3 * white
    a = np.log(np.maximum(lum(pred)[seen], floor) / li[seen])
    b = np.log(np.maximum(lum(gt)[seen], floor) / li[seen])
    a, b = a - a.mean(), b - b.mean()
    den = math.sqrt(float((a * a).sum() * (b * b).sum()))
    return float((a * b).sum() / den) if den > 1e-12 else 0.0


def erode4(mask: np.ndarray) -> np.ndarray:
    """Pixels of a (H, W) bool mask whose four neighbours are in it (outside the image: not)."""
    m = np.pad(mask, 1, constant_values=False)
    return m[1:-1, 1:-1] & m[:-2, 1:-1] & m[2:, 1:-1] & m[1:-1, :-2] & m[1:-1, 2:]


def baseline_identity(sample: dict) -> np.ndarray:
    return np.asarray(sample["img_t_i"], np.float32)


def baseline_irradiance_ratio(sample: dict) -> np.ndarray:
    src = lightvec.total_power(sample["light_i"])
    dst = lightvec.total_power(sample["light_k"])
    ratio = np.where(src > 0, dst / np.maximum(src, 1e-12), 0.0)
    return (np.asarray(sample["img_t_i"], np.float64) * ratio[:, None, None]).astype(np.float32)


def mean_metrics(rows: list[dict]) -> dict:
    return {k: float(np.mean([r[k] for r in rows])) for k in rows[0]} if rows else {}


def paired_difference(a_rows, b_rows, key: str = "rmse") -> tuple[float, float]:
    """Mean of b - a over the same samples (per-sample metric rows) and its standard error."""
    d = np.array([b[key] - a[key] for a, b in zip(a_rows, b_rows)], np.float64)
    return float(d.mean()), float(d.std(ddof=1) / np.sqrt(len(d))) if len(d) > 1 else float("nan")
