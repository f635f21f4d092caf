"""Write small ONNX graphs as bytes, without the ``onnx`` package (not bundled with the extension).

The full-resolution stages (resize, the detail transfer's multiply-add, clamping, the cast to
half) run as tiny onnxruntime graphs: vectorised and multi-threaded C++, where numpy would take
several single-threaded passes over 6 million values per 1080p frame. This module encodes just
the protobuf fields such graphs need (onnx.proto3: ModelProto, GraphProto, NodeProto,
AttributeProto, TensorProto, ValueInfoProto); tests/core/test_onnx_graph.py checks the bytes
with the ``onnx`` package's own parser and checker.
"""

from __future__ import annotations

import struct

import numpy as np

# TensorProto.DataType
FLOAT, UINT8, INT32, INT64, FLOAT16 = 1, 2, 6, 7, 10
_NP_TYPES = {np.dtype(np.float32): FLOAT, np.dtype(np.uint8): UINT8, np.dtype(np.int32): INT32,
             np.dtype(np.int64): INT64, np.dtype(np.float16): FLOAT16}
# AttributeProto.AttributeType
_A_FLOAT, _A_INT, _A_STRING, _A_INTS = 1, 2, 3, 7
IR_VERSION = 8
OPSET = 18


def _varint(n: int) -> bytes:
    n &= (1 << 64) - 1  # negative int64 as two's complement, as protobuf does
    out = bytearray()
    while True:
        b = n & 0x7F
        n >>= 7
        if n:
            out.append(b | 0x80)
        else:
            out.append(b)
            return bytes(out)


def _key(field: int, wire: int) -> bytes:
    return _varint(field << 3 | wire)


def _int(field: int, n: int) -> bytes:
    return _key(field, 0) + _varint(int(n))


def _bytes(field: int, data: bytes) -> bytes:
    return _key(field, 2) + _varint(len(data)) + data


def _str(field: int, s: str) -> bytes:
    return _bytes(field, s.encode("utf-8"))


def _attribute(name: str, value) -> bytes:
    msg = _str(1, name)
    if isinstance(value, bool) or isinstance(value, int):
        return msg + _int(3, int(value)) + _int(20, _A_INT)
    if isinstance(value, float):
        return msg + _key(2, 5) + struct.pack("<f", value) + _int(20, _A_FLOAT)
    if isinstance(value, str):
        return msg + _bytes(4, value.encode()) + _int(20, _A_STRING)
    if isinstance(value, (list, tuple)) and all(isinstance(v, int) for v in value):
        return msg + b"".join(_int(8, v) for v in value) + _int(20, _A_INTS)
    raise TypeError(f"unsupported attribute {name}={value!r}")


def node(op_type: str, inputs, outputs, **attrs) -> bytes:
    """NodeProto; an empty string in ``inputs`` is an omitted optional input."""
    msg = b"".join(_str(1, i) for i in inputs) + b"".join(_str(2, o) for o in outputs)
    msg += _str(4, op_type)
    msg += b"".join(_bytes(5, _attribute(k, v)) for k, v in sorted(attrs.items()))
    return msg


def tensor(name: str, array) -> bytes:
    """TensorProto with raw little-endian data."""
    a = np.ascontiguousarray(array)
    msg = b"".join(_int(1, d) for d in a.shape) + _int(2, _NP_TYPES[a.dtype])
    return msg + _str(8, name) + _bytes(9, a.astype(a.dtype.newbyteorder("<")).tobytes())


def value_info(name: str, elem_type: int, dims) -> bytes:
    """ValueInfoProto for a tensor; a str in ``dims`` is a symbolic (dynamic) dimension."""
    shape = b"".join(_bytes(1, _str(2, d) if isinstance(d, str) else _int(1, d)) for d in dims)
    tensor_type = _int(1, elem_type) + _bytes(2, shape)
    return _str(1, name) + _bytes(2, _bytes(1, tensor_type))


def model(nodes, inputs, outputs, initializers=(), name: str = "graph") -> bytes:
    """ModelProto bytes, ready for onnxruntime.InferenceSession(bytes)."""
    graph = (b"".join(_bytes(1, n) for n in nodes) + _str(2, name)
             + b"".join(_bytes(5, t) for t in initializers)
             + b"".join(_bytes(11, v) for v in inputs) + b"".join(_bytes(12, v) for v in outputs))
    opset = _str(1, "") + _int(2, OPSET)
    return (_int(1, IR_VERSION) + _str(2, "relight-addon") + _bytes(7, graph)
            + _bytes(8, opset))


# ---- reading: which tensors of a model keep their data outside the .onnx file ---------------

# (message, field number) -> the message type of that field, for the fields that can hold a
# TensorProto somewhere below them (onnx.proto3). Everything else is skipped unread.
_CHILDREN = {
    ("model", 7): "graph", ("model", 25): "function",
    ("graph", 1): "node", ("graph", 5): "tensor", ("graph", 15): "sparse",
    ("function", 7): "node",
    ("node", 5): "attribute",
    ("attribute", 5): "tensor", ("attribute", 6): "graph", ("attribute", 10): "tensor",
    ("attribute", 11): "graph", ("attribute", 22): "sparse", ("attribute", 23): "sparse",
    ("sparse", 1): "tensor", ("sparse", 2): "tensor",
}
_TENSOR_NAME, _TENSOR_EXTERNAL_DATA, _TENSOR_DATA_LOCATION = 8, 13, 14
_EXTERNAL = 1  # TensorProto.DataLocation.EXTERNAL


def _read_varint(buf, pos: int, end: int) -> tuple[int, int]:
    n = shift = 0
    while True:
        if pos >= end or shift > 63:
            raise ValueError("truncated or malformed varint")
        b = buf[pos]
        pos += 1
        n |= (b & 0x7F) << shift
        if not b & 0x80:
            return n, pos
        shift += 7


def _fields(buf, start: int, end: int):
    """(field number, wire type, value or (start, end) of a length-delimited field) of one
    message's bytes ``buf[start:end]``."""
    pos = start
    while pos < end:
        key, pos = _read_varint(buf, pos, end)
        field, wire = key >> 3, key & 7
        if wire == 0:
            value, pos = _read_varint(buf, pos, end)
        elif wire == 1:
            value, pos = None, pos + 8
        elif wire == 5:
            value, pos = None, pos + 4
        elif wire == 2:
            size, pos = _read_varint(buf, pos, end)
            value, pos = (pos, pos + size), pos + size
        else:
            raise ValueError(f"unsupported protobuf wire type {wire}")
        if pos > end:
            raise ValueError("truncated protobuf message")
        yield field, wire, value


def external_tensors(model_bytes: bytes) -> list[str]:
    """Names of the tensors (initializers, constants, in subgraphs and functions too) whose data
    a serialised ModelProto keeps in other files (``data_location: EXTERNAL``). ValueError for
    bytes that are not a well-formed protobuf message. Walks with an explicit stack, so a deeply
    nested file cannot exhaust Python's recursion limit."""
    buf = memoryview(model_bytes)
    found, stack = [], [("model", 0, len(buf))]
    while stack:
        kind, start, end = stack.pop()
        name, external = "", False
        for field, wire, value in _fields(buf, start, end):
            if kind == "tensor":
                if field == _TENSOR_NAME and wire == 2:
                    name = bytes(buf[value[0]:value[1]]).decode("utf-8", "replace")
                elif field == _TENSOR_DATA_LOCATION and wire == 0 and value == _EXTERNAL:
                    external = True
                elif field == _TENSOR_EXTERNAL_DATA and wire == 2:
                    external = True
            child = _CHILDREN.get((kind, field))
            if child is not None and wire == 2:
                stack.append((child, *value))
        if external:
            found.append(name or "(unnamed)")
    return found
