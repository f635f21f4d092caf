"""RELIGHT_OT_preview_light: show the target light map of the current frame in the panel.

The previews are small images (16x16 texels, each drawn as an 8x8 block so the panel shows crisp
cells): "Relight Target Light" and, after a run, "Relight Source Light"."""

import bpy
import numpy as np

from ..addon import lightvec
from ..addon.errors import RelightError
from . import bridge

TARGET_IMAGE = "Relight Target Light"
SOURCE_IMAGE = "Relight Source Light"
CELL = 8  # pixels per light-vector texel in the preview image


def set_preview(name: str, light: np.ndarray) -> bpy.types.Image:
    """Write a light vector into the preview image ``name`` (created on first use)."""
    srgb = lightvec.to_preview(light)                       # (16, 16, 3), row 0 = zenith
    big = np.repeat(np.repeat(srgb, CELL, axis=0), CELL, axis=1)
    size = big.shape[1], big.shape[0]
    image = bpy.data.images.get(name)
    if image is None or tuple(image.size) != size:
        if image is not None:
            bpy.data.images.remove(image)
        image = bpy.data.images.new(name, size[0], size[1], alpha=True, float_buffer=False)
    image.colorspace_settings.name = "Non-Color"  # already display-encoded by to_preview
    rgba = np.concatenate([big, np.ones(big.shape[:2] + (1,), np.float32)], axis=2)
    image.pixels.foreach_set(np.ascontiguousarray(rgba[::-1]).ravel())  # Blender rows go up
    image.update()
    if image.preview:
        image.preview.reload()
    return image


def preview_pixels(name: str) -> np.ndarray | None:
    """(16, 16, 3) texel colours of a preview image, zenith row first (for tests and tools)."""
    image = bpy.data.images.get(name)
    if image is None:
        return None
    w, h = image.size
    px = np.empty(w * h * 4, np.float32)
    image.pixels.foreach_get(px)
    return px.reshape(h, w, 4)[::-1][CELL // 2::CELL, CELL // 2::CELL, :3]


def target_light(context, frame: int):
    """(light vector, LightSchedule) of the scene's target lighting at ``frame``."""
    from . import scene_light

    args = bridge.light_args(context.scene, context.scene.relight)
    schedule = scene_light.light_schedule(context.scene, [frame], **args)
    return np.asarray(schedule.lights)[0], schedule


class RELIGHT_OT_preview_light(bpy.types.Operator):
    """Show the target lighting of the current frame as a 16x16 light map"""
    bl_idname = "relight.preview_light"
    bl_label = "Preview Light"
    bl_options = {'REGISTER'}

    def execute(self, context):
        frame = context.scene.frame_current
        try:
            light, schedule = target_light(context, frame)
        except RelightError as err:
            self.report({'ERROR'}, str(err))
            return {'CANCELLED'}
        set_preview(TARGET_IMAGE, light)
        for warning in getattr(schedule, "warnings", ()):
            self.report({'WARNING'}, str(warning))
        peak = float(np.max(light))
        self.report({'INFO'}, f"Target light at frame {frame}: brightest texel {peak:.3g}")
        return {'FINISHED'}


classes = (RELIGHT_OT_preview_light,)


register, unregister = bpy.utils.register_classes_factory(classes)
