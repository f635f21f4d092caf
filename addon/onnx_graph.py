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
