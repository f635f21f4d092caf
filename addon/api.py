"""``relight_image``: what the pipeline does to one frame, for one image.

Every evaluation (CroppedYale, the footage sheets, benchmarks) goes through this function, so
every figure is the product's: the same framing, normalisation, network, effects, full-resolution
transfer and default exposure mode as a relit clip, with the clip-level exposure computed from
the one image.
"""

from __future__ import annotations

import pathlib

import numpy as np

from . import colour, detail, engine, lightvec, normalise, outline, pipeline, portrait
from .errors import InputError, ModelError

MODELS_DIR = pathlib.Path(__file__).resolve().parents[1] / "models"
LINEAR = colour.lookup("Linear Rec.709")
_SESSIONS: dict = {}


def find_model(preset: str, models_dir=None) -> pathlib.Path:
    """The .onnx of the model whose card names ``preset`` in ``models_dir`` (default: the
    extension's models/). ModelError lists the presets there when none matches."""
    folder = pathlib.Path(models_dir) if models_dir else MODELS_DIR
    found = []
    for path in sorted(folder.glob("*.onnx")) if folder.is_dir() else ():
        try:
            card = engine.load_card(path)
        except ModelError:
            continue
        if card.preset == preset:
            return path
        found.append(card.preset)
    raise ModelError(f"No model for the preset '{preset}' in {folder}; available: "
                     f"{', '.join(found) or 'none'}.")


def session(model_path, threads: int | None = None, working_size: int | None = None):
    """A loaded model, kept for the next call (loading checks the file's checksum);
    ``working_size``: the network's in place of its card's (engine.check_working_size).
    ``model_path`` may be a model loaded already (engine.new_session's): it is returned as it
    is, with its own threads and working size."""
    if isinstance(model_path, (engine.RelightSession, engine.IntrinsicSession)):
        return model_path
    key = (str(pathlib.Path(model_path).resolve()), threads, working_size)
    if key not in _SESSIONS:
        _SESSIONS[key] = engine.new_session(model_path, providers=["CPUExecutionProvider"],
                                            threads=threads, spin=False,
                                            working_size=working_size)
    return _SESSIONS[key]


def relight_image(image, light, preset: str = "standard", models_dir=None, *, model=None,
                  threads: int | None = None,
                  background: str = pipeline.DEFAULT_BACKGROUND,
                  exposure: str = pipeline.DEFAULT_EXPOSURE_MODE,
                  working_size: int | None = None) -> np.ndarray:
    """Relight ``image`` ((H, W, 3) float32 scene-linear Rec.709) to ``light`` ((16, 16, 3), the
    light-vector convention) with the preset's model and return (H, W, 3) scene linear.
    ``model``: a path to an .onnx (with its card) instead of a preset, or a model loaded
    already (engine.new_session's; ``threads`` and ``working_size`` are then its own);
    ``background``: the pipeline's choice for the end-to-end presets (intrinsic presets always
    keep the footage's background); ``exposure``: the pipeline's exposure mode ("keep": the
    subject keeps this image's luminance; "physical": absolute units); ``working_size``: the
    network's working size in place of its card's (smaller is faster, larger finer;
    bench.intrinsic_frontier). NaN, infinite and negative pixels are taken as 0, as the
    pipeline does."""
    if exposure not in pipeline.EXPOSURE_MODES:
        raise InputError(f"Unknown exposure mode {exposure!r}; use one of "
                         f"{', '.join(pipeline.EXPOSURE_MODES)}.")
    img = np.asarray(image, dtype=np.float32)
    if img.ndim != 3 or img.shape[2] != 3 or img.shape[0] < 1 or img.shape[1] < 1:
        raise InputError(f"The image must be (H, W, 3), got shape {img.shape}.")
    img = np.where(np.isfinite(img) & (img > 0), img, np.float32(0.0))
    light = lightvec.validate(light)
    sess = session(model or find_model(preset, models_dir), threads, working_size)
    x = np.ascontiguousarray(img.transpose(2, 0, 1))
    if isinstance(sess, engine.IntrinsicSession):
        fullres = portrait.shared_fullres()
        res = portrait.relight_frame(sess, x, light, portrait.find_box(sess, x, fullres),
                                     exposure=exposure, fullres=fullres)
        y = fullres.finish_planar(x, res.a, res.b, float(x.max(initial=0.0)))[0]
        y = outline.apply(res.outline, x, y, fullres=fullres)
        return np.ascontiguousarray(y.astype(np.float32).transpose(1, 2, 0))
    return _network_frame(sess, x, light, background, exposure)


def _network_frame(sess, x: np.ndarray, light: np.ndarray, background: str,
                   exposure: str) -> np.ndarray:
    """The end-to-end network's path through the pipeline's per-frame stages."""
    h, w = x.shape[1:]
    s = normalise.exposure_scale([x.transpose(1, 2, 0)])
    plan = pipeline.Plan(LINEAR, s, (w, h), detail.working_shape(h, w, sess.card.working_size),
                         True, False, "none", background)
    fullres = portrait.shared_fullres()  # built once: its graphs cost more than a small frame
    xn = np.ascontiguousarray(x / np.float32(s))
    x_low = pipeline.shrink_planar(xn, plan, fullres)
    relit_low, source, fg, k = pipeline.infer_planar(sess, x_low, light)
    ab = pipeline.coefficients_planar(x_low, relit_low, k, plan, fullres)
    ab = pipeline.with_background(ab, fg, light, source * np.float32(s), plan)
    if exposure == "keep" and ab is not None:
        gain = portrait.clip_gain([pipeline.frame_luminance(x_low, ab, s)], "keep")
        ab = pipeline.scaled(ab, gain)
    y = pipeline.finish_planar(xn, ab, float(xn.max()) if xn.size else 0.0, fullres)[0]
    return np.ascontiguousarray(y.astype(np.float32).transpose(1, 2, 0))
