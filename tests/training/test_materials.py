"""Skin detail of the light stage (training/lightstage/materials.py): solid noise on the surface at
rest, round freckles that belong to light skin, the hairline's blend of hair and skin shading."""

import dataclasses

import numpy as np
import pytest
import torch

from training.lightstage import assets, materials
from training.lightstage.subject import sample_identity


def test_solid_noise_is_deterministic_bounded_and_isotropic():
    rng = np.random.default_rng(0)
    p = torch.from_numpy(rng.uniform(-10, 10, (20000, 3)).astype(np.float32))
    a = materials.solid_noise(p, 7, 1.0)
    assert torch.equal(a, materials.solid_noise(p, 7, 1.0))
    assert not torch.equal(a, materials.solid_noise(p, 8, 1.0))
    assert float(a.abs().max()) <= 1.0 and float(a.std()) > 0.2
    # The same change along any axis decorrelates it alike (texture-coordinate noise did not).
    corr = []
    for axis in range(3):
        step = torch.zeros(3)
        step[axis] = 0.5
        b = materials.solid_noise(p + step, 7, 1.0)
        corr.append(float(np.corrcoef(a.numpy(), b.numpy())[0, 1]))
    assert max(corr) - min(corr) < 0.05, corr


def test_spots_are_round_and_follow_their_density():
    g = torch.linspace(-3, 3, 241)
    yy, xx = torch.meshgrid(g, g, indexing="ij")
    p = torch.stack([xx.reshape(-1), yy.reshape(-1), torch.zeros(xx.numel())], 1)
    none = materials.spots(p, 3, 0.5, torch.zeros(p.shape[0]))
    assert float(none.max()) == 0.0
    full = materials.spots(p, 3, 0.5, torch.ones(p.shape[0])).view(241, 241)
    assert 0.0 <= float(full.min()) and float(full.max()) <= 1.0
    assert float((full > 0.5).float().mean()) > 0.02
    # Round: a spot's extent along x and along y agree (per connected blob, roughly).
    on = (full > 0.5).numpy()
    rows, cols = on.any(1).sum(), on.any(0).sum()
    assert 0.7 < rows / cols < 1.4


@pytest.fixture(scope="module")
def head(shared_data):
    m = assets.load_head(shared_data)
    rig = assets.build_rig(assets.HairStyle(), -11.0, shared_data)
    attrs = materials.vertex_attributes(rig, shared_data)
    skin = torch.full((rig.n_head,), assets.SKIN, dtype=torch.long)
    return m, rig, attrs[: rig.n_head], skin


def test_freckles_darken_light_skin_and_leave_dark_skin_alone(head):
    _, rig, attrs, skin = head
    uv = rig.uv[: rig.n_head]
    base = sample_identity(3)
    for melanin, expect in ((0.1, True), (3.0, False)):
        plain = dataclasses.replace(base, melanin=melanin, freckles=0.0)
        spotted = dataclasses.replace(base, melanin=melanin, freckles=1.0)
        a = materials.surface(skin, uv, attrs, plain)[0]
        b = materials.surface(skin, uv, attrs, spotted)[0]
        darker = (b.sum(1) < a.sum(1) - 1e-4).float().mean()
        assert (float(darker) > 0.01) == expect, (melanin, float(darker))
        assert bool((b <= a + 1e-6).all())  # freckles only ever add melanin


def test_skin_detail_sits_on_the_rest_shape(head):
    m, rig, attrs, skin = head
    np.testing.assert_allclose(attrs[:, materials.REST].numpy(), m.neutral, atol=1e-5)
    ident = sample_identity(5)
    a = materials.surface(skin, rig.uv[: rig.n_head], attrs, ident)[0]
    moved = attrs.clone()
    moved[:, materials.REST] += 0.37  # another place on the body: other pores and mottling
    b = materials.surface(skin, rig.uv[: rig.n_head], moved, ident)[0]
    assert float((a - b).abs().mean()) > 1e-3 * float(a.mean())


def test_hair_shading_thins_to_the_skins_at_the_hairline(head):
    from training.lightstage import shading

    n = 4
    pos = torch.tensor([[0.0, 0.0, -50.0]]).repeat(n, 1)
    nrm = torch.tensor([[0.0, 0.0, 1.0]]).repeat(n, 1)
    tan = torch.tensor([[0.0, 1.0, 0.0]]).repeat(n, 1)
    hair = torch.full((n,), assets.HAIR, dtype=torch.long)
    f0 = torch.full((n,), 0.028)
    rough = torch.full((n,), 0.5)
    dirs = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.95, -0.3122]])  # front; above, just behind
    vis = torch.ones(n, 2)
    k = torch.tensor([0.0, 0.3, 0.7, 1.0])
    t = shading.transfer(pos, nrm, tan, hair, f0, rough, dirs, vis, k)
    skin = shading.transfer(pos, nrm, tan, torch.full((n,), assets.SKIN), f0, rough, dirs, vis)
    full = shading.transfer(pos, nrm, tan, hair, f0, rough, dirs, vis)
    torch.testing.assert_close(t.diffuse[0], skin.diffuse[0])
    torch.testing.assert_close(t.diffuse[3], full.diffuse[3])
    # From behind, only hair's wrapped lighting reaches a front-facing point, in proportion.
    assert float(skin.diffuse[0, 1]) == 0.0 and float(full.diffuse[3, 1]) > 0.0
    torch.testing.assert_close(t.diffuse[:, 1], k * full.diffuse[3, 1])
