"""A face's mean shape as a prior on the network's up/down shape: the light stage's near-frontal
heads' normals averaged on a grid set by the face skin's own extent (training/intrinsic/template.py
builds ``models/face-template/template.npz``), laid over a crop where the network finds the face
skin, and taken as the low band of the normals' vertical component there (a least-squares
multiple of it, under the network's own detail). addon.portrait applies it to the face crop's
buffers, once on the mean of its passes (``portrait.FACE_TEMPLATE``).

On real faces the network's vertical normals are what the relit balance lacks (they correlate
about 0.7 with photometric stereo's on CroppedYale); with the template the CroppedYale test
subjects' top/bottom balance correlation rose from 0.817 to 0.833 (paired +0.016, 5-95% +0.005
to +0.028) at 20.31 -> 20.11 dB, left/right 0.982 either way, and the synthetic test set's
rmse_level_fit went from 0.0580 to 0.0576 (0.0577 since a turned head takes less of it, TURN;
0.832 and 0.0578 held once on the face crop's mean; training/README.md has the commands). It
is a prior, not the subject's shape: photometric stereo's normals on CroppedYale's tune
subjects turn less from forehead to chin (+0.06) than the network's (+0.14) and the network's
under the template (+0.25), whose vertical component correlates less with them (0.70 -> 0.62);
the relit balance follows the real light better all the same.
"""

from __future__ import annotations

import pathlib
from dataclasses import dataclass, replace

import numpy as np

from . import intrinsic

SIGMA = 6.0  # the low band's Gaussian, in pixels of a crop at the working size
BLEND_SIGMA = 2.0  # pixels over which the template's band fades in from the face skin's edge
MIN_SKIN = 64  # face-skin pixels below which a crop keeps the network's normals
# The template is a frontal face's: it holds a crop fully while the network's own normals over the
# face skin face sideways by at most TURN[0] on average (their mean x component, which follows
# the light stage's truth with a slope of 0.87 and a correlation of 0.94 on held-out heads), and
# fades out linearly to nothing at TURN[1]. On the light stage's held-out heads turned by 0.2 or
# more the template held fully cost the vertical normals' correlation with the truth 0.770 ->
# 0.687, faded 0.738 (bench/face_template_pose.py); CroppedYale's frontal faces read under 0.03.
TURN = (0.1, 0.3)
SHIPPED = pathlib.Path(__file__).resolve().parents[1] / "models" / "face-template" / "template.npz"
_LOADED: dict = {}
# The normals' components whose low band the template gives: the vertical one (y) by default,
# the up/down shape the relit balance lacks; the network's left/right shape is close to the real
# one (CroppedYale's left/right balance 0.98). AXES["xyz"]: all three.
AXES = {"y": (1,), "xyz": (0, 1, 2)}


@dataclass(frozen=True)
class Template:
    normal: np.ndarray  # (3, T, T) mean normals (not renormalised: a mean's length)
    reach: float        # the grid spans [-reach, reach] face sizes about the face skin's centre


def load(path) -> Template:
    """The template at ``path`` (an .npz with ``normal`` and ``reach``); a clear error when the
    file is missing or not one."""
    path = pathlib.Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"face template {path} not found: build it with "
                                "python -m training.intrinsic.template")
    with np.load(path) as z:
        if "normal" not in z or "reach" not in z:
            raise ValueError(f"{path} is not a face template (needs 'normal' and 'reach')")
        normal = np.asarray(z["normal"], np.float32)
        reach = float(z["reach"])
    if normal.ndim != 3 or normal.shape[0] != 3 or normal.shape[1] != normal.shape[2]:
        raise ValueError(f"{path}: the template's normals must be (3, T, T), not {normal.shape}")
    return Template(normal, reach)


def skin_frame(face: np.ndarray, matte: np.ndarray) -> tuple[float, float, float] | None:
    """(centre row, centre column, size) of the face skin (face and matte above 0.5), in pixel
    units with pixel centres at +0.5; size: the square root of its area. None below MIN_SKIN."""
    ys, xs = np.nonzero((face > 0.5) & (matte > 0.5))
    if len(ys) < MIN_SKIN:
        return None
    return float(ys.mean()) + 0.5, float(xs.mean()) + 0.5, float(np.sqrt(len(ys)))


def bilinear_weights(n: int, start: float, step: float,
                     t: int) -> tuple[np.ndarray, np.ndarray]:
    """((n, t) the bilinear weights of n pixels on a grid of t samples, the pixel i at sample
    start + i * step; (n,) whether the grid reaches it (its row of weights is 0 where not))."""
    u = start + np.arange(n, dtype=np.float64) * step
    reach = (u >= 0) & (u <= t - 1)
    u0 = np.clip(np.floor(u).astype(np.intp), 0, t - 2)
    tu = np.clip(u - u0, 0.0, 1.0)
    m = np.zeros((n, t), np.float64)
    rows = np.arange(n)
    m[rows, u0] = 1.0 - tu
    m[rows, u0 + 1] += tu
    m[~reach] = 0.0
    return m.astype(np.float32), reach


def _weights(template: Template, frame: tuple[float, float, float], hw: tuple[int, int]):
    """laid's bilinear weights: ((h, T) rows, (h,) rows reached, (w, T) columns, (w,) columns
    reached)."""
    cy, cx, size = frame
    t = template.normal.shape[1]
    scale = t / (2.0 * template.reach * size)
    wu, ru = bilinear_weights(hw[0], (0.5 - cy) * scale + t / 2.0 - 0.5, scale, t)
    wv, rv = bilinear_weights(hw[1], (0.5 - cx) * scale + t / 2.0 - 0.5, scale, t)
    return wu, ru, wv, rv


def laid(template: Template, frame: tuple[float, float, float],
         hw: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """((3, h, w) the template's normals at each pixel of an (h, w) crop whose face skin has
    ``frame`` (skin_frame's), bilinear, as two small matrix products; (h, w) where the grid
    reaches, 0 elsewhere)."""
    wu, ru, wv, rv = _weights(template, frame, hw)
    return _laid_with(template, wu, wv), ru[:, None] & rv[None, :]


def _laid_with(template: Template, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """(3, h, w) rows @ the template's normals @ cols^T: laid with (h, T) and (w, T) weights."""
    return np.matmul(np.matmul(rows, template.normal), cols.T)


def laid_low(template: Template, frame: tuple[float, float, float], hw: tuple[int, int],
             sigma: float) -> tuple[np.ndarray, np.ndarray]:
    """(laid's normals' low band, intrinsic.gaussian_blur(laid(...)[0], sigma); laid's reach
    mask)."""
    wu, ru, wv, rv = _weights(template, frame, hw)
    return _low(template, wu, wv, sigma), ru[:, None] & rv[None, :]


def _low(template: Template, wu: np.ndarray, wv: np.ndarray, sigma: float) -> np.ndarray:
    """The blur of the template laid with the bilinear weights ``wu``, ``wv`` (_weights'): the
    blur's matrices (intrinsic.blur_matrix) taken into the weights first, (B_h W_u) T (B_w
    W_v)^T, the same product associated so that no (h, w) plane is blurred: on a working-size
    crop about 1.7 times cheaper than the laid plane's blur by bands (intrinsic.banded_blur;
    bench.intrinsic_speed's face template rows), three times than by whole matrices. A blur
    narrow enough to add taps (intrinsic.TAPS_RADIUS) blurs the laid normals instead."""
    if intrinsic.blur_radius(sigma) <= intrinsic.TAPS_RADIUS:
        return intrinsic.gaussian_blur(_laid_with(template, wu, wv), sigma)
    return _laid_with(template, intrinsic.blur_matrix(wu.shape[0], sigma) @ wu,
                      intrinsic.blur_matrix(wv.shape[0], sigma) @ wv)


def turned_share(turn: float) -> float:
    """The share of the template a head takes whose face skin's mean sideways normal is
    ``turn``: 1 up to TURN[0] either way, 0 from TURN[1], linear between."""
    return float(np.clip((TURN[1] - abs(turn)) / (TURN[1] - TURN[0]), 0.0, 1.0))


def held(bufs: intrinsic.Buffers, template: Template, sigma: float = SIGMA,
         axes: tuple[int, ...] = AXES["y"]) -> intrinsic.Buffers:
    """``bufs`` with the low band (a Gaussian of ``sigma`` pixels of this crop) of their normals'
    components ``axes`` over the face skin replaced by the template's laid on it (laid,
    skin_frame), times the multiple that fits the network's own low band there best (least
    squares, over all three components), fading in over BLEND_SIGMA from the skin's edge; the
    detail, the other components and every other buffer kept (the normals renormalised). A
    crop with little face skin keeps its buffers; a turned head (TURN) takes less of the
    template or none."""
    frame = skin_frame(bufs.face, bufs.matte)
    if frame is None:
        return bufs
    wu, ru, wv, rv = _weights(template, frame, bufs.face.shape)
    skin = (bufs.face > 0.5) & (bufs.matte > 0.5) & ru[:, None] & rv[None, :]
    if int(skin.sum()) < MIN_SKIN:
        return bufs
    share = turned_share(float(bufs.normal[0][skin].mean()))
    if share <= 0.0:
        return bufs
    own, prior = intrinsic.gaussian_blur(bufs.normal, sigma), _low(template, wu, wv, sigma)
    p, o = prior[:, skin].astype(np.float64), own[:, skin].astype(np.float64)
    k = float((p * o).sum() / max(float((p * p).sum()), 1e-12))
    w = intrinsic.gaussian_blur(skin.astype(np.float32), BLEND_SIGMA) * np.float32(share)
    normal = bufs.normal.copy()
    for a in axes:
        normal[a] += w * (np.float32(k) * prior[a] - own[a])
    return replace(bufs, normal=intrinsic.unit_normals(normal).astype(np.float32))


def cached(path) -> Template:
    """load(``path``), once per path (as given: every relit frame asks)."""
    key = str(path)
    if key not in _LOADED:
        _LOADED[key] = load(path)
    return _LOADED[key]
