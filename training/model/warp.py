"""Flow warping for the temporal loss (paper sec. 4.2).

Flow conventions (training.data.dataset): ``flow_fw`` lives on frame t's pixels and holds the
displacement (dx, dy) in pixels to where that point is in frame t+1; ``flow_bw`` lives on frame
t+1's pixels and points back to frame t. Warping is backward sampling: to bring frame t+1 onto
frame t's pixel grid, each pixel p of frame t reads frame t+1 at p + flow_fw(p). Points that leave
the frame or are occluded are excluded by the dataset's validity masks, and by ``in_bounds`` here.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F


def _sample_grid(flow: torch.Tensor) -> torch.Tensor:
    """Normalised grid_sample coordinates (align_corners=True) of p + flow(p); flow [N,2,H,W]."""
    n, _, h, w = flow.shape
    ys, xs = torch.meshgrid(torch.arange(h, device=flow.device, dtype=flow.dtype),
                            torch.arange(w, device=flow.device, dtype=flow.dtype), indexing="ij")
    x = xs + flow[:, 0]
    y = ys + flow[:, 1]
    # align_corners=True maps pixel centres 0 and W-1 to -1 and +1
    gx = 2.0 * x / max(w - 1, 1) - 1.0
    gy = 2.0 * y / max(h - 1, 1) - 1.0
    return torch.stack([gx, gy], dim=-1)


def warp(image: torch.Tensor, flow: torch.Tensor) -> torch.Tensor:
    """Sample ``image`` [N,C,H,W] at p + flow(p) for every pixel p of the flow's grid (bilinear,
    zeros outside). ``warp(img_t1, flow_fw)`` is frame t+1 seen on frame t's pixels."""
    if image.shape[0] != flow.shape[0] or image.shape[-2:] != flow.shape[-2:]:
        raise ValueError(f"image {tuple(image.shape)} and flow {tuple(flow.shape)} differ in "
                         "batch or size")
    grid = _sample_grid(flow.to(image.dtype))
    return F.grid_sample(image, grid, mode="bilinear", padding_mode="zeros", align_corners=True)


def in_bounds(flow: torch.Tensor) -> torch.Tensor:
    """[N,1,H,W] 1 where p + flow(p) lands inside the image, else 0."""
    g = _sample_grid(flow)
    ok = (g[..., 0].abs() <= 1.0) & (g[..., 1].abs() <= 1.0)
    return ok[:, None].to(flow.dtype)


def to_next(image_t: torch.Tensor, flow_bw: torch.Tensor) -> torch.Tensor:
    """f_{t,t+1}: frame t's image moved onto frame t+1's pixels."""
    return warp(image_t, flow_bw)


def to_previous(image_t1: torch.Tensor, flow_fw: torch.Tensor) -> torch.Tensor:
    """f_{t+1,t}: frame t+1's image moved onto frame t's pixels."""
    return warp(image_t1, flow_fw)


def downsample_flow(flow: torch.Tensor, factor: int) -> torch.Tensor:
    """Flow for an image down-sampled by ``factor`` (area pooling): displacements shrink too."""
    if factor == 1:
        return flow
    return F.avg_pool2d(flow, factor) / factor
