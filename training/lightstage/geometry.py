"""Posing the scene (identity + expression + head/body motion) and its G-buffer with exact flow."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from . import assets
from .raster import Raster, interpolate, rasterise
from .subject import Camera, Identity

NECK_PIVOT = (0.0, -5.0, -1.0)  # cm, neutral frame: the head turns about the top of the neck


def _euler(yaw, pitch, roll):
    """Rotation matrices for per-vertex angle tensors (radians): R = Ry(yaw) Rx(pitch) Rz(roll)."""
    cy, sy = torch.cos(yaw), torch.sin(yaw)
    cp, sp = torch.cos(pitch), torch.sin(pitch)
    cr, sr = torch.cos(roll), torch.sin(roll)
    r = torch.stack([
        cy * cr + sy * sp * sr, -cy * sr + sy * sp * cr, sy * cp,
        cp * sr, cp * cr, -sp,
        -sy * cr + cy * sp * sr, sy * sr + cy * sp * cr, cy * cp], -1)
    return r.reshape(*yaw.shape, 3, 3)


@dataclass
class PosedFrame:
    verts: torch.Tensor     # (V, 3) camera frame, cm
    normals: torch.Tensor   # (V, 3)
    head_x: torch.Tensor    # (3,) the head's left-right axis in the camera frame (hair tangents)


def identity_vertices(model: assets.HeadModel, ident: Identity) -> np.ndarray:
    return model.neutral + np.tensordot(ident.shape, model.identity_modes, axes=1)


def pose(model: assets.HeadModel, rig: assets.Rig, base: np.ndarray, expression: np.ndarray,
         head_angles_deg, translation, body_yaw_deg: float, distance: float,
         hair_volume: float) -> PosedFrame:
    """Vertices of the whole scene (head, hair shell, torso) in the camera frame."""
    local = torch.from_numpy(base + np.tensordot(expression, model.expression_modes, axes=1))
    pivot = torch.tensor(NECK_PIVOT, dtype=local.dtype)
    w = rig.head_weight
    ang = torch.tensor(np.radians(np.asarray(head_angles_deg, np.float64)), dtype=local.dtype)
    rv = _euler(w * ang[0], w * ang[1], w * ang[2])  # (V, 3, 3) neck skinning
    head = torch.einsum("vij,vj->vi", rv, local - pivot) + pivot
    torso = assets.torso_vertices(head[rig.loop])
    parts = [head]
    n_head = assets.vertex_normals(head, rig.faces[: len(model.triangles)])
    if rig.scalp.numel():
        parts.append(head[rig.scalp] + n_head[rig.scalp] * (hair_volume * rig.scalp_weight
                                                             + 0.08)[:, None])
    if rig.curtain is not None:  # long hair turns with the head at its top, less lower down
        c = assets.curtain_vertices(local, rig.curtain, hair_volume)
        wc = assets.neck_weight(c[:, 1]).to(local.dtype)
        rc = _euler(wc * ang[0], wc * ang[1], wc * ang[2])
        parts.append(torch.einsum("vij,vj->vi", rc, c - pivot) + pivot)
    parts.append(torso)
    verts = torch.cat(parts, 0)
    body = _euler(*[torch.tensor(a, dtype=local.dtype) for a in (math.radians(body_yaw_deg), 0.0, 0.0)])
    t = torch.tensor([translation[0], translation[1], translation[2] - distance], dtype=local.dtype)
    verts = (verts - pivot) @ body.T + pivot + t
    head_rot = body @ _euler(*[torch.tensor(math.radians(a), dtype=local.dtype)
                               for a in head_angles_deg])
    return PosedFrame(verts.float(), assets.vertex_normals(verts, rig.faces).float(),
                      head_rot[:, 0].float())


@dataclass
class GBuffer:
    raster: Raster
    position: torch.Tensor   # (H, W, 3) camera frame cm
    normal: torch.Tensor     # (H, W, 3) unit, facing the camera
    uv: torch.Tensor         # (H, W, 2)
    material: torch.Tensor   # (H, W) int64, -1 background
    label: torch.Tensor      # (H, W) int64 parsing channel, 0 background
    attrs: torch.Tensor      # (H, W, A) per-vertex material attributes
    tangent: torch.Tensor    # (H, W, 3) hair strand direction

    @property
    def mask(self) -> torch.Tensor:
        return self.raster.mask


def gbuffer(frame: PosedFrame, rig: assets.Rig, cam: Camera, vertex_attrs: torch.Tensor) -> GBuffer:
    scr = cam.project(frame.verts.double())
    r = rasterise(scr, rig.faces, cam.height, cam.width)
    pos = interpolate(frame.verts, rig.faces, r)
    nrm = interpolate(frame.normals, rig.faces, r)
    nrm = nrm / nrm.norm(dim=-1, keepdim=True).clamp(min=1e-8)
    view = -pos / pos.norm(dim=-1, keepdim=True).clamp(min=1e-8)
    # Two-sided geometry (lash cards, the inside of the mouth): shade the side the camera sees.
    flip = (nrm * view).sum(-1, keepdim=True) < 0
    nrm = torch.where(flip, -nrm, nrm)
    m = r.mask
    f = r.face.clamp(min=0)
    mat = torch.where(m, rig.material[f], torch.full_like(f, -1))
    lab = torch.where(m, rig.label[f], torch.zeros_like(f))
    uv = interpolate(rig.uv, rig.faces, r)
    attrs = interpolate(vertex_attrs, rig.faces, r)
    tan = torch.cross(frame.head_x.expand_as(nrm), nrm, dim=-1)
    tan = tan / tan.norm(dim=-1, keepdim=True).clamp(min=1e-8)
    return GBuffer(r, pos, nrm, uv, mat, lab, attrs, tan)


COVER_SS = 2  # silhouette coverage from 2 x 2 samples per pixel


def coverage(frame: PosedFrame, rig: assets.Rig, cam: Camera, ss: int = COVER_SS) -> torch.Tensor:
    """(H, W) fraction of each pixel's ss x ss sub-samples that hit the subject: soft silhouette
    edges (the shading itself stays one sample per pixel)."""
    scr = cam.project(frame.verts.double())
    scr = torch.stack([scr[:, 0] * ss, scr[:, 1] * ss, scr[:, 2]], 1)
    r = rasterise(scr, rig.faces, cam.height * ss, cam.width * ss)
    hit = r.mask.float().view(cam.height, ss, cam.width, ss)
    return hit.mean(dim=(1, 3))


def flow(src: GBuffer, rig: assets.Rig, verts_dst: torch.Tensor, dst: GBuffer, cam: Camera,
         tol: float = 0.01):
    """Exact flow from ``src``'s pixels to the frame whose vertices are ``verts_dst``.

    Foreground pixels follow their surface point; background pixels (a static backdrop seen by a
    static camera) stay put. ``valid`` is 1 where the point is visible in both frames: it lands
    inside the image and the destination's depth there matches (relative tolerance ``tol``), or,
    for the backdrop, the destination pixel is backdrop too.
    """
    h, w = cam.height, cam.width
    m = src.mask
    p1 = interpolate(verts_dst, rig.faces, src.raster)
    q = cam.project(p1.reshape(-1, 3)).reshape(h, w, 3)
    ys, xs = torch.meshgrid(torch.arange(h, dtype=torch.float32), torch.arange(w, dtype=torch.float32),
                            indexing="ij")
    fx = torch.where(m, q[..., 0] - (xs + 0.5), torch.zeros_like(xs))
    fy = torch.where(m, q[..., 1] - (ys + 0.5), torch.zeros_like(ys))
    fx = torch.nan_to_num(fx, 0.0, 0.0, 0.0)
    fy = torch.nan_to_num(fy, 0.0, 0.0, 0.0)
    tx, ty = xs + 0.5 + fx, ys + 0.5 + fy
    inside = (tx >= 0) & (tx < w) & (ty >= 0) & (ty < h)
    ix = tx.clamp(0, w - 1).long()
    iy = ty.clamp(0, h - 1).long()
    d_dst = dst.raster.depth[iy, ix]
    same = (d_dst - q[..., 2]).abs() <= tol * q[..., 2].abs()
    valid = torch.where(m, inside & same, ~dst.mask[iy, ix])
    return torch.stack([fx, fy], 0), valid[None].float()
