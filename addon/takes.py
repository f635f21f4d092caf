"""Takes: every lighting of a strip gets its own numbered folder, so relighting with a changed
light keeps the earlier result beside the new one instead of asking to overwrite it.

``<output>/<strip folder>/v001``, ``v002``, ...: each take holds one run (the folder layout of
addon/pipeline.py) and a claim file naming that run (the digest of its identity). A run goes to
the take that claims it (a resume, and every farm chunk of one run on any machine, land in one
take), else to a new take numbered after the highest, or, with ``replace``, into the latest take,
whose frames the pipeline then clears. The choice is made under the strip folder's setup lock
(addon/runlock.py), so two processes never claim one number nor two numbers for one run."""

from __future__ import annotations

import json
import os
import pathlib
import re

from . import frames, runlock
from .errors import OutputError

TAKE_FILE = "take.json"
_NAME = re.compile(r"^v(\d{3,})$")


def take_name(number: int) -> str:
    """'v001' for take 1."""
    return f"v{int(number):03d}"


def take_number(take_dir) -> int | None:
    """The number of a take folder ('.../v012' -> 12), None for another folder."""
    match = _NAME.match(os.path.basename(os.path.normpath(str(take_dir))))
    return int(match.group(1)) if match else None


def list_takes(strip_dir) -> list[tuple[int, str]]:
    """(number, folder) of every take in ``strip_dir``, lowest first."""
    try:
        names = os.listdir(str(strip_dir))
    except FileNotFoundError:
        return []
    found = []
    for name in names:
        number = take_number(name)
        path = os.path.join(str(strip_dir), name)
        if number is not None and os.path.isdir(path):
            found.append((number, path))
    return sorted(found)


def claimed_run(take_dir) -> str | None:
    """The run (identity digest) that ``take_dir`` holds; None if it has no readable claim."""
    try:
        with open(os.path.join(str(take_dir), TAKE_FILE), encoding="utf-8") as f:
            record = json.load(f)
    except (OSError, ValueError):
        return None
    run = record.get("run") if isinstance(record, dict) else None
    return run if isinstance(run, str) else None


def _claim(take_dir: str, run: str) -> None:
    try:
        os.makedirs(take_dir, exist_ok=True)
        text = json.dumps({"run": run})
        frames.write_atomic(os.path.join(take_dir, TAKE_FILE),
                            lambda tmp: pathlib.Path(tmp).write_text(text, encoding="utf-8"))
    except OSError as err:
        raise OutputError(f"Cannot create the take folder {take_dir} ({err}); choose an output "
                          "folder you can write to.") from err


def choose_take(strip_dir, run: str, replace: bool = False, note=None,
                should_cancel=None) -> str:
    """The take folder run ``run`` writes into (created and claimed if new): the take already
    claiming it, else the latest take when ``replace`` (OutputError while another run is still
    writing there), else a new one. Cancelled when ``should_cancel()`` turns true while
    another process holds the strip folder's setup lock."""
    strip_dir = str(strip_dir)
    try:
        os.makedirs(strip_dir, exist_ok=True)
    except OSError as err:
        raise OutputError(f"Cannot create the output folder {strip_dir} ({err}); choose a folder "
                          "you can write to.") from err
    with runlock.SetupLock(strip_dir, note, should_cancel):
        takes = list_takes(strip_dir)
        for _, path in takes:
            if claimed_run(path) == run:
                return path
        if replace and takes:
            path = takes[-1][1]
            busy = runlock.other_live_run(path, run, note)
            if busy is not None:
                raise OutputError(
                    f"The latest take {path} is still being written by another relight run "
                    f"({runlock.describe(*busy)}); wait for it to finish, or turn Replace Latest "
                    "Take (--overwrite) off to make a new take.")
            _claim(path, run)
            return path
        path = os.path.join(strip_dir, take_name(takes[-1][0] + 1 if takes else 1))
        _claim(path, run)
        return path
