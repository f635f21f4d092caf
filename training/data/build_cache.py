"""Build the light-stage frame cache that LightStageDataset(cache_dir=...) reads.

    .venv/bin/python -m training.data.build_cache --res 128 --pairs 640   # 5.4 GB, 19 min here
    .venv/bin/python -m training.data.build_cache --res 256 --pairs 80    # 2.8 GB, 4 min

Writes ``<out>/<split>_<res>/pair_NNNNNN.bin`` (default out: cache/lightstage, git-ignored) and a
manifest. Each file is one pool pair of two adjacent frames: per foreground pixel and light the
diffuse and specular transfer (float16), albedo, subsurface weights, masks, parsing labels, the
backdrop, flows and occlusion masks: everything a sample needs except its lighting, which the
dataset applies on the fly as a 114-term weighted sum (training/lightstage/pairs.py). The build
resumes where it stopped (existing pairs are kept) and is a pure function of (split, resolution,
pair index, identity count), so it can be deleted and rebuilt at any time. Use the dataset with::

    LightStageDataset('train', 128, seed, cache_dir='cache/lightstage')
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import pathlib
import time

import torch

from .dataset import LightStageDataset, cache_folder, renderer_version
from ..lightstage import pairs

ROOT = pathlib.Path(__file__).resolve().parents[2]
DEFAULT_OUT = ROOT / "cache" / "lightstage"
DEFAULT_PAIRS = {128: 640, 256: 80}

_ds = None


def _init(split, res, identities, data_root):
    global _ds
    torch.set_num_threads(1)
    _ds = LightStageDataset(split, res, data_root=data_root, identities=identities)


def _render(job):
    p, folder, redo = job
    path = pairs.pair_path(folder, p)
    if path.is_file() and not redo:
        return path.stat().st_size
    scene, t = _ds.pair_scene(p)
    return pairs.save(pairs.record_pair(scene, t), path)


def build(split: str, res: int, n_pairs: int, out=None, jobs: int = 1, identities=None,
          data_root=None, progress=print) -> dict:
    folder = cache_folder(out or DEFAULT_OUT, split, res)
    folder.mkdir(parents=True, exist_ok=True)
    probe = LightStageDataset(split, res, data_root=data_root, identities=identities)
    old = folder / "manifest.json"
    old = json.loads(old.read_text()) if old.is_file() else {}
    # Pairs of another renderer version or identity pool are re-rendered in place (each file is
    # replaced atomically, so a training run reading the cache meanwhile still sees whole pairs).
    redo = bool(old) and (old.get("renderer") != renderer_version()
                          or old.get("identities") != len(probe.ids)
                          or old.get("format") != pairs.FORMAT)
    info = {"split": split, "resolution": int(res), "pairs": int(n_pairs),
            "identities": len(probe.ids), "renderer": renderer_version(),
            "command": f"python -m training.data.build_cache --split {split} --res {res} "
                       f"--pairs {n_pairs}"}
    pairs.write_manifest(folder, info)
    t0 = time.perf_counter()
    total, done = 0, 0
    work = [(p, folder, redo) for p in range(n_pairs)]
    args = (split, res, identities, data_root)
    if jobs > 1:
        ctx = multiprocessing.get_context("fork")
        with ctx.Pool(jobs, initializer=_init, initargs=args) as pool:
            for size in pool.imap(_render, work, chunksize=4):
                total, done = total + size, done + 1
                _report(progress, done, n_pairs, total, t0)
    else:
        threads = torch.get_num_threads()
        _init(*args)
        try:
            for job in work:
                total, done = total + _render(job), done + 1
                _report(progress, done, n_pairs, total, t0)
        finally:
            torch.set_num_threads(threads)
    info["bytes"] = int(total)
    pairs.write_manifest(folder, info)
    return {"folder": str(folder), "bytes": total, "seconds": time.perf_counter() - t0}


def _report(progress, done, n, total, t0):
    if progress and (done == n or done % 16 == 0):
        dt = time.perf_counter() - t0
        progress(f"{done}/{n} pairs, {total / 1e9:.2f} GB, {dt:.0f} s")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--res", type=int, nargs="+", default=[128])
    ap.add_argument("--pairs", type=int, help="pool size (default: 640 at 128, 80 at 256)")
    ap.add_argument("--split", default="train")
    ap.add_argument("--out", help=f"cache root (default {DEFAULT_OUT})")
    ap.add_argument("--jobs", type=int, default=1, help="worker processes (one thread each)")
    ap.add_argument("--identities", type=int, help="identity pool of the split (default: the "
                    "dataset's)")
    ap.add_argument("--data-root", help="the shared data folder (default ../shared/data)")
    a = ap.parse_args(argv)
    for res in a.res:
        n = a.pairs or DEFAULT_PAIRS.get(res, max(16, int(640 * (128 / res) ** 2)))
        r = build(a.split, res, n, a.out, a.jobs, a.identities, a.data_root)
        print(f"{r['folder']}: {n} pairs, {r['bytes'] / 1e9:.2f} GB in {r['seconds']:.0f} s")


if __name__ == "__main__":
    main()
