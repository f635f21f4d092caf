"""The per-clip pipeline end to end with the toy model on tiny generated clips."""

import hashlib
import json
import os
import pathlib
import subprocess
import sys

import numpy as np
import pytest

from addon import colour, frames, lightvec, pipeline
from addon.errors import Cancelled, InputError, LightingError, ModelError, OutputError
from tests.clip_fixtures import (ramp_frames, write_exr_float, write_exr_sequence, write_movie,
                                 write_png, write_png_sequence)

ROOT = pathlib.Path(__file__).resolve().parents[2]
N = 6


@pytest.fixture(scope="module")
def src(tmp_path_factory):
    return ramp_frames(N)


@pytest.fixture(scope="module")
def movie(tmp_path_factory, src):
    return str(write_movie(tmp_path_factory.mktemp("mov") / "clip.mov", src, codec="png"))


def movie_clip(path, first=0, count=N, space="sRGB"):
    return pipeline.ClipSpec("movie", path, (), first, count, space, 25.0)


def image_clip(files, first=0, count=None, space="sRGB"):
    files = tuple(files)
    return pipeline.ClipSpec("images", str(pathlib.Path(files[0]).parent), files, first,
                             len(files) - first if count is None else count, space, 0.0)


def opts(model, **kw):
    kw.setdefault("working_size", 32)
    kw.setdefault("threads", 1)
    kw.setdefault("background", "network")  # the network's own output: what these tests check
    kw.setdefault("exposure_mode", "physical")  # ... at the network's own level
    return pipeline.RelightOptions(model, **kw)


UNIFORM = lightvec.uniform(1.0)[None]


def digest(paths):
    return [hashlib.sha256(pathlib.Path(p).read_bytes()).hexdigest() for p in paths]


def test_movie_end_to_end_is_the_toys_physics(toy, movie, src, tmp_path):
    # Toy: relit = image * E(target)/E(source), its source uniform radiance s (1 in the network's
    # normalised units): uniform radiance 2 doubles the linear input over s.
    res = pipeline.relight_clip(movie_clip(movie), 2 * UNIFORM, tmp_path, opts(toy))
    assert res.written == N and res.resumed == 0 and len(res.relit_files) == N
    s = res.exposure_scale
    for i, f in enumerate(res.relit_files):
        out = frames.read_exr(f)
        want = 2 * colour.to_linear(src[i], colour.lookup("sRGB")) / s
        assert out.shape == (48, 64, 3)
        np.testing.assert_allclose(out, want, rtol=4e-3, atol=1e-4)
        assert np.load(pipeline.source_path(tmp_path, i)).shape == lightvec.SHAPE
    run = json.loads((tmp_path / pipeline.RUN_FILE).read_text())
    assert run["exposure_scale"] == res.exposure_scale


def test_trim_relights_the_visible_frames_only(toy, movie, src, tmp_path):
    res = pipeline.relight_clip(movie_clip(movie, first=2, count=3), UNIFORM, tmp_path,
                                opts(toy, detail_transfer=False, working_size=64))
    assert [os.path.basename(f) for f in res.relit_files] == [
        "relit_000000.exr", "relit_000001.exr", "relit_000002.exr"]
    for k, f in enumerate(res.relit_files):
        want = colour.to_linear(src[2 + k], colour.lookup("sRGB")) / res.exposure_scale
        np.testing.assert_allclose(frames.read_exr(f), want, rtol=4e-3, atol=1e-4)


def test_per_frame_lights_and_zero_light(toy, tmp_path):
    px = np.random.default_rng(5).random((12, 20, 3)).astype(np.float32) + 0.05
    files = write_exr_sequence(tmp_path / "in", [px] * 3)  # the same footage three times
    lights = np.stack([lightvec.uniform(v) for v in (1.0, 3.0, 0.0)])
    res = pipeline.relight_clip(image_clip(files, space="Linear Rec.709"), lights,
                                tmp_path / "out", opts(toy, working_size=8))
    a, b, c = (frames.read_exr(f) for f in res.relit_files)
    np.testing.assert_allclose(a, px / res.exposure_scale, rtol=2e-3)
    np.testing.assert_allclose(b, 3 * a, rtol=2e-3)
    assert not c.any()  # all-zero light: a black frame, the network not run
    assert np.all(np.load(pipeline.source_path(tmp_path / "out", 2)) == 0)
    assert np.load(pipeline.source_path(tmp_path / "out", 0)).any()
    # A light that goes black on some frames is a choice (a fade), said once, naming the frame.
    (warning,) = [w for w in res.warnings if "black" in w]
    assert "1 of the frames" in warning and "clip frame 2" in warning
    named = pipeline.ClipSpec(**{**image_clip(files).__dict__, "scene_start": 101,
                                 "colorspace": "Linear Rec.709"})
    res = pipeline.relight_clip(named, lights, tmp_path / "out", opts(toy, working_size=8))
    assert any("scene frame 103" in w for w in res.warnings)


def test_keep_exposure_is_one_gain_for_the_clip(toy, tmp_path):
    """The default exposure mode: the subject keeps the footage's luminance summed over the clip,
    by one gain for every frame, so an animated light still brightens and dims the clip."""
    px = np.random.default_rng(6).random((12, 20, 3)).astype(np.float32) + 0.05
    files = write_exr_sequence(tmp_path / "in", [px] * 4)
    lights = np.stack([lightvec.uniform(v) for v in (1.0, 2.0, 3.0, 6.0)])
    clip = image_clip(files, space="Linear Rec.709")
    keep = pipeline.relight_clip(clip, lights, tmp_path / "keep",
                                 opts(toy, working_size=8, exposure_mode="keep"))
    out = [frames.read_exr(f) for f in keep.relit_files]
    np.testing.assert_allclose(sum(o.sum() for o in out), 4 * px.sum(), rtol=5e-3)
    for o, v in zip(out, (1.0, 2.0, 3.0, 6.0)):
        np.testing.assert_allclose(o, v * out[0], rtol=5e-3)  # still three times at frame 3
    physical = pipeline.relight_clip(clip, lights, tmp_path / "physical",
                                     opts(toy, working_size=8, exposure_mode="physical"))
    gain = json.loads((tmp_path / "keep" / pipeline.RUN_FILE).read_text())["exposure_gain"]
    # 4 frames of mean light 3, the toy's source radiance s
    np.testing.assert_allclose(gain, keep.exposure_scale / 3, rtol=5e-3)
    for k, f in zip(out, physical.relit_files):
        np.testing.assert_allclose(k, gain * frames.read_exr(f), rtol=5e-3, atol=1e-6)
    # the mode is part of the run: the other mode into the same folder is another run
    with pytest.raises(OutputError, match="exposure_mode|settings"):
        pipeline.relight_clip(clip, lights, tmp_path / "keep",
                              opts(toy, working_size=8, exposure_mode="physical"))
    with pytest.raises(InputError, match="exposure mode"):
        pipeline.relight_clip(clip, lights, tmp_path / "other",
                              opts(toy, working_size=8, exposure_mode="auto"))


def test_twice_the_light_twice_the_output(toy, movie, tmp_path):
    one = pipeline.relight_clip(movie_clip(movie, count=2), UNIFORM, tmp_path / "a", opts(toy))
    light = lightvec.splat_direction([0.2, 0.3, 1.0], [2.0, 1.0, 0.5])
    two = pipeline.relight_clip(movie_clip(movie, count=2), 2 * light[None], tmp_path / "b",
                                opts(toy))
    ref = pipeline.relight_clip(movie_clip(movie, count=2), light[None], tmp_path / "c",
                                opts(toy))
    for f2, fr in zip(two.relit_files, ref.relit_files):
        np.testing.assert_allclose(frames.read_exr(f2), 2 * frames.read_exr(fr), rtol=2e-3,
                                   atol=1e-6)
    assert one.exposure_scale == two.exposure_scale


def test_png_and_exr_sequences(toy, src, tmp_path):
    files = write_png_sequence(tmp_path / "png", src[:3])
    res = pipeline.relight_clip(image_clip(files), UNIFORM, tmp_path / "o1", opts(toy,
                                write_matte=True))
    assert res.written == 3 and len(res.matte_files) == 3
    m = frames.read_exr(res.matte_files[0])
    assert m.shape == (48, 64, 3) and m.min() >= 0 and m.max() <= 1
    lin = [colour.to_linear(f, colour.lookup("sRGB")) for f in src[:3]]
    exr = write_exr_sequence(tmp_path / "exr", lin)
    res2 = pipeline.relight_clip(image_clip(exr, space="Linear Rec.709"), UNIFORM,
                                 tmp_path / "o2", opts(toy))
    for a, b in zip(res.relit_files, res2.relit_files):
        np.testing.assert_allclose(frames.read_exr(a), frames.read_exr(b), rtol=2e-3, atol=1e-5)


def test_cancel_then_resume_equals_one_run(toy, movie, tmp_path):
    full = pipeline.relight_clip(movie_clip(movie), UNIFORM, tmp_path / "one", opts(toy))
    calls = []

    def cancel_after_two():
        calls.append(1)
        return len(calls) > 2

    with pytest.raises(Cancelled, match="run again to resume"):
        pipeline.relight_clip(movie_clip(movie), UNIFORM, tmp_path / "two", opts(toy),
                              should_cancel=cancel_after_two)
    done = sorted(os.listdir(tmp_path / "two" / "relit"))
    assert 0 < len(done) < N and not any(n.endswith(".partial") for n in done)
    progress = []
    res = pipeline.relight_clip(movie_clip(movie), UNIFORM, tmp_path / "two", opts(toy),
                                on_progress=lambda d, t, m: progress.append((d, t)))
    assert res.resumed == len(done) and res.written == N - len(done)
    assert progress[-1] == (N, N)
    assert digest(res.relit_files) == digest(full.relit_files)


def test_farm_chunks_equal_one_run(toy, movie, tmp_path):
    full = pipeline.relight_clip(movie_clip(movie), UNIFORM, tmp_path / "one", opts(toy))
    a = pipeline.relight_clip(movie_clip(movie), UNIFORM, tmp_path / "chunks", opts(toy),
                              frames=range(0, 2))
    b = pipeline.relight_clip(movie_clip(movie), UNIFORM, tmp_path / "chunks", opts(toy),
                              frames=range(2, N))
    assert a.written == 2 and b.written == N - 2 and b.resumed == 0
    assert a.exposure_scale == b.exposure_scale == full.exposure_scale
    assert digest(a.relit_files + b.relit_files) == digest(full.relit_files)


CHUNK_SCRIPT = """
import sys, numpy as np
from addon import lightvec, pipeline
clip = pipeline.ClipSpec('movie', sys.argv[1], (), 0, {n}, 'sRGB', 25.0)
opts = pipeline.RelightOptions(sys.argv[2], working_size=32, threads=1, background='network',
                               exposure_mode='physical')
pipeline.relight_clip(clip, lightvec.uniform(1.0)[None], sys.argv[3], opts,
                      frames=range(int(sys.argv[4]), int(sys.argv[5])))
"""


def test_two_concurrent_chunk_processes_equal_one_run(toy, movie, tmp_path):
    full = pipeline.relight_clip(movie_clip(movie), UNIFORM, tmp_path / "one", opts(toy))
    code = CHUNK_SCRIPT.format(n=N)
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    procs = [subprocess.Popen([sys.executable, "-c", code, movie, toy, str(tmp_path / "farm"),
                               str(a), str(b)], env=env, cwd=ROOT)
             for a, b in ((0, 3), (3, N))]
    assert [p.wait(timeout=120) for p in procs] == [0, 0]
    farm = [pipeline.relit_path(tmp_path / "farm", i) for i in range(N)]
    assert digest(farm) == digest(full.relit_files)


def test_rerun_onto_another_run_is_refused_unless_overwrite(toy, movie, tmp_path):
    pipeline.relight_clip(movie_clip(movie, count=2), UNIFORM, tmp_path, opts(toy))
    with pytest.raises(OutputError, match=r"differs in: the lighting\)"):
        pipeline.relight_clip(movie_clip(movie, count=2), 2 * UNIFORM, tmp_path, opts(toy))
    with pytest.raises(OutputError, match=r"differs in: the settings\)"):
        pipeline.relight_clip(movie_clip(movie, count=2), UNIFORM, tmp_path,
                              opts(toy, working_size=16))
    before = frames.read_exr(pipeline.relit_path(tmp_path, 0))
    res = pipeline.relight_clip(movie_clip(movie, count=2), 2 * UNIFORM, tmp_path,
                                opts(toy, overwrite=True))
    assert res.written == 2
    np.testing.assert_allclose(frames.read_exr(res.relit_files[0]), 2 * before, rtol=2e-3)


def test_footage_reached_through_a_symlink_or_another_mount_is_the_same_run(toy, src,
                                                                             tmp_path):
    """Farm machines reach the footage through symlinks or their own mount points: the same
    files are the same run (resumed, chunks agree), wherever they are reached from; changed
    files are another run."""
    import shutil

    real = write_png_sequence(tmp_path / "plates", src)
    os.symlink(tmp_path / "plates", tmp_path / "link")
    linked = [str(tmp_path / "link" / pathlib.Path(f).name) for f in real]
    shutil.copytree(tmp_path / "plates", tmp_path / "mount" / "plates")  # copy2: same times
    mounted = [str(tmp_path / "mount" / "plates" / pathlib.Path(f).name) for f in real]
    one = pipeline.relight_clip(image_clip(real), UNIFORM, tmp_path / "one", opts(toy))
    out = tmp_path / "farm"
    pipeline.relight_clip(image_clip(linked), UNIFORM, out, opts(toy), frames=range(0, 2))
    res = pipeline.relight_clip(image_clip(real), UNIFORM, out, opts(toy), frames=range(2, N))
    assert res.written == N - 2
    res = pipeline.relight_clip(image_clip(mounted), UNIFORM, out, opts(toy))
    assert (res.written, res.resumed) == (0, N)
    farm = [pipeline.relit_path(out, i) for i in range(N)]
    assert digest(farm) == digest(one.relit_files)
    run = json.loads((out / pipeline.RUN_FILE).read_text())
    assert run["source_path"] == os.path.realpath(tmp_path / "link")
    os.utime(real[3], ns=(1, 1))  # the footage changed: another run
    with pytest.raises(OutputError, match="differs in: the footage"):
        pipeline.relight_clip(image_clip(linked), UNIFORM, out, opts(toy))


def test_a_run_begun_by_another_version_of_the_extension_is_not_finished_by_this_one(
        toy, movie, tmp_path, monkeypatch):
    """The run's identity holds the engine's source (pipeline.engine_sha256): after an update
    of the extension, which may render frames differently, a half-finished take is left as it
    was and the run goes to a new take; a plain output folder is refused with the reason.
    The same version resumes as before."""
    clip = movie_clip(movie, count=4)
    first = pipeline.relight_clip(clip, UNIFORM, tmp_path / "shot", opts(toy, takes=True),
                                  frames=range(0, 2))
    assert pathlib.Path(first.out_dir).name == "v001"
    plain = pipeline.relight_clip(clip, UNIFORM, tmp_path / "plain", opts(toy), frames=range(0, 2))
    real = pipeline.engine_sha256()
    assert len(real) == 64 and real != "0" * 64
    monkeypatch.setattr(pipeline, "engine_sha256", lambda: "0" * 64)
    later = pipeline.relight_clip(clip, UNIFORM, tmp_path / "shot", opts(toy, takes=True))
    assert pathlib.Path(later.out_dir).name == "v002" and (later.written, later.resumed) == (4, 0)
    assert sorted(os.listdir(pathlib.Path(first.out_dir, "relit"))) == [
        pathlib.Path(f).name for f in first.relit_files]  # the old take as it was left
    with pytest.raises(OutputError, match="the version of the extension that made it"):
        pipeline.relight_clip(clip, UNIFORM, plain.out_dir, opts(toy))
    again = pipeline.relight_clip(clip, UNIFORM, tmp_path / "shot", opts(toy, takes=True))
    assert pathlib.Path(again.out_dir).name == "v002" and (again.written, again.resumed) == (0, 4)


def test_unknown_frames_in_output_folder_are_refused(toy, movie, tmp_path):
    (tmp_path / "relit").mkdir()
    frames.write_exr(tmp_path / "relit" / "relit_000000.exr", np.ones((2, 2, 3), np.float32))
    with pytest.raises(OutputError, match="unknown run"):
        pipeline.relight_clip(movie_clip(movie, count=2), UNIFORM, tmp_path, opts(toy))


def test_bad_exr_pixels_give_finite_output_and_a_warning(toy, tmp_path):
    px = np.random.default_rng(0).random((20, 30, 3)).astype(np.float32)
    px[0, 0] = np.nan
    px[1, 1] = np.inf
    px[2, 2] = -np.inf
    px[3, 3] = -5.0
    files = [str(tmp_path / "in" / "bad_0001.exr")]
    (tmp_path / "in").mkdir()
    write_exr_float(files[0], px)
    logs = []
    res = pipeline.relight_clip(image_clip(files, space="Linear Rec.709"), UNIFORM,
                                tmp_path / "out", opts(toy, working_size=8), log=logs.append)
    out = frames.read_exr(res.relit_files[0])
    assert np.all(np.isfinite(out)) and out.min() >= 0
    assert any("NaN, infinite or negative" in w for w in res.warnings)
    assert any("NaN, infinite or negative" in m for m in logs)


@pytest.mark.parametrize("h,w", [(1, 1), (9, 17), (2, 1)])
def test_tiny_and_odd_sizes(toy, tmp_path, h, w):
    px = np.random.default_rng(h * w).random((h, w, 3)).astype(np.float32) + 0.1
    (tmp_path / "in").mkdir()
    files = write_exr_sequence(tmp_path / "in", [px, px])
    res = pipeline.relight_clip(image_clip(files, space="Linear Rec.709"), 2 * UNIFORM,
                                tmp_path / "out", opts(toy, working_size=8))
    out = frames.read_exr(res.relit_files[1])
    assert out.shape == (h, w, 3) and np.all(np.isfinite(out))
    np.testing.assert_allclose(out, 2 * px / res.exposure_scale, rtol=5e-3)


def test_half_overflow_is_clamped_and_reported(toy, tmp_path):
    px = np.full((8, 8, 3), 100.0, np.float32)
    px[:4] = 0.5  # keep the clip's exposure on the dim half
    files = write_exr_sequence(tmp_path / "in", [px])
    res = pipeline.relight_clip(image_clip(files, space="Linear Rec.709"), 1e7 * UNIFORM,
                                tmp_path / "out", opts(toy, working_size=8))
    out = frames.read_exr(res.relit_files[0])
    assert out.max() == 65504.0 and np.all(np.isfinite(out))
    assert any("half-float range" in w for w in res.warnings)


def test_missing_frames_and_missing_files(toy, src, tmp_path):
    files = write_png_sequence(tmp_path / "seq", src)
    os.remove(files[3])
    with pytest.raises(InputError, match="frames 4"):
        pipeline.relight_clip(image_clip(files), UNIFORM, tmp_path / "out", opts(toy))
    # trimmed to skip the hole: fine
    res = pipeline.relight_clip(image_clip(files, first=0, count=3), UNIFORM, tmp_path / "o2",
                                opts(toy))
    assert res.written == 3


def test_missing_and_corrupt_model_write_nothing(toy, movie, tmp_path):
    with pytest.raises(ModelError, match="does not exist"):
        pipeline.relight_clip(movie_clip(movie), UNIFORM, tmp_path / "a",
                              opts(str(tmp_path / "nope.onnx")))
    bad = tmp_path / "m" / "bad.onnx"
    bad.parent.mkdir()
    bad.write_bytes(pathlib.Path(toy).read_bytes()[:-10])
    pathlib.Path(bad.with_suffix(".json")).write_text(
        pathlib.Path(toy).with_suffix(".json").read_text())
    with pytest.raises(ModelError, match="corrupt"):
        pipeline.relight_clip(movie_clip(movie), UNIFORM, tmp_path / "b", opts(str(bad)))
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()


def test_source_files_are_never_modified(toy, src, tmp_path):
    files = write_png_sequence(tmp_path / "seq", src[:3])
    stamp = [(os.stat(f).st_mtime_ns, digest([f])[0]) for f in files]
    pipeline.relight_clip(image_clip(files), UNIFORM, tmp_path / "out", opts(toy,
                          write_matte=True))
    assert [(os.stat(f).st_mtime_ns, digest([f])[0]) for f in files] == stamp
    # an output folder whose relit/ is the source folder is refused before anything is written
    seq2 = write_png_sequence(tmp_path / "o" / "relit", src[:2], prefix="relit_", start=0)
    with pytest.raises(OutputError, match="source footage"):
        pipeline.relight_clip(image_clip(seq2), UNIFORM, tmp_path / "o", opts(toy))
    assert sorted(os.listdir(tmp_path / "o" / "relit")) == ["relit_0000.png", "relit_0001.png"]


def test_bad_lights_clip_and_colour_space_are_clear_errors(toy, movie, tmp_path):
    with pytest.raises(LightingError, match="shape"):
        pipeline.relight_clip(movie_clip(movie), np.ones((2, 16, 16, 3)), tmp_path, opts(toy))
    nan = lightvec.uniform(1.0)
    nan[3, 3, 1] = np.nan
    with pytest.raises(LightingError, match="NaN"):
        pipeline.relight_clip(movie_clip(movie), nan[None], tmp_path, opts(toy))
    with pytest.raises(InputError, match="shorter than the strip"):
        pipeline.relight_clip(movie_clip(movie, first=4, count=5), UNIFORM, tmp_path, opts(toy))
    with pytest.raises(InputError, match="not in Blender's colour configuration"):
        pipeline.relight_clip(movie_clip(movie, space="no such space"), UNIFORM, tmp_path,
                              opts(toy))
    with pytest.raises(InputError, match="outside the clip"):
        pipeline.relight_clip(movie_clip(movie), UNIFORM, tmp_path, opts(toy),
                              frames=range(4, 9))


def test_alpha_and_grey_footage_warn(toy, src, tmp_path):
    rgba = np.dstack([src[0], np.full((48, 64, 1), 128, np.uint8)])
    (tmp_path / "a").mkdir()
    write_png(tmp_path / "a" / "x_1.png", rgba)
    res = pipeline.relight_clip(image_clip([str(tmp_path / "a" / "x_1.png")]), UNIFORM,
                                tmp_path / "o1", opts(toy))
    assert any("alpha" in w for w in res.warnings)
    (tmp_path / "g").mkdir()
    write_png(tmp_path / "g" / "y_1.png", src[0][..., 1])
    res = pipeline.relight_clip(image_clip([str(tmp_path / "g" / "y_1.png")]), UNIFORM,
                                tmp_path / "o2", opts(toy))
    out = frames.read_exr(res.relit_files[0])
    assert any("greyscale" in w for w in res.warnings)
    np.testing.assert_array_equal(out[..., 0], out[..., 1])


@pytest.mark.parametrize("background", ["keep", "relit"])
def test_kept_backgrounds_composite_the_relit_subject_over_the_source(toy, movie, src, tmp_path,
                                                                      background):
    """keep: relit * matte + source * (1 - matte); relit: the source times the wall's change of
    light (wall_gain with the run's own source-light estimate)."""
    light = 3 * UNIFORM  # the toy triples the linear input: subject and background differ
    plain = pipeline.relight_clip(movie_clip(movie, count=2), light, tmp_path / "a",
                                  opts(toy, write_matte=True))
    kept = pipeline.relight_clip(movie_clip(movie, count=2), light, tmp_path / "b",
                                 opts(toy, write_matte=True, background=background))
    for i in range(2):
        relit, out = frames.read_exr(plain.relit_files[i]), frames.read_exr(kept.relit_files[i])
        m = frames.read_exr(plain.matte_files[i])[..., :1]
        gain = np.ones(3)
        if background == "relit":
            source_light = np.load(pipeline.source_path(str(tmp_path / "b"), i))
            gain = pipeline.wall_gain(light[0], source_light)
            assert np.all(np.abs(gain - 1) > 0.05)  # the light changed: not the same as "keep"
        source = colour.to_linear(src[i], colour.lookup("sRGB"))
        want = relit * m + source * gain * (1 - m)
        np.testing.assert_allclose(out, want, rtol=4e-3, atol=2e-4)
        assert 0.05 < float(m.mean()) < 0.95  # both subject and background are in the frame
        assert np.all(np.isfinite(out))
    # a different setting is a different run: it cannot silently resume the plain one
    with pytest.raises(OutputError):
        pipeline.relight_clip(movie_clip(movie, count=2), light, tmp_path / "a",
                              opts(toy, write_matte=True, background=background))


def test_an_unknown_background_says_which_exist(toy, movie, tmp_path):
    with pytest.raises(InputError, match="relit"):
        pipeline.relight_clip(movie_clip(movie, count=2), UNIFORM, tmp_path / "c",
                              opts(toy, background="kept"))


def test_wall_gain_is_the_change_of_light_on_a_wall_facing_the_camera():
    np.testing.assert_allclose(pipeline.wall_gain(lightvec.uniform(2.0), lightvec.uniform(1.0)),
                               [2, 2, 2], rtol=1e-6)
    warm = lightvec.uniform(1.0) * np.array([1.0, 0.5, 0.25], np.float32)
    np.testing.assert_allclose(pipeline.wall_gain(warm, lightvec.uniform(1.0)),
                               [1.0, 0.5, 0.25], rtol=1e-6)
    front = lightvec.splat_direction((0.0, 0.0, 1.0), (1.0, 1.0, 1.0))
    back = lightvec.splat_direction((0.0, 0.0, -1.0), (1.0, 1.0, 1.0))
    assert np.all(pipeline.wall_gain(back, front) < 0.05)  # a wall facing the camera goes dark
    # a source with no light on the wall: the ratio of total power, finite
    np.testing.assert_allclose(pipeline.wall_gain(2 * front, back), [2, 2, 2], rtol=1e-5)
    assert not pipeline.wall_gain(front, lightvec.zeros()).any()
    one_dark = lightvec.uniform(1.0) * np.array([1.0, 1.0, 0.0], np.float32)
    g = pipeline.wall_gain(lightvec.uniform(1.0), one_dark)
    np.testing.assert_allclose(g, [1, 1, 150], rtol=1e-5)  # floored at 1% of the mean (2/3)
    nan = lightvec.uniform(1.0).copy()
    nan[0, 0, 0] = np.nan
    assert np.all(np.isfinite(pipeline.wall_gain(front, nan)))


@pytest.mark.parametrize("background", ["keep", "relit"])
def test_keep_background_with_a_dark_light_and_bad_pixels_stays_finite(toy, tmp_path, background):
    px = np.random.default_rng(6).random((12, 20, 3)).astype(np.float32) + 0.05
    bad = px.copy()
    bad[2, 3] = np.nan
    bad[4, 5] = np.inf
    bad[6, 7] = -1.0
    files = write_exr_sequence(tmp_path / "in", [px, bad])
    lights = np.stack([lightvec.uniform(0.0), lightvec.uniform(1e4)])
    res = pipeline.relight_clip(image_clip(files, space="Linear Rec.709"), lights,
                                tmp_path / "out", opts(toy, working_size=8, background=background))
    dark, huge = (frames.read_exr(f) for f in res.relit_files)
    assert not dark.any()  # no light, no matte: the whole frame is black, not the source
    assert np.all(np.isfinite(huge)) and np.abs(huge).max() <= 65504.0
