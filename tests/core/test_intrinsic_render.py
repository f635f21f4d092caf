"""The intrinsic renderer (addon/intrinsic.py) on synthetic buffers: a sphere's normals and height
on a disc matte, and flat height fields with a bump. numpy only, no model.

(Named test_intrinsic_render.py, not test_intrinsic.py: tests/training/test_intrinsic.py exists,
and two test modules of one basename break collecting the whole suite in one pytest run.)
"""

import dataclasses
import math

import numpy as np
import pytest

from addon import intrinsic, lightvec

S, R = 64, 28.0  # crop side and sphere radius, working-size pixels
SKIN = np.array([0.8, 0.55, 0.45], np.float32)


def sphere(size=S, radius=R):
    """(normal (3, s, s), height (s, s), matte (s, s), u, v): a sphere facing the camera, centred;
    u, v are the image offsets from its centre over the radius (v grows downward)."""
    c = size / 2.0
    yy, xx = np.mgrid[0:size, 0:size] + 0.5
    u, v = (xx - c) / radius, (yy - c) / radius
    inside = u * u + v * v < 1.0
    nz = np.sqrt(np.clip(1.0 - u * u - v * v, 0.0, 1.0))
    normal = np.stack([np.where(inside, u, 0.0), np.where(inside, -v, 0.0),
                       np.where(inside, nz, 1.0)]).astype(np.float32)
    return normal, (radius * nz).astype(np.float32), inside.astype(np.float32), u, v


def exact_irradiance(light, normal):
    """(3, h, w) float64 reference irradiance (addon.lightvec)."""
    return np.moveaxis(lightvec.irradiance(light, np.moveaxis(normal.astype(np.float64), 0, -1)),
                       -1, 0)


def smooth_sky():
    """An HDRI-like smooth light: a broad warm glow up and to the right over a dim ambient."""
    d = lightvec.directions()
    a = np.array([0.4, 0.5, 0.76]) / np.linalg.norm([0.4, 0.5, 0.76])
    return ((0.3 + np.exp(2.0 * (d @ a - 1.0)))[..., None] * [1.0, 0.9, 0.8]).astype(np.float32)


def overcast():
    """The CIE overcast sky, (1 + 2 cos theta) / 3 above the horizon, over grey ground."""
    up = lightvec.directions()[..., 1]
    return (np.where(up > 0, (1 + 2 * up) / 3, 0.2)[..., None] * [1.0, 1.0, 1.05]).astype(np.float32)


def lamp(direction, power=10.0, fill=0.05):
    """A lamp splatted from ``direction`` plus a weak uniform fill."""
    return lightvec.splat_direction(direction, power) + lightvec.uniform(fill)


def unit(v):
    v = np.asarray(v, np.float64)
    return v / np.linalg.norm(v)


def portrait(albedo=SKIN, light=None):
    """(image (3, S, S), Buffers) of a sphere of skin lit by ``light``, by default softly from
    the front and above."""
    normal, height, matte, _, _ = sphere()
    alb = np.broadcast_to(np.asarray(albedo, np.float32)[:, None, None], (3, S, S)).copy()
    src = (lightvec.uniform(0.3) + lightvec.splat_direction([0.0, 0.3, 1.0], 3.0)
           if light is None else light)
    image = (alb * exact_irradiance(src, normal) * matte / math.pi).astype(np.float32)
    return image, intrinsic.Buffers(normal, height, alb, matte, matte.copy())


# ---- plan ----------------------------------------------------------------------------------

@pytest.mark.parametrize("name", ["uniform", "overcast", "smooth_sky"])
def test_soft_light_has_no_components(name):
    """Uniform, overcast and smooth HDRI-like light call for no shadows and no highlights."""
    light = {"uniform": lightvec.uniform(1.0), "overcast": overcast(), "smooth_sky": smooth_sky()}[name]
    p = intrinsic.plan(light)
    assert p.components == ()
    assert not p.shadows and not p.specular


@pytest.mark.parametrize("direction", [(0.6, 0.3, 0.74), (1.0, 0.0, 0.3), (-0.3, 0.9, 0.2),
                                       (0.1, -0.2, 1.0)])
def test_a_lamp_over_a_weak_fill_is_one_component_toward_the_lamp(direction):
    """A splatted lamp plus a weak uniform fill: exactly one component, pointing at the lamp."""
    p = intrinsic.plan(lamp(direction))
    assert len(p.components) == 1 and p.shadows and p.specular
    comp = p.components[0]
    angle = math.degrees(math.acos(min(1.0, float(comp.direction @ unit(direction)))))
    assert angle < 3.0
    assert np.linalg.norm(comp.direction) == pytest.approx(1.0, abs=1e-5)
    # It carries the lamp's irradiance (10), not the fill's.
    assert comp.irradiance == pytest.approx([10.0] * 3, rel=0.05)


def test_zero_light_has_no_components():
    """A zero light plans nothing (and does not divide by its zero power)."""
    p = intrinsic.plan(lightvec.zeros())
    assert p.components == () and not p.shadows and not p.specular


def test_effects_off_plan_nothing():
    """shadows=False and specular=False skip the search even for a lamp."""
    assert intrinsic.plan(lamp((1, 0, 0.3)), shadows=False, specular=False).components == ()


# ---- irradiance ------------------------------------------------------------------------------

def random_normals(seed=0, shape=(20, 30)):
    n = np.random.default_rng(seed).normal(size=(3, *shape))
    return (n / np.linalg.norm(n, axis=0)).astype(np.float32)


def test_irradiance_with_every_cell_exact_matches_lightvec():
    """All 256 cells summed exactly: lightvec.irradiance (float64) within 1e-4 relative."""
    light = np.random.default_rng(1).random(lightvec.SHAPE).astype(np.float32)
    n = random_normals()
    got = intrinsic.irradiance(light, n, exact_cells=lightvec.ROWS * lightvec.COLS, exact_share=-1.0)
    np.testing.assert_allclose(got, exact_irradiance(light, n), rtol=1e-4)


def test_irradiance_is_exact_for_lamps_by_default():
    """Lamps cover few cells, all summed exactly by default: within 1e-4 of the reference."""
    light = (lightvec.splat_direction([0.6, 0.3, 0.74], 10.0)
             + lightvec.splat_direction([-0.5, 0.2, 0.8], [3.0, 2.0, 1.0]))
    n = random_normals(2)
    ref = exact_irradiance(light, n)
    np.testing.assert_allclose(intrinsic.irradiance(light, n), ref, rtol=1e-4,
                               atol=1e-4 * float(ref.max()))


def test_irradiance_of_smooth_light_through_sh_is_close():
    """The default (brightest cells exact, the rest through order-2 SH) stays within a few %
    on a smooth sky, on every normal (back-facing ones included)."""
    light, n = smooth_sky(), random_normals(3)
    ref = exact_irradiance(light, n)
    rel = intrinsic.irradiance(light, n) / ref - 1.0
    assert np.abs(rel).max() < 0.05
    assert np.sqrt(np.mean(rel ** 2)) < 0.015


# ---- source fit ------------------------------------------------------------------------------

@pytest.mark.parametrize("patch", [False, True])
def test_fit_source_reproduces_smooth_shading(patch):
    """The fitted SH shading reproduces a sphere's exact irradiance under a smooth light (relative
    RMSE < 2%); a dark albedo patch (lips, brows) is divided out, not read as shadow."""
    normal, height, matte, u, v = sphere()
    alb = np.full((3, S, S), 0.5, np.float32)
    if patch:
        alb[:, (np.abs(u) < 0.3) & (np.abs(v - 0.4) < 0.15)] = 0.2
    e = intrinsic.luminance(exact_irradiance(smooth_sky(), normal).astype(np.float32))
    lum = e * intrinsic.luminance(alb)
    bufs = intrinsic.Buffers(normal, height, alb, matte, matte)
    c = intrinsic.fit_source(lum, bufs)
    fit = np.tensordot(c, intrinsic.sh_basis(normal), axes=(0, 0))
    m = matte > 0.5
    target = e[m] * 0.5  # shading at the median albedo
    assert np.sqrt(np.mean((fit[m] - target) ** 2) / np.mean(target ** 2)) < 0.02


def test_fit_source_without_foreground_is_neutral():
    """No confident foreground: a constant shading, no NaN."""
    normal, height, matte, _, _ = sphere()
    bufs = intrinsic.Buffers(normal, height, np.full((3, S, S), 0.5, np.float32),
                             np.zeros_like(matte), np.zeros_like(matte))
    c = intrinsic.fit_source(np.ones((S, S), np.float32), bufs)
    assert np.all(np.isfinite(c)) and c[0] > 0 and np.all(c[1:] == 0)


def test_directionality_orders_lamps_skies_and_a_uniform_world():
    """|band 1| / band 0 of the irradiance fitted on the sphere's visible half: a lamp reaches
    PIXEL_SOURCE_DIRECTIONAL (full per-pixel weight), an overcast sky and a broad glow fall
    short of it, a uniform world is 0."""
    normal, height, matte, _, _ = sphere()
    alb = np.full((3, S, S), 0.5, np.float32)
    bufs = intrinsic.Buffers(normal, height, alb, matte, matte)

    def d(light):
        lum = intrinsic.luminance(exact_irradiance(light, normal).astype(np.float32)) * 0.5
        return intrinsic.directionality(intrinsic.fit_source(lum, bufs))

    full = intrinsic.PIXEL_SOURCE_DIRECTIONAL
    assert d(lightvec.splat_direction([0.5, 0.2, 1.0], 5.0)) >= full
    assert d(lightvec.splat_direction([1.0, 0.1, 0.4], 5.0)) >= full
    assert 0.1 < d(smooth_sky()) < d(overcast()) < full
    assert d(lightvec.uniform(1.0)) < 0.01


def hard_source(fill=0.15):
    """(image, Buffers, exact shading) of the skin sphere lit by a hard lamp from the right."""
    normal, height, matte, _, _ = sphere()
    alb = np.broadcast_to(SKIN[:, None, None], (3, S, S)).copy()
    e = exact_irradiance(lamp([1.0, 0.1, 0.4], 5.0, fill), normal).astype(np.float32)
    image = alb * e * matte / math.pi
    return image, intrinsic.Buffers(normal, height, alb, matte, matte.copy()), e


def gain_error(x, y):
    """Relative RMSE of x against y after x's least-squares gain."""
    g = float((x * y).sum() / (x * x).sum())
    return float(np.sqrt(np.mean((g * x - y) ** 2) / np.mean(y ** 2)))


def test_a_hard_source_is_read_per_pixel_on_skin(monkeypatch):
    """Under a hard lamp, the source shading with the per-pixel read is closer to the exact
    shading (up to a gain) than the nine-coefficient fit, and relighting to the mirrored lamp
    comes closer to the truth with it (diffuse only: a sphere casts no shadow on itself)."""
    image, bufs, e = hard_source()
    lum = intrinsic.luminance(image)
    c = intrinsic.fit_source(lum, bufs)
    m = bufs.matte > 0.5
    fit_only = intrinsic.source_shading(lum, bufs, c, weight=0.0)
    np.testing.assert_allclose(fit_only, np.tensordot(c, intrinsic.sh_basis(bufs.normal),
                                                      axes=(0, 0)), rtol=1e-6, atol=1e-7)
    read = intrinsic.source_shading(lum, bufs, c)
    truth = intrinsic.luminance(e)[m]
    assert gain_error(read[m], truth) < 0.6 * gain_error(fit_only[m], truth)

    target = lamp([-1.0, 0.1, 0.4], 5.0, 0.15)
    gt = intrinsic.luminance(bufs.albedo * exact_irradiance(target, bufs.normal) / math.pi)[m]

    def relit_error(weight):
        monkeypatch.setattr(intrinsic, "PIXEL_SOURCE_WEIGHT", weight)
        sh = intrinsic.shade(image, bufs, target, intrinsic.Plan())
        return gain_error(intrinsic.luminance(image * sh.ratio + sh.highlight)[m], gt)

    monkeypatch.setattr(intrinsic, "unlit_share", lambda rel, d: np.zeros_like(rel))
    assert relit_error(0.8) < 0.8 * relit_error(0.0)


def test_skin_the_footage_left_unlit_is_rendered_from_its_albedo(monkeypatch):
    """A hard lamp from the right with little fill, relit by the mirrored lamp: the ratio cannot
    brighten the side the footage left unlit (its shading is floored and its ratio bounded), so
    there the skin comes from the albedo, in the footage's skin colour, and the relit sphere is
    closer to the truth than with the ratio alone. A soft source leaves nothing unlit."""
    image, bufs, e = hard_source(fill=0.01)
    image = image * np.float32(0.7)  # any exposure: the fill is in the footage's units
    m = bufs.matte > 0.5
    target = lamp([-1.0, 0.1, 0.4], 5.0, 0.15)
    gt = (bufs.albedo * exact_irradiance(target, bufs.normal) / math.pi)[:, m]

    def relit(share=None):
        if share is not None:
            monkeypatch.setattr(intrinsic, "unlit_share", share)
        sh = intrinsic.shade(image, bufs, target, intrinsic.Plan())
        return (image * sh.ratio + sh.highlight)[:, m], sh

    share_fn = intrinsic.unlit_share
    out, sh = relit()
    assert sh.highlight.max() > 0  # the fill (no specular in this plan)
    ratio_only, _ = relit(lambda rel, d: np.zeros_like(rel))
    err = gain_error(intrinsic.luminance(out), intrinsic.luminance(gt))
    assert err < 0.7 * gain_error(intrinsic.luminance(ratio_only), intrinsic.luminance(gt))
    dark = intrinsic.luminance(image)[m] < 0.05 * intrinsic.luminance(image)[m].max()
    chroma = out[:, dark] / intrinsic.luminance(out)[dark]
    np.testing.assert_allclose(chroma.mean(1), SKIN / intrinsic.luminance(SKIN), rtol=0.02)
    # A uniform world lights every side: no share is rendered from the albedo.
    assert not share_fn(np.full((4, 4), 0.05, np.float32), 0.0).any()
    assert share_fn(np.full((4, 4), 0.05, np.float32), 0.7).min() == 1.0


@pytest.mark.parametrize("case", ["uniform_source", "not_skin"])
def test_soft_sources_and_non_skin_keep_the_fit(case):
    """A uniform source is not directional, and pixels off face skin keep the fit: there the
    source shading is the nine-coefficient fit exactly."""
    normal, height, matte, u, _ = sphere()
    alb = np.broadcast_to(SKIN[:, None, None], (3, S, S)).copy()
    if case == "uniform_source":
        image = alb * exact_irradiance(lightvec.uniform(1.0), normal).astype(np.float32) * matte
        face = matte.copy()
    else:
        image, _, _ = hard_source()
        face = (matte * (u > 0)).astype(np.float32)  # skin on the right half only
    bufs = intrinsic.Buffers(normal, height, alb, matte, face)
    lum = intrinsic.luminance(image)
    c = intrinsic.fit_source(lum, bufs)
    fit = np.maximum(np.tensordot(c, intrinsic.sh_basis(normal), axes=(0, 0)), 1e-8)
    got = intrinsic.source_shading(lum, bufs, c)
    off = face < 1e-6
    np.testing.assert_allclose(got[off], fit[off], rtol=1e-5)
    if case == "uniform_source":
        np.testing.assert_allclose(got, fit, rtol=1e-4)
    else:
        assert np.abs(got[face > 0.5] - fit[face > 0.5]).max() > 0.05 * float(fit.max())


def test_a_patch_the_fit_reads_as_unlit_is_not_relit_as_a_brighter_albedo(monkeypatch):
    """The footage shows a patch lit (a sphere of one albedo lit from the front and above)
    whose predicted normals turn down and away from the light, off face skin (a raised chin's
    neck read wrong): the fit says it was unlit, and a lamp from below relights it as if its
    albedo were many times brighter, a blot. With the change bounded (change_bounded), the
    patch's relit radiance per unit of target irradiance stays within SOURCE_ALBEDO_BOUND of
    the rest of the sphere's."""
    image, bufs = portrait(light=lamp([0.0, 0.5, 1.0], 5.0, 0.1))
    _, _, _, u, v = sphere()
    patch = (np.abs(u) < 0.25) & (v > 0.35) & (v < 0.65)
    normal = bufs.normal.copy()
    normal[:, patch] = unit([0.0, -0.8, 0.2]).astype(np.float32)[:, None]
    face = bufs.face.copy()
    face[patch] = 0.0  # not face skin: the per-pixel reading does not reach it
    bufs = dataclasses.replace(bufs, normal=normal, face=face)
    target = lamp([0.0, -0.8, 0.6], 5.0, 0.1)
    rest = (bufs.matte > 0.5) & ~patch & (np.hypot(u, v) < 0.8)

    def per_irradiance(bound):
        monkeypatch.setattr(intrinsic, "SOURCE_ALBEDO_BOUND", bound)
        sh = intrinsic.shade(image, bufs, target, intrinsic.Plan())
        e_t = intrinsic.luminance(intrinsic.irradiance(target, bufs.normal))
        y = intrinsic.luminance(image * sh.ratio + sh.highlight) / np.maximum(e_t, 1e-6)
        return float(np.median(y[patch])) / float(np.median(y[rest]))

    assert per_irradiance(1e6) > 3.0  # unbounded: the blot
    assert per_irradiance(1.25) < 1.25 * 1.15


def test_the_change_is_bounded_only_above_the_frame_s_typical_change():
    """change_bounded leaves the shading where the change is at most its median over the
    subject; above it the shading rises toward albedo_bounded's reading (the footage's luminance
    over the albedo variations, over the bound), never so far that the change falls below the
    median; off the subject nothing moves."""
    rng = np.random.default_rng(3)
    image, bufs = portrait()
    alb = bufs.albedo * rng.uniform(0.7, 1.3, (1, S, S)).astype(np.float32)
    bufs = dataclasses.replace(bufs, albedo=alb)
    lum = intrinsic.luminance(image)
    e_src = np.maximum(lum * rng.uniform(0.2, 2.0, (S, S)), 1e-3).astype(np.float32)
    y_t = rng.uniform(0.5, 1.5, (S, S)).astype(np.float32)
    fg = bufs.matte > 0.5
    got = intrinsic.change_bounded(e_src, y_t, lum, bufs, 1.25)
    typical = float(np.median((y_t / e_src)[fg]))
    cap = intrinsic.albedo_bounded(e_src, lum, bufs, 1.25)
    a = intrinsic.luminance(alb)
    read = lum / np.maximum(a / float(np.median(a[fg])), 0.02)
    np.testing.assert_allclose(cap[fg], np.maximum(e_src, read / 1.25)[fg], rtol=1e-6)
    calm = fg & (y_t / e_src <= typical)
    np.testing.assert_array_equal(got[calm], e_src[calm])
    bright = fg & ~calm
    assert (got[bright] >= e_src[bright]).all() and (got[bright] <= cap[bright] * (1 + 1e-6)).all()
    assert (y_t / got)[bright].min() >= typical * (1 - 1e-5)
    raised = bright & (got > e_src * 1.01)
    assert raised.sum() > 0.1 * bright.sum()  # the bound does act
    np.testing.assert_array_equal(got[~fg], e_src[~fg])


# ---- shadows ---------------------------------------------------------------------------------

BUMP_ROWS, BUMP_COLS = slice(29, 35), slice(29, 35)


def bump_field():
    h = np.zeros((S, S), np.float32)
    h[BUMP_ROWS, BUMP_COLS] = 20.0
    return h


RAKING_RIGHT = unit([0.94, 0.0, 0.34])  # from the camera's right, 20 degrees above the image plane


def test_a_bump_shadows_the_side_away_from_the_light():
    """Light from +X: pixels just left of a tall bump are shadowed, pixels right of it are not,
    nor rows the bump does not cover."""
    vis = intrinsic.shadow(bump_field(), np.ones((S, S), np.float32), RAKING_RIGHT)
    assert vis.shape == (S, S) and vis.min() >= 0.0 and vis.max() <= 1.0
    assert np.all(vis[BUMP_ROWS, 20:29] < 0.5)          # just left of it
    assert np.all(vis[BUMP_ROWS, 35:] == 1.0)           # right of it, toward the light
    assert np.all(vis[BUMP_ROWS, BUMP_COLS] == 1.0)     # its own top
    assert np.all(vis[:25] == 1.0) and np.all(vis[39:] == 1.0)
    # The mirrored light shadows the other side.
    vis_left = intrinsic.shadow(bump_field(), np.ones((S, S), np.float32), RAKING_RIGHT * [-1, 1, 1])
    assert np.all(vis_left[BUMP_ROWS, 35:44] < 0.5) and np.all(vis_left[BUMP_ROWS, :29] == 1.0)


def test_a_cast_shadow_has_a_penumbra_in_the_relit_frame():
    """The march decides whole pixels; the shading softens its edge (penumbra): across
    the bump's shadow the ratio falls over several pixels, no step between neighbours taking
    more than half of the way (and the umbra stays dark)."""
    normal = np.zeros((3, S, S), np.float32)
    normal[2] = 1.0
    flat = np.ones((S, S), np.float32)
    alb = np.full((3, S, S), 0.5, np.float32)
    bufs = intrinsic.Buffers(normal, bump_field(), alb, flat, np.zeros_like(flat))
    image = np.full((3, S, S), 0.2, np.float32)
    light = lightvec.splat_direction(RAKING_RIGHT, 10.0)
    ratio = intrinsic.shade(image, bufs, light, keep_exposure=False).ratio[1]
    row = ratio[32, 10:32]  # from the open floor, through the bump's shadow, to the bump
    span = float(row.max() - row.min())
    assert span > 0.5 * float(row.max())  # there is a shadow
    assert float(np.abs(np.diff(row)).max()) < 0.5 * span


def test_a_shadow_s_edge_softens_with_the_distance_to_its_occluder():
    """A light of some size draws a shadow sharp beside its occluder and softer further away:
    ``shadow`` reports how far each shadowed pixel's occluder lies (the same visibility as
    without it), and ``penumbra`` widens the edge with that distance (the bump's shadow's upper
    edge spans more rows 21 pixels from the bump than beside it), leaving a frame without
    shadow as it was."""
    ones = np.ones((S, S), np.float32)
    vis, dist = intrinsic.shadow(bump_field(), ones, RAKING_RIGHT, distance=True)
    assert np.array_equal(vis, intrinsic.shadow(bump_field(), ones, RAKING_RIGHT))
    assert np.all(dist[vis == 1.0] == 0.0)
    assert dist[32, 5] > dist[32, 25] > 0.0
    soft = intrinsic.penumbra(vis, dist)

    def edge_rows(col):  # rows of the shadow's upper edge part way between lit and dark
        c = soft[10:32, col]
        return int(((c > 0.1) & (c < 0.9)).sum())

    assert edge_rows(5) >= edge_rows(26) + 3, (edge_rows(5), edge_rows(26))
    assert soft[32, 20] < 0.5  # the umbra stays dark
    assert np.all(intrinsic.penumbra(ones, np.zeros_like(ones)) == 1.0)


def far_ear():
    """Buffers of a far ear: a tall block (a cheek, cols 20-29) turned nearly edge-on away from a
    light from the camera's right (its normals steeper than intrinsic.SHADOW_SLOPE_MAX, so the
    shadows' height is the block's own), and left of it a strip of flat subject (the ear, cols
    14-19) facing the camera, in the block's cast shadow, between the block and the backdrop
    (cols < 14)."""
    normal = np.zeros((3, S, S), np.float32)
    normal[2] = 1.0
    height = np.zeros((S, S), np.float32)
    cheek = (slice(16, 48), slice(20, 30))
    height[cheek] = 20.0
    turned = unit([-0.97, 0.0, 0.24])
    assert -turned[0] / turned[2] > intrinsic.SHADOW_SLOPE_MAX
    normal[:, cheek[0], cheek[1]] = np.asarray(turned, np.float32)[:, None, None]
    matte = np.ones((S, S), np.float32)
    matte[:, :14] = 0.0
    return intrinsic.Buffers(normal, height, np.full((3, S, S), 0.5, np.float32), matte,
                             np.zeros_like(matte))


@pytest.mark.parametrize("shape", [(5, 7), (1, 4), (6, 1), (16, 16)])
def test_poisson_is_the_least_squares_field_of_the_differences(shape):
    """poisson's field against a dense least-squares solve of the same forward differences
    (the mean fixed at 0), on random differences that no field fits exactly."""
    h, w = shape
    rng = np.random.default_rng(7)
    fx, fy = rng.normal(size=(h, w - 1)), rng.normal(size=(h - 1, w))
    rows, rhs = [], []
    for y in range(h):
        for x in range(w - 1):
            r = np.zeros(h * w)
            r[y * w + x + 1], r[y * w + x] = 1.0, -1.0
            rows.append(r)
            rhs.append(fx[y, x])
    for y in range(h - 1):
        for x in range(w):
            r = np.zeros(h * w)
            r[(y + 1) * w + x], r[y * w + x] = 1.0, -1.0
            rows.append(r)
            rhs.append(fy[y, x])
    rows.append(np.ones(h * w))
    rhs.append(0.0)
    want = np.linalg.lstsq(np.array(rows), np.array(rhs), rcond=None)[0].reshape(h, w)
    got = intrinsic.poisson(fx.astype(np.float32), fy.astype(np.float32))
    assert got.dtype == np.float32 and got.shape == shape
    np.testing.assert_allclose(got, want, atol=2e-4)


def normals_of(height):
    """(3, h, w) the unit normals of a height field (image y down, the normal's y up)."""
    gy, gx = np.gradient(height)
    normal = np.stack([-gx, gy, np.ones_like(height)])
    return normal / np.linalg.norm(normal, axis=0)


def shadow_buffers(height, normal):
    ones = np.ones(height.shape, np.float32)
    return intrinsic.Buffers(normal.astype(np.float32), height.astype(np.float32),
                             np.full((3, *height.shape), 0.5, np.float32), ones,
                             np.zeros_like(ones))


def test_the_shadows_height_is_the_normals_shape_where_the_predicted_height_disagrees():
    """A bump the normals hold and the predicted height does not (flat, as the network's eye
    sockets are shallower than its normals) comes back from the normals, to a constant; a step
    the normals cannot hold (a block facing the camera) comes from the height."""
    yy, xx = np.mgrid[:S, :S].astype(np.float64)
    bump = 12.0 * np.exp(-((xx - 20) ** 2 + (yy - 30) ** 2) / (2 * 6.0 ** 2))
    normal = normals_of(bump)
    block = np.zeros((S, S))
    block[20:40, 40:55] = 15.0
    got = intrinsic.shadow_height(shadow_buffers(block, normal))
    want = bump + block
    offset = float(np.median(got - want))
    assert np.abs(got - want - offset).max() < 0.6, np.abs(got - want - offset).max()
    # the block alone, its sides only in the height: kept to the pixel
    got = intrinsic.shadow_height(shadow_buffers(block, normals_of(np.zeros((S, S)))))
    np.testing.assert_allclose(got - got[0, 0], block, atol=1e-3)


def test_the_shadows_height_holds_more_of_the_face_skin_s_relief():
    """A nose drawn too low (a bump 3 pixels high, 2 wide) on face skin: the shadows' height keeps
    SHADOW_DETAIL times its relief (its rise over the height blurred by SHADOW_DETAIL_SIGMA, to
    within a tenth at the bump), ``relief`` 1 keeps it as drawn, and beyond the face skin's reach
    the height is the same either way. Under a lamp 35 degrees above, only the kept relief casts
    the nose's shadow below it."""
    yy, xx = np.mgrid[:S, :S].astype(np.float64)
    bump = 3.0 * np.exp(-((xx - 32) ** 2 + (yy - 28) ** 2) / (2 * 2.0 ** 2))
    face = np.zeros((S, S), np.float32)
    face[16:48, 16:48] = 1.0
    bufs = dataclasses.replace(shadow_buffers(bump, normals_of(bump)), face=face)
    drawn, kept = intrinsic.shadow_height(bufs, 1.0), intrinsic.shadow_height(bufs)

    def rise(h):
        return float((h - intrinsic.gaussian_blur(h, intrinsic.SHADOW_DETAIL_SIGMA))[28, 32])

    assert rise(kept) == pytest.approx(intrinsic.SHADOW_DETAIL * rise(drawn), rel=0.1)
    far = np.ones((S, S), bool)
    far[8:56, 8:56] = False
    np.testing.assert_array_equal(kept[far], drawn[far])
    lamp_above = unit([0.0, math.cos(math.radians(35)), math.sin(math.radians(35))])
    below = (slice(31, 35), 32)  # just below the bump's top
    assert intrinsic.shadow(drawn, bufs.matte, lamp_above)[below].min() == 1.0
    assert intrinsic.shadow(kept, bufs.matte, lamp_above)[below].min() < 0.9


def test_a_broad_nose_as_drawn_on_real_faces_casts_its_shadow_under_a_key_lamp():
    """A nose as the network draws real ones, broad and low (5 pixels high, its sides rising at
    most a pixel of height a pixel), on face skin, under a key lamp 35 degrees to the side and 15
    up (whose ray climbs 1.3 pixels a pixel, steeper than the nose's sides): as drawn it casts
    nothing; with the relief the shadows' height keeps (SHADOW_DETAIL of the detail finer than
    SHADOW_DETAIL_SIGMA) its shadow falls beside it, away from the lamp. At 2.2 times the detail
    finer than 4 pixels it fell nowhere."""
    yy, xx = np.mgrid[:S, :S].astype(np.float64)
    nose = 5.0 * np.exp(-((xx - 32) ** 2 / (2 * 3.0 ** 2) + (yy - 30) ** 2 / (2 * 6.0 ** 2)))
    assert np.abs(np.gradient(nose)[1]).max() < 1.0
    face = np.zeros((S, S), np.float32)
    face[12:52, 12:52] = 1.0
    bufs = dataclasses.replace(shadow_buffers(nose, normals_of(nose)), face=face)
    key = unit([-0.55, 0.26, 0.79])  # from the image's left: the shadow falls to its right
    beside = (slice(26, 34), slice(33, 42))
    drawn = intrinsic.shadow(intrinsic.shadow_height(bufs, 1.0), bufs.matte, key)
    kept = intrinsic.shadow(intrinsic.shadow_height(bufs), bufs.matte, key)
    assert drawn.min() == 1.0
    assert kept[beside].min() < 0.5
    assert kept[:, :31].min() == 1.0  # nothing on the lamp's side


def test_the_shadows_height_keeps_the_predicted_steps_and_the_subject_over_its_backdrop():
    """A head (a disc 30 pixels out) over a neck (10 out) on a backdrop, all facing the camera:
    no normal holds the steps, so they stay the height's, to the pixel. (Integrating with the
    subject's outline held at the backdrop's level, the head stood 1.7 pixels out.)"""
    yy, xx = np.mgrid[:S, :S].astype(np.float64)
    head = (xx - 32) ** 2 + (yy - 28) ** 2 < 18 ** 2
    matte = head | ((np.abs(xx - 32) < 8) & (yy > 28))
    height = np.where(head, 30.0, np.where(matte, 10.0, 0.0))
    bufs = shadow_buffers(height, normals_of(np.zeros((S, S))))
    bufs = dataclasses.replace(bufs, matte=matte.astype(np.float32))
    got = intrinsic.shadow_height(bufs)
    np.testing.assert_allclose(got - got[0, 0], height, atol=1e-3)


def test_a_brow_the_normals_hold_shades_the_eye_under_a_high_light():
    """A ridge above a flat band (a brow over the eye), in the normals but not in the predicted
    height: a light from high above casts the ridge's shadow below it."""
    yy, xx = np.mgrid[:S, :S].astype(np.float64)
    ridge = 8.0 * np.exp(-((yy - 24) ** 2) / (2 * 2.5 ** 2))
    normal = normals_of(ridge)
    bufs = shadow_buffers(np.zeros((S, S)), normal)
    light = lightvec.splat_direction(unit([0.0, 0.94, 0.34]), 10.0)
    ratio = intrinsic.shade(np.full((3, S, S), 0.2, np.float32), bufs, light,
                            keep_exposure=False).ratio[1]
    # rows 25-30 face away from the light (the ridge's lower side); the cast shadow reaches on
    # over the flat band below (over the flat predicted height these kept 0.79 of the light)
    below, far = float(ratio[31:35, 20:44].mean()), float(ratio[50:55, 20:44].mean())
    assert below < 0.6 * far, (below, far)


def test_a_cast_shadow_beside_a_side_turned_from_the_light_stays_dark():
    """The penumbra does not blur the side turned from the light in as lit (shadow never marched
    it): a strip in the block's cast shadow stays dark at its edge against the block (blurred
    with the turned side's unmarched visibility of 1, the two columns there kept 0.17 and 0.36
    of the light, the strip 0.21 on average); lit subject beside the block keeps its full
    change."""
    bufs = far_ear()
    image = np.full((3, S, S), 0.2, np.float32)
    light = lightvec.splat_direction(RAKING_RIGHT, 10.0)
    ratio = intrinsic.shade(image, bufs, light, keep_exposure=False).ratio[1]
    floor = float(ratio[32, 45])
    assert floor > 1.0
    assert float(ratio[32, 18:20].max()) < 0.02 * floor, ratio[32, 14:20] / floor
    assert float(ratio[32, 14:20].mean()) < 0.15 * floor, ratio[32, 14:20] / floor
    assert np.allclose(ratio[32, 30:60], floor)


@pytest.mark.parametrize("sigma", [0.2, 0.5, 0.8, 1.0, 1.05, 1.5, 2.5, 4.0])
def test_a_blur_by_its_taps_or_by_bands_is_the_matrix_blur(sigma):
    """gaussian_blur adds a narrow blur's taps (up to TAPS_RADIUS) and takes a wider one's
    matrix products a band of rows at a time: both the whole matrix products' blur, edges
    extended, on stacks, on sides shorter than its reach and on sides of several bands."""
    rng = np.random.default_rng(3)
    for shape in ((2, 40, 52), (7, 9), (1, 6), (3, 1), (2, 3, 11, 5), (2, 70, 97)):
        a = rng.random(shape, dtype=np.float32)
        h, w = shape[-2:]
        ref = intrinsic.blur_matrix(h, sigma) @ a @ intrinsic.blur_matrix(w, sigma).T
        for got in (intrinsic.gaussian_blur(a, sigma), intrinsic.tap_blur(a, sigma),
                    intrinsic.banded_blur(a, sigma)):
            assert got.dtype == np.float32 and got.shape == a.shape
            np.testing.assert_allclose(got, ref, atol=2e-6)
    assert intrinsic.blur_radius(1.05) <= intrinsic.TAPS_RADIUS < intrinsic.blur_radius(1.5)
    assert 70 > 2 * intrinsic.BAND_BLOCK


def test_penumbra_with_no_pixel_turned_is_the_plain_blur():
    ones = np.ones((S, S), np.float32)
    vis, dist = intrinsic.shadow(bump_field(), ones, RAKING_RIGHT, distance=True)
    plain = intrinsic.penumbra(vis, dist)
    assert plain.min() < 0.5
    assert np.allclose(intrinsic.penumbra(vis, dist, np.zeros((S, S), bool)), plain, atol=1e-6)


def test_a_light_from_above_shadows_below():
    """Light from +Y (image up): the shadow falls below the bump (image y down)."""
    vis = intrinsic.shadow(bump_field(), np.ones((S, S), np.float32), unit([0.0, 0.94, 0.34]))
    assert np.all(vis[35:44, BUMP_COLS] < 0.5)
    assert np.all(vis[:29, BUMP_COLS] == 1.0)


def test_a_lit_sphere_casts_no_shadow_on_itself():
    """A convex surface cannot shadow itself: on a sphere's shadow height, no pixel facing a lamp
    (n.l above 0.05) loses any of it, for lamps all around from 10 to 70 degrees above the image
    plane (the march's samples are whole pixels; SHADOW_BIAS keeps them off the surface). Taken
    as face skin, whose relief the shadows' height raises (SHADOW_DETAIL), the sphere's rim
    stands a little proud of it: pixels facing the lamp by n.l above 0.2 still lose nothing."""
    normal, height, matte, _, _ = sphere()
    plain = shadow_buffers(height, normal)
    for bufs, least in ((plain, 0.05), (dataclasses.replace(plain, face=matte), 0.2)):
        h = intrinsic.shadow_height(bufs)
        for el in np.radians([10, 20, 35, 50, 70]):
            for az in np.radians(np.arange(0, 360, 30)):
                d = np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
                cos = np.tensordot(d, normal, 1)
                vis = intrinsic.shadow(h, matte, d, lit=cos)
                assert vis[(matte > 0.5) & (cos > least)].min() == 1.0


def test_a_wall_s_shadow_keeps_most_of_its_length():
    """A wall 12 pixels high under a lamp from above at 20 to 60 degrees over the image plane: its
    shadow below it (visibility under a half) reaches at least two thirds of the length the
    lamp's angle gives it (12 / tan(elevation)), and nothing beyond that length is shadowed."""
    wall = np.zeros((S, S), np.float32)
    wall[10:20, 20:44] = 12.0
    for el in (20, 30, 45, 60):
        e = math.radians(el)
        vis = intrinsic.shadow(wall, np.ones((S, S), np.float32),
                               np.array([0.0, math.cos(e), math.sin(e)]))
        below, geometric = vis[20:, 32], 12.0 / math.tan(e)
        length = int(np.argmax(below >= 0.5))
        assert length >= 0.65 * geometric, (el, length)
        assert np.all(below[math.ceil(geometric):] == 1.0)  # and nothing beyond it


def test_a_light_along_the_view_axis_casts_no_shadow():
    """+Z light: visibility 1 everywhere."""
    vis = intrinsic.shadow(bump_field(), np.ones((S, S), np.float32), np.array([0.0, 0.0, 1.0]))
    assert np.all(vis == 1.0)


def test_a_bump_outside_the_matte_casts_nothing():
    """The matte restricts occluders: the same bump outside the matte shadows no subject pixel."""
    matte = np.ones((S, S), np.float32)
    matte[27:37, 27:37] = 0.0
    vis = intrinsic.shadow(bump_field(), matte, RAKING_RIGHT)
    assert np.all(vis[matte > 0.5] == 1.0)


# ---- specular --------------------------------------------------------------------------------

@pytest.mark.parametrize("direction", [(0.5, 0.3, 0.81), (0.9, 0.1, 0.42), (-0.3, -0.4, 0.8)])
def test_specular_peaks_at_the_half_vector_and_is_zero_facing_away(direction):
    """The GGX highlight peaks where the normal is the half vector of the light and +Z (within
    2 px) and is zero wherever n.d <= 0."""
    normal, _, matte, _, _ = sphere()
    d = unit(direction)
    s = intrinsic.specular(normal, d.astype(np.float32))
    assert s.shape == (S, S) and np.all(np.isfinite(s)) and s.min() >= 0.0
    row, col = np.unravel_index(int(np.argmax(np.where(matte > 0.5, s, -1.0))), s.shape)
    hv = unit(d + [0.0, 0.0, 1.0])
    want_row, want_col = S / 2 - R * hv[1] - 0.5, S / 2 + R * hv[0] - 0.5
    assert math.hypot(row - want_row, col - want_col) <= 2.0
    facing_away = np.tensordot(d, normal, axes=(0, 0)) <= 0
    assert facing_away.sum() > 50
    assert np.all(s[facing_away] == 0.0)


# ---- shade -----------------------------------------------------------------------------------

def halves(chw, u, matte):
    lum = intrinsic.luminance(chw)
    m = matte > 0.5
    return float(lum[m & (u < 0)].mean()), float(lum[m & (u > 0)].mean())


@pytest.mark.parametrize("side", [1.0, -1.0])
def test_a_side_lamp_brightens_its_side(side):
    """A lamp from the right makes the right half brighter than the left, and the reverse."""
    image, bufs = portrait()
    _, _, _, u, _ = sphere()
    left0, right0 = halves(image, u, bufs.matte)
    assert left0 == pytest.approx(right0, rel=1e-3)  # the footage is symmetric
    sh = intrinsic.shade(image, bufs, lamp([side, 0.0, 0.3]))
    left, right = halves(image * sh.ratio + sh.highlight, u, bufs.matte)
    near, far = (right, left) if side > 0 else (left, right)
    assert near > 3.0 * far


def skin_chroma(chw, m):
    """Mean red over green and blue over green on the pixels ``m``."""
    return np.array([chw[0][m].mean() / chw[1][m].mean(), chw[2][m].mean() / chw[1][m].mean()])


def test_white_light_keeps_skin_colour():
    """A white light leaves the ratio achromatic off the skin (channels equal within 1e-5) and
    keeps the skin's mean colour within 3% (only its terminator warms, the light diffusing
    under it); a red light does not."""
    image, bufs = portrait()
    no_skin = intrinsic.Buffers(bufs.normal, bufs.height, bufs.albedo, bufs.matte,
                                np.zeros_like(bufs.face))
    m = bufs.matte > 0.5
    for light in (lamp([1.0, 0.2, 0.5]), smooth_sky().mean(-1, keepdims=True).repeat(3, -1)):
        ratio = intrinsic.shade(image, no_skin, light).ratio
        scale = float(np.abs(ratio).max())
        assert np.abs(ratio[0] - ratio[1]).max() <= 1e-5 * scale
        assert np.abs(ratio[2] - ratio[1]).max() <= 1e-5 * scale
        out = image * intrinsic.shade(image, bufs, light).ratio
        np.testing.assert_allclose(skin_chroma(out, m), skin_chroma(image, m), rtol=0.03)
    red = lamp([1.0, 0.2, 0.5]) * np.array([1.0, 0.3, 0.2], np.float32)
    ratio = intrinsic.shade(image, bufs, red).ratio
    assert ratio[0][m].mean() > 2.0 * ratio[1][m].mean()


def red_over_blue(chw, m):
    return float(np.log(chw[0][m].mean() / chw[2][m].mean()))


def warm_and_cool():
    """(light, image, Buffers, left, right) of the skin sphere under a warm lamp camera-left
    and a cool one camera-right of equal luminance (its left and right thirds' masks)."""
    warm = np.array([1.0, 0.75, 0.5], np.float32)
    cool = warm[::-1].copy()
    light = (lamp([-1.0, 0.0, 0.7], 6.0, 0.0) * warm / float(warm @ intrinsic.LUMA)
             + lamp([1.0, 0.0, 0.7], 6.0, 0.0) * cool / float(cool @ intrinsic.LUMA)
             + lightvec.uniform(0.05))
    image, bufs = portrait(light=light)
    _, _, matte, u, _ = sphere()
    return light, image, bufs, (matte > 0.5) & (u < -0.2), (matte > 0.5) & (u > 0.2)


def test_a_light_warm_on_one_side_and_cool_on_the_other_is_divided_out(monkeypatch):
    """A warm lamp camera-left and a cool one camera-right of equal luminance: source_chroma
    reads the warm side as warm, and relit under a white light the two sides' colours come
    within 0.7 of the footage's difference (the threshold is shrunk off what is read); with
    the colour left unread (a threshold beyond reach) they keep it."""
    _, image, bufs, left, right = warm_and_cool()
    split = red_over_blue(image, left) - red_over_blue(image, right)
    assert split > 0.3
    tint = intrinsic.source_chroma(image, bufs)
    assert tint is not None
    assert red_over_blue(tint, left) - red_over_blue(tint, right) > 0.3 * split
    white = lightvec.uniform(1.0)
    out = image * intrinsic.shade(image, bufs, white).ratio
    assert abs(red_over_blue(out, left) - red_over_blue(out, right)) < 0.7 * split
    monkeypatch.setattr(intrinsic, "CHROMA_GRADIENT_MIN", 1e6)
    kept = image * intrinsic.shade(image, bufs, white).ratio
    assert red_over_blue(kept, left) - red_over_blue(kept, right) > 0.8 * split


def test_a_known_source_shading_replaces_the_estimate():
    """shade's ``source``: given the footage's true diffuse shading per channel, the warm and
    cool lamps' colours are divided out entirely under a white light (the two sides' colours
    within 0.05 of the footage's difference); given only its luminance, they stay."""
    light, image, bufs, left, right = warm_and_cool()
    split = red_over_blue(image, left) - red_over_blue(image, right)
    true = exact_irradiance(light, sphere()[0]).astype(np.float32)
    white = lightvec.uniform(1.0)
    out = image * intrinsic.shade(image, bufs, white, source=true).ratio
    assert abs(red_over_blue(out, left) - red_over_blue(out, right)) < 0.05 * split
    grey = image * intrinsic.shade(image, bufs, white, source=intrinsic.luminance(true)).ratio
    assert red_over_blue(grey, left) - red_over_blue(grey, right) > 0.9 * split


def test_a_known_source_with_a_dark_channel_bounds_that_channel_s_ratio():
    """A given source shading with no blue at all (a pure yellow lamp): the blue ratio meets
    the ratio's bound without a division by zero, and the other channels' stay as with a
    trace of blue."""
    image, bufs = portrait()
    true = exact_irradiance(lamp([0.3, 0.2, 1.0]), bufs.normal).astype(np.float32)
    yellow = true * np.array([1.0, 1.0, 0.0], np.float32)[:, None, None]
    trace = true * np.array([1.0, 1.0, 1e-3], np.float32)[:, None, None]
    white = lightvec.uniform(1.0)
    with np.errstate(divide="raise", invalid="raise"):
        ratio = intrinsic.shade(image, bufs, white, source=yellow, keep_exposure=False).ratio
    fg = bufs.matte > 0.5
    assert np.isfinite(ratio).all()
    norm = intrinsic.shade(image, bufs, white, source=trace, keep_exposure=False).ratio
    np.testing.assert_allclose(ratio[:2][:, fg], norm[:2][:, fg], rtol=1e-3)
    assert ratio[2][fg].min() >= norm[2][fg].min()


def test_a_faces_own_colour_gradient_is_not_read_as_light():
    """Skin redder toward the chin (red up 35% from brow to chin) under a white lamp, and a grey
    photo of it: no light colour is read from either."""
    normal, height, matte, _, v = sphere()
    alb = np.broadcast_to(SKIN[:, None, None], (3, S, S)).copy()
    alb[0] *= (1.0 + 0.15 * np.clip(v, -1.0, 1.0)).astype(np.float32)
    image = (alb * exact_irradiance(lamp([0.3, 0.4, 1.0]), normal) * matte / math.pi)
    bufs = intrinsic.Buffers(normal, height, np.broadcast_to(SKIN[:, None, None], (3, S, S)),
                             matte, matte.copy())
    assert intrinsic.source_chroma(image.astype(np.float32), bufs) is None
    grey = np.repeat(intrinsic.luminance(image.astype(np.float32))[None], 3, 0)
    assert intrinsic.source_chroma(grey, bufs) is None


def test_the_light_colour_is_read_over_face_skin_where_there_is_enough_of_it():
    """A white lamp on a sphere whose lower part is skin and upper part hair the network drew
    grey, the hair's own colour turning from blue on its left to red on its right: read over
    the face skin, no light colour; with too little skin to read (none marked), the colour is
    read over the whole subject, and the hair's colour then reads as light."""
    normal, height, matte, u, v = sphere()
    hair = (v < 0.0) & (matte > 0.5)
    alb = np.broadcast_to(SKIN[:, None, None], (3, S, S)).copy()
    turn = np.exp(np.clip(u, -1.0, 1.0) * np.array([1.5, 0.0, -1.5], np.float32)[:, None, None])
    alb = np.where(hair[None], 0.3 * turn, alb).astype(np.float32)
    image = (alb * exact_irradiance(lamp([0.3, 0.4, 1.0]), normal) * matte / math.pi)
    grey = np.where(hair[None], 0.3, np.broadcast_to(SKIN[:, None, None], (3, S, S)))
    skin = (matte * ~hair).astype(np.float32)
    bufs = intrinsic.Buffers(normal, height, grey.astype(np.float32), matte, skin)
    assert int((skin[::2, ::2] > 0.5).sum()) >= intrinsic.CHROMA_MIN_PIXELS
    assert intrinsic.source_chroma(image.astype(np.float32), bufs) is None
    none_marked = dataclasses.replace(bufs, face=np.zeros_like(skin))
    tint = intrinsic.source_chroma(image.astype(np.float32), none_marked)
    assert tint is not None
    left, right = hair & (u < -0.3), hair & (u > 0.3)
    assert red_over_blue(tint, right) - red_over_blue(tint, left) > 0.3


def saturated_shadows():
    """(image, Buffers, u) of the skin sphere lit from its left, the skin redder the darker it
    is (as real, graded skin is): its chromaticity moves from the albedo's by up to +25% red
    and -25% blue as its shading falls from the lit side's."""
    image, bufs = portrait()
    normal, _, matte, u, _ = sphere()
    e = exact_irradiance(lamp([-1.0, 0.1, 0.5], fill=0.5), normal).mean(0)
    rel = np.clip(e / np.percentile(e[matte > 0.5], 90), 0.0, 1.0)
    cast = 1.0 + 0.25 * (1.0 - rel)[None] * np.array([1.0, 0.0, -1.0], np.float32)[:, None, None]
    cast /= intrinsic.luminance(cast)[None]
    image = (bufs.albedo * e[None] * cast * matte / math.pi).astype(np.float32)
    return image, bufs, u


def test_level_colour_needs_a_spread_of_levels_and_enough_skin():
    image, bufs = portrait(albedo=SKIN)
    lum = intrinsic.luminance(image)
    even = np.full(lum.shape, 0.3, np.float32)
    skin = bufs.matte > 0.5
    assert intrinsic.level_colour(image, lum, even, skin) is None
    assert intrinsic.level_colour(image, lum, lum + 1e-3, np.zeros_like(skin)) is None
    level = intrinsic.level_colour(image, lum, lum + 1e-3, skin)
    f = intrinsic.level_factor(level, lum + 1e-3, lum + 1e-3)
    np.testing.assert_allclose(f, 1.0, atol=1e-5)  # the same level: no change


def test_level_colour_reads_the_skins_colour_against_its_level():
    """Skin whose red share rises and blue share falls with its log shading's fall: the fit
    finds it, and the factor taking a shadowed pixel to a lit one's level gives the lit one's
    colour (the levels clipped to the range seen, LEVEL_PERCENTILES)."""
    rng = np.random.default_rng(0)
    e = np.exp(rng.uniform(-3.0, 0.0, (40, 40))).astype(np.float32)
    slope = np.array([-0.05, 0.0, 0.08], np.float32)
    share = 1.0 + slope[:, None, None] * np.log(e)[None]
    share /= intrinsic.luminance(share)[None]
    lum = 0.5 * e
    image = share * lum[None]
    skin = np.ones(e.shape, bool)
    coef, lo, hi = intrinsic.level_colour(image, lum, e, skin)
    assert (lo, hi) == pytest.approx(tuple(np.percentile(np.log(e), intrinsic.LEVEL_PERCENTILES)))
    dark, bright = np.float32(np.exp(lo)), np.float32(np.exp(hi))
    f = intrinsic.level_factor((coef, lo, hi), np.full((1, 1), dark), np.full((1, 1), bright * 4))
    want = (1.0 + slope * hi) / (1.0 + slope * lo)
    want /= float(intrinsic.LUMA @ want)
    np.testing.assert_allclose(f[:, 0, 0], want, rtol=0.02)
    assert float(intrinsic.luminance(f)[0, 0]) == pytest.approx(1.0, abs=1e-5)
    # A light that darkens the skin leaves its colour to the target's own shading: no change.
    f = intrinsic.level_factor((coef, lo, hi), np.full((1, 1), bright), np.full((1, 1), dark))
    np.testing.assert_allclose(f[:, 0, 0], 1.0, atol=1e-5)


def test_a_filled_shadow_takes_the_colour_of_the_footages_lit_skin(monkeypatch):
    """Footage whose shadowed side is redder, relit by a white lamp from that side: level_colour
    takes the side most of the way from the shadow's redder colour to the footage's lit
    skin's, where the ratio of shadings alone keeps it; the luminance stays within 5%."""
    image, bufs, u = saturated_shadows()
    fg = bufs.matte > 0.5
    lit, shadowed = fg & (u < -0.4), fg & (u > 0.4)
    light = lamp([1.0, 0.1, 0.5], fill=0.1)
    target = skin_chroma(image, lit)[0]
    sh = intrinsic.shade(image, bufs, light)
    fitted = image * sh.ratio + sh.highlight
    monkeypatch.setattr(intrinsic, "level_colour", lambda *args: None)
    sh = intrinsic.shade(image, bufs, light)
    plain = image * sh.ratio + sh.highlight
    before, after = skin_chroma(plain, shadowed)[0], skin_chroma(fitted, shadowed)[0]
    assert before > 1.08 * target
    assert before - after > 0.6 * (before - target)
    np.testing.assert_allclose(intrinsic.luminance(fitted)[fg], intrinsic.luminance(plain)[fg],
                               rtol=0.05, atol=1e-4)


def test_light_diffuses_under_skin_red_furthest():
    """subsurface: uniform irradiance stays as it is, nothing changes off the skin, and across a
    white lamp's terminator the dark side gets light back, red the most, blue the least (how
    much warmer, against the light stage: tests/training/test_intrinsic.py)."""
    normal, height, matte, u, _ = sphere()
    skin = matte.copy()
    flat = np.full((3, S, S), 2.0, np.float32)
    np.testing.assert_allclose(intrinsic.subsurface(flat, skin), flat, rtol=1e-5)
    irr = exact_irradiance(lightvec.splat_direction([1.0, 0.0, 0.0], 5.0), normal).astype(np.float32)
    half = skin * (u > 0)  # skin on the lit half only
    out = intrinsic.subsurface(irr, half)
    np.testing.assert_array_equal(out[:, half == 0], irr[:, half == 0])
    out = intrinsic.subsurface(irr, skin)
    band = (matte > 0.5) & (np.abs(u) < 0.12)  # around the terminator (normal x = 0)
    gain = (out[:, band] - irr[:, band]).mean(1)
    assert gain[0] > gain[1] > gain[2] > 0
    dark = (matte > 0.5) & (u < -0.05) & (u > -0.2)  # just past it, on the dark side
    back = [out[c][dark].mean() for c in range(3)]
    assert intrinsic.luminance(np.array(back)) > 2.0 * irr[1][dark].mean()
    assert back[0] > back[1] > back[2]


def test_a_cast_shadow_s_edge_on_skin_diffuses_at_the_light_stage_s_scale(monkeypatch):
    """The light a cast shadow takes from skin diffuses at the light stage's own scale
    (cast_subsurface, SSS_CHROMA_FACE_CM), whatever the terminator's wider scale (SSS_FACE_CM):
    on a skin plane a wall's shadow is the same with the terminator's diffusion twice as wide
    again, and its edge falls over more rows, and its umbra a few rows in is lighter, only when
    the light stage's scale is taken wider."""
    normal = np.zeros((3, S, S), np.float32)
    normal[2] = 1.0
    ones = np.ones((S, S), np.float32)
    wall = np.zeros((S, S), np.float32)
    wall[16:48, 29:35] = 20.0  # its shadow falls to its left, its upper edge at row 16
    bufs = intrinsic.Buffers(normal, wall, np.full((3, S, S), 0.5, np.float32), ones, ones)
    image = np.full((3, S, S), 0.2, np.float32)
    light = lightvec.splat_direction(RAKING_RIGHT, 10.0)

    def ratio():
        return intrinsic.shade(image, bufs, light, keep_exposure=False).ratio

    def red_edge():  # (rows between the open and the umbra level, the red ratio 6 rows in)
        red = ratio()[0][4:30, 26]
        t = (red - red.min()) / (red.max() - red.min())
        return int(((t > 0.1) & (t < 0.9)).sum()), float(red[18] / red[0])

    rows, umbra = red_edge()
    assert ratio()[0][22, 26] < 0.3 * ratio()[0][4, 26]  # there is a shadow
    with monkeypatch.context() as m:
        m.setattr(intrinsic, "SSS_FACE_CM", intrinsic.SSS_FACE_CM / 2)
        assert red_edge() == (rows, pytest.approx(umbra, rel=1e-4))
    with monkeypatch.context() as m:
        m.setattr(intrinsic, "SSS_CHROMA_FACE_CM", intrinsic.SSS_FACE_CM)
        rows_wide, umbra_wide = red_edge()
    assert rows_wide >= rows + 2, (rows, rows_wide)
    assert umbra < 0.75 * umbra_wide, (umbra, umbra_wide)


def test_hair_away_from_the_face_takes_the_wrapped_lobe():
    """A side lamp on a sphere: with no face skin (all hair) the far side just past the
    terminator gets light, as hair's wrapped lobe gives it; as face skin (Lambert) it stays
    dark there; and the lobe itself is Lambert's without wrap and hair's with it."""
    c = np.linspace(-1.0, 1.0, 9, dtype=np.float32)
    np.testing.assert_array_equal(intrinsic.lobe(c), np.maximum(c, 0.0))
    np.testing.assert_allclose(intrinsic.lobe(c, np.ones_like(c)), np.maximum(0.7 * c + 0.3, 0.0),
                               atol=1e-7)
    normal, height, matte, u, v = sphere()
    alb = np.broadcast_to(SKIN[:, None, None], (3, S, S)).copy()
    image = (alb * exact_irradiance(lightvec.uniform(1.0), normal) * matte / math.pi).astype(np.float32)
    light = lightvec.splat_direction([1.0, 0.0, 0.0], 5.0)
    upper = (matte > 0.5) & (v < -0.1)  # well above the chin and away from the skin below
    beyond = upper & (u < -0.15) & (u > -0.35)  # just past the terminator
    lit = upper & (u > 0.5)
    chin = (matte * (v > 0.5)).astype(np.float32)  # face skin only in the sphere's lowest part
    far = {}
    for name, face in (("hair", chin), ("skin", matte.copy())):
        bufs = intrinsic.Buffers(normal, height, alb, matte, face)
        ratio = intrinsic.shade(image, bufs, light, intrinsic.Plan()).ratio
        far[name] = float(ratio[1][beyond].mean() / ratio[1][lit].mean())
    assert far["hair"] > 0.1 and far["skin"] < 0.5 * far["hair"]
    share = intrinsic.hair_share(intrinsic.Buffers(normal, height, alb, matte, chin))
    assert share[upper].min() > 0.9
    assert share[(v > 0.65) & (np.abs(u) < 0.3) & (matte > 0.5)].max() == 0.0  # on skin
    top = (matte * (v < -0.5)).astype(np.float32)  # face skin only in the upper part
    below = intrinsic.hair_share(intrinsic.Buffers(normal, height, alb, matte, top))
    assert below[v > -0.45].max() == 0.0  # below the chin: neck and clothes stay Lambert


def head_in_hair(radius=14.0):
    """(Buffers, u, v) a face of skin (a sphere of ``radius``) framed by hair over the whole
    crop, camera-facing, at one flat height, as the network puts real hair level with the cheeks:
    a height march alone casts no shadow here. u, v as sphere's."""
    normal, _, face, u, v = sphere(radius=radius)
    alb = np.broadcast_to(SKIN[:, None, None], (3, S, S)).copy()
    flat = np.zeros((S, S), np.float32)
    return intrinsic.Buffers(normal, flat, alb, np.ones((S, S), np.float32), face), u, v


SIDE_LAMP = unit([1.0, 0.0, 1.0])  # from the image's right, 45 degrees off the view axis


def test_hair_behind_the_far_cheek_is_in_the_head_s_shadow():
    """A lamp from the right: the hair beside the left cheek, which faces away from it, is in
    the head's shadow; the hair beside the right cheek, above the head and the face itself are
    not; a lamp on the view axis shadows no hair."""
    bufs, u, v = head_in_hair()
    wrap = intrinsic.hair_share(bufs)
    cos = np.tensordot(SIDE_LAMP, bufs.normal, axes=(0, 0))
    vis = intrinsic.behind_head(cos, bufs.face, wrap, SIDE_LAMP)
    row = np.abs(v) < 0.3  # level with the face's middle, well above its chin
    far = row & (u < -1.6) & (u > -2.2)  # hair beyond the left cheek
    near = row & (u > 1.6) & (u < 2.2)
    assert wrap[far].min() > 0.9 and wrap[near].min() > 0.9  # hair, lit by the wrapped lobe
    assert vis[far].max() < 0.1
    assert vis[near].min() == 1.0
    assert vis[(v < -1.4) & (np.abs(u) < 0.3)].min() == 1.0  # above the head: the lamp's beside
    assert vis[bufs.face > 0.5].min() == 1.0  # skin: shadow's march and its own n.l
    frontal = intrinsic.behind_head(bufs.normal[2], bufs.face, wrap, np.array([0.0, 0.0, 1.0]))
    assert frontal.min() == 1.0


def test_a_lamp_leaves_the_hair_behind_the_head_dark_in_the_relit_frame():
    """Relit by a lamp from the right with shadows, the hair beyond the left cheek keeps under a
    fifth of what the same light gives it without them, while the hair beyond the right cheek
    keeps what it had; a soft sky plans no shadows and leaves it lit."""
    bufs, u, v = head_in_hair()
    image = (bufs.albedo * exact_irradiance(lightvec.uniform(1.0), bufs.normal) / math.pi
             ).astype(np.float32)
    light = lamp(SIDE_LAMP, 20.0, 0.0)
    effects = intrinsic.plan(light)
    assert effects.components and effects.shadows
    row = np.abs(v) < 0.3
    far, near = row & (u < -1.6) & (u > -2.2), row & (u > 1.6) & (u < 2.2)
    shadowed = intrinsic.shade(image, bufs, light, effects, keep_exposure=False).ratio[1]
    no_shadows = intrinsic.Plan(effects.components, False, False)
    unshadowed = intrinsic.shade(image, bufs, light, no_shadows, keep_exposure=False).ratio[1]
    assert shadowed[far].mean() < 0.2 * unshadowed[far].mean()
    assert shadowed[near].mean() == pytest.approx(unshadowed[near].mean(), rel=0.02)
    sky = intrinsic.shade(image, bufs, smooth_sky(), keep_exposure=False).ratio[1]
    assert sky[far].mean() > 0.5 * sky[near].mean()


def long_hair(bufs, u):
    """head_in_hair's buffers with the network's hair class: long hair in two curtains either
    side of the face (|u| > 1.3) down the whole crop, the rest below the chin (the neck, the
    clothes) not hair."""
    hair = (np.abs(u) > 1.3).astype(np.float32)
    return dataclasses.replace(bufs, hair=hair)


def test_the_hair_class_lets_hair_below_the_chin_be_lit_as_hair():
    """With the network's hair class, hair_share is what it was above the chin and, below it,
    the hair the class finds (long hair past the jaw), not the neck and clothes beside it; a
    class that finds no hair changes nothing."""
    bufs, u, v = head_in_hair()
    plain = intrinsic.hair_share(bufs)
    none = intrinsic.hair_share(dataclasses.replace(bufs, hair=np.zeros_like(bufs.matte)))
    np.testing.assert_array_equal(none, plain)
    share = intrinsic.hair_share(long_hair(bufs, u))
    above = v < 1.0 - 2.0 * intrinsic.HAIR_FACE_SIGMA / 14.0  # above the fade under the chin
    np.testing.assert_array_equal(share[above], plain[above])
    below = v > 1.6
    assert plain[below].max() == 0.0
    assert share[below & (np.abs(u) > 1.4)].min() > 0.99  # the curtains
    assert share[below & (np.abs(u) < 1.2)].max() == 0.0  # the neck and clothes


def test_a_lamp_leaves_long_hair_below_the_far_jaw_in_the_head_s_shadow():
    """A lamp from the right and above: the curtain below the chin on the far (left) side, lit
    by the lamp's n.l without the hair class, falls in the head's shadow with it; the neck and
    clothes below the chin keep the same light either way."""
    bufs, u, v = head_in_hair()
    image = (bufs.albedo * exact_irradiance(lightvec.uniform(1.0), bufs.normal) / math.pi
             ).astype(np.float32)
    light = lamp(unit([1.0, 0.6, 1.0]), 20.0, 0.0)
    effects = intrinsic.plan(light)
    assert effects.components and effects.shadows
    plain = intrinsic.shade(image, bufs, light, effects, keep_exposure=False).ratio[1]
    with_hair = intrinsic.shade(image, long_hair(bufs, u), light, effects,
                                keep_exposure=False).ratio[1]
    far = (v > 1.2) & (v < 1.6) & (u < -1.5) & (u > -1.9)
    neck = (v > 1.2) & (np.abs(u) < 0.5)
    assert plain[far].mean() > 0.5 * plain[neck].mean()  # lit, without the class
    assert with_hair[far].mean() < 0.2 * plain[far].mean()
    np.testing.assert_allclose(with_hair[neck], plain[neck], rtol=1e-5)


@pytest.mark.parametrize("light", ["lamp", "sky", "dim"])
def test_keep_exposure_keeps_the_mean_luminance(light):
    """keep_exposure: the matte-weighted mean luminance of image * ratio + highlight equals the
    image's within 1e-3 relative, whatever the light's power."""
    image, bufs = portrait()
    target = {"lamp": lamp([0.7, 0.4, 0.6], 50.0), "sky": smooth_sky(),
              "dim": 1e-3 * lamp([-0.5, 0.0, 0.8])}[light]
    sh = intrinsic.shade(image, bufs, target, keep_exposure=True)
    w = bufs.matte
    before = float((intrinsic.luminance(image) * w).sum())
    after = float((intrinsic.luminance(image * sh.ratio + sh.highlight) * w).sum())
    assert after == pytest.approx(before, rel=1e-3)


def test_without_keep_exposure_twice_the_light_is_twice_the_change():
    """keep_exposure=False: doubling the light doubles ratio and highlight."""
    image, bufs = portrait()
    light = lamp([0.7, 0.4, 0.6], 2.0)
    one = intrinsic.shade(image, bufs, light, keep_exposure=False)
    two = intrinsic.shade(image, bufs, 2.0 * light, keep_exposure=False)
    assert one.ratio.max() < intrinsic.RATIO_MAX / 2 and one.highlight.max() > 0
    np.testing.assert_allclose(two.ratio, 2.0 * one.ratio, rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(two.highlight, 2.0 * one.highlight, rtol=1e-5, atol=1e-9)


@pytest.mark.parametrize("case", ["black_image_zero_light", "black_image_lamp", "zero_light",
                                  "no_matte"])
def test_degenerate_inputs_stay_finite(case):
    """An all-zero image, a zero light, or no matte at all: finite ratio and highlight."""
    image, bufs = portrait()
    light = lightvec.zeros() if "zero_light" in case else lamp([0.7, 0.4, 0.6])
    if "black_image" in case:
        image = np.zeros_like(image)
    if case == "no_matte":
        bufs = intrinsic.Buffers(bufs.normal, bufs.height, bufs.albedo,
                                 np.zeros_like(bufs.matte), np.zeros_like(bufs.face))
    sh = intrinsic.shade(image, bufs, light)
    assert np.all(np.isfinite(sh.ratio)) and np.all(np.isfinite(sh.highlight))
    assert sh.ratio.shape == image.shape and sh.highlight.shape == image.shape
    assert sh.ratio.min() >= 0.0


def test_highlights_only_when_the_plan_has_components(monkeypatch):
    """Effects off (Plan()) and a uniform light give zero highlight; a lamp gives one on skin.
    (What shade adds also holds the fill of skin the footage left unlit: off here.)"""
    monkeypatch.setattr(intrinsic, "unlit_share", lambda rel, d: np.zeros_like(rel))
    image, bufs = portrait()
    assert not intrinsic.shade(image, bufs, lamp([0.7, 0.4, 0.6]), intrinsic.Plan()).highlight.any()
    assert not intrinsic.shade(image, bufs, lightvec.uniform(1.0)).highlight.any()
    lit = intrinsic.shade(image, bufs, lamp([0.7, 0.4, 0.6]))
    assert lit.highlight.max() > 0 and not lit.highlight[:, bufs.face < 0.5].any()


def test_exposure_scale_puts_the_90th_percentile_at_the_input_level():
    """The crop's 90th luminance percentile goes to INPUT_LEVEL; a black crop keeps scale 1."""
    x = np.random.default_rng(4).random((3, 16, 16)).astype(np.float32) * 3.0
    s = intrinsic.exposure_scale(x)
    q = float(np.quantile(intrinsic.luminance(x * s), intrinsic.INPUT_QUANTILE))
    assert q == pytest.approx(intrinsic.INPUT_LEVEL, rel=1e-4)
    assert intrinsic.exposure_scale(np.zeros((3, 4, 4), np.float32)) == 1.0


# ----------------------------------------------------------------------------- light transport

def unoccluded_transfer(normal):
    return intrinsic.TRANSFER_BAND[:, None, None] * intrinsic.sh_basis(normal, 3)


def test_order_3_sh_are_orthonormal_and_extend_order_2():
    d = lightvec.directions().reshape(-1, 3).T
    om = lightvec.solid_angles().reshape(-1)
    y = intrinsic.sh_basis(d, 3).astype(np.float64)
    assert y.shape == (16, d.shape[1])
    np.testing.assert_allclose((y * om) @ y.T, np.eye(16), atol=0.02)
    np.testing.assert_array_equal(y[:9], intrinsic.sh_basis(d).astype(np.float64))


def test_transfer_irradiance_of_an_unoccluded_transfer_is_lamberts():
    """transfer . light_sh with the unoccluded transfer is Lambert's irradiance to the SH order:
    for a uniform world within the reference's own cell sum (1%), close for a smooth sky."""
    normal = random_normals(3)
    t = unoccluded_transfer(normal)
    for light, tol in ((lightvec.uniform(0.7), 0.015), (smooth_sky(), 0.04)):
        ref = exact_irradiance(light, normal)
        got = intrinsic.transfer_irradiance(light, t)
        assert np.abs(got - ref).max() < tol * ref.max()
    sh = intrinsic.light_sh(lightvec.uniform(2.0))
    np.testing.assert_allclose(sh[0], 2.0 * math.sqrt(4 * math.pi), rtol=1e-3)
    assert np.abs(sh[1:]).max() < 0.005 * sh[0, 0]  # the cells sum the sphere to 0.5%


def occluded_sphere(share=0.4):
    """A sphere whose transfer lets ``share`` of the light through on a patch left of centre (a
    crease, an eye socket), the rest unoccluded; the patch's mask."""
    normal, height, matte, u, v = sphere()
    t = unoccluded_transfer(normal)
    patch = ((u + 0.35) ** 2 + (v - 0.1) ** 2 < 0.2 ** 2) & (matte > 0)
    t[:, patch] *= share
    return normal, height, matte, t, patch


def test_occlusion_is_the_share_the_transfer_lets_through():
    normal, height, matte, t, patch = occluded_sphere(0.4)
    for light in (lightvec.uniform(), smooth_sky(), lamp(unit([0.3, 0.4, 0.87]))):
        sh = intrinsic.light_sh(light) @ np.asarray(intrinsic.LUMA, np.float32)
        occ = intrinsic.occlusion(sh, t, intrinsic.free_irradiance(sh, intrinsic.sh_basis(normal)))
        lit = (matte > 0) & (normal[2] > 0.5)
        np.testing.assert_allclose(occ[lit & ~patch], 1.0, atol=0.02)
        assert abs(float(np.median(occ[lit & patch])) - 0.4) < 0.05


def test_a_patch_shadowed_from_one_side_goes_dark_when_the_light_comes_from_that_side():
    """A patch that sees no light from the camera's left (a cheek beside the nose): footage lit
    from the right shows it lit; relit from the left, the transfer knows it is in shadow, while
    Lambert's shading on its normals lights it."""
    normal, height, matte, u, v = sphere()
    t = unoccluded_transfer(normal)
    patch = ((u + 0.1) ** 2 + (v - 0.1) ** 2 < 0.25 ** 2) & (matte > 0)
    d = lightvec.directions().reshape(-1, 3)
    om = lightvec.solid_angles().reshape(-1)
    seen = (d[:, 0] > -0.1) * om  # the left of the sky is hidden
    n = normal[:, patch].T
    t[:, patch] = (intrinsic.sh_basis(d.T, 3) * seen) @ np.maximum(d @ n.T, 0.0)
    alb = np.ones((3, S, S), np.float32) * SKIN[:, None, None]
    src_light = lamp(unit([0.6, 0.3, 0.75]), fill=0.2)
    light = lamp(unit([-0.6, 0.3, 0.75]), fill=0.2)
    image = alb / math.pi * intrinsic.transfer_irradiance(src_light, t) * matte
    truth = alb / math.pi * intrinsic.transfer_irradiance(light, t) * matte
    errors, level = {}, {}
    for name, tr in (("with", t), ("without", None)):
        bufs = intrinsic.Buffers(normal, height, alb, matte, np.zeros_like(matte), tr)
        sh = intrinsic.shade(image, bufs, light, intrinsic.Plan((), False, False))
        out = image * sh.ratio + sh.highlight
        errors[name] = gain_error(out[:, matte > 0], truth[:, matte > 0])
        level[name] = float(out[1, patch].mean() / out[1, (matte > 0) & ~patch].mean())
    assert errors["with"] < 0.5 * errors["without"], errors
    want = float(truth[1, patch].mean() / truth[1, (matte > 0) & ~patch].mean())
    assert abs(level["with"] - want) < 0.5 * abs(level["without"] - want), (level, want)
