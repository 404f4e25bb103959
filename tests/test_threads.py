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
        try:
            ok = list(pmap(abs, range(-4, 0))) == [4, 3, 2, 1]
        finally:
            os._exit(0 if ok else 1)
    _, status = os.waitpid(pid, 0)
    assert os.WIFEXITED(status) and os.WEXITSTATUS(status) == 0
