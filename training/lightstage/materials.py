"""Materials: a pigment-based skin albedo with spatial detail, and the other surfaces' parameters.

Skin albedo = base * exp(-(melanin * k_mel + haemoglobin * k_hb)) per channel: melanin absorbs
more toward blue (its absorption falls with wavelength), haemoglobin mostly absorbs green and blue,
so one melanin knob spans very light to very dark skin and haemoglobin gives lips and cheeks their
redness. Skin detail is solid noise on the surface at rest (the head's neutral shape, carried as a
vertex attribute), so it moves with the skin, the flow stays exact, and it has one size and shape
everywhere: pores (a few percent of albedo), mottling (centimetre-scale melanin and blood), freckles
(round melanin spots, on light skin). Stubble and brows stay strand-like noise on the texture
coordinates, in hair colour.
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
ATTRS = ("lips", "brows", "beard", "oily", "cheeks", "pupil", "hair_cover", "lash", "neckline",
         "rest_x", "rest_y", "rest_z")
REST = slice(ATTRS.index("rest_x"), ATTRS.index("rest_z") + 1)
UV_CM = 24.0  # median size of one texture-coordinate unit on the ICT head, in cm
# Skin detail on the surface at rest, in cm (solid noise: the same size and shape everywhere,
# where texture-coordinate noise was stretched up to 7x by the head's UV layout, which drew
# freckles as streaks and blocks).
PORE_CM, MOTTLE_CM, FRECKLE_CM = 0.12, 1.6, 0.4
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
    hair shell, how far it is from the hairline (0 at the hairline, 1 on the crown); long hair's
    curtain is all hair."""
    m = assets.load_head(data_root)
    out = torch.zeros(rig.n_vertices, len(ATTRS))
    for k in _REGIONS:
        out[: rig.n_head, ATTRS.index(k)] = rig.regions[k]
    shell = slice(rig.n_head, rig.n_head + rig.scalp.numel())
    out[shell, ATTRS.index("hair_cover")] = rig.scalp_weight
    n_curtain = rig.curtain.y.numel() if rig.curtain is not None else 0
    hair = slice(rig.n_head, shell.stop + n_curtain)
    out[shell.stop:hair.stop, ATTRS.index("hair_cover")] = 1.0
    out[hair, ATTRS.index("neckline")] = -NECKLINE_FAR
    out[hair.stop:, ATTRS.index("neckline")] = NECKLINE_FAR
    # Where a point sits on the body at rest (cm), for the solid skin detail: the head's neutral
    # shape (so detail moves with the skin and the flow stays exact); hair shell and torso from
    # their texture coordinates, away from the head.
    out[: rig.n_head, REST] = torch.from_numpy(np.asarray(m.neutral, np.float32))
    out[rig.n_head:, REST.start:REST.start + 2] = rig.uv[rig.n_head:] * UV_CM
    out[rig.n_head:, REST.stop - 1] = -100.0
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


def _hash(cells: torch.Tensor, seed: int, k: int = 0) -> torch.Tensor:
    """Uniform [0, 1) per integer lattice point (N, 3), deterministic in (seed, k)."""
    c = cells.to(torch.int64) & 0xFFFFF
    h = (c[:, 0] * 73856093) ^ (c[:, 1] * 19349663) ^ (c[:, 2] * 83492791)
    h = (h ^ ((int(seed) * 2654435761 + k * 40503) & 0x7FFFFFFF)) & 0x7FFFFFFF
    for _ in range(2):  # integer mixing (xorshift-multiply), kept in 31 bits
        h = ((h ^ (h >> 15)) * 0x2C1B3C6D) & 0x7FFFFFFF
        h = ((h ^ (h >> 12)) * 0x297A2D39) & 0x7FFFFFFF
    return (h ^ (h >> 15)).to(torch.float64).div(2.0 ** 31).float()


def solid_noise(p: torch.Tensor, seed: int, cell_cm: float) -> torch.Tensor:
    """Smooth value noise in [-1, 1] at (N, 3) points (cm), lattice spacing ``cell_cm``."""
    q = p / cell_cm
    i0 = torch.floor(q)
    f = q - i0
    f = f * f * (3.0 - 2.0 * f)
    out = torch.zeros(p.shape[0])
    for dx in (0, 1):
        for dy in (0, 1):
            for dz in (0, 1):
                corner = i0 + torch.tensor([dx, dy, dz], dtype=i0.dtype)
                w = ((f[:, 0] if dx else 1 - f[:, 0]) * (f[:, 1] if dy else 1 - f[:, 1])
                     * (f[:, 2] if dz else 1 - f[:, 2]))
                out += w * (_hash(corner, seed) * 2.0 - 1.0)
    return out


def spots(p: torch.Tensor, seed: int, cell_cm: float, density: torch.Tensor) -> torch.Tensor:
    """Round spots in [0, 1] at (N, 3) points (cm): at most one per cell of ``cell_cm``, present
    with probability ``density`` (N,) there, of random radius up to 0.35 cells, soft-edged."""
    q = p / cell_cm
    base = torch.floor(q)
    out = torch.zeros(p.shape[0])
    for dx in (-1, 0, 1):
        for dy in (-1, 0, 1):
            for dz in (-1, 0, 1):
                cell = base + torch.tensor([dx, dy, dz], dtype=base.dtype)
                centre = cell + torch.stack([_hash(cell, seed, k) for k in (1, 2, 3)], 1)
                radius = 0.12 + 0.23 * _hash(cell, seed, 4)
                there = (_hash(cell, seed, 5) < density).float()
                d = (q - centre).norm(dim=1)
                out = torch.maximum(out, there * ((radius - d) / (0.35 * radius)).clamp(0.0, 1.0))
    return out


def surface(material: torch.Tensor, uv: torch.Tensor, attrs: torch.Tensor, ident: Identity):
    """Per-pixel (albedo (N, 3), F0 (N,), roughness (N,), sss weight (N,), strands (N,): how much
    of the pixel is hair, for shading.transfer) for N pixels."""
    n = material.shape[0]
    s = ident.texture_seed
    a = {k: attrs[:, i] for i, k in enumerate(ATTRS)}
    rest = attrs[:, REST]
    pores = solid_noise(rest, s + 1, PORE_CM) * 0.5 + solid_noise(rest, s + 2, 2 * PORE_CM) * 0.5
    mottle = solid_noise(rest, s + 3, MOTTLE_CM)
    # Freckles: round spots, denser over the cheeks and nose bridge, rarer and fainter the darker
    # the skin (ephelides are a trait of light skin).
    fair = float(np.clip(1.3 - 0.6 * ident.melanin, 0.0, 1.0))
    if ident.freckles > 0 and fair > 0:
        density = 0.35 + 0.6 * a["cheeks"]
        freckle = spots(rest, s + 4, FRECKLE_CM, density) * ident.freckles * fair
    else:  # most subjects: simulate only what the subject has
        freckle = torch.zeros(n)
    # Mottling as an absolute melanin change (at most 0.08), so dark skin is not blotchy.
    # Freckles add melanin (an absolute amount: visible on the light skin that has them).
    mel = (ident.melanin + 0.08 * min(ident.melanin, 1.0) * mottle) * (1.0 - 0.35 * a["lips"]) \
        + 0.7 * freckle
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
    # Fine wisps (narrower than a pixel at training sizes): a soft, broken edge instead of teeth.
    wisp = _noise(uv * torch.tensor([1.0, 0.05]), s + 8, 1200.0)
    cover = ((a["hair_cover"] - 0.06 + 0.2 * wisp) / 0.4).clamp(0.0, 1.0)[:, None]
    put(HAIR, hair_c * hair_strand[:, None] * cover + skin * (1.0 - cover))
    cloth = torch.tensor(ident.clothes_colour, dtype=torch.float32) * (1.0 + 0.1 * pores)[:, None]
    put(CLOTHES, cloth)
    lut = lambda table, default: torch.tensor(  # noqa: E731
        [table.get(i, default) for i in range(8)], dtype=torch.float32)[material.clamp(min=0)]
    f0 = lut(F0, 0.03)
    rough = lut(ROUGHNESS, 0.5) - 0.2 * a["oily"] * (material == SKIN) - 0.2 * a["lips"]
    sss = lut(SSS, 0.0)
    # Where the shell thins to skin, the skin shows with its own shading: strands is how much of
    # a hair pixel is hair (shading.transfer blends the hair's lobes with the skin's by it).
    hair = material == HAIR
    strands = torch.where(hair, cover[:, 0], 0.0)
    bare = torch.where(hair, 1.0 - cover[:, 0], 0.0)
    f0 = f0 + bare * F0[SKIN]
    rough = torch.where(hair, ROUGHNESS[SKIN] * bare + rough * (1.0 - bare), rough)
    sss = sss + bare * SSS[SKIN]
    return albedo.clamp(0.0, 0.95), f0, rough.clamp(0.05, 1.0), sss, strands
