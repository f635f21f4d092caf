"""RELIGHT_OT_preview_frame: relight the current frame only, to judge a lighting before the clip.

The frame is relit exactly as the whole run would relight it (the same framing, exposure gain and
model, computed over the whole strip and kept for the next preview of the same lighting), into the
strip's preview folder beside its takes, and shown as a one-frame image strip above the
source at the current frame. Relighting the strip afterwards is not affected."""

from __future__ import annotations

import dataclasses
import pathlib

import bpy

from ..addon.errors import RelightError
from . import bridge, relight_strip

PREVIEW_SUFFIX = " preview"
PREVIEW_FOLDER = "preview"  # in the strip's folder, beside its takes (v001, ...)


def preview_job(context, strip, models_override: str = "") -> bridge.Job:
    """The strip's job narrowed to the current frame, into the preview folder (replaced when the
    lighting or settings change, so a preview never asks for Overwrite)."""
    job = bridge.gather_job(context, strip, models_override=models_override)
    frame = context.scene.frame_current
    if not job.frame_start <= frame < job.frame_start + job.frame_count:
        raise RelightError(f"The current frame {frame} is outside the strip '{strip.name}' "
                           f"({job.frame_start}-{job.frame_start + job.frame_count - 1}); move "
                           "the playhead onto it.")
    options = dataclasses.replace(job.options, overwrite=True, write_matte=False, takes=False)
    return dataclasses.replace(job, scene_frames=(frame,), clip_frames=(frame - job.frame_start,),
                               out_dir=job.out_dir / PREVIEW_FOLDER,
                               options=options)


class RELIGHT_OT_preview_frame(bpy.types.Operator):
    """Relight only the current frame of the active footage strip and show it above the strip"""
    bl_idname = "relight.preview_frame"
    bl_label = "Preview Frame"
    bl_options = {'REGISTER'}

    models_dir: bpy.props.StringProperty(name="Models Folder", options={'SKIP_SAVE', 'HIDDEN'},
                                         description="Overrides the preferences' models folder")

    @classmethod
    def poll(cls, context):
        return relight_strip.poll_run(cls, context, need_strip=True)

    def execute(self, context):
        from ..addon import pipeline

        strip = context.scene.sequence_editor.active_strip
        try:
            job = preview_job(context, strip, self.models_dir)
            lights, warnings = relight_strip.schedule_lights(context, job)
            relight_strip.run_pipeline(job, lights)
        except RelightError as err:
            self.report({'ERROR'}, str(err))
            return {'CANCELLED'}
        for warning in warnings:
            self.report({'WARNING'}, str(warning))
        path = pathlib.Path(pipeline.relit_path(job.out_dir, job.clip_frames[0]))
        shown = relight_strip.add_image_strip(context.scene, job.strip_name + PREVIEW_SUFFIX,
                                              [path], job.channel + 1, job.scene_frames[0],
                                              bridge.LINEAR)
        self.report({'INFO'}, f"Previewed frame {job.scene_frames[0]} of '{job.strip_name}' in "
                              f"strip '{shown.name}'")
        return {'FINISHED'}


classes = (RELIGHT_OT_preview_frame,)


register, unregister = bpy.utils.register_classes_factory(classes)
