"""The hand-written ONNX encoder and the full-resolution graphs built with it."""

import numpy as np
import onnx
import pytest

from addon import detail, onnx_graph as g
from tests import reference


@pytest.mark.parametrize("build", [detail.shrink_graph, detail.area_graph,
                                   lambda: detail.finish_blocks_graph(True),
                                   lambda: detail.finish_blocks_graph(False),
                                   detail.upsample_blocks_graph,
                                   lambda: detail.finish_graph(True),
                                   lambda: detail.finish_graph(False), detail.guided_graph,
                                   detail.upsample_graph])
def test_graphs_pass_the_onnx_checker(build):
    m = onnx.load_from_string(build())
    onnx.checker.check_model(m, full_check=True)
    assert m.opset_import[0].version == g.OPSET and m.ir_version == g.IR_VERSION


def test_encoder_matches_onnx_helper():
    from onnx import helper, numpy_helper
    ours = onnx.load_from_string(g.model(
        [g.node("Clip", ["x", "lo", ""], ["y"]),
         g.node("ReduceMax", ["y"], ["m"], keepdims=0),
         g.node("LeakyRelu", ["x"], ["z"], alpha=0.25),
         g.node("Transpose", ["x"], ["t"], perm=[0, 2, 1])],
        [g.value_info("x", g.FLOAT, [1, "n", 3])],
        [g.value_info("y", g.FLOAT, [1, "n", 3]), g.value_info("m", g.FLOAT, []),
         g.value_info("z", g.FLOAT, [1, "n", 3]), g.value_info("t", g.FLOAT, [1, 3, "n"])],
        [g.tensor("lo", np.array([-1.5], np.float32))]))
    node = ours.graph.node
    assert helper.get_attribute_value(node[1].attribute[0]) == 0
    assert helper.get_attribute_value(node[2].attribute[0]) == pytest.approx(0.25)
    assert list(helper.get_attribute_value(node[3].attribute[0])) == [0, 2, 1]
    assert node[0].input[2] == ""
    np.testing.assert_array_equal(numpy_helper.to_array(ours.graph.initializer[0]), [-1.5])
    dims = ours.graph.input[0].type.tensor_type.shape.dim
    assert [d.dim_value or d.dim_param for d in dims] == [1, "n", 3]
    assert g._varint(-1) == b"\xff" * 9 + b"\x01"  # int64 -1 as protobuf writes it


@pytest.fixture(scope="module")
def fullres():
    return detail.FullRes(threads=1)


def chw(x: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(np.moveaxis(x, -1, 0))


def hwc(x: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(np.moveaxis(x, 0, -1))


def test_finish_equals_the_numpy_reference(fullres):
    rng = np.random.default_rng(0)
    x = rng.random((45, 70, 3)).astype(np.float32)
    a = rng.random((9, 14, 3)).astype(np.float32) * 2
    b = rng.random((9, 14, 3)).astype(np.float32)
    y, may_clamp, _ = fullres.finish_planar(chw(x), chw(a), chw(b), x_max=1.0)
    up = detail.resize(np.concatenate([a, b], axis=2), 45, 70)
    ref = up[..., :3] * x + up[..., 3:]
    assert y.dtype == np.float16 and y.shape == (3, 45, 70) and not may_clamp
    np.testing.assert_allclose(hwc(y).astype(np.float32), ref, rtol=1e-3, atol=1e-4)


def test_finish_clamps_to_half_when_the_bound_says_so(fullres):
    x = np.full((3, 4, 4), 10.0, np.float32)
    y, may_clamp, _ = fullres.finish_planar(x, np.full((3, 2, 2), 1e5, np.float32),
                                            np.zeros((3, 2, 2), np.float32), x_max=10.0)
    assert may_clamp and np.all(y == np.float16(65504))


def test_guided_graph_equals_the_numpy_reference(fullres):
    rng = np.random.default_rng(2)
    guide = rng.random((23, 31, 3)).astype(np.float32)
    target = guide * rng.random((1, 31, 3)).astype(np.float32) + 0.1 * rng.random((23, 31, 3))
    a, b = fullres.coefficients_planar(chw(guide), chw(target.astype(np.float32)), 3.0)
    ra, rb = reference.guided_coefficients(guide, target)
    np.testing.assert_allclose(hwc(a), 3 * ra, rtol=2e-3, atol=1e-4)
    np.testing.assert_allclose(hwc(b), 3 * rb, rtol=2e-3, atol=1e-4)
    bad = target.copy()
    bad[0, 0] = np.nan
    a, b = fullres.coefficients_planar(chw(guide), chw(bad), 1e38)
    assert np.all(np.isfinite(a)) and np.all(np.isfinite(b))


def test_shrink_is_a_mean_preserving_low_pass(fullres):
    rng = np.random.default_rng(1)
    x = rng.random((3, 108, 192)).astype(np.float32)
    y = fullres.shrink_planar(x, 29, 51)
    assert y.shape == (3, 29, 51)
    np.testing.assert_allclose(y.mean(axis=(1, 2)), x.mean(axis=(1, 2)), rtol=1e-2)
    assert y.std() < 0.5 * x.std()  # averaged, not point-sampled
    smooth = np.tile(np.linspace(0, 1, 192, dtype=np.float32)[None, None, :], (3, 108, 1))
    np.testing.assert_allclose(fullres.shrink_planar(smooth, 54, 96),
                               chw(detail.resize(hwc(smooth), 54, 96)), atol=2e-3)


def test_upsample_half_clamps(fullres):
    low = np.array([[[-1.0, 0.5], [np.nan, 2.0]]], np.float32)
    y = fullres.upsample_half_planar(low, 4, 4, 0.0, 1.0)
    assert y.dtype == np.float16 and y.shape == (1, 4, 4)
    assert y.min() >= 0 and y.max() <= 1


@pytest.mark.parametrize("big,small", [((1080, 1920), (288, 512)), ((720, 1280), (288, 512)),
                                       ((45, 70), (9, 14)), ((48, 64), (48, 32)),
                                       ((2160, 3840), (288, 512))])
def test_area_shrink_of_common_sizes_is_exact_area_averaging(fullres, big, small):
    assert detail.area_blocks(big[0], small[0]) is not None
    x = np.random.default_rng(3).random((3, *big)).astype(np.float32)
    got = fullres.shrink_planar(x, *small)
    want = detail.resize(x.transpose(1, 2, 0), *small).transpose(2, 0, 1)
    assert got.shape == (3, *small)
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-6)


def test_area_blocks_tile_the_axis_and_odd_ratios_fall_back(fullres):
    block = detail.area_blocks(1080, 288)
    assert block.shape == (4, 15)
    np.testing.assert_allclose(block.sum(axis=1), 1.0, rtol=1e-6)  # each output a mean
    np.testing.assert_allclose(block.sum(axis=0), 4 / 15, rtol=1e-6)  # every input counted once
    assert detail.area_blocks(700, 358) is None and detail.area_blocks(10, 20) is None
    x = np.random.default_rng(4).random((3, 100, 80)).astype(np.float32)
    y = fullres.shrink_planar(x, 13, 11)  # 100/13: the antialiased resize instead
    assert y.shape == (3, 13, 11)
    np.testing.assert_allclose(y.mean(axis=(1, 2)), x.mean(axis=(1, 2)), rtol=1e-2)


@pytest.mark.parametrize("big,small", [((1080, 1920), (288, 512)), ((17, 9), (5, 3)),
                                       ((48, 64), (48, 32)), ((3, 2), (1, 1)),
                                       ((100, 80), (13, 11))])  # the last: no small blocks
def test_planar_finish_by_blocks_or_resize_equals_the_numpy_reference(fullres, big, small):
    rng = np.random.default_rng(7)
    x = rng.random((3, *big)).astype(np.float32)
    a = (rng.random((3, *small)) * 2).astype(np.float32)
    b = rng.random((3, *small)).astype(np.float32)
    y, may_clamp, _ = fullres.finish_planar(x, a, b, x_max=1.0)
    up = detail.resize(np.concatenate([a, b]).transpose(1, 2, 0), *big).transpose(2, 0, 1)
    assert y.dtype == np.float16 and y.shape == (3, *big) and not may_clamp
    np.testing.assert_allclose(y.astype(np.float32), up[:3] * x + up[3:], rtol=1e-3, atol=1e-4)
    assert (detail.upsample_blocks(small[0], big[0]) is None) == (big == (100, 80))


def test_upsample_blocks_rows_are_bilinear_weights():
    mat, windows = detail.upsample_blocks(288, 1080)
    assert mat.shape == (15, 6) and windows.shape == (72, 6)
    np.testing.assert_allclose(mat.sum(axis=1), 1.0, rtol=1e-6)
    assert np.all((mat > 0).sum(axis=1) <= 2) and windows[1, 0] == 4
    assert detail.upsample_blocks(1080, 288) is None and detail.upsample_blocks(13, 100) is None


def test_planar_finish_by_blocks_clamps_to_half(fullres):
    x = np.full((3, 8, 8), 10.0, np.float32)
    y, may_clamp, _ = fullres.finish_planar(x, np.full((3, 4, 4), 1e5, np.float32),
                                            np.zeros((3, 4, 4), np.float32), x_max=10.0)
    assert may_clamp and np.all(y == np.float16(65504))


@pytest.mark.parametrize("small,big", [((4, 4), (8, 8)), ((13, 11), (100, 80))])
def test_finish_raises_negative_radiance_to_zero_and_reports_the_lowest(fullres, small, big):
    """Blocks and resize paths alike: negative values (and -Inf from an overflowing product)
    become 0, +Inf the half maximum, and the most negative value before the clamp is returned."""
    x = np.ones((3, *big), np.float32)
    a = np.zeros((3, *small), np.float32)
    b = np.full((3, *small), 0.5, np.float32)
    b[0] = -0.25
    y, may_clamp, lowest = fullres.finish_planar(x, a, b, x_max=1.0)
    assert may_clamp and lowest == pytest.approx(-0.25)
    assert np.all(y[0] == 0) and np.all(y[1:] == np.float16(0.5))
    a[1], a[2] = -1e30, 1e30  # times x = 1e10: -Inf and +Inf in float32
    y, may_clamp, lowest = fullres.finish_planar(np.full((3, *big), 1e10, np.float32),
                                                 a, b, x_max=1e10)
    assert lowest == -np.inf and np.all(y[1] == 0) and np.all(y[2] == np.float16(65504))
    assert fullres.finish_planar(x, np.ones_like(a), b * 0, 1.0)[1:] == (False, 0.0)


@pytest.mark.parametrize("small,big", [((9, 14), (45, 70)), ((13, 11), (100, 80))])
def test_matte_upsample_by_blocks_or_resize_equals_the_reference(fullres, small, big):
    low = np.random.default_rng(8).random((1, *small)).astype(np.float32) * 1.4 - 0.2
    y = fullres.upsample_half_planar(low, *big, 0.0, 1.0)
    want = np.clip(detail.resize(low.transpose(1, 2, 0), *big), 0, 1).transpose(2, 0, 1)
    assert y.dtype == np.float16 and y.shape == (1, *big)
    np.testing.assert_allclose(y.astype(np.float32), want, atol=1e-3)
