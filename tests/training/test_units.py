"""Units of the network's inputs and targets (training.model.units.normalise_sample), and the engine
bringing an exported model's output back exactly as training and evaluation do.

The first Draft model trained against ground truth relit / (s k): a target that depends on the
absolute source power, which image / s hides, and that disagreed with the self-relit path by s.
These tests fail on that version."""

import numpy as np
import pytest
import torch

import standin
from addon import colour, engine, normalise, pipeline
from training.model import network, units
from training.run import batches, export, options
from training.run.trainer import Trainer

torch.set_num_threads(1)
TINY = network.NetConfig(widths=(8, 8, 16, 16), blocks=(1, 1, 1, 1), expand=2, code=8,
                         light_embed=16)
SEEN = ("img_t", "img_t1", "light_k", "src_t", "src_t1")  # what the network sees or estimates
TARGETS = ("gt_t", "gt_t1")


def _brighter_source(sample: dict, c: float) -> dict:
    """The same scene with the source lights (and so the input frames) c times brighter."""
    out = dict(sample)
    for key in ("img_t_i", "img_t1_j", "light_i", "light_j"):
        out[key] = sample[key] * np.float32(c)
    return out


@pytest.mark.parametrize("c", [0.1, 7.0])
def test_targets_depend_only_on_what_the_network_sees(c):
    s = standin.sample(32, 3)
    a, b = units.normalise_sample(s), units.normalise_sample(_brighter_source(s, c))
    for key in SEEN:  # the exposure scale hides the source power from the network ...
        np.testing.assert_allclose(a[key], b[key], rtol=1e-5, atol=1e-7)
    for key in TARGETS:  # ... so the target must not depend on it either
        np.testing.assert_allclose(a[key], b[key], rtol=1e-5, atol=1e-7)


def test_target_path_agrees_with_the_self_relit_path():
    """Relit into its own source light, a frame is itself. The loss decodes the self-relit frame
    under the estimated source light scaled to unit power and multiplies by that power
    (RelightNet.relight_by), so unit-light target * source power must be the input."""
    s = standin.sample(32, 5)
    s["light_k"], s["gt_t_k"] = s["light_i"], s["img_t_i"]
    n = units.normalise_sample(s)
    power = network.light_power(torch.from_numpy(n["src_t"][None]))[0].item()
    np.testing.assert_allclose(n["gt_t"] * power, n["img_t"], rtol=1e-4, atol=1e-6)


def test_relit_to_absolute_inverts_the_target():
    s = standin.sample(32, 7)
    n = units.normalise_sample(s)
    back = units.relit_to_absolute(n["gt_t"], float(n["scale"]), float(n["light_scale"]))
    np.testing.assert_allclose(back, s["gt_t_k"], rtol=1e-5, atol=1e-7)


def test_engine_output_matches_training_units_for_an_exported_model(tmp_path):
    """A sample through export + addon.engine + the pipeline's output scaling equals the torch
    model's output brought back by training's relit_to_absolute."""
    net = standin.perturbed_net(TINY, 0)
    onnx_path = export.export_onnx(net, tmp_path / "tiny.onnx")
    card = export.make_card("tiny", "draft", onnx_path, net, {"recipe": {}}, {}, {},
                            working_size=64)
    export.write_card(card, onnx_path)
    session = engine.new_session(onnx_path, threads=1)

    s = standin.sample(64, 11)
    n = units.normalise_sample(s)
    with torch.no_grad():
        relit, source, _ = net(torch.from_numpy(n["img_t"][None]),
                               torch.from_numpy(n["light_k"][None]))
    want = units.relit_to_absolute(relit[0].numpy(), float(n["scale"]), float(n["light_scale"]))

    relit_low, source_hwc, _, k = pipeline.infer_planar(session, n["img_t"], s["light_k"])
    plan = pipeline.Plan(colour.lookup("Linear Rec.709"), float(n["scale"]), (64, 64), (64, 64),
                         False, False, "none")
    a, b = pipeline.coefficients_planar(n["img_t"], relit_low, k, plan, None)
    assert not a.any() and k == pytest.approx(normalise.light_scale(s["light_k"]))
    np.testing.assert_allclose(b, want, rtol=1e-3, atol=1e-4 * float(np.abs(want).max()))
    np.testing.assert_allclose(source_hwc, np.moveaxis(source[0].numpy(), 0, -1), rtol=1e-3,
                               atol=1e-5)


def test_trainer_leaves_the_temporal_term_out_until_it_starts():
    """From the first step, the temporal term drove the network to a blurred output that ignores
    the input (temporally consistent, but not relit); the trainer turns it on later."""
    from training.model import losses

    args = options.parser().parse_args(["--batch", "1"])
    trainer = Trainer(network.RelightNet(TINY), losses.Switches(), args)
    b = batches.collate([units.normalise_sample(standin.sample(32, 1))])
    assert "temporal" not in trainer.step(b, 1e-4, adv_on=False, temporal_on=False)
    assert "temporal" in trainer.step(b, 1e-4, adv_on=False, temporal_on=True)
    assert args.temporal_start > 0  # the default recipe starts without it
