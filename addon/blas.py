"""numpy's BLAS on one thread while a frame is relit.

The renderer's matrix products are small (nine spherical-harmonic coefficients fitted over a
crop's pixels, a Gaussian blur of a 128-pixel crop as two matrix products), too small for
OpenBLAS's worker threads to pay for themselves; and where the other cores are busy (the
pipeline's own decode and write threads, another job) those threads wait on each other and a
frame's renderer ran many times slower (``python -m bench.intrinsic_speed`` runs a 1080p clip
and relight_frame both ways in one run). ``one_thread()`` holds numpy's BLAS to one thread while
any caller is inside it and gives back the earlier setting when the last leaves. The limit is
the process's, so the pipeline's decode and write threads run under it too, and nested or
concurrent callers share one. threadpoolctl does the work;
where numpy has no BLAS library it can set (a build without one), nothing changes.
"""

from __future__ import annotations

import contextlib
import importlib
import threading

from .errors import DependencyError

_LOCK = threading.Lock()
_STATE = {"depth": 0, "limiter": None, "controller": None, "module": None, "held": True}


def _controller():
    """threadpoolctl's controller of the loaded BLAS libraries, found once (under a ms)."""
    if _STATE["controller"] is None:
        try:
            import threadpoolctl
        except ImportError as err:  # the extension still loads and can say what is missing
            raise DependencyError("threadpoolctl is not installed; reinstall the extension "
                                  f"({err}).") from err
        importlib.import_module("numpy")  # its BLAS loaded before threadpoolctl looks for it
        _STATE["module"] = threadpoolctl
        _STATE["controller"] = threadpoolctl.ThreadpoolController()
    return _STATE["controller"]


def _release() -> None:
    """OpenBLAS's thread pool is the process's, so threadpoolctl lets only the thread that
    first set it set it again (others silently do nothing) until that thread lets go. This
    module's lock already orders its callers: let go, so that whichever thread is next, sets."""
    openblas = getattr(_STATE["module"], "OpenBLASController", None)
    if openblas is not None and hasattr(openblas, "clear_controlling_thread"):
        openblas.clear_controlling_thread(force=True)


@contextlib.contextmanager
def one_thread():
    """Hold numpy's BLAS to one thread inside the block (also a decorator)."""
    if not _STATE["held"]:
        yield
        return
    with _LOCK:
        if _STATE["depth"] == 0:
            controller = _controller()
            _release()
            _STATE["limiter"] = controller.limit(limits=1, user_api="blas")
            _release()
        _STATE["depth"] += 1
    try:
        yield
    finally:
        with _LOCK:
            _STATE["depth"] -= 1
            if _STATE["depth"] == 0:
                _release()
                _STATE["limiter"].restore_original_limits()
                _release()
                _STATE["limiter"] = None


@contextlib.contextmanager
def left_alone():
    """Inside the block, one_thread() changes nothing (the benchmarks' comparison)."""
    was, _STATE["held"] = _STATE["held"], False
    try:
        yield
    finally:
        _STATE["held"] = was


def threads() -> list[int]:
    """The thread counts numpy's BLAS libraries use now (empty: none found)."""
    return [int(lib["num_threads"]) for lib in _controller().select(user_api="blas").info()]
