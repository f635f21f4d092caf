"""Real-face normals: the intrinsic network's normals against photometric stereo on CroppedYale.

    .venv/bin/python -m training.eval.yale_normals --onnx models/relight-portrait.onnx [--onnx ...]
        [--split tune|test] [--relight [--pairs N] [--low-sigma S] [--no-shadows] [--swap ONNX]]
        [--response] [--albedo] [--relief]

A subject's single-light images give its Lambertian normals by least squares per pixel over the
images in which that pixel is lit and unclipped (photometric stereo, yale.photometric_fit: the
sides of the face and the eye sockets too; the data decisions of training/eval/yale.py, linear
codes and the camera-frame light directions, hold here too). The network sees the subject's frontal image as the product
does (portrait framing, the crop at the working size, its normals put back on the image). Over
the face ellipse of training/eval/yale.py this prints the mean angle between the two, and, per
axis, the correlation of the normals' x (left/right) and y (up/down) components and the spread
of the network's over the truth's (1: as curved as the real face; below 1: flatter), and the
face's tilt: how much more its upper part faces up than its lower part (forehead over chin),
averaged and correlated over subjects. The y figures are the ones behind the relit faces'
top/bottom balance; per-pixel correlation is dominated by the nose and eye sockets, the tilt by
the face's large-scale shape, which a frontal light (shading ~ n_z) leaves ambiguous in sign.
``--relight`` also relights the split's pairs (training/eval/yale.py's) through
addon.relight_image twice, with the network's normals and with photometric stereo's in their
place (photometric_buffers): what better normals alone would buy; with ``--low-sigma S`` also
with only the low band (a Gaussian of S crop pixels) of one under the other's detail, which
tells the face's large-scale shape from its fine detail; with ``--no-shadows`` also both without
cast shadows (without_cast_shadows): the shadows march over the network's height, which real
normals do not match; with ``--swap ONNX`` also with each of another intrinsic model's buffers,
and its framing, in the network's place (buffers_from): which of them make two networks' relit
faces differ. ``--response`` (response) holds one lighting and sweeps the other over
each subject's single lights, in the face crop: the frontal photo relit to each light (how
strongly the relit face answers the target's elevation) and each photo relit to the frontal
light (how much of the input's light it keeps), the relit top/bottom balance against the real
photo's, per elevation band, with the network's normals and with photometric stereo's.
``--albedo`` (albedo_light) asks how much of each single-light photo's light the network leaves
in its albedo, against photometric stereo's albedo (0: none, 1: all). ``--relief`` (relief) asks
how deep the network draws the face's fine relief, its shadows' height and its normals, against
photometric stereo's.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import functools
import pathlib

import numpy as np

from addon import api, facetemplate, framing, intrinsic, portrait

from . import yale
from .facetemplate import applied as template_applied
from .facetemplate import flag_path as template_flag_path


def photometric_normals(images: np.ndarray, dirs: np.ndarray, fit=None):
    """((3, h*w) unit normals, (h*w,) bool where they were fitted) from (N, h, w) linear images
    under distant lights ``dirs`` (N, 3): yale.photometric_fit, each pixel from the images in
    which it is lit (``fit``: that fit, when already made)."""
    b, ok = yale.photometric_fit(images, dirs) if fit is None else fit
    norm = np.linalg.norm(b, axis=0)
    return b / np.maximum(norm, 1e-9), ok & (norm > 1e-9)


def network_normals(session, gray: np.ndarray) -> np.ndarray | None:
    """(3, h*w) the network's unit normals for an (h, w) linear gray image, framed as the product
    frames a frame; None when no portrait is found."""
    h, w = gray.shape
    x = np.repeat(np.asarray(gray, np.float32)[None], 3, axis=0)
    box = portrait.find_box(session, x)  # buffers() normalises the exposure itself
    if box is None:
        return None
    _, _, bufs = portrait.face_buffers(session, x, box, session.card.working_size)  # as relit
    n = framing.uncrop(np.ascontiguousarray(bufs.normal.transpose(1, 2, 0)), box, (h, w), 0.0)
    n = n.reshape(-1, 3).T
    return n / np.maximum(np.linalg.norm(n, axis=0), 1e-9)


TILT_BANDS = (0.4, 0.6)  # the face's upper and lower parts: rows above 40% and below 60% of its height


def tilt(normals: np.ndarray, mask: np.ndarray, height: int) -> float:
    """How much more the upper part of the masked face faces up than its lower part: the mean
    up/down component over rows above TILT_BANDS[0] of the image's ``height`` minus that below
    TILT_BANDS[1] (forehead over chin: positive on an upright real face)."""
    rows = np.arange(mask.size) // (mask.size // height)
    top, bottom = mask & (rows < TILT_BANDS[0] * height), mask & (rows >= TILT_BANDS[1] * height)
    if not top.any() or not bottom.any():
        return 0.0
    return float(normals[1, top].mean() - normals[1, bottom].mean())


def compare(pred: np.ndarray, truth: np.ndarray, mask: np.ndarray, height: int | None = None) -> dict:
    """Mean angle (degrees) and per-axis correlation and spread ratio over ``mask``, and the mean
    up/down component of each (how far the face as a whole faces up: ``pitch``,
    ``pitch_truth``); with the image's ``height``, the face's tilt (``tilt``) in the prediction
    and the truth."""
    p, t = pred[:, mask], truth[:, mask]
    angle = np.degrees(np.arccos(np.clip((p * t).sum(0), -1.0, 1.0)))
    out = {"angle_deg": float(angle.mean()), "pitch": float(p[1].mean()),
           "pitch_truth": float(t[1].mean())}
    for i, axis in ((0, "x"), (1, "y")):
        out[f"corr_{axis}"] = float(np.corrcoef(p[i], t[i])[0, 1])
        out[f"spread_{axis}"] = float(p[i].std() / max(t[i].std(), 1e-9))
    if height:
        out["tilt"], out["tilt_truth"] = tilt(pred, mask, height), tilt(truth, mask, height)
    return out


def run(onnx_paths, split: str = "tune", root=None) -> dict:
    root = root or yale.default_root()
    names = yale.subject_names(root)
    _, subjects = yale.select_subjects(names, False, split)  # "tune": the tune subjects
    sessions = {p: api.session(p, 1) for p in onnx_paths}
    rows = {p: [] for p in onnx_paths}
    for name in subjects:
        s = yale.load_subject(root, name)
        truth, ok = photometric_normals(s.images, s.dirs)
        front = int(np.argmin(np.abs(s.angles).sum(1)))
        mask = yale.face_mask(s.images.shape[1:]).reshape(-1) & ok
        for p, sess in sessions.items():
            pred = network_normals(sess, s.images[front])
            if pred is not None and mask.sum() > 16:
                rows[p].append(compare(pred, truth, mask, s.images.shape[1]))
    out = {}
    for p, v in rows.items():
        if v:
            out[p] = {k: float(np.mean([r[k] for r in v])) for k in v[0]} | {"subjects": len(v)}
            pt = np.array([[r["tilt"], r["tilt_truth"]] for r in v])
            ok = len(v) > 2 and pt.std(0).min() > 0
            out[p]["tilt_corr"] = float(np.corrcoef(pt.T)[0, 1]) if ok else 0.0
    return out


def _low(n: np.ndarray, sigma: float) -> np.ndarray:
    return np.stack([intrinsic.gaussian_blur(np.ascontiguousarray(c), sigma) for c in n])


def crop_normals(normals: np.ndarray, fitted: np.ndarray, hw: tuple[int, int], box,
                 size: int) -> tuple[np.ndarray, np.ndarray]:
    """((3, size, size) normals, (size, size) where fitted) of an (h, w) image's normals
    (3, h*w) and their ``fitted`` mask (h*w,), cropped to ``box`` at ``size`` as the product
    crops the image (framing.crop)."""
    h, w = hw
    field = np.concatenate([normals, fitted[None].astype(normals.dtype)], 0).reshape(4, h, w)
    t = framing.crop(np.ascontiguousarray(field.transpose(1, 2, 0), np.float32), box,
                     size).transpose(2, 0, 1)
    return t[:3], t[3] > 0.99


@contextlib.contextmanager
def crop_swap(change):
    """Within this context the buffers of each square crop the product takes (addon.portrait's
    crop_planar, then buffers of that crop: the face crop and its finer sampling; no other
    image's) are ``change(session, buffers, box, image_hw, size)``'s, the buffers given to it
    held to the face template as the crop's own (portrait.templated). The product holds the
    face crop's mean of its passes to the template (portrait.face_buffers); here that mean is
    left as the changes made it, so the shape they give is the one relit."""
    crop_planar, buffers, templated = portrait.crop_planar, portrait.buffers, portrait.templated
    state = {}

    def crop(x, box, size):
        state["box"], state["hw"], state["size"] = box, x.shape[1:], size
        return crop_planar(x, box, size)

    def swap(session, x, valid=None, mirror=False, level=None, shape=True):
        size = state.pop("size", None)  # the buffers of the crop just taken, no other image's
        taken = size is not None and x.shape[1:] == (size, size)
        out = buffers(session, x, valid, mirror, level, False)
        if shape or taken:
            out = templated(out, session.card.working_size)
        return change(session, out, state["box"], state["hw"], size) if taken else out

    portrait.crop_planar, portrait.buffers = crop, swap
    portrait.templated = lambda bufs, working_size: bufs
    try:
        yield
    finally:
        portrait.crop_planar, portrait.buffers = crop_planar, buffers
        portrait.templated = templated


@contextlib.contextmanager
def photometric_buffers(normals: np.ndarray, fitted: np.ndarray, low_sigma: float | None = None,
                        low: str = "photometric", share: float = 1.0):
    """Within this context the product's face crops (addon.portrait) carry ``normals`` (3, h*w)
    of the image being relit where ``fitted`` (h*w,) instead of the network's: what the
    pipeline would make of the face with its real normals. A diagnostic for one image size at a
    time; the network's matte, albedo and height stay (its light transport is left out: it
    holds its own normals' cosine). Each crop of the frame gets the real normals at its own
    size, the face crop's finer sampling (portrait.ZOOM) too, so the pipeline runs as it does
    on the network's. With ``low_sigma`` (pixels of a crop at the working size) only one band
    is swapped: ``low`` "photometric", the real normals' Gaussian low band under the network's
    finer detail; "network", the network's low band under the real normals' detail: which
    scale of the face's shape a relit face needs right. ``share`` (with ``low``
    "photometric"): the given low band's share, the network's own low band the rest (1: the
    given band alone). Where the detail is the real normals' (no ``low_sigma``, or ``low``
    "network"), the cast shadows march it as it is (real_relief)."""

    def change(session, out, box, hw, size):
        given, inside = crop_normals(normals, fitted, hw, box, size)
        real = np.where(inside, given, out.normal)
        if low_sigma:
            base, detail = (real, out.normal) if low == "photometric" else (out.normal, real)
            sigma = low_sigma * size / session.card.working_size
            own = _low(detail, sigma)
            given_low = _low(base, sigma)
            if low == "photometric" and share != 1.0:
                given_low = share * given_low + (1.0 - share) * own
            real = given_low + detail - own
        n = intrinsic.unit_normals(np.where(inside, real, out.normal))
        return intrinsic.Buffers(n, out.height, out.albedo, out.matte, out.face)

    with contextlib.ExitStack() as stack:
        stack.enter_context(crop_swap(change))
        if not low_sigma or low == "network":
            stack.enter_context(real_relief())
        yield


@contextlib.contextmanager
def real_relief():
    """Within this context the face skin's relief is taken as the normals draw it: their detail
    is not raised (portrait.NORMAL_DETAIL 1) and the cast shadows march it as it is
    (intrinsic.SHADOW_DETAIL 1). The product deepens the network's relief, which it draws too
    flat; deepened so, real normals' detail would stand too deep."""
    kept = portrait.NORMAL_DETAIL, intrinsic.SHADOW_DETAIL
    portrait.NORMAL_DETAIL, intrinsic.SHADOW_DETAIL = 1.0, 1.0
    try:
        yield
    finally:
        portrait.NORMAL_DETAIL, intrinsic.SHADOW_DETAIL = kept


def face_space(normals: list[np.ndarray], hw: tuple[int, int], sigma: float,
               modes: int) -> np.ndarray:
    """(modes + 1, 3, h, w): the mean of ``normals`` (each (3, h*w), 0 where unfitted) as
    Gaussian low bands of ``sigma`` image pixels, then that set's ``modes`` principal
    directions: a space of real faces' shapes at the scale that carries the balance."""
    low = np.stack([_low(np.asarray(n, np.float32).reshape(3, *hw), sigma).reshape(-1)
                    for n in normals])
    mean = low.mean(0)
    _, _, vt = np.linalg.svd(low - mean, full_matrices=False)
    return np.concatenate([mean[None], vt[:modes]], 0).reshape(-1, 3, *hw).astype(np.float32)


@contextlib.contextmanager
def face_space_buffers(space: np.ndarray, low_sigma: float):
    """Within this context the product's face crops (addon.portrait) carry the network's normals
    with their low band (a Gaussian of ``low_sigma`` pixels at the working size) over the face
    skin replaced by its least-squares fit in ``space`` (face_space's, of the image being
    relit, cropped as the crop is): the network's shape held to a space of real faces' shapes,
    its detail kept (and its light transport). Whether a face prior fitted to the network's
    own normals corrects them (the product's face template, facetemplate.held, with its
    constants, is the mean's case laid on the face skin's own extent)."""
    everywhere = np.ones(space.shape[2] * space.shape[3], bool)

    def change(session, out, box, hw, size):
        cropped = [crop_normals(b.reshape(3, -1), everywhere, hw, box, size) for b in space]
        inside = np.logical_and.reduce([ins for _, ins in cropped])
        own = _low(out.normal, low_sigma * size / session.card.working_size)
        sel = inside & (out.face > 0.5) & (out.matte > 0.5)
        if sel.sum() < facetemplate.MIN_SKIN:
            return out
        design = np.stack([b[:, sel].ravel() for b, _ in cropped], 1).astype(np.float64)
        coef = np.linalg.lstsq(design, own[:, sel].ravel().astype(np.float64), rcond=None)[0]
        fitted = sum(np.float32(c) * b for c, (b, _) in zip(coef, cropped))
        w = intrinsic.gaussian_blur(sel.astype(np.float32), facetemplate.BLEND_SIGMA)[None]
        n = intrinsic.unit_normals(out.normal + w * (fitted - own))
        return dataclasses.replace(out, normal=n)

    with crop_swap(change):
        yield


@contextlib.contextmanager
def without_cast_shadows():
    """Within this context the product plans no cast shadows for any light (intrinsic.plan with
    ``shadows`` off): the relit face is lit by its normals, transport and highlights alone."""
    plan = intrinsic.plan
    intrinsic.plan = functools.partial(plan, shadows=False)
    try:
        yield
    finally:
        intrinsic.plan = plan


# Every field of the buffers, whatever the renderer comes to read.
ALL_BUFFERS = tuple(f.name for f in dataclasses.fields(intrinsic.Buffers))
# What --swap takes from another intrinsic model (buffers_from), by name: the fields of its
# buffers in the relighting pass, and whether its face and matte maps place the portrait's box.
SWAPS = {"framing": ((), True), "normals": (("normal",), False), "height": (("height",), False),
         "albedo": (("albedo",), False), "matte and skin": (("matte", "face"), False),
         "transport": (("transfer",), False),
         # the transport holds its own normals' cosine: the two belong together
         "normals and transport": (("normal", "transfer"), False),
         "hair": (("hair",), False),
         "all buffers": (ALL_BUFFERS, False), "everything": (ALL_BUFFERS, True)}


@contextlib.contextmanager
def buffers_from(session, fields=(), framing: bool = False):
    """Within this context the product's buffers (addon.portrait) carry ``fields`` (names of
    intrinsic.Buffers' fields) from another intrinsic model's ``session`` in the relighting
    pass, the face crop's finer sampling included; the portrait's box is still found on the
    product's own buffers unless ``framing``, when that model finds it (find_box on its face
    and matte maps). Which of a second network's buffers make its relit faces differ."""
    buffers, find_box = portrait.buffers, portrait.find_box
    boxing = []

    def swap(own, x, valid=None, mirror=False, level=None, shape=True):
        out = buffers(own, x, valid, mirror, level, shape)
        if boxing or not fields:
            return out
        other = buffers(session, x, valid, mirror, level, shape)
        return dataclasses.replace(out, **{f: getattr(other, f) for f in fields})

    def box(own, *args, **kwargs):
        boxing.append(True)
        try:
            return find_box(session if framing else own, *args, **kwargs)
        finally:
            boxing.pop()

    portrait.buffers, portrait.find_box = swap, box
    try:
        yield
    finally:
        portrait.buffers, portrait.find_box = buffers, find_box


NO_SHADOWS = ", no cast shadows"  # the suffix of relight's variants without them


def face_space_variant(modes: int) -> str:
    """relight's name of the network's low band fitted in a space of real faces' shapes."""
    return f"face space of {int(modes)} modes"


def template_variant(share: float) -> str:
    """relight's name of the face template's low band blended at ``share`` with the network's."""
    return f"template low band at {float(share):g}"


PAIRS = 36  # pairs per subject for --relight, as the tune subjects' evaluation takes them


def relight(onnx_path, split: str = "tune", root=None, n_pairs: int = PAIRS, seed: int = 2021,
            low_sigma: float | None = None, shadowless: bool = False,
            other: str | None = None, template_shares=(), face_modes=()) -> dict:
    """The split's pairs (training/eval/yale.py's) relit through addon.relight_image with the
    network's normals and with photometric stereo's (and, with ``low_sigma``, with either's low
    band under the other's detail: photometric_buffers; and with the low band of the other
    subjects' mean real normals, a face template as exactly aligned as CroppedYale's crops
    are, in place of the network's or, for each of ``template_shares``, blended with it at
    that share: template_variant; for each of ``face_modes`` K, the network's low band
    fitted in the space of the other CroppedYale subjects' low bands, their mean and K
    principal modes: face_space_variant; with ``shadowless``, the network's and the real
    normals also without cast shadows: without_cast_shadows): per kind and overall, the
    scale-invariant PSNR, and the balance correlations with their intervals, their split into
    the truth's and the input's balance and each variant's gain over the network's normals
    paired over the same pairs (yale.balance_correlation's). A dozen pairs a subject do not
    tell such settings apart: on the tune subjects photometric stereo's normals read 0.931
    top/bottom with ``n_pairs`` 12, 0.750 with 36 (0.869 by rank): one of the 360 pairs, a
    light from straight above, is far off, its cast shadows marched over the network's height,
    which the real normals do not match. Without cast shadows the real normals read 0.896
    (0.87-0.92) and the network's 0.800 (0.807 with shadows): normals alone would clear 0.85.
    With ``other`` (another intrinsic model), also with each of SWAPS taken from it
    (buffers_from), named "<what> of <model>": which of its buffers, or its framing, make its
    relit faces differ."""
    if (template_shares or face_modes) and not low_sigma:
        raise ValueError("template shares and face spaces blend low bands: give low_sigma")
    root = root or yale.default_root()
    _, subjects = yale.select_subjects(yale.subject_names(root), False, split)
    rel = {"model": yale.PipelineRelighter(onnx_path, 1)}
    bank = yale.HdriBank(root.parents[1])
    swaps = {"photometric": {}}
    if low_sigma:
        swaps.update({"photometric low band": {"low_sigma": low_sigma, "low": "photometric"},
                      "network low band": {"low_sigma": low_sigma, "low": "network"},
                      "template low band": {"low_sigma": low_sigma, "low": "photometric"}})
        swaps.update({template_variant(w): {"low_sigma": low_sigma, "low": "photometric",
                                            "share": float(w)} for w in template_shares})
    variants = ("network", *swaps, *(face_space_variant(k) for k in face_modes))
    if shadowless:
        variants += ("network" + NO_SHADOWS, "photometric" + NO_SHADOWS)
    taken = {}  # variant: buffers_from's arguments
    if other is not None:
        session = api.session(other, 1)
        stem = pathlib.Path(other).stem
        taken = {f"{what} of {stem}": (session, *how) for what, how in SWAPS.items()}
        variants += tuple(taken)
    psnr = {k: [] for k in variants}
    rows = []  # (kind, None, subject, balances), as yale.balance_correlation takes them
    real = {}
    for name in subjects:
        s = yale.load_subject(root, name)
        fit = yale.photometric_fit(s.images, s.dirs)
        n, ok = photometric_normals(s.images, s.dirs, fit)
        real[name] = (s, fit, np.where(ok, n, 0.0), ok)
    total = sum(r[2] for r in real.values())  # every subject's real normals, summed
    every = {}  # with face_modes, every subject's real normals (0 where unfitted)
    if face_modes:
        for name in yale.subject_names(root):
            s = yale.load_subject(root, name)
            if name in real:
                every[name] = real[name][2]
            elif s.images.shape[1:] == real[subjects[0]][0].images.shape[1:]:
                n, ok = photometric_normals(s.images, s.dirs)
                every[name] = np.where(ok, n, 0.0)
        session = api.session(onnx_path, 1)
    for name in subjects:
        s, fit, truth, ok = real[name]
        given = {}
        if low_sigma:  # the other subjects' mean real normals
            template = intrinsic.unit_normals(total - truth)
            given["template low band"] = (template, np.ones(len(ok), bool))
            for w in template_shares:
                given[template_variant(w)] = given["template low band"]
        spaces = {}
        if face_modes:  # the other subjects' low bands, at this subject's crop's scale
            hw = s.images.shape[1:]
            front = np.repeat(s.images[int(np.argmin(np.abs(s.angles).sum(1)))][None], 3, 0)
            box = portrait.find_box(session, front.astype(np.float32))
            sigma = low_sigma * box.size / session.card.working_size
            space = face_space([n for o, n in every.items() if o != name], hw, sigma,
                               max(face_modes))
            spaces = {face_space_variant(k): space[:k + 1] for k in face_modes}
        shading = yale.subject_shading(s, fit)
        for a, b in yale.draw_pairs(s, n_pairs, seed, bank):
            balances = {}
            for which in variants:
                normals = which.removesuffix(NO_SHADOWS)
                with contextlib.ExitStack() as stack:
                    if normals in swaps:
                        stack.enter_context(photometric_buffers(
                            *given.get(normals, (truth, ok)), **swaps[normals]))
                    if normals != which:
                        stack.enter_context(without_cast_shadows())
                    if which in taken:
                        stack.enter_context(buffers_from(*taken[which]))
                    if which in spaces:
                        stack.enter_context(face_space_buffers(spaces[which], low_sigma))
                    r = yale.relight_pair(s, a, b, rel, shading)
                y = r.outputs["model"]
                gain = yale.ls_gain(y, r.gt, r.mask)
                psnr[which].append((r.kind, yale.metrics(gain * y, r.gt, r.mask)["psnr"]))
                balances[which] = yale.balance(y, r.mask)
            balances["ground_truth"] = yale.balance(r.gt, r.mask)
            balances[yale.INPUT_METHOD] = yale.balance(r.outputs[yale.INPUT_METHOD], r.mask)
            rows.append((r.kind, None, name, balances))
    corr = yale.balance_correlation(rows, reference="network")
    return {which: {k: float(np.mean([p for kind, p in psnr[which] if k in ("all", kind)]))
                    for k in (*yale.KINDS, "all")} | corr[which] for which in variants}


def crop_balance(img: np.ndarray, mask: np.ndarray) -> float:
    """Top/bottom balance of an (h, w) crop over ``mask``: (bottom - top) / (bottom + top) of the
    two halves' means, split at the middle of the mask's rows (yale.balance's, in the crop)."""
    rows = np.nonzero(mask.any(1))[0]
    if len(rows) == 0:
        return 0.0
    below = (np.arange(img.shape[0]) >= (rows.min() + rows.max()) / 2)[:, None]
    return yale.half_balance(img, mask & ~below, mask & below)


def response_stats(pred: np.ndarray, truth: np.ndarray, elevation: np.ndarray,
                   reference: np.ndarray | None = None) -> dict:
    """Per band of ``elevation`` (all; above, level, below: yale.elevation_bands) the lights, the
    Pearson correlation of ``pred`` balances with ``truth``'s, their slope (least squares of pred
    on truth: 1 when the relit face answers the light as strongly as the real one, 0 when not at
    all) and the mean error against ``reference`` (default: the truth)."""
    pred, truth, e = (np.asarray(v, np.float64) for v in (pred, truth, elevation))
    ref = truth if reference is None else np.asarray(reference, np.float64)
    out = {}
    for name, sel in {"all": np.ones(len(e), bool), **yale.elevation_bands(e)}.items():
        p, t = pred[sel], truth[sel]
        dp, dt = (p - p.mean(), t - t.mean()) if len(t) else (p, t)
        var_t, var_p = float((dt * dt).sum()), float((dp * dp).sum())
        ok = len(t) > 2 and var_t > 1e-12 and var_p > 1e-12
        out[name] = {"lights": int(sel.sum()),
                     "corr": float((dp * dt).sum() / np.sqrt(var_t * var_p)) if ok else 0.0,
                     "slope": float((dp * dt).sum() / var_t) if ok else 0.0,
                     "bias": float((p - ref[sel]).mean()) if len(t) else 0.0}
    return out


def response(onnx_path, split: str = "tune", root=None, names=None) -> dict:
    """How strongly the relit face answers the target light's elevation, and how much of the
    input light's it keeps, each with the other held fixed. "target": each subject's frontal
    image (the product's face crop and buffers, portrait.face_buffers) relit by
    intrinsic.shade to each of its single lights within yale.FRONT_AZIMUTH, the relit crop's
    top/bottom balance (crop_balance over the face skin where photometric stereo fitted)
    against the real photo's under that light in the same crop, per target band
    (response_stats). "input": each of those single-light photos relit to the frontal light,
    its balance against the input's, per input band: the slope is the share of the input's
    balance left in the relit face (0: none), the mean error against the real frontal photo's.
    Each with the network's normals (its light transport too, as the product) and with
    photometric stereo's in their place (no transport: it holds the network's own normals'
    cosine), over ``names`` (default: the split's subjects). Fewer confounds than the pairs'
    balance (one lighting held, up to 60 of the other a subject). ``subjects``: the same
    figures over all of each subject's lights, per side and normals (subject_spread)."""
    root = root or yale.default_root()
    if names is None:
        _, names = yale.select_subjects(yale.subject_names(root), False, split)
    sess = api.session(onnx_path, 1)
    size = sess.card.working_size
    rows = {"network": [], "photometric": []}
    kept = {"network": [], "photometric": []}
    truth, elevation, front_truth, subject = [], [], [], []
    for name in names:
        s = yale.load_subject(root, name)
        real, ok = photometric_normals(s.images, s.dirs)
        front = int(np.argmin(np.abs(s.angles).sum(1)))
        x = np.repeat(s.images[front][None], 3, axis=0)
        box = portrait.find_box(sess, x)
        if box is None:
            continue
        crop, _, net = portrait.face_buffers(sess, x, box, size)
        given, fitted = crop_normals(np.where(ok, real, 0.0), ok, s.images.shape[1:], box, size)
        photo = intrinsic.Buffers(intrinsic.unit_normals(np.where(fitted, given, net.normal)),
                                  net.height, net.albedo, net.matte, net.face)
        mask = fitted & (net.face > 0.5) & (net.matte > 0.5)
        if mask.sum() < 64:
            continue
        front_light = yale.light_vector(s.dirs[front:front + 1], np.ones(1))
        front_balance = crop_balance(crop[0], mask)
        for k in np.flatnonzero(np.abs(s.angles[:, 0]) <= yale.FRONT_AZIMUTH):
            light = yale.light_vector(s.dirs[k:k + 1], np.ones(1))
            truth.append(crop_balance(framing.crop(s.images[k], box, size), mask))
            elevation.append(float(s.angles[k, 1]))
            subject.append(name)
            xk = np.repeat(s.images[k][None], 3, axis=0)
            crop_k, _, net_k = portrait.face_buffers(sess, xk, box, size)
            front_truth.append(front_balance)
            photo_k = intrinsic.Buffers(photo.normal, net_k.height, net_k.albedo, net_k.matte,
                                        net_k.face)
            for which, bufs, bufs_k in (("network", net, net_k), ("photometric", photo, photo_k)):
                sh = intrinsic.shade(crop, bufs, light)
                rows[which].append(crop_balance(
                    intrinsic.luminance(sh.ratio * crop + sh.highlight), mask))
                sh = intrinsic.shade(crop_k, bufs_k, front_light)
                kept[which].append(crop_balance(
                    intrinsic.luminance(sh.ratio * crop_k + sh.highlight), mask))
    out = {"target": {w: response_stats(v, truth, elevation) for w, v in rows.items()},
           "input": {}, "subjects": {"target": {}, "input": {}}}
    for which, v in kept.items():  # against the input photos' balance (the target sweep's
        # truths, the same photos); the mean error against the subject's frontal photo's
        out["input"][which] = response_stats(v, truth, elevation, front_truth)
    # Each subject's own figures over all its lights: a model that answers well on most faces
    # and not at all on one shows it here, where the pooled figures average it away.
    subject = np.asarray(subject)
    own = {n: subject == n for n in dict.fromkeys(subject.tolist())}
    t, e = np.asarray(truth, np.float64), np.asarray(elevation, np.float64)
    for side, got, ref in (("target", rows, t), ("input", kept, front_truth)):
        ref = np.asarray(ref, np.float64)
        for which, v in got.items():
            v = np.asarray(v, np.float64)
            out["subjects"][side][which] = {
                n: response_stats(v[sel], t[sel], e[sel], ref[sel])["all"]
                for n, sel in own.items()}
    return out


def subject_spread(per_subject: dict) -> dict:
    """The median, lowest and highest of the subjects' slopes (response's ``subjects``, one side
    and normals), with the subjects that give the extremes."""
    names = sorted(per_subject, key=lambda n: per_subject[n]["slope"])
    if not names:
        return {}
    slopes = [per_subject[n]["slope"] for n in names]
    return {"median": float(np.median(slopes)), "lowest": (names[0], slopes[0]),
            "highest": (names[-1], slopes[-1])}


ALBEDO_MIN_SPREAD = 0.1  # a photo whose shading over the face varies less (log std) says nothing


def shading_left(photo: np.ndarray, real_albedo: np.ndarray, albedo: np.ndarray,
                 mask: np.ndarray) -> float | None:
    """The share of a photo's shading that an albedo keeps: the slope of log(``albedo`` /
    ``real_albedo``) on log(``photo`` / ``real_albedo``) (the photo's shading) over ``mask``,
    each about its median (the albedo's gain is free). 0: the albedo is free of the photo's
    light; 1: all of it is there. None where the mask is small or the shading even."""
    m = mask & (real_albedo > 0) & (albedo > 0) & (photo > 0)
    if m.sum() < 64:
        return None
    x = np.log(photo[m] / real_albedo[m])
    y = np.log(albedo[m] / real_albedo[m])
    x, y = x - np.median(x), y - np.median(y)
    if float(x.std()) < ALBEDO_MIN_SPREAD:
        return None
    return float((x * y).sum() / (x * x).sum())


def albedo_light(onnx_path, split: str = "tune", root=None, names=None) -> dict:
    """How much of each single-light photo's light the network leaves in its albedo, on real
    faces: per photo, shading_left of the network's albedo (luminance, the product's face crop
    and buffers, the box found on the subject's frontal photo) against photometric stereo's
    (the length of yale.photometric_fit's albedo-times-normal) over the face skin where that
    fitted and the photo is lit and unclipped (yale.lit_unclipped, as the fit takes them).
    ``photos``, ``slope``: the median over photos; ``subjects``: each subject's median
    (subject_spread)."""
    root = root or yale.default_root()
    if names is None:
        _, names = yale.select_subjects(yale.subject_names(root), False, split)
    sess = api.session(onnx_path, 1)
    size = sess.card.working_size
    slopes, subjects = [], {}
    for name in names:
        s = yale.load_subject(root, name)
        b, ok = yale.photometric_fit(s.images, s.dirs)
        rho = np.linalg.norm(b, axis=0)
        front = int(np.argmin(np.abs(s.angles).sum(1)))
        box = portrait.find_box(sess, np.repeat(s.images[front][None], 3, axis=0))
        if box is None:
            continue
        real, fitted = crop_normals(np.repeat(rho[None], 3, axis=0), ok, s.images.shape[1:],
                                    box, size)
        own = []
        for k in range(len(s.images)):
            photo = framing.crop(s.images[k], box, size)
            _, _, net = portrait.face_buffers(
                sess, np.repeat(s.images[k][None], 3, axis=0), box, size)
            mask = (fitted & yale.lit_unclipped(photo) & (net.face > 0.5)
                    & (net.matte > 0.5))
            got = shading_left(photo, real[0], intrinsic.luminance(net.albedo), mask)
            if got is not None:
                own.append(got)
        if own:
            slopes += own
            subjects[name] = {"slope": float(np.median(own)), "photos": len(own)}
    return {"photos": len(slopes), "slope": float(np.median(slopes)) if slopes else 0.0,
            "subjects": subjects}


def relief(onnx_path, split: str = "tune", root=None) -> dict:
    """How deep the network draws real faces' fine relief, against photometric stereo's: on each
    subject's frontal photo, in the product's face crop, the standard deviation over the face
    skin of the shadows' height (intrinsic.shadow_height as drawn, relief 1) less its blur of
    intrinsic.SHADOW_DETAIL_SIGMA, and of the normals' two image-plane components less theirs,
    the network's over the same with photometric stereo's normals in its place
    (photometric_buffers). The real-face side of bench.height_detail (which measures the light
    stage's held-out heads against their exact buffers): per subject, and the median and the
    10th-90th percentiles. Both as drawn (real_relief: neither deepened as the product deepens
    the network's). Photometric stereo's noise adds to its detail, so the ratios err low."""
    root = root or yale.default_root()
    _, subjects = yale.select_subjects(yale.subject_names(root), False, split)
    session = api.session(onnx_path, 1)
    sigma = intrinsic.SHADOW_DETAIL_SIGMA

    def detail(x, face):
        return float(np.stack([c - intrinsic.gaussian_blur(c, sigma) for c in x])[:, face].std())

    per = {}
    for name in subjects:
        s = yale.load_subject(root, name)
        n, ok = photometric_normals(s.images, s.dirs)
        x = np.repeat(s.images[int(np.argmin(np.abs(s.angles).sum(1)))][None], 3, 0)
        x = x.astype(np.float32)
        box = portrait.find_box(session, x)
        if box is None:
            continue
        with real_relief():
            _, _, net = portrait.face_buffers(session, x, box, session.card.working_size)
        with photometric_buffers(np.where(ok, n, 0.0), ok):
            _, _, real = portrait.face_buffers(session, x, box, session.card.working_size)
        face = (net.face > 0.5) & (net.matte > 0.5)
        if int(face.sum()) < facetemplate.MIN_SKIN:
            continue
        per[name] = {"height": detail(intrinsic.shadow_height(net, 1.0)[None], face)
                     / detail(intrinsic.shadow_height(real, 1.0)[None], face),
                     "normals": detail(net.normal[:2], face) / detail(real.normal[:2], face)}
    out = {"subjects": per, "sigma": sigma}
    for k in ("height", "normals"):
        v = [r[k] for r in per.values()]
        out[k] = {"median": float(np.median(v)),
                  "10_90": [float(q) for q in np.percentile(v, [10, 90])]} if v else None
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--onnx", action="append", required=True, help="intrinsic model (repeatable)")
    ap.add_argument("--split", default="tune", choices=["tune", "test"])
    ap.add_argument("--relight", action="store_true",
                    help="also relight the split's pairs with photometric stereo's normals in "
                         "place of the network's (what better normals would buy)")
    ap.add_argument("--pairs", type=int, default=PAIRS, help="with --relight, pairs per subject")
    ap.add_argument("--low-sigma", type=float, help="with --relight, also swap only the low "
                    "band (a Gaussian of this many crop pixels) one way and the other")
    ap.add_argument("--template-share", type=float, action="append", default=[],
                    help="with --relight --low-sigma, also the face template's low band blended "
                         "with the network's at this share (repeatable; 1: the template's alone)")
    ap.add_argument("--face-modes", type=int, action="append", default=[],
                    help="with --relight --low-sigma, also the network's low band fitted in the "
                         "space of the other subjects' real low bands (their mean and this many "
                         "principal modes; repeatable)")
    ap.add_argument("--no-shadows", action="store_true", help="with --relight, also relight "
                    "with the network's and the real normals without cast shadows")
    ap.add_argument("--swap", metavar="ONNX", help="with --relight, also relight with each of "
                    "this other intrinsic model's buffers, and its framing, in place of the "
                    "network's (which of them make the two models' relit faces differ)")
    ap.add_argument("--response", action="store_true",
                    help="also the relit face's top/bottom answer to each single light (input "
                         "held frontal) and what it keeps of each input's (target held "
                         "frontal), per elevation band (response)")
    ap.add_argument("--albedo", action="store_true",
                    help="also how much of each single-light photo's light the network leaves "
                         "in its albedo, against photometric stereo's albedo (albedo_light)")
    ap.add_argument("--relief", action="store_true",
                    help="also how deep the network draws the face's fine relief (the shadows' "
                         "height and the normals) against photometric stereo's (relief)")
    ap.add_argument("--face-template", metavar="NPZ",
                    help="the face crop's normals held to this face template instead of the "
                         "product's, or to none with 'none' (addon/facetemplate.py)")
    a = ap.parse_args(argv)
    if a.face_template:
        with template_applied(template_flag_path(a.face_template, ap.error)):
            return _main(ap, a)
    return _main(ap, a)


def _main(ap, a):
    for flag, given in (("--template-share", a.template_share), ("--face-modes", a.face_modes)):
        if given and not (a.relight and a.low_sigma):
            ap.error(f"{flag} needs --relight and --low-sigma")
    if any(k < 0 for k in a.face_modes):
        ap.error("--face-modes must be 0 or more")
    if a.relief:
        for p in a.onnx:
            got = relief(p, a.split)
            for k, what in (("height", "shadows' height"), ("normals", "normals'")):
                r = got[k]
                if r:
                    lo, hi = r["10_90"]
                    print(f"{p}: the {what} detail finer than {got['sigma']:g} px, the network's "
                          f"over photometric stereo's: median {r['median']:.2f} ({lo:.2f}-"
                          f"{hi:.2f}) over {len(got['subjects'])} subjects")
    if a.albedo:
        for p in a.onnx:
            got = albedo_light(p, a.split)
            sp = subject_spread(got["subjects"])
            print(f"{p}: the albedo keeps {got['slope']:.2f} of the photo's shading (median over "
                  f"{got['photos']} photos; 0: none, 1: all)" + (
                      f"; per subject median {sp['median']:.2f}, lowest {sp['lowest'][1]:.2f} "
                      f"({sp['lowest'][0]}), highest {sp['highest'][1]:.2f} "
                      f"({sp['highest'][0]})" if sp else ""))
    if a.response:
        for p in a.onnx:
            got = response(p, a.split)
            for side, what in (("target", "the truth's"), ("input", "the input's")):
                for which, r in got[side].items():
                    print(f"{p}, {which} normals, top/bottom against {what} per {side} "
                          "elevation (lights: correlation, slope, mean error): " + "; ".join(
                              f"{band} {v['lights']}: {v['corr']:.2f}, {v['slope']:.2f}, "
                              f"{v['bias']:+.3f}" for band, v in r.items()))
                    sp = subject_spread(got["subjects"][side][which])
                    if sp:
                        print(f"  per subject, slope: median {sp['median']:.2f}, lowest "
                              f"{sp['lowest'][1]:.2f} ({sp['lowest'][0]}), highest "
                              f"{sp['highest'][1]:.2f} ({sp['highest'][0]})")
    if a.relight:
        for p in a.onnx:
            got = relight(p, a.split, n_pairs=a.pairs, low_sigma=a.low_sigma,
                          shadowless=a.no_shadows, other=a.swap,
                          template_shares=a.template_share, face_modes=a.face_modes)
            for which, r in got.items():
                tb, tb90 = r["top_bottom"], r["top_bottom_90"]
                gain = "" if "top_bottom_gain" not in r else (
                    f"; over the network's {r['top_bottom_gain']:+.3f} ("
                    f"{r['top_bottom_gain_90'][0]:+.3f} to {r['top_bottom_gain_90'][1]:+.3f})")
                normals = which.removesuffix(NO_SHADOWS)
                name = (which if " of " in which or " at " in which
                        else f"{normals} normals{which[len(normals):]}")
                print(f"{p}, {name}: scale-invariant PSNR {r['all']:.2f} dB ("
                      + ", ".join(f"{k} {r[k]:.2f}" for k in yale.KINDS)
                      + f"); balance {r['left_right']:.3f} / {tb:.3f} ({tb90[0]:.2f}-"
                      f"{tb90[1]:.2f}; by rank {r['top_bottom_rank']:.3f}){gain}; top/bottom "
                      "from the truth "
                      f"{r['top_bottom_from']['truth']:.2f}, from the input "
                      f"{r['top_bottom_from']['input']:.2f}")
    for p, r in run(a.onnx, a.split).items():
        print(f"{p} ({r['subjects']} {a.split} subjects): angle {r['angle_deg']:.1f} deg; "
              f"left/right x corr {r['corr_x']:.3f} spread {r['spread_x']:.2f}; "
              f"up/down y corr {r['corr_y']:.3f} spread {r['spread_y']:.2f}; forehead-over-chin "
              f"tilt {r['tilt']:+.3f} (truth {r['tilt_truth']:+.3f}, correlation over subjects "
              f"{r['tilt_corr']:.2f}); mean up/down {r['pitch']:+.3f} (truth "
              f"{r['pitch_truth']:+.3f})")


if __name__ == "__main__":
    main()
