"""The resume path under failure: stale partial files, a worker thread that fails mid-run, a
frame that cannot be decoded, cancelling a resumed run. Each ends with a rerun that must equal
one uninterrupted run bit for bit."""

import hashlib
import os
import pathlib
import subprocess
import sys
import threading

import pytest

from addon import frames, lightvec, pipeline
from addon.errors import Cancelled, InputError, OutputError
from tests.clip_fixtures import ramp_frames, write_movie, write_png_sequence

N = 6
UNIFORM = lightvec.uniform(1.0)[None]


@pytest.fixture(scope="module")
def movie(tmp_path_factory):
    return str(write_movie(tmp_path_factory.mktemp("mov") / "clip.mov", ramp_frames(N),
                           codec="png"))


@pytest.fixture(scope="module")
def reference(toy, movie, tmp_path_factory):
    """Digests of one uninterrupted run (with matte)."""
    out = tmp_path_factory.mktemp("one")
    res = pipeline.relight_clip(clip_of(movie), UNIFORM, out, opts(toy))
    return digest(res.relit_files + res.matte_files)


def clip_of(movie):
    return pipeline.ClipSpec("movie", movie, (), 0, N, "sRGB", 25.0)


def opts(model, **kw):
    kw.setdefault("background", "network")
    return pipeline.RelightOptions(model, working_size=32, threads=1, write_matte=True, **kw)


def digest(paths):
    return [hashlib.sha256(pathlib.Path(p).read_bytes()).hexdigest() for p in paths]


def outputs(out):
    return ([pipeline.relit_path(out, i) for i in range(N)]
            + [pipeline.matte_path(out, i) for i in range(N)])


def leftovers(out):
    return [str(p) for p in pathlib.Path(out).rglob("*.partial")]


def no_pipeline_threads():
    return not any(t.name in ("relight-decode", "relight-write") and t.is_alive()
                   for t in threading.enumerate())


def dead_pid() -> int:
    done = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"],
                          capture_output=True, text=True, check=True)
    return int(done.stdout)


def test_stale_partials_are_swept_on_resume_and_nothing_else(toy, movie, reference, tmp_path):
    out = tmp_path / "out"
    pipeline.relight_clip(clip_of(movie), UNIFORM, out, opts(toy), frames=range(0, 2))
    dead, live = dead_pid(), os.getppid()
    ours = frames.partial_path(pipeline.relit_path(out, 3))

    def killed(path):  # what a killed writer of this machine left
        return frames.partial_path(path).replace(f"_{os.getpid()}_", f"_{dead}_")

    stale = [killed(pipeline.relit_path(out, 3)), killed(pipeline.matte_path(out, 3)),
             killed(pipeline.source_path(out, 3)), killed(str(out / pipeline.RUN_FILE))]
    kept = [ours.replace(f"_{os.getpid()}_", f"_{live}_"),                # a live writer's
            pipeline.relit_path(out, 4) + f".otherhost_{dead}_1.partial",  # another machine's
            str(out / "relit" / f"notes.txt.{dead}.partial"),             # not a name we write
            str(tmp_path / f"relit_000005.exr.{dead}.partial")]           # outside the run
    for p in stale + kept:
        pathlib.Path(p).write_bytes(b"half a frame")
    logs = []
    res = pipeline.relight_clip(clip_of(movie), UNIFORM, out, opts(toy), log=logs.append)
    assert res.resumed == 2 and res.written == N - 2
    assert not any(os.path.exists(p) for p in stale)
    assert all(os.path.exists(p) for p in kept)
    assert any("Removed 4 unfinished file(s)" in m for m in logs)
    assert digest(outputs(out)) == reference


def test_writer_failure_stops_the_run_and_a_rerun_resumes(toy, movie, reference, tmp_path,
                                                          monkeypatch):
    real = frames.write_exr_planes
    calls = []

    def full_disk(path, planes, compression="none"):
        calls.append(path)
        if len(calls) > 4:  # matte + relit of frames 0 and 1, then the disk is full
            raise OutputError(f"Cannot write {path} (No space left on device); check ...")
        real(path, planes, compression)

    monkeypatch.setattr(frames, "write_exr_planes", full_disk)
    out = tmp_path / "out"
    with pytest.raises(OutputError, match="No space left"):
        pipeline.relight_clip(clip_of(movie), UNIFORM, out, opts(toy))
    assert no_pipeline_threads()
    done = sorted(os.listdir(out / "relit"))
    assert done == ["relit_000000.exr", "relit_000001.exr"] and not leftovers(out)
    monkeypatch.setattr(frames, "write_exr_planes", real)
    res = pipeline.relight_clip(clip_of(movie), UNIFORM, out, opts(toy))
    assert (res.resumed, res.written) == (2, N - 2)
    assert digest(outputs(out)) == reference


def test_network_failure_mid_run_keeps_queued_frames_and_resumes(toy, movie, reference,
                                                                 tmp_path, monkeypatch):
    real = pipeline.infer_planar
    calls = []

    before = min(pipeline.GAIN_SAMPLES, N)  # the exposure gain's frames, before the run's

    def flaky(*args):
        calls.append(1)
        if len(calls) == before + 4:
            raise RuntimeError("onnxruntime: out of memory")  # not a RelightError: a bug-like
        return real(*args)                                    # failure surfaces as it is

    monkeypatch.setattr(pipeline, "infer_planar", flaky)
    out = tmp_path / "out"
    with pytest.raises(RuntimeError, match="out of memory"):
        pipeline.relight_clip(clip_of(movie), UNIFORM, out, opts(toy))
    assert no_pipeline_threads() and not leftovers(out)
    # the three frames the network finished were written before the error was raised
    assert sorted(os.listdir(out / "relit")) == [f"relit_{i:06d}.exr" for i in range(3)]
    monkeypatch.setattr(pipeline, "infer_planar", real)
    res = pipeline.relight_clip(clip_of(movie), UNIFORM, out, opts(toy))
    assert (res.resumed, res.written) == (3, N - 3)
    assert digest(outputs(out)) == reference


def test_undecodable_frame_mid_sequence_then_resume(toy, tmp_path):
    src = ramp_frames(N)
    files = write_png_sequence(tmp_path / "seq", src)
    clip = pipeline.ClipSpec("images", str(tmp_path / "seq"), tuple(files), 0, N, "sRGB", 0.0)
    one = pipeline.relight_clip(clip, UNIFORM, tmp_path / "one", opts(toy))
    out = tmp_path / "out"
    pipeline.relight_clip(clip, UNIFORM, out, opts(toy), frames=[0])  # exposure is stored
    good, st = pathlib.Path(files[4]).read_bytes(), os.stat(files[4])
    pathlib.Path(files[4]).write_bytes(bytes(len(good)))  # same size and time: same identity
    os.utime(files[4], ns=(st.st_atime_ns, st.st_mtime_ns))
    with pytest.raises(InputError, match="Cannot read the image"):
        pipeline.relight_clip(clip, UNIFORM, out, opts(toy))
    assert no_pipeline_threads() and not leftovers(out)
    assert sorted(os.listdir(out / "relit")) == [f"relit_{i:06d}.exr" for i in range(4)]
    pathlib.Path(files[4]).write_bytes(good)
    os.utime(files[4], ns=(st.st_atime_ns, st.st_mtime_ns))
    res = pipeline.relight_clip(clip, UNIFORM, out, opts(toy))
    assert (res.resumed, res.written) == (4, N - 4)
    assert digest(outputs(out)) == digest(one.relit_files + one.matte_files)


def test_cancelling_a_resumed_run_then_resuming_again(toy, movie, reference, tmp_path):
    out = tmp_path / "out"
    pipeline.relight_clip(clip_of(movie), UNIFORM, out, opts(toy), frames=range(0, 2))
    with pytest.raises(Cancelled):
        pipeline.relight_clip(clip_of(movie), UNIFORM, out, opts(toy),
                              should_cancel=lambda: True)
    assert no_pipeline_threads() and not leftovers(out)
    assert len(os.listdir(out / "relit")) == 2
    seen = []
    res = pipeline.relight_clip(clip_of(movie), UNIFORM, out, opts(toy),
                                on_progress=lambda d, t, m: seen.append(d))
    assert (res.resumed, res.written) == (2, N - 2) and seen[0] == 2 and seen[-1] == N
    assert digest(outputs(out)) == reference
