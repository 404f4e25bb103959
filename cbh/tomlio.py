"""TOML in and out: one reader with one-line errors, and a small writer (tomllib only reads)."""
from __future__ import annotations

import tomllib
from pathlib import Path

import numpy as np

from cbh.errors import ConfigError

__all__ = ["read_toml", "dumps_toml"]


def read_toml(path: str | Path, what: str) -> dict:
    """Parse a TOML file; :class:`ConfigError` naming ``what`` (e.g. "station") on any failure."""
    path = Path(path)
    try:
        raw = path.read_bytes()
    except FileNotFoundError:
        raise ConfigError(f"{what} file not found: {path}") from None
    except IsADirectoryError:
        raise ConfigError(f"{what} path is a directory, not a TOML file: {path}") from None
    except OSError as exc:
        raise ConfigError(f"cannot read {what} file {path}: {exc.strerror}") from None
    try:
        return tomllib.loads(raw.decode("utf-8"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{path.name}: malformed TOML: {exc}") from None


def _toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    if isinstance(v, (float, np.floating)):
        return repr(float(v))
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    raise TypeError(f"cannot write {type(v).__name__} to TOML")


def _is_table_array(v) -> bool:
    return isinstance(v, list) and bool(v) and all(isinstance(x, dict) for x in v)


def dumps_toml(data: dict, _prefix: str = "") -> str:
    """Minimal TOML writer for nested dicts, arrays of tables and plain values."""
    lines, tables = [], []
    for k, v in data.items():
        if isinstance(v, dict) or _is_table_array(v):
            tables.append((k, v))
        else:
            lines.append(f"{k} = {_toml_value(v)}")
    out = "\n".join(lines) + ("\n" if lines else "")
    for k, v in tables:
        name = f"{_prefix}{k}"
        if isinstance(v, dict):
            out += f"\n[{name}]\n" + dumps_toml(v, name + ".")
        else:
            for item in v:
                out += f"\n[[{name}]]\n" + dumps_toml(item, name + ".")
    return out
