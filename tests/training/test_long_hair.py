"""Long hair in the light stage (lightstage/assets.py ``Curtain``): it is opt-in and changes
nothing else about an identity, it never passes through the head, and a frame that has it shows
hair beside the jaw and over the ears, in the matte and the parsing, with finite images and
flows."""

import dataclasses

import numpy as np
import pytest
import torch

from addon import lightvec
from training.lightstage import assets
from training.lightstage.subject import sample_identity

RES = 64


def test_long_hair_is_opt_in_and_leaves_the_rest_of_the_identity_alone():
    plain = [sample_identity(i) for i in range(48)]
    assert all(p.hair.hang == 0.0 for p in plain)
    long = [sample_identity(i, long_hair=0.5) for i in range(48)]
    hung = [lo for lo in long if lo.hair.hang > 0]
    assert 10 <= len(hung) <= 38
    for p, lo in zip(plain, long):
        # Everything but the hair's length and front edges is the identity's own.
        assert dataclasses.replace(lo.hair, hang=0.0, reach=p.hair.reach) == p.hair
        np.testing.assert_array_equal(p.shape, lo.shape)
        assert (p.melanin, p.texture_seed) == (lo.melanin, lo.texture_seed)
        assert not (p.hair.bald and lo.hair.hang)  # the bald stay bald
    assert all(sample_identity(i, long_hair=1.0).hair.hang > 0
               for i in range(48) if not plain[i].hair.bald)


def _angle(a):
    return (a + np.pi) % (2 * np.pi) - np.pi


def test_the_curtain_falls_outside_the_head_from_its_widest_point(shared_data):
    m = assets.load_head(shared_data)
    style = assets.HairStyle(hang=12.0, reach=(60.0, 140.0), volume=0.3)
    rig = assets.build_rig(style, -12.0, shared_data)
    assert rig.curtain is not None
    head = torch.from_numpy(m.neutral).double()
    c = assets.curtain_vertices(head, rig.curtain, style.volume).numpy()
    rows, cols = rig.curtain.y.shape
    assert c.shape == (rows * cols, 3) and np.isfinite(c).all()
    v = m.neutral
    az_h = np.arctan2(v[:, 0], v[:, 2] - 1.0)
    r_h = np.hypot(v[:, 0], v[:, 2] - 1.0)
    az_c = np.arctan2(c[:, 0], c[:, 2] - 1.0)
    r_c = np.hypot(c[:, 0], c[:, 2] - 1.0)
    # The sides and the back only: nothing in front of either side's front edge (+X at 60
    # degrees, -X tucked back at 140).
    assert np.degrees(az_c[az_c > 0]).min() >= 60.0 - 0.1
    assert np.degrees(-az_c[az_c < 0]).min() >= 140.0 - 0.1
    # No curtain vertex inside the head: the head (above the bust) at its azimuth, at its height
    # or higher, is closer to the axis.
    for k in range(0, len(c), 7):
        near = (np.abs(_angle(az_h - az_c[k])) < np.radians(1.5)) & (v[:, 1] >= c[k, 1]) \
            & (v[:, 1] > assets.CURTAIN_FROM)
        if near.any():
            assert r_c[k] > r_h[near].max(), k
    # It hangs to ``hang`` below the chin (its ragged edge within a few cm of that).
    low = rig.curtain.y[-1].numpy()
    assert np.median(low) == pytest.approx(-7.5 - 12.0, abs=2.0)
    assert low.max() < -7.5 - 12.0 + 3.0


@pytest.fixture(scope="module")
def frames(shared_data):
    from training.lightstage.scene import Scene
    from training.lightstage.subject import Camera, Performance

    torch.set_num_threads(1)
    m = assets.load_head(shared_data)
    ident = next(sample_identity(i) for i in range(40) if not sample_identity(i).hair.bald)
    long = dataclasses.replace(ident, hair=dataclasses.replace(ident.hair, hang=14.0,
                                                                 reach=(70.0, 70.0)))
    cam = Camera(focal=RES * 1.2, cx=RES / 2, cy=RES / 2 - 8, distance=80.0, height=RES,
                 width=RES)
    out = {}
    for name, who in (("short", ident), ("long", long)):
        sc = Scene(who, Performance(4, m.expression_names), cam, shared_data, 2)
        out[name] = (sc, sc.frame(0.4), sc.frame(0.44))
    return out


def test_a_frame_with_long_hair_has_hair_beside_the_jaw_in_its_matte_and_labels(frames):
    hair = assets.LABEL["hair"]
    rows = {name: np.nonzero((f0.gb.label.numpy() == hair).any(1))[0].max()
            for name, (_, f0, _) in frames.items()}
    # Short hair stops above the ears; long hair reaches far lower, and the matte takes it in:
    # pixels that were backdrop beside the head and neck are now subject.
    assert rows["long"] > rows["short"] + RES // 8, rows
    gained = (frames["long"][1].cover - frames["short"][1].cover).clamp(min=0)
    assert float(gained.sum()) > 20.0
    assert float(gained[rows["short"]:].sum()) > 0.5 * float(gained.sum())
    sc, f0, f1 = frames["long"]
    img = sc.shade(f0, [lightvec.splat_direction([1.0, 0.2, 0.5], [3.0, 3.0, 3.0])])
    fl, valid = sc.flow(f0, f1)
    assert torch.isfinite(img).all() and torch.isfinite(fl).all()
    assert float(valid.mean()) > 0.5
    on_hair = f0.gb.label == hair
    assert float(img[0][:, on_hair].mean()) > 0.0  # lit, not a black hole


def test_long_hair_cannot_come_from_a_light_stage_cache(shared_data):
    from addon.errors import InputError
    from training.data.dataset import LightStageDataset

    with pytest.raises(InputError, match="renders on the fly"):
        LightStageDataset("train", 32, data_root=shared_data, cache_dir="cache/lightstage",
                          long_hair=0.5)
