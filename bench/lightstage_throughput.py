"""Light-stage throughput per stage, and the 'simulate only what the scene calls for' shortcut.

    .venv/bin/python bench/lightstage_throughput.py [--res 128 256] [--samples 6] [--threads 1]

Prints milliseconds per stage (pose, G-buffer, materials, shadow maps + visibility + BRDF transfer,
shading of one light vector, flow), whole samples per second through LightStageDataset rendered on
the fly and read from the frame cache (training/data/build_cache.py: stages read pair, lighting
triplet, relight + assemble), and for the selective shading: the error against the full 114-light
sum and the time saved, at several energy thresholds. The cache of ``--cache`` is used where it
holds the resolution; otherwise a small one (8 pairs) is built in a temporary folder (the cost per
sample does not depend on the pool size once the files are in the page cache).
"""

from __future__ import annotations

import argparse
import os
import pathlib
import sys
import tempfile
import time

import numpy as np
import torch

ROOT = pathlib.Path(__file__).resolve().parents[1]
if __package__ in (None, ""):  # run as a script: make the repository importable
    sys.path.insert(0, str(ROOT))

from addon.errors import InputError  # noqa: E402
from training.eval import report  # noqa: E402
from training.data import lighting_sampling  # noqa: E402
from training.data.build_cache import DEFAULT_OUT, build  # noqa: E402
from training.data.dataset import LightStageDataset  # noqa: E402
from training.lightstage import geometry, materials, pairs  # noqa: E402


def _ms(fn, reps=1):
    t = time.perf_counter()
    for _ in range(reps):
        out = fn()
    return (time.perf_counter() - t) * 1000.0 / reps, out


def stages(ds: LightStageDataset, n: int) -> dict:
    rows = {k: [] for k in ("pose", "gbuffer", "materials", "shadows+transfer", "shade 1 light",
                            "flow")}
    for i in range(n):
        scene, t, (li, lj, lk) = ds.scene_for(i)
        ms, posed = _ms(lambda: scene.pose(t))
        rows["pose"].append(ms)
        ms, gb = _ms(lambda: geometry.gbuffer(posed, scene.rig, scene.cam, scene.attrs))
        rows["gbuffer"].append(ms)
        f = scene.frame(t, with_transfer=False)
        mat = f.gb.material.reshape(-1)[f.idx]
        uv = f.gb.uv.reshape(-1, 2)[f.idx]
        at = f.gb.attrs.reshape(-1, f.gb.attrs.shape[-1])[f.idx]
        ms, _ = _ms(lambda: materials.surface(mat, uv, at, scene.ident))
        rows["materials"].append(ms)
        ms, f.transfer = _ms(lambda: scene.transfer(f, f.f0, f.rough))
        rows["shadows+transfer"].append(ms)
        ms, _ = _ms(lambda: scene.shade(f, [lk]), reps=3)
        rows["shade 1 light"].append(ms)
        f1 = scene.frame(t + 0.04, with_transfer=False)
        ms, _ = _ms(lambda: scene.flow(f, f1))
        rows["flow"].append(ms)
    return {k: float(np.median(v)) for k, v in rows.items()}


def cached(res: int, n: int, cache_dir) -> dict:
    """Median ms per stage and samples/s of the cached dataset."""
    tmp = None
    try:
        ds = LightStageDataset("train", res, seed=123, length=100_000, cache_dir=cache_dir)
    except InputError:  # absent or still being built
        tmp = tempfile.TemporaryDirectory()
        build("train", res, 8, tmp.name, progress=None)
        ds = LightStageDataset("train", res, seed=123, length=100_000, cache_dir=tmp.name)
    try:
        ds[0]
        rows = {"read pair": [], "lighting triplet": [], "relight + assemble": []}
        for i in range(n):
            p, rng = ds.draw(i)
            ms, rec = _ms(lambda: pairs.load(pairs.pair_path(ds.cache, p)))
            rows["read pair"].append(ms)
            ms, lights = _ms(lambda: lighting_sampling.sample_triplet(rng, ds.bank, True,
                                                                     ds.hdri_pool))
            rows["lighting triplet"].append(ms)
            ms, _ = _ms(lambda: pairs.assemble(rec, lights, 9))
            rows["relight + assemble"].append(ms)
        out = {k: float(np.median(v)) for k, v in rows.items()}
        t, cpu = time.perf_counter(), time.process_time()
        for i in range(n):
            ds[1000 + i]
        out["whole sample"] = (time.perf_counter() - t) * 1000.0 / n
        # CPU time: what the sample costs whatever else the shared machine is running
        out["cpu per sample"] = (time.process_time() - cpu) * 1000.0 / n
        out["pool"] = ds.pool
        out["source"] = "temporary 8-pair cache" if tmp else str(ds.cache)
        return out
    finally:
        if tmp:
            tmp.cleanup()


def selective(ds: LightStageDataset, n: int, energies=(0.99, 0.95, 0.9, 0.8)) -> list:
    out = []
    for e in energies:
        errs, lights, t_full, t_sel = [], [], [], []
        for i in range(n):
            scene, t, (li, lj, lk) = ds.scene_for(i)
            f = scene.frame(t, with_transfer=False)
            ms_full, full = _ms(lambda: (setattr(f, "transfer", scene.transfer(f, f.f0, f.rough)),
                                         scene.shade(f, [lk]))[1])
            ms_sel, (fast, used) = _ms(lambda: scene.shade_selective(f, [lk], e))
            m = f.gb.mask
            d = (fast - full)[0][:, m]
            ref = full[0][:, m]
            errs.append(float(torch.sqrt((d ** 2).mean()) / ref.mean().clamp(min=1e-12)))
            lights.append(used)
            t_full.append(ms_full)
            t_sel.append(ms_sel)
        out.append((e, float(np.mean(lights)), float(np.mean(errs)), float(np.max(errs)),
                    float(np.median(t_full)), float(np.median(t_sel))))
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--res", type=int, nargs="+", default=[128, 256])
    ap.add_argument("--samples", type=int, default=6)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--cache", default=str(DEFAULT_OUT), help="frame cache root")
    ap.add_argument("--cached-samples", type=int, default=200)
    ap.add_argument("--no-selective", action="store_true", help="skip the effect shortcut")
    ap.add_argument("--report", default=str(ROOT / "bench" / "results" / "lightstage_throughput"),
                    help="write REPORT.md with the printed figures")
    a = ap.parse_args(argv)
    print = report.Lines()  # noqa: A001 - to stdout and to the report
    torch.set_num_threads(a.threads)
    load = " ".join(f"{x:.1f}" for x in os.getloadavg())
    print(f"torch threads: {a.threads}; load average {load}")
    for res in a.res:
        ds = LightStageDataset("train", res, seed=123, length=10_000)
        ds[0]  # warm the caches (head model, rigs, HDRI bank)
        st = stages(ds, a.samples)
        print(f"\n== {res}x{res}: median ms per frame and stage")
        for k, v in st.items():
            print(f"  {k:18s} {v:8.1f}")
        t, cpu = time.perf_counter(), time.process_time()
        for i in range(a.samples):
            ds[100 + i]
        dt = (time.perf_counter() - t) / a.samples
        dc = (time.process_time() - cpu) / a.samples
        print(f"  whole sample (2 frames, 4 images, flows): {dt * 1000:.0f} ms = "
              f"{1 / dt:.2f} samples/s (CPU {dc * 1000:.0f} ms = {1 / dc:.2f} samples/s per "
              "core)")
        c = cached(res, a.cached_samples, a.cache)
        print(f"\n  from the frame cache ({c['source']}, pool {c['pool']}): median ms per sample")
        for k in ("read pair", "lighting triplet", "relight + assemble"):
            print(f"  {k:18s} {c[k]:8.2f}")
        print(f"  whole sample: {c['whole sample']:.1f} ms = {1000 / c['whole sample']:.1f} "
              f"samples/s (CPU {c['cpu per sample']:.1f} ms = "
              f"{1000 / c['cpu per sample']:.1f} samples/s per core)")
        if a.no_selective:
            continue
        print(f"\n  selective shading vs the full 114-light sum (L^k of {a.samples} samples):")
        print("  energy  lights  rel.RMSE(mean)  rel.RMSE(max)  full ms  selective ms  saved")
        for e, n, em, ex, tf, ts in selective(ds, a.samples):
            print(f"  {e:5.2f}  {n:6.1f}  {em:14.4f}  {ex:13.4f}  {tf:7.1f}  {ts:12.1f}  "
                  f"{100 * (1 - ts / tf):4.0f}%")
    command = ("python bench/lightstage_throughput.py "
               + " ".join(sys.argv[1:] if argv is None else argv)).strip()
    report.write(a.report, "Light-stage throughput and the selective-effects shortcut", command,
                 report.machine_line(report.machine()), __doc__.split("\n\n", 2)[2].strip()
                 + "\n\n```\n" + print.text() + "\n```")


if __name__ == "__main__":
    main()
