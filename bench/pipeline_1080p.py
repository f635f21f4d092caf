"""Time the per-frame pipeline on a synthetic 1080p clip, stage by stage and end to end.

    .venv/bin/python -m bench.pipeline_1080p [--frames 40] [--threads 1] [--gflops 5]
    .venv/bin/python -m bench.pipeline_1080p --exr-options     # EXR compressions only
    .venv/bin/python -m bench.pipeline_1080p --graph-options   # full-res graph variants only
    .venv/bin/python -m bench.pipeline_1080p --colour-options  # fast colour paths vs OpenColorIO

Makes a 1920x1080 H.264 clip (yuv420p, textured moving gradient) and a random-weight conv model
of about --gflops GFLOP per 512x512 frame (tests/onnx_fixtures.py) in a temporary folder, then
1. times each stage alone, one frame at a time (median and spread over the frames): decode,
   colour (to linear, exposure), resize (to the working size), inference (onnxruntime, incl.
   padding), full-resolution transfer (detail.py, incl. the matte and, for --background
   keep/relit, the composite over the footage's own background, folded into the coefficients),
   write (half EXR);
2. runs the real pipeline (relight_clip: decode and write overlap inference in threads) and
   reports frames per second from the per-frame completion times, and the process CPU time
   per frame (user + system, all threads): on a shared machine the frame rate follows the
   other processes' load, the CPU time much less so; with N free cores the pipeline can run at
   most N / (CPU time per frame) frames per second.
Prints the machine and the load average (before and after) it ran under, and writes the same
report to bench/results/pipeline_1080p.md (--out; the option runs only print).
"""

from __future__ import annotations

import argparse
import os
import pathlib
import platform
import statistics
import sys
import tempfile
import time

import numpy as np

from addon import engine, frames, lightvec, pipeline
from addon import colour as colour_mod
from tests.onnx_fixtures import write_conv_model
from training.eval import report

ROOT = pathlib.Path(__file__).resolve().parents[1]


def make_clip(path: str, n: int, width: int = 1920, height: int = 1080, fps: int = 25) -> str:
    import av
    rng = np.random.default_rng(0)
    y, x = np.mgrid[0:height, 0:width].astype(np.float32)
    tex = rng.integers(-12, 13, size=(height, width, 3)).astype(np.float32)
    with av.open(path, "w") as c:
        s = c.add_stream("libx264", rate=fps)
        s.width, s.height, s.pix_fmt = width, height, "yuv420p"
        s.options = {"crf": "18", "preset": "ultrafast", "g": "25"}
        for i in range(n):
            base = 60 + 80 * np.sin((x + 12 * i) / 300.0) * np.cos(y / 200.0)
            img = np.clip(base[..., None] * np.float32([1.0, 0.8, 0.7]) + 90 + tex, 0, 255)
            for p in s.encode(av.VideoFrame.from_ndarray(img.astype(np.uint8), format="rgb24")):
                c.mux(p)
        for p in s.encode():
            c.mux(p)
    return path


def stats(ms: list[float]) -> str:
    q = np.percentile(ms, [10, 50, 90])
    return f"median {q[1]:7.1f} ms  (p10 {q[0]:.1f}, p90 {q[2]:.1f})"


def time_stages(clip: pipeline.ClipSpec, session, fullres, plan: pipeline.Plan, light,
                out_dir: str, n: int) -> dict[str, list[float]]:
    keys = ("decode", "colour", "resize", "inference", "transfer", "write")
    t = {k: [] for k in keys}
    it = frames.iter_frames(clip.kind, clip.path, clip.files, range(n), plan.size, planar=True)
    for i in range(n):
        a = time.perf_counter()
        d = next(it)
        b = time.perf_counter()
        x_full, _, x_max = pipeline.linearise(d.pixels, plan)
        c = time.perf_counter()
        x_low = pipeline.shrink_planar(x_full, plan, fullres)
        e = time.perf_counter()
        relit_low, source, fg, k = pipeline.infer_planar(session, x_low, light)
        f = time.perf_counter()
        ab = pipeline.coefficients_planar(x_low, relit_low, k, plan, fullres)
        ab = pipeline.with_background(ab, fg, light, source, plan)
        relit = pipeline.finish_planar(x_full, ab, x_max, fullres)[0]
        matte = pipeline.matte_full(fg, plan, fullres) if plan.write_matte else None
        g = time.perf_counter()
        pipeline.write_frame(out_dir, i, relit, matte, source, plan)
        h = time.perf_counter()
        for key, dt in zip(keys, (b - a, c - b, e - c, f - e, g - f, h - g)):
            t[key].append(1000 * dt)
    return t


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--threads", type=int, default=None, help="onnxruntime intra-op threads")
    ap.add_argument("--gflops", type=float, default=5.0)
    ap.add_argument("--working-size", type=int, default=512)
    ap.add_argument("--compression", default="none", choices=frames.COMPRESSIONS)
    ap.add_argument("--matte", action="store_true")
    ap.add_argument("--background", default=pipeline.DEFAULT_BACKGROUND,
                    choices=pipeline.BACKGROUNDS, help="what stands behind the subject "
                    "(default: the product's default)")
    ap.add_argument("--no-detail", action="store_true")
    ap.add_argument("--exr-options", action="store_true",
                    help="only time the EXR compressions on one relit-like 1080p frame")
    ap.add_argument("--colour-options", action="store_true",
                    help="only time the hand-written colour paths against OpenColorIO's")
    ap.add_argument("--graph-options", action="store_true",
                    help="only time the full-resolution graphs against their resize-op variants")
    ap.add_argument("--out", default=str(ROOT / "bench" / "results" / "pipeline_1080p"),
                    help="write OUT.md (the end-to-end run only)")
    args = ap.parse_args(argv)
    n = args.frames
    print = report.Lines()  # noqa: A001 - to stdout and to the report
    print(f"machine: {report.cpu_name()}, {os.cpu_count()} cores, "
          f"python {platform.python_version()}, load average {os.getloadavg()[0]:.1f} "
          "(other processes share these cores: compare runs at similar load)")
    with tempfile.TemporaryDirectory(prefix="relight_bench_") as tmp:
        if args.exr_options:
            return exr_options(tmp)
        if args.graph_options:
            return graph_options()
        if args.colour_options:
            return colour_options()
        model = write_conv_model(tmp, gflops_at_512=args.gflops, name="bench")
        card = engine.load_card(model)
        arch = card.data["architecture"]
        print(f"model: {arch['gflop_per_frame']['512']} GFLOP at 512x512 "
              f"(width {arch['width']}), working size {args.working_size}, "
              f"background {args.background}")
        t0 = time.perf_counter()
        path = make_clip(os.path.join(tmp, "clip.mp4"), n)
        print(f"clip: 1920x1080 H.264, {n} frames (made in {time.perf_counter() - t0:.1f} s)")
        clip = pipeline.ClipSpec("movie", path, (), 0, n, "sRGB", 25.0)
        opts = pipeline.RelightOptions(str(model), working_size=args.working_size,
                                       detail_transfer=not args.no_detail,
                                       write_matte=args.matte, threads=args.threads,
                                       exr_compression=args.compression,
                                       background=args.background)
        light = lightvec.splat_direction([0.5, 0.4, 1.0], [3.0, 2.5, 2.0]) + 0.2
        session = engine.new_session(model, threads=args.threads, spin=False)
        fullres = pipeline.detail.FullRes(threads=1)
        plan = pipeline.Plan(colour_mod.lookup("sRGB"), 1.0, (1920, 1080),
                             pipeline.detail.working_shape(1080, 1920, args.working_size),
                             opts.detail_transfer, opts.write_matte, args.compression,
                             background=args.background)
        stage_dir = os.path.join(tmp, "stages")
        for sub in ("relit", "matte", "source_light"):
            os.makedirs(os.path.join(stage_dir, sub))
        stages = time_stages(clip, session, fullres, plan, light, stage_dir, n)
        print("\nstages alone, one frame at a time (ms per frame):")
        total = 0.0
        for k, v in stages.items():
            total += statistics.median(v)
            print(f"  {k:10s} {stats(v)}")
        print(f"  {'sum':10s} median {total:7.1f} ms  -> {1000 / total:.1f} frames/s serial")

        done_at = []
        t0, c0 = time.perf_counter(), _cpu_seconds()
        res = pipeline.relight_clip(clip, light[None], os.path.join(tmp, "run"), opts,
                                    on_progress=lambda d, tot, m: done_at.append(
                                        (d, time.perf_counter(), _cpu_seconds())))
        wall = time.perf_counter() - t0
        stamps = [t for d, t, _ in done_at if d > 0]
        gaps = 1000 * np.diff(stamps) if len(stamps) > 2 else np.array([np.nan])
        print(f"\nend to end (relight_clip, threads overlap; includes exposure sampling and "
              f"model load): {res.written} frames in {wall:.2f} s = {res.written / wall:.1f} "
              f"frames/s")
        steady = gaps[len(gaps) // 5:] if len(gaps) > 10 else gaps
        print(f"  per-frame interval after warm-up: {stats(list(steady))} -> "
              f"{1000 / np.median(steady):.1f} frames/s")
        # CPU time over the frames after warm-up (the first fifth, as above, is left out)
        cpu = [(d, c) for d, _, c in done_at if d > 0]
        (d0, c0), (d1, c1) = cpu[len(cpu) // 5], cpu[-1]
        if d1 > d0:
            per = 1000 * (c1 - c0) / (d1 - d0)
            print(f"  CPU time per frame after warm-up (all threads, user + system): {per:.1f} ms"
                  f" -> at most {2000 / per:.1f} frames/s on 2 free cores")
    print(f"load average after: {os.getloadavg()[0]:.1f}")
    command = "python -m bench.pipeline_1080p " + " ".join(sys.argv[1:] if argv is None else argv)
    report.write(args.out, "The pipeline on 1080p footage, stage by stage and end to end",
                 command.strip(), report.machine_line(report.machine()),
                 "```\n" + print.text() + "\n```")
    return 0


def exr_options(tmp: str, repeats: int = 10) -> int:
    """Write time (wall and this thread's CPU) and size of each EXR compression for the bench
    clip's first frame, linearised to half (what the pipeline writes). The options take turns,
    so a stall of the file system hits them alike."""
    path = make_clip(os.path.join(tmp, "clip.mp4"), 1)
    d = next(frames.iter_frames("movie", path, (), [0], planar=True))
    y = colour_mod.to_linear_planar(d.pixels, colour_mod.lookup("sRGB")).astype(np.float16)
    hwc = np.ascontiguousarray(y.transpose(1, 2, 0))
    options = ("none", "none via OpenEXR") + frames.COMPRESSIONS[1:]
    wall, cpu, size = ({k: [] for k in options} for _ in range(3))
    for i in range(repeats):
        for comp in options:
            out = os.path.join(tmp, f"{comp}_{i}.exr".replace(" ", "_"))
            t, c = time.perf_counter(), time.thread_time()
            if comp == "none via OpenEXR":  # the same file through OpenEXR's frame buffer
                frames.write_exr(out, hwc)
            else:
                frames.write_exr_planes(out, y, comp)
            wall[comp].append(1000 * (time.perf_counter() - t))
            cpu[comp].append(1000 * (time.thread_time() - c))
            size[comp] = os.path.getsize(out)
    print(f"EXR write of one 1920x1080 half RGB frame, median of {repeats} (options in turn)")
    for comp in options:
        print(f"  {comp:16s} wall {statistics.median(wall[comp]):6.1f} ms  CPU "
              f"{statistics.median(cpu[comp]):6.1f} ms  {size[comp] / 1e6:5.1f} MB")
    print(f"load average after: {os.getloadavg()[0]:.1f}")
    return 0


def colour_options(repeats: int = 15) -> int:
    """One 1080p frame to scene linear, channels first: each hand-written fast path against
    OpenColorIO's processor for the same space (Blender's config), taking turns."""
    rng = np.random.default_rng(0)
    cases = {"sRGB, 8 bits": rng.integers(0, 256, (3, 1080, 1920)).astype(np.uint8),
             "Linear Rec.2020, half float": rng.random((3, 1080, 1920)).astype(np.float16)}
    path = colour_mod.config_path()
    times = {}
    for label, px in cases.items():
        name = label.split(",")[0]
        fast, ocio = colour_mod.lookup(name), colour_mod.ocio_space(name, path)
        for kind, space in (("fast path", fast), ("OpenColorIO", ocio)):
            times[(label, kind)] = []
        for _ in range(repeats):
            for kind, space in (("fast path", fast), ("OpenColorIO", ocio)):
                t = time.perf_counter()
                colour_mod.to_linear_planar(px, space)
                times[(label, kind)].append(1000 * (time.perf_counter() - t))
    print(f"to scene linear, one 1920x1080 frame, median of {repeats} (paths in turn)")
    for (label, kind), v in times.items():
        print(f"  {label:28s} {kind:12s} {statistics.median(v):6.1f} ms")
    return 0


def graph_options(repeats: int = 30) -> int:
    """The 1080p shrink and finish graphs (exact area / window-gather matrix products) against
    the resize-op graphs they replace for sizes with small-integer ratios; interleaved runs."""
    detail = pipeline.detail
    fr = detail.FullRes(threads=1)
    ort = engine.import_onnxruntime()
    so, cpu = engine.session_options(ort, 1, spin=False), ["CPUExecutionProvider"]
    resize_shrink = ort.InferenceSession(detail.shrink_graph(), so, providers=cpu)
    resize_finish = ort.InferenceSession(detail.finish_graph(False), so, providers=cpu)
    rng = np.random.default_rng(0)
    x = rng.random((1, 3, 1080, 1920), dtype=np.float32)
    a, b = (rng.random((3, 288, 512), dtype=np.float32) for _ in range(2))
    full = np.array([1, 3, 1080, 1920], np.int64)
    cases = {
        "shrink: area matrix products": lambda: fr.shrink_planar(x[0], 288, 512),
        "shrink: resize op (antialiased)": lambda: resize_shrink.run(
            None, {"x": x, "sizes": np.array([1, 3, 288, 512], np.int64)}),
        "finish: window gather + matrix products": lambda: fr.finish_planar(x[0], a, b, 1.0),
        "finish: resize op": lambda: resize_finish.run(
            None, {"a": a[None], "b": b[None], "x": x, "sizes": full}),
    }
    times = {k: [] for k in cases}
    for _ in range(repeats):
        for k, f in cases.items():
            t = time.perf_counter()
            f()
            times[k].append(1000 * (time.perf_counter() - t))
    print(f"1080p graphs, one onnxruntime thread, {repeats} interleaved runs (ms):")
    for k, v in times.items():
        print(f"  {k:42s} {stats(v)}")
    print(f"load average after: {os.getloadavg()[0]:.1f}")
    return 0


def _cpu_seconds() -> float:
    t = os.times()
    return t.user + t.system


if __name__ == "__main__":
    sys.exit(main())
