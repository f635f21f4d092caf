"""Materials: a pigment-based skin albedo with spatial detail, and the other surfaces' parameters.

Skin albedo = base * exp(-(melanin * k_mel + haemoglobin * k_hb)) per channel: melanin absorbs
more toward blue (its absorption falls with wavelength), haemoglobin mostly absorbs green and blue,
so one melanin knob spans very light to very dark skin and haemoglobin gives lips and cheeks their
redness. Detail is attached to the surface through its texture coordinates (value noise on the UVs),
so it moves with the skin and the flow stays exact: pores (a few percent of albedo at high
frequency), freckles (melanin spots), stubble and brows (strand-like dark noise in hair colour).
"""

from __future__ import annotations

import numpy as np
import torch

from . import assets
from .assets import CLOTHES, HAIR, IRIS, LASHES, MOUTH, SCLERA, SKIN, TEETH
from .subject import Identity

SKIN_BASE = np.array([0.80, 0.64, 0.54])
# A flatter melanin spectrum than pure eumelanin: with it very dark skin stays a deep brown
# (linear albedo about (0.08, 0.03, 0.02) at melanin 4) instead of saturating to orange.
K_MELANIN = np.array([0.58, 0.70, 0.82])
K_HAEMOGLOBIN = np.array([0.03, 0.35, 0.25])
ATTRS = ("lips", "brows", "beard", "oily", "cheeks", "pupil", "hair_cover", "lash", "neckline")
_REGIONS = ("lips", "brows", "beard", "oily", "cheeks", "lash", "neckline")
NECKLINE_FAR = 5.0  # the neckline attribute on the torso (all clothes) and hair (none), in cm

# Specular reflectance at normal incidence and GGX roughness per material (hair uses its own lobe).
F0 = {SKIN: 0.028, SCLERA: 0.03, IRIS: 0.03, TEETH: 0.04, MOUTH: 0.03, LASHES: 0.03, HAIR: 0.0,
      CLOTHES: 0.04}
ROUGHNESS = {SKIN: 0.5, SCLERA: 0.08, IRIS: 0.08, TEETH: 0.25, MOUTH: 0.3, LASHES: 0.5, HAIR: 0.5,
             CLOTHES: 0.85}
SSS = {SKIN: 1.0, MOUTH: 1.0}


def skin_albedo(melanin, haemoglobin) -> np.ndarray:
    m = np.asarray(melanin, np.float64)[..., None]
    h = np.asarray(haemoglobin, np.float64)[..., None]
    return SKIN_BASE * np.exp(-(m * K_MELANIN + h * K_HAEMOGLOBIN))


def vertex_attributes(rig: assets.Rig, data_root=None) -> torch.Tensor:
    """(V_total, len(ATTRS)) float32: region weights on head vertices, zero elsewhere; on the
    hair shell, how far it is from the hairline (0 at the hairline, 1 on the crown)."""
    m = assets.load_head(data_root)
    out = torch.zeros(rig.n_vertices, len(ATTRS))
    for k in _REGIONS:
        out[: rig.n_head, ATTRS.index(k)] = rig.regions[k]
    shell = slice(rig.n_head, rig.n_head + rig.scalp.numel())
    out[shell, ATTRS.index("hair_cover")] = rig.scalp_weight
    out[shell, ATTRS.index("neckline")] = -NECKLINE_FAR
    out[shell.stop:, ATTRS.index("neckline")] = NECKLINE_FAR
    # Pupils: iris vertices near the front-most point of each iris.
    for side in ("left", "right"):
        a, b = m.regions[f"iris_{side}"]
        v = m.neutral[a:b + 1]
        centre = v[np.argmax(v[:, 2])]
        d = np.linalg.norm(v[:, :2] - centre[:2], axis=1)
        out[a:b + 1, ATTRS.index("pupil")] = torch.from_numpy(
            np.clip((0.32 - d) / 0.06, 0.0, 1.0).astype(np.float32))
    return out


def _noise(uv: torch.Tensor, seed: int, freq: float, size: int = 256) -> torch.Tensor:
    """Smooth value noise in [-1, 1] at (N, 2) texture coordinates, periodic over ``size``."""
    g = torch.Generator().manual_seed(int(seed) & 0x7FFFFFFF)
    lattice = torch.rand(size, size, generator=g) * 2.0 - 1.0
    p = uv * freq
    i0 = torch.floor(p)
    f = p - i0
    f = f * f * (3.0 - 2.0 * f)
    i0 = i0.long() % size
    i1 = (i0 + 1) % size
    a = lattice[i0[:, 1], i0[:, 0]]
    b = lattice[i0[:, 1], i1[:, 0]]
    c = lattice[i1[:, 1], i0[:, 0]]
    d = lattice[i1[:, 1], i1[:, 0]]
    return (a * (1 - f[:, 0]) + b * f[:, 0]) * (1 - f[:, 1]) + (c * (1 - f[:, 0]) + d * f[:, 0]) * f[:, 1]


def surface(material: torch.Tensor, uv: torch.Tensor, attrs: torch.Tensor, ident: Identity):
    """Per-pixel (albedo (N, 3), F0 (N,), roughness (N,), sss weight (N,)) for N pixels."""
    n = material.shape[0]
    s = ident.texture_seed
    a = {k: attrs[:, i] for i, k in enumerate(ATTRS)}
    pores = _noise(uv, s + 1, 180.0) * 0.5 + _noise(uv, s + 2, 90.0) * 0.5
    mottle = _noise(uv, s + 3, 12.0)
    freckle = ((_noise(uv, s + 4, 60.0) - 0.35).clamp(min=0) * 4.0).clamp(max=1.0) * ident.freckles
    # Mottling as an absolute melanin change (at most 0.08), so dark skin is not blotchy.
    mel = (ident.melanin + 0.08 * min(ident.melanin, 1.0) * mottle) * (1.0 - 0.35 * a["lips"]) \
        * (1.0 + 0.8 * freckle)
    hb = ident.haemoglobin * (1.0 + 1.6 * a["lips"] + 0.7 * a["cheeks"] + 0.15 * mottle)
    skin = torch.from_numpy(skin_albedo(mel.double().numpy(), hb.double().numpy())).float()
    skin = skin * (1.0 + 0.06 * pores)[:, None]
    hair_c = torch.tensor(ident.hair_colour, dtype=torch.float32)
    strands = (_noise(uv * torch.tensor([1.0, 0.05]), s + 5, 400.0) * 0.5 + 0.5)
    brow = (a["brows"] * ident.brow_density * (0.6 + 0.6 * strands)).clamp(0, 1)
    stubble = (a["beard"] * ident.beard * (0.4 + 0.6 * (_noise(uv, s + 6, 250.0) > 0.1).float()))
    lash = 0.85 * a["lash"]
    dark = torch.maximum(torch.maximum(brow, 0.6 * stubble), lash)[:, None]
    skin = skin * (1 - dark) + hair_c * dark
    albedo = torch.zeros(n, 3)
    put = lambda mat, val: albedo.copy_(torch.where((material == mat)[:, None], val, albedo))  # noqa: E731
    put(SKIN, skin)
    sclera = torch.tensor([0.62, 0.55, 0.50]) * (1.0 + 0.05 * mottle)[:, None]
    put(SCLERA, sclera)
    iris = torch.tensor(ident.iris_colour, dtype=torch.float32) * (1.0 + 0.3 * pores)[:, None]
    put(IRIS, iris * (1.0 - 0.95 * a["pupil"])[:, None])
    put(TEETH, torch.tensor([0.62, 0.56, 0.45]).expand(n, 3))
    put(MOUTH, torch.tensor([0.35, 0.07, 0.07]).expand(n, 3))
    put(LASHES, (hair_c * 0.5).expand(n, 3))
    hair_strand = 0.55 + 0.45 * (_noise(uv * torch.tensor([1.0, 0.02]), s + 7, 500.0) * 0.5 + 0.5)
    # The shell thins to the skin at the hairline: let skin show through there between wisps,
    # so the hairline is soft and broken rather than the hard rim of a cap.
    wisp = _noise(uv * torch.tensor([1.0, 0.05]), s + 8, 300.0)
    cover = ((a["hair_cover"] - 0.08 + 0.25 * wisp) / 0.3).clamp(0.0, 1.0)[:, None]
    put(HAIR, hair_c * hair_strand[:, None] * cover + skin * (1.0 - cover))
    cloth = torch.tensor(ident.clothes_colour, dtype=torch.float32) * (1.0 + 0.1 * pores)[:, None]
    put(CLOTHES, cloth)
    lut = lambda table, default: torch.tensor(  # noqa: E731
        [table.get(i, default) for i in range(8)], dtype=torch.float32)[material.clamp(min=0)]
    f0 = lut(F0, 0.03)
    rough = lut(ROUGHNESS, 0.5) - 0.2 * a["oily"] * (material == SKIN) - 0.2 * a["lips"]
    sss = lut(SSS, 0.0)
    return albedo.clamp(0.0, 0.95), f0, rough.clamp(0.05, 1.0), sss
