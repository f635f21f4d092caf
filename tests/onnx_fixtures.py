"""Tiny contract-conforming ONNX models built with onnx.helper (no torch), each with its card.

* ``write_toy_model(dir)``: a physically meaningful toy. The face is a flat Lambertian surface
  facing the camera, lit by a constant source estimate (uniform radiance 1 in the normalised
  image's units, so s in the footage's), so relit = image * E(target) / E(source) with E the
  irradiance on the normal +Z; parsing is a
  sigmoid of brightness computed at 1/8 resolution (so H and W must be multiples of the stride 8,
  like a real encoder-decoder, and the engine's padding is exercised).
* ``write_conv_model(dir, gflops_at_512)``: a random-weight encoder-decoder of a requested cost,
  for speed benchmarks.

* ``graph_model``, ``card_fields`` and ``save_model``: for tests that build models of their own.

Every card is laid out as training/run/export.py writes cards (addon.engine.load_card takes no
other layout). Other helpers' tests import these functions; keep their signatures stable.
"""

from __future__ import annotations

import hashlib
import json
import math
import pathlib

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

from addon import contract, lightvec

OPSET = 18
IR_VERSION = 8  # readable by every onnxruntime the extension may bundle
TOY_CLASSES = ("foreground", "skin")
TOY_STRIDE = 8


def frontal_irradiance_weights() -> np.ndarray:
    """(16, 16) weights w_t = max(0, d_t . z) Omega_t: E = sum_t L_t w_t for the normal +Z."""
    d = lightvec.directions()
    return (np.clip(d[..., 2], 0.0, None) * lightvec.solid_angles()).astype(np.float32)


def io_spec(n_classes: int):
    """The contract's graph inputs and outputs (value infos) for a model of ``n_classes``."""
    f = TensorProto.FLOAT
    inputs = [helper.make_tensor_value_info(contract.INPUT_IMAGE, f, ["N", 3, "H", "W"]),
              helper.make_tensor_value_info(contract.INPUT_LIGHT, f, ["N", 3, 16, 16])]
    outputs = [helper.make_tensor_value_info(contract.OUTPUT_RELIT, f, ["N", 3, "H", "W"]),
               helper.make_tensor_value_info(contract.OUTPUT_SOURCE_LIGHT, f, ["N", 3, 16, 16]),
               helper.make_tensor_value_info(contract.OUTPUT_PARSING, f,
                                             ["N", n_classes, "H", "W"])]
    return inputs, outputs


def _const(name: str, value) -> onnx.TensorProto:
    return numpy_helper.from_array(np.asarray(value), name)


def graph_model(nodes, inits: dict, name: str, n_classes: int = len(TOY_CLASSES)):
    """A contract model (opset OPSET, IR_VERSION) of ``nodes`` and initialisers ``inits``
    (name -> array)."""
    inputs, outputs = io_spec(n_classes)
    graph = helper.make_graph(nodes, name, inputs, outputs,
                              [numpy_helper.from_array(np.asarray(v), k) for k, v in inits.items()])
    m = helper.make_model(graph, opset_imports=[helper.make_opsetid("", OPSET)])
    m.ir_version = IR_VERSION
    return m


def card_fields(stride: int = 1, working: int = 64, classes=TOY_CLASSES,
                preset: str = "test") -> dict:
    """The card entries that differ between fixture models (save_model's ``card_extra``)."""
    return {"preset": preset, "stride": stride, "working_size": working, "classes": list(classes)}


def save_model(model: onnx.ModelProto, out_dir, name: str, card_extra: dict) -> pathlib.Path:
    """Write ``model`` as ``out_dir``/``name``.onnx with its card, laid out as
    training/run/export.py writes cards (``card_extra``: card_fields, and any entry to add or
    replace); returns the .onnx path."""
    onnx.checker.check_model(model)
    out_dir = pathlib.Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    path = out_dir / f"{name}.onnx"
    path.write_bytes(model.SerializeToString())
    classes = card_extra.get("classes", list(TOY_CLASSES))
    tensors = [(contract.INPUT_IMAGE, ["N", 3, "H", "W"]),
               (contract.INPUT_LIGHT, ["N", 3, 16, 16]),
               (contract.OUTPUT_RELIT, ["N", 3, "H", "W"]),
               (contract.OUTPUT_SOURCE_LIGHT, ["N", 3, 16, 16]),
               (contract.OUTPUT_PARSING, ["N", len(classes), "H", "W"])]
    entries = [{"name": n, "shape": shape, "dtype": "float32"} for n, shape in tensors]
    card = {
        "contract": contract.CONTRACT_VERSION,
        "name": name,
        "preset": "test",
        "onnx": path.name,
        "sha256": hashlib.sha256(path.read_bytes()).hexdigest(),
        "inputs": entries[:2],
        "outputs": entries[2:],
        "stride": TOY_STRIDE,
        "working_size": 64,
        "colour": {"space": "linear Rec.709, exposure-normalised (addon/normalise.py)"},
        "relit_scale": contract.RELIT_SCALE,
        "classes": list(classes),
        "training": {"data": "none: a test fixture built by tests/onnx_fixtures.py"},
        "metrics": {},
        "cost": {"cpu": {"provider": "CPUExecutionProvider", "threads": 1, "batch": 1,
                         "per_size": {}}},
        **card_extra,
    }
    path.with_suffix(".json").write_text(json.dumps(card, indent=2), encoding="utf-8")
    return path


def build_toy_model() -> onnx.ModelProto:
    w = frontal_irradiance_weights()
    e_source = float(w.sum())  # irradiance from the constant source estimate, uniform radiance 1
    nodes = [
        # relit = image * E(target) / E(source)
        helper.make_node("Mul", [contract.INPUT_LIGHT, "w_front"], ["lw"]),
        helper.make_node("ReduceSum", ["lw", "axes_hw"], ["e_target"], keepdims=1),
        helper.make_node("Mul", ["e_target", "inv_e_source"], ["gain"]),
        helper.make_node("Mul", [contract.INPUT_IMAGE, "gain"], [contract.OUTPUT_RELIT]),
        # source_light: the constant estimate, one per batch item
        helper.make_node("Mul", [contract.INPUT_LIGHT, "zero"], ["zeros"]),
        helper.make_node("Add", ["zeros", "one"], [contract.OUTPUT_SOURCE_LIGHT]),
        # parsing: sigmoids of brightness at 1/8 resolution, upsampled (nearest) by 8
        helper.make_node("ReduceMean", [contract.INPUT_IMAGE, "axes_c"], ["lum"], keepdims=1),
        helper.make_node("AveragePool", ["lum"], ["lum8"], kernel_shape=[TOY_STRIDE] * 2,
                         strides=[TOY_STRIDE] * 2),
        helper.make_node("Sub", ["lum8", "fg_level"], ["fg_in"]),
        helper.make_node("Mul", ["fg_in", "fg_gain"], ["fg_logit"]),
        helper.make_node("Concat", ["fg_logit", "lum8"], ["logits"], axis=1),
        helper.make_node("Sigmoid", ["logits"], ["prob8"]),
        helper.make_node("Resize", ["prob8", "", "scales8"], [contract.OUTPUT_PARSING],
                         mode="nearest"),
    ]
    inits = [
        _const("w_front", w[None, None]),
        _const("axes_hw", np.array([2, 3], np.int64)),
        _const("axes_c", np.array([1], np.int64)),
        _const("inv_e_source", np.float32(1.0 / e_source)),
        _const("zero", np.float32(0.0)),
        _const("one", np.float32(1.0)),
        _const("fg_level", np.float32(0.05)),
        _const("fg_gain", np.float32(20.0)),
        _const("scales8", np.array([1, 1, TOY_STRIDE, TOY_STRIDE], np.float32)),
    ]
    inputs, outputs = io_spec(len(TOY_CLASSES))
    graph = helper.make_graph(nodes, "relight_toy", inputs, outputs, inits)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", OPSET)],
                              producer_name="tests/onnx_fixtures.py")
    model.ir_version = IR_VERSION
    return model


def toy_reference(image_chw: np.ndarray, light_hwc: np.ndarray) -> np.ndarray:
    """What the toy's relit output must be (numpy, float64): for checking the engine."""
    e_t = np.tensordot(frontal_irradiance_weights(), np.asarray(light_hwc, np.float64),
                       axes=([0, 1], [0, 1]))
    return np.asarray(image_chw, np.float64) * (e_t / frontal_irradiance_weights().sum())[:, None,
                                                                                          None]


def write_toy_model(out_dir, name: str = "toy") -> pathlib.Path:
    """Write the toy model and its card into ``out_dir``; return the .onnx path."""
    return save_model(build_toy_model(), out_dir, name,
                      card_fields(TOY_STRIDE, 64, TOY_CLASSES, "toy"))


# ---- random-weight conv net of a requested cost ----------------------------------------------

def _conv_layers(c: int, n_mid: int, k: int):
    """(name, c_in, c_out, stride, upsample_first, out_scale) of the encoder-decoder layers;
    out_scale is the output resolution relative to the input (1, 1/2, ...)."""
    return ([("e1", 3, c, 2, False, 1 / 2), ("e2", c, 2 * c, 2, False, 1 / 4),
             ("e3", 2 * c, 4 * c, 2, False, 1 / 8)]
            + [(f"m{i}", 4 * c, 4 * c, 1, False, 1 / 8) for i in range(n_mid)]
            + [("d3", 4 * c, 2 * c, 1, True, 1 / 4), ("d2", 2 * c, c, 1, True, 1 / 2),
               ("d1", c, 3 + k, 1, True, 1.0)])


def conv_gflops(c: int, n_mid: int = 2, k: int = len(contract.PARSING_CLASSES),
                size: int = 512) -> float:
    """Multiply-adds x 2 of the 3x3 convolutions at size x size (the bulk of the cost)."""
    macs = sum(9 * ci * co * (size * s) ** 2 for _, ci, co, _, _, s in _conv_layers(c, n_mid, k))
    return 2.0 * macs / 1e9


def build_conv_model(gflops_at_512: float = 5.0, n_mid: int = 2, seed: int = 0):
    """(model, width, gflops) for the narrowest width whose cost reaches ``gflops_at_512``."""
    k = len(contract.PARSING_CLASSES)
    c = 1
    while conv_gflops(c, n_mid, k) < gflops_at_512:
        c += 1
    rng = np.random.default_rng(seed)
    nodes, inits, x = [], [], contract.INPUT_IMAGE
    for name, ci, co, stride, up, _ in _conv_layers(c, n_mid, k):
        if up:
            nodes.append(helper.make_node("Resize", [x, "", "scales2"], [f"{name}_up"],
                                          mode="nearest"))
            x = f"{name}_up"
        w = rng.standard_normal((co, ci, 3, 3)).astype(np.float32) * math.sqrt(2.0 / (9 * ci))
        inits += [_const(f"{name}_w", w), _const(f"{name}_b", np.zeros(co, np.float32))]
        nodes.append(helper.make_node("Conv", [x, f"{name}_w", f"{name}_b"], [f"{name}_conv"],
                                      kernel_shape=[3, 3], pads=[1, 1, 1, 1],
                                      strides=[stride, stride]))
        if name != "d1":
            nodes.append(helper.make_node("Relu", [f"{name}_conv"], [f"{name}_out"]))
            x = f"{name}_out"
        if name == "e3" or (n_mid and name == f"m{n_mid - 1}"):
            bottleneck = x
    mid = 4 * c
    fc = rng.standard_normal((mid, 768)).astype(np.float32) * math.sqrt(1.0 / mid)
    inits += [_const("scales2", np.array([1, 1, 2, 2], np.float32)),
              _const("fc_w", fc), _const("fc_b", np.zeros(768, np.float32)),
              _const("src_shape", np.array([-1, 3, 16, 16], np.int64)),
              _const("axes_hw", np.array([2, 3], np.int64)),
              _const("split", np.array([3, k], np.int64)),
              _const("tenth", np.float32(0.1))]
    nodes += [
        # relit = image * exp(0.1 tanh(net)) * mean target light: bounded, light-linear
        helper.make_node("Split", ["d1_conv", "split"], ["rgb_logit", "parse_logit"], axis=1),
        helper.make_node("Tanh", ["rgb_logit"], ["rgb_t"]),
        helper.make_node("Mul", ["rgb_t", "tenth"], ["rgb_s"]),
        helper.make_node("Exp", ["rgb_s"], ["rgb_gain"]),
        helper.make_node("ReduceMean", [contract.INPUT_LIGHT, "axes_hw"], ["light_mean"],
                         keepdims=1),
        helper.make_node("Mul", [contract.INPUT_IMAGE, "rgb_gain"], ["relit_a"]),
        helper.make_node("Mul", ["relit_a", "light_mean"], [contract.OUTPUT_RELIT]),
        helper.make_node("Sigmoid", ["parse_logit"], [contract.OUTPUT_PARSING]),
        # source light from the pooled bottleneck
        helper.make_node("GlobalAveragePool", [bottleneck], ["pooled"]),
        helper.make_node("Flatten", ["pooled"], ["flat"]),
        helper.make_node("Gemm", ["flat", "fc_w", "fc_b"], ["src_logit"]),
        helper.make_node("Softplus", ["src_logit"], ["src_pos"]),
        helper.make_node("Reshape", ["src_pos", "src_shape"], [contract.OUTPUT_SOURCE_LIGHT]),
    ]
    inputs, outputs = io_spec(k)
    graph = helper.make_graph(nodes, "relight_conv_bench", inputs, outputs, inits)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", OPSET)],
                              producer_name="tests/onnx_fixtures.py")
    model.ir_version = IR_VERSION
    return model, c, conv_gflops(c, n_mid, k)


def write_conv_model(out_dir, gflops_at_512: float = 5.0, name: str = "conv_bench",
                     n_mid: int = 2, seed: int = 0) -> pathlib.Path:
    """Write a random-weight conv model of about ``gflops_at_512`` GFLOP per 512x512 frame."""
    model, width, gflops = build_conv_model(gflops_at_512, n_mid, seed)
    return save_model(model, out_dir, name, {
        **card_fields(8, 512, contract.PARSING_CLASSES, "bench"),
        "architecture": {"width": width, "n_mid": n_mid,
                         "gflop_per_frame": {"512": round(gflops, 3)}}})
