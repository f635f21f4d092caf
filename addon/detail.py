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
The stages run as small onnxruntime graphs (FullRes), channels first. tests/reference.py holds
the same method in numpy; tests/core/test_detail.py measures it against a synthetic ground truth
and against the alternatives (plain upsampling, a bounded shading ratio), and
tests/core/test_onnx_graph.py checks the graphs against it.
"""

from __future__ import annotations

import functools
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


def linear_taps(n: int, m: int) -> tuple[np.ndarray, np.ndarray]:
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
        idx, w = _area_taps(n, m) if m < n else linear_taps(n, m)
        x = _apply_taps(x, axis, idx, w)
    return np.ascontiguousarray(x, dtype=np.float32)


@functools.lru_cache(maxsize=32)
def linear_matrix(n: int, m: int) -> np.ndarray:
    """(m, n) float32 matrix of linear_taps (bilinear, pixel centres aligned); read-only,
    cached (a clip asks for the same few sizes every frame)."""
    idx, w = linear_taps(n, m)
    mat = np.zeros((m, n), np.float32)
    np.add.at(mat, (np.repeat(np.arange(m), 2), idx.reshape(-1)), w.reshape(-1))
    mat.flags.writeable = False
    return mat


def enlarge_planar(x: np.ndarray, height: int, width: int) -> np.ndarray:
    """(C, h, w) float32 -> (C, height, width), bilinear as resize() (each axis at least as
    large as before), channels-first, no transposes. Per axis, by upsample_blocks where the
    ratio has small blocks (each block of outputs is one small matrix times its window of
    inputs; bench.intrinsic_speed times it against whole matrices), else one matrix product
    (linear_matrix)."""
    c, h, w = x.shape
    if height < h or width < w:
        raise ValueError(f"enlarge_planar cannot shrink {(h, w)} to {(height, width)}")
    out = np.asarray(x, np.float32)
    if width != w:
        blocks = upsample_blocks(w, width)
        if blocks is None:
            out = out @ linear_matrix(w, width).T
        else:
            mat, win = blocks
            padded = np.pad(out, ((0, 0), (0, 0), (1, 1)), mode="edge")
            out = (padded[:, :, win] @ mat.T).reshape(c, h, width)
    if height != h:
        blocks = upsample_blocks(h, height)
        if blocks is None:
            out = linear_matrix(h, height) @ out
        else:
            mat, win = blocks
            padded = np.pad(out, ((0, 0), (1, 1), (0, 0)), mode="edge")
            out = np.matmul(mat, padded[:, win]).reshape(c, height, width)
    return np.ascontiguousarray(out, np.float32)


def box_mean(x: np.ndarray, r: int) -> np.ndarray:
    """float32 mean over (2r+1)^2 windows clipped at the borders (separable shifted sums)."""
    out = np.asarray(x, dtype=np.float32)
    for axis in (0, 1):
        n = out.shape[axis]
        pad = [(0, 0)] * out.ndim
        pad[axis] = (r, r)
        p = np.pad(out, pad)
        acc = np.take(p, np.arange(n), axis=axis)
        for k in range(1, 2 * r + 1):
            acc = acc + np.take(p, np.arange(k, k + n), axis=axis)
        i = np.arange(n)
        count = (np.minimum(i + r, n - 1) - np.maximum(i - r, 0) + 1).astype(np.float32)
        shape = [1] * out.ndim
        shape[axis] = n
        out = acc / count.reshape(shape)
    return out


# ---- the stages as onnxruntime graphs --------------------------------------------------------
#
# All graphs work channels-first (1, C, H, W): the layout the network takes, the one onnxruntime's
# resize kernels are fastest in (NHWC with C = 3 measured 1.5-2x slower), and the one the EXR
# writer stores (one row of each channel after another), so no full-resolution transpose is left.

HALF_MAX = 65504.0


def shrink_graph() -> bytes:
    """(1, C, H, W) -> (1, C, h, w): antialiased linear resize (a triangle filter as wide as the
    scale), one vectorised pass instead of numpy's several."""
    from . import onnx_graph as g
    return g.model(
        [g.node("Resize", ["x", "", "", "sizes"], ["y"], mode="linear", antialias=1,
                coordinate_transformation_mode="half_pixel")],
        [g.value_info("x", g.FLOAT, [1, "C", "H", "W"]), g.value_info("sizes", g.INT64, [4])],
        [g.value_info("y", g.FLOAT, [1, "C", "h", "w"])], name="shrink")


def area_graph() -> bytes:
    """(1, C, H, W) -> (1, C, h, w): exact area averaging when each axis shrinks by a ratio of
    small integers p/q (1080p to 512x288 is 15/4 on both): every block of p rows (columns)
    becomes q by one small matrix, so each axis is a reshape and a matrix product (vectorised,
    one read of the frame) instead of a resampling loop. See area_blocks."""
    from . import onnx_graph as g
    return g.model(
        [g.node("Reshape", ["x", "rows"], ["xr"]), g.node("MatMul", ["wv", "xr"], ["v"]),
         g.node("Reshape", ["v", "cols"], ["vr"]), g.node("MatMul", ["vr", "wh"], ["hr"]),
         g.node("Reshape", ["hr", "out"], ["y"])],
        [g.value_info("x", g.FLOAT, [1, "C", "H", "W"]),
         g.value_info("wv", g.FLOAT, ["q", "p"]), g.value_info("wh", g.FLOAT, ["P", "Q"]),
         g.value_info("rows", g.INT64, [5]), g.value_info("cols", g.INT64, [5]),
         g.value_info("out", g.INT64, [4])],
        [g.value_info("y", g.FLOAT, [1, "C", "h", "w"])], name="area")


MAX_BLOCK = 64  # longest block (input samples) the area graph takes; else the resize graph


def area_blocks(n: int, m: int) -> np.ndarray | None:
    """The (q, p) matrix of an exact area reduction of n samples to m (n/m = p/q in lowest
    terms), the same for every block of p samples; None if p > MAX_BLOCK or m > n."""
    if m > n:
        return None
    g = math.gcd(n, m)
    p, q = n // g, m // g
    if p > MAX_BLOCK:
        return None
    idx, w = _area_taps(n, m)
    idx, w = idx[:q], w[:q]
    inside = idx < p  # taps past the block carry zero weight
    block = np.zeros((q, p), np.float32)
    np.add.at(block, (np.nonzero(inside)[0], idx[inside]), w[inside])
    return block


def block_scale(height: int, width: int, f: float, tolerance: float = 0.1,
                min_q: int = 4) -> tuple[int, int] | None:
    """(q, p): a scale q/p near ``f`` (< 1) at which a height x width frame shrinks to whole numbers
    of pixels in blocks no longer than MAX_BLOCK (p divides both sides, p <= MAX_BLOCK), so the
    shrink takes area_graph and the enlargement back upsample_blocks: at 1080p the finish ran
    in 11-12 ms on such grids and 19 ms on others. q >= ``min_q``: with fewer input samples a
    block the enlargement's overlapping windows cost more than they save (q = 1: 17 ms).
    The nearest such scale within ``tolerance`` (relative), else None."""
    if not 0 < f < 1:
        return None
    g = math.gcd(int(height), int(width))
    best, best_err = None, math.log1p(tolerance)
    for p in range(min_q + 1, MAX_BLOCK + 1):
        if g % p:
            continue
        for q in {max(1, math.floor(f * p)), math.ceil(f * p)}:
            if q < min_q or q >= p or math.gcd(p, q) != 1:
                continue
            err = abs(math.log(q / (p * f)))
            if err < best_err - 1e-12:
                best, best_err = (q, p), err
    return best


def _clamp_tail(clamp: bool) -> list[bytes]:
    """The end of both finish graphs: ``out`` cast to half as ``y``; with ``clamp``, first
    clamped to [0, 65504] (radiance is never negative; +Inf becomes the half maximum, -Inf 0),
    and ``lowest``, the smallest value before the clamp, reported (a negative one is warned
    about). The caller knows from a cheap bound whether that can be needed, and saves the pass."""
    from . import onnx_graph as g
    if not clamp:
        return [g.node("Cast", ["out"], ["y"], to=g.FLOAT16)]
    return [g.node("ReduceMin", ["out"], ["lowest"], keepdims=0),
            g.node("Clip", ["out", "lo", "hi"], ["clamped"]),
            g.node("Cast", ["clamped"], ["y"], to=g.FLOAT16)]


def _finish_outputs(clamp: bool) -> list[bytes]:
    from . import onnx_graph as g
    y = [g.value_info("y", g.FLOAT16, [1, "C", "H", "W"])]
    return y + [g.value_info("lowest", g.FLOAT, [])] if clamp else y


def _clamp_consts() -> list[bytes]:
    from . import onnx_graph as g
    return [g.tensor("lo", np.float32(0.0)), g.tensor("hi", np.float32(HALF_MAX))]


def finish_graph(clamp: bool) -> bytes:
    """out = up(a) * x + up(b), cast to half (see _clamp_tail for ``clamp``)."""
    from . import onnx_graph as g
    tail = _clamp_tail(clamp)
    consts = _clamp_consts()
    return g.model(
        [g.node("Resize", ["a", "", "", "sizes"], ["a_up"], mode="linear",
                coordinate_transformation_mode="half_pixel"),
         g.node("Resize", ["b", "", "", "sizes"], ["b_up"], mode="linear",
                coordinate_transformation_mode="half_pixel"),
         g.node("Mul", ["a_up", "x"], ["ax"]),
         g.node("Add", ["ax", "b_up"], ["out"])] + tail,
        [g.value_info("a", g.FLOAT, [1, "C", "h", "w"]),
         g.value_info("b", g.FLOAT, [1, "C", "h", "w"]),
         g.value_info("x", g.FLOAT, [1, "C", "H", "W"]), g.value_info("sizes", g.INT64, [4])],
        _finish_outputs(clamp), consts if clamp else [], name="finish")


def upsample_blocks(n: int, m: int) -> tuple[np.ndarray, np.ndarray] | None:
    """Bilinear (half-pixel, edge-clamped) enlargement of n samples to m as blocks: with
    m/n = P/Q in lowest terms, output block k (P samples) is a (P, Q + 2) matrix times the
    window of input samples Qk-1 .. Qk+Q (indices into the input padded by one edge sample).
    Returns (matrix, window indices (n / Q, Q + 2)), or None if P > MAX_BLOCK or m < n."""
    if m < n:
        return None
    g = math.gcd(n, m)
    q, p = n // g, m // g
    if p > MAX_BLOCK:
        return None
    c = (np.arange(p) + 0.5) * (q / p) - 0.5  # source position, from the block's first sample
    i0 = np.floor(c).astype(np.int64)
    f = c - i0
    block = np.zeros((p, q + 2))
    np.add.at(block, (np.arange(p), i0 + 1), 1.0 - f)
    np.add.at(block, (np.arange(p), i0 + 2), f)
    windows = np.arange(n // q)[:, None] * q + np.arange(q + 2)[None, :]
    return block.astype(np.float32), windows.astype(np.int64)


def _enlarge_nodes(src: str, dst: str) -> list[bytes]:
    """Nodes taking (1, C, h, w) ``src`` to (1, C, H, W) ``dst`` by upsample_blocks: per axis,
    a gather of the overlapping windows and one matrix product (inputs win_w, mat_w, win_h,
    mat_h, rows, full; constant pads)."""
    from . import onnx_graph as g
    return [g.node("Pad", [src, "pads"], [src + "_p"], mode="edge"),
            g.node("Gather", [src + "_p", "win_w"], [src + "_gw"], axis=3),
            g.node("MatMul", [src + "_gw", "mat_w"], [src + "_hw"]),
            g.node("Reshape", [src + "_hw", "rows"], [src + "_h"]),
            g.node("Gather", [src + "_h", "win_h"], [src + "_gh"], axis=2),
            g.node("MatMul", ["mat_h", src + "_gh"], [src + "_vh"]),
            g.node("Reshape", [src + "_vh", "full"], [dst])]


def _enlarge_inputs() -> list[bytes]:
    from . import onnx_graph as g
    return [g.value_info("win_w", g.INT64, ["nw", "kw"]),
            g.value_info("mat_w", g.FLOAT, ["kw", "pw"]),
            g.value_info("win_h", g.INT64, ["nh", "kh"]),
            g.value_info("mat_h", g.FLOAT, ["ph", "kh"]),
            g.value_info("rows", g.INT64, [4]), g.value_info("full", g.INT64, [4])]


def _enlarge_feeds(c: int, h: int, w: int, big_h: int, big_w: int) -> dict | None:
    """The feeds of _enlarge_nodes, or None when an axis has no small blocks."""
    vert, horiz = upsample_blocks(h, big_h), upsample_blocks(w, big_w)
    if vert is None or horiz is None:
        return None
    return {"win_w": horiz[1], "mat_w": np.ascontiguousarray(horiz[0].T), "win_h": vert[1],
            "mat_h": vert[0], "rows": np.array([1, c, h + 2, big_w], np.int64),
            "full": np.array([1, c, big_h, big_w], np.int64)}


_EDGE_PADS = np.array([0, 0, 1, 1, 0, 0, 1, 1], np.int64)


def finish_blocks_graph(clamp: bool) -> bytes:
    """finish_graph with the two enlargements done by upsample_blocks (vectorised; 20-25%
    faster at 1080p than the resize op, same values to 1 half ulp)."""
    from . import onnx_graph as g
    nodes = _enlarge_nodes("a", "a_up") + _enlarge_nodes("b", "b_up")
    nodes += [g.node("Mul", ["a_up", "x"], ["ax"]), g.node("Add", ["ax", "b_up"], ["out"])]
    nodes += _clamp_tail(clamp)
    consts = [g.tensor("pads", _EDGE_PADS)] + (_clamp_consts() if clamp else [])
    return g.model(
        nodes,
        [g.value_info("a", g.FLOAT, [1, "C", "h", "w"]),
         g.value_info("b", g.FLOAT, [1, "C", "h", "w"]),
         g.value_info("x", g.FLOAT, [1, "C", "H", "W"])] + _enlarge_inputs(),
        _finish_outputs(clamp), consts, name="finish_blocks")


def upsample_blocks_graph() -> bytes:
    """upsample_graph with the enlargement done by upsample_blocks (the matte)."""
    from . import onnx_graph as g
    return g.model(
        _enlarge_nodes("x", "u") + [g.node("Clip", ["u", "lo", "hi"], ["c"]),
                                    g.node("Cast", ["c"], ["y"], to=g.FLOAT16)],
        [g.value_info("x", g.FLOAT, [1, "C", "h", "w"]), g.value_info("lo", g.FLOAT, []),
         g.value_info("hi", g.FLOAT, [])] + _enlarge_inputs(),
        [g.value_info("y", g.FLOAT16, [1, "C", "H", "W"])], [g.tensor("pads", _EDGE_PADS)],
        name="upsample_blocks")


def guided_graph(radius: int = RADIUS, eps: float = EPS, floor: float = FLOOR) -> bytes:
    """The guided fit on (1, 3, h, w): per channel, target ~ A * guide + B over box windows of
    ``radius``, the ridge ``eps`` pulling A toward the local shading ratio
    A0 = (mean target + floor) / (mean guide + floor) rather than toward 0 (texture too fine to
    survive at the working resolution, flat there, is still carried, scaled by the light's
    change), A clamped to [0, MAX_GAIN], A and B box-averaged again (the guided filter's second
    pass), both times ``gain``."""
    from . import onnx_graph as g
    k = 2 * radius + 1
    nodes = [g.node("Mul", ["G", "G"], ["GG"]), g.node("Mul", ["G", "T"], ["GT"])]

    def box(src, dst):
        nodes.append(g.node("AveragePool", [src], [dst], kernel_shape=[k, k],
                            pads=[radius] * 4, strides=[1, 1], count_include_pad=0))
    for src in ("G", "T", "GG", "GT"):
        box(src, "m" + src)
    nodes += [
        g.node("Mul", ["mG", "mG"], ["mG2"]), g.node("Sub", ["mGG", "mG2"], ["var0"]),
        g.node("Relu", ["var0"], ["var"]),
        g.node("Mul", ["mG", "mT"], ["mGmT"]), g.node("Sub", ["mGT", "mGmT"], ["cov"]),
        g.node("Relu", ["mT"], ["pT"]), g.node("Add", ["pT", "floor"], ["numr"]),
        g.node("Relu", ["mG"], ["pG"]), g.node("Add", ["pG", "floor"], ["denr"]),
        g.node("Div", ["numr", "denr"], ["r0"]), g.node("Clip", ["r0", "zero", "maxg"], ["a0"]),
        g.node("Mul", ["a0", "eps"], ["ea0"]), g.node("Add", ["cov", "ea0"], ["num"]),
        g.node("Add", ["var", "eps"], ["den"]), g.node("Div", ["num", "den"], ["a_raw"]),
        g.node("Clip", ["a_raw", "zero", "maxg"], ["a1"]),
        g.node("Mul", ["a1", "mG"], ["amG"]), g.node("Sub", ["mT", "amG"], ["b1"])]
    box("a1", "A")
    box("b1", "B")
    nodes += [g.node("Mul", ["A", "gain"], ["a"]), g.node("Mul", ["B", "gain"], ["b"])]
    consts = [g.tensor("eps", np.float32(eps)), g.tensor("floor", np.float32(floor)),
              g.tensor("zero", np.float32(0.0)), g.tensor("maxg", np.float32(MAX_GAIN))]
    return g.model(nodes, [g.value_info("G", g.FLOAT, [1, 3, "h", "w"]),
                           g.value_info("T", g.FLOAT, [1, 3, "h", "w"]),
                           g.value_info("gain", g.FLOAT, [])],
                   [g.value_info("a", g.FLOAT, [1, 3, "h", "w"]),
                    g.value_info("b", g.FLOAT, [1, 3, "h", "w"])], consts, name="guided")


def upsample_graph() -> bytes:
    """(1, C, h, w) -> (1, C, H, W) half, bilinear, clamped to [lo, hi]."""
    from . import onnx_graph as g
    return g.model(
        [g.node("Resize", ["x", "", "", "sizes"], ["u"], mode="linear",
                coordinate_transformation_mode="half_pixel"),
         g.node("Clip", ["u", "lo", "hi"], ["c"]),
         g.node("Cast", ["c"], ["y"], to=g.FLOAT16)],
        [g.value_info("x", g.FLOAT, [1, "C", "h", "w"]), g.value_info("sizes", g.INT64, [4]),
         g.value_info("lo", g.FLOAT, []), g.value_info("hi", g.FLOAT, [])],
        [g.value_info("y", g.FLOAT16, [1, "C", "H", "W"])], name="upsample")


def mix_graph() -> bytes:
    """(3, P) half ``y``, (3, P) ``x``, (1 or 3, P) ``share``, scalar ``scale`` -> (3, P) half
    x scale + share (y - x scale): a relit pixel taken part of the way back to its footage
    (addon.outline), for all its channels or each its own, its half-float conversions
    vectorised."""
    from . import onnx_graph as g
    return g.model(
        [g.node("Cast", ["y"], ["yf"], to=g.FLOAT), g.node("Mul", ["x", "scale"], ["xs"]),
         g.node("Sub", ["yf", "xs"], ["d"]), g.node("Mul", ["d", "share"], ["ds"]),
         g.node("Add", ["xs", "ds"], ["m"]), g.node("Cast", ["m"], ["out"], to=g.FLOAT16)],
        [g.value_info("y", g.FLOAT16, [3, "P"]), g.value_info("x", g.FLOAT, [3, "P"]),
         g.value_info("share", g.FLOAT, ["S", "P"]), g.value_info("scale", g.FLOAT, [])],
        [g.value_info("out", g.FLOAT16, [3, "P"])], name="mix")


def _finite(x: np.ndarray, big: float) -> np.ndarray:
    """float32 ``x`` with NaN -> 0 and +-Inf -> +-big; no copy when all is finite already (the
    usual case: one cheap check instead of a rewrite)."""
    x = np.asarray(x, np.float32)
    if np.isfinite(x).all():
        return x
    return np.nan_to_num(x, nan=0.0, posinf=np.float32(big), neginf=-np.float32(big))


class FullRes:
    """The full-resolution stages as small onnxruntime graphs, built once per run.

    Every method takes and returns channels-first (C, H, W) arrays. Holds only its sessions (no
    per-call state), so the decode and write threads can share it.
    """

    def __init__(self, threads: int | None = 1):
        from . import engine
        ort = engine.import_onnxruntime()
        so = engine.session_options(ort, threads, spin=False)
        cpu = ["CPUExecutionProvider"]
        self._shrink = ort.InferenceSession(shrink_graph(), so, providers=cpu)
        self._area = ort.InferenceSession(area_graph(), so, providers=cpu)
        self._finish = {c: ort.InferenceSession(finish_graph(c), so, providers=cpu)
                        for c in (False, True)}
        self._finish_blocks = {c: ort.InferenceSession(finish_blocks_graph(c), so,
                                                       providers=cpu) for c in (False, True)}
        self._guided = ort.InferenceSession(guided_graph(), so, providers=cpu)
        self._upsample = ort.InferenceSession(upsample_graph(), so, providers=cpu)
        self._upsample_blocks = ort.InferenceSession(upsample_blocks_graph(), so,
                                                     providers=cpu)
        self._mix = ort.InferenceSession(mix_graph(), so, providers=cpu)

    def shrink_planar(self, x: np.ndarray, height: int, width: int) -> np.ndarray:
        """(C, H, W) float32 -> (C, height, width): exact area averaging where both axes shrink
        by a ratio of small integers (the common video sizes), else antialiased (triangle)
        resampling. A clip always takes the same path, so its frames agree bit for bit."""
        x = np.ascontiguousarray(x, dtype=np.float32)
        c, big_h, big_w = x.shape
        if (big_h, big_w) == (height, width):
            return x
        wv, wh = area_blocks(big_h, height), area_blocks(big_w, width)
        if wv is None or wh is None:
            sizes = np.array([1, c, height, width], np.int64)
            return self._shrink.run(None, {"x": x[None], "sizes": sizes})[0][0]
        (qv, pv), (qh, ph) = wv.shape, wh.shape
        feeds = {"x": x[None], "wv": wv, "wh": np.ascontiguousarray(wh.T),
                 "rows": np.array([1, c, big_h // pv, pv, big_w], np.int64),
                 "cols": np.array([1, c, height, big_w // ph, ph], np.int64),
                 "out": np.array([1, c, height, width], np.int64)}
        return self._area.run(None, feeds)[0][0]

    def coefficients_planar(self, guide: np.ndarray, target: np.ndarray, gain: float):
        """The guided fit (guided_graph) of (3, h, w) arrays times ``gain``: (a, b), each
        (3, h, w); finite
        (non-finite inputs are 0, overflow becomes a huge finite value that the half clamp then
        catches). Low resolution, so the clean-up passes here cost little."""
        top = np.finfo(np.float32).max  # as np.nan_to_num: Inf becomes the largest float
        feeds = {"G": _finite(guide, top)[None], "T": _finite(target, top)[None],
                 "gain": np.array(gain, np.float32)}
        a, b = self._guided.run(None, feeds)
        return _finite(a[0], 1e30), _finite(b[0], 1e30)

    def finish_planar(self, x_full: np.ndarray, a: np.ndarray, b: np.ndarray,
                      x_max: float) -> tuple[np.ndarray, bool, float]:
        """(half (3, H, W) of up(a) * x_full + up(b) within [0, 65504], whether it may have
        been clamped, the smallest value before clamping (0.0 when nothing could be negative)).
        ``a``, ``b`` finite; ``x_max`` bounds x_full from above (x_full >= 0): with bilinear
        weights out <= max|a| * x_max + max|b|, and out >= 0 when a and b are, so the clamp
        pass runs only when needed."""
        x = np.ascontiguousarray(x_full, dtype=np.float32)
        bound = float(np.abs(a).max()) * float(x_max) + float(np.abs(b).max())
        clamp = not bound <= HALF_MAX or not (float(a.min()) >= 0 and float(b.min()) >= 0)
        feeds = {"a": np.ascontiguousarray(a, np.float32)[None],
                 "b": np.ascontiguousarray(b, np.float32)[None], "x": x[None]}
        (c, big_h, big_w), (h, w) = x.shape, a.shape[1:]
        blocks = _enlarge_feeds(c, h, w, big_h, big_w)
        if blocks is None:
            feeds["sizes"] = np.array([1, c, big_h, big_w], np.int64)
            outs = self._finish[clamp].run(None, feeds)
        else:
            outs = self._finish_blocks[clamp].run(None, {**feeds, **blocks})
        lowest = float(outs[1]) if clamp else 0.0
        return outs[0][0], clamp, lowest if lowest < 0 else 0.0

    def mix_half(self, y: np.ndarray, x: np.ndarray, share: np.ndarray,
                 scale: float) -> np.ndarray:
        """(3, P) half: x * scale + share * (y - x * scale), for (3, P) half ``y``, (3, P)
        ``x`` and (P,) ``share``, or (3, P): a share for each channel (mix_graph)."""
        if not share.size:
            return np.zeros((3, 0), np.float16)
        share = np.ascontiguousarray(share, np.float32).reshape(-1, share.shape[-1])
        return self._mix.run(None, {"y": np.ascontiguousarray(y, np.float16),
                                    "x": np.ascontiguousarray(x, np.float32),
                                    "share": share,
                                    "scale": np.array(scale, np.float32)})[0]

    def upsample_half_planar(self, low: np.ndarray, height: int, width: int, lo: float,
                             hi: float) -> np.ndarray:
        """(C, h, w) float32 -> half (C, height, width), bilinear, clamped to [lo, hi]."""
        low = np.ascontiguousarray(np.nan_to_num(low, nan=0.0, posinf=hi, neginf=lo),
                                   dtype=np.float32)
        feeds = {"x": low[None], "lo": np.array(lo, np.float32), "hi": np.array(hi, np.float32)}
        blocks = _enlarge_feeds(*low.shape, height, width)
        if blocks is None:
            feeds["sizes"] = np.array([1, low.shape[0], height, width], np.int64)
            return self._upsample.run(None, feeds)[0][0]
        return self._upsample_blocks.run(None, {**feeds, **blocks})[0][0]
