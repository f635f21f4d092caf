"""Rebuild a training checkpoint from a shipped intrinsic model's ONNX file, so that training can
go on from a shipped model on a machine that never had the run folder it came from (run folders
are not committed).

    .venv/bin/python -m training.intrinsic.recover --onnx models/relight-portrait.onnx \
        --out runs/portrait-recovered [--cache cache/intrinsic-long]

The export folds each batch normalisation into the convolution before it, and ``--int8`` stores
most convolutions' weights as int8 with a scale per output channel. Each convolution's weights
and bias are read back (dequantised where stored as int8) into ``IntrinsicNet`` by the node's
name (``/enc.0/enc.0.0/Conv`` is module ``enc.0.0``), and each batch normalisation is set so
that it passes on the convolution's output plus the folded bias: exactly so in evaluation mode;
in training mode, where it normalises by the batch's own statistics, nearly so, its scale and
shift being set from the statistics of that output over training frames (``--frames``).

Writes ``<out>/best.pt`` (what ``train --init`` loads) and ``<out>/recipe.json``: the ONNX's
sha256 and its card's training record, which the card of a network trained from it nests
(``export.lineage``). Prints how far the rebuilt network is from the ONNX file in both modes:
int8 activations are quantised too, so an int8 file's rebuilt float network differs from it by
about what the card's ``quantisation.against_float`` records.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import pathlib

import numpy as np
import torch

from addon import contract, engine

from . import data
from .model import IntrinsicNet
from .train import git_commit, prepare

ROOT = pathlib.Path(__file__).resolve().parents[2]


def conv_weights(path: pathlib.Path) -> dict[str, tuple[np.ndarray, np.ndarray | None]]:
    """{module name: (weight, bias)} of every Conv node in an ONNX file, dequantised where the
    weights come through DequantizeLinear (int8 QDQ, per-channel or per-tensor)."""
    import onnx
    from onnx import numpy_helper

    graph = onnx.load(str(path)).graph
    inits = {t.name: numpy_helper.to_array(t) for t in graph.initializer}
    made_by = {out: node for node in graph.node for out in node.output}

    def value(name: str) -> np.ndarray:
        if name in inits:
            return inits[name].astype(np.float32)
        node = made_by.get(name)
        if node is not None and node.op_type == "Identity":  # the exporter shares equal tensors
            return value(node.input[0])
        if node is not None and node.op_type == "Constant":
            return numpy_helper.to_array(node.attribute[0].t).astype(np.float32)
        if node is None or node.op_type != "DequantizeLinear":
            raise ValueError(f"{path}: {name} is neither a weight nor a dequantised weight")
        q = inits[node.input[0]].astype(np.float32)
        scale = inits[node.input[1]].astype(np.float32)
        zero = (inits[node.input[2]].astype(np.float32) if len(node.input) > 2
                else np.zeros_like(scale))
        axis = next((a.i for a in node.attribute if a.name == "axis"), 1)
        if scale.ndim == 1 and scale.size > 1:  # per channel along ``axis``
            shape = [1] * q.ndim
            shape[axis] = -1
            scale, zero = scale.reshape(shape), zero.reshape(shape)
        return (q - zero) * scale

    out = {}
    for node in graph.node:
        if node.op_type != "Conv":
            continue
        module = node.name.strip("/").split("/")[-2] if node.name.count("/") > 1 else None
        if not module:
            raise ValueError(f"{path}: cannot tell which module the Conv node {node.name!r} is")
        bias = value(node.input[2]) if len(node.input) > 2 and node.input[2] else None
        out[module] = (value(node.input[1]), bias)
    return out


def conv_outputs(net: IntrinsicNet, x: torch.Tensor) -> dict[str, list[torch.Tensor]]:
    """Per-channel mean and variance of each folded convolution's output (before its batch
    normalisation) over the batch ``x``, in evaluation mode."""
    stats, hooks = {}, []
    for name, module in net.named_modules():
        if isinstance(module, torch.nn.Conv2d) and name != "head":
            def hook(mod, inp, out, name=name):
                y = out.detach().double()
                stats[name] = [y.mean((0, 2, 3)), y.var((0, 2, 3), unbiased=False)]
            hooks.append(module.register_forward_hook(hook))
    net.eval()
    with torch.no_grad():
        net(x)
    for h in hooks:
        h.remove()
    return stats


def architecture(card: engine.ModelCard) -> tuple[str, bool, bool]:
    """(width, whether it predicts the transfer, whether it predicts hair) of a shipped model,
    from its card."""
    outputs = [o["name"] for o in card.data.get("outputs", [])]
    return (card.data.get("architecture", {}).get("width", "standard"),
            contract.OUTPUT_TRANSFER in outputs, "hair" in card.classes)


def rebuild(path: pathlib.Path, width: str, transfer: bool,
            calibration: torch.Tensor, hair: bool = False) -> IntrinsicNet:
    """The IntrinsicNet(width, transfer, hair) of an ONNX file, its batch normalisations set
    from ``calibration`` (a batch of prepared training inputs); with the albedo's own head
    (model.albedo_head) where the file has one."""
    convs = conv_weights(path)
    net = IntrinsicNet(width, transfer=transfer, hair=hair,
                       albedo=any(n.startswith("albedo_head.") for n in convs))
    modules = dict(net.named_modules())
    if set(convs) != {n for n, m in modules.items() if isinstance(m, torch.nn.Conv2d)}:
        raise ValueError(f"{path}: its convolutions are not those of a {width} IntrinsicNet")
    folded = {}  # conv name -> the batch normalisation folded into it
    for name, (w, b) in convs.items():
        conv = modules[name]
        if tuple(conv.weight.shape) != w.shape:
            raise ValueError(f"{path}: {name} has shape {w.shape}, the network "
                             f"{tuple(conv.weight.shape)}")
        with torch.no_grad():
            conv.weight.copy_(torch.from_numpy(w))
            if conv.bias is not None:
                conv.bias.copy_(torch.from_numpy(b))
                continue
        parent, index = name.rsplit(".", 1)
        bn = modules[f"{parent}.{int(index) + 1}"]
        folded[name] = bn
        with torch.no_grad():  # first the identity plus the folded bias: exact in eval mode
            bn.weight.fill_(1.0)
            bn.bias.copy_(torch.from_numpy(b))
            bn.running_mean.zero_()
            bn.running_var.fill_(1.0 - bn.eps)
    # Then scale and shift such that training mode's batch statistics about reproduce it:
    # eval mode gives gamma (y - mean) / sqrt(var + eps) + beta = y + b for gamma =
    # sqrt(var + eps), beta = mean + b, whatever the mean and var; training mode, with the
    # batch's own, about the same.
    stats = conv_outputs(net, calibration)
    with torch.no_grad():
        for name, bn in folded.items():
            mean, var = stats[name]
            var = var.float()
            b = bn.bias.clone()
            bn.running_mean.copy_(mean.float())
            bn.running_var.copy_(var)
            bn.weight.copy_(torch.sqrt(var + bn.eps))
            bn.bias.copy_(mean.float() + b)
    return net


def distance(net: IntrinsicNet, path: pathlib.Path, x: torch.Tensor) -> dict:
    """Mean absolute difference per output between the rebuilt network (evaluation and
    training mode) and the ONNX file on the batch ``x`` (held-out val frames)."""
    import onnxruntime as ort

    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    names = [o.name for o in sess.get_outputs()]
    ref = sess.run(None, {contract.INPUT_IMAGE: x.numpy()})
    out = {}
    for mode in ("eval", "train"):
        net.train(mode == "train")
        with torch.no_grad():
            got = net(x)
        out[mode] = {n: float(np.abs(g.numpy() - r).mean()) for n, g, r in zip(names, got, ref)}
    net.eval()
    return out


def save(net: IntrinsicNet, out: pathlib.Path, path: pathlib.Path, card_training: dict | None,
         check: dict, command: str) -> None:
    """Write ``out``/best.pt and ``out``/recipe.json for the network rebuilt from ``path``
    (``card_training``: its card's training record, which export.lineage nests)."""
    out.mkdir(parents=True, exist_ok=True)
    step = ((card_training or {}).get("recipe") or {}).get("exported_checkpoint", {}).get("step")
    recovered = {"onnx": str(path), "sha256": hashlib.sha256(path.read_bytes()).hexdigest(),
                 "card_training": card_training, "against_onnx": check}
    torch.save({"state_dict": net.state_dict(), "width": net.width, "step": step,
                "recovered_from": recovered}, out / "best.pt")
    (out / "recipe.json").write_text(json.dumps(
        {"command": command, "width": net.width, "git_commit": git_commit(),
         "transfer": net.transfer, "recovered_from": recovered}, indent=2))


def calibration_batch(cache, res: int, frames: int, seed: int = 5,
                      split: str = "train") -> torch.Tensor:
    """``frames`` prepared inputs of the cache's ``split``, as training feeds them."""
    ds = data.IntrinsicFrames(split, res, seed, cache)
    return prepare(ds.batch(range(frames)), torch.Generator().manual_seed(seed))


def parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--onnx", required=True, help="an intrinsic model's .onnx (its card beside)")
    ap.add_argument("--out", required=True, help="run folder to write best.pt and recipe.json")
    ap.add_argument("--cache", help="intrinsic frame cache root (default cache/intrinsic)")
    ap.add_argument("--frames", type=int, default=48,
                    help="training frames the batch normalisations are set from")
    ap.add_argument("--res", type=int, default=128)
    return ap


def main(argv=None):
    a = parser().parse_args(argv)
    path = pathlib.Path(a.onnx)
    card = engine.load_card(path)
    x = calibration_batch(a.cache, a.res, a.frames)
    width, transfer, hair = architecture(card)
    net = rebuild(path, width, transfer, x, hair)
    check = distance(net, path, calibration_batch(a.cache, a.res, 12, seed=6, split="val"))
    cmd = (f"python -m training.intrinsic.recover --onnx {a.onnx} --out {a.out}"
           + (f" --cache {a.cache}" if a.cache else "") + f" --frames {a.frames}")
    save(net, pathlib.Path(a.out), path, card.data.get("training"), check, cmd)
    for mode, d in check.items():
        print(f"{mode} mode against the ONNX file, mean abs: "
              + ", ".join(f"{k} {v:.4f}" for k, v in d.items()))
    print(pathlib.Path(a.out) / "best.pt")


if __name__ == "__main__":
    main()
