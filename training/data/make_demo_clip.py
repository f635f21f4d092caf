"""Render the built-in demo clip (demo/): a short synthetic portrait performance by our light stage.

    .venv/bin/python -m training.data.make_demo_clip       # writes demo/frames/*.png, light.npy

48 frames at 25 fps, 256x256, 8-bit sRGB PNGs, lit by Blender's bundled studio HDRI
(../shared/data/hdri/blender/studio.exr, CC0) normalised to a mean radiance of 1. Rendered at 2x
and box-filtered down (anti-aliasing). The exposure is fixed for the whole clip. The ground-truth
light vector (demo/light.npy, (16, 16, 3) in the camera frame) is saved beside it, together with
the exposure that maps the clip's linear radiance to the PNGs (demo/clip.json).
"""

from __future__ import annotations

import argparse
import json
import pathlib
import shutil

import numpy as np
import torch

from addon import colour, hdri
from addon.hdri_io import read_hdri

from .dataset import renderer_version
from ..lightstage import assets
from ..lightstage.png import to_srgb8, write_png
from ..lightstage.scene import Scene
from ..lightstage.subject import FPS, Camera, Performance, sample_identity

ROOT = pathlib.Path(__file__).resolve().parents[2]
IDENTITY = 20        # a train-split identity with hair, chosen by looking at the candidates
PERFORMANCE = 77
HDRI = "blender/studio.exr"
YAW = 30.0           # HDRI rotation (degrees) so the key light comes from the camera's left


def render_clip(out: pathlib.Path, frames: int = 48, size: int = 256, supersample: int = 2,
                data_root=None) -> dict:
    root = pathlib.Path(data_root) if data_root else assets.default_data_root()
    img = read_hdri(root / "hdri" / HDRI)
    light = hdri.downsample(img, yaw_degrees=YAW, max_width=512, repair=True)
    light = (light / float(light.mean())).astype(np.float32)
    res = size * supersample
    cam = Camera(focal=res * 1.9, cx=res / 2, cy=res * 0.45, distance=75.0, height=res, width=res)
    model = assets.load_head(root)
    perf = Performance(PERFORMANCE, model.expression_names, head_range=0.6)
    scene = Scene(sample_identity(IDENTITY), perf, cam, root, backdrop_seed=4)
    linear = []
    for n in range(frames):
        f = scene.frame(n / FPS)
        x = scene.shade(f, [light])[0]
        x = torch.nn.functional.avg_pool2d(x[None], supersample)[0]
        linear.append(x.permute(1, 2, 0).numpy())
    # One exposure for the clip: the 90th percentile of the first frame's luminance -> 0.6.
    lum = linear[0] @ np.array(colour.REC709_LUMA)
    exposure = 0.6 / float(np.percentile(lum, 90))
    frames_dir = out / "frames"
    if frames_dir.exists():
        shutil.rmtree(frames_dir)
    frames_dir.mkdir(parents=True)
    for n, x in enumerate(linear):
        write_png(frames_dir / f"frame_{n + 1:04d}.png", to_srgb8(x, exposure))
    np.save(out / "light.npy", light)
    meta = {"frames": frames, "fps": FPS, "width": size, "height": size, "colour": "sRGB 8-bit",
            "exposure": exposure, "light": "light.npy: (16,16,3) linear, camera frame, "
            "radiance before exposure", "hdri": HDRI, "hdri_yaw_degrees": YAW,
            "identity": IDENTITY, "performance": PERFORMANCE, "render_version": renderer_version(),
            "command": ".venv/bin/python -m training.data.make_demo_clip"}
    (out / "clip.json").write_text(json.dumps(meta, indent=1) + "\n")
    write_notice(out, root)
    return meta


def write_notice(out: pathlib.Path, root: pathlib.Path) -> None:
    """The ICT-FaceKit MIT notice must travel with every image derived from the head model."""
    licence = (root / "heads" / "LICENSE-ict-facekit.txt").read_text()
    (out / "NOTICE.txt").write_text(
        "The images in this folder are rendered from the ICT-FaceKit morphable head model\n"
        "(https://github.com/ICT-VGL/ICT-FaceKit) by this project's synthetic light stage, lit by\n"
        "Blender's bundled studio HDRI (CC0). ICT-FaceKit is distributed under the MIT licence:\n\n"
        + licence)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", default=str(ROOT / "demo"))
    ap.add_argument("--frames", type=int, default=48)
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--data-root", default=None)
    a = ap.parse_args(argv)
    torch.set_num_threads(2)
    meta = render_clip(pathlib.Path(a.out), a.frames, a.size, data_root=a.data_root)
    print(f"wrote {meta['frames']} frames to {a.out}/frames (exposure {meta['exposure']:.4g})")


if __name__ == "__main__":
    main()
