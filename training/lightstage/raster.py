"""A small z-buffer rasteriser in torch (CPU, or a GPU where one is present).

Triangles are binned by the size of their pixel bounding box; each bin tests all candidate pixel
centres of all its triangles at once, and the nearest fragment per pixel wins through one
``scatter_reduce(amin)`` on a 64-bit key (depth bits high, triangle id low). Barycentrics are then
recomputed per pixel for the winning triangle only, perspective-correct.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

# Bounding-box sizes (pixels per side) that each get one vectorised pass; larger boxes are split.
_BINS = (1, 2, 4, 8, 16, 32, 64)
_EMPTY = torch.iinfo(torch.int64).max


@dataclass
class Raster:
    face: torch.Tensor   # (H, W) int64 triangle id, -1 where nothing was drawn
    bary: torch.Tensor   # (H, W, 3) float32 perspective-correct barycentrics (0 where empty)
    depth: torch.Tensor  # (H, W) float32 view depth (inf where empty)

    @property
    def mask(self) -> torch.Tensor:
        return self.face >= 0


def _edge(ax, ay, bx, by, px, py):
    return (bx - ax) * (py - ay) - (by - ay) * (px - ax)


def _candidates(tri, ids, x0, y0, side, height, width):
    """Fragments (pixel index, key) of triangles ``ids`` tested on a side x side pixel grid."""
    off = torch.arange(side, device=tri.device)
    oy, ox = torch.meshgrid(off, off, indexing="ij")
    px = (x0[:, None] + ox.reshape(1, -1))
    py = (y0[:, None] + oy.reshape(1, -1))
    t = tri[ids]  # (n, 3, 3): x, y in pixels, z view depth
    fx, fy = px.to(t.dtype) + 0.5, py.to(t.dtype) + 0.5
    ax, ay = t[:, 0, 0:1], t[:, 0, 1:2]
    bx, by = t[:, 1, 0:1], t[:, 1, 1:2]
    cx, cy = t[:, 2, 0:1], t[:, 2, 1:2]
    area = _edge(ax, ay, bx, by, cx, cy)
    w0 = _edge(bx, by, cx, cy, fx, fy) / area
    w1 = _edge(cx, cy, ax, ay, fx, fy) / area
    w2 = 1.0 - w0 - w1
    inside = (w0 >= 0) & (w1 >= 0) & (w2 >= 0) & (px < width) & (py < height) & (px >= 0) & (py >= 0)
    inv_z = w0 / t[:, 0, 2:3] + w1 / t[:, 1, 2:3] + w2 / t[:, 2, 2:3]
    depth = (1.0 / inv_z).to(torch.float32)
    # Positive float32 bit patterns sort like the floats: depth in the high 32 bits, id below.
    key = (depth.view(torch.int32).to(torch.int64) << 32) | ids[:, None]
    pix = py * width + px
    return pix[inside], key[inside]


def rasterise(screen: torch.Tensor, faces: torch.Tensor, height: int, width: int,
              cull_back: torch.Tensor | None = None) -> Raster:
    """Rasterise triangles.

    ``screen``: (V, 3) vertices as (x pixels right, y pixels down, view depth > 0).
    ``faces``: (F, 3) int64 vertex ids. ``cull_back``: optional (F,) bool, True for triangles
    that are dropped when they face away from the camera (closed meshes); others are two-sided.
    Vertices at depth <= 0 (behind the camera) drop their triangles.
    """
    dev = screen.device
    tri = screen[faces].to(torch.float64)  # (F, 3, 3); float64 keeps thin slivers exact
    xs, ys, zs = tri[..., 0], tri[..., 1], tri[..., 2]
    keep = (zs > 1e-6).all(dim=1) & torch.isfinite(tri).all(dim=(1, 2))
    area = _edge(xs[:, 0], ys[:, 0], xs[:, 1], ys[:, 1], xs[:, 2], ys[:, 2])
    keep &= area.abs() > 1e-12
    if cull_back is not None:
        # y points down, so a counter-clockwise (front-facing) triangle has negative area here.
        keep &= ~(cull_back & (area > 0))
    x0 = torch.ceil(xs.min(dim=1).values - 0.5).clamp(min=0)
    x1 = torch.floor(xs.max(dim=1).values - 0.5).clamp(max=width - 1)
    y0 = torch.ceil(ys.min(dim=1).values - 0.5).clamp(min=0)
    y1 = torch.floor(ys.max(dim=1).values - 0.5).clamp(max=height - 1)
    keep &= (x1 >= x0) & (y1 >= y0)
    ids = torch.nonzero(keep).squeeze(1)
    x0, y0 = x0[ids].long(), y0[ids].long()
    side = torch.maximum(x1[ids].long() - x0, y1[ids].long() - y0) + 1
    zbuf = torch.full((height * width,), _EMPTY, dtype=torch.int64, device=dev)
    lo = 0
    for b in _BINS:
        sel = (side > lo) & (side <= b)
        lo = b
        if sel.any():
            pix, key = _candidates(tri, ids[sel], x0[sel], y0[sel], b, height, width)
            zbuf.scatter_reduce_(0, pix, key, reduce="amin")
    big = side > _BINS[-1]
    for i in torch.nonzero(big).squeeze(1).tolist():  # rare: split huge triangles into tiles
        s = int(side[i])
        step = _BINS[-1]
        for ty in range(0, s, step):
            for tx in range(0, s, step):
                pix, key = _candidates(tri, ids[i:i + 1], x0[i:i + 1] + tx, y0[i:i + 1] + ty,
                                       step, height, width)
                zbuf.scatter_reduce_(0, pix, key, reduce="amin")
    return _resolve(zbuf, tri, height, width)


def _resolve(zbuf, tri, height, width) -> Raster:
    hit = zbuf != _EMPTY
    face = torch.where(hit, zbuf & 0xFFFFFFFF, torch.full_like(zbuf, -1))
    bary = torch.zeros(height * width, 3, dtype=torch.float32, device=zbuf.device)
    depth = torch.full((height * width,), float("inf"), dtype=torch.float32, device=zbuf.device)
    idx = torch.nonzero(hit).squeeze(1)
    if idx.numel():
        t = tri[face[idx]]
        fx = (idx % width).to(t.dtype) + 0.5
        fy = (idx // width).to(t.dtype) + 0.5
        ax, ay, bx, by, cx, cy = (t[:, 0, 0], t[:, 0, 1], t[:, 1, 0], t[:, 1, 1],
                                  t[:, 2, 0], t[:, 2, 1])
        area = _edge(ax, ay, bx, by, cx, cy)
        w = torch.stack([_edge(bx, by, cx, cy, fx, fy), _edge(cx, cy, ax, ay, fx, fy)], 1) / area[:, None]
        w = torch.cat([w, 1.0 - w.sum(1, keepdim=True)], 1).clamp(min=0.0)
        # Screen-space weights -> perspective-correct weights (divide by depth, renormalise).
        p = w / t[:, :, 2]
        z = 1.0 / p.sum(1)
        bary[idx] = (p * z[:, None]).to(torch.float32)
        depth[idx] = z.to(torch.float32)
    return Raster(face.view(height, width), bary.view(height, width, 3), depth.view(height, width))


def interpolate(attr: torch.Tensor, faces: torch.Tensor, r: Raster) -> torch.Tensor:
    """Per-pixel (H, W, C) attribute from per-vertex ``attr`` (V, C); zero where empty."""
    f = r.face.clamp(min=0)
    a = attr[faces[f]]  # (H, W, 3, C)
    out = (a * r.bary[..., None]).sum(dim=2)
    return out * r.mask[..., None]
