"""Give a shipped intrinsic network file the hair class or the albedo's own head, leaving the rest
of the file as it is.

    .venv/bin/python -m training.intrinsic.export --run runs/portrait-hair \
        --graft-onto models/relight-portrait.onnx ...

A run trained with ``--hair --train-only hair`` from a file's rebuilt checkpoint
(training.intrinsic.recover) changed only the hair head (model.hair_head); every other layer is
the file's own. Exporting that run afresh would quantise those layers again, and their int8
activation ranges, calibrated on the rebuilt float network rather than the one the file was
made from, move every buffer by about the int8 rounding (the card's
``quantisation.against_float``), and every figure measured on the file with them. So the hair
head is added to the file's graph instead: its three convolutions (float, as export's
INT8_KEEP_FLOAT keeps the head), reading what they read in IntrinsicNet (the full-resolution
decoder block's output averaged down to half size, beside the second-finest block's output),
their logit enlarged to the input's size, and its sigmoid appended to ``parsing`` as a third
channel. Every other output stays the file's to the bit; the node names are IntrinsicNet's
(``/hair_head/hair_head.0/Conv``), so recover reads the result back as it reads an exported
file.

The albedo's head (a ``--albedo-head --train-only albedo`` run, model.albedo_head) is grafted
the same way (``graft_albedo``): its convolutions read the full-resolution decoder block's output
beside the encoded input image (the first convolution's input), their correction is added to the
albedo's logit ahead of its sigmoid, and every other output stays the file's to the bit.
"""

from __future__ import annotations

import pathlib

import numpy as np

from addon import contract

from .model import IntrinsicNet

HEAD_CONV = "/head/Conv"            # the output head: its input is the finest block's output
FINE_BLOCK_CONV = "/dec.0/dec.0.0/Conv"  # the finest decoder block's first convolution
FIRST_CONV = "/enc.0/enc.0.0/Conv"  # the first convolution: its input is the encoded image


def _producer(graph, name: str):
    return next(n for n in graph.node if name in n.output)


def _base_graph(base: pathlib.Path, head: str, needs: tuple[str, ...]):
    """(model, graph, {node name: node}) of the ONNX file ``base``, refused where it has the
    ``head`` (a module name: hair_head, albedo_head) already or lacks a node of ``needs``."""
    import onnx

    model = onnx.load(str(base))
    g = model.graph
    nodes = {n.name: n for n in g.node}
    if any(n.name.startswith(f"/{head}/") for n in g.node):
        raise ValueError(f"{base} already has a {head.replace('_', ' ')}")
    missing = [n for n in needs if n not in nodes]
    if missing:
        raise ValueError(f"{base}: not an intrinsic network's graph (no {' or '.join(missing)} "
                         "node)")
    return model, g, nodes


def graft(base: pathlib.Path, net: IntrinsicNet, out: pathlib.Path) -> None:
    """Write ``out``: the ONNX file ``base`` (an IntrinsicNet without the hair class, exported by
    export.py, float or int8) with ``net``'s hair head added. ``base`` may be ``out``."""
    import onnx
    from onnx import helper, numpy_helper

    if not net.hair:
        raise ValueError("the network has no hair head to graft")
    model, g, nodes = _base_graph(base, "hair_head", (HEAD_CONV, FINE_BLOCK_CONV))
    fine = nodes[HEAD_CONV].input[0]
    cat = _producer(g, nodes[FINE_BLOCK_CONV].input[0])
    resize = _producer(g, cat.input[0])
    if cat.op_type != "Concat" or resize.op_type != "Resize":
        raise ValueError(f"{base}: the finest decoder block does not read an enlarged coarser "
                         "block as IntrinsicNet does")
    coarse = resize.input[0]
    parsing = _producer(g, contract.OUTPUT_PARSING)
    parsing.output[0] = "/hair/parsing_base"

    convs, x = _head_nodes(g, net.hair_head, "hair_head", "/hair/cat")
    g.initializer.append(numpy_helper.from_array(np.float32([1, 1, 2, 2]), "/hair/scales"))
    n = helper.make_node
    new = [n("AveragePool", [fine], ["/hair/pool"], name="/hair/AveragePool",
             kernel_shape=[2, 2], strides=[2, 2]),
           n("Concat", ["/hair/pool", coarse], ["/hair/cat"], name="/hair/Concat", axis=1)]
    new += convs
    new += [n("Resize", [x, "", "/hair/scales"], ["/hair/up"], name="/hair/Resize",
              mode="linear", coordinate_transformation_mode="half_pixel"),
            n("Sigmoid", ["/hair/up"], ["/hair/p"], name="/hair/Sigmoid"),
            n("Concat", ["/hair/parsing_base", "/hair/p"], [contract.OUTPUT_PARSING],
              name="/hair/parsing", axis=1)]
    g.node.extend(new)
    for o in g.output:
        if o.name == contract.OUTPUT_PARSING:
            o.type.tensor_type.shape.dim[1].dim_value = len(net.classes)
    onnx.checker.check_model(model)
    onnx.save(model, str(out))


def _head_nodes(g, net_head, prefix: str, x: str) -> tuple[list, str]:
    """``net_head``'s convolutions (float) as ONNX nodes named as IntrinsicNet's, reading ``x``,
    a ReLU after each but the last; their initialisers are added to ``g``. Returns the nodes and
    the name of the last one's output."""
    from onnx import helper, numpy_helper

    convs = [(f"{prefix}.{i}", m) for i, m in enumerate(net_head) if hasattr(m, "weight")]
    for name, conv in convs:
        for part in ("weight", "bias"):
            g.initializer.append(numpy_helper.from_array(
                getattr(conv, part).detach().numpy().astype(np.float32), f"{name}.{part}"))
    nodes = []
    for i, (name, conv) in enumerate(convs):
        k = conv.kernel_size[0]
        y = f"/{prefix}/{name}/Conv_output_0"
        nodes.append(helper.make_node(
            "Conv", [x, f"{name}.weight", f"{name}.bias"], [y], name=f"/{prefix}/{name}/Conv",
            kernel_shape=[k, k], pads=[k // 2] * 4, strides=[1, 1], dilations=[1, 1], group=1))
        x = y
        if i < len(convs) - 1:
            nodes.append(helper.make_node("Relu", [y], [f"{y}_relu"],
                                          name=f"/{prefix}/{name}/Relu"))
            x = f"{y}_relu"
    return nodes, x


def has_albedo_head(path: pathlib.Path) -> bool:
    """Whether the ONNX file at ``path`` has the albedo's own head."""
    import onnx

    return any(n.name.startswith("/albedo_head/") for n in onnx.load(str(path)).graph.node)


def graft_albedo(base: pathlib.Path, net: IntrinsicNet, out: pathlib.Path) -> None:
    """Write ``out``: the ONNX file ``base`` (an IntrinsicNet without the albedo's own head,
    exported by export.py, float or int8, with or without a grafted hair head) with ``net``'s
    albedo head added. ``base`` may be ``out``."""
    import onnx
    from onnx import helper

    if not net.albedo:
        raise ValueError("the network has no albedo head to graft")
    model, g, nodes = _base_graph(base, "albedo_head", (HEAD_CONV, FIRST_CONV))
    sigmoid = _producer(g, contract.OUTPUT_ALBEDO)
    if sigmoid.op_type != "Sigmoid":
        raise ValueError(f"{base}: its albedo is not a sigmoid of the head's logit, as "
                         "IntrinsicNet's is")
    logit = sigmoid.input[0]
    g.node.remove(sigmoid)  # made again after the head, the graph's order being topological
    n = helper.make_node
    new = [n("Concat", [nodes[HEAD_CONV].input[0], nodes[FIRST_CONV].input[0]],
             ["/albedo/cat"], name="/albedo/Concat", axis=1)]
    convs, x = _head_nodes(g, net.albedo_head, "albedo_head", "/albedo/cat")
    new += convs + [n("Add", [logit, x], ["/albedo/logit"], name="/albedo/Add"),
                    n("Sigmoid", ["/albedo/logit"], [contract.OUTPUT_ALBEDO],
                      name="/albedo/Sigmoid")]
    g.node.extend(new)
    onnx.checker.check_model(model)
    onnx.save(model, str(out))


def check_albedo(base_outputs: list, grafted_outputs: list, reference: np.ndarray) -> dict:
    """How the file with the albedo's head grafted compares (onnxruntime, on the same inputs):
    every output but the albedo against the base file's, and the albedo against the network's
    own (``reference``: IntrinsicNet's albedo, as numpy) and against the base file's."""
    same = max(float(np.abs(np.asarray(b) - np.asarray(g)).max())
               for i, (b, g) in enumerate(zip(base_outputs, grafted_outputs)) if i != 2)
    return {"other_outputs_max_abs_against_base": same,
            "albedo_mean_abs_against_the_network": float(
                np.abs(grafted_outputs[2] - reference).mean()),
            "albedo_mean_abs_against_base": float(
                np.abs(grafted_outputs[2] - base_outputs[2]).mean())}


def check(base_outputs: list, grafted_outputs: list, reference: np.ndarray) -> dict:
    """How the grafted file's outputs (onnxruntime, on the same inputs) compare: every output but
    the hair channel against the base file's (``base_outputs``), and the hair channel against
    the network's own (``reference``: IntrinsicNet's parsing, as numpy)."""
    same = max(float(np.abs(np.asarray(b) - np.asarray(g[:, :b.shape[1]] if i == 3 else g)).max())
               for i, (b, g) in enumerate(zip(base_outputs, grafted_outputs)))
    hair = float(np.abs(grafted_outputs[3][:, -1] - reference[:, -1]).mean())
    return {"other_outputs_max_abs_against_base": same,
            "hair_mean_abs_against_the_network": hair}


# Each head a graft adds: (the function that grafts it, the check of the grafted file's outputs,
# the index of the network output the head feeds).
HEADS = {"hair": (graft, check, 3), "albedo": (graft_albedo, check_albedo, 2)}
