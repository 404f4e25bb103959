"""The C allocator's settings for the per-pair work (glibc's malloc only; elsewhere nothing).

Why: a 1920 px pair allocates and frees a few hundred arrays of 0.1–15 MB (images, score and
cost planes, masks). With glibc's defaults the large ones are mmap'd and unmapped each time,
and the top of the heap is given back to the kernel as soon as 128 kB are free there, so every
pair faults many of the same pages in again (6 500–10 700 page faults per pair on the 2-core
development machine). Freed memory is kept in the process instead:

- ``M_MMAP_THRESHOLD`` 64 MB: arrays up to 64 MB come from the heap (glibc's adaptive threshold
  would stop at 32 MB, and only after a first free of each size);
- ``M_TRIM_THRESHOLD`` 512 MB: up to 512 MB free at the heap's top stay mapped;
- ``M_TOP_PAD`` 64 MB: the heap grows in 64 MB steps.

Measured with ``python benchmarks/bench_pipeline.py --repeat 10`` against ``CBH_MALLOC_TUNE=0``,
alternating four times (two-layers, 1920 px, 2026-12-02 03:40): wall 284 / 267 / 256 / 273 ms
per pair against 312 / 293 / 267 / 268 ms (−5 % on the mean), page faults 4 900 against
6 500–10 700, the same peak RSS (1.53 GB, simulator included). A pair's working set is about
the same every pair, so the resident size settles at its peak and stays there
(``benchmarks/bench_soak.py``); a process that once held much more keeps up to 512 MB of it.

Applied once per process by the first :class:`~cbh.pipeline.Pipeline` (so an application
embedding cbh gets it too; ``CBH_MALLOC_TUNE=0`` keeps glibc's defaults). Not applied when the
environment already sets the allocator (``MALLOC_*`` variables, ``glibc.malloc.*`` tunables):
the user's choice wins.
"""
from __future__ import annotations

import ctypes
import os
import threading

__all__ = ["tune_malloc", "MALLOC_SETTINGS"]

# glibc's malloc.h parameter numbers
_M_TRIM_THRESHOLD, _M_TOP_PAD, _M_MMAP_THRESHOLD = -1, -2, -3
MALLOC_SETTINGS = {"M_MMAP_THRESHOLD": 64 << 20, "M_TRIM_THRESHOLD": 512 << 20, "M_TOP_PAD": 64 << 20}
_PARAM = {"M_MMAP_THRESHOLD": _M_MMAP_THRESHOLD, "M_TRIM_THRESHOLD": _M_TRIM_THRESHOLD, "M_TOP_PAD": _M_TOP_PAD}

_lock = threading.Lock()
_state: dict[str, object] = {"done": False, "applied": {}}


def tune_malloc() -> dict[str, int]:
    """Apply :data:`MALLOC_SETTINGS` with glibc's ``mallopt`` (first call per process; later
    calls return what the first applied). Returns the settings applied: empty when not glibc,
    when the environment sets the allocator itself (a ``MALLOC_*`` variable, or
    ``glibc.malloc.*`` in ``GLIBC_TUNABLES``), or with ``CBH_MALLOC_TUNE`` = 0/false/off/no.

    The mmap threshold goes first: a glibc that refuses 64 MB (older ones allow at most
    32 MB) gets 32 MB, and if that fails too nothing else is set (the other two settings also
    switch glibc's adaptive mmap threshold off, which alone would leave it at 128 kB)."""
    with _lock:
        if _state["done"]:
            return dict(_state["applied"])
        _state["done"] = True
        if os.environ.get("CBH_MALLOC_TUNE", "1").strip().lower() in ("0", "false", "off", "no"):
            return {}
        if any(k.startswith("MALLOC_") for k in os.environ) or "glibc.malloc." in os.environ.get("GLIBC_TUNABLES", ""):
            return {}
        mallopt = _glibc_mallopt()
        if mallopt is None:
            return {}
        applied = {}
        for threshold in (MALLOC_SETTINGS["M_MMAP_THRESHOLD"], 32 << 20):
            if mallopt(_M_MMAP_THRESHOLD, int(threshold)) == 1:  # mallopt returns 1 on success
                applied["M_MMAP_THRESHOLD"] = int(threshold)
                break
        if not applied:
            return {}
        for name in ("M_TRIM_THRESHOLD", "M_TOP_PAD"):
            if mallopt(_PARAM[name], int(MALLOC_SETTINGS[name])) == 1:
                applied[name] = int(MALLOC_SETTINGS[name])
        _state["applied"] = applied
        return dict(applied)


def _after_fork_in_child() -> None:  # the lock may have been held by a thread that does not exist here
    global _lock
    _lock = threading.Lock()


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_after_fork_in_child)


def _glibc_mallopt():
    """glibc's ``mallopt`` (int mallopt(int, int)), or None on another C library."""
    try:
        libc = ctypes.CDLL("libc.so.6")  # (not find_library: it runs ldconfig, 10–50 ms of a cold start)
        if not hasattr(libc, "gnu_get_libc_version"):  # musl and others: different parameters
            return None
        fn = libc.mallopt
    except (OSError, AttributeError):
        return None
    fn.argtypes, fn.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    return fn
