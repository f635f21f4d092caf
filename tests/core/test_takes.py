"""Takes (addon/takes.py): one numbered folder per lighting of a strip, chosen under a lock."""

import json
import os
import pathlib
import subprocess
import sys

import pytest

from addon import runlock, takes
from addon.errors import OutputError

ROOT = pathlib.Path(__file__).resolve().parents[2]


def test_runs_get_numbered_takes_and_return_to_their_own(tmp_path):
    strip = tmp_path / "shot"
    a = takes.choose_take(strip, "run-a")
    b = takes.choose_take(strip, "run-b")
    assert (pathlib.Path(a).name, pathlib.Path(b).name) == ("v001", "v002")
    assert takes.choose_take(strip, "run-a") == a          # a resume, or a farm chunk
    assert takes.claimed_run(b) == "run-b"
    assert [n for n, _ in takes.list_takes(strip)] == [1, 2]
    assert takes.take_number(b) == 2 and takes.take_number(tmp_path) is None


def test_numbers_continue_after_the_highest_and_ignore_other_folders(tmp_path):
    strip = tmp_path / "shot"
    for name in ("v007", "preview", "v1", "notes"):
        (strip / name).mkdir(parents=True)
    (strip / "v1000").write_text("a file, not a take")
    assert pathlib.Path(takes.choose_take(strip, "run")).name == "v008"


def test_replace_reuses_the_latest_take_and_claims_it(tmp_path):
    strip = tmp_path / "shot"
    takes.choose_take(strip, "run-a")
    b = takes.choose_take(strip, "run-b")
    assert takes.choose_take(strip, "run-c", replace=True) == b
    assert takes.claimed_run(b) == "run-c"
    assert takes.choose_take(strip, "run-b") == os.path.join(strip, "v003")  # b was replaced
    assert takes.choose_take(tmp_path / "new", "run", replace=True).endswith("v001")


def test_replace_is_refused_while_another_run_writes_the_latest_take(tmp_path):
    strip = tmp_path / "shot"
    take = takes.choose_take(strip, "run-a")
    with runlock.FolderLock(take, "run-a") as lock:
        lock.end_setup()
        with pytest.raises(OutputError, match="still being written by another relight run"):
            takes.choose_take(strip, "run-b", replace=True)
        assert takes.claimed_run(take) == "run-a"
        assert takes.choose_take(strip, "run-b").endswith("v002")  # a new take is fine
        assert takes.choose_take(strip, "run-a", replace=True) == take  # its own run resumes


def test_a_damaged_claim_is_not_matched(tmp_path):
    strip = tmp_path / "shot"
    take = takes.choose_take(strip, "run-a")
    pathlib.Path(take, takes.TAKE_FILE).write_text("{not json")
    assert takes.claimed_run(take) is None
    assert takes.choose_take(strip, "run-a").endswith("v002")


def test_an_unwritable_strip_folder_says_so(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("")
    with pytest.raises(OutputError, match="Cannot create the output folder"):
        takes.choose_take(blocker / "shot", "run")


def test_processes_choosing_at_once_never_share_or_split_a_take(tmp_path):
    """Eight processes at once, two of each of four runs (farm chunks): one take per run."""
    code = ("import sys, time\nfrom addon import takes\n"
            "while time.time() < float(sys.argv[3]): pass\n"
            "print(takes.choose_take(sys.argv[1], sys.argv[2]))\n")
    import time

    start = str(time.time() + 2.0)
    procs = [subprocess.Popen([sys.executable, "-c", code, str(tmp_path / "shot"), f"run-{i % 4}",
                               start], cwd=ROOT, env=dict(os.environ, PYTHONPATH=str(ROOT)),
                              stdout=subprocess.PIPE, text=True) for i in range(8)]
    chosen = {}
    for i, p in enumerate(procs):
        out, _ = p.communicate(timeout=120)
        assert p.returncode == 0
        chosen.setdefault(f"run-{i % 4}", set()).add(out.strip())
    assert all(len(v) == 1 for v in chosen.values())
    folders = sorted(next(iter(v)) for v in chosen.values())
    assert [pathlib.Path(f).name for f in folders] == ["v001", "v002", "v003", "v004"]
    for run, (folder,) in chosen.items():
        assert json.loads(pathlib.Path(folder, takes.TAKE_FILE).read_text()) == {"run": run}
    assert not list((tmp_path / "shot").glob("*.lock"))
