"""Relit frames under the footage's own frame numbers: shot.1001.exr relights to relit.1001.exr.

The pipeline names its frames by 0-based clip index (relit/relit_000000.exr); resuming, farm
chunks and the run record rely on those names. A strip's run (the Relight Strip operator, the
batch script, a farm chunk) also publishes each finished frame under its source number, in its
take's folder, as a hard link to the pipeline's file (no second copy on disk; a copy where the
file system has no hard links); the relit strip shows those. Movies carry no numbers: their
frames take the scene frames they are shown on."""

from __future__ import annotations

import os
import re
import shutil

from . import frames, pipeline
from .errors import OutputError

MOVIE_DIGITS = 4  # relit.0001.exr for a movie's first frame at scene frame 1
_DIGITS = re.compile(r"(\d+)$")
_PUBLISHED = re.compile(r"^(relit|matte)\.-?\d+\.exr$")


def sequence_numbering(files, first_number: int = 1) -> tuple[list[int], int]:
    """(the frame number of each file, the digits its numbers are padded to). A numbered
    sequence keeps its numbers and padding (shot.0998.exr: 998, 4 digits); files without a
    trailing number count up from ``first_number``."""
    parsed = [frames.frame_number(f) for f in files]
    if files and all(p is not None for p in parsed):
        stem = os.path.splitext(os.path.basename(str(files[0])))[0]
        return [p[1] for p in parsed], len(_DIGITS.search(stem).group(1))
    return [first_number + i for i in range(len(files))], MOVIE_DIGITS


def numbered_name(prefix: str, number: int, digits: int) -> str:
    """'relit.1001.exr': the prefix, the number padded to ``digits``, and .exr."""
    return f"{prefix}.{int(number):0{int(digits)}d}.exr"


def publish(src, dest) -> None:
    """Make ``dest`` the same file as ``src``: a hard link, else a copy, renamed into place so
    a reader never sees half a frame. A link that already points at ``src`` is left alone."""
    src, dest = str(src), str(dest)
    try:
        if os.path.samefile(src, dest):
            return
    except FileNotFoundError:
        pass

    def link_or_copy(tmp):
        try:
            os.link(src, tmp)
        except OSError:  # no hard links here (some network shares, FAT): copy
            shutil.copyfile(src, tmp)
    frames.write_atomic(dest, link_or_copy)


def sweep_partials(out_dir) -> None:
    """Remove half-made numbered names that a killed process of this machine left."""
    frames.sweep_stale_partials(out_dir, _PUBLISHED)


def publish_frames(out_dir, indices, numbers, digits: int, matte: bool = False) -> list[str]:
    """Publish the finished frames ``indices`` (0-based clip indices) of the run in ``out_dir``
    under their numbers (``numbers[i]`` for clip frame i); returns the relit names written.
    OutputError when one of them is not finished (the run did not complete)."""
    sweep_partials(out_dir)
    written = []
    for i in indices:
        relit = pipeline.relit_path(out_dir, i)
        if not os.path.isfile(relit):
            raise OutputError(f"The relit frame {relit} is missing; run again to finish it.")
        name = numbered_name("relit", numbers[i], digits)
        publish(relit, os.path.join(str(out_dir), name))
        written.append(name)
        matte_file = pipeline.matte_path(out_dir, i)
        if matte and os.path.isfile(matte_file):
            publish(matte_file, os.path.join(str(out_dir), numbered_name("matte", numbers[i],
                                                                         digits)))
    return written
