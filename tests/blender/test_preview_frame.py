"""RELIGHT_OT_preview_frame: the current frame relit exactly as the whole run relights it."""

import hashlib

import bpy
import pytest

from conftest import footage_scene


def digest(path):
    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_preview_is_the_runs_own_frame_and_leaves_the_run_alone(extension, toy_models, tmp_path):
    source = footage_scene(tmp_path, count=6, frame_start=3)
    bpy.context.scene.frame_current = 5  # the strip's third frame
    assert bpy.ops.relight.preview_frame(models_dir=str(toy_models)) == {'FINISHED'}
    strips = bpy.context.scene.sequence_editor.strips
    shown = strips[source.name + " preview"]
    assert (shown.frame_final_start, shown.frame_final_duration) == (5, 1)
    assert shown.channel > source.channel and shown.colorspace_settings.name == "Linear Rec.709"
    preview = tmp_path / "out" / source.name / "preview" / "relit" / "relit_000002.exr"
    assert preview.is_file() and not (tmp_path / "out" / source.name / "v001").exists()
    import OpenEXR

    with OpenEXR.File(str(preview), header_only=True) as f:  # lossless PIZ unless chosen
        assert f.header()["compression"] == OpenEXR.PIZ_COMPRESSION
    # The whole run gives that very frame, bit for bit.
    bpy.context.scene.sequence_editor.active_strip = source
    assert bpy.ops.relight.relight_strip(models_dir=str(toy_models)) == {'FINISHED'}
    assert digest(tmp_path / "out" / source.name / "v001" / "relit.0003.exr") == digest(preview)
    # Another lighting: the preview is replaced, never an Overwrite question; one preview strip.
    bpy.context.scene.relight.exposure = 1.0
    bpy.context.scene.relight.exposure_mode = 'PHYSICAL'
    bpy.context.scene.frame_current = 3
    bpy.context.scene.sequence_editor.active_strip = source
    assert bpy.ops.relight.preview_frame(models_dir=str(toy_models)) == {'FINISHED'}
    assert [s.name for s in strips].count(source.name + " preview") == 1
    assert strips[source.name + " preview"].frame_final_start == 3


def test_preview_outside_the_strip_says_where_to_go(extension, toy_models, tmp_path):
    footage_scene(tmp_path, count=4, frame_start=1)
    bpy.context.scene.frame_current = 40
    with pytest.raises(RuntimeError, match="outside the strip"):
        bpy.ops.relight.preview_frame(models_dir=str(toy_models))


def test_preview_is_greyed_without_a_footage_strip(extension):
    bpy.ops.wm.read_homefile(use_empty=True)
    assert not bpy.ops.relight.preview_frame.poll()


def test_preview_waits_for_a_running_relight(extension, toy_models, tmp_path):
    footage_scene(tmp_path, count=2)
    assert bpy.ops.relight.preview_frame.poll()
    extension.ops.relight_strip.running = "other shot"
    try:
        assert not bpy.ops.relight.preview_frame.poll()
    finally:
        extension.ops.relight_strip.running = None
