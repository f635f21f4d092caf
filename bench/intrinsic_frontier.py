"""Portrait's accuracy/time frontier over its working size: real faces against time.

    .venv/bin/python -m bench.intrinsic_frontier [--sizes 96 128 160 192] [--threads 2]

The working size is the side of the square crop the network and the renderer see around the
portrait (the card's, or ``RelightOptions.working_size`` / ``relight_image(working_size=...)``).
For each size: accuracy on real faces, CroppedYale's held-out test subjects relit through
``addon.relight_image`` on training/eval/yale.py's pairs (the scale-invariant PSNR over all pairs,
as its table gives it, and the balance correlations with their intervals over resampled
subjects); and time on this machine: the network (the face crop's relighting passes,
portrait.face_buffers, the finer sampling's in a second thread as relight_frame runs it) plus
the renderer (key lamp) at that size, and a 1080p frame end to end
as bench/intrinsic_speed.py counts it (framing pass, relight_frame, blend, finish; decode and
write overlap in other threads). Every repeat times every size in turn, so the machine's load
falls on all of them alike. ``--write-card`` also records the card's
time per frame, the one the panel shows beside each preset (card_point). Writes
``bench/results/intrinsic_frontier.{md,json}``; ``--quick`` (two subjects, three pairs each,
two repeats) checks that it runs.
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import statistics
import sys
import time

import numpy as np

from addon import (api, blas, detail, intrinsic, lightvec, outline, pipeline, portrait,
                   temporal)
from training.eval import report, yale

from .intrinsic_speed import demo_frame, face_passes, frame_1080p, frame_ms

ROOT = pathlib.Path(__file__).resolve().parents[1]
SIZES = (96, 128, 160, 192)


def real_faces(model: str, size: int, threads: int, quick: bool) -> dict:
    """CroppedYale test subjects at working size ``size``: mean scale-invariant PSNR over the
    pairs and the balance correlations (yale.balance_correlation)."""
    root = yale.default_root()
    _, subjects = yale.select_subjects(yale.subject_names(root), quick)
    n_pairs = len(yale.KINDS) if quick else 12
    bank = yale.HdriBank(root.parents[1])
    relight = yale.PipelineRelighter(model, threads, working_size=size)
    psnr, rows = [], []
    for name in subjects:
        s = yale.load_subject(root, name)
        for a, b in yale.draw_pairs(s, n_pairs, 2021, bank):
            gt = yale.relit_sum(s, b.weights)
            y = relight(yale.relit_sum(s, a.weights), yale.light_vector(s.dirs, b.weights))
            mask = yale.face_mask(gt.shape, s, b.weights)
            psnr.append(yale.metrics(yale.ls_gain(y, gt, mask) * y, gt, mask)["psnr"])
            rows.append((a.kind, None, name, {"ground_truth": yale.balance(gt, mask),
                                              "model": yale.balance(y, mask)}))
    return {"psnr_scale_invariant": float(np.mean(psnr)), "pairs": len(psnr),
            "subjects": len(subjects), **yale.balance_correlation(rows)["model"]}


def frame_stages(sess, x: np.ndarray, lamp: np.ndarray, fullres, box=None) -> dict:
    """The per-frame path's stages on the (3, H, W) frame ``x`` as frame_ms counts them, each a
    callable: the framing pass following the frame's box (``box``, found here if not given),
    relight_frame, the finish with the outline's refit, the temporal blend."""
    box = portrait.find_box(sess, x, fullres) if box is None else box
    res = portrait.relight_frame(sess, x, lamp, box, fullres=fullres)
    return {
        "framing": lambda: portrait.find_box(sess, x, fullres, prior=box),
        "relight_frame": lambda: portrait.relight_frame(sess, x, lamp, box, fullres=fullres),
        "finish": lambda: outline.apply(res.outline, x, fullres.finish_planar(
            x, res.a, res.b, float(x.max()))[0], fullres=fullres),
        "blend": lambda: temporal.blend((res.a, res.b), (res.a, res.b), (res.a, res.b),
                                        mask=res.matte)}


def timings(model: str, sizes, threads: int, repeats: int) -> dict:
    """Median milliseconds per stage and size, the sizes timed in turn within each repeat."""
    x = frame_1080p()
    lamp = lightvec.splat_direction([0.8, 0.3, 0.5], [3, 3, 3]) + 0.05 * lightvec.uniform()
    fullres = detail.FullRes(threads=threads)
    jobs = {}
    for size in sizes:
        sess = api.session(model, threads, size)
        box = portrait.find_box(sess, x, fullres)
        crop, _ = portrait.crop_planar(x, box, size)
        bufs = portrait.buffers(sess, crop)
        jobs[size] = {
            # the face crop's relighting passes, as relight_frame makes them
            "network": lambda s=sess, b=box, n=size: face_passes(s, x, b, n),
            "renderer": lambda c=crop, b=bufs: intrinsic.shade(c, b, lamp),
            **frame_stages(sess, x, lamp, fullres, box)}
    times = {size: {k: [] for k in job} for size, job in jobs.items()}
    with blas.one_thread():  # as the product runs them (addon/blas.py)
        for rep in range(repeats + 1):
            for size, job in jobs.items():
                for k, fn in job.items():
                    t0 = time.perf_counter()
                    fn()
                    if rep:  # the first round warms up
                        times[size][k].append((time.perf_counter() - t0) * 1000)
    out = {}
    for size, stages in times.items():
        ms = {k: statistics.median(v) for k, v in stages.items()}
        frame = frame_ms(ms["framing"], ms["relight_frame"], ms["finish"], ms["blend"])
        out[size] = {"stages_ms": ms, "network_plus_renderer_fps": 1000 / (ms["network"]
                                                                         + ms["renderer"]),
                     "end_to_end_1080p_fps": 1000 / frame}
    return out


CARD_FRAME = 640  # bench/frontier.py times the end-to-end presets' cards on 640-px frames


def card_point(model: str, threads: int, repeats: int) -> dict:
    """The card's time per frame, as bench/frontier.py records the end-to-end presets': the
    per-frame path on a CARD_FRAME-px square frame (the demo's first frame enlarged) at the
    card's working size: the framing pass one frame in pipeline.FRAMING_STEP, relight_frame (key
    lamp), the finish with the outline's refit and the temporal blend; median and 10th-90th
    percentile over ``repeats`` rounds after a warm-up."""
    img = detail.resize(demo_frame(), CARD_FRAME, CARD_FRAME)
    x = np.ascontiguousarray(img.transpose(2, 0, 1), np.float32)
    lamp = lightvec.splat_direction([0.8, 0.3, 0.5], [3, 3, 3]) + 0.05 * lightvec.uniform()
    sess = api.session(model, threads)
    stages = frame_stages(sess, x, lamp, detail.FullRes(threads=threads))
    frames = []
    with blas.one_thread():  # as the product runs them
        for rep in range(repeats + 1):
            ms = {}
            for k, fn in stages.items():
                t0 = time.perf_counter()
                fn()
                ms[k] = (time.perf_counter() - t0) * 1000
            if rep:  # the first round warms up
                frames.append(frame_ms(ms["framing"], ms["relight_frame"], ms["finish"],
                                       ms["blend"]))
    return {"ms_per_frame": round(statistics.median(frames), 2),
            "p10_ms": round(float(np.percentile(frames, 10)), 2),
            "p90_ms": round(float(np.percentile(frames, 90)), 2), "runs": repeats,
            "working_size": sess.card.working_size, "full_size": CARD_FRAME,
            "provider": "CPUExecutionProvider", "threads": threads,
            "what": "per-frame path (the framing pass one frame in "
                    f"{pipeline.FRAMING_STEP}, relight_frame under a key lamp, the finish with "
                    "the outline's refit, the temporal blend; decoding and writing excluded) "
                    f"on a {CARD_FRAME}-px frame, as bench/frontier.py times the end-to-end "
                    "presets; the error the panel shows is the card's RMSE at the right level"}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--model", default=str(ROOT / "models" / "relight-portrait.onnx"))
    ap.add_argument("--sizes", type=int, nargs="+", default=list(SIZES))
    ap.add_argument("--threads", type=int, default=2, help="for the timings (accuracy: one)")
    ap.add_argument("--repeats", type=int, default=15)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--out", default=str(ROOT / "bench" / "results" / "intrinsic_frontier"))
    ap.add_argument("--write-card", action="store_true",
                    help=f"also record the card's time per frame (card_point: the per-frame path "
                         f"on {CARD_FRAME}-px frames), which the panel shows")
    a = ap.parse_args(argv)
    if not yale.default_root().is_dir():
        print(f"intrinsic_frontier: no CroppedYale at {yale.default_root()}; the accuracy half "
              "needs ../shared/data/yale (see ../shared/data/README.md).", file=sys.stderr)
        return 2
    card_size = api.session(a.model, 1).card.working_size
    load = os.getloadavg()[0]
    t0 = time.perf_counter()
    acc = {size: real_faces(a.model, size, 1, a.quick) for size in a.sizes}
    speed = timings(a.model, a.sizes, a.threads, 2 if a.quick else a.repeats)
    machine = (f"{report.cpu_name()}, {os.cpu_count()} cores, {a.threads} thread(s) for the "
               f"timings, load {load:.1f} before / {os.getloadavg()[0]:.1f} after")
    cmd = "python -m bench.intrinsic_frontier " + " ".join(argv if argv is not None
                                                           else sys.argv[1:])
    rows = {size: {**acc[size], **speed[size]} for size in a.sizes}
    some = rows[a.sizes[0]]
    lines = [f"Produced by `{cmd.strip()}` on {machine}; {time.perf_counter() - t0:.0f} s.", "",
             f"CroppedYale: {some['subjects']} held-out test subjects, {some['pairs']} pairs, "
             "relit through `addon.relight_image` (scale-invariant PSNR as in "
             "`bench/results/yale.md`; balance correlations with their 5th-95th percentile over "
             f"resampled subjects). The card's working size is {card_size}.", "",
             "| working size | scale-invariant PSNR (dB) | left/right | top/bottom | network + "
             "renderer (frames/s) | 1080p end to end (frames/s) | relight_frame at 1080p (ms) |",
             "| --- | --- | --- | --- | --- | --- | --- |"]
    for size, r in rows.items():
        lr, tb = r["left_right_90"], r["top_bottom_90"]
        lines.append(f"| {size}{' (card)' if size == card_size else ''} | "
                     f"{r['psnr_scale_invariant']:.2f} | {r['left_right']:.3f} ({lr[0]:.2f}-"
                     f"{lr[1]:.2f}) | {r['top_bottom']:.3f} ({tb[0]:.2f}-{tb[1]:.2f}) | "
                     f"{r['network_plus_renderer_fps']:.1f} | {r['end_to_end_1080p_fps']:.1f} | "
                     f"{r['stages_ms']['relight_frame']:.1f} |")
    if a.write_card:
        point = {**card_point(a.model, a.threads, 2 if a.quick else a.repeats),
                 "machine": machine, "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
                 "command": cmd}
        card_path = pathlib.Path(a.model).with_suffix(".json")
        card = json.loads(card_path.read_text())
        card["frontier"] = point
        card_path.write_text(json.dumps(card, indent=2) + "\n")
        lines += ["", f"The card's time per frame (`--write-card`, written to {card_path.name}): "
                  f"{point['ms_per_frame']:.1f} ms ({point['p10_ms']:.1f}-{point['p90_ms']:.1f}) "
                  f"on {CARD_FRAME}-px frames at {point['working_size']} px, "
                  f"{point['threads']} thread(s)."]
    md = "\n".join(lines) + "\n"
    print(md)
    pathlib.Path(a.out + ".md").write_text(md)
    pathlib.Path(a.out + ".json").write_text(json.dumps(
        {"command": cmd, "machine": machine, "card_working_size": card_size,
         "sizes": {str(k): v for k, v in rows.items()}}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
