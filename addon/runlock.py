"""Locking an output folder, so that two runs never write into one folder at once.

Farm chunks of one run write into one folder at the same time (their frames are identical
whichever writes them), so the folder is not locked for a single process: each running process
holds a *holder file* naming its run, and a process of another run is refused while a live
holder remains. Deciding what a folder holds (resume, refuse, or clear it for overwrite) and
writing its run record happen under a short exclusive *setup lock*, so two processes can never
both find a folder free, nor one clear frames another has just claimed.

Both are files in the output folder created atomically (``O_CREAT | O_EXCL``) holding the process
id, the machine and the time; a holder file also names its run (a digest of the run's identity).
They are removed when the run ends, however it ends (``with`` / ``finally``; the batch script
turns Ctrl-C and SIGTERM into such an end). A file left by a process that died (killed,
crashed) on this machine is taken over with a note. Another machine's process cannot be
checked, so a running process touches its holder file every HEARTBEAT_S: another machine's
holder file untouched for HOLDER_STALE_S was left by a crash (the machine died, or lost the
shared storage) and is taken over with a note; until then the message says which run it names
(its setup lock, held for seconds, is taken over after an hour).
"""

from __future__ import annotations

import itertools
import json
import os
import threading
import time

from .errors import Cancelled, OutputError
from .frames import HOST, pid_alive

SETUP_FILE = "relight_setup.lock"
HOLDER_PREFIX, HOLDER_SUFFIX = "relight_run_", ".lock"
SETUP_WAIT_S = 300.0  # a setup reads a few sample frames; wait this long for another's
SETUP_STALE_S = 3600.0  # a setup lock of another machine this old was left by a crash
UNREADABLE_AFTER_S = 10.0  # a lock file still empty or garbled after this was left by a crash
HEARTBEAT_S = 60.0  # a running process touches its holder file this often
HOLDER_STALE_S = 900.0  # another machine's holder file untouched this long was left by a crash
_counter = itertools.count()  # several runs of one process (threads) each hold their own file


def _create(path: str, record: dict) -> bool:
    """Create ``path`` atomically with ``record`` as JSON; False if it exists already."""
    try:
        fd = os.open(path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
    except FileExistsError:
        return False
    except OSError as err:
        raise OutputError(f"Cannot create the lock file {path} ({err}); choose an output folder "
                          "you can write to.") from err
    try:
        os.write(fd, json.dumps(record).encode("utf-8"))
    finally:
        os.close(fd)
    return True


def _read(path: str) -> dict | None:
    """A lock file's record; None if it is gone; {} if it cannot be read (yet)."""
    try:
        with open(path, encoding="utf-8") as f:
            record = json.load(f)
        return record if isinstance(record, dict) else {}
    except FileNotFoundError:
        return None
    except (OSError, ValueError):
        return {}


def _age(path: str) -> float:
    """Seconds since ``path`` was last modified (0 if it is gone)."""
    try:
        return time.time() - os.stat(path).st_mtime
    except FileNotFoundError:
        return 0.0


def _dead(path: str, record: dict, max_age: float | None = None,
          untouched_s: float | None = None) -> bool:
    """Whether the lock file ``path`` was left by a process that no longer runs: one of this
    machine whose pid is gone, a file still unreadable long after it was made, or, from another
    machine, one older than ``max_age`` (by its record) or untouched for ``untouched_s`` (its
    heartbeat stopped)."""
    if not record:
        return not os.path.exists(path) or _age(path) > UNREADABLE_AFTER_S
    if record.get("host") != HOST:  # another machine's process cannot be checked from here
        if untouched_s is not None and _age(path) > untouched_s:
            return True
        try:
            return max_age is not None and time.time() - float(record.get("time")) > max_age
        except (TypeError, ValueError):
            return False
    try:
        return not pid_alive(int(record.get("pid")))
    except (TypeError, ValueError):
        return True


def describe(path: str, record: dict) -> str:
    if not record:
        return f"an unreadable lock file {path}"
    return (f"process {record.get('pid')} on {record.get('host')}, started "
            f"{record.get('started')} (lock file {path})")


class FolderLock:
    """``with FolderLock(out_dir, run) as lock:`` holds the folder for run ``run`` (a digest of
    its identity) and its setup lock; ``lock.end_setup()`` lets the next process set up (other
    chunks of this run) while this one relights. Raises OutputError when a live process of
    another run holds the folder, Cancelled when ``should_cancel()`` turns true while waiting."""

    def __init__(self, out_dir: str, run: str, note=None, should_cancel=None,
                 wait_s: float = SETUP_WAIT_S):
        self.out_dir, self.run = str(out_dir), str(run)
        self.note = note or (lambda msg: None)
        self.should_cancel = should_cancel
        self.wait_s = float(wait_s)
        self.setup_path = os.path.join(self.out_dir, SETUP_FILE)
        self.holder_path = os.path.join(
            self.out_dir, f"{HOLDER_PREFIX}{HOST}_{os.getpid()}_{next(_counter)}{HOLDER_SUFFIX}")
        self._in_setup = self._holding = False
        self._beating = threading.Event()

    def _record(self) -> dict:
        return {"pid": os.getpid(), "host": HOST, "run": self.run,
                "started": time.strftime("%Y-%m-%d %H:%M:%S"), "time": time.time()}

    def __enter__(self) -> FolderLock:
        self.begin_setup()
        try:
            if not _create(self.holder_path, self._record()):
                raise OutputError(f"The lock file {self.holder_path} exists already; delete it.")
            self._holding = True
            threading.Thread(target=self._heartbeat, name="relight-lock-heartbeat",
                             daemon=True).start()
            self._refuse_other_runs()
        except BaseException:
            self.__exit__(None, None, None)
            raise
        return self

    def __exit__(self, *exc) -> None:
        self.end_setup()
        self._beating.set()
        if self._holding:
            self._holding = False
            _remove(self.holder_path)

    def _heartbeat(self) -> None:
        """Touch the holder file every HEARTBEAT_S while held: other machines see it alive."""
        while not self._beating.wait(HEARTBEAT_S):
            try:
                os.utime(self.holder_path)
            except OSError:  # removed (the run ended) or the storage is away for a moment
                pass

    def end_setup(self) -> None:
        if self._in_setup:
            self._in_setup = False
            _remove(self.setup_path)

    def begin_setup(self) -> None:
        """Take the folder's setup lock (waiting for another process's, within ``wait_s``)."""
        deadline = time.monotonic() + self.wait_s
        while not _create(self.setup_path, self._record()):
            record = _read(self.setup_path)
            if record is None:
                continue  # released just now: try again
            if _dead(self.setup_path, record, max_age=SETUP_STALE_S):
                self.note(f"Took over the lock of a relight run that ended without releasing "
                          f"the output folder ({describe(self.setup_path, record)}).")
                _remove(self.setup_path)
                continue
            if self.should_cancel and self.should_cancel():
                raise Cancelled("Cancelled while waiting for another relight run to set up the "
                                f"output folder {self.out_dir}; nothing was written.")
            if time.monotonic() > deadline:
                raise OutputError(
                    f"The output folder {self.out_dir} is being set up by another relight run "
                    f"({describe(self.setup_path, record)}) and has been for over "
                    f"{self.wait_s:.0f} s. Wait for it, or choose another output folder; if "
                    "that run is no longer running (its machine crashed), delete the lock file.")
            time.sleep(0.05)
        self._in_setup = True

    def _refuse_other_runs(self) -> None:
        other = other_live_run(self.out_dir, self.run, self.note, skip=self.holder_path)
        if other is not None:
            raise OutputError(
                f"The output folder {self.out_dir} is in use by another relight run (with "
                f"other footage, lighting or settings): {describe(*other)}. Wait for it to "
                "finish or choose another output folder. If that run is no longer running (its "
                "machine crashed), delete the lock file; it is taken over anyway once nobody "
                f"has touched it for {HOLDER_STALE_S / 60:.0f} minutes.")


def other_live_run(folder: str, run: str, note=None, skip: str = "") -> tuple[str, dict] | None:
    """(lock file, record) of a live process holding ``folder`` for a run other than ``run``,
    else None. Holder files that dead processes left are removed on the way, with a note."""
    note = note or (lambda msg: None)
    try:
        names = sorted(os.listdir(folder))
    except FileNotFoundError:
        return None
    except OSError as err:
        raise OutputError(f"Cannot list the output folder {folder} ({err}).") from err
    for name in names:
        path = os.path.join(folder, name)
        if not (name.startswith(HOLDER_PREFIX) and name.endswith(HOLDER_SUFFIX)) or path == skip:
            continue
        record = _read(path)
        if record is None:
            continue
        if _dead(path, record, untouched_s=HOLDER_STALE_S):
            note(f"Took over the output folder from a relight run that ended without releasing "
                 f"it ({describe(path, record)}).")
            _remove(path)
        elif record.get("run") != run:
            return path, record
    return None


class SetupLock:
    """``with SetupLock(folder):`` holds ``folder``'s short exclusive setup lock (the one
    FolderLock takes while a run decides what the folder holds)."""

    def __init__(self, folder: str, note=None, should_cancel=None, wait_s: float = SETUP_WAIT_S):
        self._lock = FolderLock(folder, "", note, should_cancel, wait_s)

    def __enter__(self) -> SetupLock:
        self._lock.begin_setup()
        return self

    def __exit__(self, *exc) -> None:
        self._lock.end_setup()


def _remove(path: str) -> None:
    try:
        os.remove(path)
    except FileNotFoundError:
        pass
