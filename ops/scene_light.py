"""The bridge from a Blender scene (world, lamps, camera, subject) to light vectors.

Blender data is gathered here into plain values (addon.lamps.Lamp, HDRI pixels, matrices); all the
conversion itself happens in addon/ (lamps.py, hdri.py) without Blender. Static lighting is
converted once; if anything that shapes the light is animated, one light vector per frame.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field

import bpy
import numpy as np

from ..addon import colour, hdri, hdri_io, lamps, lightvec
from ..addon.errors import InputError, LightingError

SOURCES = ("WORLD", "LAMPS", "WORLD_AND_LAMPS", "HDRI_FILE", "BUILTIN")
HDRI_WIDTH = 1024  # HDRI working width: bench/light_conversion.py and README give the trade-off
REL_THRESHOLD = 1e-3  # lamps below this share of the total power are skipped
MISSING_SUBJECT_DISTANCE = 1.0  # metres in front of the camera when nothing marks the subject
MAX_EXPOSURE = 128  # stops; 2^128 takes any light past float32's range


@dataclass
class LightSchedule:
    lights: np.ndarray  # (F, 16, 16, 3) float32, one per frame; F == 1 when static
    static: bool
    skipped: list[str] = field(default_factory=list)  # names of lamps skipped as negligible
    warnings: list[str] = field(default_factory=list)
    black_message: str = ""  # why the lighting would be black, and what to set


def builtin_hdris() -> dict[str, str]:
    """Blender's bundled studio HDRIs: preset name -> file path."""
    folder = bpy.utils.system_resource('DATAFILES', path="studiolights/world")
    if not folder or not os.path.isdir(folder):
        return {}
    return {os.path.splitext(f)[0]: os.path.join(folder, f) for f in sorted(os.listdir(folder))
            if f.lower().endswith(hdri_io.EXTENSIONS)}


def light_schedule(scene, frames, *, source: str, hdri_path: str | None = None,
                   hdri_builtin: str | None = None, rotation_deg=0.0, exposure=0.0,
                   subject=None, camera=None, subject_radius: float = 0.15) -> LightSchedule:
    """Light vectors for ``frames`` of ``scene`` (see the module docstring).

    ``rotation_deg`` turns the lighting about world Z (world and lamps alike) the way a Mapping
    node's Z rotation turns a world texture; ``exposure`` scales
    it by 2^exposure. Each may be a number or a callable frame -> number; a number is re-read
    per frame from ``scene.relight`` when that property is animated. ``camera`` defaults to the
    scene camera; without any camera the front view is the light frame, and ``rotation_deg`` must
    be given (not None). Raises InputError / LightingError with a message the user can act on.
    The schedule's ``black_message`` says why the lighting is black and what to set, for a
    caller that finds it too dark to relight with (pipeline.black_lights).
    """
    if source not in SOURCES:
        raise InputError(f"Unknown light source {source!r}; use one of {', '.join(SOURCES)}.")
    frames = list(frames)
    if not frames:
        raise InputError("No frames to light: the frame range is empty.")
    camera = camera or scene.camera
    if camera is None and rotation_deg is None:
        raise InputError("The scene has no camera, so the lighting has no frame of reference. "
                         "Add a camera (or pick one), or set a lighting rotation.")
    if camera is not None and camera.type != 'CAMERA':
        raise InputError(
            f"'{camera.name}' is not a camera; pick a camera object for the light frame.")
    for layer in scene.view_layers[:1]:  # object matrices are stale until the depsgraph updates
        layer.update()
    ctx = _Context(scene, source, subject, camera, float(subject_radius), rotation_deg, exposure)
    ctx.load_hdri(hdri_path, hdri_builtin)
    static = not _lighting_is_animated(ctx)
    original = scene.frame_current
    lights = []
    try:
        for f in frames[:1] if static else frames:
            if not static or f != scene.frame_current:
                scene.frame_set(f)
            lights.append(ctx.light_at(f))
    finally:
        if scene.frame_current != original:
            scene.frame_set(original)
    return LightSchedule(np.stack(lights).astype(np.float32), static, sorted(ctx.skipped),
                         ctx.warnings, ctx.black_message())


class _Context:
    """Everything one schedule reads, gathered once; ``light_at`` converts the current frame."""

    def __init__(self, scene, source, subject, camera, subject_radius, rotation, exposure):
        if not (math.isfinite(subject_radius) and subject_radius > 0):
            raise InputError(
                "The subject radius must be a positive length (about 0.15 m for a head).")
        self.scene, self.source, self.subject, self.camera = scene, source, subject, camera
        self.radius, self.rotation, self.exposure = subject_radius, rotation, exposure
        self.skipped: set[str] = set()
        self.warnings: list[str] = []
        self.image = None  # equirect pixels of a file or builtin HDRI, read once
        self.world_cache: dict = {}

    def warn(self, message: str) -> None:
        if message not in self.warnings:
            self.warnings.append(message)

    def load_hdri(self, path, builtin) -> None:
        if self.source == 'HDRI_FILE':
            if not path:
                raise InputError("The lighting is set to an HDRI file, but no file is chosen.")
            self.image = hdri_io.read_hdri(bpy.path.abspath(path))
        elif self.source == 'BUILTIN':
            presets = builtin_hdris()
            if builtin not in presets:
                raise InputError(f"Unknown studio HDRI {builtin!r}; choose one of "
                                 f"{', '.join(presets) or '(none found in this Blender)'}.")
            self.image = hdri_io.read_hdri(presets[builtin])

    # -- per frame ---------------------------------------------------------------------------
    def light_at(self, frame: int) -> np.ndarray:
        # The rotation turns the lighting like a Mapping node's Z rotation on the world texture
        # (same number, same look), which turns the picture by minus that angle about world Z.
        rotation, exposure = self.setting("rotation", frame), self.setting("exposure", frame)
        if not math.isfinite(rotation):
            raise LightingError(f"The lighting rotation is {rotation} on frame {frame}; set it "
                                "to a number of degrees.")
        if not math.isfinite(exposure) or exposure > MAX_EXPOSURE:
            raise LightingError(f"The lighting exposure is {exposure:g} on frame {frame}; set it "
                                f"to a number of stops up to {MAX_EXPOSURE} (0 keeps the light "
                                "as it is).")
        to_frame = self.world_to_frame() @ hdri.yaw_world(-rotation)
        out = lightvec.zeros()
        if self.source in ('HDRI_FILE', 'BUILTIN'):
            out = self.downsample(self.image, to_frame, 1.0, "The HDRI")
        if self.source in ('WORLD', 'WORLD_AND_LAMPS'):
            out = out + lightvec.validate(self.world_light(to_frame), self.world_name())
        if self.source in ('LAMPS', 'WORLD_AND_LAMPS'):
            out = out + lightvec.validate(self.lamps_light(to_frame), "light of the lamps")
        scaled = out * np.float32(2.0 ** exposure)
        if not np.all(np.isfinite(scaled)):
            raise LightingError(f"At exposure {exposure:g} the lighting is too bright to "
                                "represent (radiance overflows); lower the exposure.")
        return lightvec.validate(scaled, "scene lighting")

    def world_name(self) -> str:
        world = self.scene.world
        return f"light of the world '{world.name}'" if world is not None else "world light"

    def black_message(self) -> str:
        """Why the lighting is black on every frame, and what to set."""
        why = []
        if self.source in ('HDRI_FILE', 'BUILTIN'):
            why.append("the HDRI is black")
        if self.source in ('WORLD', 'WORLD_AND_LAMPS'):
            world = self.scene.world
            why.append("the scene has no world" if world is None
                       else f"the world '{world.name}' gives no light")
        if self.source in ('LAMPS', 'WORLD_AND_LAMPS'):
            objs = [o for o in self.scene.objects if o.type == 'LIGHT']
            lit = [o for o in objs if not o.hide_render and float(o.data.energy) > 0]
            why.append("no lamps" if not objs else "no lamps with energy" if not lit
                       else f"the lamps ({', '.join(o.name for o in lit[:4])}) do not reach "
                            "the subject")
        text = "The lighting is black: " + " and ".join(why) + "."
        exposure = self.exposure if not callable(self.exposure) else None
        if isinstance(exposure, (int, float)) and exposure < -20:
            text += (f" The exposure {exposure:g} darkens any light 2^{-exposure:g} times: set "
                     "it near 0.")
        return text + (" Add a lamp with energy or a world HDRI, or pick a studio HDRI in the "
                       "Relight panel.")

    def setting(self, name: str, frame: int) -> float:
        value = self.rotation if name == "rotation" else self.exposure
        if callable(value):
            return float(value(frame))
        value = float(value or 0.0)
        relight = getattr(self.scene, "relight", None)
        if relight is not None and f"relight.{name}" in _animated_paths(self.scene):
            value = getattr(relight, name)
            value = math.degrees(value) if name == "rotation" else value
        return value

    def world_to_frame(self) -> np.ndarray:
        if self.camera is None:
            return hdri.FRONT_VIEW_WORLD_TO_FRAME
        return hdri.world_to_frame_from_camera(_rotation(self.camera.matrix_world))

    def subject_centre(self) -> np.ndarray:
        if self.subject is not None:
            return np.array(self.subject.matrix_world.translation, dtype=np.float64)
        if self.camera is None:
            raise InputError("Lamps need a subject position: pick the subject object, or add a "
                             "camera so its focus point can be used.")
        cam = self.camera
        dof = cam.data.dof
        if dof.focus_object is not None:
            return np.array(dof.focus_object.matrix_world.translation, dtype=np.float64)
        forward = -_rotation(cam.matrix_world)[:, 2]
        origin = np.array(cam.matrix_world.translation, dtype=np.float64)
        if dof.use_dof:
            return origin + forward * float(dof.focus_distance)
        self.warn("No subject is set and the camera has no depth of field: lamps are measured from "
                  f"{MISSING_SUBJECT_DISTANCE:g} m in front of the camera. Pick the subject "
                  "object.")
        return origin + forward * MISSING_SUBJECT_DISTANCE

    def lamps_light(self, to_frame: np.ndarray) -> np.ndarray:
        centre = self.subject_centre()
        # A lamp hidden from diffuse rays does not light skin in Cycles either.
        objs = [o for o in self.scene.objects if o.type == 'LIGHT' and not o.hide_render
                and getattr(o, "visible_diffuse", True)]
        gathered = [(o, self.lamp_from_object(o, centre, to_frame)) for o in objs]
        gathered = [(o, lamp) for o, lamp in gathered if lamp is not None]
        light, skipped = lamps.lamps_to_light([lamp for _, lamp in gathered], self.radius,
                                              REL_THRESHOLD)
        self.skipped.update(gathered[i][0].name for i in skipped)
        return light

    def lamp_from_object(self, obj, centre, to_frame) -> lamps.Lamp | None:
        data = obj.data
        rot = _rotation(obj.matrix_world, normalise=False)
        scale = np.linalg.norm(rot, axis=0)
        rot = rot / np.where(scale > 0, scale, 1.0)
        pos = to_frame @ (np.array(obj.matrix_world.translation) - centre)
        emit = to_frame @ -rot[:, 2]
        # diffuse_factor is EEVEE's; Cycles ignores it (the referee test shows it).
        colour = np.array(data.color[:], dtype=np.float64)
        if getattr(data, "use_temperature", False):
            colour = colour * np.array(data.temperature_color[:], dtype=np.float64)
        self.warn_unsupported(obj, scale)
        numbers = {"energy": data.energy, "exposure": getattr(data, "exposure", 0.0),
                   "colour": tuple(colour), "location": tuple(obj.matrix_world.translation),
                   "size": (getattr(data, "shadow_soft_size", 0.0), getattr(data, "size", 0.0),
                            getattr(data, "size_y", 0.0), getattr(data, "angle", 0.0))}
        for what, value in numbers.items():
            if not np.all(np.isfinite(np.asarray(value, dtype=np.float64))):
                raise LightingError(f"Lamp '{obj.name}': its {what} is not a finite number "
                                    f"({value}); set it to a number.")
        kw = dict(kind=data.type, position=tuple(pos), direction=tuple(emit), color=tuple(colour),
                  energy=float(data.energy), exposure=float(getattr(data, "exposure", 0.0)),
                  normalize=bool(getattr(data, "normalize", True)))
        if data.type in ('POINT', 'SPOT'):
            kw["radius"] = float(data.shadow_soft_size)
        if data.type == 'SPOT':
            kw.update(spot_size=float(data.spot_size), spot_blend=float(data.spot_blend))
        elif data.type == 'SUN':
            kw["sun_angle"] = float(data.angle)
        elif data.type == 'AREA':
            kw.update(area_shape=data.shape, size=float(data.size) * scale[0],
                      size_y=float(data.size_y) * scale[1], axis_x=tuple(to_frame @ rot[:, 0]))
        try:
            return lamps.Lamp(**kw)
        except TypeError as err:  # a Blender property of an unexpected type: a bug, say which lamp
            raise LightingError(f"Cannot read lamp '{obj.name}': {err}") from err

    def warn_unsupported(self, obj, scale) -> None:
        data = obj.data
        if data.type == 'AREA' and float(getattr(data, "spread", math.pi)) < math.pi - 1e-4:
            self.warn(f"Lamp '{obj.name}': area spread below 180 degrees is treated as 180.")
        if data.type == 'SPOT' and (getattr(data, "use_square", False)
                                    or abs(scale[0] - scale[1]) > 1e-4 * max(scale[:2])):
            self.warn(f"Lamp '{obj.name}': square or scaled spot cones are treated as round.")
        if getattr(data, "use_nodes", False) and data.node_tree is not None \
                and len(data.node_tree.nodes) > 2:
            self.warn(f"Lamp '{obj.name}': its shader nodes are ignored; colour and power are "
                      "used.")

    def world_light(self, to_frame: np.ndarray) -> np.ndarray:
        world = self.scene.world
        if world is None:
            self.warn("The scene has no world: the world contributes no light.")
            return lightvec.zeros()
        # Before Blender 5.0 a world could switch its nodes off (5.0 deprecates use_nodes).
        uses_nodes = bpy.app.version >= (5, 0, 0) or world.use_nodes
        tree = world.node_tree if uses_nodes else None
        if tree is None:
            return lightvec.uniform(np.array(world.color[:3], dtype=np.float32))
        background = _world_background(tree)
        if background is None:
            self.warn(f"World '{world.name}' has no Background shader: it contributes no light.")
            return lightvec.zeros()
        strength = _input_value(background.inputs["Strength"], "world strength")
        colour_in = background.inputs["Color"]
        if not colour_in.is_linked:
            return lightvec.uniform(np.array(colour_in.default_value[:3], np.float32) * strength)
        node = colour_in.links[0].from_node
        if node.bl_idname != 'ShaderNodeTexEnvironment':
            raise LightingError(
                f"World '{world.name}' lights the scene through a '{node.name}' node, which the "
                "add-on cannot read. Use an Environment Texture (an HDRI) or a plain colour, or "
                "choose 'HDRI file' as the light source.")
        env_to_world = self.environment_mapping(node)
        pixels = self.environment_pixels(node)
        return self.downsample(pixels, to_frame @ env_to_world, strength,
                               f"The world image '{node.image.name}'")

    def downsample(self, pixels, to_frame, strength: float, what: str) -> np.ndarray:
        """hdri.downsample; NaN, infinite or negative pixels become black, with a warning where
        they are more than the file's rounding (hdri.damaged_texels: Blender's own studio HDRIs
        hold a few tiny negative values)."""
        bad = hdri.damaged_texels(pixels)
        if bad:
            self.warn(f"{what} has {bad} NaN, infinite or negative values; they are treated as "
                      "black.")
        return hdri.downsample(pixels, to_frame, strength=strength, max_width=HDRI_WIDTH,
                               repair=True)

    def environment_mapping(self, env) -> np.ndarray:
        """Rotation taking the texture's directions to world directions (Mapping node, if any)."""
        if env.projection != 'EQUIRECTANGULAR':
            raise LightingError(f"The world's Environment Texture uses {env.projection} "
                                "projection; only equirectangular HDRIs are supported.")
        vec = env.inputs["Vector"]
        if not vec.is_linked:
            return np.eye(3)
        mapping = vec.links[0].from_node
        if mapping.bl_idname != 'ShaderNodeMapping':
            self.warn("The world's Environment Texture has a vector input other than a Mapping "
                      "node; it is ignored.")
            return np.eye(3)
        rot = np.array(_euler_matrix(_input_value(mapping.inputs["Rotation"], "mapping rotation",
                                                  size=3)))
        # POINT and VECTOR rotate the lookup direction, so the picture turns the other way.
        return rot if mapping.vector_type == 'TEXTURE' else rot.T

    def environment_pixels(self, env) -> np.ndarray:
        image = env.image
        if image is None:
            raise LightingError("The world's Environment Texture has no image; open an HDRI in it.")
        key = (image.name, image.filepath)
        if key not in self.world_cache:
            path = bpy.path.abspath(image.filepath, library=image.library) if image.filepath else ""
            if path and os.path.isfile(path) and path.lower().endswith(hdri_io.EXTENSIONS) \
                    and image.packed_file is None:
                self.world_cache[key] = hdri_io.read_hdri(path)
            else:
                self.world_cache[key] = _image_pixels(image)
        return self.world_cache[key]


def _image_pixels(image) -> np.ndarray:
    """Linear RGB of a Blender image (packed or generated), top row first."""
    w, h = image.size
    if w == 0 or h == 0:
        raise LightingError(f"The world image '{image.name}' cannot be loaded; check its file.")
    buf = np.empty(w * h * image.channels, dtype=np.float32)
    image.pixels.foreach_get(buf)
    px = buf.reshape(h, w, image.channels)[::-1, :, :3]
    if not image.is_float and image.colorspace_settings.name.lower().startswith("srgb"):
        px = colour.srgb_to_linear(px)
    return np.ascontiguousarray(px, dtype=np.float32)


def _world_background(tree):
    out = next((n for n in tree.nodes if n.bl_idname == 'ShaderNodeOutputWorld'
                and n.is_active_output), None)
    out = out or next((n for n in tree.nodes if n.bl_idname == 'ShaderNodeOutputWorld'), None)
    if out is None or not out.inputs["Surface"].is_linked:
        return None
    node = out.inputs["Surface"].links[0].from_node
    return node if node.bl_idname == 'ShaderNodeBackground' else None


def _input_value(socket, what: str, size: int = 1):
    if socket.is_linked:
        raise LightingError(f"The {what} is driven by other nodes, which the add-on cannot read; "
                            "set it to a value.")
    return float(socket.default_value) if size == 1 else tuple(socket.default_value[:size])


def _euler_matrix(xyz) -> np.ndarray:
    """Blender's XYZ Euler rotation as a matrix (X applied first)."""
    (cx, cy, cz), (sx, sy, sz) = np.cos(xyz), np.sin(xyz)
    rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return rz @ ry @ rx


def _rotation(matrix_world, normalise: bool = True) -> np.ndarray:
    """3x3 rotation part of a world matrix (columns: local axes in world), scale removed."""
    m = np.array([matrix_world[i][:3] for i in range(3)], dtype=np.float64)
    if normalise:
        m = m / np.linalg.norm(m, axis=0)
    return m


def _animated(id_data) -> bool:
    ad = getattr(id_data, "animation_data", None) if id_data is not None else None
    return ad is not None and (ad.action is not None or len(ad.drivers) > 0
                               or len(ad.nla_tracks) > 0)


def _animated_paths(id_data) -> set[str]:
    ad = getattr(id_data, "animation_data", None)
    paths = set()
    if ad is None:
        return paths
    paths.update(d.data_path for d in ad.drivers)
    if ad.action is not None:
        from bpy_extras import anim_utils

        bag = anim_utils.action_get_channelbag_for_slot(ad.action, ad.action_slot)
        paths.update(fc.data_path for fc in (bag.fcurves if bag else ()))
    return paths


def _object_animated(obj, seen=None) -> bool:
    """An object moves or changes if it, its data, a parent or a constraint target is animated."""
    if obj is None:
        return False
    seen = seen if seen is not None else set()
    if obj.name in seen:
        return False
    seen.add(obj.name)
    if _animated(obj) or _animated(obj.data) or _object_animated(obj.parent, seen):
        return True
    return any(_object_animated(getattr(c, "target", None), seen) for c in obj.constraints)


def _lighting_is_animated(ctx: _Context) -> bool:
    if callable(ctx.rotation) or callable(ctx.exposure) or _animated(ctx.scene):
        return True
    if _object_animated(ctx.camera) or _object_animated(ctx.subject):
        return True
    if ctx.camera is not None and _object_animated(ctx.camera.data.dof.focus_object):
        return True
    if ctx.source in ('WORLD', 'WORLD_AND_LAMPS') and ctx.scene.world is not None:
        world = ctx.scene.world
        if _animated(world) or _animated(world.node_tree):
            return True
    if ctx.source in ('LAMPS', 'WORLD_AND_LAMPS'):
        return any(_object_animated(o) for o in ctx.scene.objects if o.type == 'LIGHT')
    return False
