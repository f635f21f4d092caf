"""Footage as productions have it: any container FFmpeg reads, TIFF and DPX sequences, phone clips
tagged with a display rotation, and variable-frame-rate clips (refused, saying how to convert)."""

import fractions

import av
import numpy as np
import pytest

from addon import frames
from addon.errors import InputError
from tests.clip_fixtures import ramp_frames, write_movie


def _write_images(folder, imgs, ext, codec, fmt):
    folder.mkdir()
    files = []
    for i, img in enumerate(imgs):
        path = folder / f"shot.{1001 + i}.{ext}"
        with av.open(str(path), "w", format="image2") as c:
            s = c.add_stream(codec, rate=1)
            s.width, s.height, s.pix_fmt = img.shape[1], img.shape[0], fmt
            for p in s.encode(av.VideoFrame.from_ndarray(img, format=fmt)):
                c.mux(p)
            for p in s.encode():
                c.mux(p)
        files.append(str(path))
    return files


@pytest.mark.parametrize("ext,codec", [("tif", "tiff"), ("dpx", "dpx")])
def test_tiff_and_dpx_sequences_read_exactly(tmp_path, ext, codec):
    rng = np.random.default_rng(3)
    imgs = [rng.integers(0, 65536, (10, 14, 3)).astype(np.uint16) for _ in range(3)]
    files = _write_images(tmp_path / "seq", imgs, ext, codec, "rgb48le")
    info = frames.probe_clip(str(tmp_path / "seq"))
    assert (info.kind, info.frame_count, info.width, info.height) == ("images", 3, 14, 10)
    assert info.bit_depth == 16 and list(info.files) == files
    got = [d.pixels for d in frames.iter_frames("images", str(tmp_path / "seq"), info.files,
                                                [0, 1, 2])]
    for g, want in zip(got, imgs):
        np.testing.assert_array_equal(g, want)


@pytest.mark.parametrize("name", ["clip.mxf", "clip.mts", "clip.unknownext"])
def test_any_container_ffmpeg_reads_is_a_movie(tmp_path, name):
    src = ramp_frames(4)
    path = tmp_path / name
    if name.endswith(".mxf"):
        with av.open(str(path), "w", format="mxf") as c:
            s = c.add_stream("mpeg2video", rate=25)
            s.width, s.height, s.pix_fmt = 64, 48, "yuv422p"
            s.options = {"qscale": "1"}
            for f in src:
                for p in s.encode(av.VideoFrame.from_ndarray(f, format="rgb24")):
                    c.mux(p)
            for p in s.encode():
                c.mux(p)
    else:
        write_movie(tmp_path / "tmp.mp4", src).rename(path)  # FFmpeg reads by content
    info = frames.probe_clip(str(path))
    assert (info.kind, info.frame_count, info.width, info.height) == ("movie", 4, 64, 48)
    got = list(frames.iter_frames("movie", str(path), (), [0, 3]))
    assert [d.index for d in got] == [0, 3]
    assert float(np.abs(got[1].pixels.astype(float) - src[3]).mean()) < 6  # lossy codecs


def test_a_file_that_is_not_footage_says_what_is(tmp_path):
    path = tmp_path / "notes.txt"
    path.write_text("not a movie")
    with pytest.raises(InputError, match="not footage.*image sequences"):
        frames.probe_clip(str(path))


@pytest.mark.parametrize("rotation,turns", [(90, 1), (-90, 3), (180, 2)])
def test_display_rotation_is_honoured(tmp_path, rotation, turns):
    """A phone clip tagged with a display rotation comes out upright, as Blender shows it:
    the probe's size and every decoded frame are turned like FFmpeg's own autorotation."""
    img = np.zeros((16, 32, 3), np.uint8)
    img[:, :8] = 250  # a bright band on the left of the stored frame
    path = tmp_path / "phone.mp4"
    with av.open(str(path), "w") as c:
        s = c.add_stream("libx264", rate=25)
        s.width, s.height, s.pix_fmt = 32, 16, "yuv444p"
        s.options = {"crf": "0"}
        s.set_display_rotation(rotation)
        for _ in range(3):
            for p in s.encode(av.VideoFrame.from_ndarray(img, format="rgb24")):
                c.mux(p)
        for p in s.encode():
            c.mux(p)
    info = frames.probe_clip(str(path))
    want = np.rot90(img, turns)
    assert (info.height, info.width) == want.shape[:2]
    for planar in (False, True):
        (d,) = frames.iter_frames("movie", str(path), (), [1], planar=planar)
        px = d.pixels.transpose(1, 2, 0) if planar else d.pixels
        assert px.shape == want.shape
        assert np.abs(px.astype(int) - want).max() <= 2


def test_variable_frame_rate_is_refused_saying_how_to_convert(tmp_path):
    path = tmp_path / "vfr.mp4"
    src = ramp_frames(12)
    with av.open(str(path), "w") as c:
        s = c.add_stream("libx264", rate=30)
        s.width, s.height, s.pix_fmt = 64, 48, "yuv420p"
        s.codec_context.time_base = fractions.Fraction(1, 1000)
        t = 0
        for i, f in enumerate(src):
            frame = av.VideoFrame.from_ndarray(f, format="rgb24")
            frame.pts, frame.time_base = t, fractions.Fraction(1, 1000)
            t += 33 if i % 2 else 50  # frames of 33 and 50 ms
            for p in s.encode(frame):
                c.mux(p)
        for p in s.encode():
            c.mux(p)
    with pytest.raises(InputError, match="variable frame rate.*ffmpeg"):
        frames.probe_clip(str(path))
    # a constant-rate movie is not refused
    assert frames.probe_clip(str(write_movie(tmp_path / "cfr.mp4", src))).frame_count == 12
