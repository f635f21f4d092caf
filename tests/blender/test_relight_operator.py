"""RELIGHT_OT_relight_strip end to end on the bpy module with the toy ONNX model."""

import hashlib

import bpy
import numpy as np
import pytest

from conftest import footage_scene


def relight(toy_models, **kwargs):
    return bpy.ops.relight.relight_strip(models_dir=str(toy_models), **kwargs)


def take(tmp_path, source, number=1):
    """The folder of the strip's take ``number`` (v001, ...)."""
    return tmp_path / "out" / source.name / f"v{number:03d}"


def digest(paths):
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in paths}


def read_exr(path):
    import OpenEXR

    with OpenEXR.File(str(path)) as f:
        return np.asarray(f.channels()["RGB"].pixels, dtype=np.float32)


def test_relit_strip_appears_above_with_same_timing(extension, toy_models, tmp_path):
    source = footage_scene(tmp_path, count=8, frame_start=3)
    before = digest(sorted((tmp_path / "footage").iterdir()))
    assert relight(toy_models) == {'FINISHED'}
    relit = bpy.context.scene.sequence_editor.strips[source.name + " relit v001"]
    assert relit.type == 'IMAGE' and relit.channel == source.channel + 1
    assert (relit.frame_final_start, relit.frame_final_duration) == (3, 8)
    assert relit.colorspace_settings.name == "Linear Rec.709"
    names = [e.filename for e in relit.elements]
    assert names == [f"relit.{n:04d}.exr" for n in range(1, 9)]  # frame_0001.png ...
    assert bpy.path.abspath(relit.directory).rstrip("/") == str(take(tmp_path, source))
    px = read_exr(take(tmp_path, source) / names[0])
    assert px.shape == (64, 64, 3) and np.isfinite(px).all() and px.max() > 0
    # The source footage is never touched.
    assert digest(sorted((tmp_path / "footage").iterdir())) == before


def test_trimmed_strip_relights_only_visible_frames(extension, toy_models, tmp_path):
    source = footage_scene(tmp_path, count=8, frame_start=1)
    source.frame_offset_start = 2
    source.frame_final_duration = 4                        # shows footage frames 2..5
    assert (source.frame_final_start, source.frame_final_end) == (3, 7)
    relight(toy_models)
    out = take(tmp_path, source)
    assert sorted(p.name for p in (out / "relit").glob("*.exr")) == \
        [f"relit_{i:06d}.exr" for i in range(4)]
    # named like the footage frames the strip shows (frame_0003.png ... frame_0006.png)
    assert sorted(p.name for p in out.glob("*.exr")) == [f"relit.{n:04d}.exr" for n in (3, 4, 5, 6)]
    relit = bpy.context.scene.sequence_editor.strips[source.name + " relit v001"]
    assert (relit.frame_final_start, relit.frame_final_duration) == (3, 4)
    assert [e.filename for e in relit.elements] == [f"relit.{n:04d}.exr" for n in (3, 4, 5, 6)]


def test_clip_spec_of_a_trimmed_strip(extension, tmp_path):
    from portrait_relight.ops import bridge

    source = footage_scene(tmp_path, count=8)
    source.frame_offset_start = 2
    source.frame_final_duration = 4
    clip = bridge.clip_spec(source, bpy.context.scene)
    assert (clip.kind, clip.first, clip.count, clip.colorspace) == ("images", 2, 4, "sRGB")
    assert clip.files[clip.first].endswith(source.strip_elem_from_frame(3).filename)


def test_matte_strip_above_the_relit_strip(extension, toy_models, tmp_path):
    source = footage_scene(tmp_path, count=4)
    bpy.context.scene.relight.write_matte = True
    relight(toy_models)
    strips = bpy.context.scene.sequence_editor.strips
    relit, matte = strips[source.name + " relit v001"], strips[source.name + " matte v001"]
    assert matte.channel == relit.channel + 1
    assert matte.colorspace_settings.name == "Non-Color" and matte.mute
    assert (matte.frame_final_start, matte.frame_final_duration) == (1, 4)


def test_rerun_resumes_and_replaces_its_strip(extension, toy_models, tmp_path, capsys):
    source = footage_scene(tmp_path, count=4)
    relight(toy_models)
    frames = sorted((take(tmp_path, source) / "relit").glob("*.exr"))
    first = digest(frames)
    relight(toy_models)
    said = capsys.readouterr().out
    assert "4 resumed" in said
    assert "Relit 4 frames of 'frame' with toy on CPUExecutionProvider in " in said  # the provider
    assert digest(frames) == first
    relit = [s for s in bpy.context.scene.sequence_editor.strips if "relit" in s.name]
    assert len(relit) == 1


def test_changed_lighting_makes_a_new_take_beside_the_first(extension, toy_models, tmp_path):
    source = footage_scene(tmp_path, count=4)
    bpy.context.scene.relight.exposure_mode = 'PHYSICAL'  # the exposure shows in the frames
    relight(toy_models)
    first = digest(sorted(take(tmp_path, source).glob("relit.*.exr")))
    bpy.context.scene.relight.exposure = 1.0               # different lighting: a new take
    assert relight(toy_models) == {'FINISHED'}
    second = digest(sorted(take(tmp_path, source, 2).glob("relit.*.exr")))
    assert len(second) == 4 and set(second.values()).isdisjoint(first.values())
    assert digest(sorted(take(tmp_path, source).glob("relit.*.exr"))) == first  # kept
    strips = bpy.context.scene.sequence_editor.strips
    one, two = strips[source.name + " relit v001"], strips[source.name + " relit v002"]
    assert two.channel > one.channel                       # the new take on top, both kept
    assert (two.frame_final_start, two.frame_final_duration) == (1, 4)
    bpy.context.scene.relight.exposure = 0.0               # the first lighting again: take 1
    relight(toy_models)
    assert not take(tmp_path, source, 3).exists()
    assert len([s for s in strips if "relit" in s.name]) == 2


def test_replace_latest_take_relights_into_it(extension, toy_models, tmp_path):
    source = footage_scene(tmp_path, count=4)
    bpy.context.scene.relight.exposure_mode = 'PHYSICAL'
    relight(toy_models)
    bpy.context.scene.relight.exposure = 1.0
    relight(toy_models)
    second = digest(sorted(take(tmp_path, source, 2).glob("relit.*.exr")))
    s = bpy.context.scene.relight
    s.exposure, s.overwrite = 2.0, True
    assert relight(toy_models) == {'FINISHED'}
    assert not take(tmp_path, source, 3).exists()
    replaced = digest(sorted(take(tmp_path, source, 2).glob("relit.*.exr")))
    assert replaced.keys() == second.keys() and set(replaced.values()).isdisjoint(second.values())
    assert len([s for s in bpy.context.scene.sequence_editor.strips if "relit" in s.name]) == 2


def test_frame_range_relights_a_chunk_without_adding_a_strip(extension, toy_models, tmp_path):
    source = footage_scene(tmp_path, count=8, frame_start=1)
    s = bpy.context.scene.relight
    s.use_frame_range, s.frame_start, s.frame_end = True, 3, 5
    relight(toy_models)
    out = take(tmp_path, source)
    assert sorted(p.name for p in (out / "relit").glob("*.exr")) == \
        [f"relit_{i:06d}.exr" for i in (2, 3, 4)]
    assert sorted(p.name for p in out.glob("*.exr")) == [f"relit.{n:04d}.exr" for n in (3, 4, 5)]
    assert not [s for s in bpy.context.scene.sequence_editor.strips if "relit" in s.name]
    s.frame_start, s.frame_end = 20, 30
    with pytest.raises(RuntimeError, match="do not overlap"):
        relight(toy_models)


def test_source_light_preview_after_a_run(extension, toy_models, tmp_path):
    from portrait_relight.ops import preview_light

    footage_scene(tmp_path, count=2)
    relight(toy_models)
    px = preview_light.preview_pixels(preview_light.SOURCE_IMAGE)
    assert px.shape == (16, 16, 3) and np.isfinite(px).all() and px.max() > 0


def test_target_light_preview_shows_the_sun(extension, tmp_path):
    from portrait_relight.ops import preview_light

    footage_scene(tmp_path, count=2)
    assert bpy.ops.relight.preview_light() == {'FINISHED'}
    px = preview_light.preview_pixels(preview_light.TARGET_IMAGE)
    brightest = np.unravel_index(np.argmax(px.sum(axis=2)), px.shape[:2])
    assert px.max() == pytest.approx(1.0, abs=0.01)        # the sun texel, scaled to white
    assert brightest[0] < 8                                 # the sun is above the horizon


@pytest.mark.parametrize("kind", ["TEXT", "COLOR", "META"])
def test_strips_that_are_not_footage_are_refused(extension, toy_models, tmp_path, kind):
    footage_scene(tmp_path, count=2)
    strips = bpy.context.scene.sequence_editor.strips
    if kind == "META":
        other = strips.new_meta("other", 5, 1)
    else:
        other = strips.new_effect("other", kind, 5, 1, length=10)
    bpy.context.scene.sequence_editor.active_strip = other
    with pytest.raises(RuntimeError, match="not footage"):
        relight(toy_models)
    assert not (tmp_path / "out").exists()


def test_no_active_strip(extension, toy_models, tmp_path):
    footage_scene(tmp_path, count=2)
    bpy.context.scene.sequence_editor.active_strip = None
    with pytest.raises(RuntimeError, match="No active strip"):
        relight(toy_models)


def test_missing_model_says_so(extension, tmp_path):
    footage_scene(tmp_path, count=2)
    with pytest.raises(RuntimeError, match="No relighting model is installed"):
        bpy.ops.relight.relight_strip(models_dir=str(tmp_path / "no_models"))


def test_corrupt_model_is_refused(extension, toy_models, tmp_path):
    import shutil

    models = tmp_path / "models"
    shutil.copytree(toy_models, models)
    onnx = next(models.glob("*.onnx"))
    onnx.write_bytes(onnx.read_bytes()[:-10] + b"0123456789")
    footage_scene(tmp_path, count=2)
    with pytest.raises(RuntimeError, match="corrupt"):
        bpy.ops.relight.relight_strip(models_dir=str(models))


def test_missing_footage_frame_is_refused(extension, toy_models, tmp_path):
    footage_scene(tmp_path, count=4)
    (tmp_path / "footage" / "frame_0003.png").unlink()
    with pytest.raises(RuntimeError, match="missing"):
        relight(toy_models)


def test_unwritable_output_folder_is_refused(extension, toy_models, tmp_path):
    footage_scene(tmp_path, count=2)
    blocker = tmp_path / "a_file"
    blocker.write_text("not a folder")
    bpy.context.scene.relight.output_dir = str(blocker / "sub") + "/"
    with pytest.raises(RuntimeError, match="Cannot create the output folder"):
        relight(toy_models)


def test_relative_output_folder_needs_a_saved_file(extension, toy_models, tmp_path):
    footage_scene(tmp_path, count=2)
    bpy.context.scene.relight.output_dir = "//relit/"
    with pytest.raises(RuntimeError, match="not saved yet"):
        relight(toy_models)


def test_ui_worker_cancels_half_way_and_resumes(extension, toy_models, tmp_path):
    """The modal operator's worker (timers never fire in background mode, so drive it here)."""
    from portrait_relight.addon.errors import Cancelled
    from portrait_relight.ops import bridge, relight_strip

    source = footage_scene(tmp_path, count=6)
    job = bridge.gather_job(bpy.context, source, models_override=str(toy_models))
    lights, _ = relight_strip.schedule_lights(bpy.context, job)
    state = relight_strip._WorkerState(job=job, warnings=[], started=0.0)
    answers = iter([False, False, False])              # "Esc" after three progress checks
    state.cancel.is_set = lambda: next(answers, True)
    state.run(lights)
    assert isinstance(state.error, Cancelled)
    out = take(tmp_path, source) / "relit"
    done = sorted(out.glob("relit_*.exr"))
    assert 0 < len(done) < 6
    state = relight_strip._WorkerState(job=job, warnings=[], started=0.0)
    state.run(lights)
    assert state.error is None and state.result.resumed == len(done)
    assert state.done == 6


def test_the_panel_defaults_to_the_pipelines_background_and_the_run_records_it(
        extension, toy_models, tmp_path):
    import json

    from portrait_relight.addon import pipeline

    source = footage_scene(tmp_path, count=2)
    assert bpy.context.scene.relight.background.lower() == pipeline.DEFAULT_BACKGROUND
    relight(toy_models)
    run = json.loads((take(tmp_path, source) / "relight_run.json").read_text())
    assert run["identity"]["settings"]["background"] == pipeline.DEFAULT_BACKGROUND


def test_one_run_at_a_time_and_greyed_with_the_reason(extension, toy_models, tmp_path):
    footage_scene(tmp_path, count=2)
    relight_strip = extension.ops.relight_strip
    assert bpy.ops.relight.relight_strip.poll()
    relight_strip.running = "other shot"  # an interactive run is going on
    try:
        assert not bpy.ops.relight.relight_strip.poll()
        with pytest.raises(RuntimeError, match="under way"):
            relight(toy_models)
    finally:
        relight_strip.running = None
    assert relight(toy_models) == {'FINISHED'}
    assert 'UNDO' in relight_strip.RELIGHT_OT_relight_strip.bl_options
