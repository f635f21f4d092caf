"""The fixed held-out test set: one command rebuilds it bit-identically.

    .venv/bin/python -m training.data.make_testset [--res 128] [--n 64]     # prints its sha256

It is the first ``n`` samples of ``LightStageDataset('test', res, seed=TEST_SEED)`` (the same as
training.eval.evaluate's default held-out dataset): identities that training never sees
(id % 16 == 15), and environment lighting drawn half from the four HDRIs held out of training
(training/data/lighting_sampling.py), half from the others, plus point lights. Rendered on one torch
thread, so float reductions run in one order and a rebuild on the same machine gives the same bits.

The file lives under cache/testset/ (git-ignored), named after the resolution, the count and the
light stage's sample version (training.data.dataset.RENDER_VERSION), so a change to the renderer
builds a new set rather than silently mixing two. ``load_testset(res)`` builds it when missing and
returns the stacked arrays; the sha256 printed (and stored beside it) is of the array contents, so
two builds can be compared.

The golden probe keeps RENDER_VERSION honest: two test-split samples at 40 px (with the transport
targets, and their images in front of varied backdrops) stored in tests/training/golden/;
tests/training/test_render_version.py renders them again and compares. After a deliberate change
to what samples hold, bump RENDER_VERSION and run

    .venv/bin/python -m training.data.make_testset --write-probe
"""

from __future__ import annotations

import argparse
import hashlib
import json
import pathlib

import numpy as np
import torch

from addon.frames import write_atomic

from .dataset import LightStageDataset, renderer_version

ROOT = pathlib.Path(__file__).resolve().parents[2]
DEFAULT_DIR = ROOT / "cache" / "testset"
TEST_SEED = 12345
DEFAULT_N = 64
PROBE_PATH = ROOT / "tests" / "training" / "golden" / "render_probe.npz"
PROBE_RES, PROBE_N = 40, 2
# Binary maps are stored as bytes; load_testset returns float32 like the dataset does.
_BYTES = ("parsing_t", "parsing_t1", "valid_fw", "valid_bw")


def content_sha256(arrays: dict) -> str:
    """sha256 over the arrays' names, dtypes, shapes and bytes, in name order."""
    h = hashlib.sha256()
    for k in sorted(arrays):
        a = np.ascontiguousarray(arrays[k])
        h.update(f"{k}|{a.dtype.str}|{a.shape}|".encode())
        h.update(a.tobytes())
    return h.hexdigest()


def testset_path(resolution: int, n: int = DEFAULT_N, folder=None) -> pathlib.Path:
    folder = pathlib.Path(folder) if folder else DEFAULT_DIR
    return folder / f"test_{int(resolution)}_n{int(n)}_{renderer_version()}.npz"


def render_testset(resolution: int, n: int = DEFAULT_N, data_root=None,
                   transport: bool = False, backdrops: str = "wall") -> dict:
    """The stacked samples (float32, as the dataset gives them), rendered on one thread."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        ds = LightStageDataset("test", resolution, seed=TEST_SEED, length=n, data_root=data_root,
                               transport=transport, backdrops=backdrops)
        samples = [ds[i] for i in range(n)]
    finally:
        torch.set_num_threads(threads)
    return {k: np.stack([s[k] for s in samples]) for k in samples[0]}


def build_testset(resolution: int, n: int = DEFAULT_N, folder=None, data_root=None) -> tuple:
    """Render and write the test set; returns (path, sha256 of the contents)."""
    path = testset_path(resolution, n, folder)
    path.parent.mkdir(parents=True, exist_ok=True)
    arrays = render_testset(resolution, n, data_root)
    for k in _BYTES:
        if not np.array_equal(arrays[k], arrays[k].astype(np.uint8)):
            raise ValueError(f"{k} is not binary; the test set stores it as bytes")
    stored = {k: (v.astype(np.uint8) if k in _BYTES else v) for k, v in arrays.items()}
    digest = content_sha256(arrays)

    def write(tmp):
        with open(tmp, "wb") as f:  # a file, so np.savez adds no .npz to the name
            np.savez(f, **stored)
    write_atomic(path, write)
    path.with_suffix(".json").write_text(json.dumps(
        {"sha256": digest, "split": "test", "seed": TEST_SEED, "resolution": int(resolution),
         "n": int(n), "renderer": renderer_version()}, indent=2))
    return path, digest


def load_testset(resolution: int = 128, n: int = DEFAULT_N, folder=None, data_root=None) -> dict:
    """The test set as a dict of stacked float32 arrays (the dataset's keys, a leading sample
    axis); built first when it is missing (about 1 s per sample at 128 on one core)."""
    path = testset_path(resolution, n, folder)
    if not path.is_file():
        build_testset(resolution, n, folder, data_root)
    with np.load(path) as z:
        return {k: z[k].astype(np.float32) for k in z.files}


def render_probe(data_root=None) -> dict:
    """The golden probe's samples, rendered now (see the module docstring): with the stage's
    wall, and (keys "varied/...") the images with varied backdrops, which evaluate's background
    figure is measured on."""
    out = render_testset(PROBE_RES, PROBE_N, data_root, transport=True)
    varied = render_testset(PROBE_RES, PROBE_N, data_root, backdrops="varied")
    out.update({f"varied/{k}": v for k, v in varied.items() if k.startswith(("img_", "gt_"))})
    return out


def write_probe(data_root=None, path=PROBE_PATH) -> pathlib.Path:
    path = pathlib.Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    # float16 (a relative rounding of 2**-11, well inside probe_differences' tolerance) keeps the
    # file small; the binary maps as bytes
    arrays = {k: v.astype(np.uint8 if k in _BYTES else np.float16)
              for k, v in render_probe(data_root).items()}
    np.savez_compressed(path, render_version=np.array(renderer_version()), **arrays)
    return path


def load_probe(path=PROBE_PATH) -> tuple[str, dict]:
    """(the render version it was written for, its arrays as float32)."""
    with np.load(path) as z:
        return str(z["render_version"]), {k: z[k].astype(np.float32) for k in z.files
                                          if k != "render_version"}


def probe_differences(now: dict, golden: dict, rel: float = 2e-3, share: float = 2e-3) -> list:
    """What differs between a fresh probe and the golden one, one line per array; empty when
    they agree. An element differs when it is off by more than ``rel`` of the array's largest
    magnitude; up to ``share`` of the elements may differ (another CPU may flip a shadow texel),
    never the array's shape."""
    out = [f"{k}: missing now" for k in sorted(set(golden) - set(now))]
    out += [f"{k}: new array" for k in sorted(set(now) - set(golden))]
    for k in sorted(set(now) & set(golden)):
        a, b = np.asarray(now[k], np.float64), np.asarray(golden[k], np.float64)
        if a.shape != b.shape:
            out.append(f"{k}: shape {a.shape} is not the golden {b.shape}")
            continue
        tol = rel * max(float(np.abs(b).max()), 1e-12)
        bad = float(np.mean(np.abs(a - b) > tol)) if a.size else 0.0
        if bad > share:
            out.append(f"{k}: {bad:.2%} of the elements differ by more than {tol:.3g}")
    return out


class TestSet:
    """The test set as a map-style dataset (``len``, ``[i]`` -> one sample dict), for evaluation
    code written against LightStageDataset."""

    __test__ = False  # not a pytest class

    def __init__(self, resolution: int = 128, n: int = DEFAULT_N, folder=None, data_root=None):
        self.arrays = load_testset(resolution, n, folder, data_root)
        self.n = int(n)

    def __len__(self) -> int:
        return self.n

    def __getitem__(self, i: int) -> dict:
        if not 0 <= int(i) < self.n:
            raise IndexError(i)
        return {k: v[int(i)] for k, v in self.arrays.items()}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--res", type=int, nargs="+", default=[128])
    ap.add_argument("--n", type=int, default=DEFAULT_N)
    ap.add_argument("--out", help=f"folder (default {DEFAULT_DIR})")
    ap.add_argument("--data-root", help="the shared data folder (default ../shared/data)")
    ap.add_argument("--write-probe", action="store_true",
                    help=f"rewrite the golden probe ({PROBE_PATH.relative_to(ROOT)}) after "
                         "bumping training.data.dataset.RENDER_VERSION, and stop")
    a = ap.parse_args(argv)
    if a.write_probe:
        print(f"wrote {write_probe(a.data_root)} ({renderer_version()})")
        return
    for res in a.res:
        path, digest = build_testset(res, a.n, a.out, a.data_root)
        print(f"{path}  sha256 {digest}")


if __name__ == "__main__":
    main()
