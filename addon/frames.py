"""Frame I/O: probe and decode movie files and image sequences, write half-float EXR.

Decoding returns the file's own code values (uint8, uint16 or float32; (H, W, 3), or (3, H, W)
with ``planar=True``, the pipeline's layout); colour.py turns them into scene linear. Movies go through PyAV sequentially after one seek to the first needed
frame (frame-accurate: frames before the target are decoded and dropped). PNG/JPEG go through
PyAV's image decoders, EXR through the OpenEXR module.

EXR output is written to a temporary name and renamed into place, so a killed run never leaves a
half-written frame under its final name (partial_path names the writer, so a later run can sweep
a dead writer's leftovers). Uncompressed half EXR is written directly from channels-first planes
(write_exr_planes); the compressions go through OpenEXR. Compression is a speed/size trade,
measured on the project's 2-core machine for one 1080p frame, each option in turn (`python -m
bench.pipeline_1080p --exr-options`, load average 5): none 3.3 ms CPU / 12.5 MB (11 ms through
OpenEXR's frame buffer), RLE 36 ms / 11.5 MB, PIZ 38 ms / 3.6 MB (a smooth synthetic frame;
footage compresses less), ZIPS 89 ms / 8.1 MB, ZIP 117 ms / 7.5 MB; the wall time of a write adds
the kernel's page-cache work, which varies with other processes' I/O. Uncompressed is the
default because a write slower than the network would cap the frame rate.
"""

from __future__ import annotations

import os
import pathlib
import re
import socket
import struct
import sys
import threading
from dataclasses import dataclass

import numpy as np

from .errors import DependencyError, InputError, OutputError

# Image sequences by extension (EXR through OpenEXR, the others through PyAV/FFmpeg); any other
# single file is opened as a movie, so every container FFmpeg reads (MXF, MOV with ProRes or
# DNxHR, MTS, ...) is footage.
IMAGE_EXTS = (".png", ".jpg", ".jpeg", ".exr", ".tif", ".tiff", ".dpx", ".bmp", ".webp")
VFR_TOLERANCE = 0.02  # frame durations varying more than this share mean a variable frame rate
VFR_PACKETS = 300     # packets looked at to tell
HALF_MAX = 65504.0
COMPRESSIONS = ("none", "rle", "zips", "zip", "piz")
DAMAGED = ("The file is damaged or not an image: replace it with an intact copy (re-render or "
           "re-export the frame), or trim the strip to leave it out.")


@dataclass(frozen=True)
class ClipInfo:
    kind: str                  # 'movie' | 'images'
    path: str                  # the movie file, or the folder of the sequence
    files: tuple[str, ...]     # the sequence's files in frame order (empty for movies)
    width: int
    height: int
    frame_count: int
    fps: float                 # 0.0 when the files do not say (image sequences)
    channels: int              # channels stored in the file (1 grey, 2 grey+alpha, 3, 4)
    has_alpha: bool
    bit_depth: int             # 8, 10, 12, 16 (integer) or 16/32 for EXR half/float


def _av():
    try:
        import av
    except ImportError as err:
        raise DependencyError(f"PyAV is not installed; reinstall the extension ({err}).") from err
    return av


def _exr():
    try:
        import OpenEXR
    except ImportError as err:
        raise DependencyError(f"OpenEXR is not installed; reinstall the extension ({err}).") \
            from err
    return OpenEXR


# ---- image sequences ----------------------------------------------------------------------

_NUMBER = re.compile(r"^(.*?)(\d+)$")


def frame_number(path) -> tuple[str, int] | None:
    """(prefix, number) of a sequence file name like 'shot_0042.png', or None."""
    m = _NUMBER.match(pathlib.Path(path).stem)
    return (m.group(1), int(m.group(2))) if m else None


def check_sequence(files) -> None:
    """Raise InputError naming the frames a numbered sequence lacks (missing files or gaps)."""
    absent = [f for f in files if not os.path.isfile(f)]
    if absent:
        nums = [frame_number(f) for f in absent]
        names = ", ".join(str(n[1]) if n else os.path.basename(f) for f, n in zip(absent, nums))
        raise InputError(f"The image sequence is missing {len(absent)} file(s): frames {names} "
                         f"(e.g. {absent[0]}). Restore them or trim the strip to skip them.")
    parsed = [frame_number(f) for f in files]
    if len(files) < 2 or any(p is None for p in parsed):
        return
    prefixes = {p[0] for p in parsed}
    nums = [p[1] for p in parsed]
    if len(prefixes) != 1 or len(set(nums)) != len(nums):
        return  # not one numbered sequence: the caller's order is all there is
    steps = np.diff(sorted(nums))
    step = int(np.min(steps))
    missing = sorted(set(range(min(nums), max(nums) + 1, step)) - set(nums))
    if missing:
        shown = ", ".join(map(str, missing[:20])) + (" ..." if len(missing) > 20 else "")
        raise InputError(f"The image sequence has {len(missing)} missing frame(s): {shown}. "
                         "Render or restore them, or trim the strip to a complete range.")


def list_sequence(folder) -> tuple[str, ...]:
    """The files of the largest numbered image sequence in ``folder``, in frame order."""
    folder = pathlib.Path(folder)
    groups: dict[tuple[str, str], list[tuple[int, str]]] = {}
    for p in folder.iterdir():
        if p.suffix.lower() in IMAGE_EXTS and p.is_file():
            fn = frame_number(p)
            if fn:
                groups.setdefault((fn[0], p.suffix.lower()), []).append((fn[1], str(p)))
    if not groups:
        raise InputError(f"{folder} holds no numbered image frames ({', '.join(IMAGE_EXTS)}).")
    best = max(groups.values(), key=len)
    return tuple(f for _, f in sorted(best))


def _is_exr(path) -> bool:
    return str(path).lower().endswith(".exr")


def _exr_rgb_names(names) -> tuple[list[str], bool]:
    """The channel names holding R, G, B (or one grey channel) and whether alpha is present."""
    names = list(names)
    for prefix in [""] + sorted({n.rsplit(".", 1)[0] + "." for n in names if "." in n}):
        rgb = [prefix + c for c in "RGB"]
        if all(c in names for c in rgb):
            return rgb, prefix + "A" in names
    for grey in ("Y", "L", "V"):
        if grey in names:
            return [grey], "A" in names
    raise InputError(f"The EXR has channels {sorted(names)}; the relighter needs R, G, B (or Y).")


def _read_exr(path, planar: bool = False) -> tuple[np.ndarray, bool]:
    """(float32 (H, W, 3) pixels, or (3, H, W) when ``planar``, had_alpha)."""
    OpenEXR = _exr()
    try:
        with OpenEXR.File(str(path), separate_channels=True) as f:
            chans = f.channels()
            names, alpha = _exr_rgb_names(chans.keys())
            planes = [np.asarray(chans[n].pixels, dtype=np.float32) for n in names]
    except InputError:
        raise
    except Exception as err:  # OpenEXR raises plain RuntimeError for unreadable files
        raise InputError(f"Cannot read the EXR file {path} ({err}). {DAMAGED}") from err
    if len(planes) == 1:
        planes = planes * 3
    return np.stack(planes, axis=0 if planar else -1), alpha


def _frame_alpha(fmt) -> bool:
    return any(c.is_alpha for c in fmt.components)


def _deep(fmt) -> bool:
    return max(c.bits for c in fmt.components) > 8


def _quarter_turns(frame) -> int:
    """Counter-clockwise quarter turns that show the frame upright, from its display matrix
    (a phone's rotate=90 tag): what FFmpeg's own autorotation does."""
    try:
        angle = float(frame.rotation or 0)
    except (AttributeError, TypeError, ValueError):
        return 0
    return int(round(angle / 90.0)) % 4


def _to_rgb(frame) -> np.ndarray:
    """Decoded PyAV frame -> (H, W, 3) uint8, or uint16 for sources deeper than 8 bits, turned
    upright by the stream's display rotation."""
    rgb = frame.to_ndarray(format="rgb48le" if _deep(frame.format) else "rgb24")
    k = _quarter_turns(frame)
    return np.ascontiguousarray(np.rot90(rgb, k)) if k else rgb


def _to_planes(frame) -> np.ndarray:
    """Decoded PyAV frame -> (3, H, W) RGB planes, uint8 (uint16 if deeper than 8 bits).

    Through interleaved RGB and one transposing copy of the code values (1.5 ms at 1080p): the
    pipeline then works channels-first up to the EXR write. (swscale's own planar 'gbrp' output
    would save that copy, but PyAV 18's FFmpeg leaves garbage at the right edge of rows whose
    width is not a multiple of 16; tests/core/test_frames.py checks odd widths.)"""
    return np.ascontiguousarray(_to_rgb(frame).transpose(2, 0, 1))


def _read_image(path, planar: bool = False) -> tuple[np.ndarray, bool]:
    if _is_exr(path):
        return _read_exr(path, planar)
    av = _av()
    try:
        with av.open(str(path)) as c:
            frame = next(c.decode(video=0))
            return (_to_planes if planar else _to_rgb)(frame), _frame_alpha(frame.format)
    except (av.FFmpegError, StopIteration, OSError) as err:
        raise InputError(f"Cannot read the image {path} ({err}). {DAMAGED}") from err


def _probe_image(path) -> tuple[int, int, int, bool, int]:
    """(width, height, channels, has_alpha, bit_depth) of one image file."""
    if _is_exr(path):
        OpenEXR = _exr()
        try:
            f = OpenEXR.File(str(path), header_only=True)
            h = f.header()
            names = [c.name for c in h["channels"]]
            (x0, y0), (x1, y1) = h["dataWindow"]
        except Exception as err:
            raise InputError(f"Cannot read the EXR file {path} ({err}).") from err
        rgb, alpha = _exr_rgb_names(names)
        return int(x1 - x0 + 1), int(y1 - y0 + 1), len(rgb) + int(alpha), alpha, 16  # or 32
    av = _av()
    try:
        with av.open(str(path)) as c:
            s = c.streams.video[0]
            fmt = s.codec_context.format
            return (s.codec_context.width, s.codec_context.height, len(fmt.components),
                    _frame_alpha(fmt), max(c.bits for c in fmt.components))
    except (av.FFmpegError, IndexError, OSError) as err:
        raise InputError(f"Cannot read the image {path} ({err}).") from err


# ---- movies -------------------------------------------------------------------------------

def _open_movie(path):
    av = _av()
    if not os.path.isfile(path):
        raise InputError(f"The movie file {path} does not exist.")
    try:
        c = av.open(str(path))
    except (av.FFmpegError, OSError) as err:
        raise InputError(f"Cannot open {path}: it is not footage the relighter reads ({err}); "
                         "it reads movies "
                         "FFmpeg can decode and image sequences "
                         f"({', '.join(IMAGE_EXTS)}).") from err
    if not c.streams.video:
        c.close()
        raise InputError(f"{path} has no video stream (sound only?); pick a movie strip.")
    return c


def _stream_fps(s) -> float:
    rate = s.average_rate or s.guessed_rate or s.base_rate
    return float(rate) if rate else 0.0


def _probe_movie(path) -> ClipInfo:
    av = _av()
    with _open_movie(path) as c:
        s = c.streams.video[0]
        fps = _stream_fps(s)
        count = s.frames
        cc = s.codec_context
        fmt = cc.format
        if fmt is None or not cc.width:
            raise InputError(f"Cannot read the video format of {path}.")
        _refuse_variable_rate(c, s, path)
        c.seek(0)
        if not count:  # some containers do not store it: count packets (no decoding)
            count = sum(1 for p in c.demux(s) if p.size)
            c.seek(0)
        try:
            turns = _quarter_turns(next(c.decode(s)))
        except (av.FFmpegError, StopIteration) as err:
            raise InputError(f"Cannot decode the movie {path} ({err}): the file is damaged or "
                             "its codec is not supported. Re-encode or re-export it.") from err
        w, h = (cc.height, cc.width) if turns % 2 else (cc.width, cc.height)
        return ClipInfo("movie", str(path), (), w, h, int(count), fps,
                        len(fmt.components), _frame_alpha(fmt),
                        max(comp.bits for comp in fmt.components))


def _refuse_variable_rate(c, s, path) -> None:
    """InputError for a movie whose frames do not come at one rate (phone footage often does):
    Blender and the relighter step through frames at the strip's constant rate, so such a clip's
    frames would drift against its timing. Looks at the first VFR_PACKETS packets' times."""
    pts = []
    for p in c.demux(s):
        if p.pts is not None and p.size:
            pts.append(int(p.pts))
        if len(pts) >= VFR_PACKETS:
            break
    if len(pts) < 3:
        return
    d = np.diff(np.unique(np.asarray(pts, np.int64)))
    if d.size < 2:
        return
    typical = float(np.median(d))
    if typical > 0 and float(np.max(np.abs(d - typical))) > VFR_TOLERANCE * typical:
        tb = float(s.time_base) if s.time_base else 0.0
        lo, hi = float(d.min()) * tb * 1000, float(d.max()) * tb * 1000
        raise InputError(
            f"{pathlib.Path(path).name} has a variable frame rate (frames last {lo:.1f} to "
            f"{hi:.1f} ms); Blender and the relighter step through frames at one rate, so its "
            "frames would drift. Convert it to a constant rate first, e.g. `ffmpeg -i IN "
            "-fps_mode cfr -r 30 -c:v prores_ks OUT.mov`, and import that.")


def _pts_to_index(pts, start, time_base, fps) -> int:
    return int(round(float((pts - start) * time_base) * fps))


SEEK_GAP = 48  # re-seek rather than decode more than this many unwanted frames


def _index_runs(indices: list[int]) -> list[list[int]]:
    """Split sorted indices into runs decoded after one seek each."""
    runs: list[list[int]] = []
    for i in indices:
        if runs and i - runs[-1][-1] <= SEEK_GAP:
            runs[-1].append(i)
        else:
            runs.append([i])
    return runs


def iter_movie(path, indices, planar: bool = False, name=None):
    """Yield (index, pixels) for the 0-based ``indices`` in increasing order: a seek to the first
    of each run of nearby indices, then sequential decoding (frames before a target are decoded
    and dropped, so every frame is exact). Pixels are (H, W, 3), or (3, H, W) when ``planar``.
    Raises InputError if the movie ends too early or cannot be decoded; ``name(index)`` says
    how messages name a frame (see iter_frames)."""
    indices = sorted(set(int(i) for i in indices))
    if not indices:
        return
    name = name or _source_frame
    av = _av()
    with _open_movie(path) as c:
        s = c.streams.video[0]
        s.thread_type = "AUTO"
        fps = _stream_fps(s)
        start = s.start_time or 0
        for run in _index_runs(indices):
            state = {"target": run[0]}
            try:
                yield from _decode_run(c, s, run, fps, start, path,
                                       _to_planes if planar else _to_rgb, state, name)
            except av.FFmpegError as err:
                raise InputError(
                    f"Cannot decode the movie {path} at {name(state['target'])} ({err}): the "
                    "file is damaged. Re-encode or re-export it, or trim the strip to leave "
                    "the damaged part out.") from err


def _source_frame(i: int) -> str:
    return f"source frame {int(i)} (0-based)"


def _decode_run(c, s, run, fps, start, path, convert, state, name):
    want = iter(run)
    target = next(want)
    if target > 0 and fps:
        c.seek(start + int(target / fps / s.time_base), stream=s, backward=True, any_frame=False)
    else:
        c.seek(start, stream=s, backward=True, any_frame=False)
    decoded = 0
    for frame in c.decode(s):
        idx = (_pts_to_index(frame.pts, start, s.time_base, fps)
               if frame.pts is not None and fps else decoded)
        decoded += 1
        if idx < target:
            continue
        if idx > target:
            raise InputError(f"The movie {path} skips {name(target)} (the stream jumps to "
                             f"source frame {idx}); re-encode the movie.")
        yield idx, convert(frame)
        target = state["target"] = next(want, None)
        if target is None:
            return
    raise InputError(f"The movie {path} ended before {name(target)}; the strip is longer "
                     "than the file. Trim the strip to the movie's length.")


# ---- public ---------------------------------------------------------------------------------

def probe_clip(path_or_files) -> ClipInfo:
    """Describe a movie file, a folder holding a numbered sequence, or an ordered list of image
    files. Raises InputError with a clear message for anything else."""
    if isinstance(path_or_files, (list, tuple)):
        files = tuple(str(f) for f in path_or_files)
        if not files:
            raise InputError("The image sequence is empty.")
        folder = str(pathlib.Path(files[0]).parent)
    else:
        p = pathlib.Path(path_or_files)
        if p.is_dir():
            files, folder = list_sequence(p), str(p)
        elif not p.exists():
            raise InputError(f"{p} does not exist.")
        elif p.suffix.lower() in IMAGE_EXTS:
            files, folder = (str(p),), str(p.parent)
        else:
            return _probe_movie(p)  # any container FFmpeg reads
    bad = [f for f in files if pathlib.Path(f).suffix.lower() not in IMAGE_EXTS]
    if bad:
        raise InputError(f"{bad[0]} is not an image the relighter reads as part of a sequence "
                         f"({', '.join(IMAGE_EXTS)}).")
    check_sequence(files)
    w, h, ch, alpha, bits = _probe_image(files[0])
    return ClipInfo("images", folder, files, w, h, len(files), 0.0, ch, alpha, bits)


@dataclass(frozen=True)
class Decoded:
    index: int
    pixels: np.ndarray         # (H, W, 3) or planar (3, H, W) uint8 / uint16 / float32 codes
    had_alpha: bool


def iter_frames(kind: str, path: str, files, indices, size: tuple[int, int] | None = None,
                planar: bool = False, name=None):
    """Yield Decoded frames for sorted 0-based ``indices`` of a movie or an image sequence.

    ``size`` (width, height): every frame must have it (a sequence that changes size mid-way
    is refused rather than stretched). ``planar``: pixels channels-first (3, H, W). ``name``:
    source index -> how messages name that frame (the pipeline gives scene frames); every
    message names the file and says what to do."""
    name = name or _source_frame
    if kind == "movie":
        source = ((i, px, False, path) for i, px in iter_movie(path, indices, planar, name))
    elif kind == "images":
        def _images():
            for i in sorted(indices):
                if not 0 <= i < len(files):
                    raise InputError(f"The image sequence has {len(files)} frames; "
                                     f"{name(i)} is not one of them. Trim the strip to the "
                                     "images it has.")
                try:
                    px, alpha = _read_image(files[i], planar)
                except InputError as err:
                    raise InputError(f"{_capital(name(i))}: {err}") from err
                yield i, px, alpha, files[i]
        source = _images()
    else:
        raise InputError(f"Unknown clip kind '{kind}' (expected 'movie' or 'images').")
    for i, px, alpha, file in source:
        h, w = px.shape[1:] if planar else px.shape[:2]
        if size is not None and (w, h) != tuple(size):
            raise InputError(
                f"{_capital(name(i))} ({file}) is {w}x{h}, but the clip is {size[0]}x{size[1]}: "
                "every frame of a clip must have one size. Re-export the sequence at one size, "
                "or trim the strip to the frames of one size.")
        yield Decoded(i, px, alpha)


def _capital(text: str) -> str:
    return text[:1].upper() + text[1:]


def to_half(rgb: np.ndarray) -> tuple[np.ndarray, int]:
    """float -> contiguous float16 with NaN -> 0 and values clamped to [-65504, 65504]; returns
    (pixels, number of values that were non-finite or out of half range)."""
    x = np.asarray(rgb, dtype=np.float32)
    bad = ~np.isfinite(x)
    over = np.abs(x) > HALF_MAX
    n = int(np.count_nonzero(bad | over))
    if n:
        x = np.nan_to_num(x, nan=0.0, posinf=HALF_MAX, neginf=-HALF_MAX)
        x = np.clip(x, -HALF_MAX, HALF_MAX)
    return np.ascontiguousarray(x.astype(np.float16)), n


def _compression(OpenEXR, name: str):
    if name not in COMPRESSIONS:
        raise ValueError(f"EXR compression must be one of {COMPRESSIONS}, got {name!r}")
    return getattr(OpenEXR, "NO_COMPRESSION" if name == "none" else f"{name.upper()}_COMPRESSION")


# Rec.709 primaries and D65 white (x, y of red, green, blue, white): what scene-linear RGB files
# written here hold, stated in the file so other tools read them as such.
REC709_CHROMATICITIES = (0.64, 0.33, 0.30, 0.60, 0.15, 0.06, 0.3127, 0.3290)


def write_exr(path, pixels: np.ndarray, compression: str = "none") -> int:
    """Write a half-float EXR atomically: (H, W, 3) -> R, G, B; (H, W) -> Y. Returns the number of
    values clamped to the half range (see to_half). float16 input is written as it is."""
    OpenEXR = _exr()
    px = np.asarray(pixels)
    if px.dtype == np.float16 and px.flags.c_contiguous:
        n = 0
    else:
        px, n = to_half(px)
    if px.ndim == 3 and px.shape[2] == 3:
        channels = {"RGB": px}
    elif px.ndim == 2:
        channels = {"Y": px}
    else:
        raise ValueError(f"pixels must be (H, W, 3) or (H, W), got {px.shape}")
    header = {"compression": _compression(OpenEXR, compression), "type": OpenEXR.scanlineimage}
    if "RGB" in channels:
        header["chromaticities"] = REC709_CHROMATICITIES
    write_atomic(path, lambda tmp: _openexr_write(OpenEXR, tmp, header, channels))
    return n


def write_exr_planes(path, planes: np.ndarray, compression: str = "none") -> None:
    """Write channels-first half pixels atomically: (3, H, W) -> R, G, B; (H, W) -> Y.

    Uncompressed files are written here directly (the format is a header, a line offset table
    and per scanline the channels' halves in B, G, R order): one copy into file order, no
    OpenEXR frame-buffer pass; the result reads back bit for bit through OpenEXR."""
    px = np.asarray(planes)
    if px.dtype != np.float16:
        raise ValueError(f"planes must be float16, got {px.dtype}")
    if px.ndim == 3 and px.shape[0] == 3:
        names, stored = ("B", "G", "R"), px[::-1]  # EXR stores channels in name order
    elif px.ndim == 2:
        names, stored = ("Y",), px[None]
    else:
        raise ValueError(f"planes must be (3, H, W) or (H, W), got {px.shape}")
    if compression == "none":
        write_atomic(path, lambda tmp: _write_uncompressed(tmp, stored, names))
        return
    OpenEXR = _exr()
    header = {"compression": _compression(OpenEXR, compression), "type": OpenEXR.scanlineimage}
    if len(names) == 3:
        header["chromaticities"] = REC709_CHROMATICITIES
    channels = {n: np.ascontiguousarray(p) for n, p in zip(names, stored)}  # strides ignored
    write_atomic(path, lambda tmp: _openexr_write(OpenEXR, tmp, header, channels))


def _openexr_write(OpenEXR, tmp: str, header: dict, channels: dict) -> None:
    with OpenEXR.File(header, channels) as f:
        f.write(tmp)


def _attribute(name: str, kind: str, value: bytes) -> bytes:
    return name.encode() + b"\0" + kind.encode() + b"\0" + struct.pack("<i", len(value)) + value


def exr_header(width: int, height: int, names) -> bytes:
    """Magic, version 2 (single-part scanline) and the required attributes of an uncompressed
    half-float image; ``names`` sorted (the spec's channel order). RGB images also state their
    primaries (REC709_CHROMATICITIES)."""
    half, linear, sampling = 1, 0, (1, 1)
    chlist = b"".join(n.encode() + b"\0" + struct.pack("<iB3xii", half, linear, *sampling)
                      for n in names) + b"\0"
    box = struct.pack("<4i", 0, 0, width - 1, height - 1)
    chroma = (_attribute("chromaticities", "chromaticities",
                         struct.pack("<8f", *REC709_CHROMATICITIES)) if len(names) == 3 else b"")
    return (b"\x76\x2f\x31\x01" + struct.pack("<i", 2)
            + _attribute("channels", "chlist", chlist) + chroma
            + _attribute("compression", "compression", b"\0")  # NO_COMPRESSION
            + _attribute("dataWindow", "box2i", box) + _attribute("displayWindow", "box2i", box)
            + _attribute("lineOrder", "lineOrder", b"\0")      # INCREASING_Y
            + _attribute("pixelAspectRatio", "float", struct.pack("<f", 1.0))
            + _attribute("screenWindowCenter", "v2f", struct.pack("<2f", 0.0, 0.0))
            + _attribute("screenWindowWidth", "float", struct.pack("<f", 1.0)) + b"\0")


def _write_uncompressed(tmp: str, stored: np.ndarray, names) -> None:
    """``stored`` (C, H, W) float16 in channel-name order. Scanlines go out in ~1 MB bands
    through one small buffer (a frame-sized one would be fresh memory, page-faulted in, on
    many calls)."""
    c, h, w = stored.shape
    header = exr_header(w, h, names)
    line = 8 + 2 * c * w  # int32 y, int32 byte count, then each channel's row
    offsets = len(header) + 8 * h + line * np.arange(h, dtype="<u8")
    band = max(1, min(h, (1 << 20) // line))
    buf = np.empty((band, line), np.uint8)
    head = buf[:, :8].view("<i4")
    head[:, 1] = 2 * c * w
    rows = buf[:, 8:].view("<f2").reshape(band, c, w)
    with open(tmp, "wb") as f:
        f.write(header)
        f.write(offsets.tobytes())
        for y in range(0, h, band):
            n = min(band, h - y)
            head[:n, 0] = np.arange(y, y + n)
            rows[:n] = stored[:, y:y + n].transpose(1, 0, 2)
            f.write(buf[:n].data)


HOST = re.sub(r"[^A-Za-z0-9-]", "-", socket.gethostname() or "host")
# <final name>.<host>_<pid>_<thread>.partial
_PARTIAL = re.compile(r"^(?P<final>.+?)\.(?P<host>[A-Za-z0-9-]+)_(?P<pid>\d+)_\d+\.partial$")


def partial_path(path) -> str:
    """The temporary name a file is written under before it is renamed into place; it names the
    writing machine and process, so a later run can tell a dead writer's leftovers."""
    return f"{path}.{HOST}_{os.getpid()}_{threading.get_ident()}.partial"


def stale_partial(name: str) -> str | None:
    """The final name of ``name`` if it is a partial file left by a dead process of this machine
    (an interrupted write); None for anything else, including a live writer's file."""
    m = _PARTIAL.match(name)
    if not m:
        return None
    if m.group("host") != HOST:
        return None  # another machine's (shared storage): it may still be writing
    pid = int(m.group("pid"))
    return None if pid == os.getpid() or pid_alive(pid) else m.group("final")


def sweep_stale_partials(folder, pattern) -> list[str]:
    """Remove from ``folder`` the partial files dead processes of this machine left for final
    names matching ``pattern`` (stale_partial); returns the removed paths. A concurrent
    writer's file in progress is kept, and one swept by another process meanwhile is skipped."""
    removed: list[str] = []
    if not os.path.isdir(str(folder)):
        return removed
    for entry in os.scandir(str(folder)):
        final = stale_partial(entry.name)
        if final and pattern.match(final) and entry.is_file(follow_symlinks=False):
            try:
                os.remove(entry.path)
            except FileNotFoundError:
                continue  # another process swept it first
            removed.append(entry.path)
    return removed


def pid_alive(pid: int) -> bool:
    """Whether process ``pid`` of this machine is running."""
    if sys.platform == "win32":  # os.kill(pid, 0) would send Ctrl+C there
        import ctypes
        k32 = ctypes.WinDLL("kernel32", use_last_error=True)
        handle = k32.OpenProcess(0x1000, False, pid)  # PROCESS_QUERY_LIMITED_INFORMATION
        if not handle:
            return ctypes.get_last_error() == 5  # access denied: it exists (another user's)
        code = ctypes.c_ulong()
        ok = k32.GetExitCodeProcess(handle, ctypes.byref(code))
        k32.CloseHandle(handle)
        return bool(ok) and code.value == 259  # STILL_ACTIVE
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True  # exists, another user's
    return True


def write_atomic(path, write) -> None:
    """``write(tmp)``, then rename ``tmp`` to ``path``: a reader never sees half a file, and a
    failure leaves neither file behind (OutputError for an I/O failure). ``tmp`` is
    partial_path(path), so a later run can sweep what a killed writer left. Every file the
    add-on, the benchmarks and training write atomically goes through here."""
    path = str(path)
    tmp = partial_path(path)
    try:
        write(tmp)
        os.replace(tmp, path)
    except (OSError, RuntimeError) as err:  # OpenEXR reports I/O failures as RuntimeError
        _remove_quietly(tmp)
        raise OutputError(f"Cannot write {path} ({err}); check the output folder is writable "
                          "and the disk has space.") from err
    except BaseException:
        _remove_quietly(tmp)
        raise


def _remove_quietly(path) -> None:
    try:
        os.remove(path)
    except FileNotFoundError:
        pass


def read_exr(path) -> np.ndarray:
    """float32 (H, W, 3) pixels of an EXR (grey files come back as three equal channels)."""
    return _read_exr(path)[0]
