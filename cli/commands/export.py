"""`cbh export`: layer heights of recordings as CSV, Parquet or CF NetCDF."""
from __future__ import annotations

from pathlib import Path

import typer

from cbh.actions.export import export, format_from_suffix
from cbh.errors import ConfigError


def register(app: typer.Typer) -> None:
    app.command("export")(export_cmd)


def export_cmd(
    sessions: list[Path] = typer.Argument(..., help="One or more SESSION.mcap files (or directories of rotated files)."),
    out: Path = typer.Option(..., "--out", "-o", help="Output file (replaced if it exists)."),
    fmt: str = typer.Option(None, "--format", "-f", help="csv | parquet | netcdf (default: from the --out suffix)."),
) -> None:
    """Layer heights per time step (cloud base above ground and sea level, cover, confidence)."""
    if fmt is None and format_from_suffix(out) is None:
        raise ConfigError(f"--format: not given and {out.name!r} has no known suffix (.csv, .parquet, .nc)")
    rows, steps = export(sessions, out, fmt)
    print(f"wrote {steps} time steps ({rows} rows) to {out}")
