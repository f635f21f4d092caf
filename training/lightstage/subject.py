"""Random subjects, their performance over time, and the camera (all deterministic from seeds).

An identity is drawn from its integer id alone (so a split can own a fixed set of ids): shape
weights ~ N(0, 1), skin pigments, hair style and colour, eyes, clothes. A performance is a set of
smooth curves of time (seconds): sums of a few random sinusoids for speech-like jaw and mouth
motion, smiles, brows, gaze and head motion, plus blink events; evaluating it at t and t + 1/25
gives two adjacent 25 fps frames without simulating the frames before them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from .assets import HairStyle

FPS = 25.0
IDENTITY_SALT = 0x1D3E7
LONG_HAIR_SALT = 0x10A6
HAIR_COLOURS = np.array([  # linear albedo of hair: black, dark brown, brown, auburn, blonde, grey
    [0.012, 0.010, 0.009], [0.035, 0.020, 0.012], [0.09, 0.05, 0.025], [0.16, 0.055, 0.02],
    [0.38, 0.26, 0.13], [0.35, 0.34, 0.33]])
IRIS_COLOURS = np.array([[0.06, 0.025, 0.01], [0.12, 0.06, 0.02], [0.08, 0.12, 0.16],
                         [0.07, 0.10, 0.05], [0.10, 0.16, 0.22]])


@dataclass(frozen=True)
class Identity:
    id: int
    shape: np.ndarray = field(repr=False)   # (100,) identity weights
    melanin: float = 0.5                    # 0.05 very light .. 4 very dark (see materials.py)
    haemoglobin: float = 0.6
    hair: HairStyle = HairStyle()
    hair_colour: np.ndarray = field(default=None, repr=False)
    iris_colour: np.ndarray = field(default=None, repr=False)
    clothes_colour: np.ndarray = field(default=None, repr=False)
    neckline: float = -11.0
    beard: float = 0.0
    freckles: float = 0.0
    brow_density: float = 1.0
    texture_seed: int = 0


def sample_identity(identity_id: int, shape_scale: float = 1.0,
                    long_hair: float = 0.0) -> Identity:
    """The identity ``identity_id``. With ``long_hair`` > 0 that fraction of the identities with
    hair wear it long (``HairStyle.hang``), drawn from a stream of its own, so everything else
    about an identity is the same whatever ``long_hair`` is."""
    ident = _draw_identity(identity_id, shape_scale)
    if long_hair <= 0 or ident.hair.bald:
        return ident
    rng = np.random.default_rng([IDENTITY_SALT, int(identity_id), LONG_HAIR_SALT])
    if rng.random() >= long_hair:
        return ident
    # From chin length to past the shoulders; each side's front edge from framing the cheek to
    # behind the ear, and one side in four tucked back behind the shoulder.
    hang = float(rng.uniform(3.0, 18.0))
    reach = rng.uniform(55.0, 100.0, 2)
    reach = np.where(rng.random(2) < 0.25, rng.uniform(130.0, 160.0, 2), reach)
    style = replace(ident.hair, hang=round(hang, 1),
                    reach=tuple(round(float(r), 1) for r in reach))
    return replace(ident, hair=style)


def _draw_identity(identity_id: int, shape_scale: float) -> Identity:
    rng = np.random.default_rng([IDENTITY_SALT, int(identity_id)])
    shape = rng.standard_normal(100).astype(np.float32) * shape_scale
    melanin = float(np.exp(rng.uniform(np.log(0.05), np.log(4.0))))
    bald = rng.random() < 0.12
    style = HairStyle(front=float(rng.uniform(7.5, 10.0)), side=float(rng.uniform(4.8, 6.5)),
                      nape=float(rng.uniform(-9.0, -4.0)), volume=float(rng.uniform(0.3, 2.5)),
                      bald=bool(bald))
    hair_idx = rng.choice(len(HAIR_COLOURS), p=[0.3, 0.25, 0.15, 0.08, 0.12, 0.1])
    hair = HAIR_COLOURS[hair_idx] * rng.uniform(0.8, 1.25, 3)
    return Identity(
        id=int(identity_id), shape=shape, melanin=melanin,
        haemoglobin=float(rng.uniform(0.3, 1.0)), hair=style, hair_colour=hair,
        iris_colour=IRIS_COLOURS[rng.integers(len(IRIS_COLOURS))] * rng.uniform(0.8, 1.2, 3),
        clothes_colour=rng.uniform(0.02, 0.7, 3) ** 1.5, neckline=float(rng.uniform(-16.0, -12.5)),
        beard=float(rng.random() < 0.3) * float(rng.uniform(0.2, 1.0)),
        freckles=float(rng.random() < 0.25) * float(rng.uniform(0.2, 1.0)),
        brow_density=float(rng.uniform(0.5, 1.2)), texture_seed=int(rng.integers(2 ** 31)))


class _Curve:
    """A smooth random curve: offset + sum of sinusoids with random frequencies and phases."""

    def __init__(self, rng, lo_hz, hi_hz, amplitude, offset=0.0, n=3):
        self.f = rng.uniform(lo_hz, hi_hz, n)
        self.p = rng.uniform(0, 2 * math.pi, n)
        self.a = amplitude * rng.uniform(0.5, 1.0, n) / n ** 0.5
        self.offset = offset

    def __call__(self, t: float) -> float:
        return float(self.offset + np.sum(self.a * np.sin(2 * math.pi * self.f * t + self.p)))


@dataclass
class Performance:
    """Expression weights (57,) and head pose as functions of time t (seconds)."""
    seed: int
    expression_names: tuple
    intensity: float = 1.0          # scales all expression motion; >1 for extreme tests
    head_range: float = 1.0         # scales the head's rotation range

    def __post_init__(self):
        rng = np.random.default_rng([0x9E3779, self.seed])
        s = self.intensity
        self.jaw = _Curve(rng, 2.0, 5.0, 0.45 * s, 0.12 * s)
        self.mouth = {k: _Curve(rng, 1.0, 4.0, 0.5 * s) for k in
                      ("mouthFunnel", "mouthPucker", "mouthClose", "mouthLowerDown_L",
                       "mouthUpperUp_L", "mouthStretch_L", "mouthPress_L", "mouthRollLower")}
        self.smile = _Curve(rng, 0.05, 0.3, 0.8 * s, rng.uniform(-0.3, 0.4) * s)
        self.brows = _Curve(rng, 0.1, 0.6, 0.8 * s, 0.0)
        self.gaze_x = _Curve(rng, 0.1, 0.8, 0.7 * s)
        self.gaze_y = _Curve(rng, 0.1, 0.6, 0.4 * s)
        self.blink_period = rng.uniform(2.0, 5.0)
        self.blink_seed = int(rng.integers(2 ** 31))
        r = self.head_range
        self.yaw = _Curve(rng, 0.05, 0.4, 40.0 * r, rng.uniform(-25, 25) * r)
        self.pitch = _Curve(rng, 0.05, 0.5, 14.0 * r, rng.uniform(-8, 8) * r)
        self.roll = _Curve(rng, 0.05, 0.4, 8.0 * r, 0.0)
        self.tx = _Curve(rng, 0.05, 0.4, 2.0)
        self.ty = _Curve(rng, 0.05, 0.4, 1.0)
        self.tz = _Curve(rng, 0.05, 0.3, 2.0)
        self.body_yaw = _Curve(rng, 0.03, 0.2, 10.0 * r, rng.uniform(-15, 15) * r)

    def blink(self, t: float) -> float:
        k0 = int(math.floor(t / self.blink_period))
        out = 0.0
        for k in (k0 - 1, k0, k0 + 1):
            r = np.random.default_rng([self.blink_seed, k & 0x7FFFFFFF])
            centre = (k + r.uniform(0.1, 0.9)) * self.blink_period
            half = r.uniform(0.06, 0.12)
            out = max(out, max(0.0, 1.0 - abs(t - centre) / half))
        return out

    def expression(self, t: float) -> np.ndarray:
        names = self.expression_names
        w = np.zeros(len(names), np.float32)

        def put(name, val):
            if name in names:
                w[names.index(name)] = max(w[names.index(name)], val)

        put("jawOpen", self.jaw(t))
        for k, c in self.mouth.items():
            v = c(t)
            put(k, v)
            if k.endswith("_L"):
                put(k[:-2] + "_R", v)
        put("mouthSmile_L", self.smile(t))
        put("mouthSmile_R", self.smile(t))
        put("cheekSquint_L", 0.5 * self.smile(t))
        put("cheekSquint_R", 0.5 * self.smile(t))
        b = self.brows(t)
        for side in "LR":
            put(f"browInnerUp_{side}", b)
            put(f"browOuterUp_{side}", 0.7 * b)
            put(f"browDown_{side}", -b)
            put(f"eyeBlink_{side}", self.blink(t))
        gx, gy = self.gaze_x(t), self.gaze_y(t)
        put("eyeLookOut_L", gx)
        put("eyeLookIn_R", gx)
        put("eyeLookIn_L", -gx)
        put("eyeLookOut_R", -gx)
        put("eyeLookUp_L", gy)
        put("eyeLookUp_R", gy)
        put("eyeLookDown_L", -gy)
        put("eyeLookDown_R", -gy)
        hi = 1.0 if self.intensity <= 1.0 else self.intensity
        return np.clip(w, 0.0, hi)

    def head_pose(self, t: float) -> tuple[np.ndarray, np.ndarray, float]:
        """(yaw, pitch, roll) degrees of the head, translation (cm), body yaw (degrees)."""
        return (np.array([self.yaw(t), self.pitch(t), self.roll(t)]),
                np.array([self.tx(t), self.ty(t), self.tz(t)]), self.body_yaw(t))


@dataclass(frozen=True)
class Camera:
    """Pinhole camera at the origin looking down -Z (+Y up); pixels: x right, y down."""
    focal: float        # pixels
    cx: float
    cy: float
    distance: float     # cm from the camera to the neck pivot
    height: int
    width: int

    def project(self, p):
        """(N, 3) camera-frame points (torch or numpy) -> (N, 3): x, y pixels, depth."""
        z = -p[:, 2]
        x = self.focal * p[:, 0] / z + self.cx
        y = -self.focal * p[:, 1] / z + self.cy
        lib = np if isinstance(p, np.ndarray) else __import__("torch")
        return lib.stack([x, y, z], 1)


def sample_camera(rng: np.random.Generator, resolution: int) -> Camera:
    """Portrait framings from a close-up (half the frame height covers ~12 cm at the subject) to
    head-and-shoulders (~38 cm), focal lengths 35-135 mm equivalent, subject not always centred."""
    half_extent = float(np.exp(rng.uniform(np.log(12.0), np.log(38.0))))
    fov = math.radians(rng.uniform(15.0, 55.0))
    focal = (resolution / 2) / math.tan(fov / 2)
    distance = half_extent / math.tan(fov / 2)
    # Aim: the head (about 8 cm above the neck pivot) lands off-centre by up to a fifth of a frame.
    off = rng.uniform(-0.2, 0.2, 2) * resolution
    # Wider framings put the face in the upper part of the frame, as portrait photographers do.
    lift = 0.18 * resolution * (half_extent - 12.0) / 26.0
    return Camera(focal=focal, cx=resolution / 2 + off[0], cy=resolution / 2 + off[1] - lift,
                  distance=distance, height=resolution, width=resolution)
