"""``cbh export`` in library terms: layer heights of recordings as CSV, Parquet or CF NetCDF."""
from __future__ import annotations

from pathlib import Path

from cbh.errors import ConfigError

__all__ = ["export", "format_from_suffix"]

_SUFFIX = {".csv": "csv", ".parquet": "parquet", ".nc": "netcdf", ".nc4": "netcdf", ".netcdf": "netcdf"}


def format_from_suffix(out) -> str | None:
    """csv | parquet | netcdf from the output file's suffix; None for an unknown suffix."""
    return _SUFFIX.get(Path(out).suffix.lower())


def export(sessions, out, fmt: str | None = None) -> tuple[int, int]:
    """Write the layer heights of one or more sessions to ``out`` (replaced if it exists).

    Returns (rows, time steps). ``fmt``: csv | parquet | netcdf (default: from the suffix).
    """
    from cbh.outputs.export import export_sessions

    fmt = fmt or format_from_suffix(out)
    if fmt is None:
        raise ConfigError(f"{Path(out).name!r}: no known table suffix (.csv, .parquet, .nc) and no format given")
    return export_sessions(list(sessions), fmt, Path(out))
