"""Writing files so that a crash, a full disk or Ctrl-C never leaves a half-written one."""
from __future__ import annotations

import os
import threading
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

__all__ = ["atomic_write", "refuse_inputs"]


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


_DATA_SUFFIXES = frozenset({".jpg", ".jpeg", ".png", ".tif", ".tiff", ".bmp", ".webp", ".mcap", ".nc", ".mp4",
                            ".avi", ".mkv", ".mov", ".toml", ".csv", ".parquet", ".txt"})


def _same(a: Path, b: Path) -> bool:
    """One file (or folder) under two names: the same inode when both exist, else the same
    resolved path."""
    try:
        if a.exists() and b.exists():
            return os.path.samefile(a, b)
    except OSError:
        pass
    return a.resolve() == b.resolve()


def refuse_inputs(outputs, inputs, option: str = "--out") -> None:
    """Refuse (:class:`~cbh.errors.ConfigError`, one line, exit 2) to write any of ``outputs``
    over one of the command's ``inputs``, before anything is read or written.

    Paths are compared as files, not names: resolved paths, and inodes where both exist (a
    hard link, a symlink, ``./a`` and ``a`` are caught). An input folder (image folders,
    rotated recordings) counts with every data file directly in it (images, videos, recordings,
    NetCDF: ``_DATA_SUFFIXES``); an output folder is refused when it is an input. Anything that is not a local path (a URL, ``sim``) is skipped. ``outputs``
    and ``inputs``: iterables of str / Path (None entries ignored)."""
    from cbh.errors import ConfigError

    ins: list[Path] = []
    for x in inputs:
        if x is None or (isinstance(x, str) and ("://" in x or x.strip().lower() == "sim")):
            continue
        q = Path(x)
        ins.append(q)
        if q.is_dir():
            try:
                ins.extend(f for f in q.iterdir() if f.is_file() and f.suffix.lower() in _DATA_SUFFIXES)
            except OSError:
                pass
    for o in outputs:
        if o is None:
            continue
        out = Path(o)
        for q in ins:
            if _same(out, q):
                kind = "folder" if q.is_dir() else "file"
                raise ConfigError(f"{option} {out}: that is one of the command's own inputs ({kind} {q}); "
                                  "writing it would destroy it: give another path")


def read_input(path: str | Path, what: str, error: type[Exception]) -> bytes:
    """The bytes of an input file, or ``error`` with one line naming ``what`` (e.g. "image",
    "station file", "flight log") and why: not found, a directory, or the OS's reason."""
    path = Path(path)
    try:
        return path.read_bytes()
    except FileNotFoundError:
        raise error(f"{what} not found: {path}") from None
    except IsADirectoryError:
        raise error(f"{what} is a directory, not a file: {path}") from None
    except OSError as exc:
        raise error(f"cannot read {what} {path}: {exc.strerror}") from None
