"""Varied backdrops: only the background changes, it is lit as a matte plane, the kinds differ."""

import numpy as np
import pytest
import torch

from addon.errors import InputError

RES = 40


@pytest.fixture(scope="module")
def datasets(shared_data):
    from training.data.dataset import LightStageDataset
    torch.set_num_threads(1)
    kw = dict(seed=5, length=50, data_root=shared_data, pool=3)
    return (LightStageDataset("train", RES, **kw),
            LightStageDataset("train", RES, backdrops="varied", **kw))


def test_varied_backdrops_change_the_background_only_and_light_it_as_a_plane(datasets):
    wall, varied = datasets
    changed = 0
    for idx in range(6):
        a, b = wall[idx], varied[idx]
        assert set(a) == set(b)
        for k in a:
            if k.startswith(("img_", "gt_")):
                inside = a["mask_t1" if "t1" in k else "mask_t"] >= 1.0
                np.testing.assert_array_equal(a[k] * inside, b[k] * inside, err_msg=k)
            else:
                np.testing.assert_array_equal(a[k], b[k], err_msg=k)
        bg = b["mask_t"][0] == 0
        changed += not np.allclose(a["img_t_i"][:, bg], b["img_t_i"][:, bg])
        # one static matte plane: from the source to the target light every background pixel
        # changes by the same factor per channel
        for c in range(3):
            src, dst = b["img_t_i"][c][bg], b["gt_t_k"][c][bg]
            lit = src > 1e-4 * src.max()
            ratio = dst[lit] / src[lit]
            assert ratio.max() - ratio.min() <= 1e-4 * ratio.max() + 1e-7
        again = varied[idx]
        for k in b:
            np.testing.assert_array_equal(again[k], b[k], err_msg=k)
    assert changed >= 3  # most draws are not the stage's own wall


def test_backdrop_kinds_are_albedos_with_their_own_character(shared_data):
    from training.lightstage import backdrops
    names, bank = backdrops.photo_bank(shared_data)
    assert len(names) == len(bank) >= 20
    h = w = 96
    wall = torch.full((3, h, w), 0.4)

    def detail(img):  # mean absolute difference of neighbouring pixels
        return float((img[:, 1:] - img[:, :-1]).abs().mean()
                     + (img[:, :, 1:] - img[:, :, :-1]).abs().mean())

    rng = np.random.default_rng(1)
    photos = [backdrops.photo(rng, h, w, bank[i]) for i in range(len(bank))]
    patterns = [backdrops.pattern(rng, h, w) for _ in range(8)]
    screens = [backdrops.screen(rng, h, w) for _ in range(20)]
    for img in photos + patterns + screens:
        assert img.shape == (3, h, w) and torch.isfinite(img).all()
    samples = [backdrops.sample(rng, h, w, wall, bank, np.arange(len(bank))) for _ in range(40)]
    for img in samples:
        lo, hi = np.float32(backdrops.ALBEDO[0]), np.float32(backdrops.ALBEDO[1])
        assert img.min().item() >= lo and img.max().item() <= hi
    assert any(torch.equal(s, wall) for s in samples)  # the plain wall stays in the mix
    assert np.median([detail(p) for p in photos]) > 0.002
    assert min(detail(p) for p in patterns) > 0.005
    for s in screens:  # chroma keys: green or blue dominates, folds but no edges
        mean = s.mean(dim=(1, 2))
        assert int(mean.argmax()) in (1, 2) and float(mean.max()) > 1.8 * float(mean[0])
        assert detail(s) < 0.01


def test_training_never_sees_the_held_out_maps_behind_its_subjects(shared_data):
    from training.data.lighting_sampling import HELD_OUT_HDRIS
    from training.lightstage import backdrops
    names, _ = backdrops.photo_bank(shared_data)
    train = {names[i] for i in backdrops.pool_for(names, "train")}
    test = {names[i] for i in backdrops.pool_for(names, "test")}
    assert not train & set(HELD_OUT_HDRIS)
    assert set(HELD_OUT_HDRIS) <= test


def test_an_unknown_backdrop_choice_says_which_exist(shared_data):
    from training.data.dataset import LightStageDataset
    with pytest.raises(InputError, match="varied"):
        LightStageDataset("train", RES, data_root=shared_data, backdrops="greenscreen")


def test_the_training_flag_reaches_the_dataset(shared_data):
    from training.data.dataset import make_dataset
    from training.run.options import parser

    args = parser().parse_args(["--backdrops", "varied"])
    ds = make_dataset("train", RES, 0, data_root=shared_data, pool=2, backdrops=args.backdrops)
    assert ds.backdrops == "varied"
    assert parser().parse_args([]).backdrops == "wall"


def test_background_error_scores_a_kept_backdrop_and_a_repainted_one(shared_data):
    from training.eval.evaluate import background_error
    exact = background_error(lambda s: (s["gt_t_k"], {}), n=3, resolution=RES,
                             data_root=shared_data)
    assert exact["samples"] == 3 and exact["model"] < 1e-6
    assert exact["identity"] > 0.01 and exact["irradiance_ratio"] > 0
    # a repainted backdrop: the background replaced by its mean colour
    def flat(s):
        out = np.array(s["gt_t_k"])
        bg = s["mask_t"][0] == 0
        out[:, bg] = out[:, bg].mean(axis=1, keepdims=True)
        return out, {}
    assert background_error(flat, n=3, resolution=RES, data_root=shared_data)["model"] > 0.01


def test_the_relit_background_choice_with_the_true_source_light_matches_the_stage(shared_data):
    """pipeline.wall_gain (the product's "relit" background) and the light stage's wall agree:
    given the true matte and source light, the kept-and-relit background is nearly exact."""
    from training.eval.evaluate import background_error

    def oracle(s):
        return s["gt_t_k"], {"foreground": s["mask_t"][0], "source_light": s["light_i"]}
    r = background_error(oracle, n=4, resolution=RES, data_root=shared_data)
    assert r["model"] < 1e-6
    assert r["model_relit"] < 0.25 * r["identity"]
    assert r["model_relit"] < r["model_keep"]
