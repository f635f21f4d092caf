"""One frame through an intrinsic model: find the portrait, run the network on a square crop
around it, shade the target light there (addon/intrinsic.py) and apply the change to the
full-resolution frame as a ratio. The pipeline calls these per frame; ``addon.relight_image``
calls them on one image.

Framing: a coarse pass runs the network on the whole frame shrunk to the working size and gives
face-skin and matte maps; ``addon.framing`` turns them into a square box around the face, which a
second pass on that box refines (a face of 11 pixels in the coarse pass becomes a face of about
half the working size). Over a clip the boxes are smoothed (``framing.smooth_boxes``) so the crop
does not jitter. A frame with no portrait found is left unchanged (and counted, so the run can
say so).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import detail, framing, intrinsic
from .engine import IntrinsicSession

MARGIN = 2.2  # box side over the face's extent: room for hair, chin and a little shoulder


@dataclass(frozen=True)
class FrameResult:
    relit: np.ndarray   # (3, H, W) float32, the footage's units
    matte: np.ndarray   # (H, W) float32 in [0, 1]
    found: bool         # a portrait was found (else the frame is returned unchanged)
    plan: intrinsic.Plan | None


def _buffers(session: IntrinsicSession, x: np.ndarray, valid: np.ndarray | None = None):
    """The network's buffers for a (3, h, w) linear image (normalised here)."""
    res = session.run_planar(x * np.float32(intrinsic.exposure_scale(x)))
    names = session.card.classes
    matte = res.parsing[names.index("foreground")]
    face = res.parsing[names.index("skin")] if "skin" in names else np.zeros_like(matte)
    if valid is not None:  # replicated padding beyond the frame is not the subject
        matte, face = matte * valid, face * valid
    return intrinsic.Buffers(res.normal, res.height, res.albedo, matte, face)


def find_box(session: IntrinsicSession, x_full: np.ndarray) -> framing.Box | None:
    """The portrait's square box in a (3, H, W) frame, or None when there is none."""
    h, w = x_full.shape[1:]
    size = session.card.working_size
    ch, cw = detail.working_shape(h, w, size)
    small = detail.resize(np.ascontiguousarray(x_full.transpose(1, 2, 0)), ch, cw)
    coarse = _buffers(session, np.ascontiguousarray(small.transpose(2, 0, 1)))
    box = framing.find_portrait(coarse.face, coarse.matte, (h, w), MARGIN)
    if box is None:
        return None
    # Refine on the box itself, where the face has most of the working size.
    crop = framing.crop(np.ascontiguousarray(x_full.transpose(1, 2, 0)), box, size)
    valid = framing.crop_weight(box, (h, w), size)
    fine = _buffers(session, np.ascontiguousarray(crop.transpose(2, 0, 1)), valid)
    inner = framing.find_portrait(fine.face, fine.matte, (size, size), MARGIN)
    if inner is None:
        return box
    k = box.size / size
    return framing.Box(box.cx - box.size / 2 + inner.cx * k, box.cy - box.size / 2 + inner.cy * k,
                       inner.size * k)


def relight_frame(session: IntrinsicSession, x_full: np.ndarray, light: np.ndarray,
                  box: framing.Box | None, effects: intrinsic.Plan | None = None,
                  keep_exposure: bool = True) -> FrameResult:
    """Relight a (3, H, W) linear frame to ``light`` within ``box`` (None: nothing found, the
    frame comes back unchanged with an empty matte)."""
    h, w = x_full.shape[1:]
    if box is None:
        return FrameResult(x_full.astype(np.float32, copy=True), np.zeros((h, w), np.float32),
                           False, None)
    size = session.card.working_size
    hwc = np.ascontiguousarray(x_full.transpose(1, 2, 0))
    crop = np.ascontiguousarray(framing.crop(hwc, box, size).transpose(2, 0, 1))
    valid = framing.crop_weight(box, (h, w), size)
    bufs = _buffers(session, crop, valid)
    sh = intrinsic.shade(crop, bufs, light, effects, keep_exposure)
    m = np.clip(bufs.matte, 0.0, 1.0)[None]
    ratio = 1.0 + m * (sh.ratio - 1.0)   # the background keeps the footage as it was
    high = m * sh.highlight
    stack = np.concatenate([ratio, high, m], 0).transpose(1, 2, 0)
    fill = [1.0, 1.0, 1.0, 0.0, 0.0, 0.0, 0.0]
    full = framing.uncrop(np.ascontiguousarray(stack), box, (h, w), fill)
    relit = x_full * full[..., 0:3].transpose(2, 0, 1) + full[..., 3:6].transpose(2, 0, 1)
    return FrameResult(np.ascontiguousarray(relit, np.float32),
                       np.ascontiguousarray(full[..., 6]), True, sh.plan)
