"""On-disk cache of a camera pair's precomputed tables (cold start of ``cbh pair``).

A pipeline's first pair builds per-camera tables: the point-at-infinity remap table, the plane
maps of the sweep (three exact fisheye projections of every working pixel's ray), the static
sky masks, camera 1's ENU rays and both cameras' ray and zenith maps. That is ≈ 1–3 s of a
one-shot ``cbh pair`` (the pair itself is a few hundred ms).
They depend only on the two cameras (lens models, poses, obstacle mask file), the working size
and the mask settings, so they are stored once in ``$CBH_CACHE_DIR`` (default
``$XDG_CACHE_HOME/cbh`` or ``~/.cache/cbh``; ``CBH_CACHE_DIR=off`` disables the cache) and read
back (18–100 MB, a flat file mapped into memory: ≈ 20 ms) by every later process with
the same cameras.

The key hashes everything the tables depend on, including the source text of the modules
that compute them (camera, station, match, sweep, masks, this one): editing the geometry
invalidates old entries instead of serving stale tables. At most ``_MAX_FILES`` entries are
kept (least recently used go first). A cache that cannot be read or written is ignored: the
tables are then built as without it.
"""
from __future__ import annotations

import hashlib
import json
import logging
import os
from pathlib import Path

import numpy as np
from cbh.fileio import atomic_write

__all__ = ["cache_dir", "tables_key", "load_tables", "save_tables"]

log = logging.getLogger(__name__)

_MAX_FILES = 8
_SOURCES = ("geometry/camera.py", "geometry/station.py", "pipeline/match.py", "pipeline/sweep.py",
            "pipeline/masks.py", "pipeline/tables.py")


def cache_dir() -> Path | None:
    """The cache directory, or None when disabled (``CBH_CACHE_DIR=off`` or empty)."""
    env = os.environ.get("CBH_CACHE_DIR")
    if env is not None:
        return None if env.strip().lower() in ("", "off", "0", "none") else Path(env)
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "cbh"


def _camera_text(cam) -> str:
    mask = ""
    if cam.mask is not None:
        try:
            mask = f"{Path(cam.mask).resolve()}:{Path(cam.mask).stat().st_mtime_ns}"
        except OSError:
            mask = str(cam.mask)
    return (f"{cam.name}|{cam.model!r}|{np.asarray(cam.position_m, np.float64).tobytes().hex()}|"
            f"{np.asarray(cam.R_world_from_cam, np.float64).tobytes().hex()}|{mask}")


def tables_key(cam1, cam2, masks_cfg) -> str:
    """Hash of what a pair's tables depend on (working-size cameras, mask settings, the code)."""
    h = hashlib.sha256()
    root = Path(__file__).resolve().parents[1]
    for rel in _SOURCES:
        try:
            h.update((root / rel).read_bytes())
        except OSError:
            h.update(rel.encode())
    h.update(_camera_text(cam1).encode())
    h.update(_camera_text(cam2).encode())
    h.update(repr(masks_cfg).encode())
    return h.hexdigest()[:32]


_MAGIC = b"CBHTABLES1\n"
_ALIGN = 64


def load_tables(key: str) -> dict[str, np.ndarray] | None:
    """The cached tables of ``key`` (name → array), or None.

    The whole file mapped copy-on-write, the arrays views into it (writable: a write copies that
    page for this process only, the file never changes). ``np.load`` of the same arrays in an
    ``.npz`` took 356 ms for the WAHRSIS pair's 100 MB (zipfile's reads and CRC); one read into a
    buffer ≈ 30 ms in a warm process, but 0.36–0.5 s in a fresh ``cbh reprocess`` actor, whose
    first touch of 72 MB of new memory is slow on a virtual machine; the mapping shares the
    page cache's pages instead: ≈ 20 ms either way (measured, 960 px tables)."""
    d = cache_dir()
    if d is None:
        return None
    path = d / f"tables-{key}.bin"
    try:
        buf = np.memmap(path, dtype=np.uint8, mode="c").view(np.ndarray)  # the mapping stays alive as its base
        if bytes(buf[: len(_MAGIC)]) != _MAGIC:
            raise ValueError("not a cbh table file")
        n = int(buf[len(_MAGIC): len(_MAGIC) + 8].view("<u8")[0])
        head = json.loads(bytes(buf[len(_MAGIC) + 8: len(_MAGIC) + 8 + n]))
        out = {}
        for name, (dtype, shape, offset) in head.items():
            dt = np.dtype(dtype)
            size = dt.itemsize * int(np.prod(shape, dtype=np.int64))
            if offset + size > len(buf):
                raise ValueError(f"{name} runs past the end of the file")
            out[name] = buf[offset: offset + size].view(dt).reshape(shape)
        os.utime(path)  # least recently used goes first
        return out
    except FileNotFoundError:
        return None
    except Exception as e:  # a damaged entry: rebuild (and overwrite it)
        log.warning("table cache %s unreadable (%s); rebuilding", path, e)
        return None


def save_tables(key: str, tables: dict[str, np.ndarray]) -> None:
    """Store ``tables`` under ``key`` (atomic rename) and prune the cache to ``_MAX_FILES``.

    Format: ``_MAGIC``, the header's length (8 bytes, little-endian), a JSON header (name →
    [dtype, shape, offset]), then each array's bytes (C order) at its offset, ``_ALIGN``-aligned."""
    d = cache_dir()
    if d is None:
        return
    try:
        d.mkdir(parents=True, exist_ok=True)
        arrays = {k: np.ascontiguousarray(v) for k, v in tables.items()}
        head, offset = {}, 0
        for k, a in arrays.items():  # offsets relative to the data start first
            head[k] = [a.dtype.str, list(a.shape), offset]
            offset += -(-a.nbytes // _ALIGN) * _ALIGN
        text = json.dumps(head).encode()
        start = -(-(len(_MAGIC) + 8 + len(text) + 64) // _ALIGN) * _ALIGN  # room for the absolute offsets
        for k in head:
            head[k][2] += start
        text = json.dumps(head).encode()
        assert len(_MAGIC) + 8 + len(text) <= start
        with atomic_write(d / f"tables-{key}.bin") as tmp, open(tmp, "wb") as fh:
            fh.write(_MAGIC + np.array([len(text)], "<u8").tobytes() + text)
            for k, a in arrays.items():
                fh.seek(head[k][2])
                fh.write(a.tobytes())
            fh.truncate(max([head[k][2] + arrays[k].nbytes for k in head], default=start))
        entries = sorted(list(d.glob("tables-*.bin")) + list(d.glob("tables-*.npz")),
                         key=lambda p: p.stat().st_mtime, reverse=True)
        for old in entries[_MAX_FILES:]:
            old.unlink(missing_ok=True)
    except OSError as e:
        log.warning("table cache %s not writable (%s)", d, e)
