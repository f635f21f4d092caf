"""Speed of the intrinsic presets: network and renderer at the working size, and a 1080p frame
end to end (framing pass, relighting, the temporal blend, full-resolution finish).

    .venv/bin/python -m bench.intrinsic_speed [--model models/relight-portrait.onnx] [--threads 2]

The frame is the built-in demo clip's first frame (our own render) enlarged into a 1920x1080
canvas, the portrait off-centre as in a wide shot. Each stage runs ``--repeats`` times after two
warm-up runs; the table gives the median milliseconds and the frames per second it allows.
Lights: a key lamp (one compact component: shadows and highlights are computed) and a soft
uniform world (none: diffuse only). The end-to-end figure counts the framing pass a run makes
(it follows the last framed frame's box, find_box's ``prior``); the whole-frame search it falls
back to is listed too. Writes ``bench/results/intrinsic_speed.{md,json}``.
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import platform
import statistics
import time

import numpy as np

from addon import api, colour, detail, intrinsic, lightvec, pipeline, portrait, temporal
from training.lightstage.png import read_png

ROOT = pathlib.Path(__file__).resolve().parents[1]


def timed(fn, repeats: int) -> float:
    for _ in range(2):
        fn()
    t = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        t.append(time.perf_counter() - t0)
    return statistics.median(t) * 1000


def frame_1080p() -> np.ndarray:
    src = read_png(ROOT / "demo" / "frames" / "frame_0001.png").astype(np.float32) / 255.0
    lin = colour.srgb_to_linear(src)
    face = detail.resize(lin.astype(np.float32), 640, 640)
    canvas = np.broadcast_to(face[:8, :8].mean((0, 1)), (1080, 1920, 3)).copy()
    canvas[220:860, 1100:1740] = face
    return np.ascontiguousarray(canvas.transpose(2, 0, 1), np.float32)


def run(model: str, threads: int, repeats: int) -> dict:
    sess = api.session(model, threads)
    size = sess.card.working_size
    x = frame_1080p()
    lamp = (lightvec.splat_direction([0.8, 0.3, 0.5], [3, 3, 3]) + 0.05 * lightvec.uniform())
    soft = lightvec.uniform()
    fullres = detail.FullRes(threads=threads)
    box = portrait.find_box(sess, x, fullres)
    crop, _ = portrait.crop_planar(x, box, size)
    bufs = portrait.buffers(sess, crop)
    res = portrait.relight_frame(sess, x, lamp, box, fullres=fullres)
    framing_row = (f"framing pass following the last box (a run frames one frame in "
                   f"{pipeline.FRAMING_STEP})")
    search_row = "framing pass searching the whole frame (a run's first frame, a lost portrait)"
    blend_row = f"temporal blend with two neighbours ({res.a.shape[1]}x{res.a.shape[2]} grid)"
    rows = {
        f"network, {size} px crop": timed(lambda: sess.run_planar(crop), repeats),
        "renderer, key lamp (diffuse + shadow + highlight)":
            timed(lambda: intrinsic.shade(crop, bufs, lamp), repeats),
        "renderer, soft world (diffuse only)": timed(lambda: intrinsic.shade(crop, bufs, soft), repeats),
        search_row: timed(lambda: portrait.find_box(sess, x, fullres), repeats),
        framing_row: timed(lambda: portrait.find_box(sess, x, fullres, prior=box), repeats),
        "relight_frame at 1080p (coarse + face passes, key lamp)":
            timed(lambda: portrait.relight_frame(sess, x, lamp, box, fullres=fullres), repeats),
        "full-resolution finish at 1080p":
            timed(lambda: fullres.finish_planar(x, res.a, res.b, float(x.max())), repeats),
        blend_row: timed(lambda: temporal.blend((res.a, res.b), (res.a, res.b), (res.a, res.b),
                                         mask=res.matte), repeats),
    }
    net_render = rows[f"network, {size} px crop"] + rows["renderer, key lamp (diffuse + shadow + highlight)"]
    end_to_end = (rows[framing_row] / pipeline.FRAMING_STEP
                  + rows["relight_frame at 1080p (coarse + face passes, key lamp)"]
                  + rows["full-resolution finish at 1080p"] + rows[blend_row])
    return {"stages_ms": rows, "network_plus_renderer_fps": 1000 / net_render,
            "end_to_end_1080p_fps": 1000 / end_to_end, "threads": threads, "working_size": size,
            "decode_and_write": "not included (the pipeline overlaps them in other threads)"}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--model", default=str(ROOT / "models" / "relight-portrait.onnx"))
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=15)
    ap.add_argument("--out", default=str(ROOT / "bench" / "results" / "intrinsic_speed"))
    a = ap.parse_args(argv)
    load = os.getloadavg()[0]
    res = run(a.model, a.threads, a.repeats)
    machine = (f"{platform.machine()} {os.cpu_count()}-core CPU, {a.threads} thread(s), load "
               f"{load:.1f} before / {os.getloadavg()[0]:.1f} after")
    cmd = "python -m bench.intrinsic_speed " + " ".join(argv if argv is not None else
                                                         __import__("sys").argv[1:])
    lines = [f"Produced by `{cmd.strip()}` on {machine}.", "", "| stage | ms (median) | frames/s |",
             "| --- | --- | --- |"]
    lines += [f"| {k} | {v:.1f} | {1000 / v:.1f} |" for k, v in res["stages_ms"].items()]
    lines += ["", f"Network plus renderer at the working size: {res['network_plus_renderer_fps']:.1f}"
              f" frames/s; 1080p end to end (framing, relighting, blend, finish; decode and write "
              f"overlap in other threads): {res['end_to_end_1080p_fps']:.1f} frames/s."]
    md = "\n".join(lines) + "\n"
    print(md)
    pathlib.Path(a.out + ".md").write_text(md)
    pathlib.Path(a.out + ".json").write_text(json.dumps({"command": cmd, "machine": machine, **res},
                                                        indent=1) + "\n")


if __name__ == "__main__":
    main()
