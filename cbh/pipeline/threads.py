"""Threads for the per-pair work: the planes of the sweep, the two cameras, the matchers.

Why threads: the pipeline's work is many OpenCV calls on images of 0.1–1 MPixel, which OpenCV's
own pool splits poorly (a fine sweep plane at 960 px: 3.3 ms wall with its 2 threads against
4.0 ms with one, measured on 2 cores), and OpenCV releases the GIL. Two planes at once on two
threads take 2.6 ms per plane; two cameras' segmentations likewise.

How many: ``cv2.getNumThreads()`` (the machine's cores unless set), at most ``MAX_THREADS``.
Where OpenCV is held to one thread (a one-CPU Ray actor: ``cv2.setNumThreads(1)``) everything
runs inline in the caller: whoever runs the pipeline decides how many cores a pair gets.

Separate pools per level (``pool="planes"`` inside a stage, ``pool="stages"`` across cameras
and matchers), so that a task of one pool that waits for tasks of the other never starves it.
"""
from __future__ import annotations

import os
import threading
from concurrent.futures import ThreadPoolExecutor

import cv2

__all__ = ["pmap", "pfold", "workers", "MAX_THREADS"]

MAX_THREADS = 8
_lock = threading.Lock()
_pools: dict[str, tuple[ThreadPoolExecutor, int]] = {}
_owner = [os.getpid()]


def _after_fork_in_child() -> None:  # the lock may have been held by a thread that does not exist here
    global _lock
    _lock = threading.Lock()


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_after_fork_in_child)


def workers() -> int:
    """Threads a pair may use: ``cv2.getNumThreads()``, 1 … ``MAX_THREADS``."""
    return min(max(cv2.getNumThreads(), 1), MAX_THREADS)


def pmap(fn, items, pool: str = "planes"):
    """``map(fn, items)`` in order, on up to :func:`workers` threads of the named pool.

    Returns an iterator, so the caller reduces results while later items are still computed.
    Inline (plain ``map``) where only one thread is allowed or there is one item.
    """
    items = list(items)
    n = min(workers(), len(items))
    if n <= 1:
        return map(fn, items)
    with _lock:
        if _owner[0] != os.getpid():  # a forked child inherits the pools but not their threads
            _pools.clear()
            _owner[0] = os.getpid()
        ex, size = _pools.get(pool, (None, 0))
        if size < n:
            if ex is not None:
                ex.shutdown(wait=False)  # under the lock: no caller holds it between getting it and map()
            ex = ThreadPoolExecutor(n, thread_name_prefix=f"cbh-{pool}")
            _pools[pool] = (ex, n)
        return ex.map(fn, items)  # submits every item now (map's iterator only waits for results)


def pfold(fold, items, merge, pool: str = "planes"):
    """Fold contiguous chunks of ``items`` side by side and merge the partial results in order.

    ``fold(chunk, start)`` reduces one chunk (a list; ``start`` is its first item's index) on a
    thread of the pool, one chunk per worker; ``merge(a, b)`` combines the partial results of two
    neighbouring chunks (a before b). Why: a per-item task reduced in the caller leaves the
    reduction serial and costs a hand-over per item (for the sweep's half-size planes the
    reduction's masked copies cost as much as the plane's own box filter); per chunk, each thread
    reduces its own planes and only ``workers() − 1`` merges are left.
    """
    items = list(items)
    n = min(workers(), len(items))
    if n <= 1:
        return fold(items, 0)
    bounds = [round(i * len(items) / n) for i in range(n + 1)]
    parts = pmap(lambda c: fold(items[bounds[c]: bounds[c + 1]], bounds[c]), range(n), pool=pool)
    out = next(parts)
    for p in parts:
        out = merge(out, p)
    return out
