"""One frame through an intrinsic model: find the portrait, run the network on a square crop
around it, shade the target light there (addon/intrinsic.py) and apply the change to the
full-resolution frame as a ratio. The pipeline calls these per frame; ``addon.relight_image``
calls them on one image.

Framing: a coarse pass runs the network on the whole frame shrunk to the working size and gives
face-skin and matte maps; ``addon.framing`` turns them into a square box around the face, which a
second pass on that box refines (a face of 11 pixels in the coarse pass becomes a face of about
half the working size). A run frames its frames in order and follows the portrait: each search
starts on the crop around the last box found (``find_box``'s ``prior``), the coarse pass only
when the portrait is not there. Over a clip the boxes are smoothed (``framing.smooth_boxes``) so
the crop does not jitter. ``relight_frame`` leaves a frame with no box unchanged; the pipeline
gives a frame where none was found its neighbours' box and counts it.
"""

from __future__ import annotations

import math
import os
import threading
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, replace

import numpy as np

from . import blas, detail, facetemplate, framing, intrinsic, lightvec, outline
from .engine import IntrinsicSession

MARGIN = 2.2  # box side over the face's extent: room for hair, chin and a little shoulder
_FULLRES: dict = {}
# relight_frame runs the face crop's finer sampling (its largest network pass) in a second
# thread, beside the coarse pass and the crop's own: onnxruntime and numpy's larger operations
# leave Python's lock, so the two share the cores, and a pass on one core wastes less than one
# split over two. The frame is the same to the bit. bench.intrinsic_speed on a 2-core Intel Xeon
# VM: the face crop's passes 41.7 -> 34.5 ms, relight_frame at 1080p 83.1 -> 67.8 ms; a clip
# (relight_clip) is no faster (9.5 and 9.4 frames/s, within noise), its decoding, finishing and
# writing threads keeping the second core busy already: what it shortens is one frame's wait
# (relight_image, the exposure scan, a single-frame render).
PARALLEL_PASSES = True
_LANE: dict = {}
_LANE_LOCK = threading.Lock()


def _lane() -> ThreadPoolExecutor:
    """The one worker thread relight_frame hands the finer sampling's pass to (made on first
    use, kept for the process; a process forked from one that had it makes its own, as the
    parent's thread does not exist in it and a pass handed to it would never run)."""
    with _LANE_LOCK:
        if _LANE.get("pid") != os.getpid():
            _LANE["pool"] = ThreadPoolExecutor(1, thread_name_prefix="relight-pass")
            _LANE["pid"] = os.getpid()
        return _LANE["pool"]


def shared_fullres(fullres: detail.FullRes | None = None) -> detail.FullRes:
    """The caller's full-resolution graphs, else one kept here (building them costs time: it is
    built on the first call only)."""
    if fullres is None:
        fullres = _FULLRES.get("default")
        if fullres is None:
            fullres = _FULLRES["default"] = detail.FullRes(threads=1)
    return fullres


def crop_planar(x: np.ndarray, box: framing.Box, size: int) -> tuple[np.ndarray, np.ndarray]:
    """((3, size, size) crop of a (3, H, W) frame, (size, size) share of each crop pixel inside
    the frame), channel by channel (no channels-last copy of the whole frame); beyond the
    frame's edge the crop is black, like a dark backdrop. A face that
    fills its frame (a tight crop) thus still reaches the network with room around it, as in
    training: on CroppedYale a lamp from either side moved the face's left/right balance 0.90
    with black room around it, 0.64 with the edges replicated and 0.2 with no room (the
    ground truth moves 1.1)."""
    valid = framing.crop_weight(box, x.shape[1:], size)
    return np.stack([framing.crop(x[c], box, size) * valid for c in range(x.shape[0])]), valid


# The coarse pass's size as a share of the working size: at 0.5 the wide clip s18 changed 1.69x
# as much as its input from frame to frame under key-left, at 1.0 1.56x (training.eval.footage_sheet).
COARSE = 1.0
MATTE_EDGE = (0.3, 0.9)  # matte values over which the change fades in (smoothstep) ...
MATTE_BLUR = 1.0  # ... of the matte smoothed by this Gaussian sigma, in working-size pixels
FEATHER = 0.12  # share of the crop's side over which the face crop fades into the coarse pass


def coarse_size(size: int) -> int:
    """The coarse pass's working size for a network of working size ``size`` (COARSE of it)."""
    return max(int(size * COARSE), 16)


@dataclass(frozen=True)
class FrameResult:
    """out = up(a) * x + up(b), with (a, b) on a grid of the frame (the pipeline's finish applies
    them at full resolution, as for the end-to-end models), then ``outline`` stops the change at
    the subject's outline at full resolution (addon.outline.apply)."""
    a: np.ndarray       # (3, gh, gw) float32
    b: np.ndarray       # (3, gh, gw) float32, in the units of x
    matte: np.ndarray   # (gh, gw) float32 in [0, 1]
    found: bool         # a portrait was found (else a = 1, b = 0: the frame is unchanged)
    plan: intrinsic.Plan | None
    # Before the exposure gain: the subject's luminance summed over the grid in the footage and
    # relit, and the footage's skin radiance per unit of fitted shading (intrinsic.Shading.unit),
    # from which a clip's gain is made (clip_gain).
    lum_in: float = 0.0
    lum_out: float = 0.0
    unit: float = 0.0
    outline: outline.Fit | None = None        # the change's fade refitted to colour
    matte_outline: outline.Fit | None = None  # the matte's, when asked for (refine_matte)


EXPOSURES = ("keep", "physical")


def clip_gain(results, exposure: str, scale: float = 1.0) -> float:
    """One exposure gain for a clip from FrameResults of some of its frames: "keep", the
    subject keeps the footage's luminance summed over those frames (so an animated light still
    brightens and dims the clip, and the gain does not flicker from frame to frame);
    "physical", absolute units: skin of albedo SKIN_ALBEDO under the target light's irradiance
    (``scale``: the footage is the relit image's x times this). 1.0 when nothing was found."""
    found = [r for r in results if r.found and r.lum_out > 0 and r.lum_in > 0]
    if not found:
        return 1.0
    if exposure == "physical":
        unit = float(np.median([r.unit for r in found]))
        return intrinsic.SKIN_ALBEDO / (math.pi * scale * unit) if unit > 0 else 1.0
    return sum(r.lum_in for r in found) / sum(r.lum_out for r in found)


# The face crop's relighting pass takes the mean of the network's buffers for the crop and for its
# mirror image (IntrinsicSession.run_planar's ``mirror``; the framing passes and the coarse pass
# over the whole frame do not): on the CroppedYale
# tune subjects, 36 pairs each, scale-invariant PSNR 20.14 -> 20.26 dB (HDRI 23.72 -> 23.91, one
# light 16.90 -> 17.00, two or three 19.81 -> 19.88), balance correlation left/right 0.982 ->
# 0.983, top/bottom 0.748 either way; the network's time per pass about 1.6x.
MIRROR = True

# Every pass's crop has its shadows lifted before the network: each pixel's luminance relative to
# the pass's normalisation level (intrinsic.INPUT_LEVEL, or FINER_LEVEL) is raised to this power,
# its colour kept (``lifted``), so the level itself and brighter tones barely move and a shadow
# at a tenth of the level comes up 1.6 times. Only the network sees it; the renderer and the
# ratio work on the footage as it is. Real faces' up-down shape comes out closer to the real
# light's that way. On the CroppedYale tune subjects, 36 pairs each, the top/bottom balance
# correlation rose from 0.841 to 0.845, 0.850, 0.847 and 0.840 at the powers 0.9, 0.8, 0.65
# and 0.5 (`python -m training.eval.yale --onnx models/relight-portrait.onnx --split tune
# --pairs 36 --input-lift 1 --compare-lift 0.9 --compare-lift 0.8 ...`; at 0.8 paired +0.009,
# 5-95% over resampled subjects +0.004 to +0.015), PSNR 20.37 -> 20.36 dB; on the test
# subjects 0.808 -> 0.817 at 20.34 -> 20.31 dB (bench/results/yale.md). The light stage's
# renders, which the network was trained on, lose a little: the card's test set
# rmse_level_fit 0.0570 -> 0.0580 (training.eval.evaluate).
INPUT_LIFT = 0.8

# The face crop's normals (the mean of its passes, face_buffers; not the framing passes' nor the
# coarse pass's) take the vertical component's low band over the face skin from a face template
# (facetemplate.held): the file at this path, or none where None. The template is frontal: a
# head the network reads as turned takes less of it (facetemplate.TURN). On the CroppedYale
# test subjects top/bottom balance correlation 0.817 -> 0.833 (paired +0.016, 5-95% +0.005 to
# +0.028) at 20.31 -> 20.11 dB, left/right 0.982 either way; tune 0.850 -> 0.874 at 20.36 ->
# 20.15 dB, where the vertical component alone was chosen over all three (0.870 at 20.09 dB).
# Held on each of the face crop's passes before their mean, it read the same to 0.001 (test
# 0.833, tune 0.874, training/README.md) for one more run of it a frame.
FACE_TEMPLATE = facetemplate.SHIPPED
FACE_TEMPLATE_AXES = "y"  # facetemplate.AXES' key


def lifted(x: np.ndarray, level: float, power: float | None = None) -> np.ndarray:
    """(3, h, w) ``x`` with each pixel's luminance relative to ``level`` raised to ``power``
    (default INPUT_LIFT), its chromaticity kept: a monotone curve through 0 and ``level``, so a
    crop normalised to ``level`` (intrinsic.exposure_scale) keeps its 90th luminance
    percentile there."""
    power = INPUT_LIFT if power is None else power
    if power == 1.0:
        return x
    rel = np.maximum(intrinsic.luminance(x), 1e-8) / np.float32(level)
    return (x * np.power(rel, np.float32(power - 1.0))[None]).astype(np.float32)


def result_buffers(session: IntrinsicSession, res,
                   valid: np.ndarray | None = None) -> intrinsic.Buffers:
    """The renderer's buffers of the network's result ``res`` (IntrinsicSession.run_planar's):
    its matte, face skin and hair from the parsing by the card's class names, times ``valid``
    (the share of each pixel inside the frame) where given."""
    names = session.card.classes
    matte = res.parsing[names.index("foreground")]
    face = res.parsing[names.index("skin")] if "skin" in names else np.zeros_like(matte)
    hair = res.parsing[names.index("hair")] if "hair" in names else None
    if valid is not None:  # the dark backdrop beyond the frame is not the subject
        matte, face = matte * valid, face * valid
        hair = None if hair is None else hair * valid
    return intrinsic.Buffers(res.normal, res.height, res.albedo, matte, face, res.transfer, hair)


def buffers(session: IntrinsicSession, x: np.ndarray, valid: np.ndarray | None = None,
            mirror: bool = False, level: float | None = None, shape: bool = True):
    """The network's buffers for a (3, h, w) linear image (normalised here, to ``level``:
    intrinsic.exposure_scale's, default INPUT_LEVEL); ``valid``: the share of each pixel
    inside the frame (crop_planar); ``mirror``: the mean with the mirror image's (MIRROR). The
    network sees the crop with its shadows lifted (INPUT_LIFT); its normals' vertical low band
    over the face skin is the face template's (FACE_TEMPLATE) unless ``shape`` is off (the
    framing passes read only the face and the matte; the coarse pass and the face crop's
    passes, which face_buffers holds to it once, on their mean)."""
    level = intrinsic.INPUT_LEVEL if level is None else level
    x = lifted(x * np.float32(intrinsic.exposure_scale(x, level)), level)
    bufs = result_buffers(session, session.run_planar(x, mirror=mirror), valid)
    return templated(bufs, session.card.working_size) if shape else bufs


def templated(bufs: intrinsic.Buffers, working_size: int) -> intrinsic.Buffers:
    """``bufs`` (of a crop) with the face template held over their normals as the face crop
    holds it (FACE_TEMPLATE, FACE_TEMPLATE_AXES; facetemplate.held, the low band's width
    scaled from the working size to the crop's), and then the face skin's normals' detail
    raised (deepened); as they are where FACE_TEMPLATE is None (the network's normals)."""
    if FACE_TEMPLATE is None:
        return bufs
    scale = bufs.normal.shape[1] / working_size
    bufs = facetemplate.held(bufs, facetemplate.cached(FACE_TEMPLATE), facetemplate.SIGMA * scale,
                             facetemplate.AXES[FACE_TEMPLATE_AXES])
    return deepened(bufs, NORMAL_DETAIL, NORMAL_DETAIL_SIGMA * scale)


# The network draws real faces' normals too flat in their detail: on CroppedYale's tune subjects
# the detail finer than 6 working-size pixels over the face skin is 0.66 of photometric stereo's
# (test subjects 0.69; python -m training.eval.yale_normals --onnx models/relight-portrait.onnx
# --relief), where on the light stage's held-out heads it is 0.9-1.0 of the truth's
# (bench.height_detail's rows: its normals march 0.98 of the exact relief). So over the face skin
# that detail is raised NORMAL_DETAIL times, faded in over NORMAL_DETAIL_BLEND pixels from the
# skin's edge: the nose's sides, the eye sockets and the mouth turn further from the light, and the
# shadows' height, which follows the normals' slopes, stands deeper. CroppedYale tune subjects (36
# pairs each, paired, with intrinsic.SHADOW_DETAIL 3.0 finer than 6): 20.34 -> 20.41 dB (one light
# 17.22 -> 17.36, few 20.06 -> 20.13), top/bottom +0.005 (5-95% +0.000 to +0.012), left/right
# +0.001; 1.5 read 20.37 dB and +0.000. The synthetic test set's rmse_level_fit 0.05787 -> 0.05775
# (python -m training.eval.evaluate --onnx models/relight-portrait.onnx --threads 1; a 2-core Intel
# Xeon VM). On the effects bench (network buffers, "auto") the rim lamp gains (0.4538 -> 0.4493),
# the key lamps lose (0.2258 / 0.2165 -> 0.2275 / 0.2192) and the sunniest HDRI's shadows come out
# colder (warmth -0.070 -> -0.118 against the light stage's -0.021; 0.1913 -> 0.1943): the light
# stage's heads, drawn less flat, are deepened too (bench.height_detail: marched 1.41 of the exact
# detail). On the dev footage under a key lamp the nose's shadow is better defined; frame-to-frame
# change and skin chroma as before.
NORMAL_DETAIL = 1.3
NORMAL_DETAIL_SIGMA = 6.0  # working-size pixels
NORMAL_DETAIL_BLEND = 2.0


def deepened(bufs: intrinsic.Buffers, gain: float, sigma: float) -> intrinsic.Buffers:
    """``bufs`` with their normals' detail finer than a Gaussian of ``sigma`` pixels raised
    ``gain`` times over the face skin, faded in over NORMAL_DETAIL_BLEND pixels from its edge
    (intrinsic.skin_detail_raised), and renormalised; as they are where ``gain`` is 1 or there
    is no face skin."""
    if gain == 1.0 or not ((bufs.face > 0.5) & (bufs.matte > 0.5)).any():
        return bufs
    normal = intrinsic.skin_detail_raised(bufs.normal, bufs, gain, sigma, NORMAL_DETAIL_BLEND)
    return replace(bufs, normal=intrinsic.unit_normals(normal).astype(np.float32))


# The face crop's buffers are also the mean with the network's on a finer sampling of the same
# box (ZOOM times the working size, taken from the frame, its buffers shrunk back): the network
# errs differently at the two scales, the face's up-down shape most. On the CroppedYale tune
# subjects (36 pairs each, with MIRROR) top/bottom balance correlation 0.748 -> 0.807 and PSNR
# 20.26 -> 20.34 dB (HDRI 23.99, one light 17.08, two or three 19.95), left/right 0.983 either
# way. Chosen there among 1.25, 1.5 (0.784, 20.28 dB) and 0.75 (0.772, but 20.05 dB), each
# measured with the finer crop enlarged from the working size's.
ZOOM = 1.25
# The finer sampling is fed brighter than the other passes: its 90th luminance percentile at
# this level, not intrinsic.INPUT_LEVEL, so its highlights clip. Its normals then turn the
# forehead further up against the chin, further from photometric stereo's on CroppedYale
# (training.eval.yale_normals, tune: tilt +0.101 -> +0.125 against the truth's +0.063, mean
# angle 19.7 -> 20.2 deg), yet the relit faces' up-down balance follows the real light's
# better: it answered the target's balance too weakly and kept too much of the input's (on the
# test subjects, relit = a truth + b input with a, b 0.62, 0.26 before, 0.71, 0.20 after). Its
# albedo, which the clipping flattens, is left out of the mean (the crop's own is kept). On the
# CroppedYale tune subjects (36 pairs each) top/bottom balance correlation 0.811 -> 0.843 at
# 20.38 dB, left/right 0.985; 1.2 gave 0.848 but 20.33 dB (and, with the bright albedo in the
# mean, 0.8 0.828 at 20.40 dB). With the bright albedo in the mean the synthetic test set's
# rmse_level_fit was 0.0577 against 0.0570 (0.0572 without it), and with the matte and skin
# kept too 0.0573. All of the crop's passes at 1.0 cost 0.07 dB there, and a third pass at 1.0
# whose normals alone were taken gave 0.834, for that pass's time. The scale matters with the
# level: the brighter pass at ZOOM 1.0 (the crop itself) gave 0.798 at 20.31 dB, at 1.5 0.815.
FINER_LEVEL = 1.0


def shrunk(bufs: intrinsic.Buffers, size: int,
           fullres: detail.FullRes | None = None) -> intrinsic.Buffers:
    """Buffers of a crop of the same box at another size, resampled to (size, size) (area means;
    the normals renormalised, the height in the smaller crop's pixels), all channels in one
    pass of the full-resolution graphs' shrink (FullRes.shrink_planar)."""
    planes = [bufs.normal, bufs.height[None], bufs.albedo, bufs.matte[None], bufs.face[None]]
    if bufs.hair is not None:
        planes.append(bufs.hair[None])
    if bufs.transfer is not None:
        planes.append(bufs.transfer)
    small = shared_fullres(fullres).shrink_planar(np.concatenate(planes, 0), size, size)
    k = np.float32(size / bufs.height.shape[0])
    rest = 9 if bufs.hair is None else 10
    transfer = small[rest:] if bufs.transfer is not None else None
    return intrinsic.Buffers(intrinsic.unit_normals(small[0:3]), small[3] * k, small[4:7],
                             small[7], small[8], transfer, None if bufs.hair is None else small[9])


def mean_buffers(a: intrinsic.Buffers, b: intrinsic.Buffers) -> intrinsic.Buffers:
    """The mean of two sets of buffers of one crop (the normals renormalised)."""
    half = np.float32(0.5)
    return intrinsic.Buffers(
        intrinsic.unit_normals(a.normal + b.normal), half * (a.height + b.height),
        half * (a.albedo + b.albedo), half * (a.matte + b.matte), half * (a.face + b.face),
        None if a.transfer is None or b.transfer is None else half * (a.transfer + b.transfer),
        None if a.hair is None or b.hair is None else half * (a.hair + b.hair))


def fit_in_frame(box: framing.Box, frame_hw: tuple[int, int]) -> framing.Box:
    """The box moved to lie inside the frame along each axis where it fits, centred on the
    frame along an axis where it does not (a tight portrait: the face fills the frame)."""
    h, w = frame_hw

    def centre(c: float, n: int) -> float:
        return n / 2 if box.size >= n else min(max(c, box.size / 2), n - box.size / 2)

    return framing.Box(centre(box.cx, w), centre(box.cy, h), box.size)


# A box found from a nearby frame's (find_box's ``prior``) is kept when the portrait moved by at
# most this share of the box's side and its size changed by at most this factor.
TRACK_SHIFT = 0.25
TRACK_SCALE = 1.25


def _refine(session: IntrinsicSession, x_full: np.ndarray, box: framing.Box) -> framing.Box | None:
    """The portrait's box found on the crop around ``box``, where the face has most of the
    working size; None when the crop shows none."""
    size = session.card.working_size
    fine = buffers(session, *crop_planar(x_full, box, size), shape=False)
    inner = framing.find_portrait(fine.face, fine.matte, (size, size), MARGIN)
    if inner is None:
        return None
    k = box.size / size
    return fit_in_frame(framing.Box(box.cx - box.size / 2 + inner.cx * k,
                                    box.cy - box.size / 2 + inner.cy * k, inner.size * k),
                        x_full.shape[1:])


def _follows(prior: framing.Box, box: framing.Box) -> bool:
    return (math.hypot(box.cx - prior.cx, box.cy - prior.cy) <= TRACK_SHIFT * prior.size
            and 1.0 / TRACK_SCALE <= box.size / prior.size <= TRACK_SCALE)


@blas.one_thread()
def find_box(session: IntrinsicSession, x_full: np.ndarray,
             fullres: detail.FullRes | None = None,
             prior: framing.Box | None = None) -> framing.Box | None:
    """The portrait's square box in a (3, H, W) frame, or None when there is none: a coarse pass
    over the whole frame places a box, refined on that box's crop. ``prior``: the box found in
    a nearby frame (a run frames its frames in order): the crop around it is searched first,
    without the coarse pass, and its portrait kept when it moved and grew little (TRACK_SHIFT,
    TRACK_SCALE); so the portrait a run follows stays its subject while it is in view, even if
    a larger face comes in. Otherwise, or when it is gone, the whole frame is searched."""
    h, w = x_full.shape[1:]
    if prior is not None:
        prior = fit_in_frame(prior, (h, w))
        box = _refine(session, x_full, prior)
        if box is not None and _follows(prior, box):
            return box
    size = session.card.working_size
    small = shared_fullres(fullres).shrink_planar(x_full, *detail.working_shape(h, w, size))
    coarse = buffers(session, small, shape=False)
    box = framing.find_portrait(coarse.face, coarse.matte, (h, w), MARGIN)
    if box is None:
        return None
    box = fit_in_frame(box, (h, w))
    refined = _refine(session, x_full, box)
    return box if refined is None else refined


def grid_shape(height: int, width: int, box: framing.Box, size: int) -> tuple[int, int]:
    """The grid on which the change is built: the frame scaled so the box spans about ``size``
    pixels (the face crop's own resolution), never larger than the frame. The scale is snapped
    to a nearby ratio of small whole numbers where the frame's sides allow one
    (detail.block_scale), so the grid is shrunk from the frame and the change enlarged back to
    it by exact blocks, the finish's fast path."""
    f = min(1.0, size / max(box.size, 1e-6))
    snapped = detail.block_scale(height, width, f)
    if snapped is None:
        # A close-up or a 4K frame (a box many times the working size): blocks of fewer
        # grid samples still beat the general path (1080p finish 16.6 against 25.5 ms at 1/10)
        # and keep the grid's size steady as the box drifts.
        snapped = detail.block_scale(height, width, f, min_q=1)
    if snapped is not None:
        q, p = snapped
        return height * q // p, width * q // p
    return max(1, int(round(height * f))), max(1, int(round(width * f)))


def feather(size: int, share: float = FEATHER) -> np.ndarray:
    """(size, size) weight: 1 inside the crop, falling smoothly to 0 at its edges."""
    ramp = np.clip((np.arange(size) + 0.5) / max(share * size, 1e-6), 0.0, 1.0)
    edge = np.minimum(ramp, ramp[::-1])
    edge = edge * edge * (3 - 2 * edge)
    return np.minimum(edge[:, None], edge[None, :]).astype(np.float32)


def finer_buffers(session: IntrinsicSession, x_full: np.ndarray, box: framing.Box,
                  size: int) -> intrinsic.Buffers:
    """The network's buffers of the finer sampling of the face's box (ZOOM times ``size``),
    fed brighter (FINER_LEVEL), with the mirror image's (MIRROR), as face_buffers takes them."""
    return buffers(session, *crop_planar(x_full, box, round(size * ZOOM)), mirror=MIRROR,
                   level=FINER_LEVEL, shape=False)


def finer_pass(session: IntrinsicSession, x_full: np.ndarray, box: framing.Box,
               size: int) -> Future | None:
    """finer_buffers under way in the second thread (PARALLEL_PASSES), for face_buffers'
    ``finer``; None where the product makes no such pass (ZOOM 0) or runs it in turn."""
    if not (ZOOM and PARALLEL_PASSES):
        return None
    return _lane().submit(finer_buffers, session, x_full, box, size)


def face_buffers(session: IntrinsicSession, x_full: np.ndarray, box: framing.Box, size: int,
                 fullres: detail.FullRes | None = None, finer: Future | None = None):
    """(crop, valid, buffers) of the face crop as the relighting pass takes them: the crop and
    its mirror image (MIRROR), averaged with a finer sampling of the same box (ZOOM,
    finer_buffers; ``finer``: that pass already under way in another thread), fed brighter
    (FINER_LEVEL), whose albedo is left out; the face template held once, on the mean
    (templated)."""
    crop, valid = crop_planar(x_full, box, size)
    bufs = buffers(session, crop, valid, mirror=MIRROR, shape=False)
    if ZOOM:
        fine = finer.result() if finer is not None else finer_buffers(session, x_full, box, size)
        bufs = replace(mean_buffers(bufs, shrunk(fine, size, fullres)), albedo=bufs.albedo)
    return crop, valid, templated(bufs, session.card.working_size)


def _change(session, x: np.ndarray, light, effects, valid=None, unit=None, bufs=None):
    """(ratio and highlight, each times the weight; the weight; the matte) for a (3, h, w)
    image, the weight being the matte's core (MATTE_EDGE). The ratio
    is carried times the matte, never as ratio - 1: under a faint light ratio - 1 + 1 would
    lose the ratio to rounding. ``bufs``: the image's buffers, if the caller has them."""
    bufs = buffers(session, x, valid, mirror=MIRROR) if bufs is None else bufs
    sh = intrinsic.shade(x, bufs, light, effects, keep_exposure=False)
    if unit is not None:
        unit.append(sh.unit)
    # The change fades in over the matte's confident core: at the outline the normals graze and
    # the ratio is least certain, and a soft matte there would carry it onto the background. The
    # matte is smoothed first (MATTE_BLUR): the network draws it nearly binary, and its pixel
    # steps, enlarged to the frame, showed as stair steps along a lit outline.
    m = intrinsic.gaussian_blur(bufs.matte, MATTE_BLUR)
    m = np.clip((m - MATTE_EDGE[0]) / (MATTE_EDGE[1] - MATTE_EDGE[0]), 0.0, 1.0)
    m = (m * m * (3.0 - 2.0 * m))[None]
    return m * sh.ratio, m * sh.highlight, m[0], np.clip(bufs.matte, 0.0, 1.0)


@blas.one_thread()
def relight_frame(session: IntrinsicSession, x_full: np.ndarray, light: np.ndarray,
                  box: framing.Box | None, effects: intrinsic.Plan | None = None,
                  exposure: str | float = "keep", fullres: detail.FullRes | None = None,
                  scale: float = 1.0, outline_fit: bool = True,
                  matte_fit: bool = False) -> FrameResult:
    """Relight a (3, H, W) linear frame to ``light``: a coarse pass over the whole frame lights
    the whole person, the crop around ``box`` gives the face its working size, and the crop
    fades into the coarse pass over its outer edge. ``box`` None (no portrait found): the frame
    is unchanged. ``exposure``: "keep" (the subject keeps this frame's luminance), "physical"
    (absolute units, clip_gain; ``scale``: the footage is x_full times this) or the gain itself
    (a clip's, from clip_gain over some of its frames). ``outline_fit``: the change's colour
    refit at the outline (addon.outline; not needed for the exposure's statistics alone);
    ``matte_fit``: the matte's too (a run that writes a matte strip)."""
    h, w = x_full.shape[1:]
    size = session.card.working_size
    if not float(np.max(lightvec.total_power(light))) > 0:
        # No light: a black frame, as for the end-to-end presets (nothing to keep exposure of).
        return FrameResult(np.zeros((3, 1, 1), np.float32), np.zeros((3, 1, 1), np.float32),
                           np.zeros((1, 1), np.float32), True, None)
    if box is None:
        return FrameResult(np.ones((3, 1, 1), np.float32), np.zeros((3, 1, 1), np.float32),
                           np.zeros((1, 1), np.float32), False, None)
    gh, gw = grid_shape(h, w, box, size)
    fr = shared_fullres(fullres)
    finer = finer_pass(session, x_full, box, size)  # beside the passes this thread runs
    try:
        return _relit(session, x_full, light, box, effects, exposure, fr, scale, outline_fit,
                      matte_fit, finer, gh, gw)
    finally:
        if finer is not None:
            finer.cancel()
            # an error here leaves no pass running on after the frame is given up
            if not finer.cancelled():
                finer.exception()


def _relit(session, x_full, light, box, effects, exposure, fr, scale, outline_fit, matte_fit,
           finer, gh, gw) -> FrameResult:
    """relight_frame's work once the frame has a box and a light (``finer``: the finer
    sampling's pass under way, or None)."""
    h, w = x_full.shape[1:]
    size = session.card.working_size
    grid = fr.shrink_planar(x_full, gh, gw)  # the footage at the grid's resolution
    plan = intrinsic.plan(light) if effects is None else effects
    # Everything below is channels-first on the grid: (ratio 3, highlight 3, weight, matte).
    # Coarse: the whole frame at COARSE times the working size (it lights the body beyond the
    # face's box), enlarged to the grid; not needed when the box holds the whole frame.
    covers = (box.cx - box.size / 2 <= 0 and box.cy - box.size / 2 <= 0
              and box.cx + box.size / 2 >= w and box.cy + box.size / 2 >= h)
    if covers:
        coarse = np.zeros((8, gh, gw), np.float32)
    else:
        small = fr.shrink_planar(grid, *detail.working_shape(h, w, coarse_size(size)))
        # Diffuse only: at this scale (a 1080p frame's 15 pixels a sample) cast shadows are
        # blocks, and highlights fall on face skin, which the face crop covers. One network pass
        # (no mirror image) and no face template: the face crop is where the buffers' errors
        # show, and it relights the face.
        mr, hi, m, raw = _change(session, small, light,
                                 intrinsic.Plan(plan.components, False, False),
                                 bufs=buffers(session, small, shape=False))
        coarse = detail.enlarge_planar(np.concatenate([mr, hi, m[None], raw[None]], 0), gh, gw)
    # Fine: the crop around the face, placed on the grid with its feathered edge.
    crop, valid, bufs = face_buffers(session, x_full, box, size, fr, finer)
    units: list[float] = []
    mr_f, hi_f, m_f, raw_f = _change(session, crop, light, plan, valid, units, bufs)
    fw = (1.0 if covers else feather(size)) * valid
    k = gh / h
    gbox = framing.Box(box.cx * k, box.cy * k, box.size * k)
    fine = framing.uncrop(np.concatenate([mr_f, hi_f, m_f[None], raw_f[None], fw[None]],
                                         0).transpose(1, 2, 0), gbox, (gh, gw), 0.0)
    fine = np.ascontiguousarray(fine.transpose(2, 0, 1))
    wf = fine[8]
    # The two passes fit the footage's light separately: match the coarse change's level to the
    # face's where both see the subject, so the seam does not show.
    both = (wf > 0.5) & (fine[6] > 0.5) & (coarse[6] > 0.5)
    if int(both.sum()) > 16:
        num = float(intrinsic.luminance(fine[0:3, both]).mean())
        den = float(intrinsic.luminance(coarse[0:3, both]).mean())
        g = num / den if den > 0 and num > 0 else 1.0
        coarse[0:6] *= np.float32(g)
    # mix = (1 - wf) coarse + wf fine, in place
    mix = coarse
    mix += wf * (fine[:8] - coarse)
    # The portrait is the matte's region that holds the face crop; anything else a matte marks
    # (a bright door, a lamp in the room) keeps the footage as it was.
    keep = framing.component_at(mix[7] > 0.5, wf * fine[7])
    if keep.any():
        mix *= np.clip(detail.box_mean(keep.astype(np.float32), 2) * 2.0, 0.0, 1.0)
    mr, b, matte = mix[0:3], mix[3:6], np.clip(mix[6], 0.0, 1.0)
    # The subject's luminance in the footage and relit (before any gain): the exposure gain
    # solves sum lum(x a + b) m = sum lum(x) m with a = g m ratio + (1 - m), b = g b.
    xl = intrinsic.luminance(grid)
    lum_in = float((xl * matte).sum() - (xl * (1.0 - matte) * matte).sum())
    lum_out = float((intrinsic.luminance(grid * mr + b) * matte).sum())
    unit = units[0] if units else 0.0
    stats = FrameResult(None, None, None, True, plan, lum_in, lum_out, unit)
    g = clip_gain([stats], exposure, scale) if isinstance(exposure, str) else float(exposure)
    a = np.float32(g) * mr + (1.0 - matte)
    b = np.float32(g) * b
    matte = np.clip(mix[7], 0.0, 1.0)  # the portrait's matte, for the matte strip
    return FrameResult(np.ascontiguousarray(a, np.float32), np.ascontiguousarray(b, np.float32),
                       np.ascontiguousarray(matte, np.float32), True, plan, lum_in, lum_out,
                       unit, outline.fit(grid, mix[6], subject=mix[7]) if outline_fit else None,
                       outline.fit(grid, matte, tol=outline.MATTE_TOL, colours=True) if matte_fit
                       else None)
