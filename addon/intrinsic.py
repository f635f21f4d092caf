"""The physical renderer of the intrinsic presets: shade a target light from predicted buffers.

The network (training/intrinsic) predicts, for a square crop around the portrait, per-pixel
normals, height toward the camera, albedo variations, the matte and face skin, and (networks
that have them) hair and the light transport (``transfer``: what the face itself hides from
each direction, as order-3 SH). This module turns those buffers and a light vector into a
per-pixel change of the footage:

    relit = footage * E_target / E_source + specular

* ``E_source``: the footage's own diffuse shading, an order-2 spherical-harmonic irradiance
  fitted to the crop's luminance over the predicted normals (divided by the albedo variations, so
  brows and lips do not read as shadow). Fitted on luminance: the footage keeps its own colour,
  and the target light alone sets the colour change (a white light keeps skin colour), unless
  the footage's light colour varies across the face more than skin's own colour does (a warm
  sun on one side, a blue sky on the other): that part is divided out (``source_chroma``).
  Where the footage's light is directional, nine coefficients cannot hold its hard terminator
  and cast shadows, so on face skin the shading read per pixel (luminance over albedo) is
  blended in (``source_shading``). Where the fit says a pixel was lit far less than the footage
  shows over its albedo, the ratio would paint a bright blot there under a light that reaches
  it: a change brighter than the frame's typical one is bounded by that reading
  (``change_bounded``).
* ``E_target``: the irradiance of the light vector on the predicted normals, summed exactly
  over its brightest cells and through order-2 SH for the rest (``irradiance``).
* Occlusion, with a transfer: both shadings are darkened by the share of their light the
  transfer lets through (``occlusion``: under an eye's brow, beside the nose, under the jaw),
  soft to the transfer's order; the source's under the skin as the footage shows it.
* Effects on demand (``plan``): the light's strong, compact components (a lamp, a sun) get a
  screen-space cast shadow, marched over the predicted height corrected to the normals' slopes
  (``shadow_height``), and a GGX highlight on skin; soft light (an overcast sky, a uniform
  world) gets neither, and pays nothing for them. On skin the target irradiance diffuses under
  the surface (``subsurface``), red furthest, as the light stage renders it: terminators turn
  soft and warm, and a cast shadow's edge a little warm at the light stage's own scale
  (``cast_subsurface``). Hair (the subject away from face skin above the chin, and the
  network's hair class below it) takes the light stage's wrapped lobe and the head's shadow
  (``hair_share``, ``behind_head``).

Everything is numpy, channels first, at the working size; addon/portrait.py brings the change
to the footage's full resolution as a ratio, so the footage keeps its identity and detail.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

from . import colour, contract, lightvec

LUMA = tuple(float(x) for x in colour.REC709_LUMA)
# A crop is scaled so its 90th luminance percentile sits at this level before the network (the
# same rule in training: training/intrinsic/train.py normalise_batch).
INPUT_QUANTILE = 0.9
INPUT_LEVEL = 0.6

# A component is "compact and strong" when the 3 x 3 cells around its brightest texel carry at
# least this share of the light's power: only such components can cast a visible shadow or a
# highlight. Up to MAX_COMPONENTS are simulated.
COMPONENT_SHARE = 0.12
MAX_COMPONENTS = 3
SHADOW_STEPS = 30           # march length in working-size pixels
SHADOW_SOFTNESS = 3.0       # pixels of height over which an occluder fades in
# The ray toward the light starts this many pixels of height above its pixel, so the march does not
# shadow a surface with its own samples (rounded to whole pixels): a lit sphere's shadow height
# (shadow_height) shadows none of its pixels that face the light (n.l above 0.05) from 10 to 70
# degrees above the image plane, where 1.0 took up to a tenth of the light near the terminator.
# Nothing is taken per pixel marched: the height follows the normals' slopes (shadow_height), and
# the earlier 0.1 a pixel (with 2.0), which made up for the predicted height's own slopes, cut a
# wall's shadow to 55-58% of its length under lights 20 to 60 degrees high, where this leaves
# 67-73%. On the CroppedYale tune subjects (36 pairs each, paired with (2.0, 0.1)) top/bottom
# balance correlation +0.0016 (5-95% +0.0002 to +0.0035), 20.15 -> 20.17 dB (the test subjects
# 20.11 -> 20.14 dB, 0.832 -> 0.833); the synthetic test set's rmse_level_fit 0.05779 -> 0.05781.
# 1.0 and 0.5 read +0.0020 and +0.0024 on tune, at 0.05784 and 0.05786. On the effects bench
# ("auto", 24 frames) the network's buffers under the top light gain 0.3388 -> 0.3282 (long-haired
# identities 0.3481 -> 0.3376), the key lamps within 0.0022; the exact buffers of long-haired
# identities lose under the key lamps (0.1691 / 0.1517 -> 0.1756 / 0.1570), most likely because a
# height field has no thickness (a lock of hair before a cheek marches as a wall). 2.0 with nothing
# per pixel lost less there (0.1732 / 0.1546) and gained less under the top light (0.3399).
SHADOW_BIAS = 1.5
# The visibility's penumbra (``penumbra``) widens with the distance to the occluder, as a light
# of some size draws it: a Gaussian of sigma PENUMBRA[0] + PENUMBRA[1] x the distance (working-
# size pixels), at most PENUMBRA[2], blended between blurs of PENUMBRA_LEVELS' sigmas. The march
# decides whole pixels, and enlarged to the frame its edge drew stair steps; one sigma for every
# shadow (1.5) left a jaw's shadow on the neck a dark block as sharp as the nose's. On the
# synthetic effects bench (bench/intrinsic_effects.py, "auto", 24 frames) against that fixed 1.5:
# exact buffers top light 0.1873 -> 0.1717, key lamps 0.1105 / 0.1151 -> 0.1103 / 0.1149; network
# buffers top 0.3284 -> 0.3208, key lamps within 0.0003; CroppedYale tune 20.37 -> 20.36 dB,
# top/bottom 0.809 -> 0.808 (within the resampling spread). 0.1 a pixel gained less (top 0.1760);
# 0.3 the same as 0.2.
PENUMBRA = (1.0, 0.2, 6.0)
PENUMBRA_LEVELS = (1.0, 2.0, 4.0, 8.0)
PENUMBRA_REACH = 4.0  # sigma over which a shadow's occluder distance reaches its lit edge
HAIR_WRAP = (0.7, 0.3)      # hair's diffuse lobe max(0, 0.7 n.l + 0.3), as the light stage's hair
HAIR_FACE_SIGMA = 4.0       # pixels (a Gaussian's sigma) over which hair_share fades out at skin
SKIN_ROUGHNESS = 0.5        # GGX roughness of skin, as the light stage's
SKIN_F0 = 0.028
SKIN_ALBEDO = 0.35          # luminance albedo of skin: absolute units for highlights and "physical"
# Where the footage left the skin unlit (its shading below these shares of its 90th percentile),
# a ratio has nothing to brighten: the skin is rendered there from the predicted albedo instead,
# fully below the first share, not at all above the second, as the fitted light is directional
# (a soft source leaves no region unlit). On the CroppedYale tune subjects (0.1, 0.4) gained
# 0.13 dB over the ratio alone (one-light pairs 0.46 dB); (0.05, 0.25) and (0.2, 0.6) less.
UNLIT = (0.1, 0.4)
RATIO_MAX = 16.0            # a region the footage had in deep shadow is not amplified without bound
# The source shading is taken as at least this share of its 90th percentile on the subject (a
# division by a shadow's near-zero shading): 0.02 over 0.05 gained 0.06 dB on the CroppedYale
# tune subjects, whose one-flash sources leave deep shadows; the ratio's bound still applies.
SOURCE_FLOOR = 0.02
# The source shading read per pixel counts up to this weight (log space) on face skin ...
PIXEL_SOURCE_WEIGHT = 0.8
# ... reached when the fitted source light is this directional (``directionality``: one lamp on
# a sphere's visible half fits at 0.6-0.7, an overcast sky at 0.33, a uniform world at 0).
PIXEL_SOURCE_DIRECTIONAL = 0.6
# The fit can read a pixel as unlit that the footage shows lit (a raised chin's neck, a bounce
# from below that the nine coefficients miss, a patch of wrong normals), and the ratio then
# relights it as if its albedo were several times brighter than the network predicts: a bright
# blot under a light that reaches it. So where a pixel's change is brighter than the frame's
# typical (median) change, the shading the ratio divides by is raised toward the footage's
# luminance over its albedo variations (the per-pixel reading above) divided by this, never
# past the typical change (change_bounded). The card's synthetic test set (training.eval.evaluate)
# rmse_level_fit 0.0578 -> 0.0561 (1.5 0.0563, 1 0.0565); CroppedYale tune subjects (36 pairs
# each) 20.41 -> 20.47 dB (1.5 20.44), top/bottom +0.000; effects bench, the network's buffers:
# uniform world 0.1089 -> 0.1035, softest HDRI 0.1531 -> 0.1496, key left 0.2275 -> 0.2261, rim
# and fill 0.4493 -> 0.4502. Raising the shading itself everywhere (albedo_bounded at 1.5, the
# change left unbounded by the typical one) read 0.0559 and 20.47 dB, top/bottom +0.002, but
# it breaks the cancellation of the network's errors between the source's fit and the target's
# rendering (their shared occlusion) under soft light: uniform 0.1189, softest HDRI 0.1574.
SOURCE_ALBEDO_BOUND = 1.25
# Light diffusing under the skin, as the light stage renders it (training/lightstage/shading.py):
# the share of each channel's irradiance that diffuses and how far (red travels furthest), in
# centimetres at the skin ...
SSS_ALPHA = (0.75, 0.55, 0.40)
SSS_SIGMA_CM = (0.30, 0.14, 0.07)
# ... brought to the working size by the face skin's size: the square root of its area taken as
# this many centimetres. Six is half a real face's (~12): diffusion twice as wide as the light
# stage's, chosen on the CroppedYale tune subjects (it also softens the terminator that the
# predicted normals draw too sharp). The light a cast shadow takes away diffuses at the light
# stage's own scale instead (cast_subsurface): a shadow's edge has its own softness
# (penumbra), and at twice the scale a nose's shadow on real footage read as a grey smear
# across the cheek.
SSS_FACE_CM = 6.0
# The diffusion's colour (red against blue) keeps the light stage's own scale: its skin's square
# root area over its pixels per centimetre, median 13.4 cm over the val frames (the network's
# skin map 13.4). At SSS_FACE_CM's scale the new shadows on skin turned three to four times as
# warm as the light stage's (bench/intrinsic_effects.py's shadow warmth, exact buffers, a key
# lamp from the left: +0.15 against +0.04), a red-brown band at a white lamp's terminator on
# real footage.
SSS_CHROMA_FACE_CM = 13.4
# A luminance's diffusion in one channel: the channels' shares and widths weighted by LUMA (the
# green channel's, nearly), for a shading that is luminance only.
SSS_LUMINANCE = ((sum(a * w for a, w in zip(SSS_ALPHA, LUMA)),),
                 (sum(c * w for c, w in zip(SSS_SIGMA_CM, LUMA)),))


# The skin's colour against its light's level (level_colour) is read between these percentiles
# of the levels the footage shows: above its upper quartile the footage's own tone curve, not
# the light, desaturates skin, so a brighter target keeps the colour of its well-lit skin. On
# the dev footage (training.eval.footage_sheet, 24 frames) skin chroma relit over input under
# the white lamps went from 1.40 to 1.10 on the clip whose shadowed side is warm, the others
# staying within 0.95-1.02; at the 95th percentile an evenly lit clip fell to 0.89, at the
# median the first kept 1.13. The skin's log levels must spread at least LEVEL_MIN_SPREAD.
LEVEL_PERCENTILES = (5, 75)
LEVEL_MIN_SPREAD = 0.1


def dot3(v, chw: np.ndarray) -> np.ndarray:
    """(...) the weighted sum of ``chw``'s three planes (3, ...) by ``v`` (3,), term by term: as
    a BLAS product of a short vector it took three times as long on one thread."""
    a, b, c = (np.float32(t) for t in v)
    return a * chw[0] + b * chw[1] + c * chw[2]


def luminance(chw: np.ndarray) -> np.ndarray:
    return dot3(LUMA, chw)


def exposure_scale(image_chw: np.ndarray, level: float | None = None) -> float:
    """The scale that puts the crop's 90th luminance percentile at ``level`` (default
    INPUT_LEVEL; 1 for black)."""
    level = INPUT_LEVEL if level is None else level
    lum = luminance(image_chw)
    finite = lum[np.isfinite(lum)]
    q = float(np.quantile(finite, INPUT_QUANTILE)) if finite.size else 0.0
    return level / q if q > 1e-8 else 1.0


@dataclass(frozen=True)
class Buffers:
    """The network's buffers at the working size, channels first."""
    normal: np.ndarray   # (3, h, w) unit, camera frame
    height: np.ndarray   # (h, w) pixels toward the camera, up to a constant
    albedo: np.ndarray   # (3, h, w) up to a gain per channel
    matte: np.ndarray    # (h, w) portrait foreground in [0, 1]
    face: np.ndarray     # (h, w) face skin in [0, 1]
    transfer: np.ndarray | None = None  # (16, h, w) light transport (TRANSFER_ORDER), if predicted
    hair: np.ndarray | None = None      # (h, w) hair in [0, 1], if the network has the class


@dataclass(frozen=True)
class Component:
    direction: np.ndarray   # (3,) unit, camera frame
    irradiance: np.ndarray  # (3,) W/m2 at normal incidence


@dataclass(frozen=True)
class Plan:
    """What the light calls for: the compact components that get shadows and highlights."""
    components: tuple[Component, ...] = ()
    shadows: bool = True
    specular: bool = True


def plan(light: np.ndarray, shadows: bool = True, specular: bool = True,
         share: float = COMPONENT_SHARE) -> Plan:
    """Find the light's compact, strong components (greedy: brightest cell, its 3 x 3
    neighbourhood, removed, repeat). A uniform or overcast light has none."""
    light = np.asarray(light, np.float64)
    omega = lightvec.solid_angles()
    dirs = lightvec.directions()
    power = (light @ np.asarray(LUMA)) * omega  # (16, 16) luminous power per cell
    total = float(power.sum())
    comps = []
    if total > 0 and (shadows or specular):
        left = power.copy()
        rows, cols = power.shape
        for _ in range(MAX_COMPONENTS):
            r, c = np.unravel_index(int(np.argmax(left)), left.shape)
            rr = np.clip(np.arange(r - 1, r + 2), 0, rows - 1)
            cc = np.arange(c - 1, c + 2) % cols
            sel = np.zeros_like(left, bool)
            sel[np.ix_(rr, cc)] = True
            sel &= left > 0
            p = float(left[sel].sum())
            if p < share * total:
                break
            w = left[sel]
            d = (dirs[sel] * w[:, None]).sum(0)
            d /= max(np.linalg.norm(d), 1e-12)
            irr = (light[sel] * omega[sel][:, None]).sum(0)
            comps.append(Component(d.astype(np.float32), irr.astype(np.float32)))
            left[sel] = 0.0
    return Plan(tuple(comps), shadows and bool(comps), specular and bool(comps))


# ----------------------------------------------------------------------------- shading pieces

# Lambert's cosine lobe in SH bands 0, 1, 2 (pi, 2 pi / 3, pi / 4), per coefficient.
SH_BAND = np.array([math.pi] + [2 * math.pi / 3] * 3 + [math.pi / 4] * 5, np.float32)


def unit_normals(n: np.ndarray) -> np.ndarray:
    """(3, ...) vectors scaled to unit length (a mean of normals, a resampled normal map)."""
    return (n / np.maximum(np.linalg.norm(n, axis=0, keepdims=True), 1e-6)).astype(np.float32)


def sh_basis(normal, order: int = 2, stack=None):
    """((order + 1) ** 2, ...) real orthonormal spherical harmonics of unit vectors (3, ...), in
    the usual order (band by band, m from -l to l); ``order`` 2 (nine) or 3 (sixteen).
    ``stack``: how to join the terms (default: a float32 numpy array on a new first axis), so
    the training's tensors use the same polynomials."""
    x, y, z = normal
    one = x * 0 + 1
    out = [0.282095 * one, 0.488603 * y, 0.488603 * z, 0.488603 * x,
           1.092548 * x * y, 1.092548 * y * z, 0.315392 * (3 * z * z - 1),
           1.092548 * x * z, 0.546274 * (x * x - y * y)]
    if order >= 3:
        zz = 5 * z * z
        out += [0.590044 * y * (3 * x * x - y * y), 2.890611 * x * y * z,
                0.457046 * y * (zz - 1), 0.373176 * z * (zz - 3), 0.457046 * x * (zz - 1),
                1.445306 * z * (x * x - y * y), 0.590044 * x * (x * x - 3 * y * y)]
    if stack is not None:
        return stack(out)
    return np.stack(out).astype(np.float32)


# Light transport: the network's ``transfer`` buffer holds, per pixel, the order-3 SH projection
# of the light that reaches it (the light stage's visibility times the cosine, so occlusion by
# the nose, brows, jaw and hair is in it): the diffuse irradiance under a light with SH
# coefficients L is transfer . L (light_sh). Its coefficients odd in x change sign when the
# picture is mirrored left to right.
TRANSFER_ORDER = 3
TRANSFER_CHANNELS = contract.TRANSFER_CHANNELS  # (TRANSFER_ORDER + 1) ** 2
TRANSFER_X_ODD = contract.TRANSFER_X_ODD
# An unoccluded pixel's transfer: Lambert's cosine lobe in SH (SH_BAND; its band 3 is zero)
# times the SH of its normal. The network predicts the difference occlusion makes.
TRANSFER_BAND = np.concatenate([SH_BAND, np.zeros(7, np.float32)])


def light_sh(light: np.ndarray, order: int = TRANSFER_ORDER) -> np.ndarray:
    """((order + 1) ** 2, 3) SH coefficients of a (16, 16, 3) light vector's radiance: each
    cell's power (radiance times its solid angle) at its direction."""
    d = lightvec.directions().reshape(-1, 3).astype(np.float64)
    lw = (np.asarray(light, np.float64).reshape(-1, 3)
          * lightvec.solid_angles().reshape(-1, 1))
    return (sh_basis(d.T, order).astype(np.float64) @ lw).astype(np.float32)


def transfer_irradiance(light: np.ndarray, transfer: np.ndarray) -> np.ndarray:
    """(3, h, w) diffuse irradiance under a (16, 16, 3) light from the transfer buffer (16, h, w),
    occlusion included (to the transfer's order: soft)."""
    return np.tensordot(light_sh(light).T, transfer, axes=(1, 0))


def occlusion(sh: np.ndarray, transfer: np.ndarray, free: np.ndarray) -> np.ndarray:
    """(...) in [0, 1]: the share of a light's diffuse irradiance (its luminance SH coefficients
    ``sh`` (16,)) that the transfer (16, ...) lets through, against ``free``, the unoccluded
    irradiance on the same pixels' normals (free_irradiance) at the same order."""
    occluded = np.tensordot(np.asarray(sh, np.float32), transfer, axes=(0, 0))
    # (a sample of the pixels gives the percentile: the floor need not be exact)
    floor = OCCLUSION_FLOOR * max(float(np.percentile(free.reshape(-1)[::7], 90)), 1e-12)
    return np.clip((occluded + floor) / (np.maximum(free, 0.0) + floor), 0.0, 1.0).astype(
        np.float32)


def free_irradiance(sh: np.ndarray, basis: np.ndarray) -> np.ndarray:
    """The unoccluded irradiance of a light with SH coefficients ``sh`` on normals whose order-2
    SH are ``basis`` (9, ...): Lambert's lobe (TRANSFER_BAND is zero past order 2)."""
    return np.tensordot(np.asarray(sh[:9], np.float32) * SH_BAND, basis, axes=(0, 0))


OCCLUSION_FLOOR = 0.05  # occlusion's ratio is steadied where the light barely reaches a pixel
EXACT_CELLS = 24     # at most this many of the brightest cells are summed exactly ...
EXACT_SHARE = 0.01   # ... those with at least this share of the power; the rest through SH


def lobe(cos: np.ndarray, wrap: np.ndarray | None = None) -> np.ndarray:
    """The diffuse lobe at n.d = ``cos``: Lambert's max(0, cos), blended by ``wrap`` (share per
    pixel) with hair's wrapped lobe max(0, HAIR_WRAP[0] cos + HAIR_WRAP[1]), as the light stage
    renders hair (light wraps around its volume; training/lightstage/shading.py)."""
    lam = np.maximum(cos, 0.0)
    if wrap is None:
        return lam
    return lam + wrap * (np.maximum(HAIR_WRAP[0] * cos + HAIR_WRAP[1], 0.0) - lam)


def hair_share(bufs: Buffers) -> np.ndarray:
    """(h, w) where the subject is lit as hair (``lobe``): the matte away from face skin (a
    Gaussian of HAIR_FACE_SIGMA over the skin map fades it to 0 on and next to the skin, so eyes,
    brows and lips stay Lambert) above the chin (the lowest row of face skin, fading over two
    sigma), and below it only where the network's hair class says hair (``bufs.hair``; without
    the class, nothing): below the chin are the neck and clothes, which the light stage renders
    Lambert (taking them too cost 0.06 in relative error on its key lights), and long hair
    falling past the jaw to the shoulders. Without it the far side of the hair under a lamp went
    black in a blob around the face on real footage; without the class below the chin, long
    hair there kept the footage's light beside a cheek in shadow (behind_head takes only what
    this shares). On held-out light-stage identities that all wear long hair
    (bench/results/intrinsic_effects_long_hair*.md) the class moves the network buffers' relit
    error by under 0.0005 either way; with the stage's exact buffers it rises about 0.002 under
    the key lamps."""
    face = np.clip(bufs.face, 0.0, 1.0)
    near = gaussian_blur(face, HAIR_FACE_SIGMA)
    share = np.clip(bufs.matte, 0.0, 1.0) * np.clip(1.0 - 3.0 * near, 0.0, 1.0)
    rows = np.nonzero(face.max(1) > 0.5)[0]
    if len(rows) == 0:
        return np.zeros_like(share)
    chin = float(rows.max())
    y = np.arange(face.shape[0], dtype=np.float32)
    above = np.clip((chin - y) / (2.0 * HAIR_FACE_SIGMA), 0.0, 1.0)[:, None]
    if bufs.hair is not None:
        above = above + (1.0 - above) * np.clip(bufs.hair, 0.0, 1.0)
    return (share * above).astype(np.float32)


def irradiance(light: np.ndarray, normal: np.ndarray, exact_cells: int = EXACT_CELLS,
               exact_share: float = EXACT_SHARE, wrap: np.ndarray | None = None) -> np.ndarray:
    """(3, h, w) irradiance sum_t L_t max(0, n.d_t) Omega_t on normals (3, h, w): the
    ``exact_cells`` brightest cells exactly (a lamp's terminator stays sharp), the others through
    their order-2 spherical-harmonic projection (Ramamoorthi and Hanrahan: about 1% error for
    smooth light, at the cost of nine products per pixel instead of one per cell). ``wrap``
    (h, w): where the exact cells light hair (``lobe``); smooth light stays Lambert's."""
    d = lightvec.directions().reshape(-1, 3).astype(np.float32)
    lw = (np.asarray(light, np.float32).reshape(-1, 3)
          * lightvec.solid_angles().reshape(-1, 1).astype(np.float32))
    power = lw @ np.asarray(LUMA, np.float32)
    # Exact for the brightest cells that each carry a noticeable share of the power (a lamp's);
    # a smooth light has none and goes wholly through SH. Chosen by share, not by rank alone,
    # so equal cells (a uniform world) never split between the two paths by rounding.
    order = np.argsort(-power, kind="stable")[:exact_cells]
    total = float(np.abs(power).sum())
    chosen = np.zeros(len(power), bool)
    chosen[order[power[order] > exact_share * total]] = True
    exact, rest = np.nonzero(chosen)[0], np.nonzero(~chosen)[0]
    n = normal.reshape(3, -1)
    cos = lobe(d[exact] @ n, None if wrap is None else wrap.reshape(1, -1))  # (cells, h*w)
    out = lw[exact].T @ cos
    if len(rest) and float(np.abs(lw[rest]).max(initial=0.0)) > 0:
        coeff = sh_basis(d[rest].T) @ lw[rest] * SH_BAND[:, None]  # (9, 3)
        out += coeff.T @ sh_basis(n)
    return out.reshape(3, *normal.shape[1:])


def fit_source(image_lum: np.ndarray, bufs: Buffers) -> np.ndarray:
    """Nine SH coefficients of the footage's shading, luminance only: least squares of
    lum / albedo_variation ~ SH(n) . c over the confident foreground, robustly reweighted
    twice (specular highlights and cast shadows are outliers to a smooth irradiance)."""
    alb = luminance(bufs.albedo)
    fg = (bufs.matte > 0.5) & (alb > 0.02) & np.isfinite(image_lum) & (image_lum > 0)
    if int(fg.sum()) < 16:
        return np.array([1.0] + [0.0] * 8, np.float32)
    a_med = float(np.median(alb[fg]))
    y = image_lum[fg] / (alb[fg] / a_med)
    basis = sh_basis(bufs.normal[:, fg]).T.astype(np.float64)  # (N, 9)
    if bufs.transfer is not None:  # what the footage's light cannot reach is not its shading
        c = np.linalg.lstsq(basis, y, rcond=None)[0]
        basis = basis * occlusion(source_sh(c), bufs.transfer[:, fg], basis @ c)[:, None]
    ridge = 1e-3 * np.eye(9)
    ridge[0, 0] = 0.0
    return huber_lstsq(basis, y, ridge).astype(np.float32)


def huber_lstsq(basis: np.ndarray, y: np.ndarray, ridge: np.ndarray, rounds: int = 3):
    """Coefficients c of y ~ basis @ c ((N, k) basis, (N,) y), least squares reweighted
    ``rounds`` times by Huber's weights (2 robust sigmas), with ``ridge`` (k, k) times the
    weights' sum added to the normal equations."""
    w = np.ones(len(y))
    c = np.zeros(basis.shape[1])
    for _ in range(rounds):
        bw = basis * w[:, None]
        c = np.linalg.solve(basis.T @ bw + ridge * float(w.sum()), bw.T @ y)
        r = y - basis @ c
        s = 1.4826 * float(np.median(np.abs(r))) + 1e-12
        w = 1.0 / np.maximum(1.0, np.abs(r) / (2.0 * s))  # Huber weights
    return c


def source_sh(c: np.ndarray) -> np.ndarray:
    """(16,) the light's SH coefficients that fit_source's coefficients ``c`` (irradiance on the
    normals: the light's SH up to order 2 times SH_BAND) stand for."""
    sh = np.zeros(TRANSFER_CHANNELS, np.float32)
    sh[:9] = np.asarray(c, np.float32) / SH_BAND
    return sh


def level_colour(image_chw: np.ndarray, lum: np.ndarray, e_src: np.ndarray, skin: np.ndarray):
    """The footage's skin colour as a function of its light's level: each channel's share of
    the luminance fitted as a + b log(shading) over face skin, and the range of log shadings
    it holds for (LEVEL_PERCENTILES); None when the skin is small or lit evenly. Real skin is
    more saturated in shadow (light scattered under it comes out redder, and graded footage
    deepens it), so a shadow the target light fills should take the colour the footage's lit
    skin has, not keep its own."""
    if int(skin.sum()) < 64:
        return None
    x = np.log(np.maximum(e_src[skin], 1e-8)).astype(np.float64)
    if float(x.std()) < LEVEL_MIN_SPREAD:
        return None
    share = image_chw[:, skin] / np.maximum(lum[skin], 1e-8)
    design = np.stack([np.ones_like(x), x], 1)
    coef, *_ = np.linalg.lstsq(design, share.T.astype(np.float64), rcond=None)  # (2, 3)
    lo, hi = np.percentile(x, LEVEL_PERCENTILES)
    return coef.astype(np.float32), float(lo), float(hi)


def level_factor(level, e_src: np.ndarray, e_new: np.ndarray) -> np.ndarray:
    """(3, h, w) the colour change, of unit luminance, from the skin colour the footage shows at
    its shading ``e_src`` to the one it shows at ``e_new`` (level_colour's fit ``level``; levels
    beyond those seen count as the nearest seen), where the new light fills (``e_new`` above
    ``e_src``); none where it darkens. The colour of the footage's shadows comes with its own
    light (a coloured bounce, the grade); a new shadow's warmth comes from the target light's
    own diffusion under the skin (subsurface). Carried into a white lamp's new shadows, the
    footage's turned a whole cheek a saturated red-brown on real footage."""
    coef, lo, hi = level
    xs = np.clip(np.log(np.maximum(e_src, 1e-8)), lo, hi)
    xn = np.maximum(np.clip(np.log(np.maximum(e_new, 1e-8)), lo, hi), xs)
    s = np.maximum(coef[0][:, None, None] + coef[1][:, None, None] * xs[None], 1e-3)
    n = np.maximum(coef[0][:, None, None] + coef[1][:, None, None] * xn[None], 1e-3)
    f = n / s
    return f / np.maximum(luminance(f), 1e-6)[None]


def directionality(c: np.ndarray) -> float:
    """How directional a fitted irradiance is: |band 1| / band 0 of its nine coefficients. The
    full sphere's irradiance of one distant light gives 1.15 and a uniform world 0; fitted over
    the visible half of a head (the robust fit down-weights the lamp's dark side), one lamp gives
    about 0.6-0.7, an overcast sky 0.33, a broad glow over an ambient 0.16."""
    return float(np.linalg.norm(c[1:4])) / max(abs(float(c[0])), 1e-8)


def source_shading(image_lum: np.ndarray, bufs: Buffers, c: np.ndarray,
                   weight: float | None = None, basis: np.ndarray | None = None) -> np.ndarray:
    """(h, w) the footage's diffuse shading: the SH fit ``c`` on the predicted normals (times
    its light's occlusion where the network predicts the transfer), with, on
    face skin, the shading read per pixel (luminance over the albedo variations) blended in log
    space, by up to ``weight`` as the fitted light is directional. Nine coefficients smooth a
    hard source's terminator and nose shadow away, and the ratio then leaves them in the relit
    frame; a soft source keeps the fit, whose errors in the normals cancel against the target's
    rendering on the same normals. Skin only: its albedo is nearly uniform, so what luminance
    over albedo leaves is shading; hair, eyes and clothes keep the fit. ``weight`` defaults to
    PIXEL_SOURCE_WEIGHT (0: the fit alone). ``basis``: sh_basis(bufs.normal), if the caller has
    it."""
    weight = PIXEL_SOURCE_WEIGHT if weight is None else weight
    basis = sh_basis(bufs.normal) if basis is None else basis
    e_fit = np.tensordot(c, basis, axes=(0, 0))
    if bufs.transfer is not None:
        # Occluded light, dark to the bottom of a nostril: the footage shows it diffused under
        # the skin (as the target's, in shade).
        lit = np.maximum(e_fit * occlusion(source_sh(c), bufs.transfer, e_fit), 0.0)
        e_fit = subsurface(lit[None], bufs.face * bufs.matte, *SSS_LUMINANCE)[0]
    fg = bufs.matte > 0.5
    t = weight * min(directionality(c) / PIXEL_SOURCE_DIRECTIONAL, 1.0)
    if t <= 0:
        return e_fit
    read = albedo_reading(image_lum, bufs)
    if read is None:
        return e_fit
    fit = np.maximum(e_fit, 1e-8)
    ok = fg & np.isfinite(read) & (read > 0)
    step = np.log(np.where(ok, read, 1.0) / fit) * np.where(ok, t * bufs.face, 0.0)
    return (fit * np.exp(step)).astype(np.float32)


def albedo_reading(image_lum: np.ndarray, bufs: Buffers) -> np.ndarray | None:
    """(h, w) the footage's shading read per pixel: its luminance over the predicted albedo's
    luminance about its median over the subject (matte above 0.5; the albedo taken as at least
    0.02 of that median); None where there is no subject or no albedo."""
    fg = bufs.matte > 0.5
    if not fg.any():
        return None
    alb = luminance(bufs.albedo)
    a_med = float(np.median(alb[fg]))
    if not a_med > 0:
        return None
    return image_lum / np.maximum(alb / a_med, 0.02)


def albedo_bounded(e_src: np.ndarray, image_lum: np.ndarray, bufs: Buffers,
                   bound: float | None = None) -> np.ndarray:
    """(h, w) the source shading ``e_src``, at least the footage's luminance over the predicted
    albedo variations (about their median over the subject) divided by ``bound`` on the subject
    (matte above 0.5): the shading a pixel must have had for the footage to show it with no
    more than ``bound`` times its predicted albedo. ``bound`` defaults to SOURCE_ALBEDO_BOUND."""
    bound = SOURCE_ALBEDO_BOUND if bound is None else bound
    read = albedo_reading(image_lum, bufs)
    if read is None:
        return e_src
    return np.where(bufs.matte > 0.5, np.maximum(e_src, read / np.float32(bound)),
                    e_src).astype(np.float32)


def change_bounded(e_src: np.ndarray, y_t: np.ndarray, image_lum: np.ndarray, bufs: Buffers,
                   bound: float | None = None) -> np.ndarray:
    """(h, w) the shading the ratio divides by: ``e_src`` where the change ``y_t / e_src``
    (``y_t``: the target's luminance irradiance) is at most its median over the subject (matte
    above 0.5); above it, raised toward albedo_bounded's reading (``bound``) but never so far
    that the change falls below that median. A change brighter than the frame's typical one is
    kept to what the predicted albedo allows; no pixel is darkened below the typical change, so
    what the network's errors cancel between the fit and the target's rendering stays."""
    fg = bufs.matte > 0.5
    if not fg.any():
        return e_src
    typical = float(np.median((y_t / e_src)[fg]))
    if not typical > 0:
        return e_src
    cap = albedo_bounded(e_src, image_lum, bufs, bound)
    return np.maximum(e_src, np.minimum(cap, y_t / np.float32(typical))).astype(np.float32)


# The source light's colour that varies with direction (a warm sun on one side, a blue sky on the
# other) is divided out of the footage where the colour gradient over the face's normals is
# stronger than a face's own: log chromaticity (red and blue over green, after the predicted
# albedo) changing by more than this per unit of normal. Skin's own colour gradient read this way
# (lips and chin redder than the brow, a coloured bounce) measured 0.17-0.35 on the dev footage
# when it was chosen (read then over the whole subject) and 0.04-0.16 on CroppedYale's grey
# photos; the synthetic test set's two-coloured skies reach 1.5 (read over face skin through
# the network's buffers: median 0.34, 95th percentile 1.0). Beyond the threshold only the excess
# is taken as light (soft shrinkage), so a clip's colour never jumps; a per-channel fit without
# it turned real faces red on one side and cyan on the other under a white light.
CHROMA_GRADIENT_MIN = 0.4
# The gradient is read over face skin, whose albedo is nearly uniform, where the crop holds this
# many pixels of it (sampled every other pixel each way), else over the whole subject: the
# predicted albedo of hair and clothes takes on some of the light's colour, and their normals
# are the least certain. On the card's synthetic test set (the network's buffers of the 128-pixel
# frames, bench.renderer_ceiling's "network buffers" row) rmse_level_fit 0.0555 -> 0.0545, read
# unshrunk 0.0557 -> 0.0529 (the light stage's own colour ratio: 0.0518). Under
# bench.intrinsic_effects' white source the whole subject read a gradient beyond the threshold
# in over a quarter of its frames (up to 1.0 through the network's buffers, 2.3 through the
# exact ones: a colour that light does not have), the skin at most 0.36. On the dev footage's
# face crops, under their own light, the skin read 0.20-0.46 and the whole subject 0.35-0.47.
CHROMA_MIN_PIXELS = 64


def source_chroma(image_chw: np.ndarray, bufs: Buffers,
                  threshold: float | None = None) -> np.ndarray | None:
    """(3, h, w) of unit luminance: the directional part of the footage's light colour, or None
    where it is no stronger than a face's own colour gradient (``threshold``). log(red / green)
    and log(blue / green) of the footage over the predicted albedo are fitted, robustly, as
    linear in the normal over the face skin (CHROMA_MIN_PIXELS; else the confident foreground);
    the fit's normal terms, shrunk by ``threshold`` in magnitude, give each pixel's light colour
    about the mean normal of the pixels read
    (the mean colour stays the footage's: a clip's skin tone is not re-graded). ``threshold``
    defaults to CHROMA_GRADIENT_MIN."""
    threshold = CHROMA_GRADIENT_MIN if threshold is None else threshold
    # Every other pixel each way: four coefficients a channel need no more.
    x, alb = image_chw[:, ::2, ::2], bufs.albedo[:, ::2, ::2]
    fg = (bufs.matte[::2, ::2] > 0.5) & (luminance(x) > 1e-6) & (luminance(alb) > 0.02)
    skin = fg & (bufs.face[::2, ::2] > 0.5)
    if int(skin.sum()) >= CHROMA_MIN_PIXELS:
        fg = skin
    if int(fg.sum()) < CHROMA_MIN_PIXELS:
        return None
    logc = np.log(np.maximum(x[:, fg], 1e-8) / np.maximum(alb[:, fg], 1e-4))
    n = bufs.normal[:, ::2, ::2][:, fg]
    mean_n = n.mean(1, dtype=np.float64).astype(np.float32)
    design = np.concatenate([np.ones((n.shape[1], 1)), (n - mean_n[:, None]).T], 1)
    grad = np.zeros((3, 3))
    for c in (0, 2):  # robust: highlights and odd pixels are outliers
        grad[c] = huber_lstsq(design, (logc[c] - logc[1]).astype(np.float64),
                              1e-9 * np.eye(4))[1:]
    size = float(np.linalg.norm(grad))
    if not size > threshold:
        return None
    grad *= 1.0 - threshold / size
    t = np.exp(np.tensordot(grad.astype(np.float32), bufs.normal - mean_n[:, None, None],
                            axes=(1, 0)))
    return (t / np.maximum(luminance(t), 1e-6)[None]).astype(np.float32)


def unlit_share(rel: np.ndarray, directional: float) -> np.ndarray:
    """(h, w) in [0, 1]: how far a pixel is rendered from its albedo rather than relit by the
    ratio, from its source shading over the subject's 90th percentile (``rel``) and the fitted
    light's directionality (UNLIT)."""
    lo, hi = UNLIT
    d = np.clip((hi - rel) / (hi - lo), 0.0, 1.0)
    return (d * d * (3.0 - 2.0 * d) * min(directional / PIXEL_SOURCE_DIRECTIONAL, 1.0)).astype(
        np.float32)


def skin_radiance(image_chw: np.ndarray, lum: np.ndarray, bufs: Buffers, skin: np.ndarray,
                  unit: float, level=None) -> np.ndarray:
    """(3, h, w) the footage's radiance per unit of irradiance from the predicted albedo: the
    skin's own colour in the footage times ``unit`` (radiance per unit irradiance of the median
    skin) times the albedo's variation about the skin's median. The colour is that of the
    footage's well-lit skin where level_colour's fit ``level`` says it (its upper level), else
    the skin's median chromaticity."""
    if level is not None:
        coef, _, hi = level
        chroma = np.maximum(coef[0] + coef[1] * np.float32(hi), 1e-3)
        chroma = chroma / float(np.asarray(LUMA, np.float32) @ chroma)
    else:
        chroma = np.median(image_chw[:, skin] / np.maximum(lum[skin], 1e-12), axis=1)
    ref = np.maximum(np.median(bufs.albedo[:, skin], axis=1), 1e-6)
    return (unit * chroma / ref)[:, None, None] * bufs.albedo


def blur_radius(sigma: float) -> int:
    """How far ``gaussian_blur`` reaches: its taps are cut at three sigma."""
    return max(1, int(math.ceil(3.0 * sigma)))


def blur_taps(sigma: float) -> np.ndarray:
    """(2 blur_radius + 1,) float64: ``gaussian_blur``'s taps, offsets -r .. r, summing to 1."""
    r = blur_radius(sigma)
    k = np.exp(-0.5 * (np.arange(-r, r + 1) / sigma) ** 2)
    return k / k.sum()


@functools.lru_cache(maxsize=32)
def blur_matrix(n: int, sigma: float) -> np.ndarray:
    """(n, n) the Gaussian blur of ``gaussian_blur`` along one axis of n samples as a matrix:
    taps cut at three sigma, the taps that fall past an edge on its edge sample. Read-only
    (cached)."""
    r = blur_radius(sigma)
    k = blur_taps(sigma)
    i = np.arange(n)
    d = i[None, :] - i[:, None]  # column minus row: the tap's offset
    m = np.where(np.abs(d) <= r, k[np.clip(d + r, 0, 2 * r)], 0.0)
    below = np.concatenate([[0.0], np.cumsum(k)])  # below[j]: the taps of offset < j - r
    m[:, 0] += below[np.clip(r - i, 0, 2 * r + 1)]  # offsets -r .. -i - 1 fall before sample 0
    m[:, n - 1] += below[-1] - below[np.clip(n - i + r, 0, 2 * r + 1)]  # offsets > n - 1 - i
    m = m.astype(np.float32)
    m.flags.writeable = False
    return m


# Up to this radius (blur_radius) gaussian_blur adds its taps (tap_blur): the subsurface
# diffusion's narrower channels and the matte's blurs. Wider blurs take the matrix products by
# bands (banded_blur), BAND_BLOCK rows of the output at a time: the whole products' values for
# a fraction of their work. bench.intrinsic_speed times the ways against each other at radius
# 2, at this radius and just beyond it.
TAPS_RADIUS = 4
BAND_BLOCK = 32


@functools.lru_cache(maxsize=32)
def _blur_taps32(sigma: float) -> tuple[float, ...]:
    """blur_taps(sigma) rounded to float32, as gaussian_blur adds them (cached)."""
    return tuple(float(v) for v in blur_taps(sigma).astype(np.float32))


def _edge_padded(a: np.ndarray, axis: int, r: int) -> np.ndarray:
    """``a`` extended by ``r`` samples at both ends of ``axis``, each end repeating its edge
    sample (np.pad's "edge" mode, without its overhead)."""
    n = a.shape[axis]
    shape = list(a.shape)
    shape[axis] = n + 2 * r
    p = np.empty(shape, a.dtype)
    at = [slice(None)] * a.ndim

    def put(dst: slice, src: slice) -> None:
        at[axis] = src
        value = a[tuple(at)]
        at[axis] = dst
        p[tuple(at)] = value

    put(slice(r, r + n), slice(None))
    put(slice(0, r), slice(0, 1))
    put(slice(r + n, n + 2 * r), slice(n - 1, n))
    return p


def gaussian_blur(a: np.ndarray, sigma: float) -> np.ndarray:
    """(..., h, w) separable Gaussian blur over the last two axes (edges extended), sigma in
    pixels, cut at three sigma: two matrix products (blur_matrix) by bands (banded_blur), far
    cheaper than a tap loop at the working size, or for a narrow blur (TAPS_RADIUS) its few
    taps added along each axis (tap_blur; the same blur)."""
    a = np.asarray(a, np.float32)
    if blur_radius(sigma) > TAPS_RADIUS:
        return banded_blur(a, sigma)
    return tap_blur(a, sigma)


def banded_blur(a: np.ndarray, sigma: float) -> np.ndarray:
    """gaussian_blur by the matrices blur_matrix gives, BAND_BLOCK rows (then columns) of the
    output at a time from the input samples within reach of them: the only ones their rows of
    the matrix weigh (an edge's extended taps fall on samples the block reaches too)."""
    a = np.asarray(a, np.float32)
    h, w = a.shape[-2:]
    r = blur_radius(sigma)
    mh, mw = blur_matrix(h, sigma), blur_matrix(w, sigma)
    tmp = np.empty(a.shape, np.float32)
    for out_rows, reach in _bands(h, r):
        np.matmul(mh[out_rows, reach], a[..., reach, :], out=tmp[..., out_rows, :])
    out = np.empty(a.shape, np.float32)
    for out_cols, reach in _bands(w, r):
        np.matmul(tmp[..., :, reach], mw[out_cols, reach].T, out=out[..., :, out_cols])
    return out


def _bands(n: int, r: int):
    """Yield (the slice of up to BAND_BLOCK output samples, the slice of the input samples
    within ``r`` of them) along an axis of ``n``."""
    for i0 in range(0, n, BAND_BLOCK):
        i1 = min(n, i0 + BAND_BLOCK)
        yield slice(i0, i1), slice(max(0, i0 - r), min(n, i1 + r))


def tap_blur(a: np.ndarray, sigma: float) -> np.ndarray:
    """gaussian_blur by its taps added along each axis, the two at equal offsets summed before
    their one multiply."""
    a = np.asarray(a, np.float32)
    h, w = a.shape[-2:]
    r = blur_radius(sigma)
    k = _blur_taps32(sigma)
    for axis, n in ((a.ndim - 2, h), (a.ndim - 1, w)):
        p = _edge_padded(a, axis, r)  # the taps past an edge on its edge sample
        cut = [slice(None)] * a.ndim

        def shifted(i: int) -> np.ndarray:
            cut[axis] = slice(i, i + n)
            return p[tuple(cut)]

        out = np.multiply(shifted(r), np.float32(k[r]))
        tmp = np.empty_like(out)
        for i in range(r):  # offsets -(r - i) and r - i share a tap
            np.add(shifted(i), shifted(2 * r - i), out=tmp)
            np.multiply(tmp, np.float32(k[i]), out=tmp)
            np.add(out, tmp, out=out)
        a = out
    return a


def subsurface(irr: np.ndarray, skin: np.ndarray, alphas=SSS_ALPHA,
               sigmas_cm=SSS_SIGMA_CM) -> np.ndarray:
    """(3, h, w) irradiance diffused under the skin: per channel, SSS_ALPHA of it replaced by its
    Gaussian average over the skin (weights ``skin`` (h, w), normalised, so hair and eyes do not
    bleed in), SSS_SIGMA_CM wide at the scale SSS_FACE_CM gives the skin's size; with three
    channels, the colour is the one diffusion gives at the scale SSS_CHROMA_FACE_CM gives, and
    the light the wider scale adds beyond it has the light's colour (the luminance stays
    SSS_FACE_CM's). A terminator turns soft and a little warm, as on skin; off the skin nothing
    changes. (What cast shadows take away diffuses apart: cast_subsurface.) ``alphas``,
    ``sigmas_cm``: other channels' (SSS_LUMINANCE: one luminance channel)."""
    area = float(skin.sum())
    if area < 16:
        return irr
    sk = skin > 0
    bounds = skin_bounds(sk)
    out = _diffuse(irr, skin, bounds, alphas, sigmas_cm, math.sqrt(area) / SSS_FACE_CM)
    if irr.shape[0] != 3:
        return out
    hue = _diffuse(irr, skin, bounds, alphas, sigmas_cm, math.sqrt(area) / SSS_CHROMA_FACE_CM)
    y_out, y_hue = luminance(out), luminance(hue)
    # The light the wider diffusion adds beyond the narrower one stands in for the terminator the
    # predicted normals draw too sharp, not for light that travelled under the skin: it takes
    # the light's colour on the skin. (The narrower diffusion's colour scaled up to the wider
    # one's luminance drew a pure red line along a white lamp's shadow side on real footage,
    # where only red reaches at the narrower scale.)
    tone = irr[:, sk].mean(1)
    tone = tone / max(float(luminance(tone)), 1e-12)
    extra = y_out - y_hue
    return np.where(extra[None] >= 0, hue + extra[None] * tone[:, None, None],
                    hue * (y_out / np.maximum(y_hue, 1e-12))[None]).astype(irr.dtype)


CAST_SHARE = 1e-3  # of the largest: less of a cast shadow's loss is not worth diffusing


def cast_subsurface(loss: np.ndarray, skin: np.ndarray) -> np.ndarray:
    """(3, h, w) the irradiance cast shadows take away (``loss``) diffused under the skin
    (weights ``skin`` (h, w)) as subsurface diffuses it, at the light stage's own scale
    (SSS_CHROMA_FACE_CM) rather than SSS_FACE_CM's twice as wide: the shadow's edge already has
    its penumbra, and the wider diffusion is for the terminator of the predicted normals. Only
    the window the loss reaches is computed (a shadow covers part of the face)."""
    area = float(skin.sum())
    # The penumbra's blur leaves a faint tail far from the shadow: it is taken away undiffused.
    rows, cols = np.nonzero((loss > CAST_SHARE * float(loss.max())).any(0) & (skin > 0))
    if area < 16 or not rows.size:
        return loss
    px_per_cm = math.sqrt(area) / SSS_CHROMA_FACE_CM
    # The diffusion's reach around the loss: _diffuse widens the window by as much again, so
    # every pixel the loss reaches sees all the skin its blur weighs.
    r = blur_radius(max(SSS_SIGMA_CM) * px_per_cm)
    sb = skin_bounds(skin > 0)
    bounds = (max(int(rows.min()) - r, sb[0]), min(int(rows.max()) + 1 + r, sb[1]),
              max(int(cols.min()) - r, sb[2]), min(int(cols.max()) + 1 + r, sb[3]))
    return _diffuse(loss, skin, bounds, SSS_ALPHA, SSS_SIGMA_CM, px_per_cm)


def skin_bounds(sk: np.ndarray) -> tuple[int, int, int, int]:
    """The bounding box of ``sk`` (h, w) bool, not empty: (row start, row end, column start,
    column end), ends exclusive."""
    rows, cols = np.nonzero(sk)
    return int(rows.min()), int(rows.max()) + 1, int(cols.min()), int(cols.max()) + 1


def _diffuse(irr: np.ndarray, skin: np.ndarray, bounds, alphas, sigmas_cm,
             px_per_cm: float) -> np.ndarray:
    """subsurface's diffusion at one scale; ``bounds``: the skin's bounding box (skin_bounds)."""
    sigmas = [c * px_per_cm for c in sigmas_cm]
    # Only the skin's bounding box changes: work there (a wide frame's grid is mostly not skin).
    r = blur_radius(max(sigmas))
    h, w = skin.shape
    y0, y1 = max(bounds[0] - r, 0), min(bounds[1] + r, h)
    x0, x1 = max(bounds[2] - r, 0), min(bounds[3] + r, w)
    win = (slice(None), slice(y0, y1), slice(x0, x1))
    sk = skin[win[1:]].astype(np.float32)
    out = irr.copy()
    for ch, (alpha, sigma) in enumerate(zip(alphas, sigmas)):
        if sigma < 0.3:  # narrower than a pixel: nothing to diffuse at this size
            continue
        e = irr[ch][win[1:]]
        num, den = gaussian_blur(np.stack([e * sk, sk]), sigma)
        a = alpha * sk
        out[ch][win[1:]] = e * (1.0 - a) + a * (num / np.maximum(den, 1e-6))
    return out


def march(field: np.ndarray, fill: float, yy: np.ndarray, xx: np.ndarray, step, first: int,
          last: int):
    """Yield (t, ``field``'s values t pixels from each of the pixels (``yy``, ``xx``) along the
    image-plane unit ``step`` (x right, y down)) for t from ``first`` to ``last``; beyond the
    field the values are ``fill``. The field sits on a canvas padded past the march's reach, so
    each step is one flat offset; pixels are whole numbers, so rounding the step (half up)
    rounds the sample's position."""
    h, w = field.shape
    pad = last + 1
    canvas = np.full((h + 2 * pad, w + 2 * pad), fill, np.float32)
    canvas[pad:pad + h, pad:pad + w] = field
    flat = canvas.reshape(-1)
    base = (yy + pad) * canvas.shape[1] + (xx + pad)
    ux, uy = step
    for t in range(first, last + 1):
        off = math.floor(uy * t + 0.5) * canvas.shape[1] + math.floor(ux * t + 0.5)
        yield t, flat[base + off]


def marched(matte: np.ndarray, lit: np.ndarray | None = None) -> np.ndarray:
    """(h, w) bool: the pixels ``shadow`` marches, the subject's (only the subject receives
    shadows here) that face the light (``lit`` positive, where given). Its visibility elsewhere
    is 1, meaning "not asked" (``penumbra``'s ``turned``)."""
    m = matte > 0.5
    return m if lit is None else m & (lit > 0)


def shadow(height: np.ndarray, matte: np.ndarray, direction: np.ndarray,
           steps: int = SHADOW_STEPS, lit: np.ndarray | None = None, distance: bool = False):
    """(h, w) visibility in [0, 1] toward a distant light: march from each subject pixel toward
    the light in the image plane and compare the ray's height with the predicted height there.
    ``lit`` (h, w): march only where it is positive (pixels facing the light). ``distance``:
    also return (h, w) how many pixels away the occluder lies (where it stands highest above
    the ray; 0 where nothing occludes), for ``penumbra``."""
    h, w = height.shape
    dx, dy, dz = (float(v) for v in direction)
    lat = math.hypot(dx, dy)
    vis = np.ones((h, w), np.float32)
    if lat < 1e-3:  # light along the view axis: its shadows hide behind the subject
        return (vis, np.zeros_like(vis)) if distance else vis
    ux, uy = dx / lat, -dy / lat         # image x right, image y down
    rise = dz / lat                       # height gained per pixel travelled toward the light
    # Off the subject (and off the crop) the height is far below any ray: it never occludes.
    field = np.where(matte > 0.5, height, -1e6)
    yy, xx = np.nonzero(marched(matte, lit))
    ray0 = field[yy, xx] + np.float32(SHADOW_BIAS)
    occl = np.zeros(len(yy), np.float32)
    at = np.zeros(len(yy), np.float32)
    for t, sample in march(field, -1e6, yy, xx, (ux, uy), 2, steps):
        above = sample - ray0
        above -= np.float32(rise * t)
        if distance:
            at[above > occl] = t
        np.maximum(occl, above, out=occl)
    vis[yy, xx] = 1.0 - np.clip(occl / np.float32(SHADOW_SOFTNESS), 0.0, 1.0)
    if not distance:
        return vis
    dist = np.zeros_like(vis)
    dist[yy, xx] = at
    return vis, dist


# Face skin turned this far from a lamp (n.l below this, fading in from it to 0) stands for the
# head's dark side in behind_head.
DARK_SKIN_COS = 0.2


def behind_head(cos: np.ndarray, face: np.ndarray, wrap: np.ndarray, direction: np.ndarray,
                steps: int = SHADOW_STEPS) -> np.ndarray:
    """(h, w) visibility of the hair (``wrap``: hair_share) to a distant light where the head
    stands between them (``cos``: n.l toward it, per pixel): march from each hair pixel toward
    the light in the image plane; where the march crosses face skin turned away from the light
    (DARK_SKIN_COS), the head stands between that hair and the light, and the hair's share of
    the pixel is in its shadow. Hair framing a face sits behind the cheeks, deeper than the
    network's height and transport put it on real footage, so shadow's march passed over the
    face and the hair's wrapped lobe (HAIR_WRAP) lit the far side's hair beside a cheek in
    shadow: a bright curtain beside a black stripe. On the light stage's renders the network's
    transport already occludes such hair, so there this changes little: the card's test set
    rmse_level_fit 0.0573 -> 0.0572 (training.eval.evaluate); CroppedYale's crops, which hold
    little hair, unchanged."""
    out = np.ones(face.shape, np.float32)
    dx, dy = float(direction[0]), float(direction[1])
    lat = math.hypot(dx, dy)
    yy, xx = np.nonzero(wrap > 0.01)
    if lat < 1e-3 or len(yy) == 0:
        return out
    dark = np.clip(face, 0.0, 1.0) * np.clip(1.0 - cos / np.float32(DARK_SKIN_COS), 0.0, 1.0)
    occl = np.zeros(len(yy), np.float32)
    for _, sample in march(dark, 0.0, yy, xx, (dx / lat, -dy / lat), 1, steps):
        np.maximum(occl, sample, out=occl)
    out[yy, xx] = 1.0 - wrap[yy, xx] * occl
    return out


def penumbra(vis: np.ndarray, dist: np.ndarray, turned: np.ndarray | None = None) -> np.ndarray:
    """(h, w) ``vis`` (shadow's) with its edges softened by a Gaussian that widens with the
    distance to the occluder (``dist``, shadow's; PENUMBRA): sharp beside the nose, soft where
    the jaw's shadow reaches the neck. Each pixel takes the occluder distance of the shadow
    around it (a normalised blur over PENUMBRA_REACH), so a shadow's lit edge widens as its dark
    side does.

    ``turned`` (h, w) bool: the subject's pixels turned away from the light, which shadow does not
    march; its visibility of 1 there means "not asked", so each takes the visibility of the asked
    pixels beside it before the blur. Blurred in as lit, they lit the edge of every cast shadow
    that meets the head's dark side: on dev footage under a key lamp the far ear, in the head's
    shadow but a few working pixels wide beside a cheek turned away, kept much of the footage's
    light. Elsewhere it changes little (bench.intrinsic_effects): under 0.0005 on the held-out
    identities; on long-haired ones the exact buffers' key lamps lose 0.002-0.005 and the network's
    up to 0.0012; a sunny HDRI's shadows come out a little colder (exact buffers' shadow warmth
    -0.043 -> -0.053, the stage's -0.021); CroppedYale's test subjects 20.36 -> 20.37 dB
    (training.eval.yale). Taking them as shadow instead (and the backdrop left out too) also
    darkened lit skin within the blur's reach of the terminator: CroppedYale's tune subjects liked
    that (training.eval.yale --split tune: top/bottom 0.809 -> 0.824) but the light stage's shadows
    came out too dark and, under a sunny HDRI, too cold (bench.intrinsic_effects, exact buffers:
    key lamps 0.1103 / 0.1149 -> 0.1137 / 0.1184, long hair 0.1638 -> 0.1760; shadow warmth -0.043
    -> -0.099 against the stage's -0.021), so it is not done."""
    dark = 1.0 - vis  # the cast shadow's, whose occluder distances set the width
    if not (dark > 0).any():
        return vis
    num, den = gaussian_blur(np.stack([dist * dark, dark]), PENUMBRA_REACH)
    lo, per, hi = PENUMBRA
    sigma = np.clip(lo + per * num / np.maximum(den, 1e-6), lo, hi)
    # Only the levels the widest sigma reaches: a pair's upper blur counts above its lower sigma.
    widest = float(sigma.max())
    levels = PENUMBRA_LEVELS[:1 + next((i for i, s in enumerate(PENUMBRA_LEVELS) if s >= widest),
                                       len(PENUMBRA_LEVELS) - 1)]
    if turned is not None:
        # Within the narrowest level's reach: leaving them out of every level's blur (normalised
        # over the rest) darkened the far ear as much but took the penumbra 2.1 times as long as
        # the plain blur, where this takes 1.3 times (bench.intrinsic_speed's penumbra rows).
        vis = np.where(turned, _within(vis, (~turned).astype(np.float32), levels[0]), vis)
    blurred = [gaussian_blur(vis, s) for s in levels]
    out = blurred[0]
    for a, b, sa, sb in zip(blurred[:-1], blurred[1:], levels[:-1], levels[1:]):
        t = np.clip((sigma - sa) / (sb - sa), 0.0, 1.0)
        out = np.where(sigma > sa, a + t * (b - a), out)
    return out.astype(np.float32)


def _within(x: np.ndarray, keep: np.ndarray, sigma: float) -> np.ndarray:
    """(h, w) ``x`` blurred by a Gaussian over the pixels ``keep`` weighs (a normalised blur);
    ``x`` itself where the weights around a pixel are nil."""
    num, den = gaussian_blur(np.stack([x * keep, keep]), sigma)
    return np.where(den > 1e-3, num / np.maximum(den, 1e-3), x)


def height_scale(bufs: Buffers) -> float:
    """How much steeper the predicted height is than the predicted normals say (least squares of
    its image gradient against -n_x / n_z and n_y / n_z over the confident, camera-facing
    subject). The two are predicted separately; the shading follows the normals, so the
    shadows' height is brought to the normals' slopes (the network's heights ran 1.2-1.6 times
    too steep on real footage)."""
    n, h = bufs.normal, bufs.height
    m = (bufs.matte > 0.9) & (n[2] > 0.3)
    px = -n[0] / np.maximum(n[2], 1e-3)
    py = n[1] / np.maximum(n[2], 1e-3)  # image y runs down, the normal's y up
    m &= (np.abs(px) < 3.0) & (np.abs(py) < 3.0)
    if int(m.sum()) < 32:
        return 1.0
    gx, gy = np.gradient(h, axis=1)[m], np.gradient(h, axis=0)[m]
    num = float((gx * px[m]).sum() + (gy * py[m]).sum())
    den = float((px[m] ** 2).sum() + (py[m] ** 2).sum())
    return float(np.clip(num / den, 0.3, 3.0)) if den > 0 and num > 0 else 1.0


# The cast shadows' height (shadow_height) corrects the predicted height's slope between two
# neighbouring pixels to the normals' where both face the camera (n_z above SHADOW_GRAZING,
# slopes under SHADOW_SLOPE_MAX pixels of height per pixel) and the predicted height steps less
# than SHADOW_STEP between them; elsewhere the predicted height's own step stands (a jaw over the
# neck, an ear before the hair, which no normal holds).
SHADOW_GRAZING = 0.05
SHADOW_SLOPE_MAX = 3.0
SHADOW_STEP = 1.5
# Over the face skin the shadows' height keeps SHADOW_DETAIL times its detail finer than a Gaussian
# of SHADOW_DETAIL_SIGMA working-size pixels (the nose, the brows over the eye sockets, the lips),
# faded in over SHADOW_DETAIL_BLEND pixels from the skin's edge. The network draws that detail too
# flat, and the flatness is its height's, not its normals': on the light stage's held-out heads
# (python -m bench.height_detail, median of 24 frames, before portrait.NORMAL_DETAIL raised the
# normals' detail) its shadows' height holds 0.53 of the exact height's detail finer than 6 pixels
# (0.45 of that finer than 4), while its normals over the exact height hold 0.98 and the exact
# normals over its height 0.71. Real faces it draws flatter still, and there its normals too: on
# CroppedYale's tune subjects' frontal photos its shadows' height holds 0.47 of the detail finer
# than 6 pixels that photometric stereo's normals give, its normals 0.66 (python -m
# training.eval.yale_normals --onnx models/relight-portrait.onnx --relief; test subjects 0.46 and
# 0.69). The nose's sides rise about as steeply as a lamp 35 degrees to the side and 15 up (the ray
# climbs 1.3 pixels of height a pixel), so at 2.2 times the detail finer than 4 pixels no nose
# shadow fell on yaleB09 lit so; at 3.0 times the detail finer than 6 a narrow one falls beside the
# nose. Marched at 3.0 times the detail finer than 6 pixels (1.10 of the exact detail on the light
# stage's heads), against 2.2 times that finer than 4: CroppedYale tune subjects (36 pairs each,
# paired) 20.23 -> 20.34 dB (one light 17.12 -> 17.22, few 19.93 -> 20.06, HDRIs 23.64 -> 23.73),
# top/bottom +0.003 (5-95% -0.001 to +0.010); the synthetic test set's rmse_level_fit 0.05763 ->
# 0.05787 (one thread, a 2-core Intel Xeon VM), and on the effects bench ("auto") the network's
# buffers under the top lamp 0.3195 -> 0.3117 but under the key lamps 0.2238 / 0.2127 -> 0.2258 /
# 0.2165 and the sunniest HDRI 0.1897 -> 0.1913: the light stage's heads, which the network draws
# less flat than real faces, are marched a little deeper than they are. With the normals' detail
# raised too (portrait.NORMAL_DETAIL), the product's buffers march 1.41 of it
# (bench.height_detail). 2.5 times the detail finer than 8 read 20.31 dB, 0.05783; 3.0 finer than 8
# 20.36 dB but 0.05807 (1.28 of the exact detail); 4.0 finer than 8 20.36 dB, top/bottom -0.001,
# and a sphere taken as face skin shadowed itself where n.l is 0.2; 3.0 finer than 12 20.32 dB. The
# light stage's exact height is marched as it is (shade's relief 1). A sphere taken as face skin
# still shadows none of itself where n.l is above 0.2; its raised rim takes some light at grazing.
SHADOW_DETAIL = 3.0
SHADOW_DETAIL_SIGMA = 6.0
SHADOW_DETAIL_BLEND = 2.0


@functools.lru_cache(maxsize=8)
def _dct_matrices(n: int) -> tuple[np.ndarray, np.ndarray]:
    """(n, n) float32: the unnormalised DCT-II (row k: cos(pi k (2m + 1) / 2n)) and its inverse.
    As matrix products they ran three times as fast as numpy's FFT (in double precision, with
    Makhoul's reordering) at 128 pixels, one thread, on a 2-core Intel Xeon VM."""
    k, m = np.arange(n)[:, None], np.arange(n)[None, :]
    c = np.cos(np.pi * k * (2 * m + 1) / (2 * n))
    w = np.full(n, 2.0 / n)
    w[0] = 1.0 / n
    return c.astype(np.float32), (c.T * w[None, :]).astype(np.float32)


@functools.lru_cache(maxsize=8)
def _neumann_eigenvalues(h: int, w: int) -> np.ndarray:
    lam = ((2.0 * np.cos(np.pi * np.arange(h) / h) - 2.0)[:, None]
           + (2.0 * np.cos(np.pi * np.arange(w) / w) - 2.0)[None, :])
    lam[0, 0] = 1.0  # the mean is free; poisson sets it to 0
    return lam.astype(np.float32)


def poisson(fx: np.ndarray, fy: np.ndarray) -> np.ndarray:
    """(h, w) float32 the field whose forward differences best fit ``fx`` (h, w - 1: f[:, x + 1]
    - f[:, x]) and ``fy`` (h - 1, w) in least squares, of mean 0: the Poisson equation with
    reflecting edges, solved exactly in the DCT's basis (its eigenvectors)."""
    h, w = fx.shape[0], fy.shape[1]
    div = np.zeros((h, w), np.float32)
    div[:, :-1] += fx
    div[:, 1:] -= fx
    div[:-1] += fy
    div[1:] -= fy
    (ch, ih), (cw, iw) = _dct_matrices(h), _dct_matrices(w)
    c = (ch @ div @ cw.T) / _neumann_eigenvalues(h, w)
    c[0, 0] = 0.0
    return ih @ c @ iw.T


def shadow_height(bufs: Buffers, relief: float | None = None) -> np.ndarray:
    """(h, w) the height, in pixels, over which the cast shadows are marched: the predicted height
    (height_scale brings it to the normals' slopes) plus the correction, integrated by poisson,
    that gives it the normals' slopes wherever they can say (SHADOW_STEP). The shading follows
    the normals, so the shadows follow the same shape: the brow's overhang that darkens the eye
    socket under a high light is in the normals before it is in the height. Where the normals
    cannot say, and off the subject, the height's own differences stand, so its steps and its
    standing out from the backdrop are kept. Over the predicted height alone, cast shadows
    under CroppedYale's real normals (photometric stereo's, the network's other buffers kept)
    answered the target's up/down balance at 0.818 on the tune subjects; with this correction
    0.878 (0.869 -> 0.879 by rank; training.eval.yale_normals --split tune --relight --pairs
    36). The network's own normals read the same either way (0.843, 0.841). Integrating the
    normals' slopes with the height's steps on the subject alone, its outline held at the
    backdrop's level, read 0.905, but the least squares then flattened the steps: the light
    stage's top light lost most of the jaw's shadow on the neck (bench.intrinsic_effects,
    "auto": exact buffers 0.1716 -> 0.1812, the network's 0.3196 -> 0.3434), where this keeps
    them (0.1714, 0.3255). Keeping only the correction's detail (less its Gaussian blur over
    the subject, sigma 8 or 16 pixels) read 0.857 and 0.862. Over the face skin the detail
    finer than SHADOW_DETAIL_SIGMA is then ``relief`` times the network's (default
    SHADOW_DETAIL; 1: as the network draws it)."""
    n = bufs.normal
    nz = np.maximum(n[2], 1e-3)
    p, q = -n[0] / nz, n[1] / nz  # dh/dx and dh/dy: image y runs down, the normal's y up
    fg = bufs.matte > 0.5
    ok = fg & (n[2] > SHADOW_GRAZING) & (np.abs(p) < SHADOW_SLOPE_MAX) & (
        np.abs(q) < SHADOW_SLOPE_MAX)
    h = (bufs.height / height_scale(bufs)).astype(np.float32)
    dx, dy = np.diff(h, axis=1), np.diff(h, axis=0)
    fx = np.where(ok[:, 1:] & ok[:, :-1] & (np.abs(dx) < SHADOW_STEP),
                  0.5 * (p[:, 1:] + p[:, :-1]) - dx, 0.0)
    fy = np.where(ok[1:] & ok[:-1] & (np.abs(dy) < SHADOW_STEP), 0.5 * (q[1:] + q[:-1]) - dy, 0.0)
    h = h + poisson(fx, fy)  # both float32
    relief = SHADOW_DETAIL if relief is None else float(relief)
    if relief == 1.0:
        return h
    return skin_detail_raised(h, bufs, relief, SHADOW_DETAIL_SIGMA, SHADOW_DETAIL_BLEND)


def skin_detail_raised(x: np.ndarray, bufs: Buffers, gain: float, sigma: float,
                       blend: float) -> np.ndarray:
    """``x`` ((h, w) or (C, h, w), float32) with its detail finer than a Gaussian of ``sigma``
    pixels raised ``gain`` times over the face skin (face and matte above 0.5), faded in over
    ``blend`` pixels from the skin's edge: the shadows' height's relief (shadow_height) and the
    normals' (portrait.deepened)."""
    skin = gaussian_blur(((bufs.face > 0.5) & (bufs.matte > 0.5)).astype(np.float32), blend)
    return x + np.float32(gain - 1.0) * skin * (x - gaussian_blur(x, sigma))


def specular(normal: np.ndarray, direction: np.ndarray,
             roughness: float = SKIN_ROUGHNESS, f0: float = SKIN_F0) -> np.ndarray:
    """(h, w) GGX reflectance x cosine toward a distant light, viewer along +Z (orthographic
    portrait crop): radiance per unit irradiance, as the light stage's skin."""
    v = np.array([0.0, 0.0, 1.0], np.float32)
    d = np.asarray(direction, np.float32)
    hv = d + v
    hv = hv / max(float(np.linalg.norm(hv)), 1e-8)
    nl = np.maximum(dot3(d, normal), 0.0)
    nv = np.maximum(normal[2], 1e-3)
    nh = np.maximum(dot3(hv, normal), 0.0)
    lh = max(float(d @ hv), 0.0)
    a2 = (roughness * roughness) ** 2
    dist = a2 / (math.pi * (nh * nh * (a2 - 1.0) + 1.0) ** 2)
    smith = 0.5 / np.maximum(nl * np.sqrt(nv * nv * (1 - a2) + a2) + nv * np.sqrt(nl * nl * (1 - a2) + a2),
                             1e-6)
    fres = f0 + (1.0 - f0) * (1.0 - lh) ** 5
    return (dist * smith * fres * nl).astype(np.float32)


@dataclass(frozen=True)
class Shading:
    """The change to apply, at the working size."""
    ratio: np.ndarray     # (3, h, w) multiplies the footage
    highlight: np.ndarray  # (3, h, w) added, in the footage's units: specular highlights and
    # the skin the footage left unlit, rendered from its albedo (unlit_share)
    plan: Plan
    unit: float = 1.0     # the footage's skin radiance per unit of fitted shading (its units)


def shade(image_chw: np.ndarray, bufs: Buffers, light: np.ndarray, effects: Plan | None = None,
          keep_exposure: bool = True, source: np.ndarray | None = None,
          relief: float | None = None, source_colour: np.ndarray | None = None) -> Shading:
    """The ratio and highlight that relight ``image_chw`` (the crop at the working size, linear)
    to ``light``. ``keep_exposure``: the subject keeps the footage's mean luminance, so the light
    sets direction, colour and contrast (the artist's default); without it the ratio is left as
    the light's power makes it (twice the light, twice the output). ``source``: the footage's
    own diffuse shading where it is known (a render's: what the benches measure the estimate
    against), (h, w) luminance or (3, h, w) per channel, in place of the estimate from the
    footage (source_shading, source_chroma). ``source_colour``: with ``source`` None, the
    footage's light colour where it is known, (3, h, w) of unit luminance, in place of
    source_chroma's estimate (the shading's level still estimated). ``relief``: shadow_height's,
    the multiple of the face skin's relief the cast shadows are marched over (default
    SHADOW_DETAIL, which makes up for the network's flat relief; 1 for buffers whose height is
    exact)."""
    light = np.asarray(light, np.float32)
    effects = plan(light) if effects is None else effects
    lum = luminance(image_chw)
    c = fit_source(lum, bufs)
    basis = sh_basis(bufs.normal)
    tint = None  # the footage's light colour that varies over the face (source_chroma)
    if source is None:
        e_src = source_shading(lum, bufs, c, basis=basis)  # (h, w) luminance shading
        tint = (source_chroma(image_chw, bufs) if source_colour is None
                else np.asarray(source_colour, np.float32))
    elif source.ndim == 3:
        e_src = luminance(source).astype(np.float32)
        # a channel the source leaves dark keeps a tiny share: its ratio meets RATIO_MAX
        # rather than a division by zero
        tint = np.where(e_src > 0, np.maximum(source, 1e-6 * e_src) / np.maximum(e_src, 1e-30),
                        1.0).astype(np.float32)
    else:
        e_src = np.asarray(source, np.float32)
    fg = bufs.matte > 0.5
    p90 = float(np.percentile(e_src[fg], 90)) if fg.any() else 0.0
    unlit = unlit_share(e_src / p90, directionality(c)) if p90 > 0 else None
    e_src = np.maximum(e_src, max(SOURCE_FLOOR * p90, 1e-8))
    wrap = hair_share(bufs)
    e_t = irradiance(light, bufs.normal, wrap=wrap)  # (3, h, w)
    # The transfer's occlusion (soft: its SH order) darkens what the light cannot reach through
    # the subject; a compact component's hard cast shadow is still screen-space (shadow).
    occl = None
    if bufs.transfer is not None:
        sh = light_sh(light) @ np.asarray(LUMA, np.float32)
        occl = occlusion(sh, bufs.transfer, free_irradiance(sh, basis))
        e_t = e_t * occl[None]
    spec = np.zeros_like(e_t)
    loss = None  # the irradiance the cast shadows take away (diffused apart: cast_subsurface)
    height = shadow_height(bufs, relief) if effects.shadows and effects.components else None
    for comp in effects.components:
        cos = dot3(comp.direction, bufs.normal)
        lam = lobe(cos, wrap)
        e_c = comp.irradiance[:, None, None] * lam[None]
        vis = None
        if effects.shadows:
            vis = penumbra(*shadow(height, bufs.matte, comp.direction, lit=lam, distance=True),
                           turned=marched(bufs.matte) & ~marched(bufs.matte, lam))
            vis = vis * behind_head(cos, bufs.face, wrap, comp.direction)
            cut = (1.0 - vis)[None] * e_c * (1.0 if occl is None else occl[None])
            loss = cut if loss is None else loss + cut
        if effects.specular:
            s = specular(bufs.normal, comp.direction) * (vis if vis is not None else 1.0)
            spec += comp.irradiance[:, None, None] * (s * bufs.face)[None]
    skin_w = bufs.face * bufs.matte
    e_t = subsurface(np.maximum(e_t, 0.0), skin_w)
    if loss is not None:
        e_t = np.maximum(e_t - cast_subsurface(loss, skin_w), 0.0)
    # Bound the ratio relative to its typical value, so the bound does not depend on the light's
    # absolute power (the change stays linear in the light).
    y_t = luminance(e_t)
    typical = float(np.median(y_t[fg])) if fg.any() else 0.0
    norm = float(np.median(e_src[fg])) / typical if typical > 0 else 1.0
    # what the ratio divides by: the footage's shading, raised where it would brighten a pixel
    # beyond the frame's typical change as no predicted albedo allows (change_bounded)
    e_div = e_src if source is not None else change_bounded(e_src, y_t, lum, bufs)
    e_src3 = e_div[None] if tint is None else e_div[None] * tint
    ratio = np.minimum(e_t * np.float32(norm) / e_src3, RATIO_MAX) / np.float32(norm)
    # The highlight in the footage's units: the footage's radiance per unit of irradiance on skin
    # is lum / e_src there (albedo / pi of the skin, in whatever exposure the footage has).
    skin = fg & (bufs.face > 0.5)
    unit = float(np.median((lum / e_src)[skin])) if skin.sum() > 8 else float(
        np.median((lum / e_src)[fg])) if fg.any() else 1.0
    # GGX's radiance in those units: times unit * pi / SKIN_ALBEDO, as "physical" exposure
    # converts (portrait.clip_gain). Measured against the renderer's earlier roughness 0.38 with
    # a scale 8.2 times weaker (unit * pi * SKIN_ALBEDO): effects bench, exact buffers, key lamp
    # from the left 0.1203 -> 0.1145, top light 0.1978 -> 0.1914; CroppedYale tune subjects
    # 20.34 -> 20.37 dB, top/bottom 0.807 -> 0.809; the physical scale at 0.38 was worse on both
    # (key left 0.1402, tune 20.21 dB).
    highlight = spec * (unit * math.pi / SKIN_ALBEDO)
    level = level_colour(image_chw, lum, e_src, skin)
    if unlit is not None and skin.sum() > 8:
        share = (unlit * bufs.face)[None]
        ratio = ratio * (1.0 - share)
        highlight = highlight + share * skin_radiance(image_chw, lum, bufs, skin, unit,
                                                      level) * e_t
    w = bufs.matte
    before = float((lum * w).sum())  # the subject's luminance in the footage
    if level is not None and fg.any():
        # the relit level in the footage's units: with its exposure kept, as a clip's is
        after = float((luminance(ratio * image_chw) * w).sum())
        k = before / after if after > 1e-12 else 1.0
        f = level_factor(level, e_src, e_src * luminance(ratio) * np.float32(k))
        ratio = ratio * (1.0 + bufs.face[None] * (f - 1.0))
    if keep_exposure and fg.any():
        # luminance(ratio * image), not luminance(ratio) * lum: they differ when both the
        # light and the footage are coloured.
        after = float(((luminance(ratio * image_chw) + luminance(highlight)) * w).sum())
        k = before / after if after > 1e-12 else 1.0
        ratio, highlight = ratio * k, highlight * k
    return Shading(ratio.astype(np.float32), highlight.astype(np.float32), effects, unit)
