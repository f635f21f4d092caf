"""Steadying a clip's change of light over time.

The network sees each frame alone, so its estimate of the change of light (the per-pixel
coefficients ``out = up(a) * x + up(b)`` the pipeline applies at full resolution) wavers a little
from frame to frame, most at shadow edges, the terminator and hair, and the relit clip flickers
more than the footage. Each frame's coefficients are blended with its two neighbours' (weights
WEIGHTS), where the neighbour's light is the frame's own within LIGHT_TOLERANCE: a light that
jumps (a flash, a cut in an animated light) changes on its frame, while slow animation (a
turning HDRI) is smoothed like a still light; and only on the frame's own subject (its matte),
so the change never follows a subject that moved away or left the frame.

A frame's result depends only on its own and its neighbours' frames, never on which frames a
run or a farm chunk relights: a run also decodes and infers the neighbours just outside its
frames (context_frames), so chunks and resumed runs equal one run bit for bit."""

from __future__ import annotations

import numpy as np

from . import detail, lightvec

WEIGHTS = (0.25, 0.5, 0.25)   # previous, this, next frame
LIGHT_TOLERANCE = 0.05        # relative L2 distance of two frames' diffuse shading


def context_frames(todo, count: int) -> list[int]:
    """The frames to infer for relighting ``todo`` (0-based, in a clip of ``count``): each with
    its neighbours inside the clip, ascending."""
    need = set(todo)
    for i in todo:
        need.update(j for j in (i - 1, i + 1) if 0 <= j < count)
    return sorted(need)


def signature(light: np.ndarray) -> np.ndarray:
    """(256, 3): the diffuse irradiance ``light`` gives a surface facing each of the light
    vector's directions; two lights shade alike when their signatures do."""
    return lightvec.irradiance(light, lightvec.directions().reshape(-1, 3))


def alike(sig_a: np.ndarray, sig_b: np.ndarray, tolerance: float = LIGHT_TOLERANCE) -> bool:
    """Whether two signatures differ by at most ``tolerance`` of the larger in L2 (two black
    lights are alike): a key lamp turning 1 degree a frame differs by 1.7%, twice that by 3.4%;
    the lamp 20% brighter by 17%."""
    scale = max(float(np.linalg.norm(sig_a)), float(np.linalg.norm(sig_b)))
    return scale == 0.0 or float(np.linalg.norm(sig_a - sig_b)) <= tolerance * scale


def _fit(x: np.ndarray, shape) -> np.ndarray | None:
    """(C, h, w) ``x`` on the grid ``shape`` (C, H, W); None where either is a 1x1 placeholder
    (a frame with no portrait or no light)."""
    if x.shape == tuple(shape):
        return x
    if min(x.shape[1:]) < 2 or min(shape[1:]) < 2 or x.shape[0] != shape[0]:
        return None
    return detail.resize(x.transpose(1, 2, 0), shape[1], shape[2]).transpose(2, 0, 1)


def blend(ab, previous, following, mask=None, weights=WEIGHTS):
    """This frame's coefficients ``ab`` = (a, b) blended with its neighbours' (each (a, b) or
    None: outside the clip, another light, a black frame); the missing ones' weight goes to the
    others in proportion. ``mask`` (h, w) in [0, 1], this frame's subject: the blend applies
    there only, so a neighbour's change never lands where this frame has no subject (it moved,
    or left the frame)."""
    a, b = ab
    w_prev, w_this, w_next = (float(w) for w in weights)
    near = []
    for other, w in ((previous, w_prev), (following, w_next)):
        if other is None or w == 0.0:
            continue
        oa, ob = _fit(other[0], a.shape), _fit(other[1], b.shape)
        if oa is not None and ob is not None:
            near.append((oa, ob, w))
    if not near:
        return a, b
    total = w_this + sum(w for _, _, w in near)
    out = []
    for k, x in enumerate((a, b)):
        # The neighbours' weighted difference from this frame, added on the subject:
        # x + m * sum_j w_j (x_j - x) / total (in place: the grid is large at 4K).
        acc = np.zeros_like(x)
        for other in near:
            diff = np.subtract(other[k], x)
            diff *= np.float32(other[2] / total)
            acc += diff
        if mask is not None:
            acc *= np.clip(np.asarray(mask, np.float32), 0.0, 1.0)[None]
        acc += x
        out.append(acc)
    return out[0], out[1]
