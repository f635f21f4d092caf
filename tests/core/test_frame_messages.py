"""Messages about bad frames name the file and the scene frame, and say what to do: a sequence
whose size changes, a damaged image, a movie that ends early, a frame outside the sequence."""

import pathlib

import pytest

from addon import frames, lightvec, pipeline
from addon.errors import InputError
from tests.clip_fixtures import ramp_frames, write_movie, write_png, write_png_sequence

UNIFORM = lightvec.uniform(1.0)[None]


def run(toy, files, out, first=1, scene_start=101):
    files = tuple(str(f) for f in files)
    clip = pipeline.ClipSpec("images", str(pathlib.Path(files[0]).parent), files, first,
                             len(files) - first, "sRGB", 0.0, scene_start=scene_start)
    opts = pipeline.RelightOptions(toy, working_size=16, threads=1, background="network")
    return pipeline.relight_clip(clip, UNIFORM, out, opts)


def test_a_frame_of_another_size_names_its_file_and_scene_frame(toy, tmp_path):
    files = write_png_sequence(tmp_path / "seq", ramp_frames(5))
    write_png(files[3], ramp_frames(1, height=40)[0])  # source index 3: clip frame 2
    with pytest.raises(InputError) as err:
        run(toy, files, tmp_path / "out")
    text = str(err.value)
    assert text.startswith(f"Scene frame 103 ({files[3]}) is 64x40, but the clip is 64x48")
    assert "Re-export the sequence at one size" in text
    with pytest.raises(InputError, match=r"Clip frame 2 \(0-based\) \("):  # no scene known
        run(toy, files, tmp_path / "out", scene_start=None)


def test_a_damaged_frame_names_its_file_and_scene_frame_and_what_to_do(toy, tmp_path):
    files = write_png_sequence(tmp_path / "seq", ramp_frames(5))
    pathlib.Path(files[4]).write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(200))
    with pytest.raises(InputError) as err:
        run(toy, files, tmp_path / "out", first=0, scene_start=1)
    text = str(err.value)
    assert text.startswith(f"Scene frame 5: Cannot read the image {files[4]}")
    assert "replace it with an intact copy (re-render or re-export the frame)" in text


def test_movie_and_sequence_limits_name_the_frame_and_what_to_do(tmp_path):
    movie = write_movie(tmp_path / "m.mov", ramp_frames(4), codec="png")
    name = pipeline.source_frame_name(pipeline.ClipSpec("movie", str(movie), (), 2, 9, "sRGB",
                                                        25.0, scene_start=1001))
    with pytest.raises(InputError, match=rf"The movie {movie} ended before scene frame 1005; "
                                         "the strip is longer than the file. Trim the strip"):
        list(frames.iter_frames("movie", str(movie), (), [6], name=name))
    with pytest.raises(InputError, match="scene frame 1008 is not one of them. Trim the strip"):
        list(frames.iter_frames("images", "", ["a.png"], [9], name=name))
