"""Losses, flow warping and one training step on the stand-in data."""

import math

import numpy as np
import pytest
import torch

import standin
from training.model import checkpoint, losses, network, units, warp
from training.run import batches, lineage, options, schedule
from training.run.ema import WeightAverage
from training.run.trainer import Trainer, raw_weights

torch.set_num_threads(1)
TINY = network.NetConfig(widths=(8, 8, 16, 16), blocks=(1, 1, 1, 1), expand=2, code=8,
                         light_embed=16)


def _batch(res=32, n=2, shift=1):
    return batches.collate([units.normalise_sample(standin.sample(res, i, shift))
                            for i in range(n)])


# ---- terms

def test_light_loss_is_half_squared_log_distance():
    target = torch.full((1, 3, 16, 16), math.e - 1.0)
    assert float(losses.light_loss(torch.zeros_like(target), target)) == pytest.approx(0.5)
    assert float(losses.light_loss(target, target)) == 0.0


def test_masked_l1_ignores_pixels_outside_the_mask():
    a, b = torch.zeros(1, 3, 4, 4), torch.zeros(1, 3, 4, 4)
    b[..., :2] = 1.0
    mask = torch.zeros(1, 1, 4, 4)
    mask[..., 2:] = 1.0
    assert float(losses.masked_l1(a, b, mask)) == 0.0
    assert float(losses.masked_l1(a, b, 1 - mask)) == pytest.approx(1.0)


def test_parsing_loss_is_low_for_confident_right_answers():
    target = (torch.rand(1, 3, 8, 8) > 0.5).float()
    right = losses.parsing_loss((target * 2 - 1) * 10, target)
    wrong = losses.parsing_loss((1 - 2 * target) * 10, target)
    assert float(right) < 1e-3 < 5 < float(wrong)


# ---- warping (dataset flow conventions)

def test_warp_follows_the_flow_conventions():
    s = standin.sample(32, 0, shift=2)  # frame t+1 is frame t moved 2 px right
    img_t = torch.from_numpy(s["img_t_i"])[None]
    img_t1 = torch.roll(img_t, 2, dims=-1)
    fw = torch.from_numpy(s["flow_fw"])[None]
    bw = torch.from_numpy(s["flow_bw"])[None]
    back = warp.to_previous(img_t1, fw)  # frame t+1 seen on frame t's pixels
    fwd = warp.to_next(img_t, bw)  # frame t seen on frame t+1's pixels
    assert torch.allclose(back[..., :-2], img_t[..., :-2], atol=1e-5)
    assert torch.allclose(fwd[..., 2:], img_t1[..., 2:], atol=1e-5)
    assert float(warp.in_bounds(fw)[..., -2:].max()) == 0.0  # left the frame


def test_warp_subpixel_is_bilinear():
    img = torch.arange(8.0).view(1, 1, 1, 8).repeat(1, 1, 4, 1)
    flow = torch.zeros(1, 2, 4, 8)
    flow[:, 0] = 0.25
    assert torch.allclose(warp.warp(img, flow)[..., :7], img[..., :7] + 0.25, atol=1e-5)


def test_warp_refuses_mismatched_sizes():
    with pytest.raises(ValueError, match="differ"):
        warp.warp(torch.zeros(1, 3, 8, 8), torch.zeros(1, 2, 8, 9))


def test_temporal_pair_is_zero_only_for_consistent_motion():
    b = _batch(32, 1, shift=1)
    args = (b["flow_fw"], b["flow_bw"], b["valid_fw"], b["valid_bw"])
    a_t = b["img_t"]
    consistent = torch.roll(a_t, 1, dims=-1)
    assert float(losses.temporal_pair(a_t, consistent, *args)) < 1e-6
    assert float(losses.temporal_pair(a_t, consistent * 1.5, *args)) > 1e-2


def test_downsampled_flow_still_warps_correctly():
    b = _batch(32, 1, shift=2)
    d = batches.downsample_batch(b, 2)
    assert d["img_t"].shape[-1] == 16 and float(d["flow_fw"][0, 0].mean()) == pytest.approx(1.0)


# ---- units

def test_normalise_sample_uses_one_scale_for_both_frames_and_unit_target_power():
    s = standin.sample(32, 0)
    n = units.normalise_sample(s)
    scale = float(n["scale"])
    assert np.allclose(n["img_t"] * scale, s["img_t_i"], rtol=1e-5)
    assert np.allclose(n["img_t1"] * scale, s["img_t1_j"], rtol=1e-5)
    k = float(n["light_scale"])
    assert np.allclose(n["gt_t"] * k, s["gt_t_k"], rtol=1e-4)  # relit / k: see test_units.py
    assert float(network.light_power(torch.from_numpy(n["light_k"])[None])) == pytest.approx(1.0)
    assert np.allclose(n["src_t"], network.to_channels_first(s["light_i"]) / scale, rtol=1e-5)


def test_all_dark_target_gives_black_ground_truth():
    s = standin.sample(32, 0)
    s["light_k"] = np.zeros_like(s["light_k"])
    n = units.normalise_sample(s)
    assert np.all(n["gt_t"] == 0) and np.all(np.isfinite(n["light_k"]))


# ---- critic and the whole objective

def test_critic_scores_any_size_and_clips_its_weights():
    c = losses.Critic(width=8)
    for res in (32, 64):
        x = torch.rand(2, 3, res, res)
        assert c(x, x, torch.rand(2, 3, 16, 16)).shape == (2,)
    with torch.no_grad():
        for p in c.parameters():
            p.mul_(100)
    c.clip_weights(0.01)
    assert max(float(p.detach().abs().max()) for p in c.parameters()) <= 0.01


def test_critic_loss_does_not_reach_the_generator():
    net = network.RelightNet(TINY)
    b = _batch()
    _, _, fake = losses.generator_objective(net, b, losses.Switches(adversarial=False))
    fake = fake.clone().requires_grad_(True)
    losses.critic_loss(losses.Critic(8), b["img_t"], b["gt_t"], fake, b["light_k"]).backward()
    assert fake.grad is None


@pytest.mark.parametrize("ablation,missing", [("full", set()), ("no_structure", {"latent"}),
                                              ("no_temporal", {"temporal"}),
                                              ("no_parsing", {"parsing"})])
def test_objective_terms_follow_the_ablation_switches(ablation, missing):
    torch.manual_seed(0)
    net = network.RelightNet(TINY)
    sw = losses.Switches.ablation(ablation)
    total, parts, fake = losses.generator_objective(net, _batch(), sw, losses.Critic(8))
    expected = {"basic", "latent", "parsing", "temporal", "adv"} - missing
    assert set(parts) == expected
    assert fake.shape == (2, 3, 32, 32) and math.isfinite(float(total.detach()))
    total.backward()
    assert net.encoder.to_light[1].weight.grad.abs().sum() > 0  # the light loss trains the encoder
    assert net.decoder.light.trunk[0].weight.grad is not None


def test_unknown_ablation_is_refused():
    with pytest.raises(ValueError, match="unknown ablation"):
        losses.Switches.ablation("no_everything")


def test_a_few_training_steps_reduce_the_loss():
    torch.manual_seed(0)
    args = options.parser().parse_args(["--lr", "3e-3", "--critic-width", "8"])
    trainer = Trainer(network.RelightNet(TINY), losses.Switches(adversarial=False), args)
    b = _batch(32, 2)
    first = trainer.step(b, args.lr, adv_on=False)["total"]
    for _ in range(15):
        last = trainer.step(b, args.lr, adv_on=False)["total"]
    assert last < first


def test_adversarial_step_runs_with_bf16_and_channels_last():
    args = options.parser().parse_args(["--critic-width", "8", "--bf16", "--channels-last"])
    trainer = Trainer(network.RelightNet(TINY), losses.Switches(), args)
    parts = trainer.step(_batch(32, 2), args.lr, adv_on=True)
    assert {"adv", "critic", "total"} <= set(parts) and all(map(math.isfinite, parts.values()))


def test_progressive_schedule():
    st = schedule.parse_stages("0.3:4,0.7:2,1:1")
    assert [schedule.factor_at(st, f) for f in (0.0, 0.5, 0.9, 1.2)] == [4, 2, 1, 1]
    with pytest.raises(ValueError):
        schedule.parse_stages("0.5:2")
    assert schedule.lr_at(1.0, 0.0) == pytest.approx(1.0)
    assert schedule.lr_at(1.0, 1.0) == pytest.approx(0.05)


def test_warmup_ramps_the_rate_up_to_the_cosine_then_leaves_it():
    ramp = [schedule.lr_at(1.0, 0.0, step, warmup=4) for step in range(6)]
    assert ramp == pytest.approx([0.25, 0.5, 0.75, 1.0, 1.0, 1.0])
    assert schedule.lr_at(1.0, 0.5, 10, warmup=4) == pytest.approx(schedule.lr_at(1.0, 0.5))
    assert schedule.lr_at(2.0, 0.3, 0, warmup=0) == schedule.lr_at(2.0, 0.3)  # off by default
    assert options.parser().parse_args(["--warmup-steps", "200"]).warmup_steps == 200


def test_init_loads_a_checkpoint_of_the_same_network_and_refuses_another(tmp_path):
    cfg = network.NetConfig(widths=(8, 8, 16, 16), blocks=(1, 1, 1, 1), expand=2, code=8,
                            light_embed=16, relight="ratio")
    src = standin.perturbed_net(cfg, 9)
    checkpoint.save_checkpoint(tmp_path / "a.pt", src, {"command": "x"}, 123)
    fresh = network.RelightNet(cfg)
    info = lineage.load_init(fresh, tmp_path / "a.pt")
    assert info["step"] == 123
    for a, b in zip(fresh.state_dict().values(), src.state_dict().values()):
        assert torch.equal(a, b)
    other = network.RelightNet(network.NetConfig(**{**cfg.to_dict(), "widths": (8, 8, 16, 24)}))
    with pytest.raises(SystemExit, match="same --preset"):
        lineage.load_init(other, tmp_path / "a.pt")


def test_weight_average_follows_the_weights_at_its_decay():
    net = network.RelightNet(TINY)
    start = [p.detach().clone() for p in net.parameters()]
    ema = WeightAverage(net, 0.9, warm=True)  # a run from --init: the average starts there
    with torch.no_grad():
        for p in net.parameters():
            p.add_(1.0)
    for _ in range(3):
        ema.update(net)
    for a, s in zip(ema.net.parameters(), start):  # 0.9^3 of the start, the rest of start + 1
        assert torch.allclose(a, s + (1 - 0.9 ** 3), atol=1e-5)
        assert not a.requires_grad
    for p, s in zip(net.parameters(), start):  # the trained weights are left alone
        assert torch.allclose(p, s + 1.0)
    cold = WeightAverage(network.RelightNet(TINY), 0.999, warm=False)
    rand = [a.detach().clone() for a in cold.net.parameters()]
    cold.update(net)  # from scratch the random start weighs 2/11 at the first update, not 0.999
    for a, r, p in zip(cold.net.parameters(), rand, net.parameters()):
        assert torch.allclose(a, r * (2 / 11) + p.detach() * (9 / 11), atol=1e-5)
    assert options.parser().parse_args(["--ema", "0.999"]).ema == 0.999
    assert options.parser().parse_args([]).ema == 0.0


def test_checkpoint_of_an_averaged_run_loads_the_average_or_the_raw_weights(tmp_path):
    net = network.RelightNet(TINY)
    ema = WeightAverage(net, 0.5, warm=True)
    with torch.no_grad():
        for p in net.parameters():
            p.add_(1.0)
    ema.update(net)
    checkpoint.save_checkpoint(tmp_path / "c.pt", ema.net, {"command": "x"}, 7, raw_weights(ema, net))
    avg, _ = checkpoint.load_checkpoint(tmp_path / "c.pt")
    raw, _ = checkpoint.load_checkpoint(tmp_path / "c.pt", raw=True)
    for a, r, e, p in zip(avg.parameters(), raw.parameters(), ema.net.parameters(),
                          net.parameters()):
        assert torch.equal(a, e) and torch.equal(r, p) and not torch.equal(a, r)
    checkpoint.save_checkpoint(tmp_path / "plain.pt", net, {"command": "x"}, 7, raw_weights(None, net))
    with pytest.raises(SystemExit, match="leave out --raw"):
        checkpoint.load_checkpoint(tmp_path / "plain.pt", raw=True)
