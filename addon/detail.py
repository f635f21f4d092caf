"""Full-resolution output: the network runs at a working resolution; this brings its result back
to the clip's resolution keeping the footage's own fine detail.

Method (a guided-filter transfer, after He et al.'s fast guided filter): at the working
resolution, fit per channel a local linear model  relit ~ A * input + B  (box windows of
``radius``, ridge ``eps``); upsample A and B bilinearly and apply them to the full-resolution
input:  out = A_up * input_full + B_up.
* Fine detail comes from input_full, scaled by the local gain A.
* Edges stay sharp: the model follows the guide, so no halo where the light changes at an edge.
* Dark pixels cannot blow up: where the input is flat or dark its variance is small, so A shrinks
  toward 0 (the ridge eps) and B carries the relit light; A is also clamped to [0, MAX_GAIN].
tests/core/test_detail.py measures the error against a synthetic ground truth and against the
alternatives (plain upsampling, a bounded shading ratio).
"""

from __future__ import annotations

import math

import numpy as np

RADIUS = 1          # box window radius at the working resolution (pixels)
EPS = 1e-4          # ridge, in exposure-normalised units (the clip's 90th percentile is 0.5)
MAX_GAIN = 64.0     # bound on the local gain A
FLOOR = 0.02        # added to both means of the shading ratio, so black pixels cannot divide


def working_shape(height: int, width: int, working_size: int) -> tuple[int, int]:
    """(h, w) with the long side at most ``working_size``, aspect kept; never upscales."""
    long_side = max(height, width)
    if long_side <= working_size:
        return height, width
    f = working_size / long_side
    return max(1, int(round(height * f))), max(1, int(round(width * f)))


def _area_taps(n: int, m: int) -> tuple[np.ndarray, np.ndarray]:
    """Indices and weights (m, K) of an exact box (area) reduction from n to m <= n samples."""
    scale = n / m
    k = int(math.ceil(scale)) + 1
    lo = np.arange(m) * scale
    first = np.floor(lo).astype(np.int64)
    idx = first[:, None] + np.arange(k)[None, :]
    a = np.maximum(idx, lo[:, None])
    b = np.minimum(idx + 1, (lo + scale)[:, None])
    w = np.clip(b - a, 0.0, None) / scale
    return np.minimum(idx, n - 1), w.astype(np.float32)


def _linear_taps(n: int, m: int) -> tuple[np.ndarray, np.ndarray]:
    """Indices and weights (m, 2) of bilinear resampling with pixel centres aligned."""
    c = np.clip((np.arange(m) + 0.5) * (n / m) - 0.5, 0.0, n - 1)
    i0 = np.floor(c).astype(np.int64)
    i1 = np.minimum(i0 + 1, n - 1)
    f = (c - i0).astype(np.float32)
    return np.stack([i0, i1], axis=1), np.stack([1.0 - f, f], axis=1).astype(np.float32)


def _apply_taps(x: np.ndarray, axis: int, idx: np.ndarray, w: np.ndarray) -> np.ndarray:
    x = np.moveaxis(x, axis, 0)
    out = None
    for k in range(idx.shape[1]):
        wk = w[:, k].reshape((-1,) + (1,) * (x.ndim - 1))
        term = x[idx[:, k]] * wk
        out = term if out is None else out + term
    return np.moveaxis(out, 0, axis)


def resize(x: np.ndarray, height: int, width: int) -> np.ndarray:
    """Resize (H, W, C) float32: exact area averaging when shrinking an axis, bilinear when
    enlarging it. Area averaging in linear light keeps local means exact (no aliasing)."""
    x = np.asarray(x, dtype=np.float32)
    for axis, m in ((0, height), (1, width)):
        n = x.shape[axis]
        if n == m:
            continue
        idx, w = _area_taps(n, m) if m < n else _linear_taps(n, m)
        x = _apply_taps(x, axis, idx, w)
    return np.ascontiguousarray(x, dtype=np.float32)


def box_mean(x: np.ndarray, r: int) -> np.ndarray:
    """Mean over (2r+1)^2 windows clipped at the borders (cumulative sums: O(1) per pixel)."""
    out = x.astype(np.float64)
    for axis in (0, 1):
        n = out.shape[axis]
        c = np.cumsum(out, axis=axis)
        c = np.concatenate([np.zeros_like(np.take(c, [0], axis=axis)), c], axis=axis)
        hi = np.minimum(np.arange(n) + r + 1, n)
        lo = np.maximum(np.arange(n) - r, 0)
        shape = [1] * out.ndim
        shape[axis] = n
        out = (np.take(c, hi, axis=axis) - np.take(c, lo, axis=axis)) / (hi - lo).reshape(shape)
    return out


def guided_coefficients(guide: np.ndarray, target: np.ndarray, radius: int = RADIUS,
                        eps: float = EPS, floor: float = FLOOR) -> tuple[np.ndarray, np.ndarray]:
    """Per-channel local linear fit target ~ A * guide + B on (h, w, 3) arrays; returns (A, B)
    already box-averaged (the guided filter's second pass), as float32.

    The ridge pulls A toward the local shading ratio A0 = (mean target + floor) /
    (mean guide + floor) rather than toward 0, so texture too fine to survive at the working
    resolution (flat there, so nothing to fit) is still carried, scaled by the light's change."""
    g = np.nan_to_num(np.asarray(guide, dtype=np.float64))
    t = np.nan_to_num(np.asarray(target, dtype=np.float64))
    mg, mt = box_mean(g, radius), box_mean(t, radius)
    var = np.maximum(box_mean(g * g, radius) - mg * mg, 0.0)
    cov = box_mean(g * t, radius) - mg * mt
    a0 = np.clip((np.maximum(mt, 0.0) + floor) / (np.maximum(mg, 0.0) + floor), 0.0, MAX_GAIN)
    a = np.clip((cov + eps * a0) / (var + eps), 0.0, MAX_GAIN)
    b = mt - a * mg
    return box_mean(a, radius).astype(np.float32), box_mean(b, radius).astype(np.float32)


def transfer(input_full: np.ndarray, input_low: np.ndarray, relit_low: np.ndarray,
             radius: int = RADIUS, eps: float = EPS, floor: float = FLOOR) -> np.ndarray:
    """Full-resolution relit image from the working-resolution result (see module doc)."""
    h, w = input_full.shape[:2]
    if input_low.shape[:2] == (h, w):
        return np.asarray(relit_low, dtype=np.float32)
    a, b = guided_coefficients(input_low, relit_low, radius, eps, floor)
    a_up, b_up = np.split(resize(np.concatenate([a, b], axis=2), h, w), 2, axis=2)
    return a_up * np.asarray(input_full, dtype=np.float32) + b_up


def upsample_only(relit_low: np.ndarray, height: int, width: int) -> np.ndarray:
    """The no-detail option: the working-resolution result, bilinearly enlarged."""
    return resize(relit_low, height, width)


def ratio_transfer(input_full: np.ndarray, input_low: np.ndarray, relit_low: np.ndarray,
                   floor: float = 0.02, max_ratio: float = MAX_GAIN) -> np.ndarray:
    """The simpler alternative measured in the tests: a bounded shading ratio
    (relit + floor) / (input + floor), upsampled and multiplied into the input."""
    h, w = input_full.shape[:2]
    r = np.clip((relit_low + floor) / (np.maximum(input_low, 0.0) + floor), 0.0, max_ratio)
    return resize(r, h, w) * input_full
