"""Predictors: ``predict(sample) -> (relit (3, H, W) absolute, extras)`` for a PyTorch network, an
exported ONNX model, or an intrinsic model through the product's own path, each fed the light-stage
sample exactly as the engine feeds a clip."""

from __future__ import annotations

import json

import numpy as np


def _normalised_inputs(sample: dict):
    """The engine's path: one exposure scale for the clip, the target light at unit power."""
    from ..model import units  # training-side normalisation == the engine's (addon.normalise)

    n = units.normalise_sample(sample)
    return n["img_t"][None], n["light_k"][None], float(n["scale"]), float(n["light_scale"])


def _absolute(relit, s, k):
    from ..model.units import relit_to_absolute  # the one place that defines the output's units

    return relit_to_absolute(relit, s, k)


def _pad(img: np.ndarray, stride: int) -> np.ndarray:
    h, w = img.shape[-2:]
    return np.pad(img, ((0, 0), (0, 0), (0, -h % stride), (0, -w % stride)), mode="reflect")


def _source_light(src, s) -> np.ndarray:
    """The network's source-light estimate (1, 3, 16, 16) for image / s -> absolute (16, 16, 3)."""
    return np.asarray(src, np.float32)[0].transpose(1, 2, 0) * np.float32(s)


def onnx_predictor(session, stride: int):
    def predict(sample):
        img, light, s, k = _normalised_inputs(sample)
        h, w = img.shape[-2:]
        relit, src, parsing = session.run(None, {"image": _pad(img, stride),
                                                 "target_light": light})
        return _absolute(relit[0, :, :h, :w], s, k), {"foreground": parsing[0, 0, :h, :w],
                                                      "source_light": _source_light(src, s)}
    return predict


def product_predictor(onnx_path, threads: int = 1):
    """An intrinsic model as the product runs it (``addon.relight_image``: framing, buffers,
    renderer, the footage's exposure kept): its figures are the product's. The level it keeps is
    the input's, so ``rmse_level_fit`` is the figure comparable with the end-to-end models."""
    from addon import api

    def predict(sample):
        img = np.ascontiguousarray(np.asarray(sample["img_t_i"], np.float32).transpose(1, 2, 0))
        out = api.relight_image(img, sample["light_k"], model=onnx_path, threads=threads)
        return np.ascontiguousarray(out.transpose(2, 0, 1)), {}
    return predict


def onnx_file_predictor(path, threads: int):
    """(predict, card) for an exported model: its card (the .json beside an .onnx) gives the
    stride; onnxruntime on the CPU with ``threads`` threads. Intrinsic models run through the
    product's path (product_predictor)."""
    import onnxruntime as ort

    from addon import contract

    path = str(path)
    card = json.loads(open(path[:-5] + ".json").read()) if path.endswith(".onnx") else {}
    if card.get("contract") == contract.INTRINSIC_CONTRACT:
        return product_predictor(path, threads), card
    so = ort.SessionOptions()
    so.intra_op_num_threads = threads
    session = ort.InferenceSession(path, so, providers=["CPUExecutionProvider"])
    return onnx_predictor(session, int(card.get("stride", 32))), card


def torch_predictor(net, true_source: bool = False):
    """``true_source``: the decoder gets the sample's true source light (normalised as the
    network's inputs are) in place of the encoder's estimate: a diagnostic of how much the
    estimate costs (the ONNX contract always uses the estimate)."""
    import torch

    def predict(sample):
        img, light, s, k = _normalised_inputs(sample)
        h, w = img.shape[-2:]
        x, target = torch.from_numpy(_pad(img, net.cfg.stride)), torch.from_numpy(light)
        with torch.no_grad():
            if true_source:
                from ..model.network import to_channels_first

                _, skips, code = net.encoder(x)
                src = torch.from_numpy(to_channels_first(np.asarray(sample["light_i"],
                                                                    np.float32) / s))[None]
                relit, src, parsing = net.relight_from(x, target, skips, code, src)
            else:
                relit, src, parsing = net(x, target)
        return (_absolute(relit[0, :, :h, :w].numpy(), s, k),
                {"foreground": parsing[0, 0, :h, :w].numpy(),
                 "source_light": _source_light(src.numpy(), s)})
    return predict
