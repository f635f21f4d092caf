"""training/eval/temporal_stability.py: the lighting sequence, the metric, the static performer and
an end to end run with the tiny ONNX toy (tests/onnx_fixtures.py)."""

import json
import math
import shutil

import numpy as np
import pytest

from addon.errors import InputError, ModelError
from tests.onnx_fixtures import write_toy_model
from training.data import lighting_sampling
from training.eval import temporal_stability as ts

RES = 32  # small: the light stage renders one frame for the whole module


@pytest.fixture(scope="module")
def bank():
    rng = np.random.default_rng(0)
    return rng.uniform(0.1, 2.0, (2, lighting_sampling.SUB_STEPS, 16, 16, 3)).astype(np.float32)


# ---- the sequence ---------------------------------------------------------------------------

@pytest.mark.parametrize("f", [1, 3, 7, 10])
def test_speedup_f_plays_base_frame_f_i_mod_period(bank, f):
    period, n = 50, 40
    base = ts.base_lights(bank, 1, period)
    idx = ts.sequence_indices(n, f, period)
    seq = base[idx]
    for i in range(n):
        np.testing.assert_array_equal(seq[i], base[(f * i) % period])
    # f i wraps past the period: the sequence keeps going round instead of stopping
    assert (f * (n - 1) >= period) == bool(np.any(np.diff(idx) < 0))


def test_base_sequence_is_one_turn_and_periodic(bank):
    period = 2 * ts.YAW_STEPS  # every other frame is an exactly down-sampled yaw
    base = ts.base_lights(bank, 0, period)
    step = 360.0 / ts.YAW_STEPS
    for b in (0, 2, 10, period - 2):
        np.testing.assert_allclose(base[b], lighting_sampling.environment(bank, 0, b // 2 * step),
                                   rtol=1e-6)
    # the last frame lies half way between the last yaw and the first: the turn closes smoothly
    last = lighting_sampling.environment(bank, 0, (ts.YAW_STEPS - 1) * step)
    np.testing.assert_allclose(base[-1], 0.5 * (last + base[0]), rtol=1e-5)


def test_base_sequence_changes_smoothly(bank):
    exact = np.stack([lighting_sampling.environment(bank, 0, s * 360.0 / ts.YAW_STEPS)
                      for s in range(ts.YAW_STEPS)])
    base = ts.base_lights(bank, 0, 1000)
    steps = np.abs(np.diff(np.concatenate([base, base[:1]]), axis=0)).max()
    exact_steps = np.abs(np.diff(np.concatenate([exact, exact[:1]]), axis=0)).max()
    # interpolation spreads each exact yaw step over 1000/128 frames
    assert 0 < steps <= exact_steps * ts.YAW_STEPS / 1000 * 1.0001


def test_sequence_rejects_bad_arguments(bank):
    with pytest.raises(InputError):
        ts.sequence_indices(1, 1, 10)
    with pytest.raises(InputError):
        ts.sequence_indices(10, 0, 10)
    with pytest.raises(InputError):
        ts.base_lights(bank, 0, 1)


# ---- the metric -----------------------------------------------------------------------------

def test_adjacent_rmse_of_a_constant_sequence_is_zero():
    rng = np.random.default_rng(1)
    frame = rng.uniform(0, 1, (3, 8, 8))
    mask = rng.uniform(size=(8, 8)) > 0.3
    assert np.all(ts.adjacent_rmse(np.stack([frame] * 5), mask) == 0.0)


def test_adjacent_rmse_counts_only_the_mask_and_each_pair():
    mask = np.zeros((4, 4), bool)
    mask[:2] = True
    frames = np.zeros((4, 3, 4, 4))
    frames[1, :, :2] = 1.0      # inside the mask: pairs (0,1) and (1,2) change by 1
    frames[3, :, 2:] = 5.0      # outside the mask: pair (2,3) does not count
    np.testing.assert_allclose(ts.adjacent_rmse(frames, mask), [1.0, 1.0, 0.0])


def test_tracker_in_batches_equals_the_whole_sequence():
    rng = np.random.default_rng(2)
    frames = rng.uniform(0, 1, (23, 3, 6, 6))
    gt = rng.uniform(0, 1, (3, 6, 6))
    mask = rng.uniform(size=(6, 6)) > 0.5
    tr = ts.Tracker(gt[:, mask])
    for start in range(0, 23, 5):
        tr.add(frames[start:start + 5, :, mask])
    res = tr.result()
    assert res["adjacent_rmse"] == pytest.approx(ts.adjacent_rmse(frames, mask).mean())
    to_gt = np.sqrt(((frames[:, :, mask] - gt[:, mask]) ** 2).mean(axis=(1, 2)))
    assert res["rmse_to_gt"] == pytest.approx(to_gt.mean())


# ---- the static performer -------------------------------------------------------------------

@pytest.fixture(scope="module")
def stage(shared_data):
    import torch

    torch.set_num_threads(1)
    return ts.build_stage(RES, 0, shared_data)


@pytest.fixture(scope="module")
def env(shared_data):
    return lighting_sampling.environment_bank(shared_data)


def test_olat_sum_equals_the_light_stage_render(stage, env, shared_data):
    """Linearity: the frame under a light vector is the weighted sum of its OLAT images."""
    from training.data.dataset import LightStageDataset
    from training.data.make_testset import TEST_SEED

    names, bank = env
    scene, t, _ = LightStageDataset("test", RES, seed=TEST_SEED, length=1,
                                    data_root=shared_data).scene_for(0)
    assert stage.info["identity"] % 16 == 15  # a held-out identity
    lights = [lighting_sampling.environment(bank, names.index("pmndrs/park"), 100.0),
              lighting_sampling.sample_h(np.random.default_rng(3))]
    ref = scene.shade(scene.frame(t), lights).numpy()
    np.testing.assert_allclose(stage.render(np.stack(lights)), ref, rtol=1e-4,
                               atol=1e-5 * ref.max())
    assert 0.05 < stage.mask.mean() < 0.95


def test_a_perfect_model_scores_zero_and_the_input_does_not(stage, env):
    names, bank = env
    base = ts.base_lights(bank, names.index("pmndrs/park"), 1000)
    target = lighting_sampling.environment(bank, names.index("pmndrs/lobby"), 0.0)
    gt = stage.render(target[None])[0]
    perfect = lambda x, s: np.broadcast_to(gt, x.shape)  # noqa: E731
    res = ts.measure_clip(stage, base[ts.sequence_indices(20, 10, 1000)],
                          {"perfect": perfect, "input": lambda x, s: x}, gt, batch=6)
    assert res["perfect"]["adjacent_rmse"] == 0.0 and res["perfect"]["rmse_to_gt"] == 0.0
    assert res["input"]["adjacent_rmse"] > 1e-3 and res["input"]["rmse_to_gt"] > 1e-2


# ---- end to end with the toy ONNX -----------------------------------------------------------

def test_end_to_end_with_a_toy_model_card_and_bare(tmp_path, shared_data, stage):
    toy = write_toy_model(tmp_path / "card")
    bare_dir = tmp_path / "bare"
    bare_dir.mkdir()
    bare = shutil.copy(toy, bare_dir / "toy_bare.onnx")  # no card beside it
    with pytest.raises(ModelError, match="--label"):
        ts.load_model(bare)
    out = tmp_path / "out"
    report = ts.main(["--onnx", str(toy), "--onnx", str(bare), "--label", "toy",
                      "--label", "bare", "--stride", "8", "--quick", "--resolution", str(RES),
                      "--out", str(out), "--data-root", str(shared_data)])
    saved = json.loads((out / "temporal_stability.json").read_text())
    assert saved["results"] == json.loads(json.dumps(report["results"]))
    assert (out / "temporal_stability.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    res = saved["results"]
    assert sorted(res) == ["bare", "ground_truth", "input", "toy"]
    for name, per_f in res.items():
        assert sorted(per_f, key=int) == ["1", "5", "10"]
        for stats in per_f.values():
            assert all(math.isfinite(v) for v in stats.values())
    for f in ("1", "5", "10"):
        assert res["ground_truth"][f]["adjacent_rmse"] == 0.0
        assert res["bare"][f] == res["toy"][f]  # same network, with or without its card
        assert res["toy"][f]["adjacent_rmse"] > 0.0
    # the input changes more per frame when the light turns faster
    assert res["input"]["10"]["adjacent_rmse"] > 3 * res["input"]["1"]["adjacent_rmse"]
    assert saved["protocol"]["frames"] == ts.QUICK_FRAMES
