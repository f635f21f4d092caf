"""RELIGHT_OT_import_footage: a movie or an image sequence becomes a strip in the sequencer.

Strips are added through the data API (``strips.new_movie/new_image``) because the sequencer's
add operators fail their poll in background mode."""

from __future__ import annotations

import pathlib
import re

import bpy
from bpy.props import BoolProperty, CollectionProperty, IntProperty, StringProperty

from ..addon.errors import InputError, RelightError
from . import bridge


def probe_clip(path_or_files):
    """Size, length and frame rate of footage; InputError for anything unreadable or gappy."""
    from ..addon.frames import probe_clip as probe  # PyAV and OpenEXR load on first use

    return probe(path_or_files)

LINEAR_SUFFIXES = {".exr"}  # EXR holds scene-linear light; the others are display-encoded
_NUMBERED = re.compile(r"^(.*?)(\d+)(\.[^.]+)$")


def sequence_files(path: pathlib.Path) -> list[pathlib.Path]:
    """All frames of the numbered image sequence that ``path`` belongs to, in frame order
    (the file browser hands over one file; the artist means its whole sequence)."""
    m = _NUMBERED.match(path.name)
    if not m:
        return [path]
    prefix, _, suffix = m.groups()
    pattern = re.compile(re.escape(prefix) + r"(\d+)" + re.escape(suffix) + "$")
    numbered = sorted((int(mm.group(1)), p) for p in path.parent.iterdir()
                      if (mm := pattern.match(p.name)) and p.is_file())
    return [p for _, p in numbered]


def footage_files(filepath: str, directory: str, names: list[str]) -> tuple[str, list]:
    """('movie' | 'images', files) for what the file browser (or a script) selected."""
    if names and len(names) > 1:
        files = sorted(pathlib.Path(directory) / n for n in names)
    else:
        files = [pathlib.Path(bpy.path.abspath(filepath or str(pathlib.Path(directory, *names))))]
    for f in files:
        if not f.is_file():
            raise InputError(f"The file {f} does not exist.")
    from ..addon.frames import IMAGE_EXTS

    suffixes = {f.suffix.lower() for f in files}
    if len(files) == 1 and not suffixes <= set(IMAGE_EXTS):
        return "movie", files  # any container FFmpeg reads; the probe says if it cannot
    if not suffixes <= set(IMAGE_EXTS):
        raise InputError(f"{files[0].name} is not an image of a sequence; select one movie, or "
                         f"the frames of one image sequence ({', '.join(IMAGE_EXTS)}).")
    if len(suffixes) > 1:
        raise InputError("The selected images mix file types; select one image sequence.")
    return "images", sequence_files(files[0]) if len(files) == 1 else files


def set_scene_timing(scene, strip, fps: float | None) -> None:
    """Make the scene play the strip: its frame range and, for a movie, the movie's frame rate."""
    if fps and fps > 0:
        rate = round(fps)
        scene.render.fps = rate
        scene.render.fps_base = rate / fps  # 29.97 = 30 / 1.001
    scene.frame_start = strip.frame_final_start
    scene.frame_end = strip.frame_final_end - 1


class RELIGHT_OT_import_footage(bpy.types.Operator):
    """Import a movie or an image sequence as a strip to relight"""
    bl_idname = "relight.import_footage"
    bl_label = "Import Footage"
    bl_options = {'REGISTER', 'UNDO'}

    filepath: StringProperty(subtype='FILE_PATH', options={'SKIP_SAVE'})
    directory: StringProperty(subtype='DIR_PATH', options={'SKIP_SAVE'})
    files: CollectionProperty(type=bpy.types.OperatorFileListElement, options={'SKIP_SAVE'})
    filter_movie: BoolProperty(default=True, options={'HIDDEN'})
    filter_image: BoolProperty(default=True, options={'HIDDEN'})
    filter_folder: BoolProperty(default=True, options={'HIDDEN'})
    channel: IntProperty(name="Channel", default=1, min=1, max=128)
    frame_start: IntProperty(name="Start Frame", default=-1,
                             description="Scene frame of the first footage frame; -1 = current")
    set_scene_range: BoolProperty(name="Fit Scene", default=True,
                                  description="Set the scene's frame range (and, for a movie, "
                                              "its frame rate) to the footage")

    def invoke(self, context, event):
        context.window_manager.fileselect_add(self)
        return {'RUNNING_MODAL'}

    def execute(self, context):
        try:
            strip = self._import(context)
        except RelightError as err:
            self.report({'ERROR'}, str(err))
            return {'CANCELLED'}
        self.report({'INFO'}, f"Imported '{strip.name}': {strip.frame_final_duration} frames at "
                              f"{strip.frame_final_start}-{strip.frame_final_end - 1}, "
                              f"{strip.colorspace_settings.name}")
        return {'FINISHED'}

    def _import(self, context):
        scene = context.scene
        kind, files = footage_files(self.filepath, self.directory, [f.name for f in self.files])
        start = scene.frame_current if self.frame_start < 0 else self.frame_start
        strips = scene.sequence_editor_create().strips
        info = probe_clip([str(f) for f in files] if kind == "images" else str(files[0]))
        if info.frame_count < 1:
            raise InputError(f"{files[0].name} holds no frames.")
        if kind == "movie":
            channel = bridge.free_channel(strips, self.channel, start, start + 1)
            strip = strips.new_movie(files[0].stem, str(files[0]), channel, start)
            fps = info.fps or strip.fps
        else:
            channel = bridge.free_channel(strips, self.channel, start, start + len(files))
            name = re.sub(r"[\W_]*\d+$", "", files[0].stem) or files[0].parent.name
            strip = strips.new_image(name, str(files[0]), channel, start)
            for f in files[1:]:
                strip.elements.append(f.name)
            fps = None
            if files[0].suffix.lower() in LINEAR_SUFFIXES:
                strip.colorspace_settings.name = bridge.LINEAR
        if self.set_scene_range:
            set_scene_timing(scene, strip, fps)
        scene.sequence_editor.active_strip = strip
        return strip


classes = (RELIGHT_OT_import_footage,)


register, unregister = bpy.utils.register_classes_factory(classes)
