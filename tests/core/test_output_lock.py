"""Two runs writing into one output folder at once: the folder lock (addon/runlock.py) through
the pipeline, with the toy model. Another run is refused while one is live, processes of the
same run (farm chunks) share the folder, and a lock left by a dead process is taken over."""

import hashlib
import json
import os
import pathlib
import subprocess
import sys
import time

import numpy as np
import pytest

from addon import frames, lightvec, pipeline, runlock
from addon.errors import Cancelled, OutputError
from tests.clip_fixtures import ramp_frames, write_movie

ROOT = pathlib.Path(__file__).resolve().parents[2]
N = 6
UNIFORM = lightvec.uniform(1.0)[None]


@pytest.fixture(scope="module")
def movie(tmp_path_factory):
    return str(write_movie(tmp_path_factory.mktemp("mov") / "clip.mov", ramp_frames(N),
                           codec="png"))


def clip(movie):
    return pipeline.ClipSpec("movie", movie, (), 0, N, "sRGB", 25.0)


def opts(model, **kw):
    kw.setdefault("exposure_mode", "physical")  # other lights must give other frames here
    return pipeline.RelightOptions(model, working_size=32, threads=1, background="network", **kw)


def digests(folder):
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(pathlib.Path(folder, "relit").glob("relit_*.exr"))}


def lock_files(folder):
    return sorted(p.name for p in pathlib.Path(folder).glob("*.lock"))


HOLD = """
import sys, time
from addon import runlock
with runlock.FolderLock(sys.argv[1], sys.argv[2]) as lock:
    if sys.argv[3] == "relighting":
        lock.end_setup()
    print("held", flush=True)
    sys.stdin.read()  # until the test closes stdin
"""


class Holder:
    """Another process holding ``folder`` for run ``run`` until stopped, relighting (its setup
    over) or still setting up."""

    def __init__(self, folder, run, stage="relighting"):
        os.makedirs(folder, exist_ok=True)
        self.proc = subprocess.Popen([sys.executable, "-c", HOLD, str(folder), run, stage],
                                     cwd=ROOT,
                                     env=dict(os.environ, PYTHONPATH=str(ROOT)),
                                     stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
        assert self.proc.stdout.readline().strip() == "held"

    def stop(self):
        self.proc.stdin.close()
        assert self.proc.wait(timeout=60) == 0


def test_a_live_run_of_other_lighting_refuses_another_even_with_overwrite(toy, movie, tmp_path):
    out = tmp_path / "out"
    pipeline.relight_clip(clip(movie), UNIFORM, out, opts(toy))
    before = digests(out)
    record = (out / pipeline.RUN_FILE).read_bytes()
    holder = Holder(out, "a-run-with-other-lighting")
    try:
        for overwrite in (False, True):
            with pytest.raises(OutputError, match="in use by another relight run") as err:
                pipeline.relight_clip(clip(movie), 2 * UNIFORM, out, opts(toy,
                                                                         overwrite=overwrite))
            message = str(err.value)
            assert f"process {holder.proc.pid} on {frames.HOST}" in message
            assert "Wait for it to finish or choose another output folder" in message
        assert digests(out) == before and (out / pipeline.RUN_FILE).read_bytes() == record
    finally:
        holder.stop()
    assert lock_files(out) == []  # the holder released its lock as it ended
    res = pipeline.relight_clip(clip(movie), 2 * UNIFORM, out, opts(toy, overwrite=True))
    assert res.written == N and digests(out) != before
    assert lock_files(out) == []  # and so did the run


def test_processes_of_the_same_run_share_the_folder(toy, movie, tmp_path):
    one = pipeline.relight_clip(clip(movie), UNIFORM, tmp_path / "one", opts(toy))
    out = tmp_path / "farm"
    identity = json.loads((tmp_path / "one" / pipeline.RUN_FILE).read_text())["identity"]
    run = hashlib.sha256(json.dumps(identity, sort_keys=True).encode()).hexdigest()
    holder = Holder(out, run)  # a chunk of this very run, mid-way
    try:
        res = pipeline.relight_clip(clip(movie), UNIFORM, out, opts(toy), frames=range(3))
        assert res.written == 3
    finally:
        holder.stop()
    pipeline.relight_clip(clip(movie), UNIFORM, out, opts(toy), frames=range(3, N))
    assert digests(out) == digests(tmp_path / "one") and len(one.relit_files) == N


def test_a_run_that_fails_or_is_cancelled_releases_the_folder(toy, movie, tmp_path):
    out = tmp_path / "out"
    done = []
    with pytest.raises(Cancelled):
        pipeline.relight_clip(clip(movie), UNIFORM, out, opts(toy),
                              on_progress=lambda n, *_: done.append(n),
                              should_cancel=lambda: bool(done) and done[-1] >= 2)
    assert lock_files(out) == []
    with pytest.raises(OutputError, match="already holds"):  # refused after taking the lock
        pipeline.relight_clip(clip(movie), 2 * UNIFORM, out, opts(toy))
    assert lock_files(out) == []
    res = pipeline.relight_clip(clip(movie), UNIFORM, out, opts(toy))  # resumes
    assert res.resumed >= 2 and res.resumed + res.written == N


def _dead_pid() -> int:
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    return p.pid


def test_locks_left_by_dead_processes_are_taken_over_with_a_note(toy, movie, tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    dead = {"pid": _dead_pid(), "host": frames.HOST, "run": "a-killed-run",
            "started": "2020-01-01 00:00:00", "time": 0.0}
    (out / runlock.SETUP_FILE).write_text(json.dumps(dead))
    (out / f"{runlock.HOLDER_PREFIX}{frames.HOST}_{dead['pid']}_0{runlock.HOLDER_SUFFIX}") \
        .write_text(json.dumps(dead))
    res = pipeline.relight_clip(clip(movie), UNIFORM, out, opts(toy))
    assert res.written == N
    notes = [w for w in res.warnings if "ended without releasing" in w]
    assert len(notes) == 2 and all(f"process {dead['pid']}" in w for w in notes)
    assert lock_files(out) == []


def test_a_lock_of_another_machine_is_taken_over_only_once_its_heartbeat_stops(toy, movie,
                                                                               tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    other = {"pid": _dead_pid(), "host": "render-node-7", "run": "another-run",
             "started": "2020-01-01 00:00:00", "time": 0.0}
    holder = out / f"{runlock.HOLDER_PREFIX}render-node-7_{other['pid']}_0{runlock.HOLDER_SUFFIX}"
    holder.write_text(json.dumps(other))  # touched just now: its process may be running
    with pytest.raises(OutputError, match="render-node-7.*delete the lock file; it is taken "
                                          "over anyway once nobody has touched it for 15 min"):
        pipeline.relight_clip(clip(movie), UNIFORM, out, opts(toy))
    assert not list((out / "relit").glob("*.exr")) and holder.is_file()
    assert lock_files(out) == [holder.name]  # the refused run left nothing behind
    stale = time.time() - runlock.HOLDER_STALE_S - 60
    os.utime(holder, (stale, stale))  # its machine died: the heartbeat stopped
    res = pipeline.relight_clip(clip(movie), UNIFORM, out, opts(toy))
    assert res.written == N and not holder.exists()
    assert any("ended without releasing" in w and "render-node-7" in w for w in res.warnings)
    for p in out.glob("relit/*.exr"):
        p.unlink()
    (out / pipeline.RUN_FILE).unlink()
    # Its setup lock (held for seconds) is another matter once it is an hour old.
    (out / runlock.SETUP_FILE).write_text(json.dumps({**other, "time": time.time() - 7200}))
    res = pipeline.relight_clip(clip(movie), UNIFORM, out, opts(toy))
    assert res.written == N and any("render-node-7" in w for w in res.warnings)


def test_a_held_folder_keeps_its_holder_file_touched(tmp_path, monkeypatch):
    monkeypatch.setattr(runlock, "HEARTBEAT_S", 0.05)
    with runlock.FolderLock(tmp_path, "mine") as lock:
        lock.end_setup()
        os.utime(lock.holder_path, (0, 0))
        deadline = time.monotonic() + 10
        while os.stat(lock.holder_path).st_mtime < 1 and time.monotonic() < deadline:
            time.sleep(0.02)
        assert time.time() - os.stat(lock.holder_path).st_mtime < 5
    assert lock_files(tmp_path) == []


def test_waiting_for_another_setup_can_be_cancelled_or_times_out(tmp_path):
    holder = Holder(tmp_path, "another-run", stage="setting up")  # keeps its setup lock
    try:
        with pytest.raises(Cancelled, match="nothing was written"):
            with runlock.FolderLock(tmp_path, "mine", should_cancel=lambda: True):
                pass
        started = time.monotonic()
        with pytest.raises(OutputError, match="being set up by another relight run"):
            with runlock.FolderLock(tmp_path, "mine", wait_s=0.3):
                pass
        assert time.monotonic() - started < 5
    finally:
        holder.stop()
    with runlock.FolderLock(tmp_path, "mine") as lock:
        assert lock_files(tmp_path) == sorted([runlock.SETUP_FILE,
                                               os.path.basename(lock.holder_path)])
        lock.end_setup()
        assert lock_files(tmp_path) == [os.path.basename(lock.holder_path)]
    assert lock_files(tmp_path) == []


RUN = """
import sys, time, pathlib
import numpy as np
from addon import lightvec, pipeline
from addon.errors import RelightError
clip = pipeline.ClipSpec('movie', sys.argv[1], (), 0, {n}, 'sRGB', 25.0)
opts = pipeline.RelightOptions(sys.argv[2], working_size=32, threads=1, background='network',
                               overwrite=sys.argv[5] == '1', exposure_mode='physical')
while not pathlib.Path(sys.argv[6]).exists():  # start together
    time.sleep(0.005)
try:
    pipeline.relight_clip(clip, lightvec.uniform(float(sys.argv[4]))[None], sys.argv[3], opts)
except RelightError as err:
    print(err)
    sys.exit(1)
"""


@pytest.mark.parametrize("second_overwrites", [False, True])
def test_two_runs_of_different_lights_at_once_never_mix(toy, movie, tmp_path,
                                                        second_overwrites):
    """Started together into one folder: whatever the timing, the folder ends up holding one
    run's frames, all of them, and its record names that run; a refused run says why."""
    refs = {v: digests(pipeline.relight_clip(clip(movie), v * UNIFORM, tmp_path / f"ref{v}",
                                             opts(toy)).out_dir) for v in (1, 2)}
    go, out = tmp_path / "go", tmp_path / "out"
    procs = [subprocess.Popen([sys.executable, "-c", RUN.format(n=N), movie, toy, str(out),
                               str(v), "1" if v == 2 and second_overwrites else "0", str(go)],
                              cwd=ROOT, env=dict(os.environ, PYTHONPATH=str(ROOT)),
                              stdout=subprocess.PIPE, text=True) for v in (1, 2)]
    time.sleep(1.0)
    go.touch()
    results = [(p.wait(timeout=120), p.stdout.read()) for p in procs]
    assert any(code == 0 for code, _ in results)
    for code, text in results:
        assert code == 0 or "in use by another relight run" in text \
            or "already holds another relight run" in text, text
    got = digests(out)
    assert got in (refs[1], refs[2]) and len(got) == N
    lights = {v: pipeline.run_identity(clip(movie), (v * UNIFORM).astype(np.float32),
                                       opts(toy), _card(toy), 32)["lights_sha256"]
              for v in (1, 2)}
    stored = json.loads((out / pipeline.RUN_FILE).read_text())["identity"]["lights_sha256"]
    assert got == refs[1 if stored == lights[1] else 2]
    assert lock_files(out) == []


def _card(model):
    from addon import engine
    return engine.load_card(model)
