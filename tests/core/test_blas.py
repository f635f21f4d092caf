"""numpy's BLAS held to one thread while a frame is relit (addon/blas.py)."""

import sys
import threading

import numpy as np
import pytest

from addon import blas, intrinsic, lightvec, portrait
from addon.errors import DependencyError

needs_blas = pytest.mark.skipif(not blas.threads(), reason="numpy has no BLAS library that "
                                "threadpoolctl can set here")


@pytest.fixture
def two_threads():
    """numpy's BLAS on two threads for the test (this machine's default may be one)."""
    from threadpoolctl import threadpool_limits
    with threadpool_limits(limits=2, user_api="blas"):
        yield


@needs_blas
def test_one_thread_inside_and_the_setting_given_back(two_threads):
    assert blas.threads()[0] == 2
    with blas.one_thread():
        assert set(blas.threads()) == {1}
        with blas.one_thread():  # nested
            assert set(blas.threads()) == {1}
        assert set(blas.threads()) == {1}
    assert blas.threads()[0] == 2


@needs_blas
def test_the_setting_is_given_back_after_an_error(two_threads):
    with pytest.raises(ValueError):
        with blas.one_thread():
            raise ValueError("boom")
    assert blas.threads()[0] == 2


@needs_blas
def test_overlapping_threads_share_one_limit(two_threads):
    """Thread A enters, B enters, A leaves while B is inside: B still runs on one thread, and
    the earlier setting is back only after B leaves (a plain save-and-restore per caller would
    restore A's saved 2 under B, then B's saved 1 for good)."""
    a_in, b_in, a_out, seen = threading.Event(), threading.Event(), threading.Event(), {}

    def a():
        with blas.one_thread():
            a_in.set()
            b_in.wait(5)
        a_out.set()

    def b():
        a_in.wait(5)
        with blas.one_thread():
            b_in.set()
            a_out.wait(5)
            seen["b_after_a_left"] = blas.threads()

    ts = [threading.Thread(target=a), threading.Thread(target=b)]
    for t in ts:
        t.start()
    for t in ts:
        t.join(10)
    assert set(seen["b_after_a_left"]) == {1}
    assert blas.threads()[0] == 2


@needs_blas
def test_relight_frame_and_find_box_run_on_one_thread(two_threads, monkeypatch):
    seen = []
    shade = intrinsic.shade

    def spy(*args, **kwargs):
        seen.append(tuple(blas.threads()))
        return shade(*args, **kwargs)

    monkeypatch.setattr(intrinsic, "shade", spy)

    class Card:
        working_size = 32
        classes = ("background", "foreground", "skin")

    class Session:  # a flat, camera-facing portrait filling the frame
        card = Card()

        def run_planar(self, x, mirror=False):
            h, w = x.shape[1:]
            n = np.zeros((3, h, w), np.float32)
            n[2] = 1.0
            parsing = np.zeros((3, h, w), np.float32)
            parsing[1, 4:-4, 4:-4] = 1.0
            parsing[2, 8:-8, 8:-8] = 1.0
            from types import SimpleNamespace
            return SimpleNamespace(normal=n, height=np.zeros((h, w), np.float32),
                                   albedo=np.full((3, h, w), 0.5, np.float32), parsing=parsing,
                                   transfer=None)

    x = np.full((3, 48, 48), 0.3, np.float32)
    box = portrait.find_box(Session(), x)
    assert box is not None
    portrait.relight_frame(Session(), x, lightvec.splat_direction([0.5, 0.2, 0.8], [2, 2, 2]),
                           box)
    assert seen and all(set(s) == {1} for s in seen)
    assert blas.threads()[0] == 2


@needs_blas
def test_left_alone_changes_nothing(two_threads):
    with blas.left_alone():
        with blas.one_thread():
            assert blas.threads()[0] == 2
    with blas.one_thread():
        assert set(blas.threads()) == {1}


def test_a_missing_threadpoolctl_says_to_reinstall(monkeypatch):
    monkeypatch.setitem(blas._STATE, "controller", None)
    monkeypatch.setitem(sys.modules, "threadpoolctl", None)
    with pytest.raises(DependencyError, match="reinstall the extension"):
        with blas.one_thread():
            pass
    assert blas._STATE["depth"] == 0
