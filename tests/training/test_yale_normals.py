"""training/eval/yale_normals.py: photometric stereo recovers a Lambertian sphere's normals, the
comparison reads a flattened prediction as flatter, and on a real CroppedYale subject the
shipped Portrait's normals agree with photometric stereo far better than a flat face would (data
test: skips without CroppedYale)."""

import numpy as np
import pytest

from training.eval import yale as ye
from training.eval import yale_normals as yn

S = 48


def sphere_normals():
    yy, xx = np.mgrid[0:S, 0:S] + 0.5
    u, v = (xx - S / 2) / (S * 0.45), (yy - S / 2) / (S * 0.45)
    inside = u * u + v * v < 0.95
    nz = np.sqrt(np.clip(1 - u * u - v * v, 0.0, 1.0))
    n = np.stack([u, -v, nz]).reshape(3, -1)
    return n / np.linalg.norm(n, axis=0), inside.reshape(-1)


def lights():
    angles = np.array([(a, e) for a in (-40, -20, 0, 20, 40) for e in (-30, 0, 30)], float)
    dirs = np.stack([ye.yale_direction(a, e) for a, e in angles])
    return dirs, angles


def test_photometric_stereo_recovers_a_lambertian_sphere():
    n, inside = sphere_normals()
    dirs, angles = lights()
    images = np.clip(dirs @ n, 0.0, None).reshape(len(dirs), S, S) * 0.6 + 0.1  # + ambient
    got, ok = yn.photometric_normals(images - 0.1, dirs)
    m = ok & inside
    assert m.sum() > 0.3 * inside.sum()
    assert yn.compare(got, n, m)["angle_deg"] < 0.5


def test_a_flatter_prediction_reads_as_flatter():
    n, inside = sphere_normals()
    same = yn.compare(n, n, inside)
    assert same["angle_deg"] < 1e-3 and same["corr_y"] > 0.999
    assert same["spread_x"] == pytest.approx(1.0) and same["spread_y"] == pytest.approx(1.0)
    flat = n * np.array([1.0, 0.5, 1.0])[:, None]
    flat /= np.linalg.norm(flat, axis=0)
    r = yn.compare(flat, n, inside)
    assert r["spread_y"] < 0.7 and r["spread_x"] > 0.9 and r["angle_deg"] > 3.0


def test_the_tilt_reads_a_forehead_that_faces_up():
    """A sphere's upper half faces up, its lower half down: a positive tilt, halved for a
    sphere flattened vertically to half, and the opposite sign for one turned upside down."""
    n, inside = sphere_normals()
    r = yn.compare(n, n, inside, S)
    assert r["tilt"] == pytest.approx(r["tilt_truth"]) and r["tilt"] > 0.5
    upside_down = n * np.array([1.0, -1.0, 1.0])[:, None]
    assert yn.tilt(upside_down, inside, S) == pytest.approx(-r["tilt"])
    half = n * np.array([1.0, 0.5, 1.0])[:, None]
    assert yn.tilt(half, inside, S) == pytest.approx(0.5 * r["tilt"])
    assert yn.tilt(n, inside & False, S) == 0.0


def test_the_pitch_reads_a_face_turned_up_as_facing_up():
    """The mean up/down component: about 0 for a sphere seen head on, positive for its normals
    turned up about the horizontal axis, the prediction's and the truth's apart."""
    n, inside = sphere_normals()
    a = 0.3
    up = np.stack([n[0], np.cos(a) * n[1] + np.sin(a) * n[2],
                   -np.sin(a) * n[1] + np.cos(a) * n[2]])
    r = yn.compare(up, n, inside)
    assert abs(r["pitch_truth"]) < 0.02 and r["pitch"] > 0.15


def test_the_shipped_portrait_s_normals_follow_a_real_face(shared_data):
    root = shared_data / "yale" / "CroppedYale"
    if not (root / "yaleB01").is_dir():
        pytest.skip(f"needs CroppedYale at {root}, which is absent on this machine")
    s = ye.load_subject(root, "yaleB01")
    truth, ok = yn.photometric_normals(s.images, s.dirs)
    mask = ye.face_mask(s.images.shape[1:]).reshape(-1) & ok
    front = int(np.argmin(np.abs(s.angles).sum(1)))
    from addon import api

    pred = yn.network_normals(api.session("models/relight-portrait.onnx", 1), s.images[front])
    assert pred is not None
    got = yn.compare(pred, truth, mask)
    flat = yn.compare(np.tile([[0.0], [0.0], [1.0]], (1, truth.shape[1])) + 1e-6 * truth,
                      truth, mask)
    assert got["angle_deg"] < 0.7 * flat["angle_deg"]
    assert got["corr_x"] > 0.8 and got["corr_y"] > 0.3


def test_photometric_buffers_put_the_given_normals_into_the_face_crop_and_then_step_aside(
        shared_data):
    """The face crop and its finer sampling (portrait.ZOOM) carry the given normals where they
    were fitted; the buffers of an image that is not a crop just taken, and everything after
    the context, are the network's."""
    root = shared_data / "yale" / "CroppedYale"
    if not (root / "yaleB01").is_dir():
        pytest.skip(f"needs CroppedYale at {root}, which is absent on this machine")
    from addon import api, portrait

    s = ye.load_subject(root, "yaleB01")
    h, w = s.images.shape[1:]
    gray = s.images[int(np.argmin(np.abs(s.angles).sum(1)))]
    x = np.repeat(gray[None], 3, axis=0).astype(np.float32)
    sess = api.session("models/relight-portrait.onnx", 1)
    box = portrait.find_box(sess, x)
    up = np.tile([[0.0], [1.0], [0.0]], (1, h * w))  # every fitted pixel faces straight up
    fitted = np.zeros(h * w, bool)
    fitted[: h * w // 2] = True  # the image's upper half
    finer_size = round(sess.card.working_size * portrait.ZOOM)
    with yn.photometric_buffers(up, fitted):
        crop, valid = portrait.crop_planar(x, box, sess.card.working_size)
        got = portrait.buffers(sess, crop, valid).normal
        again = portrait.buffers(sess, crop, valid).normal  # no crop taken just before it
        finer, finer_valid = portrait.crop_planar(x, box, finer_size)
        got_finer = portrait.buffers(sess, finer, finer_valid).normal
    with yn.real_relief():  # as the context leaves the network's: not deepened
        plain = portrait.buffers(sess, crop, valid).normal
        plain_finer = portrait.buffers(sess, finer, finer_valid).normal
    assert portrait.buffers.__module__ == "addon.portrait"  # restored
    np.testing.assert_array_equal(again, plain)
    for g, p, size in ((got, plain, sess.card.working_size), (got_finer, plain_finer, finer_size)):
        changed = np.abs(g - p).max(0) > 1e-6
        assert changed.any() and np.allclose(g[:, changed], [[0.0], [1.0], [0.0]], atol=1e-5)
        rows = np.nonzero(changed)[0]
        # only the part of the crop that shows the image's upper half
        assert rows.max() < size / 2


def frontal_b01(shared_data):
    """(h, w, the frontal photo of yaleB01 as a (3, h, w) frame, the shipped Portrait's session,
    its box there), or a skip where CroppedYale is absent."""
    root = shared_data / "yale" / "CroppedYale"
    if not (root / "yaleB01").is_dir():
        pytest.skip(f"needs CroppedYale at {root}, which is absent on this machine")
    from addon import api, portrait

    s = ye.load_subject(root, "yaleB01")
    h, w = s.images.shape[1:]
    x = np.repeat(s.images[int(np.argmin(np.abs(s.angles).sum(1)))][None], 3, axis=0)
    x = x.astype(np.float32)
    sess = api.session("models/relight-portrait.onnx", 1)
    return h, w, x, sess, portrait.find_box(sess, x)


def test_the_face_crop_relights_the_given_normals_not_the_template_over_them(shared_data):
    """Within photometric_buffers the face crop's buffers, the mean of its passes
    (portrait.face_buffers), keep the given normals where they were fitted: the product holds
    that mean to the face template, which would otherwise lay its own up/down shape over them;
    after the context the product holds it again."""
    from addon import portrait

    h, w, x, sess, box = frontal_b01(shared_data)
    up = np.tile([[0.0], [0.6], [0.8]], (1, h * w))  # every fitted pixel faces up and forward
    fitted = np.ones(h * w, bool)
    n = sess.card.working_size
    _, _, before = portrait.face_buffers(sess, x, box, n)
    with yn.photometric_buffers(up, fitted):
        _, _, got = portrait.face_buffers(sess, x, box, n)
    inner = (slice(n // 2 - 20, n // 2 + 20),) * 2
    np.testing.assert_allclose(got.normal[(slice(None),) + inner],
                               np.broadcast_to(np.array([0.0, 0.6, 0.8])[:, None, None],
                                               (3, 40, 40)), atol=1e-5)
    assert portrait.templated.__module__ == "addon.portrait"  # restored
    _, _, after = portrait.face_buffers(sess, x, box, n)  # the product's, held again
    np.testing.assert_array_equal(after.normal, before.normal)


def test_a_band_swap_keeps_one_shape_s_low_band_and_the_other_s_detail(shared_data):
    """photometric_buffers' low_sigma: a flat field (every normal up) has no detail, so swapping
    the network's low band in gives the network's normals blurred, and swapping the flat
    field's low band in gives "up" with the network's detail on it."""
    from addon import intrinsic, portrait

    h, w, x, sess, box = frontal_b01(shared_data)
    up = np.tile([[0.0], [1.0], [0.0]], (1, h * w))
    fitted = np.ones(h * w, bool)
    crop, valid = portrait.crop_planar(x, box, sess.card.working_size)
    with yn.real_relief():  # as the "network" swap leaves them: not deepened
        plain = portrait.buffers(sess, crop, valid).normal
    got = {}
    for low in ("network", "photometric"):
        with yn.photometric_buffers(up, fitted, low_sigma=3.0, low=low):
            crop, valid = portrait.crop_planar(x, box, sess.card.working_size)
            got[low] = portrait.buffers(sess, crop, valid).normal
    inner = np.zeros(plain.shape[1:], bool)  # well inside the image (no band at its edge)
    n = sess.card.working_size
    inner[n // 2 - 10:n // 2 + 10, n // 2 - 10:n // 2 + 10] = True
    blurred = intrinsic.unit_normals(np.stack([intrinsic.gaussian_blur(c, 3.0) for c in plain]))
    np.testing.assert_allclose(got["network"][:, inner], blurred[:, inner], atol=2e-3)
    assert got["photometric"][1, inner].mean() > 0.9  # up ...
    flat = np.array([0.0, 1.0, 0.0])[:, None]
    assert np.abs(got["photometric"][:, inner] - flat).max() > 0.05  # ... with detail on it


def test_a_shared_low_band_lies_between_the_network_s_and_the_given_one(shared_data):
    """photometric_buffers' share: 0 keeps the network's normals, 1 swaps the given low band in
    whole (the default), and a share between blends the two low bands under the network's
    detail, so a flat field's "up" pulls the normals up part of the way."""
    from addon import portrait

    h, w, x, sess, box = frontal_b01(shared_data)
    up = np.tile([[0.0], [1.0], [0.0]], (1, h * w))
    fitted = np.ones(h * w, bool)
    n = sess.card.working_size
    crop, valid = portrait.crop_planar(x, box, n)
    plain = portrait.buffers(sess, crop, valid).normal
    got = {}
    for share in (None, 0.0, 0.5, 1.0):
        kwargs = {} if share is None else {"share": share}
        with yn.photometric_buffers(up, fitted, low_sigma=3.0, **kwargs):
            crop, valid = portrait.crop_planar(x, box, n)
            got[share] = portrait.buffers(sess, crop, valid).normal
    np.testing.assert_array_equal(got[1.0], got[None])
    np.testing.assert_allclose(got[0.0], plain, atol=1e-5)
    inner = (slice(n // 2 - 10, n // 2 + 10),) * 2
    y = {k: float(v[1][inner].mean()) for k, v in got.items()}
    assert y[0.0] + 0.1 < y[0.5] < y[1.0] - 0.1


def test_a_face_space_is_the_low_bands_mean_and_their_principal_modes():
    """face_space: the first map is the mean of the fields' low bands, the others orthonormal
    directions, and a field whose low band lies in the set's span is rebuilt by them exactly."""
    hw, sigma = (24, 20), 2.0
    rng = np.random.default_rng(0)
    fields = [rng.normal(size=(3, hw[0] * hw[1])).astype(np.float32) for _ in range(5)]
    space = yn.face_space(fields, hw, sigma, 3)
    assert space.shape == (4, 3, *hw)
    lows = np.stack([yn._low(f.reshape(3, *hw), sigma) for f in fields])
    np.testing.assert_allclose(space[0], lows.mean(0), atol=1e-5)
    modes = space[1:].reshape(3, -1).astype(np.float64)
    np.testing.assert_allclose(modes @ modes.T, np.eye(3), atol=1e-4)
    full = yn.face_space(fields, hw, sigma, 4).reshape(5, -1).astype(np.float64)
    target = (0.3 * lows[0] + 0.7 * lows[3]).reshape(-1)  # in the span of mean + 4 modes
    coef = np.linalg.lstsq(full.T, target, rcond=None)[0]
    np.testing.assert_allclose(full.T @ coef, target, atol=1e-4)


def test_face_space_buffers_hold_the_face_s_low_band_to_the_space(shared_data):
    """face_space_buffers with a space of one flat field (every normal toward the camera): over
    the face skin the network's low band is replaced by its best multiple of that field, so
    where the network's cheeks turned left and right only their detail is left sideways; beyond
    the blend's reach the normals stay the network's."""
    from addon import intrinsic, portrait

    h, w, x, sess, box = frontal_b01(shared_data)
    n = sess.card.working_size
    crop, valid = portrait.crop_planar(x, box, n)
    plain = portrait.buffers(sess, crop, valid)
    space = np.zeros((1, 3, h, w), np.float32)
    space[0, 2] = 1.0
    with yn.face_space_buffers(space, 6.0):
        crop, valid = portrait.crop_planar(x, box, n)
        held = portrait.buffers(sess, crop, valid)
    # the skin the fit replaces whole (its blend's weight 1)
    skin = ((plain.face > 0.5) & (plain.matte > 0.5)).astype(np.float32)
    core = intrinsic.gaussian_blur(skin, 2.0) > 0.999
    assert core.sum() > 100
    detail = plain.normal[0] - yn._low(plain.normal, 6.0)[0]
    assert np.abs(held.normal[0][core]).mean() < 0.5 * np.abs(plain.normal[0][core]).mean()
    assert np.abs(held.normal[0][core]).mean() < 1.5 * np.abs(detail[core]).mean()
    off = (plain.matte < 0.01) & (intrinsic.gaussian_blur(skin, 2.0) == 0.0)  # beyond the blend
    assert off.sum() > 1000
    np.testing.assert_allclose(held.normal[:, off], plain.normal[:, off], atol=1e-6)


def test_relight_with_swapped_bands_reports_every_variant(shared_data):
    """--relight --low-sigma --no-shadows: the network's normals, the real ones, either's low band
    under the other's detail, a template of the other subjects' real normals, and the network's
    and the real normals without cast shadows, each with its figures; the real normals put the
    light where the truth has it at least as well as the network's."""
    root = shared_data / "yale" / "CroppedYale"
    if not (root / "yaleB01").is_dir():
        pytest.skip(f"needs CroppedYale at {root}, which is absent on this machine")
    got = yn.relight("models/relight-portrait.onnx", "tune", root, n_pairs=3, low_sigma=4.0,
                     shadowless=True, template_shares=(0.5,), face_modes=(1,))
    assert set(got) == {"network", "photometric", "photometric low band", "network low band",
                        "template low band", yn.template_variant(0.5), yn.face_space_variant(1),
                        "network" + yn.NO_SHADOWS, "photometric" + yn.NO_SHADOWS}
    for which, r in got.items():
        assert all(np.isfinite(r[k]) for k in ("all", "left_right", "top_bottom"))
        assert all(np.isfinite(r["top_bottom_from"][k]) for k in ("truth", "input"))
        lo, hi = r["top_bottom_90"]
        assert lo <= hi and r["pairs"] == 3 * r["subjects"]
        # each variant's gain over the network's normals, paired over the same pairs
        assert ("top_bottom_gain" in r) == (which != "network")
        if which != "network":
            want = r["top_bottom"] - got["network"]["top_bottom"]
            assert r["top_bottom_gain"] == pytest.approx(want, abs=1e-9)
            assert r["top_bottom_gain_90"][0] <= r["top_bottom_gain_90"][1]
    assert got["photometric"]["top_bottom"] >= got["network"]["top_bottom"] - 0.02
    assert len({round(r["all"], 6) for r in got.values()}) == 9  # nine different relightings


def test_relief_says_how_deep_the_network_draws_real_faces(shared_data):
    """--relief: per tune subject, the network's fine relief (shadows' height and normals) over
    photometric stereo's in the product's face crop, with its median and spread. The shipped
    network draws real faces' relief shallower than photometric stereo's, which is why the
    renderer deepens it (intrinsic.SHADOW_DETAIL)."""
    root = shared_data / "yale" / "CroppedYale"
    if not (root / "yaleB01").is_dir():
        pytest.skip(f"needs CroppedYale at {root}, which is absent on this machine")
    got = yn.relief("models/relight-portrait.onnx", "tune", root)
    assert len(got["subjects"]) == 10
    for k in ("height", "normals"):
        v = [r[k] for r in got["subjects"].values()]
        assert all(np.isfinite(x) and x > 0 for x in v)
        assert got[k]["median"] == pytest.approx(float(np.median(v)))
        lo, hi = got[k]["10_90"]
        assert lo <= got[k]["median"] <= hi
    assert got["height"]["median"] < 1.0 and got["normals"]["median"] < 1.0


def test_real_normals_detail_is_marched_as_drawn_and_the_network_s_deepened():
    """The real normals' detail (photometric_buffers without a band, or under the network's low
    band) is neither raised nor marched deeper; with the network's detail (the real low band
    under it) the product keeps deepening it, as it does for the network alone; both step aside
    after."""
    from addon import intrinsic, portrait
    shipped = (portrait.NORMAL_DETAIL, intrinsic.SHADOW_DETAIL)
    assert min(shipped) > 1.0
    n, ok = np.zeros((3, 4)), np.zeros(4, bool)
    for kwargs, inside in (({}, (1.0, 1.0)), ({"low_sigma": 4.0, "low": "network"}, (1.0, 1.0)),
                           ({"low_sigma": 4.0, "low": "photometric"}, shipped)):
        with yn.photometric_buffers(n, ok, **kwargs):
            assert (portrait.NORMAL_DETAIL, intrinsic.SHADOW_DETAIL) == inside
        assert (portrait.NORMAL_DETAIL, intrinsic.SHADOW_DETAIL) == shipped


def test_without_cast_shadows_plans_none_and_then_steps_aside():
    """Inside the context a lamp's plan keeps its component and highlight but no cast shadow;
    after it, the product plans shadows again."""
    from addon import intrinsic, lightvec
    d = lightvec.directions()
    lamp = np.zeros((16, 16, 3), np.float32)
    lamp[np.unravel_index(np.argmax(d @ np.array([0.6, 0.5, 0.6])), d.shape[:2])] = 50.0
    lamp += 0.01
    before = intrinsic.plan(lamp)
    assert before.shadows and before.specular and before.components
    with yn.without_cast_shadows():
        inside = intrinsic.plan(lamp)
        assert not inside.shadows and inside.specular
        assert len(inside.components) == len(before.components)
    after = intrinsic.plan(lamp)
    assert after.shadows and len(after.components) == len(before.components)


def test_the_crop_balance_reads_a_face_lit_from_below_as_positive():
    img = np.ones((40, 30))
    img[20:] = 3.0  # the lower half three times as bright
    mask = np.zeros_like(img, bool)
    mask[5:35, 5:25] = True  # its middle row is the image's
    assert yn.crop_balance(img, mask) == pytest.approx(0.5)
    assert yn.crop_balance(img[::-1], mask[::-1]) == pytest.approx(-0.5)
    assert yn.crop_balance(img, mask & False) == 0.0


def test_response_stats_read_a_half_strength_answer_per_band():
    """A relit balance that follows the truth's at half its strength reads slope 0.5 and
    correlation 1 in every band; one that ignores the truth in one band reads slope 0 there."""
    rng = np.random.default_rng(0)
    truth = rng.normal(0.0, 0.2, 90)
    elevation = np.repeat([40.0, 0.0, -40.0], 30)  # above, level, below
    r = yn.response_stats(0.5 * truth + 0.01, truth, elevation)
    assert set(r) == {"all", "above", "level", "below"}
    for band in r.values():
        assert band["slope"] == pytest.approx(0.5) and band["corr"] == pytest.approx(1.0)
    assert r["above"]["lights"] == r["level"]["lights"] == r["below"]["lights"] == 30
    assert r["all"]["bias"] == pytest.approx(0.01 - 0.5 * truth.mean())
    deaf_above = np.where(elevation > 0, 0.1, truth)
    r = yn.response_stats(deaf_above, truth, elevation)
    assert r["above"]["slope"] == 0.0 and r["level"]["slope"] == pytest.approx(1.0)
    assert r["above"]["corr"] == 0.0  # nothing to correlate with a constant


def test_response_of_a_real_subject_to_the_target_and_the_input(shared_data):
    """On one real subject: every band is measured for both normals and both sides, both answer
    the target's light, and the real normals keep less of the input's. (The network's normals,
    their finer sampling fed brighter, answer the target more strongly than the real ones
    through the renderer: slope 0.93 against 0.74 on this subject.)"""
    root = shared_data / "yale" / "CroppedYale"
    if not (root / "yaleB01").is_dir():
        pytest.skip(f"needs CroppedYale at {root}, which is absent on this machine")
    got = yn.response("models/relight-portrait.onnx", root=root, names=["yaleB01"])
    assert set(got) == {"target", "input", "subjects"}
    for side in (got["target"], got["input"]):
        assert set(side) == {"network", "photometric"}
        for r in side.values():
            assert r["all"]["lights"] > 40
            assert sum(r[b]["lights"] for b in ("above", "level", "below")) == r["all"]["lights"]
            assert all(np.isfinite(v) for band in r.values() for v in band.values())
    target, kept = got["target"], got["input"]
    for which in ("network", "photometric"):  # the relit face follows the light at all
        assert target[which]["all"]["slope"] > 0.2 and target[which]["all"]["corr"] > 0.5
    assert kept["photometric"]["all"]["slope"] < kept["network"]["all"]["slope"] + 0.05
    # one subject: its own figures are the pooled ones
    for side in ("target", "input"):
        for which in ("network", "photometric"):
            own, pooled = got["subjects"][side][which]["yaleB01"], got[side][which]["all"]
            assert own == pytest.approx(pooled, rel=1e-9, abs=1e-12)


def test_subject_spread_names_the_subjects_at_the_extremes():
    per = {"a": {"slope": 0.6}, "b": {"slope": 0.1}, "c": {"slope": 0.9}, "d": {"slope": 0.5}}
    sp = yn.subject_spread(per)
    assert sp["median"] == pytest.approx(0.55)
    assert sp["lowest"] == ("b", 0.1) and sp["highest"] == ("c", 0.9)
    assert yn.subject_spread({}) == {}


def test_shading_left_reads_the_share_of_the_light_an_albedo_keeps():
    """An albedo that is the real one reads 0, one that is the photo itself (all the light
    baked in) 1, one with the shading's square root 0.5, whatever its gain; an evenly lit photo
    says nothing (None)."""
    rng = np.random.default_rng(1)
    real = rng.uniform(0.3, 0.7, (S, S))
    shading = np.exp(rng.normal(0.0, 0.6, (S, S)))
    photo = real * shading
    mask = np.ones((S, S), bool)
    assert abs(yn.shading_left(photo, real, 2.0 * real, mask)) < 1e-9
    assert yn.shading_left(photo, real, photo, mask) == pytest.approx(1.0)
    assert yn.shading_left(photo, real, 0.3 * real * np.sqrt(shading), mask) == pytest.approx(0.5)
    assert yn.shading_left(real * 0.8, real, real, mask) is None


def test_the_shipped_albedo_keeps_little_of_a_real_photo_s_light(shared_data):
    """On one real subject, over its single-light photos: the shipped Portrait's albedo is far
    closer to photometric stereo's than the photo is (which keeps all of its light: 1)."""
    root = shared_data / "yale" / "CroppedYale"
    if not (root / "yaleB01").is_dir():
        pytest.skip(f"needs CroppedYale at {root}, which is absent on this machine")
    got = yn.albedo_light("models/relight-portrait.onnx", root=root, names=["yaleB01"])
    assert got["photos"] > 30 and set(got["subjects"]) == {"yaleB01"}
    assert got["subjects"]["yaleB01"]["photos"] == got["photos"]
    assert -0.1 < got["slope"] < 0.25


def test_buffers_from_takes_the_named_buffers_and_optionally_the_framing_then_steps_aside():
    """buffers_from: inside, the product's buffers carry the named fields from the other model
    and keep their own for the rest; the portrait's box is the product's own unless asked for
    the other model's framing; after it, the product's functions are back. (Two learned models,
    the shipped Portrait and the research cut one, on the demo clip's first frame cut close.)"""
    import pathlib

    from addon import api, portrait
    from training.lightstage.png import read_png

    root = pathlib.Path(__file__).resolve().parents[2]
    src = read_png(root / "demo" / "frames" / "frame_0001.png").astype(np.float32) / 255.0
    # cut close around the face on every side, as CroppedYale's photos are
    x = np.ascontiguousarray(src[40:200, 30:230].transpose(2, 0, 1) ** 2.2)
    own = api.session(str(root / "models" / "relight-portrait.onnx"), 1)
    other = api.session(str(root / "models" / "research" / "portrait-cut.onnx"), 1)
    box, other_box = portrait.find_box(own, x), portrait.find_box(other, x)
    assert box != other_box  # the two models frame the portrait differently
    crop, valid = portrait.crop_planar(x, box, own.card.working_size)
    mine, theirs = portrait.buffers(own, crop, valid), portrait.buffers(other, crop, valid)
    assert np.abs(mine.normal - theirs.normal).max() > 0.05
    with yn.buffers_from(other, ("normal", "matte")):
        got = portrait.buffers(own, crop, valid)
        assert portrait.find_box(own, x) == box
    np.testing.assert_array_equal(got.normal, theirs.normal)
    np.testing.assert_array_equal(got.matte, theirs.matte)
    for kept in ("height", "albedo", "face", "transfer"):
        np.testing.assert_array_equal(getattr(got, kept), getattr(mine, kept))
    with yn.buffers_from(other, (), framing=True):
        assert portrait.find_box(own, x) == other_box
        np.testing.assert_array_equal(portrait.buffers(own, crop, valid).normal, mine.normal)
    assert portrait.buffers.__module__ == portrait.find_box.__module__ == "addon.portrait"
    assert portrait.find_box(own, x) == box


def test_relight_with_everything_of_another_model_is_that_model(shared_data):
    """--swap: a variant per SWAPS entry, each with its figures; taking every buffer and the
    framing from the other model relights exactly as that model does."""
    root = shared_data / "yale" / "CroppedYale"
    if not (root / "yaleB01").is_dir():
        pytest.skip(f"needs CroppedYale at {root}, which is absent on this machine")
    other = "models/research/portrait-cut.onnx"
    got = yn.relight("models/relight-portrait.onnx", "tune", root, n_pairs=2, other=other)
    assert set(got) == {"network", "photometric"} | {f"{w} of portrait-cut" for w in yn.SWAPS}
    for r in got.values():
        assert all(np.isfinite(r[k]) for k in ("all", "left_right", "top_bottom"))
    theirs = yn.relight(other, "tune", root, n_pairs=2)["network"]
    mixed = got["everything of portrait-cut"]
    for k in ("all", "left_right", "top_bottom"):
        assert mixed[k] == pytest.approx(theirs[k], abs=1e-6)
    assert got["network"]["all"] != pytest.approx(theirs["all"], abs=1e-3)


@pytest.mark.parametrize("flag", [["--template-share", "0.5"], ["--face-modes", "3"]])
@pytest.mark.parametrize("extra", [[], ["--relight"], ["--low-sigma", "6"]])
def test_blending_low_bands_without_a_band_is_refused(flag, extra, capsys):
    """--template-share and --face-modes work on the relit pairs' low bands: without --relight
    and --low-sigma there are none, so the command says so (exit 2) before any work; relight
    itself refuses them without a low_sigma."""
    with pytest.raises(SystemExit) as e:
        yn.main(["--onnx", "models/relight-portrait.onnx", *flag, *extra])
    assert e.value.code == 2
    assert f"{flag[0]} needs --relight and --low-sigma" in capsys.readouterr().err
    with pytest.raises(ValueError, match="low_sigma"):
        yn.relight("models/relight-portrait.onnx", face_modes=(3,))


def test_negative_face_modes_are_refused(capsys):
    with pytest.raises(SystemExit) as e:
        yn.main(["--onnx", "models/relight-portrait.onnx", "--relight", "--low-sigma", "6",
                 "--face-modes", "-1"])
    assert e.value.code == 2
    assert "--face-modes must be 0 or more" in capsys.readouterr().err
