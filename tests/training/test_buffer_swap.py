"""training/eval/buffer_swap.py: a model relit with some buffers taken from another network."""

from __future__ import annotations

import pathlib

import numpy as np
import pytest

from addon import api, engine, lightvec
from addon.errors import InputError
from training.eval import buffer_swap
from training.lightstage.png import read_png

ROOT = pathlib.Path(__file__).resolve().parents[2]
LAMP = lightvec.splat_direction([1.0, 0.2, 0.5], 10.0) + lightvec.uniform(0.05)


@pytest.fixture(scope="module")
def pair():
    """The shipped Portrait network, a research one trained further from it, and the demo's
    first frame, (H, W, 3) linear."""
    load = lambda p: engine.new_session(ROOT / p, providers=["CPUExecutionProvider"], threads=1,
                                        spin=False)
    src = read_png(ROOT / "demo" / "frames" / "frame_0001.png").astype(np.float32) / 255.0
    return (load("models/relight-portrait.onnx"), load("models/research/portrait-gpu.onnx"),
            np.ascontiguousarray(src ** 2.2))


def test_the_named_buffers_are_the_other_network_s_and_the_rest_the_model_s(pair):
    base, other, img = pair
    x = np.ascontiguousarray(img[:64, :64].transpose(2, 0, 1))
    swapped = buffer_swap.BuffersFrom(base, other, ("albedo", "transfer"))
    got = swapped.run_planar(x, mirror=True)
    mine, theirs = base.run_planar(x, mirror=True), other.run_planar(x, mirror=True)
    assert np.abs(mine.albedo - theirs.albedo).max() > 1e-3  # the two networks differ
    np.testing.assert_array_equal(got.albedo, theirs.albedo)
    np.testing.assert_array_equal(got.transfer, theirs.transfer)
    for field in ("normal", "height", "parsing"):
        np.testing.assert_array_equal(getattr(got, field), getattr(mine, field))
    assert swapped.card.name != base.card.name and other.card.name in swapped.card.name
    assert swapped.card.working_size == base.card.working_size


def test_swaps_that_cannot_be_made_are_refused_with_a_reason(pair):
    base, other, _ = pair
    with pytest.raises(InputError, match="some of normal"):
        buffer_swap.BuffersFrom(base, other, ("shading",))
    with pytest.raises(InputError, match="some of normal"):
        buffer_swap.BuffersFrom(base, other, ())
    # the shipped network parses hair, the research one does not
    with pytest.raises(InputError, match="parsing cannot be swapped"):
        buffer_swap.BuffersFrom(base, other, ("parsing",))


def test_relight_image_takes_a_loaded_model_as_its_file(pair):
    """api.relight_image with a loaded session relights as with the session's file, and with
    a swapped one relights differently."""
    base, other, img = pair
    by_file = api.relight_image(img, LAMP, model=ROOT / "models" / "relight-portrait.onnx",
                                threads=1)
    np.testing.assert_array_equal(api.relight_image(img, LAMP, model=base), by_file)
    swapped = api.relight_image(img, LAMP, model=buffer_swap.BuffersFrom(base, other,
                                                                         ("albedo",)))
    assert swapped.shape == by_file.shape and np.isfinite(swapped).all()
    assert np.abs(swapped - by_file).max() > 1e-4


def test_the_table_has_a_row_per_model_and_a_paired_gain_where_there_is_one():
    corr = {"left_right": 0.98, "top_bottom": 0.88}
    res = {"onnx": "a.onnx", "other": "b.onnx", "pairs_per_subject": 36,
           "rmse_level_fit": {"a": 0.0554, "a, b's albedo": 0.0538},
           "yale_tune_psnr": {"a": 20.47, "a, b's albedo": 20.59},
           "balance_correlation": {"a": corr, "a, b's albedo": corr | {
               "top_bottom_gain": -0.0004, "top_bottom_gain_90": [-0.005, 0.005]}}}
    md = buffer_swap.markdown(res, "python -m training.eval.buffer_swap --other b.onnx", "a CPU")
    rows = [line for line in md.splitlines() if line.startswith("| a")]
    assert rows == ["| a | 0.0554 | 20.47 | 0.980 | 0.880 | - |",
                    "| a, b's albedo | 0.0538 | 20.59 | 0.980 | 0.880 | -0.000 (-0.005 to "
                    "+0.005) |"]
