import os

import numpy as np
import OpenEXR
import pytest

from addon import frames
from addon.errors import InputError, OutputError
from tests.clip_fixtures import (ramp_frames, write_exr_float, write_exr_sequence, write_movie,
                                 write_png, write_png_sequence)


@pytest.fixture(scope="module")
def movie(tmp_path_factory):
    src = ramp_frames(12)
    return write_movie(tmp_path_factory.mktemp("mov") / "clip.mov", src, fps=24, codec="png"), src


def test_probe_movie(movie):
    path, src = movie
    info = frames.probe_clip(str(path))
    assert (info.kind, info.width, info.height, info.frame_count) == ("movie", 64, 48, 12)
    assert info.fps == pytest.approx(24.0) and not info.has_alpha and info.bit_depth == 8


@pytest.mark.parametrize("indices", [[0], [5], [11], [2, 3, 9], [0, 11], list(range(12))])
def test_movie_decode_is_frame_accurate(movie, indices, monkeypatch):
    path, src = movie
    monkeypatch.setattr(frames, "SEEK_GAP", 2)  # force re-seeks between far indices
    got = list(frames.iter_frames("movie", str(path), (), indices))
    assert [d.index for d in got] == sorted(indices)
    for d in got:
        np.testing.assert_array_equal(d.pixels, src[d.index])


def test_h264_mp4_decodes_close_to_source(tmp_path):
    src = ramp_frames(9)
    path = write_movie(tmp_path / "clip.mp4", src)
    got = {d.index: d.pixels for d in frames.iter_frames("movie", str(path), (), [1, 6, 8])}
    for i, px in got.items():
        assert np.abs(px.astype(int) - src[i]).max() <= 3  # yuv444 round trip only


def test_movie_shorter_than_asked(movie):
    path, _ = movie
    with pytest.raises(InputError, match="ended before source frame 15"):
        list(frames.iter_frames("movie", str(path), (), [10, 15]))


def test_not_a_movie(tmp_path):
    fake = tmp_path / "fake.mp4"
    fake.write_bytes(b"not a video at all")
    with pytest.raises(InputError, match="Cannot open"):
        frames.probe_clip(str(fake))
    txt = tmp_path / "notes.txt"
    txt.write_text("hi")
    with pytest.raises(InputError, match="not footage"):
        frames.probe_clip(str(txt))
    with pytest.raises(InputError, match="does not exist"):
        frames.probe_clip(str(tmp_path / "missing.mov"))


def test_sound_only_file_is_refused(tmp_path):
    import av
    path = tmp_path / "sound.mp4"
    with av.open(str(path), "w") as c:
        s = c.add_stream("aac", rate=8000)
        frame = av.AudioFrame.from_ndarray(np.zeros((1, 1024), np.float32), format="fltp",
                                           layout="mono")
        frame.sample_rate = 8000
        for p in s.encode(frame):
            c.mux(p)
        for p in s.encode():
            c.mux(p)
    with pytest.raises(InputError, match="no video stream"):
        frames.probe_clip(str(path))


@pytest.mark.parametrize("kind", ["grey8", "rgb8", "rgba8", "grey16", "rgb16", "rgba16"])
def test_png_variants_decode_exactly(tmp_path, kind):
    base = ramp_frames(1)[0]
    px = {"grey8": base[..., 0], "rgb8": base, "rgba8": np.dstack([base, base[..., :1]]),
          "grey16": base[..., 0].astype(np.uint16) * 257 + 1,
          "rgb16": base.astype(np.uint16) * 257 + 1,
          "rgba16": np.dstack([base, base[..., :1]]).astype(np.uint16) * 257}[kind]
    path = tmp_path / "f_0001.png"
    write_png(path, px)
    info = frames.probe_clip([str(path)])
    assert info.has_alpha == kind.startswith("rgba")
    assert info.bit_depth == (16 if kind.endswith("16") else 8)
    d = next(frames.iter_frames("images", str(tmp_path), [str(path)], [0]))
    want = np.repeat(px[..., None], 3, axis=2) if px.ndim == 2 else px[..., :3]
    assert d.pixels.dtype == want.dtype
    np.testing.assert_array_equal(d.pixels, want)
    assert d.had_alpha == kind.startswith("rgba")


def test_exr_sequence_reads_float_values_exactly(tmp_path):
    rng = np.random.default_rng(0)
    src = [rng.random((5, 7, 3)).astype(np.float32) * 100 for _ in range(3)]
    files = write_exr_sequence(tmp_path, src)
    info = frames.probe_clip(str(tmp_path))
    assert info.files == tuple(files) and (info.width, info.height) == (7, 5)
    for d in frames.iter_frames("images", str(tmp_path), files, [0, 2]):
        np.testing.assert_array_equal(d.pixels, src[d.index])


def test_jpeg_via_pyav(tmp_path):
    import av
    px = ramp_frames(1)[0]
    frame = av.VideoFrame.from_ndarray(px, format="rgb24").reformat(format="yuvj444p")
    cc = av.CodecContext.create("mjpeg", "w")
    cc.width, cc.height, cc.pix_fmt = 64, 48, "yuvj444p"
    cc.options = {"qscale": "2"}
    (tmp_path / "p_01.jpg").write_bytes(b"".join(bytes(p) for p in cc.encode(frame)
                                                 + cc.encode(None)))
    d = next(frames.iter_frames("images", "", [str(tmp_path / "p_01.jpg")], [0]))
    assert d.pixels.shape == (48, 64, 3) and np.abs(d.pixels.astype(int) - px).mean() < 4


def test_missing_frames_are_named(tmp_path):
    files = write_png_sequence(tmp_path, ramp_frames(6), start=1)
    os.remove(files[2])
    os.remove(files[4])
    with pytest.raises(InputError, match=r"2 missing frame\(s\): 3, 5"):
        frames.probe_clip(str(tmp_path))
    with pytest.raises(InputError, match=r"missing 1 file\(s\): frames 3"):
        frames.probe_clip(files[:4])


def test_sequences_with_a_step_are_not_gaps(tmp_path):
    src = ramp_frames(3)
    for i, n in enumerate((10, 20, 30)):
        write_png(tmp_path / f"s_{n:03d}.png", src[i])
    assert frames.probe_clip(str(tmp_path)).frame_count == 3


def test_size_change_mid_sequence_is_refused(tmp_path):
    a, b = ramp_frames(1)[0], ramp_frames(1, height=40)[0]
    write_png(tmp_path / "x_1.png", a)
    write_png(tmp_path / "x_2.png", b)
    files = [str(tmp_path / "x_1.png"), str(tmp_path / "x_2.png")]
    with pytest.raises(InputError, match="one size"):
        list(frames.iter_frames("images", str(tmp_path), files, [0, 1], (64, 48)))


def test_exr_without_rgb_channels(tmp_path):
    path = tmp_path / "depth.exr"
    with OpenEXR.File({"type": OpenEXR.scanlineimage}, {"Z": np.zeros((4, 4), np.float32)}) as f:
        f.write(str(path))
    with pytest.raises(InputError, match="needs R, G, B"):
        frames.probe_clip(str(path))


def test_write_exr_is_half_clamped_and_finite(tmp_path):
    px = np.array([[[1.5, -2.0, 1e6], [np.nan, np.inf, -np.inf]]], np.float32)
    path = tmp_path / "o.exr"
    n = frames.write_exr(path, px)
    assert n == 4
    with OpenEXR.File(str(path)) as f:
        out = f.channels()["RGB"].pixels
        assert out.dtype == np.float16
    np.testing.assert_array_equal(out.astype(np.float32),
                                  [[[1.5, -2.0, 65504.0], [0.0, 65504.0, -65504.0]]])
    assert sorted(os.listdir(tmp_path)) == ["o.exr"]


@pytest.mark.parametrize("compression", frames.COMPRESSIONS)
def test_write_exr_compressions_are_lossless_for_half(tmp_path, compression):
    px = np.random.default_rng(0).random((9, 11, 3)).astype(np.float16)
    frames.write_exr(tmp_path / "c.exr", px, compression)
    np.testing.assert_array_equal(frames.read_exr(tmp_path / "c.exr"), px.astype(np.float32))


def test_failed_write_leaves_no_partial_file(tmp_path, monkeypatch):
    target = tmp_path / "f.exr"

    class Boom(Exception):
        pass

    real = OpenEXR.File

    class Failing:
        def __init__(self, *a, **k):
            self.f = real(*a, **k)

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            return False

        def write(self, path):
            with open(path, "wb") as fh:
                fh.write(b"half")
            raise Boom()

    monkeypatch.setattr(OpenEXR, "File", Failing)
    with pytest.raises(Boom):
        frames.write_exr(target, np.zeros((2, 2, 3), np.float32))
    assert os.listdir(tmp_path) == []


def test_unwritable_folder_is_an_output_error(tmp_path):
    with pytest.raises(OutputError, match="Cannot write"):
        frames.write_exr(tmp_path / "no" / "such" / "dir.exr", np.zeros((2, 2, 3), np.float32))


# ---- channels-first decoding and the direct EXR writer (the pipeline's fast path) ----------

def test_planar_movie_decode_equals_interleaved(movie):
    path, src = movie
    got = list(frames.iter_frames("movie", str(path), (), [0, 5, 6], planar=True))
    assert [d.index for d in got] == [0, 5, 6]
    for d in got:
        assert d.pixels.shape == (3, 48, 64) and d.pixels.dtype == np.uint8
        np.testing.assert_array_equal(d.pixels, src[d.index].transpose(2, 0, 1))


def test_planar_h264_yuv420_equals_interleaved(tmp_path):
    # Chroma-subsampled 4:2:0 (what cameras write): swscale's planar and interleaved RGB agree.
    import av
    src = ramp_frames(2, height=36, width=50)
    path = tmp_path / "c.mp4"
    with av.open(str(path), "w") as c:
        s = c.add_stream("libx264", rate=25)
        s.width, s.height, s.pix_fmt = 50, 36, "yuv420p"
        for f in src:
            for p in s.encode(av.VideoFrame.from_ndarray(f, format="rgb24")):
                c.mux(p)
        for p in s.encode():
            c.mux(p)
    hwc = [d.pixels for d in frames.iter_frames("movie", str(path), (), [0, 1])]
    chw = [d.pixels for d in frames.iter_frames("movie", str(path), (), [0, 1], planar=True)]
    for a, b in zip(hwc, chw):
        np.testing.assert_array_equal(b, a.transpose(2, 0, 1))


@pytest.mark.parametrize("kind", ["grey8", "rgba8", "rgb16"])
def test_planar_png_and_exr_decode_equal_interleaved(tmp_path, kind):
    base = ramp_frames(1)[0]
    px = {"grey8": base[..., 0], "rgba8": np.dstack([base, base[..., :1]]),
          "rgb16": base.astype(np.uint16) * 257 + 1}[kind]
    write_png(tmp_path / "f_0001.png", px)
    files = [str(tmp_path / "f_0001.png")]
    files += write_exr_sequence(tmp_path / "exr", [base.astype(np.float32) / 7])
    for f in files:
        a = next(frames.iter_frames("images", "", [f], [0])).pixels
        b = next(frames.iter_frames("images", "", [f], [0], (64, 48), planar=True)).pixels
        assert b.dtype == a.dtype
        np.testing.assert_array_equal(b, a.transpose(2, 0, 1))


@pytest.mark.parametrize("h,w", [(1, 1), (3, 5), (48, 64), (17, 2)])
def test_direct_exr_writer_reads_back_bit_for_bit(tmp_path, h, w):
    rng = np.random.default_rng(h * w)
    rgb = rng.standard_normal((3, h, w)).astype(np.float16)
    rgb[0, 0, 0], rgb[1, -1, -1] = np.float16(65504), np.float16(-0.0)
    frames.write_exr_planes(tmp_path / "c.exr", rgb)
    with OpenEXR.File(str(tmp_path / "c.exr")) as f:
        header, channels = f.header(), f.channels()
        assert header["compression"] == OpenEXR.NO_COMPRESSION
        assert [tuple(v) for v in header["dataWindow"]] == [(0, 0), (w - 1, h - 1)]
        assert [c.name for c in header["channels"]] == ["B", "G", "R"]
        got = channels["RGB"].pixels
    assert got.dtype == np.float16
    np.testing.assert_array_equal(got.view(np.uint16), rgb.transpose(1, 2, 0).view(np.uint16))
    grey = rng.random((h, w)).astype(np.float16)
    frames.write_exr_planes(tmp_path / "m.exr", grey)
    with OpenEXR.File(str(tmp_path / "m.exr")) as f:
        np.testing.assert_array_equal(f.channels()["Y"].pixels, grey)
    assert sorted(os.listdir(tmp_path)) == ["c.exr", "m.exr"]


@pytest.mark.parametrize("compression", ["rle", "zip", "piz"])
def test_planar_writer_compressed_is_lossless(tmp_path, compression):
    rgb = np.random.default_rng(1).random((3, 9, 11)).astype(np.float16)
    frames.write_exr_planes(tmp_path / "c.exr", rgb, compression)
    np.testing.assert_array_equal(frames.read_exr(tmp_path / "c.exr"),
                                  rgb.transpose(1, 2, 0).astype(np.float32))


def test_planar_writer_refuses_bad_input_and_reports_unwritable(tmp_path):
    with pytest.raises(ValueError, match="float16"):
        frames.write_exr_planes(tmp_path / "a.exr", np.zeros((3, 2, 2), np.float32))
    with pytest.raises(ValueError, match="compression"):
        frames.write_exr_planes(tmp_path / "a.exr", np.zeros((3, 2, 2), np.float16), "lzw")
    with pytest.raises(OutputError, match="Cannot write"):
        frames.write_exr_planes(tmp_path / "no" / "a.exr", np.zeros((3, 2, 2), np.float16))
    assert os.listdir(tmp_path) == []


def test_stale_partial_names_a_dead_local_writer_only(tmp_path):
    import subprocess
    import sys
    done = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"],
                          capture_output=True, text=True, check=True)
    dead = int(done.stdout)
    live = os.getppid()  # the process that started pytest is running
    mine = os.path.basename(frames.partial_path("/x/relit_000001.exr"))
    assert frames.stale_partial(mine) is None  # this process: may be writing it now
    ours_dead = mine.replace(f"_{os.getpid()}_", f"_{dead}_")
    assert frames.stale_partial(ours_dead) == "relit_000001.exr"
    assert frames.stale_partial(mine.replace(f"_{os.getpid()}_", f"_{live}_")) is None
    assert frames.stale_partial(f"relit_000001.exr.otherhost_{dead}_7.partial") is None
    run_file = os.path.basename(frames.partial_path("/x/relight_run.json"))
    assert frames.stale_partial(run_file.replace(f"_{os.getpid()}_", f"_{dead}_")) == \
        "relight_run.json"
    assert frames.stale_partial("relit_000001.exr") is None
    assert frames.stale_partial(f"notes.{dead}.txt") is None


@pytest.mark.parametrize("compression", ["none", "zip"])
def test_rgb_exrs_state_rec709_primaries(tmp_path, compression):
    rgb = np.full((3, 4, 5), 0.5, np.float16)
    frames.write_exr_planes(tmp_path / "p.exr", rgb, compression)
    frames.write_exr(tmp_path / "i.exr", rgb.transpose(1, 2, 0), compression)
    frames.write_exr_planes(tmp_path / "m.exr", rgb[0], compression)
    for name in ("p.exr", "i.exr"):
        with OpenEXR.File(str(tmp_path / name), header_only=True) as f:
            np.testing.assert_allclose(f.header()["chromaticities"],
                                       frames.REC709_CHROMATICITIES, atol=1e-6)
    with OpenEXR.File(str(tmp_path / "m.exr"), header_only=True) as f:
        assert "chromaticities" not in f.header()  # a matte is data, not colour
