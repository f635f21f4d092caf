"""addon.outline: the change of light stops at the subject's outline at full resolution."""

from __future__ import annotations

import numpy as np
import pytest

from addon import detail, intrinsic, outline, portrait

GREEN = np.array([0.08, 0.45, 0.12], np.float32)  # a chroma-key screen, linear
SKIN = np.array([0.55, 0.33, 0.25], np.float32)


def scene(h: int, w: int, radius: float, seed: int = 0):
    """(3, h, w) footage: a textured skin-coloured disc on a noisy green screen, and the disc's
    exact coverage (4x4 supersampled)."""
    rng = np.random.default_rng(seed)
    ss = 4
    yy, xx = np.mgrid[0:h * ss, 0:w * ss] / ss + 0.5 / ss
    inside = np.hypot(xx - w / 2, yy - h / 2) < radius
    cover = inside.reshape(h, ss, w, ss).mean((1, 3)).astype(np.float32)
    skin = SKIN[:, None, None] * (1 + 0.08 * rng.standard_normal((1, h, w))).astype(np.float32)
    green = GREEN[:, None, None] * (1 + 0.03 * rng.standard_normal((1, h, w))).astype(np.float32)
    return (cover * skin + (1 - cover) * green).astype(np.float32), cover


def grid_of(x: np.ndarray, k: int) -> np.ndarray:
    c, h, w = x.shape
    return x.reshape(c, h // k, k, w // k, k).mean((2, 4))


def soft_weight(cover_grid: np.ndarray, sigma: float) -> np.ndarray:
    """The change's weight as Portrait builds it on its grid (portrait.MATTE_EDGE): the matte
    blurred by ``sigma`` samples, then faded in over its core; enlarged, its fade reaches a
    sample or two past the outline."""
    m = intrinsic.gaussian_blur(cover_grid, sigma)
    m = np.clip((m - portrait.MATTE_EDGE[0]) / (portrait.MATTE_EDGE[1] - portrait.MATTE_EDGE[0]),
                0.0, 1.0)
    return (m * m * (3.0 - 2.0 * m)).astype(np.float32)


def finish(x: np.ndarray, weight: np.ndarray, gain: float) -> np.ndarray:
    """The frame with the change ``gain`` faded in by ``weight`` (a = 1 + weight (gain - 1)),
    through the product's finish (half float)."""
    a = np.repeat((1.0 + weight * (gain - 1.0))[None], 3, 0).astype(np.float32)
    b = np.zeros_like(a)
    return detail.FullRes(threads=1).finish_planar(x, a, b, float(x.max()))[0]


def test_no_fade_no_fit():
    x, _ = scene(40, 40, 12.0)
    g = grid_of(x, 4)
    assert outline.fit(g, np.zeros(g.shape[1:], np.float32)) is None
    assert outline.fit(g, np.ones(g.shape[1:], np.float32)) is None
    y = x.astype(np.float16)
    assert outline.apply(None, x, y) is y


def test_the_screen_beside_the_subject_keeps_the_footage():
    """A change that doubles the subject, faded in over several grid samples past its outline:
    enlarged, it brightens the green screen beside the disc; refitted to colour, the screen keeps
    the footage while the disc keeps its change."""
    h, w, k = 160, 200, 5
    x, cover = scene(h, w, 45.0)
    g = grid_of(x, k)
    weight = soft_weight(grid_of(cover[None], k)[0], 1.2)
    y = finish(x, weight, 2.0)
    fit = outline.fit(g, weight)
    fixed = outline.apply(fit, x, y.copy()).astype(np.float32)
    before = y.astype(np.float32)
    screen = cover == 0.0
    reached = screen & (np.abs(before / np.maximum(x, 1e-6) - 1.0).max(0) > 0.05)
    assert reached.sum() > 500  # the enlarged fade does spill onto the screen
    change_before = np.abs(before - x)[:, reached].mean()
    change_after = np.abs(fixed - x)[:, reached].mean()
    assert change_after < 0.1 * change_before, (change_before, change_after)
    core = cover == 1.0
    faded = core & (np.abs(before - x).max(0) > 1e-3)
    kept = np.abs(fixed - x)[:, faded].sum() / np.abs(before - x)[:, faded].sum()
    assert kept > 0.9, kept  # the subject's own pixels keep (nearly all) their change


@pytest.mark.parametrize("shape,grid,scale,with_matte", [((101, 137), (23, 31), 1.0, False),
                                                          ((120, 160), (24, 32), 2.5, False),
                                                          ((101, 137), (23, 31), 1.0, True)])
def test_sparse_correction_equals_the_dense_one(shape, grid, scale, with_matte):
    """apply touches only the fade's pixels; the result equals the same correction computed on
    every pixel from the fit enlarged with detail.enlarge_planar (bilinear taps as the finish's),
    including on grids that do not divide the frame, for footage ``scale`` times x_full (the
    pipeline's normalisation: the unchanged frame is scale * x_full), and with the subject's
    matte fitted too."""
    h, w = shape
    x, cover = scene(h, w, 0.3 * min(h, w), seed=3)
    g = detail.resize(x.transpose(1, 2, 0), *grid).transpose(2, 0, 1).astype(np.float32)
    cg = detail.resize(cover[..., None], *grid)[..., 0]
    weight = soft_weight(cg, 1.0)
    y = (finish(x, weight, 0.4).astype(np.float32) * scale).astype(np.float16)
    fit = outline.fit(g, weight, subject=cg if with_matte else None)
    sparse = outline.apply(fit, x, y.copy(), scale=scale).astype(np.float32)
    extra = [fit.coef[4:], fit.subject[None]] if with_matte else []
    up = detail.enlarge_planar(np.concatenate([fit.coef[:4], fit.weight[None]] + extra, 0), h, w)
    refit = np.clip((up[:3] * x).sum(0) / fit.level + up[3], 0.0, 1.0)
    given = refit
    if with_matte:
        lo, hi = outline.SURE
        sure = np.clip(((up[5:8] * x).sum(0) / fit.level + up[8] - lo) / (hi - lo), 0.0, 1.0)
        cap = np.minimum(up[9] / outline.MATTE_WHOLE, 1.0)
        given = np.maximum(refit, np.minimum(sure * sure * (3.0 - 2.0 * sure), cap))
    share = np.where(up[4] >= outline.UP_FLOOR, given, refit) / np.maximum(up[4], outline.FLOOR)
    share = np.where(up[4] >= outline.UP_FLOOR, share, np.minimum(share, 1.0))
    if with_matte:  # skin against a screen: the two-colour model splits the change
        assert fit.colours is not None
        col = detail.enlarge_planar(fit.colours, h, w)
        share = outline.split(up[4].reshape(-1), up[9].reshape(-1), col.reshape(7, -1),
                              x.reshape(3, -1), share.reshape(-1)).reshape(3, h, w)
    share = np.where((up[4] > outline.FLOOR) & (up[4] < 1.0), share, 1.0)
    yf = y.astype(np.float32)
    dense = (scale * x + share * (yf - scale * x)).astype(np.float16).astype(np.float32)
    np.testing.assert_allclose(sparse, dense, rtol=2e-3, atol=1e-5)
    # the comparison covers pixels the refit takes change from and pixels it gives change to
    assert (share < 0.99).sum() > 50 and (share > 1.01).sum() > 50


def test_fit_is_the_guided_filter_where_its_windows_are_whole():
    """On fade samples away from the grid's border the fit equals He et al.'s colour guided
    filter written densely with box means."""
    x, cover = scene(120, 160, 40.0, seed=5)
    g = grid_of(x, 4)
    weight = soft_weight(grid_of(cover[None], 4)[0], 1.0)
    fit = outline.fit(g, weight)
    r, eps = outline.RADIUS, outline.EPS
    guide = g / fit.level
    bm = lambda a: detail.box_mean(a, r)  # noqa: E731
    mi = np.stack([bm(c) for c in guide])
    mp = bm(weight)
    cov = np.stack([bm(c * weight) for c in guide]) - mi * mp
    sig = np.empty(weight.shape + (3, 3), np.float32)
    for i in range(3):
        for j in range(3):
            sig[..., i, j] = bm(guide[i] * guide[j]) - mi[i] * mi[j]
    sig += eps * np.eye(3, dtype=np.float32)
    alpha = np.linalg.solve(sig, cov.transpose(1, 2, 0)[..., None])[..., 0].transpose(2, 0, 1)
    beta = mp - (alpha * mi).sum(0)
    dense = np.concatenate([np.stack([bm(c) for c in alpha]), bm(beta)[None]], 0)
    fade = (weight > 0) & (weight < 1)
    inner = np.zeros_like(fade)
    inner[2 * r:-2 * r, 2 * r:-2 * r] = True
    pick = fade & inner
    assert pick.sum() > 50
    np.testing.assert_allclose(fit.coef[:, pick], dense[:, pick], atol=2e-3)
    # Outside the fade the weight stands as it is.
    assert np.all(fit.coef[:3, ~fade] == 0) and np.all(fit.coef[3, ~fade] == weight[~fade])


def test_a_pixel_stays_between_the_footage_and_the_subject_s_full_change():
    """The refit moves a fade pixel's share of the change, never past the footage on one side
    nor past the subject's own full change (the change at weight 1) on the other; where the
    enlarged weight is below UP_FLOOR it never adds change."""
    x, cover = scene(90, 120, 28.0, seed=7)
    g = grid_of(x, 3)
    weight = soft_weight(grid_of(cover[None], 3)[0], 1.5)
    up = detail.enlarge_planar(weight[None], *x.shape[1:])[0]
    for gain in (0.2, 3.0):
        y = finish(x, weight, gain)
        fixed = outline.apply(outline.fit(g, weight), x, y.copy()).astype(np.float32)
        full = gain * x
        lo = np.minimum(x, full) - 1e-3
        hi = np.maximum(x, full) + 1e-3
        assert np.all((fixed >= lo) & (fixed <= hi))
        faint = up < outline.UP_FLOOR
        yf = y.astype(np.float32)
        assert np.all(np.abs(fixed - x)[:, faint] <= np.abs(yf - x)[:, faint] + 1e-3)


def ear_scene(h: int = 160, w: int = 200, k: int = 5):
    """The disc with a skin-coloured strip six pixels wide beside it (an ear against a screen):
    (footage, cover, the ear's pixels, the footage on the grid, the matte on the grid, the
    weight: the matte's core)."""
    x, cover = scene(h, w, 45.0, seed=2)
    ear = np.zeros((h, w), bool)
    ear[60:100, 145:151] = True  # the disc reaches x = 145 at its equator
    rng = np.random.default_rng(4)
    skin = SKIN[:, None] * (1 + 0.08 * rng.standard_normal((1, int(ear.sum())))).astype(np.float32)
    x[:, ear] = skin
    cover = np.maximum(cover, ear.astype(np.float32))
    matte = grid_of(cover[None], k)[0]
    return x, cover, ear, grid_of(x, k), matte, soft_weight(matte, 1.2)


def test_an_ear_in_the_fade_takes_more_of_the_subject_s_change():
    """A skin-coloured strip six pixels wide beside the disc (an ear against a screen): the
    matte holds it, but the weight's fade (the matte's core, soft_weight) reaches only part of
    it, so enlarged it kept much of the footage's light beside a subject the new light leaves
    dark. Refitted to colour it takes more of the subject's change, while the screen beside it
    keeps the footage."""
    x, cover, ear, g, _, weight = ear_scene()
    gain = 0.2  # a key lamp from the other side leaves the subject dark
    y = finish(x, weight, gain).astype(np.float32)
    fixed = outline.apply(outline.fit(g, weight), x, y.astype(np.float16)).astype(np.float32)

    def change(img, where):  # share of the full change, 1 - img / x, over ``where``
        return float((1.0 - img[:, where] / x[:, where]).mean() / (1.0 - gain))

    before, after = change(y, ear), change(fixed, ear)
    assert before < 0.45, before  # enlarged, the fade left the ear more than half lit
    assert after > before + 0.1, (before, after)
    screen = (cover == 0.0) & ~outline._dilate(ear, 2)
    assert change(fixed, screen) <= change(y, screen) + 1e-4
    assert change(fixed, screen) < 2e-3


def test_skin_at_the_outline_takes_the_change_its_matte_says():
    """With the subject's own matte fitted too, a fade pixel whose colour surely says subject
    takes the subject's full change where the weight's core under-reads it (the ear of the test
    above, and the disc's own rim, which enlarged kept part of the footage's light), also where
    the network's matte itself fades (the disc's outermost pixels: held to that matte, they kept
    a fifth of the footage's light, a lit line along the outline), while the screen still keeps
    the footage."""
    x, cover, ear, g, matte, weight = ear_scene()
    h, w = x.shape[1:]
    gain = 0.2
    y = finish(x, weight, gain)

    def change(img, where):
        img = img.astype(np.float32)
        return float((1.0 - img[:, where] / x[:, where]).mean() / (1.0 - gain))

    core = outline.apply(outline.fit(g, weight), x, y.copy())
    both = outline.apply(outline.fit(g, weight, subject=matte), x, y.copy())
    assert change(both, ear) > max(change(core, ear) + 0.2, 0.8), (
        change(core, ear), change(both, ear))
    rim = (cover == 1.0) & ~ear & (np.abs(y.astype(np.float32) / x - gain).max(0) > 0.01)
    assert rim.sum() > 500
    assert change(both, rim) > 0.98 > 0.9 > change(core, rim), (change(core, rim),
                                                                 change(both, rim))
    edge = (cover == 1.0) & ~ear & (detail.enlarge_planar(matte[None], h, w)[0] < 0.9)
    assert edge.sum() > 300
    assert change(both, edge) > 0.95, change(both, edge)
    screen = (cover == 0.0) & ~outline._dilate(ear, 2)
    assert change(both, screen) < 2e-3


def test_a_pixel_half_skin_half_screen_takes_the_change_on_its_skin_only():
    """Where the subject's colour and the screen's are far apart, a pixel of the outline that is
    part skin, part screen comes out as the relit skin over the same screen, as the light stage
    composites its renders: the change on the whole pixel kept part of the skin's footage light
    there under a lamp that leaves the subject dark (a lit, pixel-stepped rim along a jaw against
    a green screen), and a brighter light greened the skin there too."""
    h, w, k = 160, 200, 5
    x, cover = scene(h, w, 45.0, seed=5)
    skin = (x - (1.0 - cover) * GREEN[:, None, None]) / np.maximum(cover, 1e-6)
    matte = grid_of(cover[None], k)[0]
    weight = soft_weight(matte, 1.2)
    g = grid_of(x, k)
    mixed = (cover > 0.2) & (cover < 0.8)
    screen = (cover == 0.0) & (detail.enlarge_planar(weight[None], h, w)[0] > outline.FLOOR)
    assert mixed.sum() > 100 and screen.sum() > 200
    for gain in (0.2, 2.0):
        y = finish(x, weight, gain)
        truth = cover * gain * skin + (1.0 - cover) * GREEN[:, None, None]
        fit = outline.fit(g, weight, subject=matte)
        assert fit.colours is not None
        split = outline.apply(fit, x, y.copy()).astype(np.float32)
        with pytest.MonkeyPatch.context() as mp:  # the two colours never distinct enough
            mp.setattr(outline, "DISTINCT", (2.0, 2.5))  # no two colours are 2 apart
            whole_fit = outline.fit(g, weight, subject=matte)
            assert whole_fit.colours is None
            whole = outline.apply(whole_fit, x, y.copy()).astype(np.float32)

        def err(img):
            return float(np.abs(img - truth)[:, mixed].mean() / np.abs(truth[:, mixed]).mean())

        assert err(split) < 0.5 * err(whole), (gain, err(split), err(whole))
        assert float(np.abs(split - x)[:, screen].max()) < 0.01 * float(GREEN.max())


def test_a_thin_part_unlike_the_core_beside_it_takes_its_change():
    """An ear's skin against a screen beside dark hair, where the network's matte over the ear
    is soft (not the core): the subject colour beside the ear is the hair's, so the ear's skin
    projects short on the line from the screen to the hair, yet it lies as far from the screen
    as the hair does. Read by that distance too, the ear takes most of the subject's change
    under a lamp that leaves it dark (the projection alone left it lit like the footage: 0.37
    of the change), while the screen beside it keeps the footage."""
    hair = np.array([0.05, 0.035, 0.03], np.float32)
    h, w, k = 160, 200, 5
    _, cover = scene(h, w, 45.0, seed=2)
    rng = np.random.default_rng(8)

    def noise(a):
        return (1 + a * rng.standard_normal((1, h, w))).astype(np.float32)

    x = (cover * hair[:, None, None] * noise(0.08)
         + (1 - cover) * GREEN[:, None, None] * noise(0.03)).astype(np.float32)
    ear = np.zeros((h, w), bool)
    ear[60:100, 145:151] = True
    x[:, ear] = SKIN[:, None] * (1 + 0.08 * rng.standard_normal((1, int(ear.sum()))))
    cover = np.maximum(cover, ear.astype(np.float32))
    matte = grid_of(cover[None], k)[0]
    matte[12:20, 29] *= 0.8  # the ear's own samples: soft in the network's matte
    weight = soft_weight(matte, 1.2)
    gain = 0.2
    y = finish(x, weight, gain)
    fixed = outline.apply(outline.fit(grid_of(x, k), weight, subject=matte), x, y.copy())

    def change(img, where):
        img = img.astype(np.float32)
        return float((1.0 - img[:, where] / x[:, where]).mean() / (1.0 - gain))

    assert change(y, ear) < 0.35
    assert change(fixed, ear) > 0.6, change(fixed, ear)
    screen = (cover == 0.0) & ~outline._dilate(ear, 2) & (
        detail.enlarge_planar(weight[None], h, w)[0] > outline.FLOOR)
    assert screen.sum() > 200
    assert float(np.abs(fixed.astype(np.float32) - x)[:, screen].max()) < 0.02 * float(GREEN.max())


def test_a_wall_of_the_subject_s_colour_is_given_no_change():
    """Where the background's colour is nearly the subject's (auburn hair against a pink wall)
    the matte's refit is unsure (well below SURE's upper end) and gives back nothing: the wall
    beside the subject takes no more change than the weight's refit alone leaves it; given back
    as the refit reads it (SURE (0, 1)), it would take more."""
    h, w, k = 160, 200, 5
    x, cover = scene(h, w, 45.0, seed=6)
    rng = np.random.default_rng(6)
    wall = np.array([0.50, 0.33, 0.28], np.float32)[:, None, None] * (
        1 + 0.08 * rng.standard_normal((1, h, w))).astype(np.float32)
    x = (cover * x + (1 - cover) * wall).astype(np.float32)
    g = grid_of(x, k)
    matte = grid_of(cover[None], k)[0]
    weight = soft_weight(matte, 1.2)
    near = (cover == 0.0) & (detail.enlarge_planar(weight[None], h, w)[0] >= outline.UP_FLOOR)
    assert near.sum() > 200
    for gain in (0.2, 3.0):
        y = finish(x, weight, gain)

        def change(f):
            img = outline.apply(f, x, y.copy()).astype(np.float32)
            return float(np.abs(img[:, near] - x[:, near]).mean())

        core, both = change(outline.fit(g, weight)), change(outline.fit(g, weight, subject=matte))
        assert both <= core + 1e-6, (gain, core, both)
        linear = pytest.MonkeyPatch.context()
        with linear as mp:
            mp.setattr(outline, "SURE", (0.0, 1.0))
            assert change(outline.fit(g, weight, subject=matte)) > core + 1e-6


def test_half_mixing_graph_matches_numpy():
    rng = np.random.default_rng(1)
    y = rng.uniform(0, 8, (3, 1000)).astype(np.float16)
    x = rng.uniform(0, 4, (3, 1000)).astype(np.float32)
    share = rng.uniform(0, 1, 1000).astype(np.float32)
    out = detail.FullRes(threads=1).mix_half(y, x, share, 1.5)
    want = 1.5 * x + share * (y.astype(np.float32) - 1.5 * x)
    assert out.dtype == np.float16 and out.shape == (3, 1000)
    np.testing.assert_allclose(out.astype(np.float32), want, rtol=1e-3, atol=1e-3)
    assert detail.FullRes(threads=1).mix_half(y[:, :0], x[:, :0], share[:0], 1.0).shape == (3, 0)
    each = rng.uniform(0, 1, (3, 1000)).astype(np.float32)  # a share for each channel
    out = detail.FullRes(threads=1).mix_half(y, x, each, 1.5)
    want = 1.5 * x + each * (y.astype(np.float32) - 1.5 * x)
    np.testing.assert_allclose(out.astype(np.float32), want, rtol=1e-3, atol=1e-3)


def test_the_matte_strip_follows_the_footage_s_edges():
    """The network's matte on the grid, enlarged, blurs the outline over several pixels;
    refitted to colour at full resolution it is far closer to the subject's true coverage
    there, and untouched away from the outline; read as a mix of the skin's colour and the
    screen's it comes closer still."""
    h, w, k = 160, 200, 5
    x, cover = scene(h, w, 45.0, seed=11)
    g = grid_of(x, k)
    raw = np.clip(intrinsic.gaussian_blur(grid_of(cover[None], k)[0], 0.7), 0.0, 1.0)
    enlarged = detail.enlarge_planar(raw[None].astype(np.float32), h, w)[0].astype(np.float16)
    fit = outline.fit(g, raw, tol=outline.MATTE_TOL)
    refined = outline.refine_matte(fit, x, enlarged.copy()).astype(np.float32)
    band = np.abs(enlarged.astype(np.float32) - cover) > 0.05
    assert band.sum() > 500
    before = np.abs(enlarged.astype(np.float32) - cover)[band].mean()
    after = np.abs(refined - cover)[band].mean()
    assert after < 0.5 * before, (before, after)
    still = (enlarged == 0) | (enlarged == 1)
    assert np.array_equal(refined[still], enlarged.astype(np.float32)[still])
    # Skin against a screen: read as a mix of the two colours, the strip comes closer still.
    fit = outline.fit(g, raw, tol=outline.MATTE_TOL, colours=True)
    assert fit.colours is not None
    mixed = outline.refine_matte(fit, x, enlarged.copy()).astype(np.float32)
    two = np.abs(mixed - cover)[band].mean()
    assert two < 0.7 * after, (after, two)
    assert np.array_equal(mixed[still], enlarged.astype(np.float32)[still])
