"""TOML in and out: the one strict config reader of cbh, and a small writer (tomllib only reads).

Every config table (station, ``[pipeline]``, scene, ``[service]``) is read with these, so they
all follow one set of rules:

- unknown keys are errors that name the key path (``pipeline.matching.lk.window_px``);
- numbers must be numbers (not booleans) and finite (no ``nan``/``inf``), with optional bounds;
- integers, booleans, strings, fixed-length vectors and choices are checked for their type;
- every error is one :class:`~cbh.errors.ConfigError` whose message starts with the key path.

:func:`dataclass_from_table` builds a frozen config dataclass (fields typed ``float``, ``int``,
``bool``, ``str``, ``tuple[...]``, ``X | None`` or a nested dataclass) from a table with these rules.
"""
from __future__ import annotations

import dataclasses
import math
import re
import tomllib
import types
import typing
from pathlib import Path

import numpy as np

from cbh.errors import ConfigError

__all__ = [
    "read_toml", "dumps_toml", "check_keys", "table", "number", "integer", "boolean", "string", "vector",
    "choice", "dataclass_from_table", "dataclass_to_dict",
]


# --- strict values ------------------------------------------------------------------------------

def check_keys(where: str, value: dict, allowed) -> None:
    """ConfigError naming ``where.key`` for the first key of ``value`` not in ``allowed``."""
    extra = sorted(set(value) - set(allowed))
    if extra:
        key = f"{where}.{extra[0]}" if where else extra[0]
        raise ConfigError(f"{key}: unknown key (allowed: {', '.join(sorted(allowed))})")


def table(where: str, value) -> dict:
    """``value`` if it is a table (dict)."""
    if not isinstance(value, dict):
        raise ConfigError(f"{where}: expected a table, got {type(value).__name__}")
    return value


def number(where: str, value, *, lo: float | None = None, hi: float | None = None, lo_open: bool = False,
           positive: bool = False) -> float:
    """A finite number (int or float, not bool) as float, within [lo, hi] (``lo_open``: > lo)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ConfigError(f"{where}: expected a number, got {value!r}")
    v = float(value)
    if not math.isfinite(v):
        raise ConfigError(f"{where}: must be finite, got {value!r}")
    if positive and v <= 0:
        raise ConfigError(f"{where}: must be > 0, got {value!r}")
    if lo is not None and (v <= lo if lo_open else v < lo):
        raise ConfigError(f"{where}: must be {'>' if lo_open else '>='} {lo:g}, got {value!r}")
    if hi is not None and v > hi:
        raise ConfigError(f"{where}: must be <= {hi:g}, got {value!r}")
    return v


def integer(where: str, value, *, lo: int | None = None, hi: int | None = None) -> int:
    """An integer (not bool) within [lo, hi]."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise ConfigError(f"{where}: expected an integer, got {value!r}")
    if (lo is not None and value < lo) or (hi is not None and value > hi):
        lo_s = "" if lo is None else str(lo)
        hi_s = "" if hi is None else str(hi)
        raise ConfigError(f"{where}: must be in {lo_s}..{hi_s}, got {value!r}")
    return int(value)


def boolean(where: str, value) -> bool:
    if not isinstance(value, bool):
        raise ConfigError(f"{where}: expected true or false, got {value!r}")
    return value


def string(where: str, value) -> str:
    if not isinstance(value, str):
        raise ConfigError(f"{where}: expected a string, got {value!r}")
    return value


def vector(where: str, value, n: int, **bounds) -> tuple[float, ...]:
    """A list of exactly ``n`` finite numbers (``bounds`` as for :func:`number`)."""
    if not isinstance(value, (list, tuple)) or len(value) != n:
        raise ConfigError(f"{where}: expected a list of {n} numbers, got {value!r}")
    return tuple(number(f"{where}[{i}]", v, **bounds) for i, v in enumerate(value))


def choice(where: str, value, choices, what: str = "value") -> str:
    """A string out of ``choices`` (e.g. a method registry's names)."""
    value = string(where, value)
    if value not in choices:
        raise ConfigError(f"{where}: unknown {what} {value!r} (valid: {', '.join(choices)})")
    return value


# --- tables -> frozen dataclasses ---------------------------------------------------------------

def dataclass_from_table(cls, data, where: str):
    """Build dataclass ``cls`` from a table: unknown keys, wrong types and non-finite numbers
    are ConfigErrors naming the key path; missing keys take the field defaults."""
    data = table(where, data)
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls)}
    check_keys(where, data, fields)
    kwargs = {name: _coerce(hints[name], data[name], f"{where}.{name}") for name in fields if name in data}
    return cls(**kwargs)


def _coerce(tp, value, where):
    if dataclasses.is_dataclass(tp):
        return dataclass_from_table(tp, value, where)
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):  # X | None
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        return _coerce(args[0], value, where)
    if origin is tuple:
        if isinstance(value, str):
            value = [value]
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{where}: expected a list, got {value!r}")
        return tuple(_coerce(typing.get_args(tp)[0], v, f"{where}[{i}]") for i, v in enumerate(value))
    if tp is bool:
        return boolean(where, value)
    if tp is int:
        return integer(where, value)
    if tp is float:
        return number(where, value)
    if tp is str:
        return string(where, value)
    raise ConfigError(f"{where}: unsupported type {tp!r}")  # pragma: no cover


def dataclass_to_dict(obj) -> dict:
    """Plain dict (TOML/JSON-ready) that :func:`dataclass_from_table` reads back to an equal object."""
    out = {}
    for f in dataclasses.fields(obj):
        v = getattr(obj, f.name)
        if dataclasses.is_dataclass(v):
            v = dataclass_to_dict(v)
        elif isinstance(v, tuple):
            v = list(v)
        out[f.name] = v
    return out



def read_toml(path: str | Path, what: str) -> dict:
    """Parse a TOML file; :class:`ConfigError` naming ``what`` (e.g. "station") on any failure."""
    from cbh.fileio import read_input

    path = Path(path)
    raw = read_input(path, f"{what} file", ConfigError)
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
        return _toml_string(v)
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    raise TypeError(f"cannot write {type(v).__name__} to TOML")


_ESCAPES = {"\\": "\\\\", '"': '\\"', "\b": "\\b", "\t": "\\t", "\n": "\\n", "\f": "\\f", "\r": "\\r"}
_BARE_KEY = re.compile(r"[A-Za-z0-9_-]+")


def _toml_string(v: str) -> str:
    """A TOML basic string: quotes, backslashes and control characters escaped (a raw newline
    or control character is not valid in one)."""
    return '"' + "".join(_ESCAPES.get(c) or (f"\\u{ord(c):04X}" if ord(c) < 0x20 or ord(c) == 0x7F else c)
                         for c in v) + '"'


def _toml_key(k) -> str:
    """A bare key where TOML allows one, else a quoted key (``"a b"``, ``"x.y"``)."""
    k = str(k)
    return k if _BARE_KEY.fullmatch(k) else _toml_string(k)


def _is_table_array(v) -> bool:
    return isinstance(v, list) and bool(v) and all(isinstance(x, dict) for x in v)


def dumps_toml(data: dict, _prefix: str = "") -> str:
    """Minimal TOML writer for nested dicts, arrays of tables and plain values."""
    lines, tables = [], []
    for k, v in data.items():
        if isinstance(v, dict) or _is_table_array(v):
            tables.append((k, v))
        else:
            lines.append(f"{_toml_key(k)} = {_toml_value(v)}")
    out = "\n".join(lines) + ("\n" if lines else "")
    for k, v in tables:
        name = f"{_prefix}{_toml_key(k)}"
        if isinstance(v, dict):
            out += f"\n[{name}]\n" + dumps_toml(v, name + ".")
        else:
            for item in v:
                out += f"\n[[{name}]]\n" + dumps_toml(item, name + ".")
    return out
