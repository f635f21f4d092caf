"""Portrait framing: the network runs on a square crop around the portrait, so a face gets the
working resolution whatever the frame's size or orientation.

The caller runs a coarse pass on the whole (downscaled) frame that gives per-pixel probability
maps of face skin and of the person; ``find_portrait`` turns them into a square ``Box``,
``smooth_boxes`` steadies the boxes over a clip, and ``crop`` / ``crop_weight`` / ``uncrop`` move
pixels between the frame and the network's square.

Coordinates are full-frame pixels, x to the right and y down; pixel (row i, column j) has its
centre at (j + 0.5, i + 0.5), so a frame of width W spans [0, W].
numpy only: this module must never import bpy or torch (scipy is not bundled either).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np

THRESHOLD = 0.5          # probability above which a coarse pixel counts as face / person
HEAD_FRACTION = 0.6      # matte fallback: the head is the top 0.6 x the person's width
LIFT = 0.05              # the box moves up by this fraction of its side: the head's top has hair
MIN_SIDE = 8.0           # full-frame pixels; a box never collapses below this
# The 2nd-98th percentile span of a filled disc (or ellipse) is this fraction of its diameter;
# dividing by it makes the robust extent of a face-shaped region its full diameter.
_ELLIPSE_SPAN = 0.8953
_UNCROP_ROWS = 256       # uncrop works in bands of rows so temporaries stay small at 4K and 8K


@dataclass(frozen=True)
class Box:
    """A square in full-frame pixels: centre (cx, cy) and side length ``size``."""

    cx: float
    cy: float
    size: float

    def __post_init__(self) -> None:
        # A NaN or empty box would silently produce garbage crops much later; fail here instead.
        if not (math.isfinite(self.cx) and math.isfinite(self.cy) and math.isfinite(self.size)):
            raise ValueError(f"Box needs finite values, got {self.to_tuple()}")
        if self.size <= 0:
            raise ValueError(f"Box needs a positive size, got {self.size}")

    def to_tuple(self) -> tuple[float, float, float]:
        """(cx, cy, size), for storing boxes in plain data (JSON, arrays)."""
        return (self.cx, self.cy, self.size)


def full_frame_box(frame_hw: tuple[int, int]) -> Box:
    """The fallback when no portrait is found: the square that holds the whole frame."""
    h, w = int(frame_hw[0]), int(frame_hw[1])
    return Box(w / 2.0, h / 2.0, float(max(h, w, 1)))


# --------------------------------------------------------------------------------------------
# Finding the portrait


def _components(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Label 8-connected components of a bool mask; returns (labels, areas), labels -1 off-mask.

    Run-length union-find: the Python loops go over runs, not pixels, so a coarse map is cheap
    (scipy.ndimage is not available in the extension).
    """
    h, w = mask.shape
    labels = np.full((h, w), -1, np.int64)
    if not mask.any():
        return labels, np.zeros(0, np.int64)
    padded = np.zeros((h, w + 2), np.int8)
    padded[:, 1:-1] = mask
    edges = np.diff(padded, axis=1)
    srow, start = np.nonzero(edges == 1)      # row-major order, so starts and ends pair up
    _, end = np.nonzero(edges == -1)          # end is exclusive
    n = len(start)
    parent = list(range(n))

    def root(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    row_first = np.searchsorted(srow, np.arange(h + 1))
    for r in range(h - 1):
        a, a_end = int(row_first[r]), int(row_first[r + 1])
        b, b_end = a_end, int(row_first[r + 2])
        while a < a_end and b < b_end:
            # 8-connectivity: runs on adjacent rows touch if they overlap or meet at a corner.
            if start[a] <= end[b] and start[b] <= end[a]:
                ra, rb = root(a), root(b)
                if ra != rb:
                    parent[max(ra, rb)] = min(ra, rb)
            if end[a] < end[b]:
                a += 1
            else:
                b += 1
    roots = np.array([root(i) for i in range(n)], np.int64)
    _, comp = np.unique(roots, return_inverse=True)
    comp = comp.reshape(-1)
    labels[mask] = np.repeat(comp, end - start)   # mask's pixels are the runs, in order
    areas = np.bincount(comp, weights=end - start).astype(np.int64)
    return labels, areas


def component_at(mask: np.ndarray, weight: np.ndarray) -> np.ndarray:
    """The 8-connected component of ``mask`` that holds most of ``weight`` (same shape, >= 0):
    the portrait among everything a matte marks; all False when the mask is empty."""
    labels, areas = _components(mask)
    if len(areas) == 0:
        return np.zeros_like(mask)
    held = np.bincount(labels[mask], weights=np.asarray(weight, np.float64)[mask],
                       minlength=len(areas))
    return labels == int(np.argmax(held))


def _largest(mask: np.ndarray) -> tuple[np.ndarray, int]:
    """The largest component (ties: the one found first, i.e. topmost) and its area."""
    labels, areas = _components(mask)
    if len(areas) == 0:
        return np.zeros_like(mask), 0
    k = int(np.argmax(areas))
    return labels == k, int(areas[k])


def find_portrait(face: np.ndarray, matte: np.ndarray, frame_hw: tuple[int, int],
                  margin: float = 2.0, min_face_px: float = 4.0) -> Box | None:
    """Square box around the portrait's head, or None when neither face nor person is seen.

    The face map decides where possible (with several faces the largest wins: the main subject
    is usually the nearest); without a usable face, the top of the largest person blob stands
    in for the head. ``margin`` scales the head's extent to leave room for hair, chin and
    shoulders. ``min_face_px`` is in coarse pixels: smaller face specks are noise.
    """
    face = np.asarray(face, np.float32)
    matte = np.asarray(matte, np.float32)
    if face.ndim != 2 or face.shape != matte.shape:
        raise ValueError(f"face and matte must be 2-D maps of one shape, got {face.shape} "
                         f"and {matte.shape}")
    if face.size == 0:
        return None
    h, w = face.shape
    frame_h, frame_w = int(frame_hw[0]), int(frame_hw[1])
    sy, sx = frame_h / h, frame_w / w          # full-frame pixels per coarse pixel

    region, area = _largest(face > THRESHOLD)   # NaN compares False: never part of a region
    if area < max(min_face_px, 1):
        person, area = _largest(matte > THRESHOLD)
        if area == 0:
            return None
        rows, cols = np.nonzero(person)
        top = rows.min()
        width = (cols.max() - cols.min() + 1) * sx                  # full-frame pixels
        head_rows = max(1, int(math.ceil(HEAD_FRACTION * width / sy)))
        region = person & (np.arange(h)[:, None] < top + head_rows)

    rows, cols = np.nonzero(region)
    ys = (rows + 0.5) * sy
    xs = (cols + 0.5) * sx
    cx, cy = float(xs.mean()), float(ys.mean())
    # Robust extent: percentiles ignore stray pixels (at least one coarse pixel).
    x2, x98 = np.percentile(xs, [2, 98])
    y2, y98 = np.percentile(ys, [2, 98])
    extent = max((x98 - x2) / _ELLIPSE_SPAN, (y98 - y2) / _ELLIPSE_SPAN, sx, sy)
    side = max(float(margin) * float(extent), MIN_SIDE)
    return Box(cx, cy - LIFT * side, side)


# --------------------------------------------------------------------------------------------
# Smoothing over a clip


def _centred(values: np.ndarray, window: int, reduce: Callable[..., np.ndarray]) -> np.ndarray:
    """Centred moving ``reduce`` (nanmedian / nanmean); the window is cut short at the ends."""
    half = window // 2
    padded = np.concatenate([np.full(half, np.nan), values, np.full(half, np.nan)])
    views = np.lib.stride_tricks.sliding_window_view(padded, 2 * half + 1)
    return reduce(views, axis=1)


def smooth_boxes(boxes: list[Box | None], window: int = 9) -> list[Box | None]:
    """Steady the crop over a clip: a jittering crop would make the relit face swim.

    Frames where nothing was found take the box interpolated from their found neighbours (held
    at the clip's ends). The median removes outliers and keeps cuts sharp; the average then
    removes the remaining jitter. The size is smoothed in log space, as zooms are relative.
    Windows are cut short at the clip's ends rather than padded (so the first and last frames
    are smoothed too), and an even ``window`` is widened by one to stay centred.
    """
    if window < 1:
        raise ValueError(f"window must be at least 1, got {window}")
    n = len(boxes)
    found = np.array([i for i, b in enumerate(boxes) if b is not None], np.int64)
    if len(found) == 0:
        return [None] * n
    data = np.array([[b.cx, b.cy, math.log(b.size)] for b in boxes if b is not None], np.float64)
    t = np.arange(n)
    out = np.empty((n, 3), np.float64)
    for k in range(3):
        filled = np.interp(t, found, data[:, k])
        if window > 1:
            filled = _centred(_centred(filled, window, np.nanmedian), window, np.nanmean)
        out[:, k] = filled
    return [Box(float(cx), float(cy), float(math.exp(ls))) for cx, cy, ls in out]


# --------------------------------------------------------------------------------------------
# Resampling between the frame and the square


def _span(coords: np.ndarray, n: int) -> tuple[int, int]:
    """Index range [lo, hi) of the source that bilinear taps at ``coords`` can touch (at least
    one pixel, inside the source)."""
    lo = int(np.clip(math.floor(float(coords.min())) - 2, 0, n - 1))
    hi = int(np.clip(math.ceil(float(coords.max())) + 2, lo + 1, n))
    return lo, hi


def _block_means(img: np.ndarray, lo_y: int, rows: int, lo_x: int, cols: int, f: int) -> np.ndarray:
    """Means of f x f blocks on a grid starting at source pixel (lo_y, lo_x), which may lie
    beyond the source: clamped indices make blocks there copies of the edge, as in crop()."""
    h, w = img.shape[:2]
    ry = np.clip(lo_y + np.arange(rows * f), 0, h - 1).reshape(rows, f)
    rx = np.clip(lo_x + np.arange(cols * f), 0, w - 1).reshape(cols, f)
    x0, x1 = int(rx.min()), int(rx.max()) + 1
    sub = img[:, x0:x1]
    acc = sub[ry[:, 0]].astype(np.float32)          # a loop over f keeps temporaries small
    for t in range(1, f):
        acc += sub[ry[:, t]]
    rx = rx - x0
    out = acc[:, rx[:, 0]]
    for t in range(1, f):
        out += acc[:, rx[:, t]]
    out /= np.float32(f * f)                        # divide, not multiply: keeps constants exact
    return out


def _linear_taps(pos: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Bilinear taps at continuous index ``pos`` (pixel centres at integers), clamped: beyond
    the source the edge pixel is replicated."""
    p = np.clip(pos, 0.0, n - 1)
    i0 = np.floor(p).astype(np.int64)
    i1 = np.minimum(i0 + 1, n - 1)
    f = (p - i0).astype(np.float32)
    return i0, i1, f


def _resample(img: np.ndarray, xs: np.ndarray, ys: np.ndarray, step: float) -> np.ndarray:
    """Sample ``img`` (H, W, C) at the grid xs x ys (pixel-centre convention: pixel k spans
    [k, k+1]), spaced ``step`` source pixels apart; returns (len(ys), len(xs), C) float32.

    Only the part of ``img`` the samples touch is read. When the samples are more than 2 pixels
    apart the source is area-averaged by the whole factor first, so fine detail does not alias.
    """
    f = int(step) if step > 2.0 else 1
    h, w = img.shape[:2]
    if f == 1:
        y0, y1 = _span(ys - 0.5, h)
        x0, x1 = _span(xs - 0.5, w)
        grid = img[y0:y1, x0:x1]
    else:
        # A block grid covering the samples with a block to spare on each side, so the taps
        # never clamp on the grid itself (beyond the frame the blocks are edge copies). It is
        # aligned with the samples where it can be, so a whole-number step is an exact box filter.
        y0 = round(float(ys.min()) - f / 2) - f
        x0 = round(float(xs.min()) - f / 2) - f
        rows = math.ceil((float(ys.max()) - y0) / f) + 2
        cols = math.ceil((float(xs.max()) - x0) / f) + 2
        grid = _block_means(img, y0, rows, x0, cols, f)
    iy0, iy1, fy = _linear_taps((ys - y0) / f - 0.5, grid.shape[0])
    ix0, ix1, fx = _linear_taps((xs - x0) / f - 0.5, grid.shape[1])
    # a + (b - a) * t rather than a * (1 - t) + b * t: equal taps give exactly a, so replicated
    # edges and flat areas come out bit-exact.
    top = grid[iy0]
    band = top + (grid[iy1] - top) * fy[:, None, None]
    left = band[:, ix0]
    return (left + (band[:, ix1] - left) * fx[None, :, None]).astype(np.float32, copy=False)


def _as_hwc(image: np.ndarray) -> tuple[np.ndarray, bool]:
    image = np.asarray(image, np.float32)
    if image.ndim == 2:
        return image[..., None], True
    if image.ndim != 3:
        raise ValueError(f"expected an (H, W, C) or (H, W) image, got shape {image.shape}")
    return image, False


def _crop_centres(box: Box, size: int) -> np.ndarray:
    """Centres of the crop's pixels along one axis, relative to the box's left/top edge."""
    return (np.arange(size, dtype=np.float64) + 0.5) * (box.size / size)


def crop(image: np.ndarray, box: Box, size: int) -> np.ndarray:
    """The box's square of ``image`` resampled to (size, size, C) float32 for the network.

    Beyond the frame the edge pixels are replicated (not zeros): the network then sees a
    plausible continuation instead of a black border it would try to relight.
    """
    if size < 1:
        raise ValueError(f"crop size must be at least 1, got {size}")
    img, flat = _as_hwc(image)
    if img.shape[0] == 0 or img.shape[1] == 0:
        raise ValueError(f"cannot crop an empty image of shape {img.shape}")
    offsets = _crop_centres(box, size)
    xs = box.cx - box.size / 2.0 + offsets
    ys = box.cy - box.size / 2.0 + offsets
    out = _resample(img, xs, ys, box.size / size)
    return out[..., 0] if flat else out


def crop_weight(box: Box, frame_hw: tuple[int, int], size: int) -> np.ndarray:
    """Fraction of each crop pixel that lies inside the frame: 1 inside, 0 where crop() filled
    by replication, in between on the frame's edge; lets losses and statistics skip padding."""
    h, w = int(frame_hw[0]), int(frame_hw[1])
    step = box.size / size
    starts = np.arange(size, dtype=np.float64) * step

    def cover(lo: float, n: int) -> np.ndarray:
        a = lo + starts
        return np.clip(np.minimum(a + step, n) - np.maximum(a, 0.0), 0.0, None) / step

    wy = cover(box.cy - box.size / 2.0, h)
    wx = cover(box.cx - box.size / 2.0, w)
    return np.clip(wy[:, None] * wx[None, :], 0.0, 1.0).astype(np.float32)


def uncrop(buffer: np.ndarray, box: Box, frame_hw: tuple[int, int],
           fill: float | Sequence[float]) -> np.ndarray:
    """Put a (size, size, C) result defined on the box back into an (H, W, C) frame.

    Frame pixels whose centre lies in the box are sampled bilinearly from ``buffer``; the rest
    get ``fill``. Works in bands of rows, so a 4K or 8K frame needs little beyond the output.
    """
    buf, flat = _as_hwc(buffer)
    if buf.shape[0] != buf.shape[1] or buf.shape[0] == 0:
        raise ValueError(f"uncrop needs a square (size, size, C) buffer, got {buf.shape}")
    h, w = int(frame_hw[0]), int(frame_hw[1])
    c = buf.shape[2]
    size = buf.shape[0]
    fill_c = np.broadcast_to(np.asarray(fill, np.float32).reshape(-1), (c,))
    out = np.empty((h, w, c), np.float32)
    out[...] = fill_c
    left = box.cx - box.size / 2.0
    top = box.cy - box.size / 2.0
    # Frame pixels whose centre k + 0.5 lies in [left, left + size] (closed).
    j0, j1 = max(0, math.ceil(left - 0.5)), min(w, math.floor(left + box.size - 0.5) + 1)
    i0, i1 = max(0, math.ceil(top - 0.5)), min(h, math.floor(top + box.size - 0.5) + 1)
    if j0 < j1 and i0 < i1:
        per_px = size / box.size                    # buffer pixels per frame pixel
        xs = (np.arange(j0, j1) + 0.5 - left) * per_px
        for r in range(i0, i1, _UNCROP_ROWS):
            r1 = min(r + _UNCROP_ROWS, i1)
            ys = (np.arange(r, r1) + 0.5 - top) * per_px
            out[r:r1, j0:j1] = _resample(buf, xs, ys, per_px)
    return out[..., 0] if flat else out
