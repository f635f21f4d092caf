"""Export a trained intrinsic network to ONNX with its model card.

    .venv/bin/python -m training.intrinsic.export --run runs/intrinsic-standard \
        --name relight-portrait --preset portrait

Writes models/<name>.onnx (opset 17, dynamic N/H/W) and models/<name>.json (contract
``relight-intrinsic/1``), after checking onnxruntime against PyTorch on two sizes and measuring
the per-buffer errors on held-out val identities. Held-out quality on real faces is measured by
``python -m training.eval.yale`` through ``addon.relight_image``.

``--int8`` ships the network quantised (static int8, QDQ, per-channel weights, calibrated on
training frames through the simulated camera), with its first convolution, its full-resolution
decoder block and its output head kept float (``INT8_KEEP_FLOAT``): quantised, those cost most
of the error and of the frame-to-frame flicker for little of the time. The card records how far
the int8 buffers are from the float network's on held-out val identities; every other figure
on it is the int8 file's.

``--graft-onto FILE`` (a run that trained only the hair head, or only the albedo's head, from
FILE's rebuilt checkpoint): FILE's graph with that head added (graft.py), every other output
FILE's own, in place of exporting and quantising the whole network again; the card keeps FILE's
quantisation record and says what was grafted onto which file.
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import time

import numpy as np
import torch

from addon import contract, engine

from ..eval.report import cpu_name
from . import data, graft
from .model import (HAIR_TARGET, STRIDE, IntrinsicNet, has_albedo_head, has_hair, has_transfer,
                    unoccluded)
from .train import prepare

ROOT = pathlib.Path(__file__).resolve().parents[2]


def outputs(net: IntrinsicNet) -> list[tuple[str, int]]:
    """(name, channels) of the network's outputs, in the contract's order."""
    return ([(contract.OUTPUT_NORMAL, 3), (contract.OUTPUT_HEIGHT, 1), (contract.OUTPUT_ALBEDO, 3),
             (contract.OUTPUT_PARSING, len(net.classes))]
            + ([(contract.OUTPUT_TRANSFER, contract.TRANSFER_CHANNELS)] if net.transfer else []))


def export_onnx(net: IntrinsicNet, path: pathlib.Path) -> None:
    net.eval()
    names = [name for name, _ in outputs(net)]
    dyn = {"image": {0: "N", 2: "H", 3: "W"}, **{n: {0: "N", 2: "H", 3: "W"} for n in names}}
    torch.onnx.export(net, (torch.rand(1, 3, 128, 128),), str(path),
                      input_names=[contract.INPUT_IMAGE], output_names=names, opset_version=17,
                      dynamic_axes=dyn, dynamo=False)


def check_against_torch(net: IntrinsicNet, path: pathlib.Path) -> float:
    import onnxruntime as ort

    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    net.eval()  # batch statistics would differ from the exported running ones
    worst = 0.0
    for h, w in ((128, 128), (96, 160)):
        x = torch.rand(1, 3, h, w) * 0.8
        with torch.no_grad():
            ref = net(x)
        got = sess.run(None, {contract.INPUT_IMAGE: x.numpy()})
        for r, g in zip(ref, got):
            worst = max(worst, float(np.abs(r.numpy() - g).max()))
    if worst > 1e-3:
        raise RuntimeError(f"onnxruntime differs from PyTorch by {worst}")
    return worst


@torch.no_grad()
def val_inputs(n: int = 96, res: int = 128, cache_dir=None) -> tuple[dict, torch.Tensor]:
    """(batch, network inputs) of n held-out val identities through the simulated camera."""
    b = data.IntrinsicFrames("val", res, 4321, cache_dir).batch(range(n))
    return b, prepare(b, torch.Generator().manual_seed(7))


def onnx_forward(path: pathlib.Path, threads: int = 1):
    """The ONNX file as a function of a (N, 3, H, W) tensor, one image at a time: its buffers
    as tensors, as IntrinsicNet returns them."""
    from ..run.export import session

    sess = session(path, threads)

    def forward(x: torch.Tensor) -> tuple:
        outs = [sess.run(None, {contract.INPUT_IMAGE: x[i:i + 1].numpy()}) for i in range(len(x))]
        return tuple(torch.from_numpy(np.concatenate(k, 0)) for k in zip(*outs))

    return forward


@torch.no_grad()
def val_metrics(forward, n: int = 96, res: int = 128, cache_dir=None) -> dict:
    """Per-buffer errors on held-out val identities (through the simulated camera) of the
    network or of an exported file (onnx_forward); ``cache_dir``: another frame cache's val
    frames (long hair: training.intrinsic.data --long-hair)."""
    b, x = val_inputs(n, res, cache_dir)
    normal, height, albedo, parsing, *transfer = forward(x)
    fg = b["fg"] > 0.5
    t = b["target"]
    cos = (normal * t[:, 0:3]).sum(1, keepdim=True).clamp(-1, 1)
    ang = torch.rad2deg(torch.acos(cos))[fg]
    d = (height - t[:, 3:4])
    dm = torch.stack([d[i][fg[i]].median() for i in range(len(d))]).view(-1, 1, 1, 1)
    la = torch.log(albedo + 0.02) - torch.log(t[:, 4:7] + 0.02)
    la_m = torch.stack([la[i][:, fg[i, 0]].mean(1) for i in range(len(la))])[..., None, None]
    pm = parsing[:, 0:1] > 0.5
    tm = t[:, 7:8] > 0.5
    iou = float((pm & tm).sum() / (pm | tm).sum().clamp(min=1))
    pf, tf_ = parsing[:, 1:2] > 0.5, t[:, 8:9] > 0.5
    extra = {}
    if parsing.shape[1] > 2:
        ph, th = parsing[:, 2:3] > 0.5, t[:, HAIR_TARGET:HAIR_TARGET + 1] > 0.5
        extra["hair_iou"] = float((ph & th).sum() / (ph | th).sum().clamp(min=1))
    if transfer:
        # Mean absolute error of the transfer's coefficients, and that of the transfer the true
        # normals give unoccluded (what a network without it, exact in its normals, would miss).
        tt = t[:, data.TRANSFER].permute(1, 0, 2, 3)[:, fg[:, 0]]
        extra |= {"transfer_abs": float((transfer[0].permute(1, 0, 2, 3)[:, fg[:, 0]] - tt)
                                        .abs().mean()),
                  "transfer_abs_unoccluded_truth": float(
                      (unoccluded(t[:, 0:3]).permute(1, 0, 2, 3)[:, fg[:, 0]] - tt).abs().mean())}
    return {"normal_angle_deg_mean": float(ang.mean()), "normal_angle_deg_median": float(ang.median()),
            "height_abs_px": float((d - dm)[fg].abs().mean()),
            "albedo_log_abs": float((la - la_m).abs().permute(1, 0, 2, 3)[:, fg[:, 0]].mean()),
            "matte_iou": iou,
            "face_iou": float((pf & tf_).sum() / (pf | tf_).sum().clamp(min=1)), **extra,
            "samples": n, "split": "val (held-out identities)", "resolution": res}


# Left float in the int8 file (the modules whose convolutions they are): the first (it reads
# the image's full range), the full-resolution decoder block's two, the output head and the hair
# class's head (model.hair_head).
# In a trial on 16 held-out val frames, quantising every convolution put the buffers 3.9 degrees
# of normal (albedo 8% in log) from the float network's, the first and the head kept float 0.6
# degrees; on the dev footage (training.eval.footage_sheet) the latter still raised the relit
# frame-to-frame change over the input's from 1.00 to 1.07 on the steadiest clip, and with the
# full-resolution decoder float too, to 1.02, the network 1.3x faster than float instead of 1.6x
# (two threads).
INT8_KEEP_FLOAT = ("enc.0.0", "dec.0.0", "dec.0.3", "head", "hair_head")
INT8_CALIBRATION = 32  # training frames the activation ranges are calibrated on


def conv_nodes(path: pathlib.Path) -> list[str]:
    import onnx

    return [node.name for node in onnx.load(str(path)).graph.node if node.op_type == "Conv"]


def kept_float(convs: list[str]) -> list[str]:
    """The Conv node names (``/enc.0/enc.0.0/Conv``: module ``enc.0.0``) of INT8_KEEP_FLOAT's
    modules and of the modules inside them."""
    def module(name: str) -> str:
        return name.strip("/").split("/")[-2]

    return [c for c in convs if any(module(c) == m or module(c).startswith(m + ".")
                                    for m in INT8_KEEP_FLOAT)]


def quantise(float_path: pathlib.Path, out_path: pathlib.Path, calibration: dict,
             check: dict, res: int = 128) -> dict:
    """Write the int8 network of ``float_path`` to ``out_path`` (INT8_KEEP_FLOAT left float),
    its activation ranges calibrated on the frames of the batch ``calibration``; returns the
    card's record of it: how far its buffers are from the float network's over the foreground
    of the batch ``check`` (held-out frames), and both files' time in the same run."""
    from ..run.export import quantize_int8

    x = prepare(calibration, torch.Generator().manual_seed(11)).numpy()
    feeds = [{contract.INPUT_IMAGE: x[i:i + 1]} for i in range(len(x))]
    convs = conv_nodes(float_path)
    keep = kept_float(convs)
    quantize_int8(float_path, out_path, feeds, keep_float=keep)
    xv = prepare(check, torch.Generator().manual_seed(7))
    ref, got = onnx_forward(float_path)(xv), onnx_forward(out_path)(xv)
    fg = check["fg"][:, 0] > 0.5
    cos = torch.nn.functional.cosine_similarity(ref[0], got[0], dim=1).clamp(-1, 1)
    alb = (torch.log(ref[2] + 0.02) - torch.log(got[2] + 0.02)).abs().mean(1)
    ms = {"float": [], "int8": []}
    for _ in range(3):  # interleaved: the machine's load falls on both alike
        ms["float"].append(time_onnx(float_path, 1, res))
        ms["int8"].append(time_onnx(out_path, 1, res))
    return {"kind": "int8 static, QDQ, per-channel weights (onnxruntime.quantization)",
            "kept_float": keep, "calibration": f"{len(x)} training frames",
            "ms_one_thread": {k: round(float(np.median(v)), 2) for k, v in ms.items()},
            "against_float": {
                "normal_angle_deg_mean": float(torch.rad2deg(torch.acos(cos))[fg].mean()),
                "albedo_log_abs": float(alb[fg].mean()),
                "parsing_abs": float((ref[3] - got[3]).abs().mean()),
                **({"transfer_abs": float((ref[4] - got[4]).abs().mean(1)[fg].mean())}
                   if len(ref) > 4 else {}),
                "samples": len(xv), "split": "val (held-out identities)"}}


def time_onnx(path: pathlib.Path, threads: int, size: int = 128, runs: int = 20) -> float:
    import onnxruntime as ort

    sess = ort.InferenceSession(str(path), sess_options=engine.session_options(ort, threads),
                                providers=["CPUExecutionProvider"])
    x = {contract.INPUT_IMAGE: np.random.default_rng(0).random((1, 3, size, size), np.float32)}
    sess.run(None, x)
    t = []
    for _ in range(runs):
        t0 = time.perf_counter()
        sess.run(None, x)
        t.append(time.perf_counter() - t0)
    return float(np.median(t) * 1000)


TRAIN_ARGS = ("width", "res", "cache", "val_cache", "minutes", "steps", "batch", "lr", "ema",
              "seed", "threads", "val_n", "val_every", "zoom", "cut", "face_weight",
              "gradient_weight", "start_step", "init", "sky_flip", "studio", "up_weight",
              "albedo_weight", "low_weight", "low_sigma", "bright", "device", "workers", "out")


def train_command(recipe: dict) -> str:
    """The training command a run's recipe.json records (every argument that shapes the run)."""
    args = []
    for k in TRAIN_ARGS:
        v = recipe.get(k)
        if v is None or (k == "minutes" and recipe.get("minutes") is None):
            continue
        if k == "steps" and recipe.get("minutes"):
            continue  # a time-boxed run: --steps is not used
        args.append(f"--{k.replace('_', '-')} {v}")
    if not recipe.get("bf16", True):
        args.append("--no-bf16")
    if not recipe.get("transfer", False):  # runs recorded before the transfer had none
        args.append("--no-transfer")
    for flag in ("hair", "albedo_head", "hold_others"):
        if recipe.get(flag):
            args.append(f"--{flag.replace('_', '-')}")
    if recipe.get("hold_others") and recipe.get("learn"):
        args.append("--learn " + " ".join(recipe["learn"]))
    if recipe.get("train_only", "all") != "all":
        args.append(f"--train-only {recipe['train_only']}")
    return "python -m training.intrinsic.train " + " ".join(args)


def training_data(recipe: dict) -> str:
    """What the run's samples were, for the card."""
    text = ("synthetic light stage frames (training.intrinsic.data: ICT-FaceKit heads, CC0 HDRIs "
            "and backdrops) through a simulated camera (training.intrinsic.camera); exact "
            "per-pixel buffers as targets")
    share = float(recipe.get("long_hair") or 0.0)
    if share:
        text += (f"; the last run's frames gave {share:.0%} of the identities with hair long "
                 "hair (--long-hair), the runs before it none")
    return text


def lineage(run: pathlib.Path, checkpoint: str) -> dict:
    """The run's record for the card: its command, code, samples and the exported checkpoint's
    step, and (nested) the run its --init checkpoint came from, as training.run.reproduce reads."""
    recipe = json.loads((run / "recipe.json").read_text())
    state = torch.load(run / checkpoint, map_location="cpu")
    if "recovered_from" in recipe:  # rebuilt from a shipped ONNX (training.intrinsic.recover)
        return recovered_lineage(recipe, run, checkpoint, state)
    out = {"command": train_command(recipe), "args": {"out": recipe["out"]},
           "git_commit": recipe.get("git_commit"), "render_version": recipe.get("render_version"),
           "exported_checkpoint": {"file": checkpoint, "step": state.get("step")}}
    if recipe.get("accelerator"):
        out["machine"] = (f"{recipe.get('machine')}, {recipe.get('cpus')} CPUs, "
                          f"{recipe['accelerator']}")
    init = recipe.get("init")
    if init:
        parent = pathlib.Path(init)
        rec = lineage(parent.parent, parent.name) if (parent.parent / "recipe.json").is_file() else {}
        out["init"] = {"checkpoint": init, "step": rec.get("exported_checkpoint", {}).get("step"),
                       "recipe": rec.get("command"), "git_commit": rec.get("git_commit"),
                       "render_version": rec.get("render_version"), "init": rec.get("init")}
        if "recovered_from" in rec:
            out["init"]["recovered_from"] = rec["recovered_from"]
        stopped = json.loads((parent.parent / "recipe.json").read_text()).get("stopped")
        if stopped:
            out["init"]["note"] = stopped
    return out


def recovered_lineage(recipe: dict, run: pathlib.Path, checkpoint: str, state: dict) -> dict:
    """lineage() of a run folder training.intrinsic.recover made from a shipped ONNX: its
    command, the file it read, and (as ``init``) the runs behind that file, from its card."""
    src = recipe["recovered_from"]
    before = (src.get("card_training") or {}).get("recipe") or {}
    return {"command": recipe["command"], "args": {"out": str(run)},
            "git_commit": recipe.get("git_commit"), "render_version": before.get("render_version"),
            "exported_checkpoint": {"file": checkpoint, "step": state.get("step")},
            "recovered_from": {"onnx": src["onnx"], "sha256": src["sha256"]},
            "init": {"checkpoint": f"{before.get('args', {}).get('out')}/"
                                   f"{before.get('exported_checkpoint', {}).get('file')}",
                     "step": before.get("exported_checkpoint", {}).get("step"),
                     "recipe": before.get("command"), "git_commit": before.get("git_commit"),
                     "render_version": before.get("render_version"),
                     "init": before.get("init")} if before else None}


def parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--run", required=True)
    ap.add_argument("--checkpoint", default="best.pt")
    ap.add_argument("--name", default="relight-portrait")
    ap.add_argument("--preset", default="portrait")
    ap.add_argument("--out", default=str(ROOT / "models"))
    ap.add_argument("--working-size", type=int, default=128)
    ap.add_argument("--eval", type=int, default=64, help="held-out test samples for the card "
                    "(0: none, a quick export, e.g. of a run's --keep-every snapshots to measure "
                    "on real faces)")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--recommended", action="store_true",
                    help="mark the card as the recommended preset (the panel's default)")
    ap.add_argument("--long-hair-val", metavar="CACHE",
                    help="also measure the buffers on this frame cache's val frames (built with "
                         "training.intrinsic.data --split val --long-hair 1 --out CACHE)")
    ap.add_argument("--int8", action="store_true",
                    help="ship the network quantised to int8 (INT8_KEEP_FLOAT's layers float)")
    ap.add_argument("--init-share", type=float, default=0.0, metavar="S",
                    help="export the checkpoint's weights averaged with those of the run's --init "
                         "checkpoint, S being the init's share (0 <= S < 1; with_init)")
    ap.add_argument("--graft-onto", metavar="ONNX",
                    help="add the run's hair head or albedo head to this file (the one the "
                         "run's --init was rebuilt from) instead of exporting the whole network "
                         "(graft.py)")
    return ap


def with_init(state_dict: dict, recipe: dict, share: float) -> dict:
    """The run's weights averaged with its --init checkpoint's, ``share`` being the init's: a
    fine-tune and the network it started from lie in one basin, so every weight and batch
    statistic is interpolated between the two (integer counters stay the run's). A fine-tune
    on the light stage's frames alone improved them and lowered real faces' up/down balance;
    halfway back to its start kept the start's balance and most of the fine-tune's gain in
    PSNR (training/README.md, the fine-tunes' table)."""
    if not 0.0 <= share < 1.0:
        raise SystemExit(f"--init-share {share:g}: give the init's share, from 0 up to below 1.")
    init = recipe.get("init")
    if not init:
        raise SystemExit("--init-share: this run did not start from a checkpoint (no --init).")
    if not pathlib.Path(init).is_file():
        raise SystemExit(f"--init-share: the run's --init checkpoint {init} is not here; put it "
                         "back (training.run.reproduce makes it) or export without the option.")
    other = torch.load(init, map_location="cpu")["state_dict"]
    if set(other) != set(state_dict) or any(other[k].shape != v.shape
                                            for k, v in state_dict.items()):
        raise SystemExit(f"--init-share: {init} is another network than the run's checkpoint.")
    return {k: ((1.0 - share) * v + share * other[k]).to(v.dtype) if v.is_floating_point()
            else v for k, v in state_dict.items()}


def grafted(a, net: IntrinsicNet, onnx_path: pathlib.Path) -> dict:
    """--graft-onto: write ``onnx_path`` as the base file with the head of ``net``'s that the
    file lacks (the hair class's or the albedo's), and return the card's record of it: the base
    file, the check on held-out val frames and both files' time (interleaved, one thread), the
    base card's quantisation record (still the truth for every layer but the new head's, which
    is float) and its per-frame time (``frontier``, from bench.intrinsic_frontier, marked as the
    base file's until that bench is run again)."""
    base = pathlib.Path(a.graft_onto)
    base_card = engine.load_card(base)  # read before the same path is written
    new_heads = [h for h, has in (("hair", net.hair and "hair" not in base_card.classes),
                                  ("albedo", net.albedo and not graft.has_albedo_head(base)))
                 if has]
    if len(new_heads) != 1:
        raise SystemExit(f"{base}: the run's network must add one head the file lacks (hair or "
                         f"albedo); it would add {new_heads or 'none'}")
    head = new_heads[0]
    add, compare, output = graft.HEADS[head]
    record = {"onnx": str(base), "sha256": engine.file_sha256(base),
              "what": f"the {head} head (model.{head}_head) added to this file's graph; every "
                      "other output is the file's own"}
    base_bytes = base.read_bytes()
    part = onnx_path.with_suffix(".part.onnx")
    add(base, net, part)
    import onnxruntime as ort

    _, x = val_inputs(16)
    feeds = [{contract.INPUT_IMAGE: x[i:i + 1].numpy()} for i in range(len(x))]
    before = ort.InferenceSession(base_bytes, providers=["CPUExecutionProvider"])
    after = ort.InferenceSession(str(part), providers=["CPUExecutionProvider"])
    ref, got = ([np.concatenate(o, 0) for o in zip(*[s.run(None, f) for f in feeds])]
                for s in (before, after))
    with torch.no_grad():
        mine = net(x)[output].numpy()
    record["check"] = {**compare(ref, got, mine), "samples": len(x),
                       "split": "val (held-out identities)"}
    if record["check"]["other_outputs_max_abs_against_base"] != 0.0:
        part.unlink()
        raise SystemExit(f"grafting changed the other outputs: {record['check']}")
    ms = {"base": [], "grafted": []}
    for _ in range(5):  # interleaved: the machine's load falls on both alike
        ms["base"].append(time_onnx(base, 1, a.working_size))
        ms["grafted"].append(time_onnx(part, 1, a.working_size))
    record["ms_one_thread"] = {k: round(float(np.median(v)), 2) for k, v in ms.items()}
    record["machine"] = f"{cpu_name()}, {os.cpu_count()} cores"
    part.replace(onnx_path)
    front = base_card.data.get("frontier")
    if front:
        front = {**front, "file": f"measured on the file before the {head} head was grafted "
                                  f"(sha256 {record['sha256']}); graft.ms_one_thread says what "
                                  "the head adds to the network"}
    quant = base_card.data.get("quantisation")
    if quant:
        quant = {**quant, "kept_float": quant["kept_float"] + [
            c for c in conv_nodes(onnx_path) if c.startswith(f"/{head}_head/")]}
    return {"graft": record, "quantisation": quant, "frontier": front}


def main(argv=None):
    ap = parser()
    a = ap.parse_args(argv)
    if a.eval < 0:
        ap.error("--eval takes a number of samples, 0 or more")
    run = pathlib.Path(a.run)
    state = torch.load(run / a.checkpoint, map_location="cpu")
    recipe = json.loads((run / "recipe.json").read_text())
    if a.init_share:
        state = {**state, "state_dict": with_init(state["state_dict"], recipe, a.init_share)}
    net = IntrinsicNet(state["width"], has_transfer(state["state_dict"]),
                       has_hair(state["state_dict"]), has_albedo_head(state["state_dict"]))
    net.load_state_dict(state["state_dict"])
    net.eval()
    out = pathlib.Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    onnx_path = out / f"{a.name}.onnx"
    float_path = onnx_path.with_suffix(".float.onnx") if a.int8 else onnx_path
    quant = worst = graft_record = front = None
    if a.graft_onto:
        done = grafted(a, net, onnx_path)
        graft_record, quant, front = done["graft"], done["quantisation"], done["frontier"]
    else:
        export_onnx(net, float_path)
        worst = check_against_torch(net, float_path)
    if a.int8 and not a.graft_onto:
        try:
            calibration = data.IntrinsicFrames("train", 128, 97).batch(range(INT8_CALIBRATION))
            check = data.IntrinsicFrames("val", 128, 4321).batch(range(32))
            quant = quantise(float_path, onnx_path, calibration, check, a.working_size)
        finally:
            float_path.unlink(missing_ok=True)
    ms = {str(t): time_onnx(onnx_path, t, a.working_size) for t in (1, 2)}
    card_path = out / f"{a.name}.json"
    onnx_sha = engine.file_sha256(onnx_path)
    card = {
        "contract": contract.INTRINSIC_CONTRACT, "name": a.name, "preset": a.preset,
        "recommended": a.recommended, "onnx": onnx_path.name, "sha256": engine.file_sha256(onnx_path),
        "inputs": [{"name": contract.INPUT_IMAGE, "shape": ["N", 3, "H", "W"], "dtype": "float32"}],
        "outputs": [{"name": name, "shape": ["N", c, "H", "W"]} for name, c in outputs(net)],
        "stride": STRIDE, "working_size": a.working_size,
        "colour": {"space": "linear Rec.709 scene-referred, channels first",
                   "image": "a square crop around the portrait (addon.framing), scaled so its 90th "
                            "luminance percentile is 0.6 (addon.intrinsic.exposure_scale)"},
        "classes": list(net.classes),
        "training": {"data": training_data(recipe),
                     "render_version": recipe.get("render_version"),
                     "recipe": lineage(run, a.checkpoint)},
        "metrics": {},
        "cost": {"cpu": {"provider": "CPUExecutionProvider", "threads": 1, "batch": 1,
                         "per_size": {str(a.working_size): {"ms": round(ms["1"], 2),
                                                            "fps": round(1000 / ms["1"], 1)}},
                         "two_threads_ms": round(ms["2"], 2),
                         "what": "the network alone at the working size; the whole frame's "
                                 "path: python -m bench.intrinsic_speed"},
                 "machine": f"{cpu_name()}, {os.cpu_count()} cores, shared and noisy"},
        "architecture": {"kind": "U-Net, dense 3x3", "width": state["width"],
                         "parameters": sum(p.numel() for p in net.parameters())},
    }
    if a.init_share:
        card["training"]["init_share"] = {
            "share": a.init_share, "init": recipe["init"],
            "what": "the exported weights are the checkpoint's averaged with the run's --init "
                    "checkpoint's, this being the init's share"}
    if worst is not None:
        card["onnx_check_max_abs"] = worst
    if graft_record:
        card["graft"] = graft_record
    if front:
        card["frontier"] = front
    if quant:
        card["quantisation"] = quant
    card_path.write_text(json.dumps(card, indent=1) + "\n")  # the product path reads the card
    # Held-out figures: the relit test set through the product's path (as the end-to-end
    # presets' cards), and each buffer against the light stage on val identities.
    from ..eval import evaluate, predictors

    if a.eval:
        metrics = evaluate.card_metrics(predictors.product_predictor(onnx_path, a.threads),
                                        evaluate.heldout_dataset(128), a.eval, 128)
    else:  # a quick export (a run's snapshots, to be measured on real faces): no test set
        metrics = {"note": "exported with --eval 0: the held-out test set was not measured"}
    forward = onnx_forward(onnx_path) if a.int8 or a.graft_onto else net
    metrics["val_buffers"] = val_metrics(forward)
    if a.long_hair_val:
        long_hair = data.IntrinsicFrames("val", 128, 0, a.long_hair_val)
        metrics["val_buffers_long_hair"] = {
            **val_metrics(forward, min(64, long_hair.n), 128, a.long_hair_val),
            "split": "val (held-out identities), every one with hair wearing it long",
            "command": f"python -m training.intrinsic.data --split val --res 128 --frames "
                       f"{long_hair.n} --long-hair {long_hair.long_hair:g} --out {a.long_hair_val}"}
    card["metrics"] = metrics
    assert engine.file_sha256(onnx_path) == onnx_sha
    card_path.write_text(json.dumps(card, indent=1) + "\n")
    print(json.dumps({k: metrics[k] for k in ("model", "identity", "val_buffers", "note")
                      if k in metrics}, indent=1), ms)


if __name__ == "__main__":
    main()
