"""Real faces: relighting checked against CroppedYale, real one-light-at-a-time data.

    .venv/bin/python -m training.eval.yale --onnx models/relight-draft.onnx [--onnx ...]
    .venv/bin/python -m training.eval.yale --onnx models/relight-draft.onnx --quick
    .venv/bin/python -m training.eval.yale --check-data      # the data checks quoted below

A subject's image under any lighting made of the 64 light directions is the weighted sum of its
single-light images (light transport is linear), so every relighting here has real ground truth.
The data (``../shared/data/yale/CroppedYale``) is for evaluation only: never commit or ship it,
nor pictures made from it (the sheet goes to the git-ignored ``out/yale/``).

Data decisions, each checked on the data (``--check-data`` prints the figures):
* Linear 8-bit: code / 255 is taken as linear radiance. Check: a Lambertian fit to the near-frontal
  lights (|azimuth| <= 50, |elevation| <= 40) predicts each left-out image best when the codes are
  decoded with a gamma near 1 and clearly worse with 2.2 (an sRGB-like camera): leave-one-out RMS
  in code values 12.8-17.4 at gamma 1.0 against 16.5-21.9 at 2.2 on the six subjects that
  ``--check-data`` samples (yaleB01 08 16 23 30 37; the best of 0.8/1.0/1.2/1.8/2.2 is 1.0 for
  five of them, 1.2 for yaleB01).
* Azimuth sign: a positive file-name azimuth lights the image's left half (the subject's right),
  so Yale (A, E) is the camera-frame direction (-cos E sin A, sin E, cos E cos A) and lands at
  light-vector azimuth -A (addon/lightvec.py: column 8 faces the camera, higher columns toward
  the camera's right, +X). Check: in all 667 mirror pairs (A, -A), 20 <= |A| <= 95, of all 38
  subjects, the image lit from camera +X is the brighter on the image's right half.
* Ambient: subtracted (then clipped at 0) where ``*_Ambient.pgm`` is the crop's size (subjects
  01-10). From yaleB11 on the database ships it uncropped (640x480), which cannot be registered to
  the crop; there the ambient is taken as 0 (in subjects 01-10 it averages 0.5-3.3 codes, under 3%
  of a frontal image's mean).
* Failed strobes: an image darker than 10% of the median of its neighbours within 35 degrees is a
  strobe that did not fire (10 images, e.g. yaleB34-39 at A+095E+00, at 0.3-8% of their
  neighbours; the darkest genuine image is at 19%); it is dropped like the images the database
  itself omits (a subject has 59-64 usable directions). Lightings use only a subject's usable
  directions, for the ground truth and the network's light alike.
* Saturation: 8-bit codes clip at 255. A pixel whose ground truth under B draws more than 10% of
  its value from saturated images is left out of the comparison mask.

Lightings (each a weight per usable direction; weight 1 = one strobe, i.e. one single-light image;
every lighting's weights sum to a random intensity, log-uniform in [1/2, 2]):
* ``hdri``: one of the 26 HDRIs in ``../shared/data/hdri`` at a random yaw, down-sampled to a light
  vector by ``addon.hdri.downsample`` (front view), restricted to the 64 directions: every
  direction's weight is the light vector's Rec.709 luminance integrated over its cell, the part of
  the sphere nearer to it than to any other usable direction and within ``CELL_CAP_DEG`` of it
  (the cells tile the dome without gaps; light from behind or below the dome is dropped).
* ``single``: one direction; ``few``: two or three directions at weights uniform in [0.3, 1].
  Both draw from the directions with |azimuth| <= 95: lights further back leave the crop nearly
  black, and the white level would then measure sensor noise.
The light vector fed to the network is the same weights splatted with ``lightvec.splat_direction``
(equal RGB, irradiance = weight), so the network's light and the ground truth agree exactly. Both
lightings of a pair are of the same kind; pairs take the kinds in turn.

Relighting is ``addon.relight_image``, exactly what the pipeline does to one frame (for the
end-to-end presets: exposure scale s of the input, area shrink to the card's working size, network
fed light / k, guided full-resolution transfer; for the intrinsic presets: portrait framing,
buffers, the renderer's effects, the ratio at full resolution). The grayscale image is replicated
to three channels on the way in and the output turned back to gray by Rec.709 luminance
(normalise.luminance).

Metrics: training/eval/evaluate.py's image_metrics on the single gray channel (white level = the
ground truth's 99th percentile, clipped, sRGB-encoded; RMSE, PSNR, SSIM), over a centred ellipse
(semi-axes 0.40 W x 0.46 H: cheeks, forehead, chin; the crop's corners hold hair and background)
minus saturated pixels. Two views, the same for every method:
* ``calibrated``: each method's output times one gain, the one that minimises its mean RMSE over
  the ``tune`` subjects' pairs. The network cannot see absolute albedo or camera gain (the engine
  normalises exposure away), and a unit of Yale weight is one strobe of unknown irradiance, so
  the units are calibrated once per method, never per pair. The baselines get the same
  treatment (the search includes gain 1, their units' own).
* ``scale_invariant``: every output times its own least-squares gain (linear, over the mask)
  against the ground truth, pair by pair: only the shape of the shading counts. Under gray light
  both baselines are the input times a number, so here they coincide (a check, not a bug).
Baselines (as training/eval/evaluate.py): ``identity`` (output = input) and ``irradiance_ratio``
(input times total power of B over that of A: an oracle on the lighting). A third, light-blind
reference, ``flattened_ratio`` = ratio * sqrt(input * mean(input)), halves the input's contrast (in
log terms) without knowing where B's light comes from: a model that beats the baselines only by
flattening the shading scores about as well as it.

Subjects 01-10 are ``tune`` (only the calibration gains come from them), the other 28 ``test``;
tables and the verdict use ``test`` only. Pairs (A, B) are drawn per subject from a fixed seed.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import functools
import math
import pathlib
import re
import sys
import time

import numpy as np

from addon import api, facetemplate, hdri, intrinsic, lightvec, normalise, portrait
from addon.errors import InputError
from addon.intrinsic import SOURCE_FLOOR

from . import report
from .facetemplate import applied as template_applied
from .facetemplate import flag_path as template_flag_path
from .metrics import (baseline_identity, baseline_irradiance_ratio, image_metrics, mean_metrics,
                      srgb_encode, to_unit, white_level)

ROOT = pathlib.Path(__file__).resolve().parents[2]
TUNE_SUBJECTS = tuple(range(1, 11))
KINDS = ("hdri", "single", "few")
VIEWS = ("calibrated", "scale_invariant")
BASELINES = ("identity", "irradiance_ratio")
# A light-blind reference (beside the two baselines): the irradiance-ratio output with
# its contrast halved in log terms. It knows B's power but not where the light comes from, so a
# model that only flattens the input's shading scores about the same.
FLATTENED = "flattened_ratio"
# Two ceilings, not methods: they see all of the subject's photos (a Lambertian photometric-
# stereo fit, albedo times normal per pixel, subject_shading), which no relighter of one image has.
# LAMBERT_FIT renders lighting B from the fit; LAMBERT_RATIO multiplies the input by the fit's
# Lambertian shading under B over that under A (floored as the product floors its source): what a
# ratio of diffuse shadings can do with exact normals. Neither casts shadows.
LAMBERT_FIT, LAMBERT_RATIO = "lambert_fit", "lambert_ratio"
REFERENCES = (*BASELINES, FLATTENED, LAMBERT_FIT, LAMBERT_RATIO)
GAIN_SEARCH_STRIDE = 4   # every 4th mask pixel is plenty to place one gain per method
CELL_CAP_DEG = 20.0      # the Yale dome's largest nearest-neighbour spacing is 26 degrees
FRONT_AZIMUTH = 95       # single / few lights come from |azimuth| <= this
NEIGHBOUR_DEG = 35.0     # failed-strobe test: neighbours within this angle
FAILED_RATIO = 0.1       # ... an image darker than this share of its neighbours' median
SATURATED_SHARE = 0.1    # mask out pixels whose ground truth owes more than this to clipped codes
ELLIPSE = (0.40, 0.46)   # mask semi-axes as shares of width and height

_LIGHT = re.compile(r"^yaleB(\d{2})_P00A([+-]\d{3})E([+-]\d{2})\.pgm$")
_AMBIENT = re.compile(r"^yaleB(\d{2})_P00_Ambient\.pgm$")
_TOKEN = re.compile(rb"\S+")


def default_root() -> pathlib.Path:
    from ..lightstage import assets

    return assets.default_data_root() / "yale" / "CroppedYale"


# --------------------------------------------------------------------------------- the files

@dataclasses.dataclass(frozen=True)
class YaleName:
    subject: int
    ambient: bool
    azimuth: int = 0     # degrees; positive lights the image's left half (the subject's right)
    elevation: int = 0   # degrees; positive is above the camera axis


def parse_name(name: str) -> YaleName | None:
    """A CroppedYale file name -> subject and light direction (or ambient); None for other files."""
    m = _LIGHT.match(name)
    if m:
        return YaleName(int(m[1]), False, int(m[2]), int(m[3]))
    m = _AMBIENT.match(name)
    return YaleName(int(m[1]), True) if m else None


def read_pgm(path) -> tuple[np.ndarray, int]:
    """A binary PGM (P5; '#' comments allowed in its header) -> (H, W) codes, maximum code."""
    data = pathlib.Path(path).read_bytes()
    fields, pos = [], 0
    while len(fields) < 4 and pos < len(data):
        if data[pos:pos + 1].isspace():
            pos += 1
        elif data[pos:pos + 1] == b"#":
            end = data.find(b"\n", pos)
            pos = len(data) if end < 0 else end + 1
        else:
            m = _TOKEN.match(data, pos)
            fields.append(m.group())
            pos = m.end()
    try:
        if fields[0] != b"P5":
            raise ValueError("not P5")
        w, h, top = (int(f) for f in fields[1:4])
        dtype = np.dtype(np.uint8 if top < 256 else ">u2")
        pix = np.frombuffer(data, dtype, count=w * h, offset=pos + 1).reshape(h, w)
    except (IndexError, ValueError) as err:
        raise InputError(f"{path} is not a readable binary PGM ({err}); restore the file from "
                         "the CroppedYale archive.") from err
    return pix.astype(np.uint16 if top > 255 else np.uint8), top


def yale_direction(azimuth, elevation) -> np.ndarray:
    """Camera-frame unit direction(s) of Yale light(s): positive azimuth toward camera -X."""
    a = np.radians(np.asarray(azimuth, np.float64))
    e = np.radians(np.asarray(elevation, np.float64))
    return np.stack([-np.cos(e) * np.sin(a), np.sin(e), np.cos(e) * np.cos(a)], axis=-1)


def failed_strobes(dirs: np.ndarray, means: np.ndarray) -> np.ndarray:
    """(K,) bool: images darker than FAILED_RATIO of the median of their neighbours' means."""
    cos = np.clip(dirs @ dirs.T, -1.0, 1.0)
    near = (cos >= math.cos(math.radians(NEIGHBOUR_DEG))) & ~np.eye(len(dirs), dtype=bool)
    out = np.zeros(len(dirs), dtype=bool)
    for i in range(len(dirs)):
        if near[i].any():
            out[i] = means[i] < FAILED_RATIO * float(np.median(means[near[i]]))
    return out


@dataclasses.dataclass(frozen=True)
class Subject:
    name: str
    number: int
    angles: np.ndarray     # (K, 2) int: azimuth, elevation of each usable image
    dirs: np.ndarray       # (K, 3) camera-frame unit directions
    images: np.ndarray     # (K, H, W) float32 linear, ambient subtracted, >= 0
    saturated: np.ndarray  # (K, H, W) bool: code at its maximum
    ambient: str           # "subtracted" or why not
    dropped: tuple         # ((azimuth, elevation), reason) of unusable images


def subject_names(root) -> list[str]:
    root = pathlib.Path(root)
    if not root.is_dir():
        raise InputError(f"CroppedYale is not at {root}; unpack it there (see "
                         "../shared/data/README.md) or pass --data.")
    return sorted(p.name for p in root.iterdir()
                  if p.is_dir() and re.fullmatch(r"yaleB\d\d", p.name))


def load_subject(root, name: str) -> Subject:
    """Read one subject's usable single-light images (linear, ambient subtracted)."""
    folder = pathlib.Path(root) / name
    lights, ambient_file = [], None
    for p in sorted(folder.glob("*.pgm")):
        n = parse_name(p.name)
        if n is None:
            continue
        if n.ambient:
            ambient_file = p
        else:
            lights.append(((n.azimuth, n.elevation), read_pgm(p)))
    if not lights:
        raise InputError(f"{folder} holds no single-light images (yaleBxx_P00A+000E+00.pgm ...).")
    if len({c.shape for _, (c, _) in lights}) > 1:
        raise InputError(f"The images in {folder} differ in size; restore the subject from the "
                         "CroppedYale archive.")
    angles = np.array([a for a, _ in lights], np.int64)
    codes = np.stack([c for _, (c, _) in lights]).astype(np.float32)
    top = float(max(t for _, (_, t) in lights))
    dirs = yale_direction(angles[:, 0], angles[:, 1])
    failed = failed_strobes(dirs, codes.mean(axis=(1, 2)))
    ambient, how = _ambient(ambient_file, codes.shape[1:])
    keep = ~failed
    return Subject(name, int(name[5:]), angles[keep], dirs[keep],
                   (np.clip(codes[keep] - ambient, 0.0, None) / top).astype(np.float32),
                   codes[keep] >= top, how,
                   tuple((tuple(int(v) for v in a), "failed strobe") for a in angles[failed]))


def _ambient(path, shape) -> tuple[np.ndarray | float, str]:
    if path is None:
        return 0.0, "none: no ambient image"
    codes, _ = read_pgm(path)
    if codes.shape != tuple(shape):
        return 0.0, f"none: the ambient image is {codes.shape[1]}x{codes.shape[0]}, not the crop"
    return codes.astype(np.float32), "subtracted"


# --------------------------------------------------------------------------------- lightings

@functools.lru_cache(maxsize=1)
def _sphere_grid(step_deg: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Directions (N, 3) and exact solid angles (N,) of a fine latitude-longitude grid."""
    step = math.radians(step_deg)
    edges = np.arange(0.0, math.pi + 1e-9, step)
    theta = 0.5 * (edges[:-1] + edges[1:])
    phi = -math.pi + (np.arange(round(2 * math.pi / step)) + 0.5) * step
    t, p = np.meshgrid(theta, phi, indexing="ij")
    omega = np.repeat(((np.cos(edges[:-1]) - np.cos(edges[1:])) * step)[:, None], len(phi), 1)
    return lightvec.angles_to_directions(t, p).reshape(-1, 3), omega.reshape(-1)


@functools.lru_cache(maxsize=1)
def _grid_cells() -> tuple[np.ndarray, np.ndarray]:
    """Light-vector row and column of every fine-grid direction."""
    return lightvec.directions_to_cells(_sphere_grid()[0])


@functools.lru_cache(maxsize=64)
def _cell_index(dirs_bytes: bytes) -> np.ndarray:
    grid, _ = _sphere_grid()
    cos = grid @ np.frombuffer(dirs_bytes, np.float64).reshape(-1, 3).T
    best = np.argmax(cos, axis=1)
    inside = cos[np.arange(len(grid)), best] >= math.cos(math.radians(CELL_CAP_DEG))
    return np.where(inside, best, -1)


def cell_index(dirs: np.ndarray) -> np.ndarray:
    """For every fine-grid direction, the nearest of ``dirs`` within CELL_CAP_DEG, else -1."""
    return _cell_index(np.ascontiguousarray(dirs, np.float64).tobytes())


def cell_solid_angles(dirs: np.ndarray) -> np.ndarray:
    """(K,) solid angle of each direction's cell."""
    idx = cell_index(dirs)
    _, omega = _sphere_grid()
    return np.bincount(idx[idx >= 0], weights=omega[idx >= 0], minlength=len(dirs))


def restrict_light(light: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """(K,) weights: the light vector's luminance integrated over each direction's cell."""
    _, omega = _sphere_grid()
    row, col = _grid_cells()
    radiance = normalise.luminance(lightvec.validate(light))[row, col].astype(np.float64)
    idx = cell_index(dirs)
    ok = idx >= 0
    return np.bincount(idx[ok], weights=(radiance * omega)[ok], minlength=len(dirs))


def light_vector(dirs: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """The network's light: every direction's weight splatted as gray irradiance."""
    out = np.zeros(lightvec.SHAPE, np.float64)
    for d, w in zip(dirs, weights):
        if w > 0:
            out += lightvec.splat_direction(d, (w, w, w))
    return out.astype(np.float32)


class HdriBank:
    """The shared HDRIs, read on first use and down-sampled to light vectors at a given yaw."""

    def __init__(self, data_root):
        from ..data.lighting_sampling import hdri_paths

        self.paths = hdri_paths(data_root)
        self.names = [f"{p.parent.name}/{p.stem}" for p in self.paths]
        self._images: dict[int, np.ndarray] = {}

    def light(self, index: int, yaw_degrees: float) -> np.ndarray:
        if index not in self._images:
            from addon.hdri_io import read_hdri
            self._images[index] = read_hdri(self.paths[index])
        return hdri.downsample(self._images[index], yaw_degrees=yaw_degrees, max_width=256,
                               repair=True)  # a few CC0 maps hold tiny negative pixels


@dataclasses.dataclass(frozen=True)
class Lighting:
    kind: str
    label: str
    weights: np.ndarray  # (K,) per usable direction of the subject, >= 0


def draw_lighting(kind: str, subject: Subject, rng: np.random.Generator,
                  bank: HdriBank | None) -> Lighting:
    """A lighting of the given kind whose weights sum to a random intensity (log-uniform in
    [1/2, 2], so that output = input gets the level wrong)."""
    if kind == "hdri":
        i, yaw = int(rng.integers(len(bank.paths))), float(rng.integers(360))
        w = restrict_light(bank.light(i, yaw), subject.dirs)
        label = f"{bank.names[i]} yaw {yaw:.0f}"
    else:
        front = np.flatnonzero(np.abs(subject.angles[:, 0]) <= FRONT_AZIMUTH)
        n = 1 if kind == "single" else int(rng.integers(2, 4))
        pick = rng.choice(front, size=n, replace=False)
        w = np.zeros(len(subject.dirs))
        w[pick] = 1.0 if n == 1 else rng.uniform(0.3, 1.0, size=n)
        label = " + ".join(f"{w[k] / w.sum():.2f} A{a:+d}E{e:+d}"
                           for k, (a, e) in zip(pick, subject.angles[pick]))
    intensity = float(np.exp(rng.uniform(math.log(0.5), math.log(2.0))))
    if w.sum() <= 0:
        raise InputError(f"{subject.name}: the lighting {label} misses every usable direction.")
    return Lighting(kind, f"{intensity:.2f} x ({label})", w * (intensity / w.sum()))


def draw_pairs(subject: Subject, n: int, seed: int, bank: HdriBank | None) -> list:
    """n fixed (A, B) pairs for a subject, lighting kinds in turn (hdri, single, few, ...)."""
    rng = np.random.default_rng([seed, subject.number])
    pairs = []
    for i in range(n):
        kind = KINDS[i % len(KINDS)]
        a = draw_lighting(kind, subject, rng, bank)
        b = draw_lighting(kind, subject, rng, bank)
        while np.allclose(a.weights, b.weights):  # a pair must change the light
            b = draw_lighting(kind, subject, rng, bank)
        pairs.append((a, b))
    return pairs


def relit_sum(subject: Subject, weights: np.ndarray) -> np.ndarray:
    """The subject's real image under a lighting: the weighted sum of its single-light images."""
    return np.tensordot(np.asarray(weights, np.float32), subject.images, axes=1)


def saturated_share(subject: Subject, weights: np.ndarray) -> np.ndarray:
    """(H, W) share of relit_sum that comes from clipped codes."""
    w = np.asarray(weights, np.float32)[:, None, None]
    clipped = (w * subject.images * subject.saturated).sum(axis=0)
    return clipped / np.maximum(relit_sum(subject, weights), 1e-12)


def face_mask(shape, subject: Subject | None = None, weights=None) -> np.ndarray:
    """The centred ellipse, minus pixels whose ground truth owes too much to clipped codes."""
    h, w = shape
    y, x = np.mgrid[:h, :w]
    ax, ay = ELLIPSE
    mask = ((x + 0.5 - w / 2) / (ax * w)) ** 2 + ((y + 0.5 - h / 2) / (ay * h)) ** 2 <= 1.0
    if subject is not None:
        mask &= saturated_share(subject, weights) <= SATURATED_SHARE
    return mask


# --------------------------------------------------------------------------------- relighting

class PipelineRelighter:
    """A shipped model run exactly as the product runs it (``addon.relight_image``) on a gray
    image replicated to three channels; the output goes back to gray by Rec.709 luminance.
    ``onnx_path``: the model's file, or a model loaded already (an engine session, which keeps
    its own threads and working size)."""

    def __init__(self, onnx_path, threads: int = 1, background: str | None = None,
                 exposure: str | None = None, working_size: int | None = None,
                 lift: float | None = None, template=None, template_axes: str = "y"):
        self.onnx_path = onnx_path
        self.threads = threads
        self.background = background or api.pipeline.DEFAULT_BACKGROUND
        self.exposure = exposure or api.pipeline.DEFAULT_EXPOSURE_MODE
        self.working_size = working_size  # None: the card's
        self.lift = lift  # None: the product's (portrait.INPUT_LIFT)
        # a face template's path in place of the product's (portrait.FACE_TEMPLATE), "none" for
        # none; None: the product's
        self.template = template
        self.template_axes = template_axes
        self.card = api.session(onnx_path, threads, working_size).card
        self.name = self.card.name if lift is None else f"{self.card.name} lift {lift:g}"
        if template is not None:
            self.name += (" no face template" if template == "none" else " face template"
                          + ("" if template_axes == "y" else f" {template_axes}"))

    def __call__(self, gray: np.ndarray, light: np.ndarray) -> np.ndarray:
        """(H, W) linear gray under some light -> (H, W) linear gray under ``light``."""
        rgb = np.repeat(np.asarray(gray, np.float32)[..., None], 3, axis=2)
        product = portrait.INPUT_LIFT
        try:
            if self.lift is not None:
                portrait.INPUT_LIFT = self.lift
            with (template_applied(None if self.template == "none" else self.template,
                                   self.template_axes)
                  if self.template is not None else contextlib.nullcontext()):
                y = api.relight_image(rgb, light, model=self.onnx_path, threads=self.threads,
                                      background=self.background, exposure=self.exposure,
                                      working_size=self.working_size)
        finally:
            portrait.INPUT_LIFT = product
        return normalise.luminance(y.astype(np.float32))


def baselines(gray_a: np.ndarray, light_a: np.ndarray, light_b: np.ndarray) -> dict:
    """training/eval/evaluate.py's two baselines on the gray image (replicated, then luminance), and
    the light-blind FLATTENED reference: ratio * sqrt(input * mean(input))."""
    sample = {"img_t_i": np.repeat(np.asarray(gray_a, np.float32)[None], 3, axis=0),
              "light_i": light_a, "light_k": light_b}
    gray = np.asarray(gray_a, np.float32)
    power_a, power_b = (float(normalise.luminance(lightvec.total_power(x).astype(np.float32)))
                        for x in (light_a, light_b))
    ratio = power_b / power_a if power_a > 0 else 0.0
    return {"identity": normalise.luminance(baseline_identity(sample).transpose(1, 2, 0)),
            "irradiance_ratio": normalise.luminance(
                baseline_irradiance_ratio(sample).transpose(1, 2, 0)),
            FLATTENED: np.float32(ratio) * np.sqrt(gray * np.float32(gray.mean()))}


FIT_MIN_LIT = 4  # a pixel's photometric fit needs this many images in which it is lit
FIT_CODES = (15, 250)  # a pixel is lit and unclipped where its code lies strictly between these


def lit_unclipped(images: np.ndarray) -> np.ndarray:
    """Bool of the shape of ``images`` (linear, 1 at the top code): lit and unclipped pixels,
    their codes within FIT_CODES."""
    codes = np.asarray(images) * 255.0
    return (codes > FIT_CODES[0]) & (codes < FIT_CODES[1])


def photometric_fit(images: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """((3, h*w) albedo times unit normal, (h*w,) bool where fitted) from (K, h, w) linear images
    under distant lights ``dirs`` (K, 3): per pixel, least squares over the images in which that
    pixel is lit and unclipped (lit_unclipped), so that the sides of the face and the eye
    sockets, which some lights leave dark, are fitted from the lights that reach them."""
    k = len(dirs)
    y = images.reshape(k, -1).astype(np.float64)
    w = lit_unclipped(y).astype(np.float64)
    d = np.asarray(dirs, np.float64)
    gram = np.einsum("kp,ki,kj->pij", w, d, d) + 1e-9 * np.eye(3)
    rhs = np.einsum("kp,ki->pi", w * y, d)
    ok = w.sum(0) >= FIT_MIN_LIT
    b = np.zeros((y.shape[1], 3))
    b[ok] = np.linalg.solve(gram[ok], rhs[ok][..., None])[..., 0]
    return b.T, ok


def subject_shading(subject: Subject, fit=None) -> tuple[np.ndarray, np.ndarray]:
    """((K, h*w) each usable light's Lambertian radiance from the subject's photometric_fit,
    (h*w,) bool where the fit exists; ``fit``: that fit, when already made)."""
    b, ok = photometric_fit(subject.images, subject.dirs) if fit is None else fit
    return np.clip(subject.dirs @ b, 0.0, None), ok


def ceilings(gray_a: np.ndarray, a: Lighting, b: Lighting, shading) -> dict:
    """LAMBERT_FIT and LAMBERT_RATIO for one pair (``shading``: subject_shading); where the fit
    does not exist both take the input times the fitted pixels' median ratio."""
    per_light, ok = shading
    h, w = gray_a.shape
    x = np.asarray(gray_a, np.float64).reshape(-1)
    e_a, e_b = a.weights @ per_light, b.weights @ per_light
    if not ok.any():
        return {LAMBERT_FIT: gray_a.copy(), LAMBERT_RATIO: gray_a.copy()}
    floor = max(SOURCE_FLOOR * float(np.percentile(e_a[ok], 90)), 1e-12)
    ratio = e_b / np.maximum(e_a, floor)
    rest = float(np.median(ratio[ok]))
    out = {LAMBERT_FIT: np.where(ok, e_b, x * rest), LAMBERT_RATIO: x * np.where(ok, ratio, rest)}
    return {k: v.reshape(h, w).astype(np.float32) for k, v in out.items()}


def ls_gain(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray) -> float:
    """The gain g minimising |g pred - gt|^2 over the mask (1 where pred is black there)."""
    p, t = pred[mask].astype(np.float64), gt[mask].astype(np.float64)
    pp = float(p @ p)
    return float(p @ t) / pp if pp > 0 and np.isfinite(pp) else 1.0


def metrics(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray) -> dict:
    return image_metrics(pred[None], gt[None], mask)


@dataclasses.dataclass
class PairResult:
    subject: str
    kind: str
    a: str
    b: str
    gt: np.ndarray
    mask: np.ndarray
    inputs: np.ndarray     # (H, W) the real image under A
    light_b: np.ndarray    # (16, 16, 3) the network's target light
    outputs: dict          # method -> (H, W) linear gray, absolute
    elevations: tuple = (0.0, 0.0)  # degrees: A's and B's light_elevation


def relight_pair(subject: Subject, a: Lighting, b: Lighting, relighters: dict,
                 shading=None) -> PairResult:
    """Ground truth, mask and every method's output for one (A, B) pair (``shading``: the
    subject's subject_shading, computed here when not given)."""
    img_a, gt = relit_sum(subject, a.weights), relit_sum(subject, b.weights)
    light_a = light_vector(subject.dirs, a.weights)
    light_b = light_vector(subject.dirs, b.weights)
    outs = {name: fn(img_a, light_b) for name, fn in relighters.items()}
    outs.update(baselines(img_a, light_a, light_b))
    outs.update(ceilings(img_a, a, b, subject_shading(subject) if shading is None else shading))
    return PairResult(subject.name, a.kind, a.label, b.label, gt,
                      face_mask(gt.shape, subject, b.weights), img_a, light_b, outs,
                      (light_elevation(subject.dirs, a.weights),
                       light_elevation(subject.dirs, b.weights)))


def light_elevation(dirs: np.ndarray, weights: np.ndarray) -> float:
    """Degrees above the camera's horizontal plane of a lighting's centre: the weighted mean of
    its directions (K, 3) (+Y up)."""
    d = (np.asarray(weights, np.float64)[:, None] * np.asarray(dirs, np.float64)).sum(0)
    norm = float(np.linalg.norm(d))
    return float(np.degrees(np.arcsin(np.clip(d[1] / norm, -1.0, 1.0)))) if norm > 0 else 0.0


def iter_pairs(subjects, relighters: dict, n_pairs: int, seed: int, bank):
    for subject in subjects:
        shading = subject_shading(subject)
        for a, b in draw_pairs(subject, n_pairs, seed, bank):
            yield relight_pair(subject, a, b, relighters, shading)


def fit_gains(results) -> dict:
    """One gain per method: the one that minimises its mean RMSE (the reported metric, on a
    subset of each mask) over the given pairs (the tune subjects')."""
    store: dict[str, list] = {}
    for r in results:
        white = white_level(r.gt[None], r.mask)
        target = to_unit(r.gt[r.mask][::GAIN_SEARCH_STRIDE], white)
        for name, y in r.outputs.items():
            store.setdefault(name, []).append((y[r.mask][::GAIN_SEARCH_STRIDE] / white, target))
    return {name: best_gain(pairs) for name, pairs in store.items()}


def mean_rmse(pairs, gain: float) -> float:
    return float(np.mean([np.sqrt(np.mean((srgb_encode(gain * p) - t) ** 2))
                          for p, t in pairs]))


def best_gain(pairs) -> float:
    """Grid search in log2 gain over [1/256, 256] by quarter steps, then refined by 1/64 steps."""
    coarse = 2.0 ** np.arange(-8.0, 8.01, 0.25)
    g = min(coarse, key=lambda c: mean_rmse(pairs, c))
    fine = g * 2.0 ** np.arange(-0.25, 0.2501, 1.0 / 64)
    return float(min(fine, key=lambda c: mean_rmse(pairs, c)))


def balance(img: np.ndarray, mask: np.ndarray) -> tuple[float, float]:
    """(left/right, top/bottom) balance of an image over the mask: (right - left) / (right +
    left) of the two halves' means (and bottom - top): where the light comes from, independent
    of the image's gain."""
    h, w = img.shape
    right = np.arange(w)[None, :] >= w / 2
    below = np.arange(h)[:, None] >= h / 2
    return (half_balance(img, mask & ~right, mask & right),
            half_balance(img, mask & ~below, mask & below))


def half_balance(img: np.ndarray, first: np.ndarray, second: np.ndarray) -> float:
    """(second - first) / (second + first) of ``img``'s means over two masks (a side with no
    pixels counts as 0; 0 when both are 0): balance's, for any split."""
    a = float(img[first].mean()) if first.any() else 0.0
    b = float(img[second].mean()) if second.any() else 0.0
    return (b - a) / (a + b) if a + b > 0 else 0.0


BOOTSTRAP = 1000  # resamplings of the subjects for the balance correlations' intervals


def _correlation(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.corrcoef(a, b)[0, 1]) if np.std(a) > 0 and np.std(b) > 0 else 0.0


def _ranks(a: np.ndarray) -> np.ndarray:
    return np.argsort(np.argsort(a, kind="stable"), kind="stable").astype(np.float64)


INPUT_METHOD = "identity"  # the baseline whose output is the input: its balance is the input's


def balance_split(pred: np.ndarray, truth: np.ndarray, inputs: np.ndarray) -> dict:
    """{"truth": a, "input": b}: the least-squares split pred ~ a truth + b inputs + c of one
    balance axis over pairs (balance_correlation's ``<axis>_from``)."""
    design = np.stack([truth, inputs, np.ones_like(truth)], 1)
    coef = np.linalg.lstsq(design, pred, rcond=None)[0]
    return {"truth": float(coef[0]), "input": float(coef[1])}


def subject_draws(subjects, seed: int = 0) -> list[np.ndarray]:
    """BOOTSTRAP resamplings of the subjects (with replacement), each as the indices of all its
    subjects' rows (``subjects``: each row's subject); none for a single subject."""
    subjects = np.asarray(subjects)
    names = sorted(set(subjects.tolist()))
    rng = np.random.default_rng(seed)
    return [np.concatenate([np.flatnonzero(subjects == names[k])
                            for k in rng.integers(len(names), size=len(names))])
            for _ in range(BOOTSTRAP if len(names) > 1 else 0)]


def balance_correlation(rows: list[tuple], seed: int = 0, reference: str | None = None) -> dict:
    """Per method, the Pearson correlation over pairs of its output's balance with the ground
    truth's, left/right and top/bottom (rows: (kind, scores, subject, balances)), and the 5th
    and 95th percentiles of each over BOOTSTRAP resamplings of the subjects (with replacement,
    each with all its pairs): how far the figure moves with the faces it was measured on. On a
    dozen subjects the top/bottom figure moves by several hundredths, so settings that differ
    by less are not told apart by it. Where the rows hold the input's balance (the identity
    method's), also the least-squares split of each method's balance into the truth's and the
    input's (``<axis>_from``: {"truth": a, "input": b} in a truth + b input + c): a relit face
    that follows the target light has a near 1 and b near 0; the ratio of a network whose
    normals are wrong keeps part of the input's light (b) and answers the target's weakly (a).
    With ``reference`` (a method's name), each other method's gain in correlation over it
    (``<axis>_gain``) and the gain's percentiles over the same resamplings (``<axis>_gain_90``):
    a paired comparison, in which the pairs' own difficulty cancels. ``<axis>_rank``: the rank
    (Spearman) correlation, which one pair far off the truth cannot carry as it carries the
    Pearson figure: photometric stereo's normals on the tune subjects, 0.75 against 0.87 by
    rank, lose the difference on one pair (a light from straight above on one subject)."""
    out, boots = {}, {}
    truth = np.array([r[3]["ground_truth"] for r in rows], np.float64)
    inputs = (np.array([r[3][INPUT_METHOD] for r in rows], np.float64)
              if rows and INPUT_METHOD in rows[0][3] else None)
    subjects = [r[2] for r in rows]
    n_subjects = len(set(subjects))
    draws = subject_draws(subjects, seed)

    def interval(values, fallback):  # 5th and 95th percentiles; a single subject has none
        return ([float(np.percentile(values, 5)), float(np.percentile(values, 95))]
                if len(values) else [fallback, fallback])

    for m in rows[0][3] if rows else ():
        if m == "ground_truth":
            continue
        pred = np.array([r[3][m] for r in rows], np.float64)
        res = {"pairs": len(rows), "subjects": n_subjects}
        for axis, key in ((0, "left_right"), (1, "top_bottom")):
            a, b = pred[:, axis], truth[:, axis]
            res[key] = _correlation(a, b)
            res[f"{key}_rank"] = _correlation(_ranks(a), _ranks(b))
            boots[m, key] = np.array([_correlation(a[i], b[i]) for i in draws])
            res[f"{key}_90"] = interval(boots[m, key], res[key])
            if inputs is not None and m != INPUT_METHOD and len(rows) > 3:
                res[f"{key}_from"] = balance_split(a, b, inputs[:, axis])
        out[m] = res
    for m, res in out.items() if reference else ():
        for key in ("left_right", "top_bottom") if m != reference else ():
            res[f"{key}_gain"] = res[key] - out[reference][key]
            res[f"{key}_gain_90"] = interval(boots[m, key] - boots[reference, key],
                                             res[f"{key}_gain"])
    return out


ELEVATION_BAND = 15.0  # degrees: a lighting's centre above, within or below this of level


def elevation_bands(elevation: np.ndarray) -> dict:
    """{"above", "level", "below": bool masks} of lightings by their centre's ``elevation``
    (degrees): more than ELEVATION_BAND above level, within it, more than it below."""
    e = np.asarray(elevation, np.float64)
    return {"above": e > ELEVATION_BAND, "level": np.abs(e) <= ELEVATION_BAND,
            "below": e < -ELEVATION_BAND}


def balance_by_elevation(rows: list[tuple]) -> dict:
    """Per method, its top/bottom balance against the truth's over the pairs whose input (A) or
    target (B) light lies above, level with or below the face (ELEVATION_BAND; rows carry
    (elevation A, elevation B) as their fifth item): pairs, Pearson correlation, mean error
    (relit minus truth; the balance is bottom minus top, so positive: the relit face brighter
    at the bottom than the truth is, as a light from above that the relit face answers too
    weakly leaves it) and mean absolute error. Where a network's up/down goes wrong: with the
    input's light, or with the target's."""
    rows = [r for r in rows if len(r) > 4]
    if not rows:
        return {}
    truth = np.array([r[3]["ground_truth"][1] for r in rows], np.float64)
    elev = np.array([r[4] for r in rows], np.float64)
    bins = {f"{side} {band}": sel for side, col in (("input", 0), ("target", 1))
            for band, sel in elevation_bands(elev[:, col]).items()}
    out = {}
    for m in rows[0][3]:
        if m == "ground_truth":
            continue
        pred = np.array([r[3][m][1] for r in rows], np.float64)
        res = {}
        for name, sel in bins.items():
            err = pred[sel] - truth[sel]
            res[name] = {"pairs": int(sel.sum()),  # None: too few pairs for the figure
                         "correlation": _correlation(pred[sel], truth[sel])
                         if sel.sum() > 2 else None,
                         "bias": float(err.mean()) if len(err) else None,
                         "mae": float(np.abs(err).mean()) if len(err) else None}
        out[m] = res
    return out


def score_pair(r: PairResult, gains: dict) -> dict:
    """{view: {method: metrics}} for one pair."""
    out = {v: {} for v in VIEWS}
    for name, y in r.outputs.items():
        out["calibrated"][name] = metrics(gains.get(name, 1.0) * y, r.gt, r.mask)
        out["scale_invariant"][name] = metrics(ls_gain(y, r.gt, r.mask) * y, r.gt, r.mask)
    return out


def summarise(rows: list[tuple]) -> dict:
    """rows of (kind, score_pair, ...) -> {view: {method: {kind|'all': mean metrics + pairs}}}."""
    out: dict = {}
    for view in VIEWS:
        methods = list(rows[0][1][view]) if rows else []
        out[view] = {}
        for m in methods:
            out[view][m] = {}
            for kind in (*KINDS, "all"):
                sel = [s[view][m] for k, s, *_ in rows if kind in ("all", k)]
                if sel:
                    out[view][m][kind] = {**mean_metrics(sel), "pairs": len(sel)}
    return out


# --------------------------------------------------------------------------------- reporting

def markdown(summary: dict, models: list[str], paired: dict | None = None) -> str:
    lines = []
    for view in VIEWS:
        lines += metrics_table(summary[view], view, models)
    if paired:
        lines += paired_table(paired, models)
    return "\n".join(lines)


def metrics_table(table: dict, view: str, models: list[str]) -> list[str]:
    kinds = [k for k in (*KINDS, "all") if any(k in table[m] for m in table)]
    lines = [f"**{view}** (RMSE / PSNR dB / SSIM on the face ellipse, test subjects)", "",
             "| method | " + " | ".join(kinds) + " |", "| --- |" + " --- |" * len(kinds)]
    for m in [*models, *REFERENCES]:
        cells = [("{rmse:.4f} / {psnr:.2f} / {ssim:.4f}".format(**table[m][k])
                  if k in table[m] else "-") for k in kinds]
        lines.append(f"| {m} | " + " | ".join(cells) + " |")
    return lines + [""]


def paired_table(paired: dict, models: list[str]) -> list[str]:
    lines = ["Model minus reference, overall RMSE (negative: the model is better), +- one "
             "standard error over subjects; share of pairs the model wins", "",
             "| model, view | " + " | ".join(REFERENCES) + " |",
             "| --- |" + " --- |" * len(REFERENCES)]
    for m in models:
        for view in VIEWS:
            cells = []
            for ref in REFERENCES:
                c = paired[view][m][ref]
                se = "" if c["se_subjects"] is None else f" +- {c['se_subjects']:.4f}"
                cells.append(f"{c['mean_rmse_diff']:+.4f}{se}; wins {c['win_share']:.2f}")
            lines.append(f"| {m}, {view} | " + " | ".join(cells) + " |")
    return lines + [""]


def paired_comparison(rows: list[tuple], models: list[str]) -> dict:
    """{view: {model: {reference: win share, mean RMSE difference and its standard error}}}.

    rows: (kind, score_pair, subject). The difference is model minus reference (negative: the
    model is better); its standard error is taken over subjects' mean differences, because the
    pairs of one subject are not independent of each other."""
    out: dict = {}
    for view in VIEWS:
        out[view] = {}
        for m in models:
            out[view][m] = {}
            for ref in REFERENCES:
                d = np.array([s[view][m]["rmse"] - s[view][ref]["rmse"] for _, s, *_ in rows])
                subj = np.array([row[2] for row in rows])
                means = np.array([d[subj == n].mean() for n in dict.fromkeys(subj)])
                se = float(means.std(ddof=1) / math.sqrt(len(means))) if len(means) > 1 else None
                out[view][m][ref] = {"win_share": float(np.mean(d < 0)),
                                     "mean_rmse_diff": float(means.mean()), "se_subjects": se}
    return out


def verdict(summary: dict, models: list[str], against=BASELINES) -> dict:
    """Per view and model: whether its overall RMSE is below that of every method in ``against``."""
    out = {}
    for view in VIEWS:
        t = summary[view]
        out[view] = {m: bool(all(t[m]["all"]["rmse"] < t[b]["all"]["rmse"] for b in against))
                     for m in models if "all" in t.get(m, {})}
    return out


def sheet_row(r: PairResult, gains: dict, order: list[str]) -> np.ndarray:
    """input | each method (calibrated) | ground truth | B's light map, display-normalised."""
    white = white_level(r.gt[None], r.mask)
    tiles = [r.inputs * (white / max(white_level(r.inputs[None], r.mask), 1e-12))]
    tiles += [gains.get(m, 1.0) * r.outputs[m] for m in order] + [r.gt]
    gray = [to_unit(t, white) for t in tiles]
    h, w = r.gt.shape
    preview = np.kron(lightvec.to_preview(r.light_b), np.ones((w // 16, w // 16, 1)))
    pad = np.zeros((h, w, 3))
    pad[(h - preview.shape[0]) // 2:][:preview.shape[0], :preview.shape[1]] = preview
    return np.concatenate([np.repeat(g[..., None], 3, axis=2) for g in gray] + [pad], axis=1)


def write_sheet(path, rows: list[np.ndarray]) -> None:
    from ..lightstage.png import write_png

    img = np.concatenate(rows, axis=0)
    path = pathlib.Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_png(path, (np.clip(img, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8))


# --------------------------------------------------------------------------------- data checks

def azimuth_sign_check(subjects) -> dict:
    """Mirror pairs (A, -A), 20 <= |A| <= FRONT_AZIMUTH (lights further back barely reach the
    face): is the image lit from camera +X the brighter one on the image's right half?"""
    agree = total = 0
    for s in subjects:
        index = {tuple(a): k for k, a in enumerate(s.angles)}
        for (az, el), k in index.items():
            j = index.get((-az, el))
            if not 20 <= az <= FRONT_AZIMUTH or j is None:
                continue
            plus_x = j if s.dirs[j, 0] > 0 else k  # the image whose light is at camera +X
            other = k if plus_x == j else j
            w = s.images.shape[2] // 2
            right = s.images[plus_x][:, w:].mean() - s.images[other][:, w:].mean()
            agree += bool(right > 0)
            total += 1
    return {"pairs": total, "agree": agree}


def gamma_check(subject: Subject, gammas=(0.8, 1.0, 1.2, 1.8, 2.2)) -> dict:
    """Leave-one-out Lambertian prediction error (RMS, codes) of the near-frontal images for each
    decoding gamma, on pixels lit and unclipped in all of them: the true decoding predicts best."""
    az, el = np.abs(subject.angles).T
    sel = np.flatnonzero((az <= 50) & (el <= 40))
    images = subject.images[sel].reshape(len(sel), -1)
    codes = images * 255.0
    ok = np.all(lit_unclipped(images), axis=0)
    lights, x = subject.dirs[sel], codes[:, ok]
    out = {}
    for g in gammas:
        y = (x / 255.0) ** g
        err = []
        for k in range(len(sel)):
            rest = np.arange(len(sel)) != k
            b = np.linalg.lstsq(lights[rest], y[rest], rcond=None)[0]
            pred = 255.0 * np.clip(lights[k] @ b, 0.0, None) ** (1.0 / g)
            err.append(np.mean((pred - x[k]) ** 2))
        out[f"{g:.1f}"] = float(np.sqrt(np.mean(err)))
    return out


def check_data(root, names) -> None:
    subjects = [load_subject(root, n) for n in names]
    print("ambient:", {s.name: s.ambient for s in subjects})
    print("dropped:", {s.name: s.dropped for s in subjects if s.dropped})
    print("usable directions per subject:", sorted({len(s.dirs) for s in subjects}))
    print("azimuth sign (camera +X lights the right half):", azimuth_sign_check(subjects))
    for s in subjects[:: max(1, len(subjects) // 5)]:
        print(f"{s.name} leave-one-out RMS (codes) by decoding gamma:", gamma_check(s))


# --------------------------------------------------------------------------------- main

DEFAULT_JSON = ROOT / "bench" / "results" / "yale.json"


def select_subjects(names: list[str], quick: bool,
                    split: str = "test") -> tuple[list[str], list[str]]:
    """(subjects the gains are fitted on, subjects reported). ``split`` "tune": the tune
    subjects are reported too, for choosing between variants without looking at the test
    subjects (their calibrated view is then in-sample)."""
    tune = [n for n in names if int(n[5:]) in TUNE_SUBJECTS]
    test = [n for n in names if int(n[5:]) not in TUNE_SUBJECTS]
    if split == "tune":
        test = tune
    return (tune[:1], test[:2]) if quick else (tune, test)


def _refuse(message: str):
    raise InputError(message) from None


def run(onnx_paths, root=None, data_root=None, n_pairs: int = 12, seed: int = 2021,
        quick: bool = False, threads: int = 1, sheet_path=None, sheet_rows: int = 6,
        progress=print, split: str = "test", lifts=(), template=None,
        template_axes: str = "y", sessions=()) -> dict:
    """Evaluate the models; returns the JSON-able result (tables on the test subjects).
    ``sessions``: models loaded already (engine sessions, each card with its own name: e.g.
    training.eval.buffer_swap's), relit after the files' on the same pairs.
    ``lifts``: the first model again for each, its crops lifted by that power (an experiment
    on portrait.INPUT_LIFT, compared on the same pairs). ``template``: a face template's path,
    or "none": the first model again with that template over its normals' components
    ``template_axes`` in place of the product's, or with none (template_applied; an
    experiment, on the same pairs)."""
    data_root = pathlib.Path(data_root) if data_root else default_root().parents[1]
    root = pathlib.Path(root) if root else data_root / "yale" / "CroppedYale"
    tune_names, test_names = select_subjects(subject_names(root), quick, split)
    if quick:
        n_pairs = min(n_pairs, len(KINDS))
    relighters = {}
    for p in [*onnx_paths, *sessions]:
        r = PipelineRelighter(p, threads)
        if r.name in relighters or r.name in REFERENCES:
            raise InputError(f"Two models are named {r.name} (or a model is named like a "
                             "baseline); give each --onnx model a card with its own name.")
        relighters[r.name] = r
    for lift in lifts:
        r = PipelineRelighter(onnx_paths[0], threads, lift=lift)
        relighters[r.name] = r
    if template is not None:
        template_flag_path(template, _refuse)  # refused here, before any relighting
        r = PipelineRelighter(onnx_paths[0], threads, template=template,
                              template_axes=template_axes)
        relighters[r.name] = r
    models = list(relighters)
    bank = HdriBank(data_root)
    t0 = time.perf_counter()
    tune = [load_subject(root, n) for n in tune_names]
    # A reported subject that is also a tune one (--split tune) is relit once: its pairs are
    # kept from the gains' fit for the tables (they are drawn per subject, so they are the same).
    reported, kept = set(test_names), {}

    def tune_pairs():
        for r in iter_pairs(tune, relighters, n_pairs, seed, bank):
            if r.subject in reported:
                kept.setdefault(r.subject, []).append(r)
            yield r

    gains = fit_gains(tune_pairs())
    progress(f"gains from {len(tune)} tune subjects: "
             + ", ".join(f"{k} {v:.3f}" for k, v in gains.items()))
    rows, sheet, dropped, ambient = [], [], {}, {}
    loaded = {s.name: s for s in tune}
    for name in test_names:
        s = loaded.get(name) or load_subject(root, name)
        dropped[name] = [list(a) for a, _ in s.dropped]
        ambient[name] = s.ambient
        for r in kept.pop(name, None) or iter_pairs([s], relighters, n_pairs, seed, bank):
            bal = {name: balance(y, r.mask) for name, y in r.outputs.items()}
            bal["ground_truth"] = balance(r.gt, r.mask)
            rows.append((r.kind, score_pair(r, gains), r.subject, bal, r.elevations))
            if sheet_path and len(sheet) < sheet_rows and r.kind == KINDS[len(sheet) % 3]:
                sheet.append(r)  # one pair of each kind in turn, from the first subjects
        progress(f"{name}: {len(rows)} pairs so far, {time.perf_counter() - t0:.0f} s")
    summary = summarise(rows)
    if sheet_path and sheet:
        write_sheet(sheet_path, [sheet_row(r, gains, [*models, *REFERENCES]) for r in sheet])
    return {
        "what": "CroppedYale real-data relighting check (training/eval/yale.py)",
        "models": {m: {"onnx": str(relighters[m].card.onnx_path.relative_to(ROOT))
                       if relighters[m].card.onnx_path.is_relative_to(ROOT)
                       else str(relighters[m].card.onnx_path),
                       "sha256": relighters[m].card.sha256,
                       "working_size": relighters[m].card.working_size} for m in models},
        "split": {"tune": tune_names, "test": test_names, "reported": split},
        "pairs_per_subject": n_pairs, "seed": seed, "quick": quick,
        "gains": gains, "results": summary, "beats_both_baselines": verdict(summary, models),
        "beats_flattened_ratio": verdict(summary, models, (FLATTENED,)),
        "paired": paired_comparison(rows, models) if rows else {},
        # with several models, each one's paired gain over the first (the pairs' own
        # difficulty cancels: a checkpoint against the shipped model)
        "balance_correlation": balance_correlation(rows, reference=models[0]
                                                   if len(models) > 1 else None),
        "top_bottom_by_elevation": balance_by_elevation(rows),
        "data": {"dropped_failed_strobes": {k: v for k, v in dropped.items() if v},
                 "ambient": ambient},
        "seconds": round(time.perf_counter() - t0, 1),
    }


def report_body(res: dict) -> str:
    """The Markdown of one run: what was compared, the tables, the balance correlations."""
    models = list(res["models"])
    n_test = len(res["split"]["test"])
    who = (f"{n_test} held-out CroppedYale subjects ({len(res['split']['tune'])} more are kept "
           "to calibrate one gain per method)" if res["split"].get("reported") != "tune" else
           f"the {n_test} CroppedYale tune subjects, not the held-out test subjects (the gains "
           "are fitted on the same ones, so the calibrated view is in-sample)")
    lines = [f"Real one-light-at-a-time images of {who}, "
             f"{res['pairs_per_subject']} pairs each, relit from lighting A to B and compared with "
             "the real sum for B, grey in and grey out. Every image goes through "
             "`addon.relight_image`, exactly what the pipeline does to a frame. Calibrated view: "
             "one gain per method; scale-invariant view: each output times its own least-squares "
             "gain. Models: " + ", ".join(f"`{res['models'][m]['onnx']}`" for m in models) + ". "
             f"`{LAMBERT_FIT}` and `{LAMBERT_RATIO}` are ceilings, not methods: they see all of "
             "the subject's photos (a Lambertian photometric-stereo fit per pixel); the first "
             "renders B from the fit, the second multiplies the input by the fit's exact diffuse "
             "shading ratio, B over A (no cast shadows in either).",
             "", res.get("table_markdown") or markdown(res["results"], models, res["paired"]), "",
             "Correlation of the output's left/right and top/bottom balance with the truth's "
             "(in brackets, its 5th to 95th percentile when the subjects are resampled: how much "
             "of a difference is the faces it was measured on):", "",
             "| | left/right | top/bottom |", "|---|---|---|"]

    def cell(c: dict, key: str) -> str:
        lo_hi = c.get(f"{key}_90")
        return f"{c[key]:.3f}" + (f" ({lo_hi[0]:.2f}-{lo_hi[1]:.2f})" if lo_hi else "")

    for name, c in res["balance_correlation"].items():
        lines.append(f"| {name} | {cell(c, 'left_right')} | {cell(c, 'top_bottom')} |")
    gains = {n: c for n, c in res["balance_correlation"].items() if "top_bottom_gain" in c
             and n in res["models"]}
    if gains:
        lines += ["", f"Paired gain in correlation over `{models[0]}` on the same pairs (in "
                  "brackets, its 5th to 95th percentile over the same resamplings):", "",
                  "| | left/right | top/bottom |", "|---|---|---|"]
        for name, c in gains.items():
            lines.append(f"| {name} | " + " | ".join(
                f"{c[k + '_gain']:+.3f} ({c[k + '_gain_90'][0]:+.3f} to "
                f"{c[k + '_gain_90'][1]:+.3f})" for k in ("left_right", "top_bottom")) + " |")
    by_elev = {n: c for n, c in res.get("top_bottom_by_elevation", {}).items()
               if n in res["models"]}
    if by_elev:
        lines += ["", "Top/bottom balance by where the input's (A) and the target's (B) light "
                  f"lies (above, level within {ELEVATION_BAND:g} degrees, below): correlation "
                  "with the truth's, mean error (relit minus truth; +: brighter at the bottom), "
                  "pairs.",
                  "", "| | " + " | ".join(next(iter(by_elev.values()))) + " |",
                  "|---|" + "---|" * len(next(iter(by_elev.values())))]
        for name, c in by_elev.items():
            lines.append(f"| {name} | " + " | ".join(
                ("-" if b["correlation"] is None else f"{b['correlation']:.2f}") + ", "
                + ("-" if b["bias"] is None else f"{b['bias']:+.3f}") + f", {b['pairs']}"
                for b in c.values())
                + " |")
    split = {n: c for n, c in res["balance_correlation"].items() if "top_bottom_from" in c}
    if split:
        lines += ["", "Each output's balance split by least squares into the truth's and the "
                  "input's (a truth + b input + c over the pairs): a method that follows the "
                  "target light has a near 1 and b near 0.", "",
                  "| | left/right a, b | top/bottom a, b |", "|---|---|---|"]
        for name, c in split.items():
            lr, tb = c["left_right_from"], c["top_bottom_from"]
            lines.append(f"| {name} | {lr['truth']:.2f}, {lr['input']:.2f} | "
                         f"{tb['truth']:.2f}, {tb['input']:.2f} |")
    for view, verdicts in res["beats_both_baselines"].items():
        beat = [m for m, yes in verdicts.items() if yes]
        lines += ["", f"Beat both light-blind baselines on overall RMSE, {view.replace('_', '-')} "
                  f"view: {', '.join(beat) or 'none'}."]
    lines += ["", f"{res['seconds']} s."]
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description="relighting checked against CroppedYale real faces")
    p.add_argument("--onnx", action="append", default=[], help="a model (.onnx beside its card); "
                   "repeat for several")
    p.add_argument("--data", help="the shared data folder (default ../shared/data)")
    p.add_argument("--pairs", type=int, default=12, help="(A, B) pairs per subject (kinds in turn)")
    p.add_argument("--seed", type=int, default=2021)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--quick", action="store_true", help="1 tune and 2 test subjects, 3 pairs each")
    p.add_argument("--json", default=str(DEFAULT_JSON))
    p.add_argument("--sheet", default=str(ROOT / "out" / "yale" / "yale_sheet.png"),
                   help="PNG sheet (git-ignored out/: never commit pictures of this data)")
    p.add_argument("--check-data", action="store_true", help="print the data checks and exit")
    p.add_argument("--split", choices=["test", "tune"], default="test",
                   help="tune: report the 10 tune subjects instead, to choose between variants "
                        "without looking at the test subjects (give --json elsewhere)")
    p.add_argument("--input-level", type=float, help="feed the intrinsic networks' crops at this "
                   "level instead of the product's (addon.intrinsic.INPUT_LEVEL; the face crop's "
                   "finer sampling keeps addon.portrait.FINER_LEVEL): an experiment (its results "
                   "are not the product's)")
    p.add_argument("--input-lift", type=float, help="lift the intrinsic networks' crops by this "
                   "power instead of the product's (addon.portrait.INPUT_LIFT; 1: not at all): "
                   "an experiment (its results are not the product's)")
    p.add_argument("--compare-lift", type=float, action="append", default=[],
                   help="also relight with the first model's crops lifted by this power, on the "
                        "same pairs (its balance gain is paired with the first model's); repeat "
                        "for several")
    p.add_argument("--compare-face-template", metavar="NPZ",
                   help="also relight with the first model's normals' low band over the face "
                        "skin taken from this face template (training.intrinsic.template) "
                        "instead of the product's (addon/facetemplate.py), or from none with "
                        "'none', on the same pairs: an experiment")
    p.add_argument("--face-template-axes", choices=sorted(facetemplate.AXES), default="y",
                   help="the normals' components the face template gives (default y, the "
                        "vertical: the up/down shape)")
    a = p.parse_args(argv)
    if a.input_level is not None and not a.input_level > 0:
        p.error("--input-level must be positive")
    for lift in ([] if a.input_lift is None else [a.input_lift]) + a.compare_lift:
        if not 0 < lift <= 1:
            p.error("--input-lift and --compare-lift must lie in (0, 1]")
    if a.split == "tune" and pathlib.Path(a.json).resolve() == DEFAULT_JSON.resolve():
        p.error("--split tune would overwrite the test subjects' results; give --json elsewhere")
    data_root = pathlib.Path(a.data) if a.data else default_root().parents[1]
    root = data_root / "yale" / "CroppedYale"
    if a.check_data:
        check_data(root, subject_names(root))
        return 0
    if not a.onnx:
        p.error("give at least one --onnx model (or --check-data)")
    m = report.machine()
    level, lift = intrinsic.INPUT_LEVEL, portrait.INPUT_LIFT
    try:
        if a.input_level is not None:
            intrinsic.INPUT_LEVEL = a.input_level
        if a.input_lift is not None:
            portrait.INPUT_LIFT = a.input_lift
        res = run(a.onnx, root, data_root, a.pairs, a.seed, a.quick, a.threads, a.sheet,
                  progress=lambda msg: print(msg, file=sys.stderr), split=a.split,
                  lifts=a.compare_lift, template=a.compare_face_template,
                  template_axes=a.face_template_axes)
    except InputError as e:  # bad data or models: the message says what to do
        print(f"yale: {e}", file=sys.stderr)
        return 2
    finally:
        intrinsic.INPUT_LEVEL, portrait.INPUT_LIFT = level, lift
    models = list(res["models"])
    table = markdown(res["results"], models, res["paired"])
    res.update({"table_markdown": table, "date": m["date"], "machine": report.machine_line(m),
                "command": "python -m training.eval.yale " + " ".join(argv if argv is not None
                                                                     else sys.argv[1:])})
    print(table)
    print(f"beats both baselines (overall RMSE, {a.split} subjects):",
          res["beats_both_baselines"])
    print("beats the light-blind flattened_ratio:", res["beats_flattened_ratio"])
    print("balance correlation with the ground truth (left/right, top/bottom):")
    for name, c in res["balance_correlation"].items():
        print(f"  {name}: {c['left_right']:.3f}, {c['top_bottom']:.3f}")
    print(f"{res['seconds']} s; gains {res['gains']}")
    out = pathlib.Path(a.json)
    md = report.write(out.with_suffix(""), "Real faces: CroppedYale", res["command"], res["machine"],
                      report_body(res), res)
    print(f"wrote {md}, {out}" + (f" and {a.sheet}" if a.sheet else ""))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
