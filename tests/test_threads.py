"""cbh/pipeline/threads.py: the per-pair thread pools."""
from __future__ import annotations

import os
import threading

import cv2
import pytest

from cbh.pipeline.threads import pmap, workers


def test_pmap_keeps_order_and_raises():
    assert list(pmap(lambda x: x * x, range(20))) == [x * x for x in range(20)]

    def boom(x):
        if x == 3:
            raise ValueError("three")
        return x

    with pytest.raises(ValueError, match="three"):
        list(pmap(boom, range(6)))


def test_one_opencv_thread_runs_inline():
    """A one-CPU Ray actor sets cv2.setNumThreads(1): the pipeline must then use one thread."""
    old = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        assert workers() == 1
        assert set(pmap(lambda _: threading.get_ident(), range(8))) == {threading.get_ident()}
    finally:
        cv2.setNumThreads(old)


@pytest.mark.skipif(not hasattr(os, "fork") or cv2.getNumThreads() < 2, reason="needs fork and 2 threads")
def test_a_forked_child_gets_pools_of_its_own():
    list(pmap(abs, range(4)))  # the parent's pools exist
    pid = os.fork()
    if pid == 0:  # child: the inherited pools have no threads; pmap must not hang
        import signal

        signal.alarm(20)  # a hang ends the child by SIGALRM: the test fails instead of hanging
        try:
            ok = list(pmap(abs, range(-4, 0))) == [4, 3, 2, 1]
        finally:
            os._exit(0 if ok else 1)
    _, status = os.waitpid(pid, 0)
    assert os.WIFEXITED(status) and os.WEXITSTATUS(status) == 0


def test_pools_grow_while_other_threads_map():
    """A pool that grows (a caller asks for more threads than it has) is replaced; a caller that
    got the old one must still be able to submit (it was: 'cannot schedule new futures after
    shutdown', 10 in 8000 calls, when a third matcher grew the stages pool under the look-ahead)."""
    from concurrent.futures import ThreadPoolExecutor

    from cbh.pipeline import threads as T

    old = cv2.getNumThreads()
    cv2.setNumThreads(8)
    errors = []

    def caller(k):
        for i in range(300):
            try:
                assert list(pmap(abs, range(-(2 + (i + k) % 7), 0), pool=f"grow{i % 5}")) == list(range(2 + (i + k) % 7, 0, -1))
            except Exception as e:  # noqa: BLE001 - counted
                errors.append(repr(e))
            if i % 50 == 0:
                with T._lock:
                    for name in [p for p in T._pools if p.startswith("grow")]:
                        T._pools.pop(name)[0].shutdown(wait=False)  # force regrowth
    try:
        with ThreadPoolExecutor(4) as ex:
            list(ex.map(caller, range(4)))
    finally:
        cv2.setNumThreads(old)
    assert not errors, errors[:3]


@pytest.mark.parametrize("n", [1, 2, 3, 5])
def test_pfold_folds_contiguous_chunks_and_merges_them_in_order(monkeypatch, n):
    import cbh.pipeline.threads as th

    monkeypatch.setattr(th, "workers", lambda: n)
    seen = []

    def fold(chunk, start):
        seen.append((start, len(chunk)))
        return [f"{start + i}:{x}" for i, x in enumerate(chunk)]

    assert th.pfold(fold, "abcdefg", lambda a, b: a + b) == [f"{i}:{c}" for i, c in enumerate("abcdefg")]
    assert sorted(seen)[0][0] == 0 and sum(k for _, k in seen) == 7 and len(seen) == min(n, 7)


@pytest.mark.parametrize("n", [2, 3, 4])
@pytest.mark.parametrize("neighbours", [True, False])
def test_chunked_best_plane_equals_the_serial_one(monkeypatch, n, neighbours):
    """The sweep's best-plane reduction in chunks side by side gives the serial result exactly:
    ties keep the first plane, and a winner on a chunk's edge gets its neighbours from the next
    and the previous chunk (the parabola refinement reads them)."""
    import numpy as np

    import cbh.pipeline.threads as th
    from cbh.pipeline.sweep import _best3, _best3_map

    monkeypatch.setattr(th, "workers", lambda: n)
    rng = np.random.default_rng(n)
    stack = rng.integers(0, 4, size=(9, 6, 7)).astype(np.float32)  # few levels: many ties
    want = _best3(list(stack), neighbours)
    got = _best3_map(lambda x: x, list(stack), neighbours)
    P = len(stack)
    inner = (want[0] > 0) & (want[0] < P - 1)  # the ends' neighbours are not defined (the refinement skips them)
    np.testing.assert_array_equal(got[0], want[0])
    np.testing.assert_array_equal(got[1], want[1])
    if neighbours:
        np.testing.assert_array_equal(got[2][inner], want[2][inner])
        np.testing.assert_array_equal(got[3][inner], want[3][inner])
        j = want[0]
        yy, xx = np.nonzero(inner)
        np.testing.assert_array_equal(got[2][inner], stack[j[inner] - 1, yy, xx])
        np.testing.assert_array_equal(got[3][inner], stack[j[inner] + 1, yy, xx])
