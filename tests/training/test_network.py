"""The relighting network: contract shapes, units, presets and cost."""

import numpy as np
import pytest
import torch

import standin
from addon import contract, lightvec, normalise
from training.model import network

torch.set_num_threads(1)
TINY = network.NetConfig(widths=(8, 8, 16, 16), blocks=(1, 1, 1, 1), expand=2, code=8,
                         light_embed=16)


@pytest.fixture(scope="module")
def net():
    torch.manual_seed(0)
    return network.RelightNet(TINY).eval()


def _light(n=1, seed=0):
    g = torch.Generator().manual_seed(seed)
    return torch.rand(n, 3, 16, 16, generator=g)


@pytest.mark.parametrize("h,w", [(32, 32), (64, 96), (96, 32)])
def test_forward_follows_the_contract_for_any_multiple_of_the_stride(net, h, w):
    assert TINY.stride == 32
    img = torch.rand(2, 3, h, w)
    relit, source, parsing = net(img, _light(2))
    assert relit.shape == (2, 3, h, w)
    assert source.shape == (2, 3, 16, 16)
    assert parsing.shape == (2, len(contract.PARSING_CLASSES), h, w)
    assert torch.all(relit >= 0) and torch.all(source >= 0)
    assert torch.all((parsing >= 0) & (parsing <= 1))


def test_untrained_network_starts_as_the_identity(net):
    # zero-initialised residual and unit gain: before training, relit == input (a sane start)
    img = torch.rand(1, 3, 32, 64) * 2
    relit, _, _ = net(img, _light())
    assert torch.allclose(relit, img, atol=1e-6)


def test_light_power_matches_the_engine_normalisation():
    rng = np.random.default_rng(1)
    for _ in range(3):
        light = rng.random((16, 16, 3)).astype(np.float32) * rng.uniform(0.1, 50)
        k_np = normalise.light_scale(light)
        k_t = network.light_power(torch.from_numpy(network.to_channels_first(light))[None])
        assert float(k_t) == pytest.approx(k_np, rel=1e-5)


def test_channels_first_light_is_the_light_vector_transposed():
    light = np.zeros(lightvec.SHAPE, np.float32)
    light[3, 12, 0] = 5.0  # red texel on the camera's right
    cf = network.to_channels_first(light)
    assert cf.shape == (3, 16, 16) and cf[0, 3, 12] == 5.0 and cf.sum() == 5.0


def test_relight_by_is_linear_in_the_light_power():
    net = standin.perturbed_net(TINY, 3)  # the decoder depends on the light, unlike at the start
    img = torch.rand(1, 3, 32, 32)
    with torch.no_grad():
        _, skips, code = net.encode(img)
        a, _ = net.relight_by(img, _light(), skips, code)
        b, _ = net.relight_by(img, 2.0 * _light(), skips, code)
        c, _ = net.relight_by(img, _light(seed=5), skips, code)
    assert torch.allclose(b, 2.0 * a, rtol=1e-4, atol=1e-5)
    assert not torch.allclose(a, c, atol=1e-4)  # the light does change the output


def test_source_light_responds_to_the_image():
    torch.manual_seed(4)
    net = network.RelightNet(TINY).eval()
    with torch.no_grad():
        s1 = net(torch.rand(1, 3, 32, 32), _light())[1]
        s2 = net(torch.rand(1, 3, 32, 32) * 5, _light())[1]
    assert not torch.allclose(s1, s2)


def test_presets_grow_in_cost_and_stay_within_budget():
    flops = {p: network.count_flops(network.build(p), 512, 512) for p in network.PRESETS}
    assert flops["draft"] < flops["standard"] < flops["final"]
    # design target: Standard well under 5 GFLOP at 512x512
    assert flops["standard"] < 5e9 and flops["draft"] < flops["standard"] / 2
    params = {p: network.parameter_count(network.build(p)) for p in network.PRESETS}
    assert params["final"] * 4 < 20e6  # fp32 ONNX under ~20 MB


def test_unknown_preset_is_refused():
    with pytest.raises(ValueError, match="unknown preset"):
        network.build("huge")


def test_hdr_and_black_inputs_stay_finite(net):
    img = torch.zeros(1, 3, 32, 32)
    img[..., :16, :] = 1e6  # far beyond the clip ceiling
    out = net(img, _light())
    assert all(torch.isfinite(o).all() for o in out)
    out = net(torch.zeros(1, 3, 32, 32), torch.zeros(1, 3, 16, 16))
    assert all(torch.isfinite(o).all() for o in out)


# ---- the ratio head: E(T, L_target) / E(T, L_source) with a per-pixel SH transport T

RATIO = network.NetConfig(**{**TINY.to_dict(), "widths": (8, 8, 16, 16),
                             "blocks": (1, 1, 1, 1), "relight": "ratio"})


def test_presets_use_the_ratio_head_and_old_checkpoints_keep_theirs():
    assert all(network.PRESETS[p].relight == "ratio" for p in ("draft", "standard", "final"))
    assert network.NetConfig().relight == "gain"  # configs saved before the key existed


def test_sh_projection_gives_a_lights_spherical_harmonics():
    # a uniform light of radiance 1 has only the constant band: 4 pi * Y00
    basis = network.sh_projection()
    coeff = torch.ones(1, 3, 256) @ basis
    assert float(coeff[0, 0, 0]) == pytest.approx(4 * np.pi * 0.282095, rel=1e-3)
    assert float(coeff[0, 0, 1:].abs().max()) < 1e-3 * 4 * np.pi
    # a light from the camera's right (+x) gives a positive x band (index 3)
    light = np.zeros(lightvec.SHAPE, np.float32)
    light[8, 12] = 1.0
    c = torch.from_numpy(network.to_channels_first(light)).flatten(1) @ basis
    assert float(c[0, 3]) > 0 and abs(float(c[0, 3])) > abs(float(c[0, 1]))


def test_ratio_head_starts_as_the_identity_and_turns_light_direction_into_shading():
    torch.manual_seed(5)
    net = network.RelightNet(RATIO).eval()
    img = torch.rand(1, 3, 32, 32) + 0.5
    relit, _, _ = net(img, _light())
    assert torch.allclose(relit, img, atol=1e-6)
    # a transport of "normal facing +x on the left half, -x on the right half" (band 3 = x)
    with torch.no_grad():
        net.decoder.transport.bias.zero_()
    left, right = np.zeros(lightvec.SHAPE, np.float32), np.zeros(lightvec.SHAPE, np.float32)
    left[8, 4], right[8, 12] = 1.0, 1.0  # from the camera's left / right
    tl, tr = (torch.from_numpy(network.to_channels_first(x))[None] for x in (left, right))
    with torch.no_grad():
        source, skips, code = net.encode(img)
        h, w = skips[0].shape[-2:]
        t = torch.zeros(1, 9, h, w)
        t[:, 0], t[:, 3, :, : w // 2], t[:, 3, :, w // 2:] = 1.0, -2.0, 2.0
        e_r = net.decoder._irradiance(t, tr)
        e_l = net.decoder._irradiance(t, tl)
    assert float(e_r[..., w // 2:].mean()) > 2 * float(e_r[..., : w // 2].mean())
    assert float(e_l[..., : w // 2].mean()) > 2 * float(e_l[..., w // 2:].mean())
    assert torch.all(e_r > 0) and torch.all(e_l > 0)  # the softplus floor: never a zero divisor


def test_ratio_head_stays_finite_for_a_black_source_and_extreme_lights():
    net = standin.perturbed_net(RATIO, 6, scale=0.2)
    img = torch.rand(1, 3, 32, 32)
    spike = torch.zeros(1, 3, 16, 16)
    spike[0, :, 3, 5] = 1e5
    for image, light in [(torch.zeros_like(img), _light()), (img, spike), (img, 0 * spike),
                         (img * 1e4, _light())]:
        with torch.no_grad():
            relit, source, parsing = net(image, light)
        assert torch.isfinite(relit).all() and torch.isfinite(source).all()
