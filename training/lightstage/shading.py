"""OLAT shading: shadows, Lambert + GGX specular, a Kajiya-Kay hair highlight, subsurface diffusion.

Every step is linear in the stage weights w (114, C): per pixel and light we build transfer
coefficients (visibility x cosine for diffuse, visibility x BRDF x cosine for specular), multiply by
w, then diffuse the skin's irradiance in screen space (a linear filter) and add the backdrop. So the
image under any light vector equals the weighted sum of the 114 OLAT images (tested).

Shadows: one small orthographic depth map per light, built by splatting only the vertices that face
away from the light (second-depth shadow mapping: the surface's far side is the occluder, which
removes self-shadowing acne without a large bias), dilated by one texel to close gaps between
vertices, and looked up with four-tap percentage-closer filtering.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as tf

from .assets import HAIR

SHADOW_RES = 256  # texels across the subject (about 0.3 cm): finer maps, sharper contact shadows
SHADOW_DILATE = 3  # max-filter width closing gaps between splatted vertices (1: none)
SHADOW_CLOSE = 5   # holes up to this wide inside an occluder are filled without growing it
# Shadow lookups start this many shadow-map texels out along the surface normal (normal-offset
# shadow mapping): at grazing light a point's own surface no longer shadows it. Against Cycles
# (bench/lightstage_cycles.py, grey Lambert, 128 px) the relative RMSE over skin and clothes went
# 0.112 -> 0.081 (key), 0.179 -> 0.143 (side), 0.383 -> 0.189 (top; ours/Cycles 0.92 -> 1.00);
# 3 texels began to leak light (top 1.03), 4 more (1.06).
NORMAL_OFFSET = 2.0
SSS_ALPHA = (0.75, 0.55, 0.40)     # share of irradiance that diffuses, per channel (R, G, B)
SSS_SIGMA_CM = (0.30, 0.14, 0.07)  # diffusion width at the skin, per channel: red travels furthest
HAIR_WRAP = (0.7, 0.3)  # hair's diffuse lobe max(0, 0.7 n.l + 0.3): light wraps around its volume


def _basis(dirs: torch.Tensor):
    """Two unit vectors per light direction (M, 3) spanning the plane normal to it."""
    up = torch.tensor([0.0, 1.0, 0.0]).expand_as(dirs)
    alt = torch.tensor([1.0, 0.0, 0.0]).expand_as(dirs)
    ref = torch.where((dirs[:, 1:2].abs() > 0.9), alt, up)
    u = torch.cross(ref, dirs, dim=1)
    u = u / u.norm(dim=1, keepdim=True)
    return u, torch.cross(dirs, u, dim=1)


def shadow_maps(verts: torch.Tensor, normals: torch.Tensor, dirs: torch.Tensor, centre, radius,
                res: int = SHADOW_RES):
    """(M, res, res) depth toward each light of its nearest back-facing occluder (-inf: none)."""
    u, v = _basis(dirs)
    m = dirs.shape[0]
    basis = torch.cat([u, v, dirs], 0).T  # (3, 3M)
    c = (verts - centre) @ basis  # (V, 3M)
    a, b, d = c[:, :m], c[:, m:2 * m], c[:, 2 * m:]
    back = (normals @ dirs.T) < 0.0
    ia = ((a / (2 * radius) + 0.5) * res).floor().long()
    ib = ((b / (2 * radius) + 0.5) * res).floor().long()
    ok = back & (ia >= 0) & (ia < res) & (ib >= 0) & (ib < res)
    light = torch.arange(m).expand_as(ia)
    idx = (light * res + ib) * res + ia
    maps = torch.full((m * res * res,), -float("inf"))
    maps.scatter_reduce_(0, idx[ok], d[ok], reduce="amax")
    maps = maps.view(m, 1, res, res)
    if SHADOW_DILATE > 1:
        maps = _max_filter(maps, SHADOW_DILATE)
    if SHADOW_CLOSE > 1:
        # Morphological closing of the covered texels: holes where the mesh's vertices are
        # sparser than the texels (jaw underside, neck) get the nearby occluders' depth, while
        # the occluder's outline (its shadow's edge) stays where it was.
        cov = torch.isfinite(maps)
        grown = _max_filter(cov.to(torch.uint8), SHADOW_CLOSE, 0)
        closed = 1 - _max_filter(1 - grown, SHADOW_CLOSE, 0)  # erosion of the grown cover
        maps = torch.where(~cov & (closed > 0), _max_filter(maps, SHADOW_CLOSE), maps)
    return maps.view(m, res, res)


def _max_filter(x: torch.Tensor, k: int, outside=-float("inf")) -> torch.Tensor:
    """k x k max filter (k odd) of (M, 1, H, W), same size, ``outside`` beyond the border.
    Separable, each axis by doubling windows of shifted maxima (torch's CPU max_pool2d is ~10x
    slower here)."""
    r = k // 2
    for dim in (3, 2):
        pad = [0, 0, 0, 0]
        pad[2 * (3 - dim)] = pad[2 * (3 - dim) + 1] = r
        y = tf.pad(x, pad, value=outside)
        n = x.shape[dim]
        width = 1
        while width < k:  # y[i] becomes the max over [i, i + width)
            step = min(width, k - width)
            y = torch.maximum(y.narrow(dim, 0, y.shape[dim] - step), y.narrow(dim, step, y.shape[dim] - step))
            width += step
        x = y.narrow(dim, 0, n)
    return x


def visibility(points: torch.Tensor, maps: torch.Tensor, dirs: torch.Tensor, centre, radius):
    """(N, M) visibility in [0, 1] of points (N, 3) for each light (bilinear PCF)."""
    m, res, _ = maps.shape
    u, v = _basis(dirs)
    basis = torch.cat([u, v, dirs], 0).T
    c = (points - centre) @ basis
    a = (c[:, :m] / (2 * radius) + 0.5) * res - 0.5
    b = (c[:, m:2 * m] / (2 * radius) + 0.5) * res - 0.5
    d = c[:, 2 * m:] + 1.5 * (2 * radius / res)  # bias: one and a half texels
    a0, b0 = a.floor(), b.floor()
    fa, fb = a - a0, b - b0
    a0, b0 = a0.long(), b0.long()
    flat = maps.reshape(-1)
    light = torch.arange(m).expand_as(a0) * res * res
    vis = torch.zeros_like(a)
    for da, db, w in ((0, 0, (1 - fa) * (1 - fb)), (1, 0, fa * (1 - fb)), (0, 1, (1 - fa) * fb),
                      (1, 1, fa * fb)):
        ia, ib = a0 + da, b0 + db
        inside = (ia >= 0) & (ia < res) & (ib >= 0) & (ib < res)
        occ = flat[light + ib.clamp(0, res - 1) * res + ia.clamp(0, res - 1)]
        vis += w * (~inside | (d >= occ)).float()
    return vis


@dataclass
class Transfer:
    """Per-pixel, per-light transfer for the N foreground pixels of one frame."""
    diffuse: torch.Tensor   # (N, M) visibility x cos
    specular: torch.Tensor  # (N, M) visibility x BRDF x cos (radiance per unit irradiance)


def transfer(pos, nrm, tangent, material, f0, rough, dirs, vis, strands=None,
             layered: bool = True) -> Transfer:
    """``strands`` (N,): how much of each pixel is hair (materials.surface; default: the hair
    material's pixels wholly): hair's wrap-lit diffuse and Kajiya-Kay lobe there, blended with
    Lambert and GGX for the skin that shows through where the shell thins. ``layered=False``:
    the diffuse keeps the energy the specular layer reflects (plain Lambert, for referees)."""
    view = -pos / pos.norm(dim=1, keepdim=True).clamp(min=1e-8)
    nl = nrm @ dirs.T                                    # (N, M)
    nv = (nrm * view).sum(1, keepdim=True).clamp(min=1e-3)
    cos = nl.clamp(min=0.0)
    h = tf.normalize(view[:, None, :] + dirs[None, :, :], dim=2)
    nh = (nrm[:, None, :] * h).sum(2).clamp(min=0.0)
    lh = (dirs[None, :, :] * h).sum(2).clamp(min=0.0)
    a2 = (rough * rough).clamp(min=1e-4)[:, None] ** 2
    d = a2 / (math.pi * ((nh * nh) * (a2 - 1.0) + 1.0) ** 2)
    vis_smith = 0.5 / (cos * torch.sqrt(nv * nv * (1 - a2) + a2)
                       + nv * torch.sqrt(cos * cos * (1 - a2) + a2)).clamp(min=1e-6)
    fres = f0[:, None] + (1.0 - f0[:, None]) * (1.0 - lh) ** 5
    spec = d * vis_smith * fres * cos
    k = (material == HAIR).float() if strands is None else strands.float()
    # Energy: the light the specular layer reflects does not reach the diffuse below it. The
    # diffuse is weighted by one minus the lobe's directional albedo toward the viewer, as the
    # Principled BSDF takes the lobe's energy from its diffuse (bench/lightstage_cycles.py: without
    # it ours was 2-3% brighter than Cycles with diffuse + GGX).
    diffuse = cos * (1.0 - ggx_albedo(f0, rough, nv[:, 0]))[:, None] if layered else cos.clone()
    hair = k > 0
    if hair.any():
        # Kajiya-Kay: the highlight lies where the strand tangent makes equal angles with the light
        # and the view; shifted toward the root by tilting the tangent (the cuticle scales).
        t = tf.normalize(tangent[hair] + 0.15 * nrm[hair], dim=1)
        tl = t @ dirs.T
        tv = (t * view[hair]).sum(1, keepdim=True)
        cone = (tl * tv + torch.sqrt((1 - tl * tl).clamp(min=0)) * torch.sqrt((1 - tv * tv).clamp(min=0)))
        kh = k[hair][:, None]
        spec[hair] = kh * 0.06 * cone.clamp(min=0.0) ** 60 * cos[hair] + (1 - kh) * spec[hair]
        wrap = (nl[hair] * HAIR_WRAP[0] + HAIR_WRAP[1]).clamp(min=0.0)
        diffuse[hair] = kh * wrap + (1 - kh) * diffuse[hair]
    return Transfer(vis * diffuse, vis * spec)


def ggx_albedo(f0: torch.Tensor, rough: torch.Tensor, nv: torch.Tensor) -> torch.Tensor:
    """Directional albedo of the GGX lobe with Schlick's Fresnel at view cosine ``nv``: Karis'
    analytic fit of the split-sum environment BRDF (Unreal Engine 4 mobile, after Lazarov 2013)."""
    r0 = -1.0 * rough + 1.0
    r1 = -0.0275 * rough + 0.0425
    r2 = -0.572 * rough + 1.04
    r3 = 0.022 * rough - 0.04
    a004 = torch.minimum(r0 * r0, torch.exp2(-9.28 * nv)) * r0 + r1
    return (f0 * (-1.04 * a004 + r2) + (1.04 * a004 + r3)).clamp(0.0, 1.0)


@dataclass
class ShadeInputs:
    """What shading one frame needs (a Frame's, or the same read back from the frame cache)."""
    idx: torch.Tensor        # (N,) flat indices of the foreground pixels
    diffuse: torch.Tensor    # (N, M) transfer (any float dtype; promoted to float32)
    specular: torch.Tensor   # (N, M)
    albedo: torch.Tensor     # (N, 3)
    sss: torch.Tensor        # (H, W) subsurface weight
    px_per_cm: float
    mask: torch.Tensor       # (H, W) bool foreground (the pixel centre hits the subject)
    backdrop: torch.Tensor   # (3, H, W) albedo of the wall behind the subject
    cover: torch.Tensor | None = None  # (H, W) sub-pixel coverage of the subject (None: mask)


def terms(s: ShadeInputs, w: torch.Tensor, lights=None) -> tuple[torch.Tensor, torch.Tensor]:
    """(diffuse irradiance after subsurface diffusion, specular radiance), each (C*3, H*W) and
    zero off the foreground, under stage weights ``w`` (C, M_all, 3): relight's two terms of
    the subject (``lights`` as there)."""
    c = w.shape[0]
    h, wd = s.mask.shape
    wsel = w if lights is None else w[:, lights]
    wm = wsel.permute(1, 0, 2).reshape(wsel.shape[1], c * 3).float()
    irr = torch.zeros(c * 3, h * wd)
    spec = torch.zeros(c * 3, h * wd)
    irr[:, s.idx] = (s.diffuse.float() @ wm).T
    spec[:, s.idx] = (s.specular.float() @ wm).T
    return subsurface(irr.view(c * 3, h, wd), s.sss, s.px_per_cm).view(c * 3, -1), spec


def relight(s: ShadeInputs, w: torch.Tensor, dirs: torch.Tensor, lights=None,
            extra_irradiance=None) -> torch.Tensor:
    """Images (C, 3, H, W) under stage weights ``w`` (C, M_all, 3): linear in ``w``.

    ``lights``: indices of the lights the transfer holds (all when None); ``extra_irradiance``
    (N, C*3): irradiance added after subsurface diffusion (the low-frequency path)."""
    c = w.shape[0]
    h, wd = s.mask.shape
    irr, spec = terms(s, w, lights)
    if extra_irradiance is not None:
        irr[:, s.idx] += extra_irradiance
    alb = torch.zeros(3, h * wd)
    alb[:, s.idx] = s.albedo.T
    fg = alb.repeat(c, 1) / math.pi * irr + spec
    # Backdrop: a matte wall facing the camera, unshadowed (it is far behind the subject).
    cos_bg = dirs[:, 2].clamp(min=0.0)
    e_bg = (cos_bg[None] @ w.float()).reshape(c * 3, 1)  # (C*3, 1)
    bg = (s.backdrop.reshape(1, 3, -1).expand(c, 3, -1).reshape(c * 3, -1) / math.pi) * e_bg
    if s.cover is not None:  # silhouette pixels blend subject and wall by their coverage
        k = s.cover.reshape(1, -1)
        fg = fg * k + bg * (1.0 - k)
    return torch.where(s.mask.reshape(1, -1), fg, bg).view(c, 3, h, wd)


def gaussian_blur(img: torch.Tensor, sigma: float) -> torch.Tensor:
    """Separable Gaussian blur of (C, H, W) with zero padding."""
    if sigma < 0.3:
        return img
    r = int(min(3 * sigma + 1, 40))
    x = torch.arange(-r, r + 1, dtype=img.dtype)
    k = torch.exp(-0.5 * (x / sigma) ** 2)
    k = k / k.sum()
    out = tf.conv2d(img[:, None], k.view(1, 1, 1, -1), padding=(0, r))
    out = tf.conv2d(out, k.view(1, 1, -1, 1), padding=(r, 0))
    return out[:, 0]


def subsurface(irr: torch.Tensor, sss: torch.Tensor, px_per_cm: float) -> torch.Tensor:
    """Diffuse irradiance (C*3, H, W) under the skin (weights (H, W)) per colour channel."""
    out = irr.clone()
    w = sss[None]
    for ch in range(3):
        sig = SSS_SIGMA_CM[ch] * px_per_cm
        if sig < 0.3:
            continue
        sl = irr[ch::3]
        num = gaussian_blur(sl * w, sig)
        den = gaussian_blur(w, sig).clamp(min=1e-6)
        a = SSS_ALPHA[ch] * w
        out[ch::3] = sl * (1 - a) + a * num / den
    return out


def _sh9(d: torch.Tensor) -> torch.Tensor:
    """Real spherical harmonics up to order 2 at unit directions (N, 3) -> (N, 9)."""
    x, y, z = d[:, 0], d[:, 1], d[:, 2]
    return torch.stack([0.282095 * torch.ones_like(x), 0.488603 * y, 0.488603 * z, 0.488603 * x,
                        1.092548 * x * y, 1.092548 * y * z, 0.315392 * (3 * z * z - 1),
                        1.092548 * x * z, 0.546274 * (x * x - y * y)], 1)


def cell_sh(dtype=torch.float64) -> tuple[torch.Tensor, torch.Tensor]:
    """The order-2 SH basis at the light vector's cell centres (256, 9) and the cells' solid
    angles (256,): a light vector's SH coefficients are ``light.flatten @ (basis * omega)``
    (training/model/network.py's ratio head and the transport targets of pairs.py)."""
    from addon import lightvec

    d = torch.from_numpy(lightvec.directions().reshape(-1, 3)).to(dtype)
    omega = torch.from_numpy(lightvec.solid_angles().reshape(-1)).to(dtype)
    return _sh9(d), omega


def sh_irradiance(normals: torch.Tensor, dirs: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """(N, C*3) unshadowed irradiance from distant lights ``dirs`` (M, 3) with weights (C, M, 3),
    through the order-2 SH fit of the clamped cosine (Ramamoorthi and Hanrahan 2001)."""
    c = w.shape[0]
    coeff = _sh9(dirs).T @ w.permute(1, 0, 2).reshape(dirs.shape[0], c * 3)  # (9, C*3)
    band = torch.tensor([math.pi] + [2 * math.pi / 3] * 3 + [math.pi / 4] * 5)
    return _sh9(normals) @ (coeff * band[:, None])
