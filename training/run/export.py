"""Export a trained network to ONNX with its model card (the contract in addon/contract.py).

    python -m training.run.export --run runs/draft-01 --name relight-draft \
        [--checkpoint best.pt] [--int8]

Steps: export (opset 17, dynamic N, H, W; names from addon.contract), verify onnxruntime against
PyTorch on several sizes within ``TOLERANCE``, optionally quantise to int8 (static, QDQ, calibrated
on light-stage frames) and keep it only if it is faster, evaluate on held-out light-stage samples,
measure the cost per resolution and provider, and write ``models/<name>.onnx`` + ``<name>.json``.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import time
import warnings

import numpy as np
import torch

from addon import contract, engine, normalise

from ..model import network

OPSET = 17
# ONNX vs PyTorch agreement required on the relit image (normalised units, values ~0..2), the
# source light and the parsing probabilities: max |difference| <= atol + rtol * |torch value|.
TOLERANCE = {"atol": 1e-4, "rtol": 1e-3}
VERIFY_SIZES = ((64, 64), (96, 160))
CALIBRATION_SEED = 4242  # int8 calibration frames: training identities, not the eval samples
MODELS = pathlib.Path(__file__).resolve().parents[2] / "models"


def export_onnx(net: network.RelightNet, path, opset: int = OPSET) -> pathlib.Path:
    path = pathlib.Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    net = net.eval().to(memory_format=torch.contiguous_format)
    s = net.cfg.stride
    dummy = (torch.rand(1, 3, 2 * s, 2 * s), torch.ones(1, *network.LIGHT_SHAPE))
    names_in = [contract.INPUT_IMAGE, contract.INPUT_LIGHT]
    names_out = [contract.OUTPUT_RELIT, contract.OUTPUT_SOURCE_LIGHT, contract.OUTPUT_PARSING]
    axes = {contract.INPUT_IMAGE: {0: "N", 2: "H", 3: "W"}, contract.INPUT_LIGHT: {0: "N"},
            contract.OUTPUT_RELIT: {0: "N", 2: "H", 3: "W"}, contract.OUTPUT_SOURCE_LIGHT: {0: "N"},
            contract.OUTPUT_PARSING: {0: "N", 2: "H", 3: "W"}}
    with torch.no_grad(), warnings.catch_warnings():
        # the TorchScript exporter is deprecated, but the dynamo one needs onnxscript (not pinned)
        warnings.simplefilter("ignore", DeprecationWarning)
        torch.onnx.export(net, dummy, str(path), dynamo=False, opset_version=opset,
                          input_names=names_in, output_names=names_out, dynamic_axes=axes,
                          do_constant_folding=True)
    return path


def session(path, threads: int = 2, providers=("CPUExecutionProvider",)):
    import onnxruntime as ort

    so = ort.SessionOptions()
    so.intra_op_num_threads = threads
    so.inter_op_num_threads = 1
    so.log_severity_level = 3
    return ort.InferenceSession(str(path), so, providers=list(providers))


def verify(net: network.RelightNet, path, sizes=VERIFY_SIZES, seed: int = 0) -> dict:
    """Max |ONNX - torch| per output over random inputs of several sizes; raises if any output is
    outside TOLERANCE."""
    sess = session(path)
    rng = np.random.default_rng(seed)
    worst = {}
    for h, w in sizes:
        img = (rng.random((2, 3, h, w)) * 1.5).astype(np.float32)
        light = (rng.random((2, *network.LIGHT_SHAPE)) * 2).astype(np.float32)
        with torch.no_grad():
            ref = [t.numpy() for t in net.eval()(torch.from_numpy(img), torch.from_numpy(light))]
        got = sess.run(None, {contract.INPUT_IMAGE: img, contract.INPUT_LIGHT: light})
        for name, r, g in zip((contract.OUTPUT_RELIT, contract.OUTPUT_SOURCE_LIGHT,
                               contract.OUTPUT_PARSING), ref, got):
            if r.shape != g.shape:
                raise AssertionError(f"{name}: ONNX shape {g.shape} != torch {r.shape}")
            excess = np.abs(g - r) - (TOLERANCE["atol"] + TOLERANCE["rtol"] * np.abs(r))
            worst[name] = max(worst.get(name, 0.0), float(np.abs(g - r).max()))
            if np.any(excess > 0):
                raise AssertionError(f"{name}: ONNX differs from torch by {np.abs(g - r).max():.3g}"
                                     f" at {h}x{w}, beyond {TOLERANCE}")
    return {"max_abs_diff": worst, "tolerance": TOLERANCE, "sizes": [list(s) for s in sizes]}


# ---------------------------------------------------------------------------------- int8 (QDQ)

def calibration_feeds(samples, stride: int) -> list[dict]:
    """Network inputs from light-stage samples, normalised exactly as at inference."""
    from ..model.units import normalise_sample

    feeds = []
    for s in samples:
        n = normalise_sample(s)
        img = n["img_t"][None]
        h, w = img.shape[-2:]
        img = np.pad(img, ((0, 0), (0, 0), (0, -h % stride), (0, -w % stride)), mode="reflect")
        feeds.append({contract.INPUT_IMAGE: img, contract.INPUT_LIGHT: n["light_k"][None]})
    return feeds


def quantize_int8(fp32_path, out_path, feeds: list[dict], keep_float=()) -> pathlib.Path:
    """Static int8 quantisation, QDQ format, per-channel weights, calibrated on ``feeds``;
    the nodes named in ``keep_float`` stay float."""
    from onnxruntime.quantization import (CalibrationDataReader, QuantFormat, QuantType,
                                          quantize_static)
    from onnxruntime.quantization.shape_inference import quant_pre_process

    class Reader(CalibrationDataReader):
        def __init__(self):
            self.it = iter(feeds)

        def get_next(self):
            return next(self.it, None)

    out_path = pathlib.Path(out_path)
    pre = out_path.with_suffix(".pre.onnx")
    quant_pre_process(str(fp32_path), str(pre), skip_symbolic_shape=True)
    try:
        # Only convolutions are quantised: the light MLP (Gemm) and the element-wise output
        # stage (gain * image + residual) stay float, as they set colour and exposure directly.
        quantize_static(str(pre), str(out_path), Reader(), quant_format=QuantFormat.QDQ,
                        activation_type=QuantType.QUInt8, weight_type=QuantType.QInt8,
                        per_channel=True, op_types_to_quantize=["Conv"],
                        nodes_to_exclude=list(keep_float))
    finally:
        pre.unlink(missing_ok=True)
    return out_path


# ----------------------------------------------------------------------------------------- cost

def measure_cost(path, sizes=(256, 512), threads: int = 2, repeats: int = 20,
                 providers=("CPUExecutionProvider",)) -> dict:
    """Median milliseconds per frame (batch 1, network only) per size, after warm-up."""
    sess = session(path, threads, providers)
    out = {}
    rng = np.random.default_rng(0)
    for size in sizes:
        feeds = {contract.INPUT_IMAGE: rng.random((1, 3, size, size), dtype=np.float32),
                 contract.INPUT_LIGHT: np.ones((1, *network.LIGHT_SHAPE), np.float32)}
        for _ in range(3):
            sess.run(None, feeds)
        times = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            sess.run(None, feeds)
            times.append(time.perf_counter() - t0)
        ms = float(np.median(times) * 1e3)
        out[str(size)] = {"ms": round(ms, 2), "fps": round(1e3 / ms, 1)}
    return {"provider": sess.get_providers()[0], "threads": threads, "batch": 1,
            "per_size": out}


# ----------------------------------------------------------------------------------------- card



COLOUR = {
    "space": "linear Rec.709 scene-referred (Blender scene linear), channels first",
    "image": ("image / s: s = addon.normalise.exposure_scale over the clip's sampled frames "
              f"(its {normalise.PERCENTILE:g}th-percentile luminance maps to "
              f"{normalise.REFERENCE_LEVEL}); one s per clip, never per frame"),
    "target_light": ("light vector / k, channels first [N,3,16,16]: k = "
                     "addon.normalise.light_scale (mean radiance), so the input has unit power"),
    "relit": ("the input relit under the target light, in the units of image / k: multiply by "
              "k (not s) for scene-linear radiance (card key relit_scale 'k'). image / s is the "
              "scene under lights / s, so a decoder fed light / k renders relit / k"),
    "source_light": ("the estimated light of the input in the normalised image's units "
                     "(light / s): multiply by s for absolute radiance"),
    "parsing": "sigmoid probabilities in [0, 1], one channel per class (multi-label)",
}


def io_spec(classes: int) -> tuple[list, list]:
    inputs = [{"name": contract.INPUT_IMAGE, "shape": ["N", 3, "H", "W"], "dtype": "float32"},
              {"name": contract.INPUT_LIGHT, "shape": ["N", 3, 16, 16], "dtype": "float32"}]
    outputs = [{"name": contract.OUTPUT_RELIT, "shape": ["N", 3, "H", "W"], "dtype": "float32"},
               {"name": contract.OUTPUT_SOURCE_LIGHT, "shape": ["N", 3, 16, 16],
                "dtype": "float32"},
               {"name": contract.OUTPUT_PARSING, "shape": ["N", classes, "H", "W"],
                "dtype": "float32"}]
    return inputs, outputs


def make_card(name: str, preset: str, onnx_path, net: network.RelightNet, training: dict,
              metrics: dict, cost: dict, working_size: int, extra: dict | None = None) -> dict:
    inputs, outputs = io_spec(net.cfg.classes)
    card = {
        "contract": contract.CONTRACT_VERSION, "name": name, "preset": preset,
        "onnx": pathlib.Path(onnx_path).name, "sha256": engine.file_sha256(onnx_path),
        "inputs": inputs, "outputs": outputs, "stride": net.cfg.stride,
        "working_size": int(working_size), "colour": COLOUR,
        "relit_scale": contract.RELIT_SCALE,
        "classes": list(contract.PARSING_CLASSES[:net.cfg.classes]),
        "training": training, "metrics": metrics, "cost": cost,
        "architecture": {"config": net.cfg.to_dict(), "parameters": network.parameter_count(net),
                         "gflop_per_frame": {str(s): round(network.count_flops(net, s, s) / 1e9, 3)
                                             for s in (256, 512)}},
    }
    card.update(extra or {})
    missing = [k for k in contract.REQUIRED_CARD_KEYS if k not in card]
    if missing:
        raise AssertionError(f"card lacks {missing}")
    return card


def write_card(card: dict, onnx_path) -> pathlib.Path:
    path = pathlib.Path(onnx_path).with_suffix(".json")
    path.write_text(json.dumps(card, indent=2) + "\n")
    return path


# ------------------------------------------------------------------------------------------ CLI

def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description="export a run to models/<name>.onnx + card")
    p.add_argument("--run", required=True)
    p.add_argument("--checkpoint", default="checkpoint.pt",
                   help="file in the run folder: checkpoint.pt (last) or best.pt (best on val)")
    p.add_argument("--name", required=True)
    p.add_argument("--out-dir", default=str(MODELS))
    p.add_argument("--eval", type=int, default=64, help="held-out samples for the card metrics")
    p.add_argument("--eval-resolution", type=int, default=0, help="default: the training size")
    p.add_argument("--working-size", type=int, default=0, help="default: the training size")
    p.add_argument("--int8", action="store_true", help="also try static int8 QDQ")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--note", default="")
    return p


def main(argv=None):
    from ..eval import evaluate, predictors
    from ..model.checkpoint import load_checkpoint
    from .lineage import resolve_lineage, samples_version

    a = parser().parse_args(argv)
    torch.set_num_threads(a.threads)
    net, ck = load_checkpoint(pathlib.Path(a.run) / a.checkpoint)
    recipe = {**ck["recipe"], "init": resolve_lineage(ck["recipe"].get("init")),
              "exported_checkpoint": {"file": a.checkpoint, "step": ck["step"],
                                      "val": ck.get("val")}}
    final = pathlib.Path(a.run) / "recipe.json"  # a finished run's recipe adds its totals
    if final.is_file():
        done = json.loads(final.read_text())
        recipe.update({k: done[k] for k in ("steps", "trained_minutes") if k in done})
    res = a.eval_resolution or int(recipe["args"]["resolution"])
    working = a.working_size or int(recipe["args"]["resolution"])
    out_dir = pathlib.Path(a.out_dir)
    onnx_path = export_onnx(net, out_dir / f"{a.name}.onnx")
    check = verify(net, onnx_path)
    print("verified:", json.dumps(check))
    ds = evaluate.heldout_dataset(res)
    predict = predictors.onnx_predictor(session(onnx_path, a.threads), net.cfg.stride)
    metrics = evaluate.card_metrics(predict, ds, a.eval, res)
    print("metrics:", json.dumps(metrics))
    cost = {"cpu": measure_cost(onnx_path, threads=a.threads),
            "machine": "2-core x86-64 CPU (AMD EPYC, AVX-512 VNNI), shared and noisy"}
    training = {"data": "synthetic dynamic light stage (training.data.dataset, ICT-FaceKit heads, "
                        "CC0 HDRIs); held-out identities for metrics",
                "render_version": samples_version(recipe), "recipe": recipe, "note": a.note,
                "onnx_check": check}
    card = make_card(a.name, recipe["args"]["preset"], onnx_path, net, training, metrics, cost,
                     working)
    print("card:", write_card(card, onnx_path))
    if a.int8:
        export_int8(a, net, onnx_path, ds, training, res, working, cost)


def export_int8(a, net, fp32_path, ds, training, res, working, fp32_cost):
    from ..eval import evaluate, predictors
    from ..data.dataset import make_dataset

    train_ds = make_dataset("train", res, CALIBRATION_SEED)  # training identities: never the test set
    calib = [train_ds[i] for i in range(16)]
    q_path = quantize_int8(fp32_path, fp32_path.with_name(f"{a.name}-int8.onnx"),
                           calibration_feeds(calib, net.cfg.stride))
    cost = {"cpu": measure_cost(q_path, threads=a.threads), "machine": fp32_cost["machine"]}
    metrics = evaluate.card_metrics(predictors.onnx_predictor(session(q_path, a.threads),
                                                            net.cfg.stride), ds, a.eval, res)
    speedup = fp32_cost["cpu"]["per_size"]["512"]["ms"] / cost["cpu"]["per_size"]["512"]["ms"]
    print(f"int8: {json.dumps(metrics)} speed-up at 512: {speedup:.2f}x")
    if speedup < 1.1:
        print("int8 does not pay on this CPU: not kept")
        q_path.unlink()
        return
    # its own preset name: the panel picks a model by preset, and int8 must be chosen knowingly
    preset = training["recipe"]["args"]["preset"] + "-int8"
    card = make_card(f"{a.name}-int8", preset, q_path, net,
                     {**training, "quantisation": "static int8 QDQ, per-channel, calibrated on "
                                                  "16 light-stage training frames"},
                     metrics, cost, working, {"speedup_vs_fp32_512": round(speedup, 2)})
    print("card:", write_card(card, q_path))


if __name__ == "__main__":
    main()
