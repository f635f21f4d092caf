"""The change of light stops at the subject's outline at full resolution.

Portrait builds the change on a grid of about the face crop's resolution and fades it in over
the matte's core (addon/portrait.py). Enlarged to the frame, that fade spans several pixels, and
where they show the background (a green screen beside the hair, a wall beside a shoulder) the
background takes the change: a bright or dark line along the outline. Here the fade's weight is
refitted to the footage's colours, a colour guided filter (He et al., "Guided Image Filtering",
2010) of the weight against the grid's footage, evaluated at full resolution where the footage's
own edges are; each pixel of the fade takes the share of the change its colour says is subject.
Mostly that takes change away (the background beside the outline); it also gives it back where
the fade, a working pixel or two wide when enlarged, lay over something thin the subject holds
(an ear against a screen, lit as the footage was beside a cheek the key lamp left dark), though
never where the enlarged weight was below UP_FLOOR, nor beyond the subject's own full change.
How much it gives back comes from the subject's own matte refitted the same way: the weight is
the matte's core, so its refit reads skin at the outline as partly background, and a jaw against
a screen kept a lit line beside a cheek the lamp left dark. A run that writes a matte strip
refits the matte the same way (``refine_matte``), so the strip follows the footage's edges too.

Only the fade is touched: the fit runs on the grid samples whose windows meet it, and the
correction on the full-resolution pixels whose bilinear samples do (a few percent of a frame).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from . import detail

RADIUS = 1     # the fit's window: (2 RADIUS + 1)^2 grid samples
EPS = 1e-3     # the fit's ridge, in units of the guide normalised to its LEVEL percentile
LEVEL = 99     # the percentile of the fade's guide samples that normalises the guide
FLOOR = 1e-3   # below this enlarged weight the change is nil and nothing is corrected
# The refit adds change (up to the subject's full change) only where the enlarged weight is at
# least this: within the fade's reach, so it never draws change far out onto the background, and
# the full change it scales up to (the relit value over the weight) stays well conditioned.
UP_FLOOR = 0.15
# Where the subject's own matte is fitted too (fit's ``subject``), a fade pixel takes the change
# as much as its colour surely says subject: the matte's refit faded in over SURE (smoothstep).
# Below SURE[0] (a colour the subject shares with the background: auburn hair against a pink
# wall) it adds nothing: given back linearly, such pixels darkened the wall beside the hair (dev
# footage, outline's darkest tenth 0.91 -> 0.88).
SURE = (0.5, 0.9)
# ... and at most the network's matte over this: whole where that matte, a sigmoid, says the
# subject at least half (where it draws the outline). Held to the matte itself, skin at the
# outline kept the footage's light in proportion to the matte's fade, a working pixel or two
# wide: a lit line along a jaw and a shoulder on the side a key lamp left dark (dev footage).
MATTE_WHOLE = 0.5


@dataclass
class Fit:
    """The fade's weight refitted to colour, on the grid: at each sample w ~ alpha . x / level
    + beta (outside the fade alpha = 0 and beta = the weight itself); the subject's matte the
    same way where it was given."""
    coef: np.ndarray     # (4, gh, gw) float32: alpha (3) and beta; (8, ...): the matte's after
    weight: np.ndarray   # (gh, gw) float32 in [0, 1]: what was fitted (a weight, a matte)
    cells: np.ndarray    # (gh, gw) bool: grid cells whose bilinear corners meet the fade
    level: float         # the guide's normalisation, in the units of the footage
    subject: np.ndarray | None = None  # (gh, gw) the subject's matte, where it was given


def _window(shape, flat: np.ndarray, r: int) -> np.ndarray:
    """((2r+1)^2, N) flat indices of the windows around ``flat`` samples, clamped at the
    grid's border (the window's offsets first, so sums over a window run along whole rows)."""
    h, w = shape
    y, x = np.divmod(flat, w)
    d = np.arange(-r, r + 1)
    yy = np.clip(y[None, None, :] + d[:, None, None], 0, h - 1)
    xx = np.clip(x[None, None, :] + d[None, :, None], 0, w - 1)
    return (yy * w + xx).reshape(-1, len(flat))


def _solve3(m: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Solutions of N symmetric 3x3 systems: ``m`` (6, N) as (00, 01, 02, 11, 12, 22), ``v``
    (3, N); by cofactors (the ridge keeps every system well away from singular)."""
    a, b, c, d, e, f = m
    c0, c1, c2 = d * f - e * e, c * e - b * f, b * e - c * d
    c4, c5, c8 = a * f - c * c, b * c - a * e, a * d - b * b
    inv_det = 1.0 / (a * c0 + b * c1 + c * c2)
    return np.stack([(c0 * v[0] + c1 * v[1] + c2 * v[2]) * inv_det,
                     (c1 * v[0] + c4 * v[1] + c5 * v[2]) * inv_det,
                     (c2 * v[0] + c5 * v[1] + c8 * v[2]) * inv_det])


def _dilate(mask: np.ndarray, r: int) -> np.ndarray:
    """``mask`` grown by ``r`` samples (a square)."""
    out = mask.copy()
    for axis in (0, 1):
        grown = out.copy()
        for k in range(1, r + 1):
            lo = [slice(None)] * 2
            hi = [slice(None)] * 2
            lo[axis], hi[axis] = slice(k, None), slice(None, -k)
            grown[tuple(lo)] |= out[tuple(hi)]
            grown[tuple(hi)] |= out[tuple(lo)]
        out = grown
    return out


def fit(grid: np.ndarray, weight: np.ndarray, radius: int = RADIUS, eps: float = EPS,
        tol: float = 0.0, subject: np.ndarray | None = None) -> Fit | None:
    """The colour guided filter of ``weight`` (gh, gw) in [0, 1] against ``grid`` (3, gh, gw),
    the footage on the grid, on the fade (tol < weight < 1 - tol) only; None when there is no
    fade. ``subject`` (gh, gw): the subject's own matte, of which the weight is the core; its
    filter over the same windows says how much of the subject a fade pixel's colour is (the
    share the refit gives back, ``shares``)."""
    weight = np.clip(np.asarray(weight, np.float32), 0.0, 1.0)
    fade = (weight > tol) & (weight < 1.0 - tol)
    if not fade.any():
        return None
    h, w = weight.shape
    near = _dilate(fade, radius)  # where the coefficients' window means need them
    src = np.flatnonzero(near)
    win = _window((h, w), src, radius)  # (K, N)
    k = np.float32(1.0 / win.shape[0])
    g = np.asarray(grid, np.float32).reshape(3, -1)[:, win]  # (3, K, N)
    level = float(np.percentile(g[:, win.shape[0] // 2].mean(0), LEVEL))
    level = level if level > 1e-12 else 1.0
    g *= np.float32(1.0 / level)
    mg = g.sum(1) * k
    pairs = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))
    sigma = np.stack([(g[i] * g[j]).sum(0) * k - mg[i] * mg[j] + (eps if i == j else 0.0)
                      for i, j in pairs]).astype(np.float32)
    targets = [weight] if subject is None else [
        weight, np.clip(np.asarray(subject, np.float32), 0.0, 1.0)]
    coef = np.zeros((4 * len(targets), h * w), np.float32)
    for t, target in enumerate(targets):
        p = target.reshape(-1)[win]  # (K, N)
        mp = p.sum(0) * k
        alpha = _solve3(sigma, (g * p[None]).sum(1) * k - mg * mp)  # (3, N)
        coef[4 * t:4 * t + 3, src], coef[4 * t + 3, src] = alpha, mp - (alpha * mg).sum(0)
    # The filter's second step: the coefficients averaged over each fade sample's window.
    dst = np.flatnonzero(fade)
    out = np.zeros_like(coef)
    for t, target in enumerate(targets):
        out[4 * t + 3] = target.reshape(-1)
    out[:, dst] = coef[:, _window((h, w), dst, radius)].sum(1) * k
    # Cells (top-left corners of a bilinear stencil) whose four corners meet the fade.
    cells = fade.copy()
    cells[:-1] |= fade[1:]
    cells[:, :-1] |= fade[:, 1:]
    cells[:-1, :-1] |= fade[1:, 1:]
    return Fit(out.reshape(-1, h, w), weight, cells, level,
               None if subject is None else targets[1])


def _axis(n: int, big: int):
    """Per full-resolution index along an axis of ``big`` pixels enlarged from ``n`` samples
    (detail.enlarge_planar's bilinear taps): the lower sample and the upper one's weight."""
    idx, wts = detail.linear_taps(n, big)
    return idx[:, 0], np.ascontiguousarray(wts[:, 1])


def pixels(f: Fit, height: int, width: int):
    """The full-resolution pixels whose bilinear stencil's first sample is a cell of ``f`` (so
    may lie in the enlarged fade), cell after cell (np.nonzero(f.cells) order): (their flat
    indices into the frame, how many each cell has, the upper row's and the right column's
    bilinear weight of each)."""
    h, w = f.weight.shape
    (r0, ty), (c0, tx) = _axis(h, height), _axis(w, width)
    # Each grid row owns a contiguous run of full-resolution rows (the runs' starts and lengths).
    y_start = np.searchsorted(r0, np.arange(h), side="left")
    y_len = np.searchsorted(r0, np.arange(h), side="right") - y_start
    x_start = np.searchsorted(c0, np.arange(w), side="left")
    x_len = np.searchsorted(c0, np.arange(w), side="right") - x_start
    cy, cx = np.nonzero(f.cells)
    n = y_len[cy] * x_len[cx]
    off = np.arange(int(n.sum())) - np.repeat(np.cumsum(n) - n, n)
    rows, cols = np.divmod(off, np.repeat(x_len[cx], n))
    rows += np.repeat(y_start[cy], n)
    cols += np.repeat(x_start[cx], n)
    return rows * width + cols, n, np.take(ty, rows), np.take(tx, cols)


def _at_pixels(f: Fit, x_full: np.ndarray, height: int, width: int):
    """At the fit's full-resolution pixels (``pixels``): their flat indices, (5, P) alpha (3),
    beta and the enlarged weight there (bilinear, as the finish enlarges), followed where the
    fit has the subject's matte by its alpha (3), beta and the enlarged matte ((10, P) in all),
    and (3, P) x_full."""
    pix, n, ty, tx = pixels(f, height, width)
    h, w = f.weight.shape
    # Each cell's stencil as a bilinear polynomial in the pixel's (tx, ty), per channel (alpha 3,
    # beta, the weight): c00 + tx d1 + ty (d2 + tx d3).
    cy, cx = np.nonzero(f.cells)
    cy1, cx1 = np.minimum(cy + 1, h - 1), np.minimum(cx + 1, w - 1)
    extra = [] if f.subject is None else [f.coef[4:], f.subject[None]]
    stack = np.concatenate([f.coef[:4], f.weight[None]] + extra, 0)
    c = stack.shape[0]
    stack = stack.reshape(c, -1)
    c00, c01 = np.take(stack, cy * w + cx, axis=1), np.take(stack, cy * w + cx1, axis=1)
    c10, c11 = np.take(stack, cy1 * w + cx, axis=1), np.take(stack, cy1 * w + cx1, axis=1)
    poly = np.concatenate([c00, c01 - c00, c10 - c00, c11 - c10 - c01 + c00], 0)  # (4c, K)
    e = np.repeat(poly, n, axis=1)  # (4c, P): the pixels come cell after cell
    e[c:2 * c] *= tx
    e[0:c] += e[c:2 * c]
    e[3 * c:] *= tx
    e[2 * c:3 * c] += e[3 * c:]
    e[2 * c:3 * c] *= ty
    e[0:c] += e[2 * c:3 * c]
    x = np.take(np.asarray(x_full, np.float32).reshape(3, -1), pix, axis=1)
    return pix, e[:c], x


def _refit(e: np.ndarray, x: np.ndarray, level: float) -> np.ndarray:
    return (e[0] * x[0] + e[1] * x[1] + e[2] * x[2]) * np.float32(1.0 / level) + e[3]


def shares(e: np.ndarray, x: np.ndarray, level: float) -> np.ndarray:
    """(P,) the share of its enlarged change each fade pixel keeps (1: as it was): the refitted
    weight over the enlarged one, clipped to [0, 1] as a weight, and not raised where the enlarged
    weight is below UP_FLOOR; where the fit has the subject's matte, a pixel at least UP_FLOOR
    in takes the larger of the weight's refit and the matte's, the latter faded in over SURE and
    at most the enlarged matte over MATTE_WHOLE (``e``, ``x``: _at_pixels')."""
    refit = np.clip(_refit(e, x, level), 0.0, 1.0)
    w = np.maximum(e[4], FLOOR)
    if len(e) >= 10:
        sure = np.clip((_refit(e[5:], x, level) - SURE[0]) / (SURE[1] - SURE[0]), 0.0, 1.0)
        cap = np.minimum(e[9] * np.float32(1.0 / MATTE_WHOLE), 1.0)
        up = np.maximum(refit, np.minimum(sure * sure * (3.0 - 2.0 * sure), cap))
    else:
        up = refit
    return np.where(e[4] >= UP_FLOOR, up / w, np.minimum(refit / w, 1.0)).astype(np.float32)


def apply(f: Fit | None, x_full: np.ndarray, y: np.ndarray, scale: float = 1.0,
          fullres: detail.FullRes | None = None) -> np.ndarray:
    """``y`` (3, H, W) half, the relit frame of ``x_full`` (3, H, W) (the footage over
    ``scale``: ``scale * x_full`` is the frame unchanged), with the change on the fade's pixels
    scaled by the refitted weight over the enlarged one (``shares``). In place; returns ``y``.
    ``fullres``: its graphs do the half-float mixing (built once if not given)."""
    if f is None:
        return y
    pix, e, x = _at_pixels(f, x_full, *y.shape[1:])
    share = shares(e, x, f.level)
    # Only where the refit changes the share (the rest keeps its value exactly).
    cut = np.flatnonzero((share != 1.0) & (e[4] > FLOOR) & (e[4] < 1.0))
    pix = np.take(pix, cut)
    flat = y.reshape(3, -1)
    mixed = (fullres or _fullres()).mix_half(np.take(flat, pix, axis=1), np.take(x, cut, axis=1),
                                             np.take(share, cut), scale)
    for c in range(3):
        flat[c][pix] = mixed[c]
    return y


MATTE_TOL = 0.02  # the network's matte is a sigmoid: its fade lies this far inside (0, 1)


def refine_matte(f: Fit | None, x_full: np.ndarray, matte: np.ndarray) -> np.ndarray:
    """``matte`` (H, W), the enlargement of the grid matte ``f`` was fitted to (fit(grid,
    matte, tol=MATTE_TOL)), with its fade's pixels taken from the colour refit, clipped to
    [0, 1]: the matte strip follows the footage's own edges (a hair's outline against a screen)
    instead of the grid's. In place; returns ``matte``."""
    if f is None:
        return matte
    pix, e, x = _at_pixels(f, x_full, *matte.shape)
    inside = np.flatnonzero((e[4] > MATTE_TOL) & (e[4] < 1.0 - MATTE_TOL))
    refit = _refit(np.take(e, inside, axis=1), np.take(x, inside, axis=1), f.level)
    matte.reshape(-1)[np.take(pix, inside)] = np.clip(refit, 0.0, 1.0)
    return matte


@functools.lru_cache(maxsize=1)
def _fullres() -> detail.FullRes:
    return detail.FullRes(threads=1)
