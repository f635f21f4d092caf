"""A frame pair: everything one training sample needs except its lighting.

A sample is two adjacent frames (t, t+1) shaded under three light vectors. The costly part (pose,
G-buffer, materials, shadow maps, per-light transfer, flow) depends on the frames only; the lighting
enters through one linear map (shading.relight). So a pair is computed once -- on the fly from a
Scene, or read back from the frame cache (training/data/build_cache.py) -- and relit as often as
wanted.

Both routes end in ``assemble``, the one function that turns a pair and a lighting triplet into a
sample dict, so cached samples equal on-the-fly samples up to the cache's float16 transfer (a
relative rounding of at most 2**-11 per term; tested).
"""

from __future__ import annotations

import functools
import json
import pathlib
from dataclasses import dataclass

import numpy as np
import torch

from addon.frames import write_atomic

from . import layout, shading
from .scene import Scene, next_time, stage_dirs

FORMAT = 2
MAGIC = "lightstage-pair/2"  # "cover" arrays are optional: older files lack them
_F16_MAX = 65504.0


@dataclass
class PairRecord:
    frames: tuple            # (ShadeInputs at t, ShadeInputs at t+1)
    labels: tuple            # two (H, W) int64 parsing channels (0 = background)
    flow_fw: torch.Tensor    # (2, H, W)
    flow_bw: torch.Tensor
    valid_fw: torch.Tensor   # (1, H, W)
    valid_bw: torch.Tensor


def record_pair(scene: Scene, t: float) -> PairRecord:
    f0 = scene.frame(t)
    f1 = scene.frame(next_time(t))
    flow_fw, valid_fw = scene.flow(f0, f1)
    flow_bw, valid_bw = scene.flow(f1, f0)
    return PairRecord((scene.shade_inputs(f0), scene.shade_inputs(f1)),
                      (f0.gb.label, f1.gb.label), flow_fw, flow_bw, valid_fw, valid_bw)


@functools.lru_cache(maxsize=1)
def transport_matrix() -> torch.Tensor:
    """(114, 9) Q: a pixel's diffuse transfer D (irradiance = D @ stage weights) times Q is its
    order-2 SH transport T, the weighted least-squares fit of E(L) = T . SH(L) with SH(L) the
    light vector's projection as training/model/network.py computes it (basis at cell centres times
    solid angle): D @ layout.projection() maps cell power to irradiance, and the fit over the
    cells (weighted by solid angle) gives Q = P^T diag(omega) Y (Y^T diag(omega) Y)^-1."""
    y, omega = shading.cell_sh(torch.float64)
    gram = y.T @ (omega[:, None] * y)
    proj = torch.from_numpy(layout.projection().copy())  # (114, 256): weights from cell power
    return (proj @ (omega[:, None] * y) @ torch.linalg.inv(gram)).float()


def transport(s: shading.ShadeInputs) -> torch.Tensor:
    """(9, H, W) SH transport of the foreground pixels (0 elsewhere): the target of the network's
    ratio head (training.model.losses transport term)."""
    h, w = s.mask.shape
    out = torch.zeros(9, h * w)
    out[:, s.idx] = (s.diffuse.float() @ transport_matrix()).T
    return out.view(9, h, w)


def assemble(rec: PairRecord, lights, n_classes: int, with_transport: bool = False) -> dict:
    """The sample dict (see training/data/dataset.py) of a pair under the triplet (L^i, L^j, L^k);
    ``with_transport`` adds each frame's SH transport (``transport_t``, ``transport_t1``)."""
    li, lj, lk = lights
    w = torch.from_numpy(np.stack([layout.weights(x) for x in (li, lk, lj, lk)])).float()
    dirs = stage_dirs()
    a = shading.relight(rec.frames[0], w[:2], dirs)
    b = shading.relight(rec.frames[1], w[2:], dirs)
    out = {"img_t_i": a[0], "gt_t_k": a[1], "img_t1_j": b[0], "gt_t1_k": b[1],
           "flow_fw": rec.flow_fw, "flow_bw": rec.flow_bw,
           "valid_fw": rec.valid_fw, "valid_bw": rec.valid_bw}
    for key, s, lab in (("t", rec.frames[0], rec.labels[0]), ("t1", rec.frames[1], rec.labels[1])):
        parsing = torch.stack([(lab == i) for i in range(n_classes)], 0).float()
        parsing[0] = s.mask.float()
        out[f"mask_{key}"] = (s.mask.float() if s.cover is None else s.cover)[None]
        out[f"parsing_{key}"] = parsing
        if with_transport:
            out[f"transport_{key}"] = transport(s)
    out = {k: np.ascontiguousarray(v.numpy(), dtype=np.float32) for k, v in out.items()}
    out.update(light_i=np.asarray(li, np.float32), light_j=np.asarray(lj, np.float32),
               light_k=np.asarray(lk, np.float32))
    return out


# ------------------------------------------------------------------------------ the cache format

def save(rec: PairRecord, path: pathlib.Path) -> int:
    """Write a pair: a JSON header (names, dtypes, shapes, offsets) then the raw arrays, so that
    reading it back is one read and no parsing, checksums or decompression. Returns the bytes
    written. The transfer is stored as float16 (values are far below its
    range; anything above is refused rather than turned into infinity)."""
    arrs = {"flow_fw": rec.flow_fw.numpy(), "flow_bw": rec.flow_bw.numpy(),
            "valid_fw": rec.valid_fw.numpy().astype(np.uint8),
            "valid_bw": rec.valid_bw.numpy().astype(np.uint8)}
    for n, (s, lab) in enumerate(zip(rec.frames, rec.labels)):
        for name in ("diffuse", "specular"):
            x = getattr(s, name)
            big = float(x.abs().max()) if x.numel() else 0.0
            if not bool(torch.isfinite(x).all()) or big > _F16_MAX:
                raise ValueError(f"{name} transfer out of float16 range in {path.name}")
            arrs[f"{name}{n}"] = x.numpy().astype(np.float16)
        arrs[f"idx{n}"] = s.idx.numpy().astype(np.int32)
        arrs[f"albedo{n}"] = s.albedo.numpy()
        arrs[f"sss{n}"] = s.sss.numpy()
        arrs[f"mask{n}"] = s.mask.numpy()
        arrs[f"cover{n}"] = (s.mask.float() if s.cover is None else s.cover).numpy()
        arrs[f"label{n}"] = lab.numpy().astype(np.uint8)
        arrs[f"backdrop{n}"] = s.backdrop.numpy()
        arrs[f"px_per_cm{n}"] = np.float64(s.px_per_cm)
    write_arrays(path, arrs)
    return path.stat().st_size


def write_arrays(path: pathlib.Path, arrs: dict) -> None:
    entries, offset = [], 0
    for k, v in arrs.items():
        v = np.ascontiguousarray(v)
        entries.append({"name": k, "dtype": v.dtype.str, "shape": list(v.shape), "offset": offset})
        offset += -(-v.nbytes // 8) * 8  # 8-byte aligned, so every view is aligned
    head = json.dumps({"magic": MAGIC, "arrays": entries}).encode()
    head += b" " * (-(len(head) + 8) % 64)

    def write(tmp):
        with open(tmp, "wb") as fh:
            fh.write(len(head).to_bytes(8, "little") + head)
            for e, v in zip(entries, arrs.values()):
                b = np.ascontiguousarray(v).tobytes()
                fh.write(b + b"\0" * (-len(b) % 8))
    write_atomic(path, write)  # a reader never sees half a file


def read_arrays(path: pathlib.Path) -> dict:
    buf = bytearray(path.stat().st_size)  # writable, so the arrays below are views, not copies
    with open(path, "rb") as fh:
        fh.readinto(buf)
    n = int.from_bytes(buf[:8], "little")
    head = json.loads(buf[8:8 + n])
    if head.get("magic") != MAGIC:
        raise ValueError(f"{path} is not a light-stage pair file")
    base = 8 + n
    out = {}
    for e in head["arrays"]:
        dt = np.dtype(e["dtype"])
        count = int(np.prod(e["shape"], dtype=np.int64))
        a = np.frombuffer(buf, dt, count, base + e["offset"]).reshape(e["shape"])
        out[e["name"]] = a
    return out


def load(path: pathlib.Path) -> PairRecord:
    a = read_arrays(path)
    t = torch.from_numpy
    frames, labels = [], []
    for n in range(2):
        frames.append(shading.ShadeInputs(
            t(a[f"idx{n}"]).long(), t(a[f"diffuse{n}"]), t(a[f"specular{n}"]),
            t(a[f"albedo{n}"]), t(a[f"sss{n}"]), float(a[f"px_per_cm{n}"].reshape(-1)[0]),
            t(a[f"mask{n}"]), t(a[f"backdrop{n}"]),
            t(a[f"cover{n}"]) if f"cover{n}" in a else None))
        labels.append(t(a[f"label{n}"]).long())
    return PairRecord(tuple(frames), tuple(labels), t(a["flow_fw"]), t(a["flow_bw"]),
                      t(a["valid_fw"]).float(), t(a["valid_bw"]).float())


def write_manifest(folder: pathlib.Path, info: dict) -> None:
    text = json.dumps({"format": FORMAT, **info}, indent=2)
    write_atomic(folder / "manifest.json", lambda tmp: pathlib.Path(tmp).write_text(text))


def pair_path(folder: pathlib.Path, p: int) -> pathlib.Path:
    return folder / f"pair_{p:06d}.bin"
