"""The README's picture: a frame of the built-in demo clip and the same frame relit.

    .venv/bin/python -m training.eval.before_after [--preset portrait] [--out demo/before_after.png]

Each relit frame is what the product writes (``addon.relight_image``, the pipeline's own path)
under lamps converted in Blender's units (``addon.lamps``); the demo clip is our own synthetic
render (demo/README.md), so the picture may be committed.
"""

from __future__ import annotations

import argparse
import pathlib

import numpy as np

from addon import api, colour, lamps

from ..lightstage.png import read_png, write_png

ROOT = pathlib.Path(__file__).resolve().parents[2]
SUBJECT_RADIUS = 0.15  # metres: the demo head's scale


def _point(position, color, energy) -> lamps.Lamp:
    return lamps.Lamp("POINT", position, (0.0, 0.0, -1.0), color, energy)


LIGHTINGS = (
    ("key from the left", (_point((-1.0, 0.5, 1.0), (1.0, 0.93, 0.85), 1000.0),)),
    ("key from the right", (_point((1.0, 0.4, 0.9), (1.0, 0.93, 0.85), 1000.0),)),
    ("blue rim + fill", (_point((0.8, 0.7, -1.1), (0.25, 0.5, 1.0), 2000.0),
                         _point((0.0, 0.0, 1.6), (1.0, 1.0, 1.0), 250.0))),
)


def sheet(frame: np.ndarray, preset: str, models_dir=None, gap: int = 4) -> np.ndarray:
    """[input | relit under each of LIGHTINGS] as one 8-bit sRGB image."""
    linear = colour.srgb_to_linear(frame.astype(np.float32) / 255.0)
    tiles = [frame]
    for _, setup in LIGHTINGS:
        light, _ = lamps.lamps_to_light(setup, SUBJECT_RADIUS)
        out = api.relight_image(linear, light, preset, models_dir)
        tiles.append(np.round(255 * np.clip(colour.linear_to_srgb(np.clip(out, 0, 1)), 0, 1))
                     .astype(np.uint8))
    h = frame.shape[0]
    bar = np.full((h, gap, 3), 255, np.uint8)
    return np.concatenate([t if i == 0 else np.concatenate([bar, t], 1)
                           for i, t in enumerate(tiles)], 1)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--preset", default="portrait")
    p.add_argument("--frame", type=int, default=1, help="demo frame number (1-48)")
    p.add_argument("--out", default=str(ROOT / "demo" / "before_after.png"))
    a = p.parse_args(argv)
    frame = read_png(ROOT / "demo" / "frames" / f"frame_{a.frame:04d}.png")[..., :3]
    write_png(a.out, sheet(frame, a.preset))
    print(f"wrote {a.out}: input, then " + ", ".join(name for name, _ in LIGHTINGS))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
