"""One subject in front of one camera: pose a frame, build its G-buffer and OLAT transfer, shade.

Usage::

    scene = Scene(sample_identity(7), Performance(seed, names), camera)
    f0, f1 = scene.frame(t), scene.frame(t + 1 / FPS)
    imgs = scene.shade(f0, [light_a, light_b])           # (2, 3, H, W) linear radiance
    flow_fw, valid_fw = scene.flow(f0, f1)

Radiometry: a texel of radiance L in the light vector is L W/(m2 sr); a white Lambertian surface
under a uniform environment of radiance 1 has radiance 1, so images are in the light's own units.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
import torch

from . import assets, geometry, layout, materials, shading
from .subject import FPS, Camera, Identity, Performance

BACKDROP_ALBEDO = (0.05, 0.6)  # range of the backdrop's albedo (a matte wall behind the subject)


@functools.lru_cache(maxsize=1)
def stage_dirs() -> torch.Tensor:
    return torch.tensor(layout.directions(), dtype=torch.float32)


@dataclass
class Frame:
    t: float
    posed: geometry.PosedFrame
    gb: geometry.GBuffer
    idx: torch.Tensor            # (N,) flat indices of foreground pixels
    albedo: torch.Tensor         # (N, 3)
    sss: torch.Tensor            # (H, W) subsurface weight
    transfer: shading.Transfer | None
    px_per_cm: float
    f0: torch.Tensor | None = None      # (N,) specular reflectance
    rough: torch.Tensor | None = None   # (N,) GGX roughness
    cover: torch.Tensor | None = None   # (H, W) sub-pixel coverage where the centre hits
    strands: torch.Tensor | None = None  # (N,) how much of the pixel is hair (materials.surface)


class Scene:
    def __init__(self, ident: Identity, perf: Performance, cam: Camera, data_root=None,
                 backdrop_seed: int = 0):
        self.ident, self.perf, self.cam = ident, perf, cam
        self.model = assets.load_head(data_root)
        self.rig = assets.build_rig(ident.hair, round(ident.neckline, 3), data_root)
        self.attrs = materials.vertex_attributes(self.rig, data_root)
        self.base = geometry.identity_vertices(self.model, ident)
        self.backdrop = self._backdrop(backdrop_seed)
        self.dirs = stage_dirs()

    def _backdrop(self, seed: int) -> torch.Tensor:
        """(3, H, W) albedo of a matte wall: a smooth random colour field (fixed in the image,
        since camera and wall are static)."""
        g = torch.Generator().manual_seed(int(seed) & 0x7FFFFFFF)
        lo, hi = BACKDROP_ALBEDO
        grey = lo + (hi - lo) * torch.rand(1, 4, 4, generator=g) ** 1.5
        colour = 0.75 + 0.25 * torch.rand(3, 4, 4, generator=g)  # mostly muted walls
        tint = torch.rand(3, 1, 1, generator=g) * 0.5 + 0.5
        up = torch.nn.functional.interpolate((grey * colour * tint)[None],
                                             size=(self.cam.height, self.cam.width),
                                             mode="bicubic", align_corners=False)[0]
        return up.clamp(0.01, 0.95)

    def pose(self, t: float) -> geometry.PosedFrame:
        ang, trans, body = self.perf.head_pose(t)
        return geometry.pose(self.model, self.rig, self.base, self.perf.expression(t), ang, trans,
                             body, self.cam.distance, self.ident.hair.volume)

    def frame(self, t: float, with_transfer: bool = True) -> Frame:
        posed = self.pose(t)
        gb = geometry.gbuffer(posed, self.rig, self.cam, self.attrs)
        self._neckline(gb)
        idx = torch.nonzero(gb.mask.reshape(-1)).squeeze(1)
        mat = gb.material.reshape(-1)[idx]
        uv = gb.uv.reshape(-1, 2)[idx]
        at = gb.attrs.reshape(-1, gb.attrs.shape[-1])[idx]
        albedo, f0, rough, sss, strands = materials.surface(mat, uv, at, self.ident)
        sss_img = torch.zeros(self.cam.height * self.cam.width)
        sss_img[idx] = sss
        depth = float(gb.raster.depth.reshape(-1)[idx].median()) if idx.numel() else self.cam.distance
        # Coverage only where the pixel centre hits: those pixels carry the subject's shading.
        cover = geometry.coverage(posed, self.rig, self.cam) * gb.mask
        f = Frame(t, posed, gb, idx, albedo, sss_img.view(self.cam.height, self.cam.width), None,
                  self.cam.focal / max(depth, 1e-3), f0, rough, cover, strands)
        if with_transfer:
            f.transfer = self.transfer(f, f0, rough)
        return f

    @staticmethod
    def _neckline(gb: geometry.GBuffer) -> None:
        """Skin or clothes per pixel from the interpolated height below the neckline, not per
        triangle (which gave a zigzag collar)."""
        s = gb.attrs[..., materials.ATTRS.index("neckline")]
        body = gb.mask & ((gb.material == assets.SKIN) | (gb.material == assets.CLOTHES))
        cloth = body & (s > 0)
        bare = body & (s <= 0)
        gb.material = torch.where(cloth, assets.CLOTHES, torch.where(bare, assets.SKIN, gb.material))
        was_cloth = gb.label == assets.LABEL["clothes"]
        gb.label = torch.where(cloth, assets.LABEL["clothes"],
                               torch.where(bare & was_cloth, assets.LABEL["neck"], gb.label))

    def transfer(self, f: Frame, f0, rough, lights: torch.Tensor | None = None,
                 layered: bool = True) -> shading.Transfer:
        """Transfer for all 114 lights (or the subset ``lights``, indices); ``layered``: see
        shading.transfer."""
        dirs = self.dirs if lights is None else self.dirs[lights]
        v = f.posed.verts
        head = v[: self.rig.n_head]
        centre = head.mean(0)
        radius = float((v - centre).norm(dim=1).quantile(0.98)) if v.numel() else 1.0
        radius = min(max(radius, 20.0), 45.0)  # head and shoulders; the lower torso is cut off
        pos = f.gb.position.reshape(-1, 3)[f.idx]
        nrm = f.gb.normal.reshape(-1, 3)[f.idx]
        tan = f.gb.tangent.reshape(-1, 3)[f.idx]
        mat = f.gb.material.reshape(-1)[f.idx]
        maps = shading.shadow_maps(v, f.posed.normals, dirs, centre, radius)
        offset = shading.NORMAL_OFFSET * 2 * radius / shading.SHADOW_RES
        vis = shading.visibility(pos + offset * nrm, maps, dirs, centre, radius)
        return shading.transfer(pos, nrm, tan, mat, f0, rough, dirs, vis, f.strands, layered)

    def shade_inputs(self, f: Frame, tr: shading.Transfer | None = None) -> shading.ShadeInputs:
        """Everything shading needs from a frame (what the frame cache stores)."""
        tr = f.transfer if tr is None else tr
        return shading.ShadeInputs(f.idx, tr.diffuse, tr.specular, f.albedo, f.sss, f.px_per_cm,
                                   f.gb.mask, self.backdrop, f.cover)

    def shade_weights(self, f: Frame, w: torch.Tensor, tr: shading.Transfer | None = None,
                      lights: torch.Tensor | None = None, low: torch.Tensor | None = None):
        """Images (C, 3, H, W) under stage weights ``w`` (C, 114, 3).

        ``tr``/``lights``: a transfer computed for a subset of the lights only (indices); ``low``
        (C, 114, 3): weights of the other lights, shaded through the cheap low-frequency path
        (unshadowed diffuse irradiance from an order-2 spherical-harmonic fit, no specular, no
        subsurface)."""
        extra = None
        if low is not None:
            nrm = f.gb.normal.reshape(-1, 3)[f.idx]
            extra = shading.sh_irradiance(nrm, self.dirs, low.float()).T
        return shading.relight(self.shade_inputs(f, tr), w, self.dirs, lights, extra)

    def shade(self, f: Frame, lights) -> torch.Tensor:
        """Images (C, 3, H, W) under light vectors (C, 16, 16, 3)."""
        w = np.stack([layout.weights(lv) for lv in lights])
        return self.shade_weights(f, torch.from_numpy(w).float())

    def shade_selective(self, f: Frame, lights, energy: float = 0.95):
        """Images under light vectors, simulating shadows, specular and subsurface only for the
        strongest lights that together carry ``energy`` of the power; the rest go through the
        low-frequency path. Returns (images (C, 3, H, W), number of fully simulated lights)."""
        w = torch.from_numpy(np.stack([layout.weights(lv) for lv in lights])).float()
        e = w.sum(dim=2).max(dim=0).values  # per light: its largest power over the C lights
        order = torch.argsort(e, descending=True)
        total = float(e.sum())
        if total <= 0:
            return self.shade_weights(f, w, shading.Transfer(torch.zeros(len(f.idx), 0),
                                                             torch.zeros(len(f.idx), 0)),
                                      torch.zeros(0, dtype=torch.long)), 0
        n = int(torch.searchsorted(torch.cumsum(e[order], 0), energy * total).item()) + 1
        sel = torch.sort(order[:min(n, len(order))]).values
        rest = torch.ones(len(e), dtype=torch.bool)
        rest[sel] = False
        tr = self.transfer(f, f.f0, f.rough, lights=sel)
        low = w * rest[None, :, None]
        return self.shade_weights(f, w, tr, sel, low), int(len(sel))

    def flow(self, a: Frame, b: Frame):
        return geometry.flow(a.gb, self.rig, b.posed.verts, b.gb, self.cam)

    def parsing(self, f: Frame, k: int) -> torch.Tensor:
        """(K, H, W) {0, 1}: channel 0 the foreground, then one channel per semantic class."""
        lab = f.gb.label
        out = torch.stack([(lab == i) for i in range(k)], 0).float()
        out[0] = f.gb.mask.float()
        return out


def next_time(t: float) -> float:
    return t + 1.0 / FPS
