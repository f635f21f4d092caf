"""RENDER_VERSION is bumped whenever samples change: the golden probe notices when it was not."""

import numpy as np


def test_the_light_stage_still_renders_its_golden_probe(shared_data):
    from training.data.dataset import renderer_version
    from training.data.make_testset import load_probe, probe_differences, render_probe

    version, golden = load_probe()
    assert version == renderer_version(), (
        f"the golden probe was written for {version}, the light stage is {renderer_version()}: "
        "rewrite it with `python -m training.data.make_testset --write-probe`")
    diffs = probe_differences(render_probe(shared_data), golden)
    assert not diffs, (
        "the light stage's samples changed but training.data.dataset.RENDER_VERSION did not: if "
        "the change is meant, bump RENDER_VERSION (caches and the test set then rebuild) and run "
        "`python -m training.data.make_testset --write-probe`; differences:\n" + "\n".join(diffs))


def test_probe_differences_tolerate_rounding_and_a_stray_texel_but_not_a_change():
    from training.data.make_testset import probe_differences

    rng = np.random.default_rng(0)
    golden = {"img": rng.uniform(0, 2, (2, 3, 40, 40)).astype(np.float32),
              "mask": (rng.uniform(size=(2, 1, 40, 40)) > 0.5).astype(np.float32)}
    same = {k: v.copy() for k, v in golden.items()}
    assert probe_differences(same, golden) == []
    rounded = {**same, "img": golden["img"].astype(np.float16).astype(np.float32)}
    assert probe_differences(rounded, golden) == []
    stray = {**same, "mask": golden["mask"].copy()}
    stray["mask"][0, 0, 3, 3] = 1 - stray["mask"][0, 0, 3, 3]  # one flipped texel of 3200
    assert probe_differences(stray, golden) == []

    brighter = {**same, "img": golden["img"] * 1.01}  # a 1% change of the look
    assert [d.split(":")[0] for d in probe_differences(brighter, golden)] == ["img"]
    patch = {**same, "img": golden["img"].copy()}
    patch["img"][:, :, 10:20, 10:20] += 0.1  # a local change (6% of the elements)
    assert len(probe_differences(patch, golden)) == 1
    resized = {**same, "mask": golden["mask"][:, :, :20]}
    assert "shape" in probe_differences(resized, golden)[0]
    extra = {**same, "flow": np.zeros((2, 2, 40, 40), np.float32)}
    assert probe_differences(extra, golden) == ["flow: new array"]
    assert probe_differences({"img": golden["img"]}, golden) == ["mask: missing now"]
