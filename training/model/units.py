"""The network's units: a light-stage sample (absolute radiance) in the normalised units the network
sees, exactly as the engine shows it a clip (addon/normalise.py), and its relit output back in
absolute radiance. Training, export (int8 calibration) and evaluation share them."""

from __future__ import annotations

import numpy as np

from addon import normalise

from .network import to_channels_first

IMAGE_KEYS = ("img_t", "img_t1", "gt_t", "gt_t1")
MASK_KEYS = ("mask_t", "mask_t1", "parsing_t", "parsing_t1")
TRANSPORT_KEYS = ("transport_t", "transport_t1")


def _hwc(img: np.ndarray) -> np.ndarray:
    return np.moveaxis(img, 0, -1) if img.shape[0] == 3 else img


def normalise_sample(sample: dict) -> dict:
    """A light-stage sample (absolute radiance) -> the network's normalised units, exactly as the
    engine will see a clip: one exposure scale s for both frames (one clip), the target light at
    unit power (k), ground truth relit / k, source lights / s. Images stay channels-first.

    Why relit / k and not / (s k): image / s is the scene seen under lights / s (shading is linear
    in the light), so the target light L^k is L^k / s there, and its render is R(L^k / k) * k / s;
    back to absolute (* s) that is R(L^k / k) * k. The decoder sees L^k / k, so its output is
    R(L^k / k) = relit / k, a function of what the network sees. Dividing by s as well made the
    target depend on the absolute source power (unobservable in image / s) and the self-relit
    path (training.model.losses) disagree with the target path by that factor."""
    f32 = lambda a: np.asarray(a, dtype=np.float32)  # noqa: E731
    s = normalise.exposure_scale([_hwc(f32(sample["img_t_i"])), _hwc(f32(sample["img_t1_j"]))])
    unit_k, k = normalise.normalise_light(f32(sample["light_k"]))
    gain = 1.0 / k if k > 0 else 0.0  # an all-dark target: black ground truth
    out = {
        "img_t": f32(sample["img_t_i"]) / s, "img_t1": f32(sample["img_t1_j"]) / s,
        "gt_t": f32(sample["gt_t_k"]) * gain, "gt_t1": f32(sample["gt_t1_k"]) * gain,
        "light_k": to_channels_first(unit_k),
        "src_t": to_channels_first(f32(sample["light_i"]) / s),
        "src_t1": to_channels_first(f32(sample["light_j"]) / s),
        "scale": np.float32(s), "light_scale": np.float32(k),
    }
    for key in MASK_KEYS + ("flow_fw", "flow_bw", "valid_fw", "valid_bw"):
        out[key] = f32(sample[key])
    for key in TRANSPORT_KEYS:  # light-independent: no normalisation
        if key in sample:
            out[key] = f32(sample[key])
    return out


def relit_to_absolute(relit, scale: float, light_scale: float):
    """The network's relit output -> absolute radiance: the inverse of normalise_sample's target
    (relit / k). ``scale`` (s) is taken for symmetry with the inputs and deliberately unused."""
    del scale
    return relit * light_scale
