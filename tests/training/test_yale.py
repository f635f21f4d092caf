"""CroppedYale real-data check (training/eval/yale.py): file names, directions, linear sums, the
HDRI restriction, and the end-to-end evaluation with a tiny ONNX model. Data tests skip without
../shared/data; nothing here writes pictures of the data outside tmp_path."""

import json
import pathlib

import numpy as np
import pytest

from addon import lightvec
from addon.errors import InputError
from training.eval import yale as ye

ROOT = pathlib.Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def yale_root(shared_data):
    root = shared_data / "yale" / "CroppedYale"
    if not (root / "yaleB01").is_dir():
        pytest.skip(f"needs CroppedYale at {root}, which is absent on this machine")
    return root


@pytest.fixture(scope="module")
def b01(yale_root):
    return ye.load_subject(yale_root, "yaleB01")


def index_of(subject, azimuth, elevation):
    return next(k for k, a in enumerate(subject.angles) if tuple(a) == (azimuth, elevation))


# ---- file names and files ------------------------------------------------------------------

def test_parse_name_reads_direction_signs_and_the_ambient_image():
    assert ye.parse_name("yaleB01_P00A-035E+40.pgm") == ye.YaleName(1, False, -35, 40)
    assert ye.parse_name("yaleB39_P00A+130E+20.pgm") == ye.YaleName(39, False, 130, 20)
    assert ye.parse_name("yaleB05_P00A+000E-35.pgm") == ye.YaleName(5, False, 0, -35)
    assert ye.parse_name("yaleB12_P00_Ambient.pgm") == ye.YaleName(12, True)
    for other in ("yaleB01_P00.info", "yaleB01_P00A+000E+00.pgm.bad", "README.md",
                  "yaleB01_P01A+000E+00.pgm"):
        assert ye.parse_name(other) is None


def test_read_pgm_skips_header_comments_and_rejects_other_files(tmp_path):
    pix = np.arange(12, dtype=np.uint8).reshape(3, 4)
    p = tmp_path / "a.pgm"
    p.write_bytes(b"P5\n#@DOME@ xc75a yaleB20\n4 3\n255\n" + pix.tobytes())
    codes, top = ye.read_pgm(p)
    np.testing.assert_array_equal(codes, pix)
    assert top == 255
    bad = tmp_path / "b.pgm"
    bad.write_bytes(b"P6\n4 3\n255\n" + bytes(36))
    with pytest.raises(InputError, match="PGM"):
        ye.read_pgm(bad)


def test_failed_strobe_is_an_image_far_darker_than_its_neighbours():
    dirs = ye.yale_direction([0, 10, -10, 20, 25], [0, 0, 0, 10, -10])
    means = np.array([100.0, 90.0, 95.0, 5.0, 80.0])
    np.testing.assert_array_equal(ye.failed_strobes(dirs, means),
                                  [False, False, False, True, False])
    means[3] = 15.0  # 15% of the neighbours' median: a dim but genuine image
    assert not ye.failed_strobes(dirs, means).any()


# ---- directions ---------------------------------------------------------------------------

def test_yale_directions_land_on_the_documented_side_of_the_light_vector():
    # Negative Yale azimuth lights the image's right half: camera +X, columns above 8.
    right = lightvec.splat_direction(ye.yale_direction(-50, 0), 1.0)[..., 0]
    rows, cols = np.nonzero(right)
    assert cols.min() > lightvec.FRONT_COL and set(rows) <= {7, 8}
    left = lightvec.splat_direction(ye.yale_direction(50, 0), 1.0)[..., 0]
    assert np.nonzero(left)[1].max() < lightvec.FRONT_COL
    mirror = right[:, (16 - np.arange(16)) % 16]  # column c <-> 16 - c about the camera axis
    np.testing.assert_allclose(left, mirror, atol=1e-6)
    up = lightvec.splat_direction(ye.yale_direction(0, 45), 1.0)[..., 0]
    assert np.nonzero(up)[0].max() < 8 and set(np.nonzero(up)[1]) <= {7, 8}
    np.testing.assert_allclose(ye.yale_direction(0, 0), [0.0, 0.0, 1.0], atol=1e-12)
    # A lamp to the camera's right brightens normals facing +X, not -X.
    e = lightvec.irradiance(right[..., None].repeat(3, 2), np.array([[1.0, 0, 0], [-1.0, 0, 0]]))
    assert e[0, 0] > 0.5 and e[1, 0] == 0.0


def test_azimuth_sign_matches_the_images(b01):
    k = index_of(b01, -50, 0)  # camera +X under the convention above
    w = b01.images.shape[2] // 2
    assert b01.images[k][:, w:].mean() > 2 * b01.images[k][:, :w].mean()
    check = ye.azimuth_sign_check([b01])
    assert check["pairs"] >= 15 and check["agree"] == check["pairs"]


# ---- linearity, ambient, saturation -------------------------------------------------------

def test_weighted_sum_path_is_linear_and_matches_the_light_vector(b01):
    k1, k2 = index_of(b01, 0, 0), index_of(b01, -50, 0)
    w = np.zeros(len(b01.dirs))
    w[[k1, k2]] = 1.0
    np.testing.assert_allclose(ye.relit_sum(b01, w), b01.images[k1] + b01.images[k2], rtol=1e-6)
    np.testing.assert_allclose(ye.relit_sum(b01, 0.25 * w), 0.25 * ye.relit_sum(b01, w),
                               rtol=1e-6)
    lv = ye.light_vector(b01.dirs, w)
    single = [lightvec.splat_direction(b01.dirs[k], 1.0) for k in (k1, k2)]
    np.testing.assert_allclose(lv, single[0] + single[1], rtol=1e-6)
    np.testing.assert_allclose(lightvec.total_power(lv), [2.0] * 3, rtol=1e-5)


def test_the_codes_are_linear_not_gamma_encoded(b01):
    err = ye.gamma_check(b01, gammas=(1.0, 2.2))
    assert err["1.0"] < 0.85 * err["2.2"]


def test_ambient_is_subtracted_where_it_has_the_crops_size(yale_root, b01):
    k = index_of(b01, 0, 0)
    raw, _ = ye.read_pgm(yale_root / "yaleB01" / "yaleB01_P00A+000E+00.pgm")
    amb, _ = ye.read_pgm(yale_root / "yaleB01" / "yaleB01_P00_Ambient.pgm")
    expect = np.clip(raw.astype(np.float32) - amb, 0, None) / 255.0
    np.testing.assert_allclose(b01.images[k], expect, atol=1e-7)
    assert b01.ambient == "subtracted" and b01.images.min() >= 0.0
    b11 = ye.load_subject(yale_root, "yaleB11")  # ships its ambient image uncropped
    assert b11.ambient.startswith("none") and "640x480" in b11.ambient
    assert len(b11.dirs) == 60  # four images the database itself omits


def test_failed_strobes_are_dropped(yale_root):
    b02 = ye.load_subject(yale_root, "yaleB02")
    assert b02.dropped == (((95, 0), "failed strobe"),)
    assert (95, 0) not in {tuple(a) for a in b02.angles} and len(b02.dirs) == 63


def test_mask_leaves_out_pixels_that_owe_their_value_to_clipped_codes(b01):
    k = int(np.argmax(b01.saturated.sum(axis=(1, 2))))
    w = np.zeros(len(b01.dirs))
    w[k] = 1.0
    ellipse, mask = ye.face_mask(b01.images.shape[1:]), ye.face_mask(b01.images.shape[1:], b01, w)
    clipped = b01.saturated[k] & ellipse
    assert clipped.any() and not (mask & clipped).any()
    assert mask.sum() == (ellipse & ~b01.saturated[k]).sum()


# ---- lightings ------------------------------------------------------------------------------

def test_restricting_a_light_vector_integrates_it_over_each_cell():
    dirs = ye.yale_direction([0, 50, -50, 0], [0, 0, 0, 60])
    omega = ye.cell_solid_angles(dirs)
    # A cell is a cap of 20 degrees at most (solid angle 2 pi (1 - cos 20)), cut by its neighbours.
    assert np.all(omega > 0) and np.all(omega <= 2 * np.pi * (1 - np.cos(np.radians(20))) * 1.01)
    np.testing.assert_allclose(ye.restrict_light(lightvec.uniform(2.0), dirs), 2.0 * omega,
                               rtol=1e-6)
    one = lightvec.zeros()
    row, col = lightvec.directions_to_cells(dirs[1])  # only the texel holding A+050E+00 is lit
    one[row, col] = 1.0
    w = ye.restrict_light(one, dirs)
    assert w[1] > 0 and w[0] == w[2] == w[3] == 0.0


def test_pairs_are_fixed_by_the_seed_and_lightings_sum_to_their_intensity(yale_root, b01):
    bank = ye.HdriBank(yale_root.parents[1])
    p1, p2 = (ye.draw_pairs(b01, 3, 7, bank) for _ in range(2))
    assert [a.kind for a, _ in p1] == list(ye.KINDS)
    for (a1, b1), (a2, b2) in zip(p1, p2):
        assert a1.label == a2.label and b1.label == b2.label
        np.testing.assert_array_equal(a1.weights, a2.weights)
        for lt in (a1, b1):
            intensity = float(lt.label.split(" x ")[0])
            assert 0.5 <= lt.weights.sum() <= 2.0
            assert abs(lt.weights.sum() - intensity) < 0.006
    assert np.count_nonzero(p1[1][0].weights) == 1 and 2 <= np.count_nonzero(p1[2][0].weights) <= 3
    assert np.count_nonzero(p1[0][0].weights) > 20  # an HDRI reaches most of the dome


# ---- relighting and the evaluation ---------------------------------------------------------

@pytest.fixture(scope="module")
def toy(tmp_path_factory):
    from tests.onnx_fixtures import write_toy_model

    return write_toy_model(tmp_path_factory.mktemp("yale_toy"))


def test_pipeline_relighter_follows_the_units_of_the_card(toy, b01):
    from tests.onnx_fixtures import frontal_irradiance_weights

    from addon import normalise

    # the network's own output at its own level
    relight = ye.PipelineRelighter(toy, background="network", exposure="physical")
    img = b01.images[index_of(b01, 0, 0)]
    light = ye.light_vector(b01.dirs[[3]], np.array([1.5]))
    out = relight(img, light)
    # The toy relights by E_front(target) / E_front(its source), its source uniform radiance s,
    # the image's exposure scale (1 in the network's normalised units; relit comes back by k).
    w = frontal_irradiance_weights()
    s = normalise.exposure_scale([np.repeat(img[..., None], 3, axis=2).astype(np.float32)])
    gain = float((w * light[..., 0]).sum() / w.sum()) / s
    # Half-float output and the guided full-resolution transfer blur a few edge pixels slightly.
    assert out.mean() == pytest.approx(img.mean() * gain, rel=1e-3)
    rel = np.abs(out - img * gain) / np.maximum(img * gain, 1e-3)
    assert np.percentile(rel, 99) < 0.01 and rel.max() < 0.15


def test_one_subject_end_to_end_with_a_tiny_model(toy, yale_root, b01):
    relighters = {"toy": ye.PipelineRelighter(toy)}
    bank = ye.HdriBank(yale_root.parents[1])
    pairs = ye.draw_pairs(b01, 3, 1, bank)
    results = [ye.relight_pair(b01, a, b, relighters) for a, b in pairs]
    gains = ye.fit_gains(results)
    assert set(gains) == {"toy", *ye.REFERENCES} and all(np.isfinite(list(gains.values())))
    rows = [(r.kind, ye.score_pair(r, gains)) for r in results]
    summary = ye.summarise(rows)
    for view in ye.VIEWS:
        for m in ("toy", *ye.REFERENCES):
            cell = summary[view][m]["all"]
            assert cell["pairs"] == 3
            assert all(np.isfinite(cell[k]) for k in ("rmse", "psnr", "ssim"))
    for r, (a, b) in zip(results, pairs):
        np.testing.assert_allclose(r.outputs["identity"], r.inputs, rtol=1e-6)
        np.testing.assert_allclose(r.outputs["irradiance_ratio"],
                                   r.inputs * b.weights.sum() / a.weights.sum(), rtol=1e-4)
        np.testing.assert_allclose(r.gt, ye.relit_sum(b01, b.weights))
        flat = np.sqrt(r.inputs * r.inputs.mean()) * b.weights.sum() / a.weights.sum()
        np.testing.assert_allclose(r.outputs[ye.FLATTENED], flat, rtol=1e-4)
    # Under gray light both baselines are the input times a number: equal once gain-aligned.
    si = summary["scale_invariant"]
    assert si["identity"]["all"]["rmse"] == pytest.approx(si["irradiance_ratio"]["all"]["rmse"],
                                                          rel=1e-5)
    assert "| toy |" in ye.markdown(summary, ["toy"])


def test_calibration_finds_the_gain_that_minimises_the_reported_rmse(b01):
    gt = b01.images[:4]
    mask = ye.face_mask(gt.shape[1:])
    results = [ye.PairResult("s", "single", "a", "b", g, mask, g, lightvec.zeros(),
                             {"dim": g / 3.0, "right": g.copy()}) for g in gt]
    gains = ye.fit_gains(results)
    assert gains["dim"] == pytest.approx(3.0, rel=0.012)  # 1/64-octave grid
    assert gains["right"] == pytest.approx(1.0, rel=0.012)
    scored = ye.score_pair(results[0], gains)["calibrated"]
    assert scored["dim"]["rmse"] < 0.01 and scored["right"]["rmse"] < 0.01


def test_paired_comparison_takes_its_standard_error_over_subjects():
    def score(model, ref):
        return {v: {"m": {"rmse": model}, **{r: {"rmse": ref} for r in ye.REFERENCES}}
                for v in ye.VIEWS}
    # Subject "a": the model wins both pairs by 0.1; subject "b": it loses one by 0.1, ties one.
    rows = [("hdri", score(0.1, 0.2), "a"), ("single", score(0.2, 0.3), "a"),
            ("hdri", score(0.3, 0.2), "b"), ("few", score(0.2, 0.2), "b")]
    c = ye.paired_comparison(rows, ["m"])["calibrated"]["m"]["identity"]
    assert c["win_share"] == 0.5
    assert c["mean_rmse_diff"] == pytest.approx((-0.1 + 0.05) / 2)
    assert c["se_subjects"] == pytest.approx(np.std([-0.1, 0.05], ddof=1) / np.sqrt(2))


def test_balance_correlation_carries_an_interval_over_resampled_subjects():
    """Exact balances correlate 1 on every resampling; noisy ones give an interval around the
    figure that narrows with more subjects."""
    rng = np.random.default_rng(0)

    def rows(n_subjects, noise):
        out = []
        for s in range(n_subjects):
            for _ in range(6):
                gt = tuple(rng.normal(0, 0.1, 2))
                pred = tuple(np.array(gt) + rng.normal(0, noise, 2))
                out.append(("few", {}, f"s{s}", {"ground_truth": gt, "m": pred}))
        return out

    exact = ye.balance_correlation(rows(5, 0.0))["m"]
    assert exact["top_bottom"] == pytest.approx(1.0)
    assert exact["top_bottom_90"] == pytest.approx([1.0, 1.0])
    few = ye.balance_correlation(rows(8, 0.1))["m"]
    many = ye.balance_correlation(rows(80, 0.1))["m"]
    for c in (few, many):
        lo, hi = c["left_right_90"]
        assert lo < c["left_right"] < hi and c["subjects"] in (8, 80)
    width = lambda c: c["top_bottom_90"][1] - c["top_bottom_90"][0]
    assert width(many) < 0.6 * width(few)


def test_a_paired_gain_tells_apart_what_the_intervals_alone_do_not():
    """Two methods that share each pair's error and differ by a little more: each one's interval
    is wide and they overlap, but the gain of the better over the worse, taken over the same
    resampled subjects, stays above zero; the reference itself has no gain."""
    rng = np.random.default_rng(2)
    rows = []
    for s in range(10):
        for _ in range(12):
            gt = rng.normal(0, 0.1, 2)
            shared = rng.normal(0, 0.1, 2)  # the pair's own difficulty, common to both
            worse = gt + shared + rng.normal(0, 0.03, 2)
            better = gt + 0.8 * shared + rng.normal(0, 0.03, 2)
            rows.append(("few", {}, f"s{s}", {"ground_truth": tuple(gt), "a": tuple(worse),
                                              "b": tuple(better)}))
    res = ye.balance_correlation(rows, reference="a")
    a, b = res["a"], res["b"]
    assert "top_bottom_gain" not in a
    assert b["top_bottom_gain"] == pytest.approx(b["top_bottom"] - a["top_bottom"])
    assert b["top_bottom_90"][0] < a["top_bottom_90"][1]  # the intervals overlap ...
    assert 0 < b["top_bottom_gain_90"][0] < b["top_bottom_gain"] < b["top_bottom_gain_90"][1]
    assert "top_bottom_gain" not in ye.balance_correlation(rows)["b"]  # only with a reference


def test_one_pair_far_off_the_truth_carries_the_pearson_figure_but_not_the_rank_one():
    rng = np.random.default_rng(3)
    rows = []
    for s in range(10):
        for _ in range(12):
            gt = rng.normal(0, 0.1, 2)
            rows.append(("few", {}, f"s{s}", {"ground_truth": tuple(gt),
                                              "m": tuple(gt + rng.normal(0, 0.02, 2))}))
    clean = ye.balance_correlation(rows)["m"]
    gt = rows[0][3]["ground_truth"]
    rows[0] = ("few", {}, "s0", {"ground_truth": gt, "m": (gt[0], -10.0 * gt[1] + 0.9)})
    off = ye.balance_correlation(rows)["m"]
    assert clean["top_bottom"] > 0.95 and clean["top_bottom_rank"] > 0.95
    assert off["top_bottom"] < 0.6 and off["top_bottom_rank"] > 0.9


def test_top_bottom_by_elevation_says_which_lights_a_method_gets_wrong():
    """A method exact under targets from above and 0.1 too bright on top (balance is bottom
    minus top) under targets from below shows it in the target bins alone: correlation 1 and no
    error above, a bias of -0.1 below; the input bins mix both. Rows without elevations
    (yale_normals') are left out."""
    rng = np.random.default_rng(0)
    rows = []
    for i in range(40):
        eb = 40.0 if i % 2 else -30.0
        t = float(rng.normal()) * 0.05
        p = t if eb > 0 else t - 0.1
        bal = {"ground_truth": (0.0, t), "m": (0.0, p)}
        rows.append(("single", None, f"s{i % 4}", bal, (rng.choice([-30.0, 0.0, 40.0]), eb)))
    rows.append(("single", None, "s0", {"ground_truth": (0.0, 9.0), "m": (0.0, -9.0)}))
    res = ye.balance_by_elevation(rows)["m"]
    assert res["target above"]["pairs"] == 20 and res["target below"]["pairs"] == 20
    assert res["target above"]["correlation"] == pytest.approx(1.0)
    assert res["target above"]["bias"] == pytest.approx(0.0, abs=1e-12)
    assert res["target below"]["bias"] == pytest.approx(-0.1)
    assert res["target level"] == {"pairs": 0, "correlation": None, "bias": None, "mae": None}
    assert sum(res[f"input {k}"]["pairs"] for k in ("above", "level", "below")) == 40
    assert -0.1 < res["input level"]["bias"] < 0.0
    assert ye.balance_by_elevation([r[:4] for r in rows]) == {}
    dirs = np.array([[0.0, 1.0, 1.0], [0.0, -1.0, 1.0]]) / np.sqrt(2)
    assert ye.light_elevation(dirs, np.array([1.0, 0.0])) == pytest.approx(45.0)
    assert ye.light_elevation(dirs, np.array([1.0, 1.0])) == pytest.approx(0.0, abs=1e-9)


def test_balance_splits_into_the_truths_and_the_inputs():
    """A method whose balance is 0.6 x the truth's + 0.3 x the input's (plus noise) is split so;
    the input's own row (the identity method) has no split."""
    rng = np.random.default_rng(1)
    rows = []
    for s in range(6):
        for _ in range(10):
            gt, inp = rng.normal(0, 0.1, 2), rng.normal(0, 0.1, 2)
            pred = 0.6 * gt + 0.3 * inp + 0.02 + rng.normal(0, 0.002, 2)
            rows.append(("few", {}, f"s{s}", {"ground_truth": tuple(gt), "identity": tuple(inp),
                                              "m": tuple(pred)}))
    res = ye.balance_correlation(rows)
    for axis in ("left_right", "top_bottom"):
        split = res["m"][f"{axis}_from"]
        assert split["truth"] == pytest.approx(0.6, abs=0.02)
        assert split["input"] == pytest.approx(0.3, abs=0.02)
    assert "top_bottom_from" not in res["identity"]
    without_input = [(k, sc, s, {"ground_truth": b["ground_truth"], "m": b["m"]})
                     for k, sc, s, b in rows]
    assert "top_bottom_from" not in ye.balance_correlation(without_input)["m"]


def test_identity_is_exact_when_the_light_does_not_change(toy, b01):
    a = ye.Lighting("few", "same", np.where(np.arange(len(b01.dirs)) % 9 == 0, 0.1, 0.0))
    r = ye.relight_pair(b01, a, a, {"toy": ye.PipelineRelighter(toy)})
    for view in ye.score_pair(r, {}).values():
        assert view["identity"]["rmse"] < 1e-6 and view["irradiance_ratio"]["rmse"] < 1e-6


def test_command_line_quick_run_writes_the_table_and_sheet(toy, shared_data, yale_root,
                                                           tmp_path, capsys):
    out, sheet = tmp_path / "yale.json", tmp_path / "sheet.png"
    assert ye.main(["--onnx", str(toy), "--quick", "--data", str(shared_data), "--json", str(out),
                    "--sheet", str(sheet)]) == 0
    res = json.loads(out.read_text())
    assert res["split"] == {"tune": ["yaleB01"], "test": ["yaleB11", "yaleB12"],
                            "reported": "test"}
    assert res["results"]["calibrated"]["toy"]["all"]["pairs"] == 6
    assert set(res["beats_both_baselines"]["calibrated"]) == {"toy"}
    paired = res["paired"]["calibrated"]["toy"]
    assert set(paired) == set(ye.REFERENCES)
    assert all(0.0 <= c["win_share"] <= 1.0 and c["se_subjects"] >= 0 for c in paired.values())
    assert sheet.stat().st_size > 1000 and "| identity |" in capsys.readouterr().out


def test_command_line_says_what_to_do_with_two_models_of_one_name(toy, shared_data, yale_root,
                                                                  tmp_path, capsys):
    rc = ye.main(["--onnx", str(toy), "--onnx", str(toy), "--quick", "--data", str(shared_data),
                  "--json", str(tmp_path / "y.json"), "--sheet", ""])
    assert rc == 2 and "its own name" in capsys.readouterr().err
    assert not (tmp_path / "y.json").exists()


def test_several_models_are_compared_pair_by_pair_with_the_first(toy, shared_data, yale_root,
                                                                tmp_path):
    """With two models, the second's balance correlations carry their paired gain over the
    first's (the same network under another name: no gain, on every resampling either)."""
    from tests.onnx_fixtures import write_toy_model

    twin = write_toy_model(tmp_path / "twin", name="twin")
    out = tmp_path / "y.json"
    assert ye.main(["--onnx", str(toy), "--onnx", str(twin), "--quick", "--data",
                    str(shared_data), "--json", str(out), "--sheet", ""]) == 0
    bc = json.loads(out.read_text())["balance_correlation"]
    assert "top_bottom_gain" not in bc["toy"]
    for key in ("left_right", "top_bottom"):
        assert bc["twin"][f"{key}_gain"] == pytest.approx(0.0, abs=1e-12)
        assert bc["twin"][f"{key}_gain_90"] == pytest.approx([0.0, 0.0], abs=1e-12)
    report = out.with_suffix(".md").read_text()
    assert "Paired gain in correlation over `toy`" in report
    by_elev = json.loads(out.read_text())["top_bottom_by_elevation"]
    assert sum(by_elev["toy"][f"target {k}"]["pairs"] for k in ("above", "level", "below")) == 6
    assert "Top/bottom balance by where the input's" in report


def test_the_tune_split_reports_only_tune_subjects_and_never_overwrites_the_results(
        toy, shared_data, yale_root, tmp_path, capsys, monkeypatch):
    """... and relights a subject both fitted on and reported once: its pairs for the gains
    are its pairs in the tables."""
    calls = []
    relight_pair = ye.relight_pair

    def counted(subject, a, b, *args, **kwargs):
        calls.append((subject.name, a.label, b.label))
        return relight_pair(subject, a, b, *args, **kwargs)

    monkeypatch.setattr(ye, "relight_pair", counted)
    out = tmp_path / "tune.json"
    assert ye.main(["--onnx", str(toy), "--quick", "--split", "tune", "--data", str(shared_data),
                    "--json", str(out), "--sheet", ""]) == 0
    res = json.loads(out.read_text())
    assert res["split"] == {"tune": ["yaleB01"], "test": ["yaleB01", "yaleB02"],
                            "reported": "tune"}
    # three pairs each (--quick): yaleB01's for the gains and the tables, then yaleB02's
    assert [c[0] for c in calls] == ["yaleB01"] * 3 + ["yaleB02"] * 3
    assert len(set(calls)) == 6
    assert sum(res["top_bottom_by_elevation"]["toy"][f"target {k}"]["pairs"]
               for k in ("above", "level", "below")) == 6
    assert all(int(n[5:]) in ye.TUNE_SUBJECTS for n in res["split"]["test"])
    assert "tune subjects, not the held-out test subjects" in out.with_suffix(".md").read_text()
    with pytest.raises(SystemExit):  # the default --json holds the test subjects' results
        ye.main(["--onnx", str(toy), "--quick", "--split", "tune"])
    assert "give --json elsewhere" in capsys.readouterr().err


def test_input_lift_and_compare_lift_set_the_lift_while_they_relight(toy, shared_data, yale_root,
                                                                     tmp_path, monkeypatch,
                                                                     capsys):
    """--input-lift: the whole run's crops are lifted by that power, and the product's after it;
    --compare-lift: the first model again at that power, on the same pairs, reported beside it
    with its paired balance gain; a power outside (0, 1] is refused."""
    from addon import api, portrait

    shipped, seen = portrait.INPUT_LIFT, []
    relight = api.relight_image

    def spied(*args, **kwargs):
        seen.append(portrait.INPUT_LIFT)
        return relight(*args, **kwargs)

    monkeypatch.setattr(api, "relight_image", spied)
    out = tmp_path / "y.json"
    assert ye.main(["--onnx", str(toy), "--quick", "--split", "tune", "--input-lift", "0.9",
                    "--data", str(shared_data), "--json", str(out), "--sheet", ""]) == 0
    assert seen and set(seen) == {0.9} and portrait.INPUT_LIFT == shipped
    seen.clear()
    assert ye.main(["--onnx", str(toy), "--quick", "--split", "tune", "--compare-lift", "0.5",
                    "--data", str(shared_data), "--json", str(out), "--sheet", ""]) == 0
    assert set(seen) == {shipped, 0.5} and seen.count(0.5) == seen.count(shipped)
    assert portrait.INPUT_LIFT == shipped
    res = json.loads(out.read_text())
    name = next(iter(res["models"]))
    assert list(res["models"]) == [name, f"{name} lift 0.5"]
    assert "top_bottom_gain" in res["balance_correlation"][f"{name} lift 0.5"]
    for bad in ("0", "1.5"):
        with pytest.raises(SystemExit):
            ye.main(["--onnx", str(toy), "--quick", "--compare-lift", bad, "--json", str(out)])
        assert "must lie in (0, 1]" in capsys.readouterr().err


def test_input_level_feeds_the_crops_at_that_level_for_the_run_only(toy, shared_data, yale_root,
                                                                   tmp_path, monkeypatch, capsys):
    """--input-level: the intrinsic networks' crops are normalised to that level while the run
    relights (the experiment the training option --bright follows), and to the product's after
    it; a level that is not positive is refused."""
    from addon import intrinsic

    shipped, seen = intrinsic.INPUT_LEVEL, []
    run = ye.run

    def spied(*args, **kwargs):
        seen.append(intrinsic.INPUT_LEVEL)
        return run(*args, **kwargs)

    monkeypatch.setattr(ye, "run", spied)
    out = tmp_path / "y.json"
    assert ye.main(["--onnx", str(toy), "--quick", "--split", "tune", "--input-level", "0.8",
                    "--data", str(shared_data), "--json", str(out), "--sheet", ""]) == 0
    assert seen == [0.8] and intrinsic.INPUT_LEVEL == shipped
    assert "--input-level 0.8" in json.loads(out.read_text())["command"]
    with pytest.raises(SystemExit):
        ye.main(["--onnx", str(toy), "--quick", "--input-level", "0", "--json", str(out)])
    assert "--input-level must be positive" in capsys.readouterr().err


def test_the_lambertian_ceilings_are_exact_on_a_lambertian_subject():
    """A subject that is exactly Lambertian, lit everywhere by every light (a sphere facing the
    lights, no attached shadows on the lit cap): the fit renders any lighting exactly, and so
    does the exact shading ratio; where the fit does not exist both fall back to a gain."""
    s = 24
    yy, xx = np.mgrid[0:s, 0:s] + 0.5
    u, v = (xx - s / 2) / (s * 0.9), (yy - s / 2) / (s * 0.9)
    n = np.stack([u, -v, np.sqrt(np.clip(1 - u * u - v * v, 0, 1))]).reshape(3, -1)
    n /= np.linalg.norm(n, axis=0)
    albedo = 0.3 + 0.4 * (xx > s / 2).reshape(-1)
    angles = np.array([(a, e) for a in (-20, 0, 20) for e in (-20, 0, 20)])
    dirs = np.stack([ye.yale_direction(a, e) for a, e in angles])
    images = (np.clip(dirs @ n, 0, None) * albedo).reshape(len(dirs), s, s).astype(np.float32)
    subject = ye.Subject("toy", 99, angles, dirs, images, np.zeros(images.shape, bool), "", ())
    shading = ye.subject_shading(subject)
    assert shading[1].mean() > 0.5
    rng = np.random.default_rng(3)
    a = ye.Lighting("few", "a", rng.uniform(0, 1, len(dirs)))
    b = ye.Lighting("few", "b", rng.uniform(0, 1, len(dirs)))
    out = ye.ceilings(ye.relit_sum(subject, a.weights), a, b, shading)
    gt = ye.relit_sum(subject, b.weights).reshape(-1)
    ok = shading[1]
    for name in (ye.LAMBERT_FIT, ye.LAMBERT_RATIO):
        np.testing.assert_allclose(out[name].reshape(-1)[ok], gt[ok], rtol=1e-4)
    assert {ye.LAMBERT_FIT, ye.LAMBERT_RATIO} <= set(ye.REFERENCES)


def test_portrait_frontier_measures_each_working_size_on_real_faces_and_in_time(yale_root,
                                                                                tmp_path):
    """bench.intrinsic_frontier --quick: each size is its own run (the crop size reaches the
    product path), with accuracy, balance intervals and per-stage times; the card's size is
    marked."""
    from bench import intrinsic_frontier

    model = str(ROOT / "models" / "relight-portrait.onnx")
    out = tmp_path / "frontier"
    assert intrinsic_frontier.main(["--model", model, "--quick", "--sizes", "96", "128",
                                    "--threads", "1", "--out", str(out)]) == 0
    res = json.loads(out.with_suffix(".json").read_text())
    assert res["card_working_size"] == 128 and set(res["sizes"]) == {"96", "128"}
    small, card = res["sizes"]["96"], res["sizes"]["128"]
    for r in (small, card):
        assert r["pairs"] == 6 and 10 < r["psnr_scale_invariant"] < 40
        assert r["top_bottom_90"][0] <= r["top_bottom_90"][1]
        assert all(v > 0 for v in r["stages_ms"].values()) and r["end_to_end_1080p_fps"] > 0
    assert small["psnr_scale_invariant"] != card["psnr_scale_invariant"]
    assert "| 128 (card) |" in out.with_suffix(".md").read_text()


def test_portrait_frontier_writes_the_card_s_time_per_frame(yale_root, tmp_path):
    """--write-card: the card records the per-frame path on 640-px frames, as bench/frontier.py
    records the end-to-end presets', and the panel's summary shows it; the error beside it stays
    the card's RMSE at the right level."""
    import shutil

    from addon import engine
    from bench import intrinsic_frontier

    for suffix in (".onnx", ".json"):
        shutil.copy(ROOT / "models" / f"relight-portrait{suffix}", tmp_path / f"p{suffix}")
    model = tmp_path / "p.onnx"
    before = engine.load_card(model)
    assert intrinsic_frontier.main(["--model", str(model), "--quick", "--sizes", "128",
                                    "--threads", "1", "--out", str(tmp_path / "f"),
                                    "--write-card"]) == 0
    card = engine.load_card(model)
    point = card.data["frontier"]
    assert point["full_size"] == intrinsic_frontier.CARD_FRAME == 640
    assert point["p10_ms"] <= point["ms_per_frame"] <= point["p90_ms"]
    assert card.timing == (point["ms_per_frame"], "128 px, CPU")
    assert point["ms_per_frame"] > before.ms_per_frame  # the whole path, not the network alone
    assert card.held_out_error == before.held_out_error
    assert card.held_out_error[1] == "RMSE at the right level"


def test_compare_face_template_relights_the_first_model_again_with_the_template(
        toy, shared_data, yale_root, tmp_path, monkeypatch, capsys):
    """--compare-face-template: the first model again with that template in place of the
    product's while that relighter runs (or none, with 'none'; the product's otherwise and
    after it), on the same pairs, reported beside it with its paired balance gain (named for
    its --face-template-axes where not the vertical's alone); a missing template is a clear
    error (exit 2)."""
    from addon import api, facetemplate, portrait

    seen = []
    relight = api.relight_image

    def spied(*args, **kwargs):
        seen.append((portrait.FACE_TEMPLATE, portrait.FACE_TEMPLATE_AXES))
        return relight(*args, **kwargs)

    monkeypatch.setattr(api, "relight_image", spied)
    shape = tmp_path / "t.npz"
    np.savez(shape, normal=np.tile(np.array([0.0, 0.0, 1.0], np.float32)[:, None, None],
                                   (1, 8, 8)), reach=np.float32(1.3))
    out = tmp_path / "y.json"
    product = (facetemplate.SHIPPED, "y")
    for given, axes, suffix, during in ((str(shape), "y", " face template", (str(shape), "y")),
                                        (str(shape), "xyz", " face template xyz",
                                         (str(shape), "xyz")),
                                        ("none", "y", " no face template", (None, "y"))):
        seen.clear()
        assert ye.main(["--onnx", str(toy), "--quick", "--split", "tune",
                        "--compare-face-template", given, "--face-template-axes", axes,
                        "--data", str(shared_data), "--json", str(out), "--sheet", ""]) == 0
        assert seen and seen.count(during) == seen.count(product) == len(seen) // 2
        assert (portrait.FACE_TEMPLATE, portrait.FACE_TEMPLATE_AXES) == product
        res = json.loads(out.read_text())
        name = next(iter(res["models"]))
        assert list(res["models"]) == [name, name + suffix]
        assert "top_bottom_gain" in res["balance_correlation"][name + suffix]
    assert ye.main(["--onnx", str(toy), "--quick", "--split", "tune", "--compare-face-template",
                    str(tmp_path / "none.npz"), "--data", str(shared_data), "--json",
                    str(out), "--sheet", ""]) == 2
    assert "python -m training.intrinsic.template" in capsys.readouterr().err
