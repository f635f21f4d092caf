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

Where the subject's colour and the background's beside it are far apart (skin against a green
screen), a fade pixel is also read as a mix of the two (a two-colour model of the pixel: the
local colours of the subject's core and of the clear background around it): it takes the
change on the subject's part of its colour only, channel by channel, and its share of the
subject from that model where the model says more than the refit. Taken on the whole pixel, a
pixel half skin and half screen kept half the skin's footage light: under a key lamp from the
other side, a lit pink rim along a jaw and an ear against the screen, pixel-stepped.

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
# The two-colour model of a fade pixel (where the subject's matte is fitted too): the subject's
# colour is the mean of the grid samples within COLOUR_RADIUS whose matte is above CORE, the
# background's of those below CLEAR; each counts where at least FOUND of the window holds it.
# It takes over as the two colours' distance, over the larger colour's size, rises over
# DISTINCT. On the dev footage the outline's samples read 0.7-0.9 (skin and hair against a green
# screen), 0.9 (dark hair against a grey wall) and 0.6-0.85 (auburn hair against a paler pink
# wall); a wall of the skin's own colour and brightness, 0.09, is left to the refit alone.
CORE, CLEAR = 0.95, 0.05
COLOUR_RADIUS = 2
FOUND = 0.2
DISTINCT = (0.1, 0.3)
# A pixel's distance from the background's colour counts toward its share of the subject only
# beyond this share of the subject colour's distance: the screen's own noise and texture stay
# background (at none, a noisy screen beside the outline took up to 8% of the change).
FAR_FLOOR = 0.2


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
    # (7, gh, gw) on the fade, where the subject's matte was given and some fade sample has
    # two distinct colours beside it: the subject's colour (3), the background's (3) and how
    # far the two-colour model takes over (0 elsewhere); else None
    colours: np.ndarray | None = None


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
        tol: float = 0.0, subject: np.ndarray | None = None,
        colours: bool | None = None) -> Fit | None:
    """The colour guided filter of ``weight`` (gh, gw) in [0, 1] against ``grid`` (3, gh, gw),
    the footage on the grid, on the fade (tol < weight < 1 - tol) only; None when there is no
    fade. ``subject`` (gh, gw): the subject's own matte, of which the weight is the core; its
    filter over the same windows says how much of the subject a fade pixel's colour is (the
    share the refit gives back, ``shares``). ``colours``: whether to fit the two-colour model
    too (Fit's ``colours``, on the subject's matte, else on ``weight`` as a matte); by default
    where ``subject`` is given."""
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
    cells = _cells(fade)
    two = (subject is not None) if colours is None else colours
    return Fit(out.reshape(-1, h, w), weight, cells, level,
               None if subject is None else targets[1],
               _colours(np.asarray(grid, np.float32), targets[-1], near) if two else None)


def _cells(mask: np.ndarray) -> np.ndarray:
    """(gh, gw) bool: the cells (named by the top-left corner of their bilinear stencil) with a
    corner in ``mask``."""
    cells = mask.copy()
    cells[:-1] |= mask[1:]
    cells[:, :-1] |= mask[:, 1:]
    cells[:-1, :-1] |= mask[1:, 1:]
    return cells


def _colours(grid: np.ndarray, subject: np.ndarray, near: np.ndarray) -> np.ndarray | None:
    """Fit's ``colours`` on ``near`` (gh, gw) bool (the fade and the samples beside it, so a
    cell at the fade's outer edge has them at every corner), the colours times the share ``t``
    the model takes (so that enlarged bilinearly they stay a weighted mean); None where no sample
    has two distinct colours beside it."""
    h, w = subject.shape
    core, clear = subject > CORE, subject < CLEAR
    # Only samples with both within reach can have both colours.
    at = np.flatnonzero(near & _dilate(core, COLOUR_RADIUS) & _dilate(clear, COLOUR_RADIUS))
    if not at.size:
        return None
    win = _window((h, w), at, COLOUR_RADIUS)  # (K, N)
    g = grid.reshape(3, -1)[:, win]  # (3, K, N)
    inner, outer = core.reshape(-1)[win], clear.reshape(-1)[win]
    n_in, n_out = inner.sum(0), outer.sum(0)
    fg = np.maximum((g * inner).sum(1), 0.0) / np.maximum(n_in, 1)  # colours, not negative
    bg = np.maximum((g * outer).sum(1), 0.0) / np.maximum(n_out, 1)
    size = np.maximum(np.linalg.norm(fg, axis=0), np.linalg.norm(bg, axis=0))
    apart = np.linalg.norm(fg - bg, axis=0) / np.maximum(size, 1e-12)
    found = np.float32(1.0 / (FOUND * win.shape[0]))
    t = (np.clip((apart - DISTINCT[0]) / (DISTINCT[1] - DISTINCT[0]), 0.0, 1.0)
         * np.clip(n_in * found, 0.0, 1.0) * np.clip(n_out * found, 0.0, 1.0))
    if not (t > 0).any():
        return None
    out = np.zeros((7, h * w), np.float32)
    out[0:3, at], out[3:6, at], out[6, at] = fg * t, bg * t, t
    return out.reshape(7, h, w)


def _axis(n: int, big: int):
    """Per full-resolution index along an axis of ``big`` pixels enlarged from ``n`` samples
    (detail.enlarge_planar's bilinear taps): the lower sample and the upper one's weight."""
    idx, wts = detail.linear_taps(n, big)
    return idx[:, 0], np.ascontiguousarray(wts[:, 1])


def _enlarged(f: Fit, stack: np.ndarray, height: int, width: int,
              cells: np.ndarray | None = None):
    """(flat indices into the frame of the full-resolution pixels whose bilinear stencil's first
    sample is a cell of ``f`` (or of ``cells``, a subset of f.cells), cell after cell in
    np.nonzero order and row by row within a cell; how many each cell has; (c, P) ``stack``
    (c, gh, gw) enlarged bilinearly at them, as the finish enlarges)."""
    h, w = f.weight.shape
    (r0, ty), (c0, tx) = _axis(h, height), _axis(w, width)
    # Each grid row owns a contiguous run of full-resolution rows (the runs' starts and lengths).
    y_start = np.searchsorted(r0, np.arange(h), side="left")
    y_len = np.searchsorted(r0, np.arange(h), side="right") - y_start
    x_start = np.searchsorted(c0, np.arange(w), side="left")
    x_len = np.searchsorted(c0, np.arange(w), side="right") - x_start
    cy, cx = np.nonzero(f.cells if cells is None else cells)
    cy1, cx1 = np.minimum(cy + 1, h - 1), np.minimum(cx + 1, w - 1)
    c = stack.shape[0]
    stack = stack.reshape(c, -1)
    c00, c01 = np.take(stack, cy * w + cx, axis=1), np.take(stack, cy * w + cx1, axis=1)
    c10, c11 = np.take(stack, cy1 * w + cx, axis=1), np.take(stack, cy1 * w + cx1, axis=1)
    # Each cell's stencil is c00 + tx d1 + ty (d2 + tx d3) in the pixel's (tx, ty): along one
    # full-resolution row of a cell (a segment) it is a + tx b, a and b set by the row's ty.
    rows = y_len[cy]
    seg = np.repeat(np.arange(len(cy)), rows)  # the cell of each segment
    seg_y = y_start[cy][seg] + np.arange(len(seg)) - np.repeat(np.cumsum(rows) - rows, rows)
    t = np.take(ty, seg_y)
    a = np.take(c10 - c00, seg, axis=1)
    a *= t
    a += np.take(c00, seg, axis=1)
    b = np.take(c11 - c10 - c01 + c00, seg, axis=1)
    b *= t
    b += np.take(c01 - c00, seg, axis=1)
    cols = x_len[cx][seg]  # pixels in each segment
    first = np.repeat(np.cumsum(cols) - cols, cols)
    x = np.repeat(x_start[cx][seg], cols) + np.arange(int(cols.sum())) - first
    e = np.repeat(a, cols, axis=1)
    e += np.repeat(b, cols, axis=1) * np.take(tx, x)
    return np.repeat(seg_y, cols) * width + x, rows * x_len[cx], e


def _at_pixels(f: Fit, x_full: np.ndarray, height: int, width: int):
    """At the fit's full-resolution pixels (_enlarged's): their flat indices, (5, P) alpha (3),
    beta and the enlarged weight there (bilinear, as the finish enlarges), followed where the
    fit has the subject's matte by its alpha (3), beta and the enlarged matte ((10, P) in all),
    (3, P) x_full, and how many of the pixels each cell has."""
    extra = [] if f.subject is None else [f.coef[4:], f.subject[None]]
    stack = np.concatenate([f.coef[:4], f.weight[None]] + extra, 0)
    pix, n, e = _enlarged(f, stack, height, width)
    x = np.take(np.asarray(x_full, np.float32).reshape(3, -1), pix, axis=1)
    return pix, e, x, n


def _coloured(f: Fit, n: np.ndarray, height: int, width: int):
    """Where the fit has colours: (the indices into _at_pixels' pixels (``n`` of them a cell)
    of those in cells with a corner the two-colour model reaches, (7, P') the colours enlarged
    at them)."""
    cells = f.cells & _cells(f.colours[6] > 0)
    cy, cx = np.nonzero(f.cells)
    _, _, col = _enlarged(f, f.colours, height, width, cells)
    return np.flatnonzero(np.repeat(cells[cy, cx], n)), col


def _refit(e: np.ndarray, x: np.ndarray, level: float) -> np.ndarray:
    out = np.einsum("cp,cp->p", e[0:3], x)
    out *= np.float32(1.0 / level)
    out += e[3]
    return out


def shares(e: np.ndarray, x: np.ndarray, level: float) -> np.ndarray:
    """(P,) the share of its enlarged change each fade pixel keeps (1: as it was): the refitted
    weight over the enlarged one, clipped to [0, 1] as a weight, and not raised where the enlarged
    weight is below UP_FLOOR; where the fit has the subject's matte, a pixel at least UP_FLOOR
    in takes the larger of the weight's refit and the matte's, the latter faded in over SURE and
    at most the enlarged matte over MATTE_WHOLE (``e``, ``x``: _at_pixels')."""
    refit = np.clip(_refit(e, x, level), 0.0, 1.0)
    w = np.maximum(e[4], FLOOR)
    if len(e) >= 10:  # in place: this runs on every pixel of the fade
        sure = _refit(e[5:], x, level)
        sure -= np.float32(SURE[0])
        sure *= np.float32(1.0 / (SURE[1] - SURE[0]))
        np.clip(sure, 0.0, 1.0, out=sure)
        smooth = np.float32(3.0) - np.float32(2.0) * sure
        sure *= sure
        sure *= smooth
        cap = e[9] * np.float32(1.0 / MATTE_WHOLE)
        np.minimum(cap, 1.0, out=cap)
        np.minimum(sure, cap, out=sure)
        up = np.maximum(refit, sure, out=sure)
    else:
        up = refit.copy()
    up /= w
    refit /= w
    np.minimum(refit, 1.0, out=refit)
    return np.where(e[4] >= UP_FLOOR, up, refit)


def _two_colour(colours: np.ndarray, x: np.ndarray):
    """(alpha (P,), t (P,), t (F - B) (3, P), t B (3, P)) at pixels of colour ``x`` (3, P), from
    the fit's ``colours`` enlarged there (7, P): F and B the subject's colour and the
    background's beside the pixel, t the share the model takes. alpha, in [0, 1], is the pixel's
    colour projected on the line from B to F, or, where more, its distance from B over F's (less
    FAR_FLOOR of it): a thin part of the subject whose colour is not the core's beside it (an
    ear's skin beside dark hair) projects short on that line but lies as far from the screen.
    The colours come times t, which both ratios cancel."""
    fg, bg, t = colours[0:3], colours[3:6], colours[6]
    d = fg - bg
    off = x * t
    off -= bg
    inv = np.float32(1.0) / np.maximum(np.einsum("cp,cp->p", d, d), 1e-24)
    along = np.einsum("cp,cp->p", off, d)
    along *= inv
    far = np.einsum("cp,cp->p", off, off)
    far *= inv
    np.sqrt(far, out=far)
    far -= np.float32(FAR_FLOOR)
    far *= np.float32(1.0 / (1.0 - FAR_FLOOR))
    np.maximum(along, far, out=along)
    return np.clip(along, 0.0, 1.0, out=along), np.clip(t, 0.0, 1.0), d, bg


def split(weight: np.ndarray, matte: np.ndarray, colours: np.ndarray, x: np.ndarray,
          share: np.ndarray) -> np.ndarray:
    """(3, P) each fade pixel's share of its enlarged change per channel, from ``shares``'
    ``share`` (P,), the enlarged weight and matte there (P,) and the fit's ``colours`` enlarged
    there (7, P), at pixels of colour ``x`` (3, P): the pixel read as a mix of the subject's
    colour F and the background's B beside it, alpha F + (1 - alpha) B, alpha as _two_colour
    reads it (no more than the enlarged matte over MATTE_WHOLE, and raising the refit's weight
    only where the enlarged weight is at least UP_FLOOR), takes the change on alpha F only,
    channel by channel; faded in by the colours' share t."""
    w = np.maximum(weight, FLOOR)
    now = share * w  # the weight of the change the refit gives
    alpha, t, d, bg = _two_colour(colours, x)
    np.minimum(alpha, matte * np.float32(1.0 / MATTE_WHOLE), out=alpha)
    alpha = np.where(weight >= UP_FLOOR, np.maximum(alpha, now), now)
    # alpha F over the pixel's whole, alpha F + (1 - alpha) B = B + alpha (F - B) (all times t)
    whole = d * alpha
    whole += bg
    np.maximum(whole, 1e-30, out=whole)
    part = d  # _two_colour's, no longer needed: F, then alpha F
    part += bg
    part *= alpha
    part /= whole
    np.minimum(part, 1.0, out=part)
    # now + t (part - now), over w
    inv = np.float32(1.0) / w
    part *= t * inv
    part += now * (np.float32(1.0) - t) * inv
    return part


def apply(f: Fit | None, x_full: np.ndarray, y: np.ndarray, scale: float = 1.0,
          fullres: detail.FullRes | None = None) -> np.ndarray:
    """``y`` (3, H, W) half, the relit frame of ``x_full`` (3, H, W) (the footage over
    ``scale``: ``scale * x_full`` is the frame unchanged), with the change on the fade's pixels
    scaled by the refitted weight over the enlarged one (``shares``), per channel where the fit
    has the two colours (``split``). In place; returns ``y``. ``fullres``: its graphs do the
    half-float mixing (built once if not given)."""
    if f is None:
        return y
    pix, e, x, n = _at_pixels(f, x_full, *y.shape[1:])
    share = shares(e, x, f.level)
    fade = (e[4] > FLOOR) & (e[4] < 1.0)
    flat = y.reshape(3, -1)
    mix = (fullres or _fullres()).mix_half

    def put(at, x_at, share_at):  # mix the pixels ``at`` (indices into pix) in place
        p = np.take(pix, at)
        mixed = mix(np.take(flat, p, axis=1), x_at, share_at, scale)
        for c in range(3):
            flat[c][p] = mixed[c]

    if f.colours is not None:  # the pixels the two-colour model reaches: a share per channel
        on, col = _coloured(f, n, *y.shape[1:])
        keep = fade[on]
        on, col = on[keep], col[:, keep]
        x_on = np.take(x, on, axis=1)
        put(on, x_on, split(np.take(e[4], on), np.take(e[9], on), col, x_on, np.take(share, on)))
        fade[on] = False  # mixed
    # Only where the refit changes the share (the rest keeps its value exactly).
    cut = np.flatnonzero((share != 1.0) & fade)
    put(cut, np.take(x, cut, axis=1), np.take(share, cut))
    return y


MATTE_TOL = 0.02  # the network's matte is a sigmoid: its fade lies this far inside (0, 1)


def refine_matte(f: Fit | None, x_full: np.ndarray, matte: np.ndarray) -> np.ndarray:
    """``matte`` (H, W), the enlargement of the grid matte ``f`` was fitted to (fit(grid,
    matte, tol=MATTE_TOL, colours=True)), with its fade's pixels taken from the colour refit,
    clipped to [0, 1], and where the fit has colours from the two-colour model's alpha as far
    as it takes over (``split``'s): the matte strip follows the footage's own edges (a hair's
    outline against a screen) instead of the grid's. In place; returns ``matte``."""
    if f is None:
        return matte
    pix, e, x, n = _at_pixels(f, x_full, *matte.shape)
    alpha = np.clip(_refit(e, x, f.level), 0.0, 1.0)
    if f.colours is not None:
        on, col = _coloured(f, n, *matte.shape)
        a2, t, _, _ = _two_colour(col, np.take(x, on, axis=1))
        alpha[on] += t * (a2 - alpha[on])
    inside = np.flatnonzero((e[4] > MATTE_TOL) & (e[4] < 1.0 - MATTE_TOL))
    matte.reshape(-1)[np.take(pix, inside)] = np.take(alpha, inside)
    return matte


@functools.lru_cache(maxsize=1)
def _fullres() -> detail.FullRes:
    return detail.FullRes(threads=1)
