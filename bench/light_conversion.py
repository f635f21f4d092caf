"""Lighting conversion against Cycles: referee error and conversion time.

Blender's own renderer is the referee: a diffuse white sphere (radius R, at the subject position) is
rendered by Cycles on the CPU under a lamp or a world HDRI, and the same sphere is shaded
analytically from the light vector that ops/scene_light.py converts from that very scene
(irradiance x albedo / pi). The error is the relative RMSE ||shaded - render|| / ||render|| over
the sphere's pixels that face the light (all of the sphere's pixels for a world).

    .venv/bin/python bench/light_conversion.py            # full table (about 1-2 minutes)
    .venv/bin/python bench/light_conversion.py --quick    # fewer cases

Writes bench/results/light_conversion.md (--out) with the tables and what they say.

tests/blender/test_cycles_referee.py uses the same scene builder with asserted bounds.
"""

from __future__ import annotations

import argparse
import math
import pathlib
import sys
import tempfile
import time

import bpy
import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]
if __package__ in (None, ""):  # run as a script: make the repository importable
    sys.path.insert(0, str(ROOT))

from bench import extension  # noqa: E402
from training.eval import report  # noqa: E402

RADIUS = 1.0  # the sphere (subject) radius in metres; everything scales with it
ORTHO_SCALE = 2.2 * RADIUS
# A lamp direction off every axis and between cell centres, as the light frame sees it.
LAMP_DIR = np.array([0.45, 0.35, 0.82]) / np.linalg.norm([0.45, 0.35, 0.82])
DISTANCES = (1.2, 2.0, 4.0, 10.0)


def addon_module(name: str):
    """``addon.<name>`` from the extension package (works when run as a script, too)."""
    return extension.submodule(f"addon.{name}")


def scene_light_module():
    return extension.submodule("ops.scene_light")


def direct_light_scene(width: int, height: int, samples: int, world_name: str = "black"):
    """A fresh empty scene for the Cycles referees (here and bench/lightstage_cycles.py): Cycles
    on the CPU, direct light only (the renderers compared have no interreflection), no denoising
    or adaptive sampling, box filter, fixed seed, two threads, a 'Standard' view, 32-bit EXR
    output and a black world."""
    bpy.ops.wm.read_homefile(use_empty=True)
    scene = bpy.context.scene
    scene.render.engine = 'CYCLES'
    cyc = scene.cycles
    cyc.device = 'CPU'
    cyc.samples, cyc.use_denoising, cyc.use_adaptive_sampling = samples, False, False
    cyc.max_bounces = 0
    cyc.pixel_filter_type = 'BOX'
    cyc.seed = 1
    scene.render.resolution_x, scene.render.resolution_y = width, height
    scene.render.resolution_percentage = 100
    scene.render.threads_mode, scene.render.threads = 'FIXED', 2
    scene.view_settings.view_transform = 'Standard'
    scene.view_settings.exposure, scene.view_settings.gamma = 0.0, 1.0
    scene.render.image_settings.file_format = 'OPEN_EXR'
    scene.render.image_settings.color_depth = '32'
    world = bpy.data.worlds.new(world_name)
    world.node_tree.nodes["Background"].inputs["Strength"].default_value = 0.0
    scene.world = world
    return scene


def diffuse_material(name: str, albedo: float):
    """A grey Lambertian material (a Diffuse BSDF in place of the Principled one)."""
    mat = bpy.data.materials.new(name)
    nodes = mat.node_tree.nodes
    nodes.remove(nodes["Principled BSDF"])
    diffuse = nodes.new('ShaderNodeBsdfDiffuse')
    diffuse.inputs["Color"].default_value = (albedo, albedo, albedo, 1.0)
    mat.node_tree.links.new(diffuse.outputs[0], nodes["Material Output"].inputs["Surface"])
    return mat


def render_rgba(scene, path) -> np.ndarray:
    """Render with Cycles to a 32-bit EXR at ``path``; its RGBA pixels (top row first)."""
    import OpenEXR

    scene.render.filepath = str(path)
    bpy.ops.render.render(write_still=True)
    with OpenEXR.File(str(path)) as f:
        return np.array(f.channels()["RGBA"].pixels, dtype=np.float64)


def referee_scene(res: int = 64, samples: int = 32):
    """A fresh scene: a white diffuse sphere at the origin, an orthographic camera on -Y looking
    at it (Blender's front view: light frame X = world X, Y = world Z, Z = world -Y), black world,
    Cycles on the CPU with no denoising and a 'Standard' view. Returns (scene, camera, sphere)."""
    import bmesh

    scene = direct_light_scene(res, res, samples, "referee")
    mesh = bpy.data.meshes.new("sphere")
    bm = bmesh.new()
    bmesh.ops.create_uvsphere(bm, u_segments=128, v_segments=64, radius=RADIUS)
    bm.to_mesh(mesh)
    bm.free()
    mesh.shade_smooth()
    mesh.materials.append(diffuse_material("white", 1.0))
    sphere = bpy.data.objects.new("subject", mesh)
    scene.collection.objects.link(sphere)

    cam_data = bpy.data.cameras.new("camera")
    cam_data.type, cam_data.ortho_scale = 'ORTHO', ORTHO_SCALE
    camera = bpy.data.objects.new("camera", cam_data)
    camera.location, camera.rotation_euler = (0.0, -20.0 * RADIUS, 0.0), (math.pi / 2, 0.0, 0.0)
    scene.collection.objects.link(camera)
    scene.camera = camera
    return scene, camera, sphere


def frame_to_world(v) -> tuple[float, float, float]:
    """A light-frame vector in the referee scene's world (camera on -Y looking at +Y)."""
    x, y, z = v
    return (float(x), float(-z), float(y))


def add_lamp(scene, kind: str, distance: float | None = None, direction=LAMP_DIR, name="lamp",
             **props):
    """A lamp ``distance`` radii from the centre along ``direction`` (light frame), aimed at the
    centre; ``props`` set Blender light properties."""
    from mathutils import Vector

    data = bpy.data.lights.new(name, kind)
    for key, value in props.items():
        setattr(data, key, value)
    obj = bpy.data.objects.new(name, data)
    toward = Vector(frame_to_world(direction))
    obj.location = toward * (distance or 20.0) * RADIUS
    obj.rotation_euler = (-toward).to_track_quat('-Z', 'Y').to_euler()  # emit toward the centre
    scene.collection.objects.link(obj)
    return obj


def render_linear(scene, folder) -> np.ndarray:
    """Render with Cycles; read the scene-linear result back from a 32-bit EXR (top row first)."""
    return render_rgba(scene, pathlib.Path(folder) / "referee.exr")[..., :3]


def sphere_normals(res: int) -> tuple[np.ndarray, np.ndarray]:
    """Light-frame normals of the sphere under each pixel, and the mask of pixels well inside the
    silhouette (the rim mixes sphere and background and is left out)."""
    c = ((np.arange(res) + 0.5) / res - 0.5) * ORTHO_SCALE / RADIUS
    x, y = np.meshgrid(c, -c)
    r2 = x * x + y * y
    normals = np.stack([x, y, np.sqrt(np.clip(1.0 - r2, 0.0, None))], axis=-1)
    return normals, r2 < 0.95 ** 2


def shade(light: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """The white Lambertian sphere under a light vector: irradiance / pi."""
    return addon_module("lightvec").irradiance(light, normals) / math.pi


def rel_rmse(pred: np.ndarray, truth: np.ndarray, mask: np.ndarray) -> float:
    diff = (pred - truth)[mask]
    return float(np.linalg.norm(diff) / np.linalg.norm(truth[mask]))


def convert(scene, camera, sphere, **kw):
    """The scene's light vector (frame 1) through the real bridge, and the seconds it took."""
    scene_light = scene_light_module()
    args = dict(source='LAMPS', rotation_deg=0.0, exposure=0.0, subject=sphere, camera=camera,
                subject_radius=RADIUS) | kw
    t0 = time.perf_counter()
    schedule = scene_light.light_schedule(scene, [scene.frame_current], **args)
    return schedule.lights[0], time.perf_counter() - t0


def lamp_case(kind: str, distance: float | None, folder, res=64, samples=32, **props) -> dict:
    """Render one lamp case and compare; returns error, conversion time and the images."""
    scene, camera, sphere = referee_scene(res, samples)
    add_lamp(scene, kind, distance, **props)
    truth = render_linear(scene, folder)
    light, _ = convert(scene, camera, sphere)
    seconds = float(np.median([convert(scene, camera, sphere)[1] for _ in range(5)]))
    normals, inside = sphere_normals(res)
    facing = inside & (normals @ LAMP_DIR > 0)
    pred = shade(light, normals)
    return dict(error=rel_rmse(pred, truth, facing), seconds=seconds, truth=truth, pred=pred,
                mask=facing, light=light)


def synthetic_hdri(height: int = 64) -> np.ndarray:
    """A small equirect map: a dim sky gradient plus one bright warm patch at u=0.3, v=0.35."""
    w = 2 * height
    v = (np.arange(height) + 0.5) / height
    img = np.zeros((height, w, 3), np.float32)
    img[:] = (0.2 + 0.6 * np.clip(1 - v, 0, 1))[:, None, None] * np.array([0.4, 0.6, 1.0])
    r0, c0 = int(0.35 * height), int(0.3 * w)
    img[r0 - 3:r0 + 3, c0 - 4:c0 + 4] = [40.0, 30.0, 20.0]
    return img


def write_exr(path, rgb: np.ndarray) -> str:
    import OpenEXR

    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with OpenEXR.File(header, {"RGB": np.ascontiguousarray(rgb, dtype=np.float32)}) as f:
        f.write(str(path))
    return str(path)


def set_world_hdri(scene, path: str, strength: float = 1.0, mapping_z_deg: float = 0.0):
    """The world lit by an equirect HDRI through an Environment Texture (and a Mapping node)."""
    tree = scene.world.node_tree
    bg = tree.nodes["Background"]
    bg.inputs["Strength"].default_value = strength
    env = tree.nodes.new('ShaderNodeTexEnvironment')
    env.image = bpy.data.images.load(path)
    tree.links.new(env.outputs["Color"], bg.inputs["Color"])
    if mapping_z_deg:
        coords = tree.nodes.new('ShaderNodeTexCoord')
        mapping = tree.nodes.new('ShaderNodeMapping')
        mapping.inputs["Rotation"].default_value[2] = math.radians(mapping_z_deg)
        tree.links.new(coords.outputs["Generated"], mapping.inputs["Vector"])
        tree.links.new(mapping.outputs["Vector"], env.inputs["Vector"])


def world_case(path: str, folder, res=48, samples=256, mapping_z_deg=0.0, widths=None) -> dict:
    """Render the sphere under a world HDRI; the error of the conversion at each working width."""
    scene_light = scene_light_module()
    scene, camera, sphere = referee_scene(res, samples)
    set_world_hdri(scene, path, mapping_z_deg=mapping_z_deg)
    truth = render_linear(scene, folder)
    normals, inside = sphere_normals(res)
    out = {}
    saved = scene_light.HDRI_WIDTH
    widths = widths or (saved,)
    try:
        for width in widths:
            scene_light.HDRI_WIDTH = width
            light, seconds = convert(scene, camera, sphere, source='WORLD')
            out[width] = dict(error=rel_rmse(shade(light, normals), truth, inside),
                              seconds=seconds, light=light, truth=truth, mask=inside)
    finally:
        scene_light.HDRI_WIDTH = saved
    return out


def _time_conversion(fn, repeats: int = 5) -> tuple[float, float]:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times)), float(np.max(times) - np.min(times))


FINDINGS = """What the figures say:
- **Units are Blender's, as Cycles renders them**: point and spot intensity
  `colour x energy x 2^exposure / (4 pi)` W/sr, the spot cone only masks (Cycles' smoothstep
  blend), sun irradiance `colour x energy x 2^exposure` W/m2 spread over its disc, area radiance
  `P / (pi A)` (`normalize` off: `P / pi`, power per m2), temperature through Blender's own
  `temperature_color`. The light's `diffuse_factor` is EEVEE's and Cycles ignores it; a lamp
  hidden from diffuse rays gives no light.
- **Suns and worlds are within a few per cent**, what the 16x16 cells cost: they quantise a small
  bright source's direction by up to half a cell.
- **Near lamps cannot be reproduced by distant light; that error is unavoidable.** A point lamp at
  k radii lights less than a hemisphere and its shading falls off faster than the cosine from its
  brightest point; any non-negative distant light's shading falls off no faster than the cosine,
  so no light vector can match it. The conversion takes the least-squares best fit (one direction
  scaled by `lamps.near_field_gain(k)`); the floor of that fit is printed above ("unavoidable
  part") and matches the measured errors within the cells' cost. Area lamps are split into 64
  patches, so a big close panel becomes a broad light.
- The HDRI working width changes conversion time and power conservation, not the shading.
- Lamps whose share of the total power is below 1e-3 are skipped (`lamps.lamps_to_light`).
  Static lighting is converted once; keyed lamps, world, camera, subject or rotation give one
  light vector per frame. `rotation` turns the lighting like a world Mapping node's Z rotation.
"""


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="fewer distances and widths")
    parser.add_argument("--out", default=str(ROOT / "bench" / "results" / "light_conversion"),
                        help="write OUT.md")
    args = parser.parse_args(argv)
    distances = (1.2, 4.0) if args.quick else DISTANCES
    print = report.Lines()  # noqa: A001 - the tables go to stdout and to the report
    setup = (f"Blender {bpy.app.version_string}, Cycles CPU (32 samples, no denoising, linear EXR); "
             f"sphere radius {RADIUS} m, 64x64 pixels; relative RMSE = ||shaded - render|| / "
             "||render|| over the sphere's pixels that face the light (all of them for a world).")
    print(setup)
    print("\n| lamp | distance (radii) | relative RMSE | conversion (ms, median of 5) |\n"
          "| --- | --- | --- | --- |")
    with tempfile.TemporaryDirectory() as folder:
        for kind, props in LAMP_CASES:
            for k in ([None] if kind == 'SUN' else distances):
                r = lamp_case(kind, k, folder, **props)
                label = f"{kind.lower()} {_describe(props)}".strip()
                print(f"| {label} | {'-' if k is None else k} | {r['error']:.3f} | "
                      f"{1e3 * r['seconds']:.2f} |")
        print("\nUnavoidable part for a point lamp (least-squares distant fit, analytic, "
              "addon.lamps): " + ", ".join(f"{k} radii: {_point_floor(k):.3f}" for k in distances))
        _world_table(folder, args.quick, print)
    command = "python bench/light_conversion.py " + " ".join(sys.argv[1:] if argv is None else argv)
    report.write(args.out, "Lighting conversion against Cycles", command.strip(),
                 report.machine_line(report.machine()), print.text() + "\n\n" + FINDINGS)


LAMP_CASES = (
    ('POINT', {}),
    ('SPOT', dict(spot_size=math.radians(60.0), spot_blend=0.15)),
    ('AREA', dict(size=1.0 * RADIUS)),
    ('SUN', dict(angle=math.radians(0.5))),
    ('SUN', dict(angle=math.radians(30.0))),
    ('SUN', dict(angle=math.radians(90.0))),
)


def _describe(props: dict) -> str:
    parts = []
    if "spot_size" in props:
        parts.append(f"{math.degrees(props['spot_size']):.0f} deg cone")
    if "size" in props:
        parts.append(f"{props['size'] / RADIUS:g} R square")
    if "angle" in props:
        parts.append(f"{math.degrees(props['angle']):g} deg disc")
    return ", ".join(parts)


def _point_floor(k: float) -> float:
    """Relative RMSE over the lit hemisphere of the best distant fit of a point lamp (no cells)."""
    lamps = addon_module("lamps")
    n = lamps.fibonacci_sphere(20000)
    n = n[n[:, 2] > 0]
    to_lamp = np.array([0.0, 0.0, k]) - n
    d = np.linalg.norm(to_lamp, axis=1)
    truth = np.clip(np.sum(n * to_lamp, axis=1), 0, None) / d ** 3
    fit = lamps.near_field_gain(k) / k ** 2 * n[:, 2]
    return float(np.linalg.norm(fit - truth) / np.linalg.norm(truth))


def _world_table(folder, quick: bool, print=print) -> None:  # noqa: A002
    hdri, hdri_io = addon_module("hdri"), addon_module("hdri_io")

    widths = (128, 256) if quick else (128, 256, 512, 1024)
    synthetic = write_exr(pathlib.Path(folder) / "synthetic.exr", synthetic_hdri())
    maps = [("synthetic 128x64", synthetic)]
    shared = ROOT.parent / "shared" / "data" / "hdri" / "blender" / "studio.exr"
    if shared.is_file():
        maps.append(("Blender studio.exr 1024x512", str(shared)))
    print("\n| world HDRI | working width | relative RMSE | power error "
          "| conversion (ms, median of 5) |\n| --- | --- | --- | --- | --- |")
    lightvec = addon_module("lightvec")
    # Power is checked in a camera frame pitched 20 degrees down and turned 33 degrees, where pixel
    # rows no longer line up with the light vector's rows.
    a = math.radians(20.0)
    pitch = np.array([[1, 0, 0], [0, math.cos(a), -math.sin(a)], [0, math.sin(a), math.cos(a)]])
    tilted = pitch @ hdri.FRONT_VIEW_WORLD_TO_FRAME
    for label, path in maps:
        results = world_case(path, folder, widths=widths)
        image = np.clip(hdri_io.read_hdri(path), 0, None)
        h, w = image.shape[:2]
        omega = hdri.pixel_row_solid_angles(h, w)[:, None, None]
        truth = (image.astype(np.float64) * omega).sum((0, 1))
        for width, r in results.items():
            med, spread = _time_conversion(lambda: hdri.downsample(image, max_width=width))
            power = lightvec.total_power(hdri.downsample(image, tilted, yaw_degrees=33.0,
                                                         max_width=width))
            power_err = np.abs(power / truth - 1).max()
            print(f"| {label} | {width} | {r['error']:.3f} | {power_err:.2%} | "
                  f"{1e3 * med:.1f} (spread {1e3 * spread:.1f}) |")


if __name__ == "__main__":
    main()
