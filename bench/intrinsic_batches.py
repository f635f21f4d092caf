"""What one training batch of the intrinsic model costs to make, with frames read from the disk
cache per sample (``train.py --workers N``) and kept in memory with their targets
(``--preload``), one thread.

    .venv/bin/python -m bench.intrinsic_batches [--cache cache/intrinsic-long] [--batch 24]

On a GPU the workers making batches, not the network, set the rate (training/README.md), so
the milliseconds per batch here are a worker's share of a step. Both ways make the same batches
(``step_batch`` is a pure function of the seed and the step); the bench checks that too. With
no ``--cache`` holding frames, a small cache of 16 frames is built in a temporary folder (the
shared data's heads and HDRIs are needed).
"""

from __future__ import annotations

import argparse
import pathlib
import statistics
import tempfile
import time

import torch

from training.intrinsic import data, train

from .intrinsic_effects import write_report

ROOT = pathlib.Path(__file__).resolve().parents[1]


def per_batch(ds, a, steps: int) -> tuple[float, list]:
    """Median seconds per batch over ``steps`` batches after one warm-up, and the batches."""
    train.step_batch(ds, a, 0)
    times, made = [], []
    for s in range(1, steps + 1):
        t = time.perf_counter()
        made.append(train.step_batch(ds, a, s))
        times.append(time.perf_counter() - t)
    return statistics.median(times), made


def measure(cache: pathlib.Path, batch: int, steps: int) -> dict:
    a = train.parser().parse_args(["--out", "unused", "--batch", str(batch),
                                   "--start-step", "60000"])
    disk = data.IntrinsicFrames("train", a.res, a.seed, cache, keep_frames=False)
    t_disk, from_disk = per_batch(disk, a, steps)
    kept = data.IntrinsicFrames("train", a.res, a.seed, cache)
    t0 = time.perf_counter()
    kept.preload(progress=None)
    t_load = time.perf_counter() - t0
    t_kept, from_memory = per_batch(kept, a, steps)
    same = all(torch.equal(x, y) for p, q in zip(from_disk, from_memory) for x, y in zip(p, q))
    return {"frames": disk.n, "batch": batch, "steps": steps, "same_batches": same,
            "ms_per_batch_disk": 1e3 * t_disk, "ms_per_batch_preloaded": 1e3 * t_kept,
            "speedup": t_disk / t_kept, "preload_s": t_load}


def markdown(res: dict, command: str, machine: str) -> str:
    return "\n".join([
        "# Intrinsic training batches: read per sample or preloaded", "",
        f"Command: `{command}`", "", f"Machine: {machine}", "",
        f"{res['frames']} cached frames, batch {res['batch']}, median of {res['steps']} batches "
        "(the same batches both ways: " + ("yes" if res["same_batches"] else "NO") + ").", "",
        "| frames | ms per batch | batches/s per worker |", "|---|---|---|",
        f"| read from the disk cache per sample (--workers) | {res['ms_per_batch_disk']:.0f} | "
        f"{1e3 / res['ms_per_batch_disk']:.2f} |",
        f"| preloaded with their targets (--preload) | {res['ms_per_batch_preloaded']:.0f} | "
        f"{1e3 / res['ms_per_batch_preloaded']:.2f} |", "",
        f"Speed-up {res['speedup']:.2f}x; preloading took {res['preload_s']:.0f} s.", ""])


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--cache", default=str(ROOT / "cache" / "intrinsic-long"))
    ap.add_argument("--batch", type=int, default=24)
    ap.add_argument("--steps", type=int, default=8)
    ap.add_argument("--out", default=str(ROOT / "bench" / "results" / "intrinsic_batches"))
    a = ap.parse_args(argv)
    torch.set_num_threads(1)
    cache = pathlib.Path(a.cache)
    with tempfile.TemporaryDirectory() as tmp:
        if not (data.folder_for(cache, "train", 128) / "manifest.json").is_file():
            cache = pathlib.Path(tmp)
            data.build("train", 128, 16, cache, progress=None)
        res = measure(cache, a.batch, a.steps)
    write_report(a.out, "intrinsic_batches", argv, res, markdown)


if __name__ == "__main__":
    main()
