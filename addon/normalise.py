"""Exposure and light normalisation shared by the engine and training (one code path).

The network sees ``image / s`` and ``light / k``; its relit output is brought back to scene-linear
radiance with ``relit * k`` (model cards say ``relit_scale: "k"``):
* ``s`` is one exposure scale per clip (never per frame: per-frame normalisation flickers), from a
  fixed sample of frames spread over the whole clip, so farm chunks agree bit for bit. It only
  conditions the input; the output does not depend on the footage's exposure, because the source
  light's absolute power cannot be observed from a normalised image (training targets that kept
  ``s`` asked the network for exactly that);
* ``k`` is the target light's mean radiance, so twice the light gives twice the output exactly,
  and an all-zero light gives a black frame without running the network.
Training divides its inputs the same way and its relit ground truth by ``k``; the estimated source
light is in the normalised image's units (light / s). The engine loads no card that says otherwise
(addon/contract.py RELIT_SCALE).
"""

from __future__ import annotations

import numpy as np

from . import colour

# The clip's 90th-percentile luminance is mapped to this level. Portraits are mostly mid-tones
# with dark backgrounds; the 90th percentile follows the lit face, not the background.
REFERENCE_LEVEL = 0.5
PERCENTILE = 90.0
TINY = 1e-8
REC709 = np.array(colour.REC709_LUMA, dtype=np.float32)


def luminance(rgb: np.ndarray) -> np.ndarray:
    """Rec.709 luminance of (..., 3) linear RGB (channels last)."""
    return np.asarray(rgb, dtype=np.float32) @ REC709


def sample_frame_indices(frame_count: int, n: int = 16) -> list[int]:
    """The fixed frames (0-based within the clip) that set the clip's exposure scale."""
    if frame_count <= 0:
        return []
    n = min(n, frame_count)
    return sorted({int(round(i * (frame_count - 1) / max(n - 1, 1))) for i in range(n)})


def exposure_scale(frames) -> float:
    """One scale s for a clip from sampled linear frames ((H, W, 3) each, channels last).

    Non-finite and negative pixels are ignored. A black clip gives s = 1 (nothing to normalise)."""
    vals = []
    for f in frames:
        y = luminance(f).reshape(-1)
        y = y[np.isfinite(y) & (y > 0)]
        if y.size > 65536:  # a strided subset is plenty for a percentile and keeps this fast
            y = y[:: y.size // 65536]
        vals.append(y)
    y = np.concatenate(vals) if vals else np.zeros(0, np.float32)
    if y.size == 0:
        return 1.0
    p = float(np.percentile(y, PERCENTILE))
    if not np.isfinite(p) or p <= TINY:
        return 1.0
    return p / REFERENCE_LEVEL


def light_scale(light: np.ndarray) -> float:
    """k: the mean radiance of a light vector over the sphere and the three channels."""
    from . import lightvec

    power = lightvec.total_power(light)  # per channel, steradian-weighted
    k = float(np.mean(power) / (4.0 * np.pi))
    return k if np.isfinite(k) and k > 0 else 0.0


def normalise_light(light: np.ndarray) -> tuple[np.ndarray, float]:
    """(light / k, k); an all-zero light returns (zeros, 0.0): the caller outputs black."""
    k = light_scale(light)
    if k <= 0:
        return np.zeros_like(np.asarray(light, dtype=np.float32)), 0.0
    return (np.asarray(light, dtype=np.float64) / k).astype(np.float32), k
