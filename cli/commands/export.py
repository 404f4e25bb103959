"""`cbh export`: layer heights of recordings as CSV, Parquet or CF NetCDF."""
from __future__ import annotations

from pathlib import Path

import typer

_SUFFIX = {".csv": "csv", ".parquet": "parquet", ".nc": "netcdf", ".nc4": "netcdf", ".netcdf": "netcdf"}


def register(app: typer.Typer) -> None:
    app.command("export")(export_cmd)


def export_cmd(
    sessions: list[Path] = typer.Argument(..., help="One or more SESSION.mcap files (or directories of rotated files)."),
    out: Path = typer.Option(..., "--out", "-o", help="Output file (replaced if it exists)."),
    fmt: str = typer.Option(None, "--format", "-f", help="csv | parquet | netcdf (default: from the --out suffix)."),
) -> None:
    """Layer heights per time step (cloud base above ground and sea level, cover, confidence)."""
    from cbh.errors import ConfigError
    from cbh.outputs.export import export_sessions

    if fmt is None:
        fmt = _SUFFIX.get(out.suffix.lower())
        if fmt is None:
            raise ConfigError(f"--format: not given and {out.name!r} has no known suffix (.csv, .parquet, .nc)")
    rows, steps = export_sessions(sessions, fmt, out)
    print(f"wrote {steps} time steps ({rows} rows) to {out}")
