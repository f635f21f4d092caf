"""Experiments with the face template (addon/facetemplate.py): ``applied`` runs the product's
passes with another template, or none, in place of the shipped one
(``training.eval.yale --compare-face-template``, ``training.eval.evaluate`` and
``training.eval.yale_normals --face-template``); ``flag_path`` reads such a flag."""

from __future__ import annotations

import contextlib

from addon import facetemplate, portrait


@contextlib.contextmanager
def applied(path, axes: str = "y"):
    """Within this context the product's passes (addon.portrait.buffers) take the face template
    at ``path`` (None: none) over their normals' components ``axes`` (AXES' key) instead of the
    product's (portrait.FACE_TEMPLATE, FACE_TEMPLATE_AXES); a missing or wrong file is refused
    before anything runs (load)."""
    if path is not None:
        facetemplate.cached(path)
    if axes not in facetemplate.AXES:
        raise ValueError(f"face template axes must be one of {sorted(facetemplate.AXES)}, "
                         f"not {axes!r}")
    kept = portrait.FACE_TEMPLATE, portrait.FACE_TEMPLATE_AXES
    portrait.FACE_TEMPLATE, portrait.FACE_TEMPLATE_AXES = path, axes
    try:
        yield
    finally:
        portrait.FACE_TEMPLATE, portrait.FACE_TEMPLATE_AXES = kept


def flag_path(value: str, error):
    """The template path a ``--face-template`` flag's ``value`` names (None for 'none'), the file
    checked first: ``error(message)`` (an argparse parser's ``error``) when it is missing or not
    a face template, with what to build."""
    path = None if value == "none" else value
    try:
        if path is not None:
            facetemplate.cached(path)
    except (OSError, ValueError) as e:
        error(str(e))
    return path
