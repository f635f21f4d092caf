"""The head model and the static parts of the scene built around it.

``ict_facekit.npz`` (ICT-FaceKit, MIT) is in centimetres, +Y up, the face looking down +Z; its
bust already holds neck and upper chest. Around it this module builds, once per hair style:
* a hair shell: the scalp's triangles duplicated and pushed out along the normals by the style's
  volume, tapering to zero at the hairline (so the shell meets the skin);
* for long hair, a curtain: a sheet that follows the skull's sides and back and falls straight
  from their widest point, over the ears, past the jaw to the shoulders, with a ragged lower
  edge (``HairStyle.hang``; each side's front edge at its own angle, so hair can frame the face
  or sit behind an ear);
* a torso: the bust's bottom boundary loop extruded down and out into shoulders and chest;
* per-triangle material and parsing labels. The labels come from the neutral mesh (lips from the
  68 landmarks, brows around the brow landmarks, neck under the jaw line, clothes below the
  neckline), so they follow the mesh through every identity and expression.
The eye occlusion, eye blend and lacrimal fluid meshes are transparent overlays in ICT-FaceKit and
are left out, and so are the eyelash cards (opaque, they look like goggles; alpha-tested lashes are
future work).
"""

from __future__ import annotations

import functools
import pathlib
from dataclasses import dataclass

import numpy as np
import torch

from addon.contract import PARSING_CLASSES
from addon.errors import InputError

LABEL = {name: i for i, name in enumerate(PARSING_CLASSES)}  # channel ids, 0 = foreground

# Materials (shading models and albedo sources), per triangle.
SKIN, SCLERA, IRIS, TEETH, MOUTH, LASHES, HAIR, CLOTHES = range(8)
_ICT_MATERIAL = {"M_Face": SKIN, "M_BackHead": SKIN, "M_GumsTongue": MOUTH, "M_Teeth": TEETH,
                 "M_ScleraLeft": SCLERA, "M_IrisLeft": IRIS, "M_ScleraRight": SCLERA,
                 "M_IrisRight": IRIS}
# The eyelash cards are left out too: drawn opaque they read as thick black goggles at 128-256 px.
_DROPPED = ("M_LacrimalFluid", "M_EyeBlend", "M_EyeOcclusion", "M_EyeLashes")

# Torso extrusion rings: (drop below the bust's bottom loop in cm, lateral scale, depth scale).
_TORSO_RINGS = ((2.0, 1.25, 1.05), (5.0, 1.55, 1.10), (9.0, 1.68, 1.12), (15.0, 1.70, 1.10),
                (25.0, 1.66, 1.05), (40.0, 1.62, 1.0))


def default_data_root() -> pathlib.Path:
    return pathlib.Path(__file__).resolve().parents[3] / "shared" / "data"


@dataclass(frozen=True)
class HeadModel:
    neutral: np.ndarray          # (V, 3) float32 cm
    identity_modes: np.ndarray   # (100, V, 3) float32
    expression_modes: np.ndarray  # (57, V, 3) float32
    expression_names: tuple
    triangles: np.ndarray        # (F, 3) int64, overlay meshes removed
    material: np.ndarray         # (F,) int64 material ids (SKIN, ...)
    uv: np.ndarray               # (V, 2) float32, one UV per vertex (first seen)
    landmarks: np.ndarray        # (68,) vertex ids
    regions: dict                # name -> (first, last) vertex id, inclusive

    def expression_index(self, name: str) -> int:
        return self.expression_names.index(name)


@functools.lru_cache(maxsize=2)
def load_head(data_root=None) -> HeadModel:
    root = pathlib.Path(data_root) if data_root is not None else default_data_root()
    path = root / "heads" / "ict_facekit.npz"
    if not path.is_file():
        raise InputError(f"The head model {path} is missing; the synthetic light stage needs "
                         "../shared/data/heads/ict_facekit.npz (set data_root to its folder).")
    d = np.load(path)
    names = [str(n) for n in d["material_names"]]
    tri_mat = d["triangle_material"]
    keep = ~np.isin(tri_mat, [names.index(n) for n in _DROPPED])
    keep &= ~_cornea(d, names)
    tris = d["triangles"][keep].astype(np.int64)
    material = np.array([_ICT_MATERIAL[names[m]] for m in tri_mat[keep]], dtype=np.int64)
    uv = np.zeros((len(d["neutral"]), 2), np.float32)
    uv[d["triangles"].reshape(-1)] = d["uv"][d["triangle_uvs"].reshape(-1)]
    regions = {str(n): (int(a), int(b)) for n, (a, b) in zip(d["region_names"],
                                                            d["region_vertex_ranges"])}
    return HeadModel(d["neutral"].astype(np.float32), d["identity_modes"].astype(np.float32),
                     d["expression_modes"].astype(np.float32),
                     tuple(str(n) for n in d["expression_names"]), tris, material, uv,
                     d["landmarks68"].astype(np.int64), regions)


CORNEA_RADIUS = 0.62  # cm: the visible iris (about 12 mm across)


def _cornea(d, names) -> np.ndarray:
    """(F,) True for the sclera triangles over the iris. ICT-FaceKit's sclera mesh runs over the
    cornea, which is clear in a real eye; drawn opaque it hides the iris (white, blind-looking
    eyes), so it is left out and the iris mesh behind it shows."""
    v, tri, mat = d["neutral"], d["triangles"], d["triangle_material"]
    regions = {str(n): (int(a), int(b)) for n, (a, b) in zip(d["region_names"],
                                                            d["region_vertex_ranges"])}
    out = np.zeros(len(tri), bool)
    for side, label in (("left", "M_ScleraLeft"), ("right", "M_ScleraRight")):
        a, b = regions[f"iris_{side}"]
        front = v[a + int(np.argmax(v[a:b + 1, 2]))]
        r = np.linalg.norm(v[tri][..., :2] - front[:2], axis=2).max(axis=1)
        z = v[tri][..., 2].min(axis=1)
        out |= (mat == names.index(label)) & (r < CORNEA_RADIUS) & (z > front[2] - 0.6)
    return out


def vertex_normals(verts: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """Area-weighted vertex normals (V, 3); isolated or degenerate vertices get +Z."""
    v = verts[faces]
    n = torch.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0], dim=1)
    acc = torch.zeros_like(verts).index_add_(0, faces.reshape(-1), n.repeat_interleave(3, 0))
    length = acc.norm(dim=1, keepdim=True)
    fallback = torch.tensor([0.0, 0.0, 1.0], dtype=verts.dtype, device=verts.device)
    return torch.where(length > 1e-12, acc / length.clamp(min=1e-12), fallback)


def _smoothstep(x):
    """Smooth 0 -> 1 over x in [0, 1] (a numpy array or a torch tensor)."""
    x = x.clip(0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


def _polyline_distance(p: np.ndarray, line: np.ndarray) -> np.ndarray:
    """Distance from 2-D points (N, 2) to a polyline (M, 2)."""
    best = np.full(len(p), np.inf)
    for a, b in zip(line[:-1], line[1:]):
        ab = b - a
        t = np.clip(((p - a) @ ab) / max(ab @ ab, 1e-12), 0.0, 1.0)
        best = np.minimum(best, np.linalg.norm(p - (a + t[:, None] * ab), axis=1))
    return best


def _inside_polygon(p: np.ndarray, poly: np.ndarray) -> np.ndarray:
    inside = np.zeros(len(p), bool)
    x, y = p[:, 0], p[:, 1]
    for a, b in zip(poly, np.roll(poly, -1, axis=0)):
        cross = (a[1] > y) != (b[1] > y)
        xint = a[0] + (y - a[1]) * (b[0] - a[0]) / (b[1] - a[1] + 1e-12)
        inside ^= cross & (x < xint)
    return inside


@functools.lru_cache(maxsize=2)
def head_regions(data_root=None) -> dict:
    """Per-vertex region weights in [0, 1] on the neutral mesh (identity-independent)."""
    m = load_head(data_root)
    v = m.neutral
    lm = v[m.landmarks]
    front = _smoothstep((v[:, 2] - 4.0) / 2.0)
    skin_v = np.zeros(len(v), bool)
    skin_v[m.triangles[m.material == SKIN].reshape(-1)] = True
    lips = _inside_polygon(v[:, :2], lm[48:60, :2]) & (v[:, 2] > 8.0) & skin_v
    brow_d = np.minimum(_polyline_distance(v[:, :2], lm[17:22, :2] + [0, 0.15]),
                        _polyline_distance(v[:, :2], lm[22:27, :2] + [0, 0.15]))
    brows = _smoothstep((0.55 - brow_d) / 0.25) * front * skin_v
    # Jaw line from the contour landmarks: below it (and in front of the ears) is neck.
    jaw = lm[0:17]
    jaw_y = np.interp(v[:, 0], jaw[:, 0], jaw[:, 1], left=jaw[0, 1], right=jaw[-1, 1])
    neck = skin_v & (((v[:, 1] < jaw_y - 0.4) & (v[:, 2] > 1.5)) | (v[:, 1] < -6.5))
    cheeks = np.exp(-(((np.abs(v[:, 0]) - 4.2) ** 2) + (v[:, 1] + 0.5) ** 2) / 3.0) * front
    chin_dist = v[:, 1] - (-1.8)  # moustache and beard: below the nose, in front of the ears
    beard = (_smoothstep(-chin_dist / 1.0) * _smoothstep((v[:, 2] - 2.0) / 2.0)
             * skin_v * (~lips) * (v[:, 1] > jaw_y - 3.0))
    oily = (np.exp(-((v[:, 0] / 1.5) ** 2)) * _smoothstep((v[:, 1] + 1.0) / 3.0)
            * front)  # the T-zone: nose ridge and forehead
    # Lash line: skin within a millimetre or two of the eyelash cards' roots. The cards
    # themselves are left out; at 128-256 pixels lashes read as a dark line along the lid.
    lash_d = _lash_root_distance(m)
    lash = _smoothstep((0.16 - lash_d) / 0.1) * skin_v
    return {"lips": lips.astype(np.float32), "brows": brows.astype(np.float32),
            "lash": lash.astype(np.float32),
            "neck": neck, "cheeks": cheeks.astype(np.float32), "beard": beard.astype(np.float32),
            "oily": oily.astype(np.float32), "skin": skin_v}


def _lash_root_distance(m: HeadModel) -> np.ndarray:
    """Distance (cm, neutral mesh) from every vertex to the nearest eyelash root: the lash-card
    vertices nearest the face (where the lashes grow from the lid)."""
    lash_ids = np.concatenate([np.arange(a, b + 1) for n, (a, b) in m.regions.items()
                               if n.startswith("eyelashes")])
    face = torch.from_numpy(m.neutral[: m.regions["face"][1] + 1]).double()
    lash = torch.from_numpy(m.neutral[lash_ids]).double()
    to_face = torch.cdist(lash, face).min(dim=1).values
    roots = lash[to_face <= torch.quantile(to_face, 0.25)]
    d = torch.cdist(torch.from_numpy(m.neutral).double(), roots).min(dim=1).values
    return d.numpy()


@functools.lru_cache(maxsize=2)
def bottom_loop(data_root=None) -> np.ndarray:
    """Vertex ids of the bust's bottom boundary loop, ordered around the body."""
    m = load_head(data_root)
    e = np.sort(np.concatenate([m.triangles[:, [0, 1]], m.triangles[:, [1, 2]],
                                m.triangles[:, [2, 0]]]), axis=1)
    u, c = np.unique(e, axis=0, return_counts=True)
    b = u[c == 1]
    b = b[(m.neutral[b[:, 0], 1] < -12.0) & (m.neutral[b[:, 1], 1] < -12.0)]
    adj: dict = {}
    for a, c2 in b:
        adj.setdefault(int(a), []).append(int(c2))
        adj.setdefault(int(c2), []).append(int(a))
    start = min(adj)
    loop, prev = [start], None
    while True:
        nxt = [n for n in adj[loop[-1]] if n != prev]
        if not nxt or nxt[0] == start:
            break
        prev = loop[-1]
        loop.append(nxt[0])
    return np.array(loop, dtype=np.int64)


@dataclass(frozen=True)
class HairStyle:
    front: float = 8.8      # hairline height (cm, neutral) above the forehead
    side: float = 5.5       # above the ears
    nape: float = -7.0      # at the back
    volume: float = 1.2     # shell thickness (cm) on the crown
    bald: bool = False
    hang: float = 0.0       # long hair: how far (cm, neutral) below the chin it falls; 0 = none
    reach: tuple = (75.0, 75.0)  # the curtain's front edge on each side (+X, -X): degrees
                                 # round from the face's front (90 = at the ear)


@dataclass(frozen=True)
class Curtain:
    """Long hair's sheet, a grid of ``rows x cols`` vertices: column azimuths round the head's
    vertical axis (radians, 0 = the face's front, as ``_hair_weight``), each vertex's height in
    the neutral frame (cm) and its radial clump factor. Where it sits depends on the head's shape
    (``curtain_vertices``), so it is placed per frame."""
    phi: torch.Tensor            # (C,)
    y: torch.Tensor              # (R, C)
    clump: torch.Tensor          # (R, C)


@dataclass
class Rig:
    """Topology of one scene (head + hair shell + long hair's curtain + torso) with per-triangle
    labels; vertices in that order."""
    n_head: int
    faces: torch.Tensor          # (F, 3) int64
    material: torch.Tensor       # (F,) int64
    label: torch.Tensor          # (F,) int64 parsing channel (1..K-1)
    scalp: torch.Tensor          # (S,) head vertex ids duplicated into the hair shell
    scalp_weight: torch.Tensor   # (S,) taper in [0, 1] (0 at the hairline)
    loop: torch.Tensor           # (L,) bust bottom loop vertex ids
    head_weight: torch.Tensor    # (V_head,) how much of the head's rotation each vertex follows
    uv: torch.Tensor             # (V_total, 2) texture coordinates (hair/torso: procedural)
    regions: dict                # per-vertex region weights (head vertices), torch float32
    curtain: Curtain | None = None  # long hair; its vertices follow the shell's

    @property
    def n_vertices(self) -> int:
        return int(self.uv.shape[0])


def _hair_weight(v: np.ndarray, style: HairStyle) -> np.ndarray:
    ang = np.degrees(np.abs(np.arctan2(v[:, 0], v[:, 2] - 1.0)))  # 0 front, 180 back
    line = np.interp(ang, [0.0, 45.0, 80.0, 115.0, 150.0, 180.0],
                     [style.front, style.front - 1.0, style.side, style.side, style.nape + 2.0,
                      style.nape])
    return _smoothstep((v[:, 1] - line) / 1.2)


def _clumps(p: np.ndarray) -> np.ndarray:
    """A fixed smooth field in [0.6, 1.4] over neutral-mesh positions (cm)."""
    rng = np.random.default_rng(0xC1A3)
    k = rng.normal(size=(6, 3))
    k *= rng.uniform(1.2, 2.6, (6, 1)) / np.linalg.norm(k, axis=1, keepdims=True)
    phase = rng.uniform(0, 2 * np.pi, 6)
    return np.clip(1.0 + 0.4 * np.sin(p @ k.T + phase).mean(axis=1) * np.sqrt(6) / 1.5, 0.6, 1.4)


@functools.lru_cache(maxsize=32)
def build_rig(style: HairStyle, neckline: float, data_root=None) -> Rig:
    m = load_head(data_root)
    reg = head_regions(data_root)
    v = m.neutral
    nv = len(v)
    label_v = np.full(nv, LABEL["skin"], np.int64)
    label_v[reg["neck"]] = LABEL["neck"]
    label_v[reg["brows"] > 0.35] = LABEL["brows"]
    label_v[reg["lips"] > 0.5] = LABEL["lips_mouth"]
    # Signed height below the neckline (cm, > 0 on the clothes): interpolated per pixel, it puts
    # the neckline between triangle edges (scene.py), so it is a smooth curve, not a zigzag.
    neck_s = neckline - 0.04 * np.maximum(v[:, 2], 0.0) ** 2 - v[:, 1]
    below = reg["skin"] & (neck_s > 0)
    label_v[below] = LABEL["clothes"]
    mat_label = {SKIN: None, SCLERA: LABEL["eyes"], IRIS: LABEL["eyes"], LASHES: LABEL["eyes"],
                 TEETH: LABEL["teeth"], MOUTH: LABEL["lips_mouth"]}
    faces = m.triangles
    # A triangle's label: the commonest of its vertices' labels (ties: the first vertex's).
    lv = label_v[faces]
    tri_label = np.where(lv[:, 1] == lv[:, 2], lv[:, 1], lv[:, 0])
    for mat, lab in mat_label.items():
        if lab is not None:
            tri_label[m.material == mat] = lab
    tri_mat = m.material.copy()
    tri_mat[(tri_mat == SKIN) & (tri_label == LABEL["clothes"])] = CLOTHES
    all_faces, all_mat, all_label = [faces], [tri_mat], [tri_label]
    uv = [m.uv]
    offset = nv
    # Hair shell over the scalp.
    if style.bald:
        scalp = np.zeros(0, np.int64)
        sw = np.zeros(0, np.float32)
    else:
        w = _hair_weight(v, style) * reg["skin"]
        skin_faces = faces[m.material == SKIN]
        hf = skin_faces[(w[skin_faces] > 0.02).any(axis=1)]
        scalp = np.unique(hf)
        remap = np.full(nv, -1, np.int64)
        remap[scalp] = np.arange(len(scalp)) + offset
        all_faces.append(remap[hf])
        all_mat.append(np.full(len(hf), HAIR, np.int64))
        all_label.append(np.full(len(hf), LABEL["hair"], np.int64))
        # Clumps: the shell's thickness varies over the head (a few cm across), so the outline
        # is uneven like hair, not a smooth cap.
        sw = (w[scalp] * _clumps(v[scalp])).astype(np.float32)
        # Hair "uv": azimuth around the crown and height, so strand noise runs down the head.
        c = v[scalp] - np.array([0.0, 4.0, 0.0])
        uv.append(np.stack([np.arctan2(c[:, 0], c[:, 2]) / (2 * np.pi) + 0.5,
                            c[:, 1] / 30.0], 1).astype(np.float32))
        offset += len(scalp)
    curtain = None
    if not style.bald and style.hang > 0:
        curtain = _curtain_grid(style)
        rows, cols = curtain.y.shape
        ids = offset + np.arange(rows * cols).reshape(rows, cols)
        a, b, c, d = ids[:-1, :-1], ids[:-1, 1:], ids[1:, :-1], ids[1:, 1:]
        cf = np.concatenate([np.stack([a, c, b], -1).reshape(-1, 3),
                             np.stack([b, c, d], -1).reshape(-1, 3)])
        all_faces.append(cf)
        all_mat.append(np.full(len(cf), HAIR, np.int64))
        all_label.append(np.full(len(cf), LABEL["hair"], np.int64))
        phi = np.broadcast_to(curtain.phi.numpy(), (rows, cols))
        uv.append(np.stack([phi / (2 * np.pi) + 0.5, (curtain.y.numpy() - 4.0) / 30.0],
                           -1).reshape(-1, 2).astype(np.float32))
        offset += rows * cols
    # Torso: rings extruded from the bust's bottom loop.
    loop = bottom_loop(data_root)
    n = len(loop)
    rings = [loop]
    for k in range(len(_TORSO_RINGS)):
        rings.append(np.arange(n) + offset + k * n)
    tface = []
    for a, b in zip(rings[:-1], rings[1:]):
        i = np.arange(n)
        j = (i + 1) % n
        tface.append(np.stack([a[i], b[i], a[j]], 1))
        tface.append(np.stack([a[j], b[i], b[j]], 1))
    tface = np.concatenate(tface)
    # Match the bust's winding: our triangle (a0, b0, a1) runs a1 -> a0 along the loop, so the
    # bust's triangle on that edge must run a0 -> a1; flip ours otherwise.
    a0, a1 = loop[0], loop[1]
    bust = faces[(faces == a0).any(1) & (faces == a1).any(1)][0]
    k = int(np.nonzero(bust == a0)[0][0])
    if bust[(k + 1) % 3] != a1:
        tface = tface[:, [0, 2, 1]]
    all_faces.append(tface)
    all_mat.append(np.full(len(tface), CLOTHES, np.int64))
    all_label.append(np.full(len(tface), LABEL["clothes"], np.int64))
    t_uv = np.tile(np.linspace(0, 1, n, endpoint=False), len(_TORSO_RINGS))
    uv.append(np.stack([t_uv, np.repeat(np.arange(1, len(_TORSO_RINGS) + 1) / 8.0, n)],
                       1).astype(np.float32))
    # Head rotation: full above the jaw, fading out down the neck; the torso follows the body.
    head_w = neck_weight(v[:, 1]).astype(np.float32)
    t = lambda a, dt=torch.float32: torch.as_tensor(np.ascontiguousarray(a), dtype=dt)  # noqa: E731
    return Rig(n_head=nv, faces=t(np.concatenate(all_faces), torch.int64),
               material=t(np.concatenate(all_mat), torch.int64),
               label=t(np.concatenate(all_label), torch.int64),
               scalp=t(scalp, torch.int64), scalp_weight=t(sw), loop=t(loop, torch.int64),
               head_weight=t(head_w), uv=t(np.concatenate(uv)),
               regions={k: t(val.astype(np.float32))
                        for k, val in {**reg, "neckline": neck_s}.items()}, curtain=curtain)


CURTAIN_TOP = 12.0     # cm (neutral): where the curtain starts, under the shell near the crown
CURTAIN_FROM = -11.0   # cm: head vertices above this (not the bust) shape it
CURTAIN_STEP = 1.0     # cm between its rows
CURTAIN_COLS = 64
_CHIN = -7.5           # cm: the chin's height on the neutral mesh


def _curtain_grid(style: HairStyle) -> Curtain:
    """The curtain's grid: columns from the +X side's front edge round the back to the -X side's,
    rows from ``CURTAIN_TOP`` down to ``hang`` below the chin, the lower edge ragged (a few cm,
    smooth along the edge) and the clump factor varying like the shell's."""
    right, left = (float(r) for r in style.reach)
    phi = np.radians(np.linspace(right, 360.0 - left, CURTAIN_COLS))
    phi = np.where(phi > np.pi, phi - 2 * np.pi, phi)
    bottom = _CHIN - style.hang
    rows = int(np.ceil((CURTAIN_TOP - bottom) / CURTAIN_STEP)) + 1
    rng = np.random.default_rng([0xC0A7, int(style.hang * 100), int(right), int(left)])
    k = rng.uniform(2.0, 7.0, 3)
    ph = rng.uniform(0, 2 * np.pi, 3)
    t = np.linspace(0.0, 1.0, CURTAIN_COLS)
    ragged = 1.2 * np.sin(2 * np.pi * k[:, None] * t + ph[:, None]).sum(0) / np.sqrt(3)
    low = bottom + ragged - 0.8 * np.abs(ragged)  # strands reach down more than they stop short
    frac = np.linspace(0.0, 1.0, rows)[:, None]
    y = CURTAIN_TOP + (low[None] - CURTAIN_TOP) * frac  # (R, C): each column ends at its own
    # Clumps vary round the head and only slowly down it: hair hangs in smooth locks.
    pos = np.stack([np.sin(phi)[None].repeat(rows, 0) * 9.0, 0.2 * y,
                    np.cos(phi)[None].repeat(rows, 0) * 9.0], -1).reshape(-1, 3)
    clump = _clumps(pos).reshape(rows, CURTAIN_COLS)
    f = torch.float32
    return Curtain(torch.tensor(phi, dtype=f), torch.tensor(y, dtype=f),
                   torch.tensor(clump, dtype=f))


CURTAIN_BIN = (np.radians(4.0), 1.0)  # azimuth (radians) and height (cm) of the skull's bins


def curtain_vertices(head: torch.Tensor, curtain: Curtain, volume: float) -> torch.Tensor:
    """(R * C, 3) the curtain's vertices for the head's vertices ``head`` (neutral frame, before
    the head turns): each column at its azimuth, as far out as the head (ears included) is at
    that height or anywhere above it, so the hair falls straight from the skull's widest point,
    plus a clearance that grows with the style's volume and varies in clumps."""
    x, y, z = head[:, 0], head[:, 1], head[:, 2] - 1.0
    az = torch.atan2(x, z)
    r = torch.hypot(x, z)
    da, dy = CURTAIN_BIN
    na = int(round(2 * np.pi / da))
    ny = int(np.ceil((CURTAIN_TOP + 4.0 - CURTAIN_FROM) / dy))
    keep = (y > CURTAIN_FROM) & (y < CURTAIN_TOP + 4.0)
    ia = ((az[keep] + np.pi) / da).long().clamp(0, na - 1)
    iy = ((y[keep] - CURTAIN_FROM) / dy).long().clamp(0, ny - 1)
    grid = torch.zeros(ny * na, dtype=head.dtype)
    grid = grid.scatter_reduce(0, iy * na + ia, r[keep], "amax", include_self=True)
    grid = grid.view(ny, na)
    # Widest at or above each height (hair falls straight), then over neighbouring azimuths.
    grid = torch.flip(torch.cummax(torch.flip(grid, [0]), 0).values, [0])
    fn = torch.nn.functional
    wrap = torch.cat([grid[:, -4:], grid, grid[:, :4]], 1)[:, None]
    grid = fn.max_pool1d(wrap, 5, 1)[:, 0]  # (ny, na + 4): azimuth bins -2 .. na + 1
    # Smoothed, then read bilinearly: the bins' steps would show as ridges across the hair.
    grid = fn.avg_pool2d(fn.pad(grid[None, None], (0, 0, 1, 1), mode="replicate"), 3, 1)[0, 0]
    # (ny, na + 2): azimuth bins -1 .. na
    cy = curtain.y.to(head.dtype)
    phi = curtain.phi.to(head.dtype)[None].expand_as(cy)
    u = ((phi + np.pi) / da - 0.5 + 1.0) / (na + 2 - 1) * 2 - 1    # columns -1 .. na
    v = ((cy - CURTAIN_FROM) / dy - 0.5) / (ny - 1) * 2 - 1
    at = torch.stack([u, v], -1)[None]
    widest = fn.grid_sample(grid[None, None], at, mode="bilinear", padding_mode="border",
                            align_corners=True)[0, 0]
    rad = widest + (0.25 + 0.5 * volume) * curtain.clump.to(head.dtype)
    out = torch.stack([torch.sin(phi) * rad, cy, 1.0 + torch.cos(phi) * rad], -1)
    return out.reshape(-1, 3)


def neck_weight(y):
    """How much of the head's rotation a point at height ``y`` (cm, neutral) follows: all of it
    above the jaw, fading out down the neck (numpy or torch)."""
    return _smoothstep((y + 15.0) / 8.0)


def torso_vertices(loop_pts: torch.Tensor) -> torch.Tensor:
    """Torso ring vertices (R * L, 3) extruded from the bust's bottom loop points (L, 3)."""
    c = loop_pts.mean(dim=0)
    out = []
    for drop, sx, sz in _TORSO_RINGS:
        p = loop_pts.clone()
        p[:, 0] = c[0] + (loop_pts[:, 0] - c[0]) * sx
        p[:, 2] = c[2] + (loop_pts[:, 2] - c[2]) * sz
        p[:, 1] = loop_pts[:, 1] - drop
        out.append(p)
    return torch.cat(out, 0)
