"""Temporal stability under changing light, as in the paper (sec. 5.2, Fig. "10x"): a static
performer whose input lighting changes ever faster, relit into one static light.

    .venv/bin/python -m training.eval.temporal_stability --onnx models/relight-draft.onnx \
        --onnx models/relight-standard.onnx                     # 1000 frames, speed-ups 1..10
    .venv/bin/python -m training.eval.temporal_stability --onnx runs/x.onnx --label full --quick

Protocol (every choice is an option; the defaults are recorded in the JSON):
* Performer: one frame of one held-out identity, the scene of sample ``--sample`` of the fixed
  test set's dataset (``LightStageDataset('test', res, seed=make_testset.TEST_SEED)``; identity
  ids with id % 16 == 15 are never trained on). Its 114 OLAT images are rendered once; light
  transport is linear, so the frame under any light vector L is sum_j w_j(L) OLAT_j with
  w = training.lightstage.layout.weights(L): 1000 frames cost a few matrix products.
* Base lighting sequence (period P = ``--period`` = 1000 frames): the held-out HDRI
  ``--source-hdri`` (pmndrs/park: a sunny park, strongly directional) turning in yaw (the yaw of
  addon.hdri.downsample) at 360 degrees per P frames. Base frame b has yaw 360 b / P, linearly
  interpolated between the environment bank's 128 exactly down-sampled yaws (2.8125 degrees
  apart; training.data.lighting_sampling.environment), each map at mean radiance 1.
* Speed-up f plays that sequence f times faster: frame i of the clip is base frame (f i) mod P,
  so with 1000 frames f = 1 is one turn and f = 10 is ten turns.
* Target: the held-out HDRI ``--target-hdri`` (pmndrs/lobby) at yaw ``--target-yaw``, the same
  for every frame, so the ground truth is one image and a perfect model scores 0.
* Each clip goes through the shipped pipeline's normalisation (addon/normalise.py): one exposure
  s per clip from the clip's sampled frames, the network sees frame / s and light / k, its output
  is brought back by k (contract.RELIT_SCALE). onnxruntime on the CPU,
  ``--threads`` (1) intra-op threads, ``--batch`` frames per call.
* Metric: mean over adjacent pairs (i, i+1) of the RMSE between the two output frames, in the
  held-out evaluation's units (training/eval/evaluate.py): every frame is divided by the ground
  truth's 99th-percentile channel value inside the portrait mask, clipped to [0, 1] and
  sRGB-encoded; the RMSE is over the mask's pixels (the static frame's coverage > 0.5). Also per
  speed-up: the same metric for "output = input" (how much the input itself changes) and for the
  ground truth (0 by construction), and each model's mean RMSE to the ground truth (accuracy: a
  model that ignored its input would be perfectly stable and useless).

Writes temporal_stability.json and .png into ``--out`` (bench/results) and prints a markdown
table. Models: any contract ONNX with its card beside it (label = card name unless --label), or
a bare ONNX with a --label (stride ``--stride``, relit scale "k"). Give either no --label or one
per --onnx, in order (an empty one, --label "", keeps a card's name).
"""

from __future__ import annotations

import argparse
import functools
import math
import pathlib
import sys
import time
from dataclasses import dataclass, field

import numpy as np

from addon import contract, engine, normalise
from addon.errors import InputError, LightingError, ModelError, RelightError
from ..data import lighting_sampling
from ..lightstage import layout
from . import metrics, report

ROOT = pathlib.Path(__file__).resolve().parents[2]
DEFAULT_OUT = ROOT / "bench" / "results"
SPEEDUPS = tuple(range(1, 11))
QUICK_SPEEDUPS = (1, 5, 10)
QUICK_FRAMES = 60
SHOWN = {"input": "output = input", "ground_truth": "ground truth"}  # the two references
YAW_STEPS = lighting_sampling.SUB_STEPS * 16  # exactly down-sampled yaws per turn (16 columns)


# ---- the lighting sequence ----------------------------------------------------------------

def base_lights(bank: np.ndarray, index: int, period: int) -> np.ndarray:
    """(period, 16, 16, 3) float32: HDRI ``index`` of the bank turning 360 degrees over
    ``period`` frames, linearly interpolated between the bank's exactly down-sampled yaws."""
    if period < 2:
        raise InputError(f"A lighting period of {period} frames cannot change; use 2 or more.")
    step = 360.0 / YAW_STEPS
    exact = np.stack([lighting_sampling.environment(bank, index, s * step)
                      for s in range(YAW_STEPS)]).astype(np.float64)
    u = np.arange(period) * (YAW_STEPS / period)  # position in exact yaw steps
    lo = np.floor(u).astype(np.int64)
    frac = (u - lo)[:, None, None, None]
    out = (1.0 - frac) * exact[lo % YAW_STEPS] + frac * exact[(lo + 1) % YAW_STEPS]
    return out.astype(np.float32)


def sequence_indices(n_frames: int, speedup: int, period: int) -> np.ndarray:
    """Base-frame index of each clip frame at speed-up ``speedup``: (speedup * i) mod period."""
    if n_frames < 2:
        raise InputError(f"{n_frames} frames have no adjacent pair; use 2 or more.")
    if int(speedup) != speedup or speedup < 1:
        raise InputError(f"Speed-up {speedup} must be a whole number of 1 or more.")
    return (int(speedup) * np.arange(n_frames, dtype=np.int64)) % int(period)


# ---- the static performer -----------------------------------------------------------------

@dataclass(frozen=True)
class Stage:
    olat: np.ndarray   # (114, 3, H, W) float32: the frame under each stage light (irradiance 1)
    mask: np.ndarray   # (H, W) bool: the portrait region (coverage > 0.5)
    info: dict = field(default_factory=dict)

    @functools.cached_property
    def _planes(self) -> np.ndarray:
        """(3, 114, H*W): the OLAT images channel by channel, contiguous for the products."""
        return np.ascontiguousarray(self.olat.transpose(1, 0, 2, 3).reshape(
            self.olat.shape[1], self.olat.shape[0], -1))

    def render(self, lights: np.ndarray) -> np.ndarray:
        """(N, 3, H, W) float32 absolute radiance under light vectors (N, 16, 16, 3)."""
        w = np.stack([layout.weights(lv) for lv in lights]).astype(np.float32)  # (N, 114, 3)
        # contiguous (3, N, 114): numpy's matmul leaves BLAS (30x slower) on strided operands
        w = np.ascontiguousarray(w.transpose(2, 0, 1))
        out = np.stack([w[ch] @ self._planes[ch] for ch in range(3)], axis=1)
        return out.reshape(len(lights), 3, *self.olat.shape[2:])


def build_stage(resolution: int = 128, sample: int = 0, data_root=None) -> Stage:
    """The OLAT images of the scene of held-out sample ``sample`` (its identity, performance time,
    camera and backdrop; its random lighting is not used)."""
    import torch

    from ..data.dataset import LightStageDataset
    from ..data.make_testset import TEST_SEED

    ds = LightStageDataset("test", resolution, seed=TEST_SEED, length=sample + 1,
                           data_root=data_root)
    scene, t, _ = ds.scene_for(sample)
    frame = scene.frame(t)
    n = layout.N_LIGHTS
    olat = scene.shade_weights(frame, torch.ones(n, 1, 3) * torch.eye(n)[:, :, None]).numpy()
    cover = frame.gb.mask.float() if frame.cover is None else frame.cover
    info = {"split": "test", "seed": TEST_SEED, "sample": int(sample),
            "identity": int(scene.ident.id), "time_s": float(t), "resolution": int(resolution)}
    return Stage(np.ascontiguousarray(olat, np.float32), cover.numpy() > 0.5, info)


# ---- the metric ---------------------------------------------------------------------------

def adjacent_rmse(frames: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """RMSE between frames i and i+1 over the mask's pixels, one per adjacent pair: frames
    (N, 3, H, W) -> (N - 1,)."""
    return _pair_rmse(np.asarray(frames, np.float64)[:, :, mask])


def _pair_rmse(px: np.ndarray) -> np.ndarray:
    """(N, 3, M) pixels -> (N - 1,) RMSE between consecutive frames."""
    return np.sqrt(np.mean((px[1:] - px[:-1]) ** 2, axis=(1, 2)))


def to_unit(frames: np.ndarray, white: float) -> np.ndarray:
    """Absolute frames -> training/eval/evaluate.py's [0, 1] display units (non-finite values as
    metrics.image_metrics treats them)."""
    return metrics.to_unit(np.nan_to_num(frames, nan=0.0, posinf=white, neginf=0.0), white)


class Tracker:
    """Adjacent-frame RMSE and RMSE to the ground truth over a clip fed in batches of the
    portrait region's pixels ((B, 3, M), in [0, 1] units; the ground truth (3, M))."""

    def __init__(self, gt_px: np.ndarray):
        self.gt = gt_px
        self.prev = None
        self.adjacent: list[float] = []
        self.to_gt: list[float] = []

    def add(self, px: np.ndarray) -> None:
        seq = px if self.prev is None else np.concatenate([self.prev[None], px])
        self.adjacent.extend(_pair_rmse(seq).tolist())
        self.to_gt.extend(np.sqrt(np.mean((px - self.gt[None]) ** 2, axis=(1, 2))).tolist())
        self.prev = px[-1]

    def result(self) -> dict:
        return {"adjacent_rmse": float(np.mean(self.adjacent)),
                "adjacent_rmse_max": float(np.max(self.adjacent)),
                "rmse_to_gt": float(np.mean(self.to_gt))}


# ---- models -------------------------------------------------------------------------------

@dataclass
class Model:
    label: str
    path: pathlib.Path
    session: object          # onnxruntime.InferenceSession
    stride: int
    card: bool
    sha256: str
    seconds: float = 0.0     # time spent in the network

    def relit(self, images: np.ndarray, light_cf: np.ndarray) -> np.ndarray:
        """Normalised (B, 3, H, W) images and one unit-power light (3, 16, 16) -> relit (B, 3,
        H, W) in the network's units; images reflect-padded to the stride and cropped back."""
        b, _, h, w = images.shape
        s = self.stride
        x = np.pad(images, ((0, 0), (0, 0), (0, -h % s), (0, -w % s)), mode="reflect")
        feeds = {contract.INPUT_IMAGE: np.ascontiguousarray(x, np.float32),
                 contract.INPUT_LIGHT: np.ascontiguousarray(
                     np.broadcast_to(light_cf, (b,) + light_cf.shape), np.float32)}
        t0 = time.perf_counter()
        relit = self.session.run([contract.OUTPUT_RELIT], feeds)[0]
        self.seconds += time.perf_counter() - t0
        return relit[:, :, :h, :w]


def load_model(path, label: str | None = None, threads: int = 1, stride: int = 32) -> Model:
    """A contract ONNX with its card (checked as the add-on checks it), or a bare one and a label."""
    import onnxruntime as ort

    path = pathlib.Path(path)
    if not path.is_file():
        raise ModelError(f"The model file {path} does not exist; give the path of an .onnx file.")
    has_card = engine.card_path_for(path).is_file()
    if has_card:
        card = engine.load_card(path)
        engine.verify_checksum(card)
        label, stride = label or card.name, card.stride
    elif not label:
        raise ModelError(f"{path.name} has no model card beside it ({path.stem}.json); give a "
                         "--label for each --onnx to benchmark a bare ONNX file.")
    try:
        sess = ort.InferenceSession(str(path), engine.session_options(ort, threads),
                                    providers=["CPUExecutionProvider"])
    except Exception as err:  # onnxruntime raises its own untyped errors for bad files
        raise ModelError(f"onnxruntime cannot load {path} ({err}); re-export the model.") from err
    names = {i.name for i in sess.get_inputs()} | {o.name for o in sess.get_outputs()}
    need = {contract.INPUT_IMAGE, contract.INPUT_LIGHT, contract.OUTPUT_RELIT}
    if not need <= names:
        raise ModelError(f"{path.name} does not follow the ONNX contract (it needs "
                         f"{sorted(need)}, it has {sorted(names)}); export it with "
                         "training.run.export.")
    return Model(label, path, sess, int(stride), has_card, engine.file_sha256(path))


def model_predictor(model: Model, target_light: np.ndarray):
    """``predict(frames_abs, s) -> relit_abs``: the pipeline's normalisation around the network."""
    unit, k = normalise.normalise_light(target_light)
    if k <= 0:
        raise LightingError("The target light is black; pick a target HDRI with some light.")
    light_cf = np.ascontiguousarray(unit.transpose(2, 0, 1))

    def predict(frames, s):
        return model.relit(frames / np.float32(s), light_cf) * np.float32(k)
    return predict


# ---- the benchmark ------------------------------------------------------------------------

def clip_exposure(stage: Stage, lights: np.ndarray) -> float:
    """s of the clip as the pipeline takes it: from its fixed sample frames, channels last."""
    idx = normalise.sample_frame_indices(len(lights))
    return normalise.exposure_scale(list(stage.render(lights[idx]).transpose(0, 2, 3, 1)))


def measure_clip(stage: Stage, lights: np.ndarray, predictors: dict, gt: np.ndarray,
                 batch: int = 10) -> dict:
    """Per predictor (label -> predict(frames_abs, s)) the Tracker result over one clip."""
    mask = stage.mask
    white = metrics.white_level(gt, mask)
    s = clip_exposure(stage, lights)
    trackers = {name: Tracker(to_unit(gt[:, mask], white)) for name in predictors}
    for start in range(0, len(lights), batch):
        frames = stage.render(lights[start:start + batch])
        for name, predict in predictors.items():  # only the portrait region is measured
            trackers[name].add(to_unit(predict(frames, s)[:, :, mask], white))
    return {name: {**tr.result(), "exposure_scale": s} for name, tr in trackers.items()}


def run(stage: Stage, models: list[Model], base: np.ndarray, target: np.ndarray,
        frames: int, speedups, batch: int = 10, on_progress=None) -> dict:
    """{"input": {f: stats}, "ground_truth": {f: stats}, <label>: {f: stats}} per speed-up f."""
    gt = stage.render(target[None])[0]
    gt_unit = to_unit(gt, metrics.white_level(gt, stage.mask))
    zero = float(adjacent_rmse(np.stack([gt_unit, gt_unit]), stage.mask)[0])  # static target
    predictors = {"input": lambda x, s: x}
    predictors.update({m.label: model_predictor(m, target) for m in models})
    out = {name: {} for name in ["ground_truth", *predictors]}
    for f in speedups:
        lights = base[sequence_indices(frames, f, len(base))]
        res = measure_clip(stage, lights, predictors, gt, batch)
        for name, stats in res.items():
            out[name][int(f)] = stats
        out["ground_truth"][int(f)] = {"adjacent_rmse": zero, "rmse_to_gt": 0.0}
        if on_progress:
            on_progress(f)
    return out


# ---- report -------------------------------------------------------------------------------

def markdown(results: dict, labels: list[str]) -> str:
    speedups = sorted(results["input"])
    keys = ["ground_truth", "input", *labels]
    cols = [SHOWN.get(k, k) for k in keys]
    lines = ["Adjacent-frame RMSE (lower = more stable; [0, 1] sRGB units of "
             "training/eval/evaluate.py, portrait region)", "",
             "| speed-up | " + " | ".join(cols) + " |", "|---" * (len(cols) + 1) + "|"]
    for f in speedups:
        lines.append(f"| {f} | " + " | ".join(f"{results[k][f]['adjacent_rmse']:.5f}"
                                               for k in keys) + " |")
    lines += ["", "RMSE to the ground truth (accuracy, same units)", "",
              "| speed-up | output = input | " + " | ".join(labels) + " |",
              "|---" * (len(labels) + 2) + "|"]
    for f in speedups:
        lines.append(f"| {f} | " + " | ".join(f"{results[k][f]['rmse_to_gt']:.4f}"
                                               for k in ["input", *labels]) + " |")
    return "\n".join(lines)


def plot(path, results: dict, labels: list[str], footer: str = "") -> None:
    """temporal_stability.png: adjacent-frame RMSE against the speed-up (with both references,
    then the models alone) and the RMSE to the ground truth; the references dashed."""
    fs = sorted(results["input"])
    refs = {"input": {"color": "grey", "ls": "--"}, "ground_truth": {"color": "black", "ls": "--"}}
    style = {**refs, **{n: {"color": report.COLOURS[i % len(report.COLOURS)]}
                        for i, n in enumerate(labels)}}
    panels = (("Adjacent-frame RMSE", "adjacent_rmse", ["input", "ground_truth", *labels]),
              ("Adjacent-frame RMSE, models", "adjacent_rmse", ["ground_truth", *labels]),
              ("RMSE to the ground truth", "rmse_to_gt", ["input", *labels]))
    fig, axes = report.figure(len(panels), footer[:190])
    for ax, (title, key, names) in zip(axes, panels):
        for name in names:
            ys = [results[name][f][key] for f in fs]
            ax.plot(fs, [y if math.isfinite(y) else math.nan for y in ys], marker="s", ms=4, lw=2,
                    label=SHOWN.get(name, name), **style[name])
        ax.set_title(title)
        ax.set_xlabel("lighting speed-up factor")
        ax.set_ylabel("RMSE")
        ax.set_xticks(fs)
        ax.set_ylim(bottom=0.0)
        ax.grid(True, alpha=0.25)
        ax.legend(loc="upper left", fontsize=7)
    fig.savefig(path)


# ---- command line -------------------------------------------------------------------------

def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--onnx", action="append", required=True, help="a model (repeat)")
    p.add_argument("--label", action="append", help="a name per --onnx, in order (needed for "
                   "an ONNX without a card beside it; \"\" keeps a card's name)")
    p.add_argument("--frames", type=int, default=1000)
    p.add_argument("--speedups", type=int, nargs="+", default=list(SPEEDUPS))
    p.add_argument("--quick", action="store_true", help=f"{QUICK_FRAMES} frames, speed-ups "
                   f"{', '.join(map(str, QUICK_SPEEDUPS))} (a smoke run)")
    p.add_argument("--period", type=int, default=1000, help="frames per turn at speed-up 1")
    p.add_argument("--source-hdri", default="pmndrs/park")
    p.add_argument("--target-hdri", default="pmndrs/lobby")
    p.add_argument("--target-yaw", type=float, default=0.0)
    p.add_argument("--resolution", type=int, default=128)
    p.add_argument("--sample", type=int, default=0, help="held-out sample whose scene is used")
    p.add_argument("--stride", type=int, default=32, help="padding stride of a bare ONNX")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--batch", type=int, default=10)
    p.add_argument("--out", default=str(DEFAULT_OUT))
    p.add_argument("--data-root", help="the shared data folder (default ../shared/data)")
    a = p.parse_args(argv)
    if a.quick:
        a.frames, a.speedups = QUICK_FRAMES, list(QUICK_SPEEDUPS)
    if a.label and len(a.label) != len(a.onnx):
        p.error(f"give one --label per --onnx ({len(a.onnx)}), or none")
    return a


def main(argv=None) -> dict:
    import torch

    from ..lightstage import assets

    a = parse_args(argv)
    torch.set_num_threads(max(1, a.threads))
    t0 = time.perf_counter()
    labels = a.label or [None] * len(a.onnx)
    models = [load_model(p, lab, a.threads, a.stride) for p, lab in zip(a.onnx, labels)]
    if len({m.label for m in models} - set(SHOWN)) != len(models):
        raise InputError("Two models have the same label (or one is called 'input' or "
                         "'ground_truth'); give each --onnx its own --label.")
    root = pathlib.Path(a.data_root) if a.data_root else assets.default_data_root()
    names, bank = lighting_sampling.environment_bank(root)
    for n in (a.source_hdri, a.target_hdri):
        if n not in names:
            raise InputError(f"No HDRI {n!r} in {root / 'hdri'}; pick one of {', '.join(names)}.")
    base = base_lights(bank, names.index(a.source_hdri), a.period)
    target = lighting_sampling.environment(bank, names.index(a.target_hdri), a.target_yaw)
    stage = build_stage(a.resolution, a.sample, root)
    t_stage = time.perf_counter() - t0
    results = run(stage, models, base, target, a.frames, a.speedups, a.batch,
                  on_progress=lambda f: print(f"  speed-up {f} done "
                                              f"({time.perf_counter() - t0:.0f} s)", flush=True))
    labels = [m.label for m in models]
    table = markdown(results, labels)
    print(table)
    wall = time.perf_counter() - t0
    data = {
        "command": "python -m training.eval.temporal_stability " + " ".join(
            sys.argv[1:] if argv is None else argv),
        "protocol": {
            "performer": stage.info, "mask_pixels": int(stage.mask.sum()),
            "frames": a.frames, "speedups": [int(f) for f in a.speedups], "period": a.period,
            "source": f"{a.source_hdri} turning in yaw 360 deg per {a.period} frames at speed-up "
                      f"1 (mean radiance 1); clip frame i = base frame (f i) mod {a.period}",
            "target": f"{a.target_hdri} at yaw {a.target_yaw} deg (mean radiance 1), static",
            "normalisation": "pipeline: one exposure s per clip (addon.normalise), light / k, "
                             "relit * k",
            "units": "RMSE of [0,1] sRGB values over the portrait mask after dividing by the "
                     "ground truth's 99th-percentile in-mask value (training/eval/evaluate.py)",
            "threads": a.threads, "batch": a.batch},
        "models": {m.label: {"onnx": str(m.path), "sha256": m.sha256, "card": m.card,
                             "network_seconds": round(m.seconds, 2),
                             "ms_per_frame": round(1000 * m.seconds / (a.frames * len(a.speedups)),
                                                   3)} for m in models},
        "results": {k: {str(f): v for f, v in r.items()} for k, r in results.items()},
        "seconds": {"stage": round(t_stage, 2), "total": round(wall, 2)},
        "machine": report.machine(),
    }
    out = pathlib.Path(a.out)
    write_report(out / "temporal_stability", data)
    footer = (f"{a.frames} frames, static held-out performer (identity "
              f"{stage.info['identity']}), {a.source_hdri} turning 360 deg per {a.period} frames "
              f"at speed-up 1 -> {a.target_hdri}")
    plot(out / "temporal_stability.png", results, labels, footer)
    print(f"\n{a.frames} frames x {len(a.speedups)} speed-ups, {len(models)} model(s): "
          f"{wall:.0f} s wall ({t_stage:.0f} s stage); wrote {out / 'temporal_stability.json'} "
          ".md and .png")
    return data


def write_report(stem: pathlib.Path, data: dict) -> pathlib.Path:
    """temporal_stability.md and .json from one run's results."""
    p = data["protocol"]
    labels = list(data["models"])
    results = {k: {int(f): v for f, v in r.items()} for k, r in data["results"].items()}
    body = (f"A static held-out performer (identity {p['performer']['identity']}), {p['frames']} "
            f"frames; source: {p['source']}; target: {p['target']}; mean RMSE of adjacent "
            "output frames (0 for the ground truth: its target is static). Models: "
            + ", ".join(f"{k} `{m['onnx']}`" for k, m in data["models"].items())
            + ".\n\n![temporal stability](temporal_stability.png)\n\n"
            + markdown(results, labels))
    return report.write(stem, "Temporal stability (the paper's protocol)", data["command"],
                        report.machine_line(data["machine"]), body, data)


if __name__ == "__main__":
    try:
        main()
    except RelightError as err:  # a usage problem: say what to do, no traceback
        sys.exit(f"error: {err}")
