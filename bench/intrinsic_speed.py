"""Speed of the intrinsic presets: network and renderer at the working size, and a 1080p frame
end to end (framing pass, relighting, the temporal blend, full-resolution finish).

    .venv/bin/python -m bench.intrinsic_speed [--model models/relight-portrait.onnx] [--threads 2]

The frame is the built-in demo clip's first frame (our own render) enlarged into a 1920x1080
canvas, the portrait off-centre as in a wide shot. Each stage runs ``--repeats`` times after two
warm-up runs; the table gives the median milliseconds and the frames per second it allows.
Lights: a key lamp (one compact component: shadows and highlights are computed) and a soft
uniform world (none: diffuse only); the key lamp's penumbra is timed alone too, beside the
plain blur it replaces. The stages run as the product runs them, numpy's BLAS on one
thread (addon/blas.py); relight_frame (and the clip below) also run with it left on its own
threads, for comparison. relight_frame runs the face crop's finer sampling in a second
thread (portrait.PARALLEL_PASSES); its passes one after another are timed too (the face crop's,
relight_frame, and with ``--clip`` the clip), for comparison. The end-to-end figure counts the
framing pass a run makes (it follows the last framed frame's box, find_box's ``prior``); the
whole-frame search it falls back to is listed too. ``--clip N`` also runs the whole product
path on an N-frame 1080p H.264 clip of the demo's frames in the same canvas
(addon.pipeline.relight_clip: framing pass, exposure, decode, relighting, finish and
half-float EXR writing, its threads overlapping as they do for an artist) and reports the
frames per second after warm-up and the CPU time a frame takes over all threads. Writes
``bench/results/intrinsic_speed.{md,json}``.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import os
import pathlib
import statistics
import time

import numpy as np

from addon import (api, blas, colour, detail, facetemplate, intrinsic, lightvec, outline, pipeline,
                   portrait, temporal)
from training.eval import report
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


def in_canvas(img: np.ndarray) -> np.ndarray:
    """(1080, 1920, 3): a demo frame (H, W, 3) enlarged to 640x640, off-centre in a canvas of
    its corner's colour, as a portrait in a wide shot."""
    face = detail.resize(img.astype(np.float32), 640, 640)
    canvas = np.broadcast_to(face[:8, :8].mean((0, 1)), (1080, 1920, 3)).copy()
    canvas[220:860, 1100:1740] = face
    return canvas


def demo_frame() -> np.ndarray:
    """(H, W, 3) linear: the built-in demo clip's first frame (our own render)."""
    src = read_png(ROOT / "demo" / "frames" / "frame_0001.png").astype(np.float32) / 255.0
    return colour.srgb_to_linear(src)


def frame_1080p() -> np.ndarray:
    canvas = in_canvas(demo_frame())
    return np.ascontiguousarray(canvas.transpose(2, 0, 1), np.float32)


def write_clip(path: str, n: int) -> str:
    """An n-frame 1920x1080 H.264 clip: the demo's frames in_canvas, sRGB."""
    import av
    files = sorted((ROOT / "demo" / "frames").glob("frame_*.png"))
    with av.open(path, "w") as c:
        s = c.add_stream("libx264", rate=25)
        s.width, s.height, s.pix_fmt = 1920, 1080, "yuv420p"
        s.options = {"crf": "18", "preset": "ultrafast"}
        for i in range(n):
            src = read_png(files[i % len(files)]).astype(np.float32) / 255.0
            img = np.clip(in_canvas(src) * 255.0 + 0.5, 0, 255).astype(np.uint8)
            for p in s.encode(av.VideoFrame.from_ndarray(img, format="rgb24")):
                c.mux(p)
        for p in s.encode():
            c.mux(p)
    return path


def run_clip(model: str, threads: int, n: int) -> dict:
    """The product path on an n-frame 1080p clip: frames per second after warm-up (the median
    interval between written frames, the first fifth left out) and CPU seconds per frame."""
    import tempfile
    lamp = (lightvec.splat_direction([0.8, 0.3, 0.5], [3, 3, 3]) + 0.05 * lightvec.uniform())
    with tempfile.TemporaryDirectory(prefix="intrinsic_speed_") as tmp:
        path = write_clip(os.path.join(tmp, "clip.mp4"), n)
        clip = pipeline.ClipSpec("movie", path, (), 0, n, "sRGB", 25.0)
        opts = pipeline.RelightOptions(model, threads=threads)
        done = []

        def cpu() -> float:
            t = os.times()
            return t.user + t.system

        t0 = time.perf_counter()
        res = pipeline.relight_clip(clip, lamp[None], os.path.join(tmp, "run"), opts,
                                    on_progress=lambda d, total, msg: done.append(
                                        (d, time.perf_counter(), cpu())))
        wall = time.perf_counter() - t0
    stamps = [(d, t, c) for d, t, c in done if d > 0]
    steady = stamps[len(stamps) // 5:]
    gaps = np.diff([t for _, t, _ in steady])
    (d0, _, c0), (d1, _, c1) = steady[0], steady[-1]
    return {"frames": res.written, "wall_s": wall,
            "fps_after_warm_up": float(1.0 / np.median(gaps)),
            "cpu_ms_per_frame": float(1000 * (c1 - c0) / max(d1 - d0, 1))}


def frame_ms(framing: float, relight: float, finish: float, blend: float) -> float:
    """A 1080p frame end to end from its stages' milliseconds: the framing pass a run makes
    for one frame in pipeline.FRAMING_STEP, relight_frame, the finish (with the outline's refit,
    addon.outline.apply) and the temporal blend (decode and write overlap in other threads)."""
    return framing / pipeline.FRAMING_STEP + relight + finish + blend


# What the network costs a relit frame: every pass relight_frame makes on the face crop, as it
# makes them (the finer sampling's in a second thread: portrait.PARALLEL_PASSES).
FACE_ROW = ("network, the face crop's relighting passes (portrait.face_buffers: the crop "
            "and its mirror image, the finer sampling and its mirror image)")
SEQUENTIAL = ", the passes one after another (comparison)"


def face_passes(sess, x: np.ndarray, box, size: int):
    """portrait.face_buffers as relight_frame runs it: the finer sampling's pass handed to the
    second thread first (portrait.finer_pass)."""
    return portrait.face_buffers(sess, x, box, size,
                                 finer=portrait.finer_pass(sess, x, box, size))


@contextlib.contextmanager
def sequential():
    """relight_frame with its network passes one after another (for comparison)."""
    was = portrait.PARALLEL_PASSES
    portrait.PARALLEL_PASSES = False
    try:
        yield
    finally:
        portrait.PARALLEL_PASSES = was


def held_on_each(sess, x: np.ndarray, box, size: int) -> intrinsic.Buffers:
    """portrait.face_buffers with the face template held on the crop's pass and on the finer
    sampling's, then averaged, not once on their mean (for comparison)."""
    crop, valid = portrait.crop_planar(x, box, size)
    bufs = portrait.buffers(sess, crop, valid, mirror=portrait.MIRROR)
    finer = portrait.buffers(sess, *portrait.crop_planar(x, box, round(size * portrait.ZOOM)),
                             mirror=portrait.MIRROR, level=portrait.FINER_LEVEL)
    return dataclasses.replace(portrait.mean_buffers(bufs, portrait.shrunk(finer, size)),
                               albedo=bufs.albedo)


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
    # The same change on the grid the box's scale gives unsnapped (portrait.grid_shape without
    # detail.block_scale): the finish's slower general path, for comparison in the same run.
    f = size / box.size
    lh, lw = max(1, round(x.shape[1] * f)), max(1, round(x.shape[2] * f))
    loose = tuple(detail.resize(v.transpose(1, 2, 0), lh, lw).transpose(2, 0, 1).copy()
                  for v in (res.a, res.b))
    loose_row = f"full-resolution finish at 1080p from an unsnapped {lh}x{lw} grid (comparison)"
    framing_row = (f"framing pass following the last box (a run frames one frame in "
                   f"{pipeline.FRAMING_STEP})")
    search_row = "framing pass searching the whole frame (a run's first frame, a lost portrait)"
    blend_row = f"temporal blend with two neighbours ({res.a.shape[1]}x{res.a.shape[2]} grid)"
    outline_row = "outline refit at 1080p (the fade's pixels, after the finish)"
    y = fullres.finish_planar(x, res.a, res.b, float(x.max()))[0]  # refitted in place, repeatedly
    # As the product runs them: relight_frame and relight_clip hold numpy's BLAS to one thread.
    with blas.one_thread():
        rows = {
            f"network, {size} px crop (a framing pass)": timed(lambda: sess.run_planar(crop),
                                                               repeats),
            f"network, {size} px crop and its mirror in one batch (a relighting pass)": timed(
                lambda: sess.run_planar(crop, mirror=portrait.MIRROR), repeats),
            FACE_ROW: timed(lambda: face_passes(sess, x, box, size), repeats),
            FACE_ROW + SEQUENTIAL: timed(lambda: portrait.face_buffers(sess, x, box, size),
                                         repeats),
            FACE_ROW + ", one after another, the face template held on each pass before the "
                       "mean (comparison)":
                timed(lambda: held_on_each(sess, x, box, size), repeats),
            "renderer, key lamp (diffuse + shadow + highlight)":
                timed(lambda: intrinsic.shade(crop, bufs, lamp), repeats),
        }
        # The key lamp's penumbra alone, the pixels turned from it filled from the asked ones
        # (as shade runs it), and the plain blur beside it: what the fill costs.
        comp = intrinsic.plan(lamp).components[0]
        lam = intrinsic.lobe(np.tensordot(comp.direction, bufs.normal, axes=(0, 0)),
                             intrinsic.hair_share(bufs))
        vis, dist = intrinsic.shadow(bufs.height / intrinsic.height_scale(bufs), bufs.matte,
                                     comp.direction, lit=lam, distance=True)
        turned = intrinsic.marched(bufs.matte) & ~intrinsic.marched(bufs.matte, lam)
        fill_row = "penumbra, key lamp (the pixels turned from it filled from their neighbours)"
        rows[fill_row] = timed(lambda: intrinsic.penumbra(vis, dist, turned), repeats)
        rows["penumbra, key lamp, the plain blur (comparison)"] = timed(
            lambda: intrinsic.penumbra(vis, dist), repeats)
        # Blurs as the subsurface diffusion runs them (a value and its weight), each way
        # gaussian_blur has (its taps up to TAPS_RADIUS, the matrix products by bands beyond)
        # and by the whole matrix products: at radius 2, at TAPS_RADIUS and one beyond it.
        pair = np.stack([bufs.matte, bufs.face])
        h, w = pair.shape[1:]
        ways = {"its taps": intrinsic.tap_blur, "matrices by bands": intrinsic.banded_blur}
        for r in (2, intrinsic.TAPS_RADIUS, intrinsic.TAPS_RADIUS + 1):
            sigma = (r - 0.5) / 3.0
            label = f"blur, sigma {sigma:.2f} px (radius {r}), two planes"
            chosen = "its taps" if r <= intrinsic.TAPS_RADIUS else "matrices by bands"
            for way, fn in ways.items():
                rows[f"{label}, {way}" + ("" if way == chosen else " (comparison)")] = timed(
                    lambda: fn(pair, sigma), repeats)
            rows[f"{label}, whole matrices (comparison)"] = timed(
                lambda: intrinsic.blur_matrix(h, sigma) @ pair
                @ intrinsic.blur_matrix(w, sigma).T, repeats)
        # The face template's low band on the crop (facetemplate.held takes it every frame), the
        # blur taken into the template's bilinear weights, and laid on the crop then blurred.
        template = facetemplate.cached(facetemplate.SHIPPED)
        frame = facetemplate.skin_frame(bufs.face, bufs.matte)
        if frame is not None:
            rows["face template's low band on the crop (blur taken into its weights)"] = timed(
                lambda: facetemplate.laid_low(template, frame, (h, w), facetemplate.SIGMA),
                repeats)
            rows["face template's low band on the crop, laid then blurred (comparison)"] = timed(
                lambda: intrinsic.gaussian_blur(facetemplate.laid(template, frame, (h, w))[0],
                                                facetemplate.SIGMA), repeats)
        # The coarse pass's change (ratio, highlight, weight, matte) enlarged to the grid, by
        # small blocks (detail.enlarge_planar where the ratio has them) and by whole matrices.
        coarse = np.zeros((8,) + detail.working_shape(*x.shape[1:], portrait.coarse_size(size)),
                          np.float32)
        gh, gw = res.a.shape[1:]
        enlarge_row = f"coarse change enlarged, {coarse.shape[1]}x{coarse.shape[2]} to {gh}x{gw}"
        rows[enlarge_row] = timed(lambda: detail.enlarge_planar(coarse, gh, gw), repeats)
        rows[enlarge_row + ", by whole matrices (comparison)"] = timed(
            lambda: detail.linear_matrix(coarse.shape[1], gh) @ coarse
            @ detail.linear_matrix(coarse.shape[2], gw).T, repeats)
        if bufs.transfer is not None:  # what the transfer's occlusion costs, in the same run
            plain = dataclasses.replace(bufs, transfer=None)
            rows["renderer, key lamp, the transfer left out (comparison)"] = timed(
                lambda: intrinsic.shade(crop, plain, lamp), repeats)
        rows |= {
            "renderer, soft world (diffuse only)":
                timed(lambda: intrinsic.shade(crop, bufs, soft), repeats),
            search_row: timed(lambda: portrait.find_box(sess, x, fullres), repeats),
            framing_row: timed(lambda: portrait.find_box(sess, x, fullres, prior=box), repeats),
            "relight_frame at 1080p (coarse + face passes, key lamp)": timed(
                lambda: portrait.relight_frame(sess, x, lamp, box, fullres=fullres), repeats),
        }
        with sequential():
            rows["relight_frame at 1080p" + SEQUENTIAL] = timed(
                lambda: portrait.relight_frame(sess, x, lamp, box, fullres=fullres), repeats)
        rows |= {
            "full-resolution finish at 1080p":
                timed(lambda: fullres.finish_planar(x, res.a, res.b, float(x.max())), repeats),
            outline_row: timed(lambda: outline.apply(res.outline, x, y, fullres=fullres), repeats),
            # The same without the two-colour model of the outline's pixels: what it costs.
            "outline refit at 1080p, the change on whole pixels (comparison)": timed(
                lambda: outline.apply(res.outline and dataclasses.replace(
                    res.outline, colours=None), x, y, fullres=fullres), repeats),
            loose_row: timed(lambda: fullres.finish_planar(x, *loose, float(x.max())), repeats),
            blend_row: timed(lambda: temporal.blend((res.a, res.b), (res.a, res.b), (res.a, res.b),
                                             mask=res.matte), repeats),
        }
    if max(blas.threads(), default=1) > 1:
        # relight_frame holds numpy's BLAS to one thread (addon/blas.py); without that:
        with blas.left_alone():
            rows[f"relight_frame at 1080p, numpy's BLAS left on its {max(blas.threads())} "
                 "threads (comparison)"] = timed(lambda: portrait.relight_frame(
                     sess, x, lamp, box, fullres=fullres), repeats)
    net_render = rows[FACE_ROW] + rows["renderer, key lamp (diffuse + shadow + highlight)"]
    end_to_end = frame_ms(rows[framing_row],
                          rows["relight_frame at 1080p (coarse + face passes, key lamp)"],
                          rows["full-resolution finish at 1080p"] + rows[outline_row],
                          rows[blend_row])
    return {"stages_ms": rows, "network_plus_renderer_fps": 1000 / net_render,
            "end_to_end_1080p_fps": 1000 / end_to_end, "threads": threads, "working_size": size,
            "decode_and_write": "not included (the pipeline overlaps them in other threads)"}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--model", default=str(ROOT / "models" / "relight-portrait.onnx"))
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=15)
    ap.add_argument("--clip", type=int, default=0,
                    help="also run the product path on a clip of this many 1080p frames")
    ap.add_argument("--out", default=str(ROOT / "bench" / "results" / "intrinsic_speed"))
    a = ap.parse_args(argv)
    load = os.getloadavg()[0]
    res = run(a.model, a.threads, a.repeats)
    if a.clip:
        res["clip"] = run_clip(a.model, a.threads, a.clip)
        with sequential():  # the same clip, each frame's network passes one after another
            res["clip_sequential"] = run_clip(a.model, a.threads, a.clip)
        if max(blas.threads(), default=1) > 1:
            with blas.left_alone():  # the same clip, numpy's BLAS left on its own threads
                res["clip_blas_left_alone"] = run_clip(a.model, a.threads, a.clip)
    machine = (f"{report.cpu_name()}, {os.cpu_count()} cores, {a.threads} thread(s), load "
               f"{load:.1f} before / {os.getloadavg()[0]:.1f} after")
    cmd = "python -m bench.intrinsic_speed " + " ".join(argv if argv is not None else
                                                         __import__("sys").argv[1:])
    lines = [f"Produced by `{cmd.strip()}` on {machine}.", "", "| stage | ms (median) | frames/s |",
             "| --- | --- | --- |"]
    lines += [f"| {k} | {v:.1f} | {1000 / v:.1f} |" for k, v in res["stages_ms"].items()]
    lines += ["", f"Network plus renderer at the working size (the face crop's passes, a key "
              f"lamp): {res['network_plus_renderer_fps']:.1f} frames/s; 1080p end to end "
              f"(framing, relighting, blend, finish; decode and write overlap in other "
              f"threads): {res['end_to_end_1080p_fps']:.1f} frames/s."]
    if "clip" in res:
        c = res["clip"]
        lines += ["", f"The product path on a {c['frames']}-frame 1080p clip (relight_clip: "
                  f"framing pass, exposure, decode, relighting, finish, half-float EXR writing, "
                  f"its threads overlapping): {c['fps_after_warm_up']:.1f} frames/s after warm-up, "
                  f"{c['cpu_ms_per_frame']:.0f} ms of CPU a frame over all threads "
                  f"({c['wall_s']:.1f} s in all, with the model's loading)."]
    if "clip_sequential" in res:
        c = res["clip_sequential"]
        lines += ["", f"The same with each frame's network passes one after another "
                  f"(comparison): {c['fps_after_warm_up']:.1f} frames/s after warm-up, "
                  f"{c['cpu_ms_per_frame']:.0f} ms of CPU a frame ({c['wall_s']:.1f} s in all)."]
    if "clip_blas_left_alone" in res:
        c = res["clip_blas_left_alone"]
        lines += ["", f"The same with numpy's BLAS left on its own {max(blas.threads())} threads "
                  f"(the product holds it to one, addon/blas.py; comparison): "
                  f"{c['fps_after_warm_up']:.1f} frames/s after warm-up, "
                  f"{c['cpu_ms_per_frame']:.0f} ms of CPU a frame ({c['wall_s']:.1f} s in all)."]
    md = "\n".join(lines) + "\n"
    print(md)
    pathlib.Path(a.out + ".md").write_text(md)
    pathlib.Path(a.out + ".json").write_text(json.dumps({"command": cmd, "machine": machine, **res},
                                                        indent=1) + "\n")


if __name__ == "__main__":
    main()
