"""The light stage: 114 distant lights on a sphere, and light vectors projected onto them.

Layout: a Fibonacci (golden-angle) spiral of 114 directions over the whole sphere, so every light
owns the same solid angle (4 pi / 114, about 0.11 sr, about 19 degrees apart) and the floor bounce
of an environment is captured as well as the sky. Light 0 is nearest the zenith, light 113 nearest
the nadir. The stage is fixed to the camera rig (as in a real light stage, where the cameras are
mounted on the stage), so the light directions are constant in the camera frame, which is the light
vector's frame (addon/lightvec.py); a head that turns sees the lights move relative to it.

Each OLAT image is the subject under one distant light delivering irradiance 1 (W/m2 at normal
incidence). A light vector L maps to stage weights w = P @ (L * Omega): each texel's power goes to
the lights nearest its direction with smooth weights that sum to one, so power is conserved
(sum_j w_j = sum_t L_t Omega_t per channel) and the image under L is sum_j w_j OLAT_j exactly.
"""

from __future__ import annotations

import functools
import math

import numpy as np

from addon import lightvec

N_LIGHTS = 114
# Concentration of the texel->light kernel: wide enough that a moving point light fades smoothly
# between neighbouring lights (about 19 degrees apart), narrow enough to keep directionality.
KAPPA = 40.0


@functools.lru_cache(maxsize=1)
def directions() -> np.ndarray:
    """(114, 3) float64 unit directions in the camera frame (+X right, +Y up, +Z to camera)."""
    i = np.arange(N_LIGHTS, dtype=np.float64) + 0.5
    y = 1.0 - 2.0 * i / N_LIGHTS
    r = np.sqrt(1.0 - y * y)
    phi = math.pi * (3.0 - math.sqrt(5.0)) * i  # golden angle
    d = np.stack([r * np.sin(phi), y, r * np.cos(phi)], axis=1)
    d.setflags(write=False)
    return d


@functools.lru_cache(maxsize=1)
def projection() -> np.ndarray:
    """(114, 256) float64: stage weight per unit texel power; every column sums to 1."""
    d = lightvec.directions().reshape(-1, 3)
    k = np.exp(KAPPA * (d @ directions().T - 1.0))  # (256, 114)
    p = (k / k.sum(axis=1, keepdims=True)).T
    p.setflags(write=False)
    return p


def weights(light: np.ndarray) -> np.ndarray:
    """(114, 3) float64 stage weights (irradiance per light) for a (16, 16, 3) light vector."""
    light = np.asarray(light, dtype=np.float64).reshape(-1, 3)
    power = light * lightvec.solid_angles().reshape(-1, 1)
    return projection() @ power


def light_vector_of(w: np.ndarray) -> np.ndarray:
    """A (16, 16, 3) light vector that puts stage weights (114, 3) back on the sphere: each light
    becomes a bilinear splat at its direction (for previews and the one-light tests)."""
    out = np.zeros(lightvec.SHAPE, dtype=np.float64)
    for j, dj in enumerate(directions()):
        if np.any(w[j] != 0):
            out += lightvec.splat_direction(dj, w[j])
    return out.astype(np.float32)
