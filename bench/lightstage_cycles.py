"""The light stage's renderer against Cycles: the same posed head, camera and light.

    .venv/bin/python bench/lightstage_cycles.py [--res 128] [--samples 64] [--out cache/cycles]

Scope: geometry, normals, the cosine term and cast shadows -- the parts every OLAT image rests on.
Both renderers get the same mesh (an ICT-FaceKit identity with expression, hair shell and torso,
posed by training.lightstage), a grey Lambertian albedo of 0.5 everywhere, the same pinhole camera
(our camera frame is Blender's camera frame: +Y up, looking down -Z) and one distant light of
irradiance 1 from a light-stage direction (a Cycles sun of strength 1, angle 0, no bounces). Ours
is ``albedo / pi * transfer.diffuse`` (shadow maps + cosine, no subsurface, no specular). Skin
texture, subsurface scattering and GGX are not compared here. Hair is Lambertian in Cycles but
wrap-lit in ours, so it is reported apart.

Prints per light: the mean of ours over the mean of Cycles (colour/energy agreement) and the
relative RMSE over the pixels both see as foreground (one pixel in from the silhouette), for
skin/clothes and for hair; writes a side-by-side PNG per light (ours | Cycles | |difference| x4).
"""

from __future__ import annotations

import argparse
import math
import pathlib
import sys
import tempfile

import bpy
import numpy as np
import torch

if __package__ in (None, ""):  # run as a script: make the repository importable
    sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))

from bench import light_conversion  # noqa: E402
from training.lightstage import assets, layout  # noqa: E402
from training.lightstage.png import to_srgb8, write_png  # noqa: E402
from training.lightstage.scene import Scene  # noqa: E402
from training.lightstage.subject import Camera, Performance, sample_identity  # noqa: E402

ALBEDO = 0.5
# Stage lights: near the camera axis up-left (a key light), to the right (a side light, strong
# nose and neck shadows) and above (eye sockets, under the chin).
LIGHTS = {"key": (-0.45, 0.45, 0.77), "side": (0.95, 0.1, 0.3), "top": (0.1, 0.95, 0.3)}


def nearest_light(d) -> int:
    d = np.asarray(d, np.float64) / np.linalg.norm(d)
    return int(np.argmax(layout.directions() @ d))


def our_frame(res: int, identity: int = 3, t: float = 0.8, data_root=None):
    root = data_root or assets.default_data_root()
    m = assets.load_head(root)
    cam = Camera(focal=res * 1.8, cx=res / 2, cy=res / 2, distance=72.0, height=res, width=res)
    perf = Performance(identity, m.expression_names, head_range=0.4)
    scene = Scene(sample_identity(identity), perf, cam, root, 1)
    return scene, scene.frame(t)


def ours(scene, frame, light: int) -> np.ndarray:
    h, w = scene.cam.height, scene.cam.width
    img = torch.zeros(h * w)
    img[frame.idx] = ALBEDO / math.pi * frame.transfer.diffuse[:, light]
    return img.view(h, w).numpy().astype(np.float64)


def cycles_scene(scene, frame, samples: int):
    sc = light_conversion.direct_light_scene(scene.cam.width, scene.cam.height, samples)
    sc.render.film_transparent = True

    mesh = bpy.data.meshes.new("subject")
    verts = frame.posed.verts.numpy().astype(np.float64)
    mesh.from_pydata(verts.tolist(), [], scene.rig.faces.numpy().tolist())
    mesh.shade_smooth()
    mesh.materials.append(light_conversion.diffuse_material("grey", ALBEDO))
    sc.collection.objects.link(bpy.data.objects.new("subject", mesh))

    cam = bpy.data.cameras.new("camera")  # at the origin, looking down -Z, +Y up: our frame
    cam.sensor_fit, cam.sensor_width = 'HORIZONTAL', 36.0
    cam.lens = scene.cam.focal * 36.0 / scene.cam.width
    cam.clip_start, cam.clip_end = 1.0, 1000.0
    obj = bpy.data.objects.new("camera", cam)
    sc.collection.objects.link(obj)
    sc.camera = obj
    sun = bpy.data.lights.new("sun", 'SUN')
    sun.energy, sun.angle = 1.0, 0.0
    sun_obj = bpy.data.objects.new("sun", sun)
    sc.collection.objects.link(sun_obj)
    return sc, sun_obj


def render(sc, sun_obj, direction, folder) -> tuple[np.ndarray, np.ndarray]:
    from mathutils import Vector

    toward = Vector(tuple(float(x) for x in direction))
    sun_obj.rotation_euler = (-toward).to_track_quat('-Z', 'Y').to_euler()
    px = light_conversion.render_rgba(sc, pathlib.Path(folder) / "cycles.exr")
    return px[..., :3].mean(axis=2), px[..., 3]


def compare(res: int, samples: int, out: pathlib.Path, data_root=None) -> list[dict]:
    torch.set_num_threads(2)
    scene, frame = our_frame(res, data_root=data_root)
    sc, sun = cycles_scene(scene, frame, samples)
    mat = frame.gb.material.numpy()
    ours_fg = frame.gb.mask.numpy()
    rows = []
    out.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        for name, d in LIGHTS.items():
            j = nearest_light(d)
            a = ours(scene, frame, j)
            b, alpha = render(sc, sun, layout.directions()[j], tmp)
            both = ours_fg & (alpha > 0.999)
            inner = both.copy()  # one pixel in from every silhouette
            for dy, dx in ((0, 1), (0, -1), (1, 0), (-1, 0)):
                inner &= np.roll(both, (dy, dx), axis=(0, 1))
            row = {"light": name, "stage_light": j}
            for region, sel in (("skin+clothes", inner & (mat != assets.HAIR)),
                                ("hair", inner & (mat == assets.HAIR))):
                if sel.sum() < 20:
                    continue
                ra, rb = a[sel], b[sel]
                row[region] = {"pixels": int(sel.sum()), "mean_ratio": float(ra.mean() / rb.mean()),
                               "rel_rmse": float(np.sqrt(((ra - rb) ** 2).mean()) / rb.mean())}
            row["silhouette_iou"] = float((ours_fg & (alpha > 0.5)).sum()
                                          / max((ours_fg | (alpha > 0.5)).sum(), 1))
            rows.append(row)
            e = 0.8 / max(float(np.percentile(b[both], 99)), 1e-6)
            tile = np.concatenate([a, b, 4 * np.abs(a - b) * both], 1)
            write_png(out / f"cycles_{name}.png", to_srgb8(np.repeat(tile[..., None], 3, 2), e))
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--res", type=int, default=128)
    ap.add_argument("--samples", type=int, default=64)
    ap.add_argument("--out", default="cache/cycles", help="folder for the side-by-side PNGs")
    a = ap.parse_args(argv)
    print(f"Blender {bpy.app.version_string}, Cycles CPU, {a.samples} samples, {a.res}x{a.res}; "
          f"grey Lambert {ALBEDO}, one sun of irradiance 1 per row")
    print("light  stage  region        pixels  ours/Cycles  rel.RMSE   silhouette IoU")
    for r in compare(a.res, a.samples, pathlib.Path(a.out)):
        for region in ("skin+clothes", "hair"):
            if region in r:
                m = r[region]
                print(f"{r['light']:5s}  {r['stage_light']:5d}  {region:12s}  {m['pixels']:6d}  "
                      f"{m['mean_ratio']:11.3f}  {m['rel_rmse']:8.3f}   {r['silhouette_iou']:.3f}")
    print(f"side-by-side PNGs (ours | Cycles | |diff| x4) in {a.out}")


if __name__ == "__main__":
    main()
