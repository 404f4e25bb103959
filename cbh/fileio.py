"""Writing files so that a crash, a full disk or Ctrl-C never leaves a half-written one."""
from __future__ import annotations

import os
import threading
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

__all__ = ["atomic_write"]


@contextmanager
def atomic_write(path: str | Path) -> Iterator[Path]:
    """A temporary path beside ``path``, renamed over ``path`` (``os.replace``) when the block
    succeeds and removed when it fails.

    Readers see either the previous file (or none) or the complete new one, never a partial
    file. The temporary name is hidden (``.NAME.PID.THREAD.tmp``) and unique per writer, so
    concurrent writers do not share it. OS errors propagate: callers turn them into their own
    one-line errors.

    Examples
    --------
    >>> with atomic_write("/tmp/out.json") as tmp:      # doctest: +SKIP
    ...     tmp.write_text("{}")
    """
    path = Path(path)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.{threading.get_ident()}.tmp")
    try:
        yield tmp
        os.replace(tmp, path)
    finally:
        try:
            tmp.unlink()
        except FileNotFoundError:
            pass
        except OSError:  # pragma: no cover - e.g. the folder went away; the caller reports its own error
            pass
