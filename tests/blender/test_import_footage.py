"""RELIGHT_OT_import_footage: movies and image sequences become strips with the right timing."""

import bpy
import pytest

from conftest import write_movie, write_png_sequence


def strips():
    return bpy.context.scene.sequence_editor.strips


def test_png_sequence_from_one_file(extension, tmp_path):
    files = write_png_sequence(tmp_path / "seq", count=8, start=11)
    bpy.context.scene.frame_current = 5
    assert bpy.ops.relight.import_footage(filepath=str(files[3])) == {'FINISHED'}
    (strip,) = strips()
    assert strip.type == 'IMAGE'
    assert [e.filename for e in strip.elements] == [f.name for f in files]
    assert (strip.frame_final_start, strip.frame_final_duration) == (5, 8)
    assert strip.colorspace_settings.name == "sRGB"
    scene = bpy.context.scene
    assert (scene.frame_start, scene.frame_end) == (5, 12)
    assert bpy.context.scene.sequence_editor.active_strip == strip
    # The strip shows each file at its frame, in order.
    assert strip.strip_elem_from_frame(5 + 6).filename == files[6].name


def test_selected_files_become_one_strip(extension, tmp_path):
    files = write_png_sequence(tmp_path / "seq", count=6)
    picked = [{"name": f.name} for f in files[1:4]]
    bpy.ops.relight.import_footage(directory=str(tmp_path / "seq"), files=picked, frame_start=1)
    (strip,) = strips()
    assert [e.filename for e in strip.elements] == [f.name for f in files[1:4]]


def test_exr_sequence_is_scene_linear(extension, tmp_path):
    import numpy as np
    import OpenEXR

    folder = tmp_path / "exr"
    folder.mkdir()
    for i in range(3):
        rgb = np.full((16, 16, 3), 0.25 * (i + 1), np.float16)
        with OpenEXR.File({"compression": OpenEXR.NO_COMPRESSION},
                          {"RGB": np.ascontiguousarray(rgb)}) as f:
            f.write(str(folder / f"plate.{i + 1:04d}.exr"))
    bpy.ops.relight.import_footage(filepath=str(folder / "plate.0001.exr"), frame_start=1)
    (strip,) = strips()
    assert strip.colorspace_settings.name == "Linear Rec.709"
    assert strip.frame_final_duration == 3


def test_movie_sets_fps_and_range(extension, tmp_path):
    movie = write_movie(tmp_path / "take.mp4", count=8, fps=30)
    assert bpy.context.scene.render.fps != 30
    bpy.ops.relight.import_footage(filepath=str(movie), frame_start=1)
    (strip,) = strips()
    assert strip.type == 'MOVIE' and strip.frame_final_duration == 8
    scene = bpy.context.scene
    assert scene.render.fps / scene.render.fps_base == pytest.approx(30.0)
    assert (scene.frame_start, scene.frame_end) == (1, 8)


def test_second_import_goes_to_a_free_channel(extension, tmp_path):
    files = write_png_sequence(tmp_path / "seq", count=4)
    bpy.ops.relight.import_footage(filepath=str(files[0]), frame_start=1)
    bpy.ops.relight.import_footage(filepath=str(files[0]), frame_start=3)
    channels = sorted(s.channel for s in strips())
    assert channels == [1, 2]


def test_gap_in_sequence_is_refused_with_a_message(extension, tmp_path):
    files = write_png_sequence(tmp_path / "seq", count=6)
    files[2].unlink()
    files[3].unlink()
    with pytest.raises(RuntimeError, match=r"2 missing frame\(s\): 3, 4"):
        bpy.ops.relight.import_footage(filepath=str(files[0]))
    assert bpy.context.scene.sequence_editor is None or len(strips()) == 0


@pytest.mark.parametrize("name,message", [("missing.mp4", "does not exist"),
                                          ("notes.txt", "not footage")])
def test_bad_files_are_refused(extension, tmp_path, name, message):
    path = tmp_path / name
    if name.endswith(".txt"):
        path.write_text("hello")
    with pytest.raises(RuntimeError, match=message):
        bpy.ops.relight.import_footage(filepath=str(path))


def test_corrupt_movie_is_refused(extension, tmp_path):
    path = tmp_path / "broken.mp4"
    path.write_bytes(b"\x00" * 1000)
    with pytest.raises(RuntimeError, match="broken.mp4"):
        bpy.ops.relight.import_footage(filepath=str(path))
    assert len(strips()) == 0
