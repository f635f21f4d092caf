"""Network-only speed per preset with onnxruntime on this machine: fp32 and static int8 (QDQ).

    .venv/bin/python -m bench.network_speed [--sizes 256 512] [--threads 2] [--no-int8]

Speed does not depend on the weight values, so each preset is exported fresh from
training/model/network.py (untrained) unless --models points at shipped models/<name>.onnx files.
int8 here is calibrated on random normalised images (enough for timing; shipped int8 models are
calibrated on light-stage frames by training/run/export.py). Writes bench/results/network_speed.md
and .json (--out).
"""

from __future__ import annotations

import argparse
import json
import pathlib
import sys
import tempfile

import numpy as np
import torch

from training.eval import report
from training.run import export
from training.model import network

ROOT = pathlib.Path(__file__).resolve().parents[1]


def _random_feeds(n: int, size: int, seed: int = 0) -> list[dict]:
    rng = np.random.default_rng(seed)
    return [{"image": (rng.random((1, 3, size, size)) * 1.2).astype(np.float32),
             "target_light": rng.random((1, 3, 16, 16)).astype(np.float32)} for _ in range(n)]


def bench(presets, sizes, threads: int, repeats: int, int8: bool, folder: pathlib.Path) -> list:
    rows = []
    for preset in presets:
        net = network.build(preset).eval()
        fp32 = export.export_onnx(net, folder / f"{preset}.onnx")
        variants = [("fp32", fp32)]
        if int8:
            q = export.quantize_int8(fp32, folder / f"{preset}-int8.onnx", _random_feeds(8, 256))
            variants.append(("int8", q))
        for precision, path in variants:
            cost = export.measure_cost(path, sizes, threads, repeats)
            for size in sizes:
                r = cost["per_size"][str(size)]
                rows.append({"preset": preset, "precision": precision, "size": size,
                             "ms": r["ms"], "fps": r["fps"], "provider": cost["provider"],
                             "threads": threads,
                             "gflop": round(network.count_flops(net, size, size) / 1e9, 3),
                             "mb": round(path.stat().st_size / 1e6, 2)})
                print(json.dumps(rows[-1]), flush=True)
    return rows


def table(rows) -> str:
    lines = ["| preset | precision | size | GFLOP | ms/frame | frames/s | ONNX MB |",
             "| --- | --- | --- | --- | --- | --- | --- |"]
    lines += [f"| {r['preset']} | {r['precision']} | {r['size']} | {r['gflop']} | {r['ms']} | "
              f"{r['fps']} | {r['mb']} |" for r in rows]
    return "\n".join(lines)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--presets", nargs="+", default=list(network.PRESETS))
    p.add_argument("--sizes", nargs="+", type=int, default=[256, 512])
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--repeats", type=int, default=30)
    p.add_argument("--no-int8", action="store_true")
    p.add_argument("--out", default=str(ROOT / "bench" / "results" / "network_speed"),
                   help="write OUT.md and OUT.json")
    a = p.parse_args(argv)
    torch.set_num_threads(1)
    with tempfile.TemporaryDirectory() as tmp:
        rows = bench(a.presets, a.sizes, a.threads, a.repeats, not a.no_int8, pathlib.Path(tmp))
    print(table(rows))
    m = report.machine()
    command = "python -m bench.network_speed " + " ".join(sys.argv[1:] if argv is None else argv)
    body = ("onnxruntime, batch 1, each preset's architecture exported untrained (weights do not "
            f"change the cost), {a.threads} thread(s); median of {a.repeats} runs.\n\n" + table(rows))
    report.write(a.out, "Network speed per preset", command, report.machine_line(m), body,
                 {"machine": m, "rows": rows})


if __name__ == "__main__":
    main()
