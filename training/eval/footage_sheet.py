"""Relight the real footage through the product pipeline and lay out contact sheets to look at.

    .venv/bin/python -m training.eval.footage_sheet [--models models/relight-draft.json ...]
        [--out out/footage] [--frames 24] [--clips d0 s18] [--lightings key-left ...]

Each clip of ``../shared/data/footage/*.mp4`` (first ``--frames`` frames) goes through
``addon.pipeline.relight_clip`` (the code path the Blender operator runs) under three HDRIs and two
lamp setups, into ``<out>/<clip>/<lighting>/<model>/``. Then:

* the console and ``<out>/sheet.json``: per run, the left/right balance of the middle frame
  (input and relit), its skin's chroma relit over input (skin_chroma), the hue the skin the
  light darkens takes (shadow_warmth), how much the background just beyond the subject's
  outline changed (outline_change: a dark halo shows as below 1) and the share of the frame the
  foreground matte covers (a matte that covers the room makes the kept background fall back to
  the network's);
* ``<out>/sheet.png``: one row per clip (and model), columns = the input and each lighting, the
  clip's middle frame; above each lighting column its light vector (16x16 latitude-longitude map:
  top = up, centre = toward the camera, right = the camera's right, both edges = behind).
* ``<out>/sequence.png``: per clip (and model), ``--seq-length`` consecutive frames around the
  middle under one lighting: input, relit, then |relit(t) - relit(t-1)| and the same for the input,
  both x4 (a flickering relight shows changes the input does not have).

Tiles are display-encoded with addon.colour's sRGB curve. Each run's relit frames share one
exposure, chosen so its middle frame's 90th-percentile luminance equals the input's: the sheet
shows light direction, colour and artefacts, not absolute brightness. The footage's provenance is
unknown: everything here is for local viewing only, never commit ``out/`` or publish the sheets.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import sys
import time
from dataclasses import dataclass

import numpy as np

from addon import colour, detail, frames, hdri, hdri_io, lamps, lightvec, normalise, pipeline
from addon.errors import InputError, RelightError

from ..lightstage.png import write_png

ROOT = pathlib.Path(__file__).resolve().parents[2]
DATA = ROOT.parent / "shared" / "data"
COLOURSPACE = "sRGB"  # what Blender assumes for a movie strip
SUBJECT_RADIUS = 0.15  # metres: the bridge's default head-sized subject

TILE = (320, 256)      # (width, height) box per tile on the main sheet; frames keep their aspect
SEQ_TILE = (256, 200)  # the same on the sequence sheet
HEADER_H = 72          # the light-vector row above the main sheet
PREVIEW = (128, 64)    # a light vector drawn 2:1, as the latitude-longitude map it is
GAP = 4
BACKGROUND = 24
DIFF_GAIN = 4.0


@dataclass(frozen=True)
class Lighting:
    name: str
    what: str                      # one line for the legend
    hdri: str | None = None        # path relative to the data root
    yaw: float = 0.0
    lamps: tuple = ()              # addon.lamps.Lamp, light frame, metres from the subject


def _point(position, color, energy) -> lamps.Lamp:
    return lamps.Lamp("POINT", position, (0.0, 0.0, -1.0), color, energy)


# Varied on purpose: a low warm sun (hard, directional), an overcast sky (soft, from above), a room
# lit by a window, one key lamp, and a coloured rim from behind (the front fill keeps the face
# from going black, as a photographer would).
LIGHTINGS = (
    Lighting("sun-warm", "blender/sunrise.exr: low warm sun, ~65 deg to the camera's right",
             hdri="hdri/blender/sunrise.exr"),
    Lighting("overcast", "pmndrs/city.exr: overcast street, soft light from the sky",
             hdri="hdri/pmndrs/city.exr"),
    Lighting("indoor", "pmndrs/apartment.exr: white room, window to the camera's right",
             hdri="hdri/pmndrs/apartment.exr"),
    Lighting("key-left", "one warm-white point lamp, camera-left, 45 deg up-front, 1.5 m",
             lamps=(_point((-1.0, 0.5, 1.0), (1.0, 0.93, 0.85), 1000.0),)),
    Lighting("key-white-left", "one white point lamp, camera-left, 45 deg up-front, 1.5 m (skin "
             "must keep its colour)", lamps=(_point((-1.0, 0.5, 1.0), (1.0, 1.0, 1.0), 1000.0),)),
    Lighting("key-white-right", "the same white lamp, camera-right",
             lamps=(_point((1.0, 0.5, 1.0), (1.0, 1.0, 1.0), 1000.0),)),
    Lighting("rim-blue", "blue point lamp behind the subject, up-right, + white fill at the "
             "camera (1/8 power)",
             lamps=(_point((0.8, 0.7, -1.1), (0.25, 0.5, 1.0), 2000.0),
                    _point((0.0, 0.0, 1.6), (1.0, 1.0, 1.0), 250.0))),
)


def light_vector(lighting: Lighting, data_root: pathlib.Path) -> np.ndarray:
    """The (16, 16, 3) light vector of a lighting: the product's own HDRI and lamp conversions."""
    if lighting.hdri:
        # Some Poly Haven maps hold a few slightly negative pixels; the add-on's "Repair HDRI".
        return hdri.downsample(hdri_io.read_hdri(data_root / lighting.hdri),
                               yaw_degrees=lighting.yaw, repair=True)
    light, _ = lamps.lamps_to_light(lighting.lamps, SUBJECT_RADIUS)
    return light


def clip_spec(path: pathlib.Path, count: int) -> pipeline.ClipSpec:
    info = pipeline.probe_clip(str(path))
    if info.frame_count < count:
        raise InputError(f"{path.name} has {info.frame_count} frames; ask for at most that many "
                         "with --frames.")
    return pipeline.ClipSpec("movie", str(path), (), 0, count, COLOURSPACE, info.fps)


@dataclass
class Run:
    clip: str
    lighting: str
    model: str
    out_dir: pathlib.Path
    frames: int
    written: int
    seconds: float
    steady_fps: float | None   # from the first finished frame to the last (no load, no probe)
    balance: tuple[float, float] = (float("nan"), float("nan"))  # (input, relit), see balance()
    matte_cover: float = float("nan")  # share of the middle frame the foreground matte covers
    chroma: tuple[float, float] = (float("nan"), float("nan"))  # skin_chroma (input, relit)
    outline: tuple[float, float] = (float("nan"), float("nan"))  # outline_change
    warmth: float = float("nan")  # shadow_warmth

    def fps_text(self) -> str:
        if not self.written:
            return "already done (resumed; no timing)"
        steady = f", {self.steady_fps:.1f} steady" if self.steady_fps else ""
        return (f"{self.written} frames in {self.seconds:.1f} s = {self.written / self.seconds:.1f}"
                f" fps incl. model load and exposure scan{steady}")


def relight(clip: pipeline.ClipSpec, light: np.ndarray, out_dir: pathlib.Path, model: pathlib.Path,
            threads: int, background: str,
            temporal: bool = True) -> tuple[int, float, float | None]:
    """Run the product pipeline; (frames written, wall seconds, steady-state fps)."""
    stamps: list[tuple[float, int]] = []
    # The matte is written to measure which side of the portrait the light falls on (balance).
    options = pipeline.RelightOptions(str(model), threads=threads, write_matte=True,
                                      overwrite=True, background=background,
                                      temporal=temporal)
    start = time.perf_counter()
    result = pipeline.relight_clip(clip, light[None], str(out_dir), options,
                                   on_progress=lambda done, total, _: stamps.append(
                                       (time.perf_counter(), done)))
    seconds = time.perf_counter() - start
    steady = None
    if len(stamps) >= 3 and stamps[-1][1] - stamps[1][1] >= 3:  # stamps[0]: the resumed count
        steady = (stamps[-1][1] - stamps[1][1]) / (stamps[-1][0] - stamps[1][0])
    return result.written, seconds, steady


# ---- pictures ---------------------------------------------------------------------------------

def input_frames(clip: pipeline.ClipSpec, indices) -> dict[int, np.ndarray]:
    """Linear (H, W, 3) frames of the clip, decoded the way the pipeline decodes them."""
    space = colour.lookup(clip.colorspace)
    return {d.index: colour.to_linear(d.pixels, space)
            for d in frames.iter_frames(clip.kind, clip.path, clip.files, sorted(indices))}


def relit_frame(out_dir: pathlib.Path, i: int) -> np.ndarray:
    return frames.read_exr(pipeline.relit_path(out_dir, i))


def balance(linear: np.ndarray, matte: np.ndarray) -> float:
    """Mean luminance of the portrait's image-left half over its right half (image left is the
    camera's left): a light from the camera's left should raise it above the input's, one from
    the right lower it. The halves split at the matte's centre column."""
    m = np.asarray(matte) > 0.5
    if m.sum() < 16:
        return float("nan")
    cols = np.broadcast_to(np.arange(m.shape[1]), m.shape)
    left = m & (cols < cols[m].mean())
    y = normalise.luminance(linear)
    lo, hi = y[left], y[m & ~left]
    return float(lo.mean() / hi.mean()) if lo.size and hi.size and hi.mean() > 0 else float("nan")


def skin_core(matte: np.ndarray, source: np.ndarray) -> np.ndarray | None:
    """The matte's core where the source is skin-like (r > g > b) and lit; None when it holds
    fewer than 64 pixels."""
    m = (np.asarray(matte) > 0.9) & (source[..., 0] > source[..., 1]) & \
        (source[..., 1] > source[..., 2]) & (normalise.luminance(source) > 0)
    return m if m.sum() >= 64 else None


def skin_chroma(linear: np.ndarray, matte: np.ndarray, source: np.ndarray) -> float:
    """How coloured the subject's skin is: the mean distance of its chromaticity (r, g, b over
    their sum) from grey, over skin_core where the relit frame's luminance is above its median
    there (so shadows' noise does not count). Comparing a relit frame's with its source's under
    a white light says whether skin kept its colour."""
    m = skin_core(matte, source)
    if m is None:
        return float("nan")
    y = normalise.luminance(linear)
    m &= y > np.median(y[m])
    rgb = np.clip(linear[m], 0.0, None)
    total = rgb.sum(axis=1, keepdims=True)
    ok = total[:, 0] > 0
    chroma = np.linalg.norm(rgb[ok] / total[ok] - 1.0 / 3.0, axis=1)
    return float(chroma.mean()) if chroma.size else float("nan")


SHADOW_DARKER = 0.5  # skin the relit frame darkens below this share of its source luminance


def shadow_warmth(linear: np.ndarray, matte: np.ndarray, source: np.ndarray) -> float:
    """How much warmer skin the light darkens turns: the median change of log(red / blue) from
    the source to the relit frame over skin_core where the source's luminance is above its
    median there and the relit frame, its exposure matched to the source's over those pixels,
    keeps less than SHADOW_DARKER of it. A white lamp's new shadows on skin are a little warm
    at their edges (light diffusing under the skin); a large figure is a shadow painted
    red-brown. nan when fewer than 64 pixels are darkened."""
    m = skin_core(matte, source)
    if m is None:
        return float("nan")
    y_src = normalise.luminance(source)
    m &= y_src > np.median(y_src[m])
    y = normalise.luminance(linear)[m]
    q = y / y_src[m] * (float(y_src[m].sum()) / max(float(y.sum()), 1e-12))
    dark = q < SHADOW_DARKER
    if dark.sum() < 64:
        return float("nan")

    def red_blue(rgb):
        return np.log(np.maximum(rgb[..., 0], 1e-8) / np.maximum(rgb[..., 2], 1e-8))

    return float(np.median((red_blue(linear[m]) - red_blue(source[m]))[dark]))


def dilate(mask: np.ndarray, r: int) -> np.ndarray:
    """``mask`` grown by r pixels (a square neighbourhood, separable; nothing wraps around)."""
    out = np.asarray(mask, bool)
    for axis in (0, 1):
        pad = [(0, 0), (0, 0)]
        pad[axis] = (r, r)
        p = np.pad(out, pad)
        n = out.shape[axis]
        grown = np.zeros_like(out)
        for k in range(2 * r + 1):
            grown |= np.take(p, np.arange(k, k + n), axis=axis)
        out = grown
    return out


OUTLINE_BAND = (3, 12)  # pixels beyond the subject's outline where its change should not reach


def outline_change(source: np.ndarray, relit: np.ndarray, matte: np.ndarray) -> tuple[float, float]:
    """(mean, darkest tenth's mean) of the relit luminance over the source's in the band
    OUTLINE_BAND pixels beyond the outline of the subject's matte (> 0.5): 1 when the change
    stops at the outline; below 1, a dark halo on the background."""
    subject = np.asarray(matte) > 0.5
    band = dilate(subject, OUTLINE_BAND[1]) & ~dilate(subject, OUTLINE_BAND[0])
    y_src, y_out = normalise.luminance(source), normalise.luminance(relit)
    band &= y_src > 1e-3
    if band.sum() < 64:
        return float("nan"), float("nan")
    ratio = np.sort(y_out[band] / y_src[band])
    return float(ratio.mean()), float(ratio[:max(1, ratio.size // 10)].mean())


def read_matte(out_dir: pathlib.Path, i: int) -> np.ndarray:
    return frames.read_exr(pipeline.matte_path(out_dir, i))[..., 0]


def p90(linear: np.ndarray) -> float:
    return float(np.percentile(normalise.luminance(linear), normalise.PERCENTILE))


def matched_exposure(relit: np.ndarray, reference: np.ndarray) -> float:
    """Gain that puts the relit frame's 90th-percentile luminance at the input's."""
    r = p90(relit)
    return p90(reference) / r if r > normalise.TINY else 1.0


def encode(linear: np.ndarray, gain: float = 1.0) -> np.ndarray:
    """Linear -> display sRGB in [0, 1] (clipped)."""
    x = np.clip(np.nan_to_num(np.asarray(linear, np.float32) * np.float32(gain)), 0.0, 1.0)
    return colour.linear_to_srgb(x)


def to8(display: np.ndarray) -> np.ndarray:
    return (np.clip(display, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


def fit(img: np.ndarray, box: tuple[int, int]) -> np.ndarray:
    """Resize (area averaging) to fit the (width, height) box, aspect kept, centred on grey."""
    bw, bh = box
    h, w = img.shape[:2]
    f = min(bw / w, bh / h)
    nh, nw = max(1, round(h * f)), max(1, round(w * f))
    small = detail.resize(img.astype(np.float32), nh, nw)
    out = np.full((bh, bw, 3), BACKGROUND / 255.0, np.float32)
    y, x = (bh - nh) // 2, (bw - nw) // 2
    out[y:y + nh, x:x + nw] = small
    return out


def light_preview(light: np.ndarray, box: tuple[int, int]) -> np.ndarray:
    """The light vector as a 2:1 latitude-longitude picture (nearest texels), centred in box."""
    pw, ph = PREVIEW
    img = lightvec.to_preview(light)
    img = np.repeat(np.repeat(img, ph // lightvec.ROWS, 0), pw // lightvec.COLS, 1)
    out = np.full((box[1], box[0], 3), BACKGROUND / 255.0, np.float32)
    y, x = (box[1] - ph) // 2, (box[0] - pw) // 2
    out[y:y + ph, x:x + pw] = img
    return out


def grid(rows: list[list[np.ndarray]]) -> np.ndarray:
    """Tiles (display values, equal widths per column) joined with GAP-pixel gutters."""
    def join(parts, axis):
        gap_shape = list(parts[0].shape)
        gap_shape[axis] = GAP
        gap = np.full(gap_shape, BACKGROUND / 255.0, np.float32)
        out = [parts[0]]
        for p in parts[1:]:
            out += [gap, p]
        return np.concatenate(out, axis)
    return to8(join([join(r, 1) for r in rows], 0))


def sheet_size(n_rows: int, n_lightings: int) -> tuple[int, int]:
    """(width, height) of the main sheet."""
    cols = n_lightings + 1
    return cols * TILE[0] + (cols - 1) * GAP, HEADER_H + n_rows * TILE[1] + n_rows * GAP


def main_sheet(rows, lights: dict[str, np.ndarray], mid: int) -> np.ndarray:
    """rows: (clip spec, {lighting: Run}); columns: input, then each lighting's middle frame."""
    header = [np.full((HEADER_H, TILE[0], 3), BACKGROUND / 255.0, np.float32)]
    header += [light_preview(lights[n], (TILE[0], HEADER_H)) for n in lights]
    out = [header]
    for clip, runs in rows:
        x = input_frames(clip, [mid])[mid]
        tiles = [fit(encode(x), TILE)]
        for name in lights:
            y = relit_frame(runs[name].out_dir, mid)
            tiles.append(fit(encode(y, matched_exposure(y, x)), TILE))
        out.append(tiles)
    return grid(out)


def sequence_rows(clip, runs: list[Run], first: int, length: int):
    """One clip's rows: input and |input(t) - input(t-1)| x DIFF_GAIN, then the same two for
    each run; and each run's flicker figure, the mean frame-to-frame change of its display
    values next to the input's (a stable relight changes about as much as its input)."""
    idx = list(range(first, first + length))
    xs = input_frames(clip, idx)
    ref = xs[idx[length // 2]]
    blank = np.full((SEQ_TILE[1], SEQ_TILE[0], 3), BACKGROUND / 255.0, np.float32)

    def two_rows(shown):
        diffs = [np.abs(b - a) for a, b in zip(shown, shown[1:])]
        return ([[fit(x, SEQ_TILE) for x in shown],
                 [blank] + [fit(d * DIFF_GAIN, SEQ_TILE) for d in diffs]],
                float(np.mean(diffs)))

    rows, change_in = two_rows([encode(xs[i]) for i in idx])
    changes = []
    for run in runs:
        gain = matched_exposure(relit_frame(run.out_dir, idx[length // 2]), ref)
        r, change = two_rows([encode(relit_frame(run.out_dir, i), gain) for i in idx])
        rows += r
        changes.append({"clip": run.clip, "model": run.model, "relit": change,
                        "input": change_in})
    return rows, changes


# ---- the command ------------------------------------------------------------------------------

def model_path(arg: str) -> pathlib.Path:
    """A model given by its card (.json) or its .onnx."""
    p = pathlib.Path(arg)
    return p.with_suffix(".onnx") if p.suffix == ".json" else p


def pick(items, names, what: str):
    if not names:
        return list(items)
    known = {i.name if hasattr(i, "name") else i: i for i in items}
    missing = [n for n in names if n not in known]
    if missing:
        raise InputError(f"Unknown {what} {', '.join(missing)}; choose from "
                         f"{', '.join(known)}.")
    return [known[n] for n in names]


def parse_args(argv):
    p = argparse.ArgumentParser(prog="training.eval.footage_sheet",
                                description=__doc__.split("\n")[0])
    p.add_argument("--models", nargs="+", default=[str(ROOT / "models" / "relight-draft.json")],
                   help="model cards (.json) or .onnx files (default: the shipped Draft)")
    p.add_argument("--out", default=str(ROOT / "out" / "footage"), help="output folder")
    p.add_argument("--frames", type=int, default=24, help="first N frames of each clip")
    p.add_argument("--clips", nargs="+", help="clip names (file stems; default: all)")
    p.add_argument("--lightings", nargs="+", help="lighting names (default: all): " +
                   ", ".join(lt.name for lt in LIGHTINGS))
    p.add_argument("--seq-lighting", help="lighting of the sequence sheet (default: the first "
                   "lamp setup, else the first lighting)")
    p.add_argument("--seq-length", type=int, default=6, help="frames on the sequence sheet")
    p.add_argument("--data", default=str(DATA), help="the shared data folder")
    p.add_argument("--threads", type=int, default=1, help="onnxruntime threads")
    p.add_argument("--background", default=pipeline.DEFAULT_BACKGROUND,
                   choices=pipeline.BACKGROUNDS,
                   help="what stands behind the relit subject (the panel's Background choice; "
                        "default: the product's)")
    p.add_argument("--no-temporal", action="store_true",
                   help="relight each frame alone (RelightOptions.temporal off), to measure "
                        "what the blend with neighbouring frames buys")
    a = p.parse_args(argv)
    if a.frames < 1 or a.seq_length < 2:
        p.error("--frames must be at least 1 and --seq-length at least 2")
    return a


def run_one(spec, clip_name: str, name: str, light, model: pathlib.Path, out: pathlib.Path,
            threads: int, mid: int, x_mid: np.ndarray, background: str,
            temporal: bool = True) -> Run:
    """Relight one clip under one lighting with one model, and measure its middle frame."""
    run_dir = out / clip_name / name / model.stem
    written, seconds, steady = relight(spec, light, run_dir, model, threads, background,
                                       temporal)
    matte = read_matte(run_dir, mid)
    y_mid = relit_frame(run_dir, mid)
    return Run(clip_name, name, model.stem, run_dir, spec.count, written, seconds, steady,
               (balance(x_mid, matte), balance(y_mid, matte)), float(np.mean(matte)),
               (skin_chroma(x_mid, matte, x_mid), skin_chroma(y_mid, matte, x_mid)),
               outline_change(x_mid, y_mid, matte), shadow_warmth(y_mid, matte, x_mid))


def relight_all(data, clips, lights, models, out, frames_n: int, threads: int,
                background: str, temporal: bool = True):
    """[(clip spec, {lighting: Run})], one entry per clip and model, grouped by clip."""
    rows, mid = [], frames_n // 2
    for clip_name in clips:
        spec = clip_spec(data / "footage" / f"{clip_name}.mp4", frames_n)
        x_mid = input_frames(spec, [mid])[mid]
        for model in models:
            row = {}
            for name, light in lights.items():
                run = run_one(spec, clip_name, name, light, model, out, threads, mid, x_mid,
                              background, temporal)
                print(f"{clip_name:>4} {name:<9} {model.stem}: {run.fps_text()}; left/right "
                      f"balance input {run.balance[0]:.2f} -> relit {run.balance[1]:.2f}; "
                      f"skin chroma relit/input {run.chroma[1] / run.chroma[0]:.2f}, "
                      f"shadow warmth {run.warmth:+.3f}; "
                      f"beyond the outline relit/input {run.outline[0]:.2f} (darkest tenth "
                      f"{run.outline[1]:.2f}); matte covers {run.matte_cover:.0%}", flush=True)
                row[name] = run
            rows.append((spec, row))
    return rows


def sequence_sheet(rows, n_models: int, lighting: str, first: int, length: int):
    """The sequence sheet and its flicker figures (one per clip and model)."""
    tiles, changes = [], []
    for i in range(0, len(rows), n_models):
        group = rows[i:i + n_models]  # one clip, each model
        r, c = sequence_rows(group[0][0], [row[lighting] for _, row in group], first, length)
        tiles += r
        changes += c
    return grid(tiles), changes


def _num(x: float):
    return round(x, 4) if np.isfinite(x) else None  # JSON has no NaN


def make_sheets(a) -> dict:
    """Relight everything asked for, write both sheets and sheet.json; return the summary."""
    data = pathlib.Path(a.data)
    movies = sorted((data / "footage").glob("*.mp4"))
    if not movies:
        raise InputError(f"No footage (*.mp4) in {data / 'footage'}; pass --data with the shared "
                         "data folder.")
    clips = pick([m.stem for m in movies], a.clips, "clip")
    lightings = pick(LIGHTINGS, a.lightings, "lighting")
    seq_name = a.seq_lighting or next((lt.name for lt in lightings if lt.lamps),
                                      lightings[0].name)
    if seq_name not in [lt.name for lt in lightings]:
        raise InputError(f"--seq-lighting {seq_name} is not among the lightings run.")
    lights = {lt.name: light_vector(lt, data) for lt in lightings}
    models = [model_path(m) for m in a.models]
    out = pathlib.Path(a.out)
    mid = a.frames // 2
    rows = relight_all(data, clips, lights, models, out, a.frames, a.threads, a.background,
                       not a.no_temporal)
    write_png(out / "sheet.png", main_sheet(rows, lights, mid))
    length = min(a.seq_length, a.frames)
    first = max(0, min(mid - length // 2, a.frames - length))
    seq, changes = sequence_sheet(rows, len(models), seq_name, first, length)
    write_png(out / "sequence.png", seq)
    runs = [r for _, row in rows for r in row.values()]
    summary = {
        "rows": [f"{c} / {m.stem}" for c in clips for m in models],
        "columns": ["input"] + [lt.name for lt in lightings],
        "lightings": {lt.name: lt.what for lt in lightings},
        "middle_frame": mid,
        "background": a.background,
        "temporal": not a.no_temporal,
        "sequence": {"lighting": seq_name, "frames": [first, first + length - 1],
                     "mean_change": changes},
        "runs": [{"clip": r.clip, "lighting": r.lighting, "model": r.model, "frames": r.frames,
                  "written": r.written, "seconds": round(r.seconds, 3),
                  "steady_fps": r.steady_fps and round(r.steady_fps, 2),
                  "balance_input": _num(r.balance[0]), "balance_relit": _num(r.balance[1]),
                  "matte_cover": _num(r.matte_cover), "skin_chroma_input": _num(r.chroma[0]),
                  "skin_chroma_relit": _num(r.chroma[1]), "shadow_warmth": _num(r.warmth),
                  "outline_relit_over_input": _num(r.outline[0]),
                  "outline_darkest_tenth": _num(r.outline[1])}
                 for r in runs],
    }
    (out / "sheet.json").write_text(json.dumps(summary, indent=2) + "\n", encoding="utf-8")
    return summary


def main(argv=None) -> int:
    a = parse_args(argv)
    try:
        summary = make_sheets(a)
    except RelightError as err:
        print(f"footage_sheet: error: {err}", file=sys.stderr)
        return 1
    out = pathlib.Path(a.out)
    print(f"sheet: {out / 'sheet.png'} (rows {summary['rows']}; columns {summary['columns']})")
    print(f"sequence: {out / 'sequence.png'} ({summary['sequence']['lighting']}, frames "
          f"{summary['sequence']['frames']}; per clip: input, |input(t) - input(t-1)| x4, "
          f"then the same two rows for each model's relit frames)")
    for c in summary["sequence"]["mean_change"]:
        ratio = c["relit"] / c["input"] if c["input"] > 0 else float("nan")
        print(f"  {c['clip']} / {c['model']}: mean frame-to-frame change relit {c['relit']:.4f}, "
              f"input {c['input']:.4f} (ratio {ratio:.2f})")
    print("Local viewing only: the footage's provenance is unknown; never commit or publish these.")
    return 0


if __name__ == "__main__":
    sys.exit(main())
