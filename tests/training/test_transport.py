"""The ratio head's transport target: the light stage's OLAT transfer projected to order-2 SH
(training/lightstage/pairs.py transport), its loss, and the --transport-loss switch."""

import numpy as np
import pytest
import torch

from addon import lightvec
from training.model import losses, network
from training.lightstage import layout, pairs

torch.set_num_threads(1)
RES = 48


@pytest.fixture(scope="module")
def frame(shared_data):
    from training.lightstage import assets
    from training.lightstage.scene import Scene
    from training.lightstage.subject import Performance, sample_camera, sample_identity

    m = assets.load_head(shared_data)
    cam = sample_camera(np.random.default_rng(5), RES)
    scene = Scene(sample_identity(3), Performance(1, m.expression_names), cam, shared_data, 9)
    return scene.shade_inputs(scene.frame(0.4))


def _irradiance(s, light):
    """(exact from the transfer, through the SH transport) for a (16,16,3) light vector."""
    exact = s.diffuse.double() @ torch.from_numpy(layout.weights(light))
    coeff = (torch.from_numpy(network.to_channels_first(light)).double().flatten(1)
             @ network.sh_projection().double())
    t = pairs.transport(s).view(9, -1)[:, s.idx].double().T
    return exact, t @ coeff.T


def test_transport_reproduces_the_irradiance_of_smooth_light(frame):
    exact, sh = _irradiance(frame, np.ones(lightvec.SHAPE, np.float32))
    assert torch.allclose(sh, exact, rtol=1e-4)  # the constant band is exact
    yy = lightvec.directions()[..., 1]  # a sky: brighter above, a smooth gradient
    sky = np.repeat((1.0 + yy)[..., None], 3, axis=-1).astype(np.float32)
    exact, sh = _irradiance(frame, sky)
    assert float((sh - exact).norm() / exact.norm()) < 0.1  # order 2 is a smooth fit, not exact


def test_transport_sees_left_from_right(frame):
    t = pairs.transport(frame)
    h, w = frame.mask.shape
    tx = t[3]  # the x band: positive where the surface faces the camera's right
    left = tx[:, : w // 2][frame.mask[:, : w // 2]].mean()
    right = tx[:, w // 2:][frame.mask[:, w // 2:]].mean()
    assert float(right) > float(left) + 0.1
    assert torch.all(t[:, ~frame.mask] == 0)


def test_transport_loss_is_zero_at_the_pooled_target_and_counts_only_the_portrait():
    target = torch.rand(2, 9, 16, 16)
    mask = torch.zeros(2, 1, 16, 16)
    mask[..., 4:12, 4:12] = 1.0
    pred = torch.nn.functional.avg_pool2d(target, 4).repeat(3, 1, 1, 1)  # 3 decodes of 2 frames
    assert float(losses.transport_loss(pred, target, mask)) == pytest.approx(0.0, abs=1e-7)
    off = pred.clone()
    off[..., 0, 0] += 5.0  # outside the portrait: no cost
    assert float(losses.transport_loss(off, target, mask)) == pytest.approx(0.0, abs=1e-7)
    off[..., 1, 1] += 5.0  # inside: costs
    assert float(losses.transport_loss(off, target, mask)) > 0.1


def test_objective_has_a_transport_term_only_when_switched_on():
    import standin

    net = network.RelightNet(network.NetConfig(widths=(8, 8, 16, 16), blocks=(1, 1, 1, 1),
                                               expand=2, code=8, light_embed=16,
                                               relight="ratio"))
    from training.model.units import normalise_sample
    from training.run.batches import collate

    samples = []
    for i in range(2):
        s = standin.sample(32, seed=i)
        s["transport_t"] = s["transport_t1"] = np.random.default_rng(i).random(
            (9, 32, 32), dtype=np.float32)
        samples.append(normalise_sample(s))
    b = collate(samples)
    _, on, _ = losses.generator_objective(net, b, losses.Switches(transport=True))
    _, off, _ = losses.generator_objective(net, b, losses.Switches())
    assert on["transport"] > 0 and "transport" not in off
