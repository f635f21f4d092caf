"""numpy reference implementations of the full-resolution stages (addon/detail.py), channels
last (H, W, 3): what the tests measure the method with, and check the shipped onnxruntime graphs
against (tests/core/test_detail.py, tests/core/test_onnx_graph.py)."""

from __future__ import annotations

import numpy as np

from addon.detail import EPS, FLOOR, MAX_GAIN, RADIUS, box_mean, resize


def guided_coefficients(guide: np.ndarray, target: np.ndarray, radius: int = RADIUS,
                        eps: float = EPS, floor: float = FLOOR) -> tuple[np.ndarray, np.ndarray]:
    """Per-channel local linear fit target ~ A * guide + B on (h, w, 3) arrays; returns (A, B)
    already box-averaged (the guided filter's second pass), as float32.

    The ridge pulls A toward the local shading ratio A0 = (mean target + floor) /
    (mean guide + floor) rather than toward 0, so texture too fine to survive at the working
    resolution (flat there, so nothing to fit) is still carried, scaled by the light's change."""
    g = np.nan_to_num(np.asarray(guide, dtype=np.float32))
    t = np.nan_to_num(np.asarray(target, dtype=np.float32))
    mg, mt = box_mean(g, radius), box_mean(t, radius)
    var = np.maximum(box_mean(g * g, radius) - mg * mg, 0.0)
    cov = box_mean(g * t, radius) - mg * mt
    a0 = np.clip((np.maximum(mt, 0.0) + floor) / (np.maximum(mg, 0.0) + floor), 0.0, MAX_GAIN)
    a = np.clip((cov + np.float32(eps) * a0) / (var + np.float32(eps)), 0.0, MAX_GAIN)
    b = mt - a * mg
    return box_mean(a, radius), box_mean(b, radius)


def transfer(input_full: np.ndarray, input_low: np.ndarray, relit_low: np.ndarray,
             radius: int = RADIUS, eps: float = EPS, floor: float = FLOOR) -> np.ndarray:
    """Full-resolution relit image from the working-resolution result (addon/detail.py's
    method: out = up(A) * input_full + up(B))."""
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
