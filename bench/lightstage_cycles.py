"""The light stage's renderer against Cycles: the same posed head, camera and light.

    .venv/bin/python bench/lightstage_cycles.py [--res 128] [--samples 64] [--out cache/cycles]

Scope, first: geometry, normals, the cosine term and cast shadows -- the parts every OLAT image
rests on. Both renderers get the same mesh (an ICT-FaceKit identity with expression, hair shell
and torso, posed by training.lightstage), a grey Lambertian albedo of 0.5 everywhere, the same
pinhole camera (our camera frame is Blender's camera frame: +Y up, looking down -Z) and one
distant light of irradiance 1 from a light-stage direction (a Cycles sun of strength 1, angle 0,
no bounces). Ours is ``albedo / pi * transfer.diffuse`` (shadow maps + cosine, no subsurface, no
specular). Hair is Lambertian in Cycles but wrap-lit in ours, so it is reported apart.

Then the skin's material (``--materials``, on by default): the skin faces get a Principled BSDF
with the stage's own parameters (single-scatter GGX; the per-vertex roughness map of
training/lightstage/materials.py as a mesh attribute, so oilier forehead and nose and the lips
match; IOR from the skin's F0 0.028; one constant skin albedo, since the albedo's pore-scale
noise is not carried over) and the other faces stay grey Lambert. Three comparisons over the skin
pixels: the specular lobe alone (base colour black), diffuse + specular, and diffuse + specular +
subsurface scattering (ours: the screen-space per-channel diffusion of shading.subsurface; Cycles:
random-walk subsurface with radius SSS_SIGMA_CM per channel). A fourth row, ours *without*
subsurface against Cycles *with* it, says how much of the gap our subsurface approximation closes.
Albedo texture (pores, freckles, lips' colour) is not compared.

Prints per light: the mean of ours over the mean of Cycles (colour/energy agreement) and the
relative RMSE over the pixels both see as foreground (one pixel in from the silhouette), for
skin/clothes and for hair; writes a side-by-side PNG per light (ours | Cycles | |difference| x4).
The skin rows add the red channel's ratio, Cycles' own noise (relative RMS difference of two
renders with different seeds, over sqrt 2) and the error beyond that noise (sqrt(RMSE^2 -
noise^2)) and the relative RMSE after a 3x3 box filter of both images (what is left when
sub-pixel placement is forgiven: ours shades the pixel centre, Cycles averages over the pixel,
which matters for highlights narrower than a pixel); their PNGs (cycles_skin_*.png) show the GGX
lobe and the subsurface case, skin only.
"""

from __future__ import annotations

import argparse
import builtins
import math
import pathlib
import sys
import tempfile
import time

import bpy
import numpy as np
import torch

ROOT = pathlib.Path(__file__).resolve().parents[1]
if __package__ in (None, ""):  # run as a script: make the repository importable
    sys.path.insert(0, str(ROOT))

from bench import light_conversion  # noqa: E402
from training.eval import report  # noqa: E402
from training.lightstage import assets, layout, materials, shading  # noqa: E402
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
    """Plain Lambert (the diffuse keeps what the skin's specular layer would take)."""
    h, w = scene.cam.height, scene.cam.width
    img = torch.zeros(h * w)
    lambert = scene.transfer(frame, frame.f0, frame.rough, torch.tensor([light]), layered=False)
    img[frame.idx] = ALBEDO / math.pi * lambert.diffuse[:, 0]
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


def aim(sun_obj, direction) -> None:
    """Point the sun so its light arrives from ``direction`` (toward the light)."""
    from mathutils import Vector

    toward = Vector(tuple(float(x) for x in direction))
    sun_obj.rotation_euler = (-toward).to_track_quat('-Z', 'Y').to_euler()


def render(sc, sun_obj, direction, folder) -> tuple[np.ndarray, np.ndarray]:
    aim(sun_obj, direction)
    px = light_conversion.render_rgba(sc, pathlib.Path(folder) / "cycles.exr")
    return px[..., :3].mean(axis=2), px[..., 3]


# The skin comparison's constant albedo: a mid skin tone of the stage's pigment model (linear).
SKIN_MELANIN, SKIN_HAEMOGLOBIN = 0.5, 0.6
# Principled's IOR for the stage's skin F0: F0 = ((n - 1) / (n + 1))^2.
SKIN_IOR = (1 + math.sqrt(materials.F0[assets.SKIN])) / (1 - math.sqrt(materials.F0[assets.SKIN]))


def skin_material(rough_attribute: str):
    """Principled BSDF: single-scatter GGX, roughness from the mesh attribute, the skin's IOR."""
    mat = bpy.data.materials.new("skin")
    nodes, links = mat.node_tree.nodes, mat.node_tree.links
    bsdf = nodes["Principled BSDF"]
    bsdf.distribution, bsdf.subsurface_method = 'GGX', 'RANDOM_WALK'
    bsdf.inputs["IOR"].default_value = SKIN_IOR
    bsdf.inputs["Specular IOR Level"].default_value = 0.5  # 0.5: the reflectance the IOR gives
    bsdf.inputs["Subsurface Radius"].default_value = tuple(float(x) for x in shading.SSS_SIGMA_CM)
    bsdf.inputs["Subsurface Scale"].default_value = 1.0
    attr = nodes.new('ShaderNodeAttribute')
    attr.attribute_type, attr.attribute_name = 'GEOMETRY', rough_attribute
    links.new(attr.outputs["Fac"], bsdf.inputs["Roughness"])
    return mat, bsdf


def set_skin(bsdf, albedo, subsurface: float) -> None:
    bsdf.inputs["Base Color"].default_value = (*(float(a) for a in albedo), 1.0)
    bsdf.inputs["Subsurface Weight"].default_value = subsurface


def our_skin(scene, frame, light: int, albedo, spec: bool = True, sss: bool = True) -> np.ndarray:
    """(3, H, W) ours under one stage light of irradiance 1 with a constant albedo: diffuse
    (optionally diffused under the skin) plus the GGX lobe."""
    h, w = scene.cam.height, scene.cam.width
    irr = torch.zeros(3, h * w)
    irr[:, frame.idx] = frame.transfer.diffuse[:, light].float()
    irr = irr.view(3, h, w)
    if sss:
        irr = shading.subsurface(irr, frame.sss, frame.px_per_cm)
    img = torch.as_tensor(np.asarray(albedo, np.float32))[:, None, None] / math.pi * irr
    if spec:
        s = torch.zeros(h * w)
        s[frame.idx] = frame.transfer.specular[:, light].float()
        img = img + s.view(1, h, w)
    return img.numpy().astype(np.float64)


def vertex_roughness(scene) -> np.ndarray:
    """The skin's roughness map at the mesh's vertices (what ours interpolates per pixel)."""
    n = scene.rig.n_vertices
    skin = torch.full((n,), assets.SKIN, dtype=torch.long)
    _, _, rough, _, _ = materials.surface(skin, scene.rig.uv, scene.attrs, scene.ident)
    return rough.numpy().astype(np.float64)


def erode(mask: np.ndarray) -> np.ndarray:
    """The pixels of ``mask`` whose four neighbours are in it too."""
    out = mask.copy()
    for dy, dx in ((0, 1), (0, -1), (1, 0), (-1, 0)):
        out &= np.roll(mask, (dy, dx), axis=(0, 1))
    return out


def box3(img: np.ndarray) -> np.ndarray:
    """3x3 box filter of (C, H, W) (wrapping at the border; used away from it)."""
    return sum(np.roll(img, (dy, dx), axis=(1, 2)) for dy in (-1, 0, 1) for dx in (-1, 0, 1)) / 9


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
            inner = erode(both)  # one pixel in from every silhouette
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


def compare_materials(res: int, samples: int, out: pathlib.Path, data_root=None) -> list[dict]:
    """The skin's material against Cycles (module doc), per light: mean ratio and relative RMSE
    over skin pixels one pixel in from every edge, for each comparison."""
    torch.set_num_threads(2)
    scene, frame = our_frame(res, data_root=data_root)
    albedo = materials.skin_albedo(SKIN_MELANIN, SKIN_HAEMOGLOBIN)
    sc, sun = cycles_scene(scene, frame, samples)
    mesh = sc.objects["subject"].data
    rough = mesh.attributes.new("rough", 'FLOAT', 'POINT')
    rough.data.foreach_set("value", vertex_roughness(scene).astype(np.float32))
    skin, bsdf = skin_material("rough")
    mesh.materials.append(skin)  # index 1 (index 0: the grey Lambert)
    face_mat = scene.rig.material.numpy()
    mesh.polygons.foreach_set("material_index", (face_mat == assets.SKIN).astype(np.int32))
    face = frame.gb.raster.face.numpy()
    skin_px = (frame.gb.material.numpy() == assets.SKIN) & (face >= 0)
    skin_px &= face_mat[np.maximum(face, 0)] == assets.SKIN  # a skin face in both renderers
    black = (0.0, 0.0, 0.0)
    cases = (("ggx", black, 0.0, dict(spec=True, sss=False)),
             ("diffuse+ggx", albedo, 0.0, dict(spec=True, sss=False)),
             ("diffuse+ggx+sss", albedo, 1.0, dict(spec=True, sss=True)),
             ("ours no sss vs cycles sss", albedo, 1.0, dict(spec=True, sss=False)))
    rows = []
    out.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        for name, d in LIGHTS.items():
            j = nearest_light(d)
            row = {"light": name, "stage_light": j}
            aim(sun, layout.directions()[j])
            tiles = []
            for case, alb, sss, opts in cases:
                set_skin(bsdf, alb, sss)
                t0 = time.perf_counter()
                px = light_conversion.render_rgba(sc, pathlib.Path(tmp) / "cycles.exr")
                secs = time.perf_counter() - t0
                sc.cycles.seed = 2  # Cycles' own noise: the same image with other random numbers
                px2 = light_conversion.render_rgba(sc, pathlib.Path(tmp) / "cycles.exr")
                sc.cycles.seed = 1
                b = px[..., :3].transpose(2, 0, 1)
                b2 = px2[..., :3].transpose(2, 0, 1)
                a = our_skin(scene, frame, j, alb, **opts)
                inner = erode(skin_px & (px[..., 3] > 0.999))
                ra, rb = a[:, inner], b[:, inner]
                deep = erode(inner)  # a 3x3 box there sees skin only
                ba, bb = box3(a)[:, deep], box3(b)[:, deep]
                row[case] = {"pixels": int(inner.sum()),
                             "mean_ratio": float(ra.mean() / max(rb.mean(), 1e-12)),
                             "rel_rmse": float(np.sqrt(((ra - rb) ** 2).mean())
                                               / max(rb.mean(), 1e-12)),
                             "red_ratio": float(ra[0].mean() / max(rb[0].mean(), 1e-12)),
                             "cycles_noise": float(np.sqrt(((b2[:, inner] - rb) ** 2).mean() / 2)
                                                   / max(rb.mean(), 1e-12)),
                             "rel_rmse_box3": float(np.sqrt(((ba - bb) ** 2).mean())
                                                    / max(bb.mean(), 1e-12)),
                             "cycles_seconds": secs}
                m = row[case]  # the error beyond Cycles' noise: RMSE^2 = bias^2 + noise^2
                m["rel_rmse_beyond_noise"] = math.sqrt(max(m["rel_rmse"] ** 2
                                                           - m["cycles_noise"] ** 2, 0.0))
                if case in ("diffuse+ggx+sss", "ggx"):
                    tiles.append((a, b, inner))
            rows.append(row)
            strips = []
            for a, b, inner in tiles:
                e = 0.8 / max(float(np.percentile(b[:, inner].max(0), 99)), 1e-6)
                diff = 4 * np.abs(a - b) * inner
                strips.append(np.concatenate([a * inner * e, b * inner * e, diff * e], 2))
            img = np.concatenate(strips, 1).transpose(1, 2, 0)
            write_png(out / f"cycles_skin_{name}.png", to_srgb8(img, 1.0))
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--res", type=int, default=128)
    ap.add_argument("--samples", type=int, default=64)
    ap.add_argument("--out", default="cache/cycles", help="folder for the side-by-side PNGs")
    ap.add_argument("--report", default=str(ROOT / "bench" / "results" / "lightstage_cycles"),
                    help="write REPORT.md with the printed tables")
    ap.add_argument("--no-materials", dest="materials", action="store_false",
                    help="skip the skin-material comparison (GGX, subsurface)")
    a = ap.parse_args(argv)
    print = report.Lines()  # noqa: A001 - to stdout and to the report
    print("```")
    print(f"Blender {bpy.app.version_string}, Cycles CPU, {a.samples} samples, {a.res}x{a.res}; "
          f"grey Lambert {ALBEDO}, one sun of irradiance 1 per row")
    print("light  stage  region        pixels  ours/Cycles  rel.RMSE   silhouette IoU")
    for r in compare(a.res, a.samples, pathlib.Path(a.out)):
        for region in ("skin+clothes", "hair"):
            if region in r:
                m = r[region]
                print(f"{r['light']:5s}  {r['stage_light']:5d}  {region:12s}  {m['pixels']:6d}  "
                      f"{m['mean_ratio']:11.3f}  {m['rel_rmse']:8.3f}   {r['silhouette_iou']:.3f}")
    if a.materials:
        albedo = np.round(materials.skin_albedo(SKIN_MELANIN, SKIN_HAEMOGLOBIN), 3)
        print(f"\nskin material (Principled, single-scatter GGX, per-vertex roughness, IOR "
              f"{SKIN_IOR:.3f}, albedo {albedo}); over skin pixels")
        print("light  comparison                  pixels  ours/Cycles  red o/C  rel.RMSE  "
              "Cycles noise  beyond noise  3x3 box  Cycles s")
        for r in compare_materials(a.res, a.samples, pathlib.Path(a.out)):
            for case, m in r.items():
                if isinstance(m, dict):
                    print(f"{r['light']:5s}  {case:26s}  {m['pixels']:6d}  "
                          f"{m['mean_ratio']:11.3f}  {m['red_ratio']:7.3f}  {m['rel_rmse']:8.3f}  "
                          f"{m['cycles_noise']:12.3f}  {m['rel_rmse_beyond_noise']:12.3f}  "
                          f"{m['rel_rmse_box3']:7.3f}  "
                          f"{m['cycles_seconds']:8.1f}")
    print("```")
    builtins.print(f"side-by-side PNGs (ours | Cycles | |diff| x4) in {a.out}")
    command = "python bench/lightstage_cycles.py " + " ".join(sys.argv[1:] if argv is None else argv)
    report.write(a.report, "The light stage against Cycles", command.strip(),
                 report.machine_line(report.machine()), "\n\n".join(__doc__.split("\n\n")[2:]).split(
                     "\n\nPrints")[0] + "\n\n" + print.text())


if __name__ == "__main__":
    main()
