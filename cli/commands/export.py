"""`cbh export`: layer heights of recordings as CSV, Parquet or CF NetCDF; cloud and shadow maps."""
from __future__ import annotations

from pathlib import Path

import typer


def register(app: typer.Typer) -> None:
    app.command("export")(export_cmd)


def export_cmd(
    sessions: list[Path] = typer.Argument(..., help="One or more SESSION.mcap files (or directories of rotated files)."),
    out: Path = typer.Option(..., "--out", "-o", help="Output file (replaced if it exists); a directory with --daily."),
    fmt: str = typer.Option(None, "--format", "-f", help="csv | parquet | netcdf | npz (default: from the --out suffix)."),
    product: str = typer.Option("layers", "--product", help="layers | irradiance (GHI nowcast at --site: csv or netcdf) | cloudmap | shadow (maps: netcdf or npz) | metar (csv, ampycloud) | cl61 | eprofile (netcdf)."),
    daily: bool = typer.Option(False, "--daily", help="One file per UTC day in the --out directory (layers)."),
    station: str = typer.Option(None, "--station", help="Station TOML whose [ground] grid the maps use (default: recorded)."),
    site: list[str] = typer.Option(None, "--site", metavar="[NAME=]LAT,LON[,ALT_M]",
                                   help="Irradiance: a ground site (repeatable; ALT above sea level, default the station's); "
                                        "a plant: NAME=LAT,LON;LAT,LON;… (points averaged) or NAME=polygon:LAT,LON;… "
                                        "(the area inside); @FILE.csv: sites (name,latitude,longitude[,altitude_m]; "
                                        "rows sharing a name are one plant)."),
    leads: str = typer.Option(None, "--leads", help="Irradiance: lead times in minutes, e.g. 0,1,5,10 or 0:20 (default 0:20)."),
    pyranometer: Path = typer.Option(None, "--pyranometer", help="Irradiance: a pyranometer's GHI record (CSV) to learn the sun and shade levels from."),
) -> None:
    """Layer heights per time step (height, cover, okta, ceiling, motion, flags), or ground maps."""
    from cbh.actions.export import export
    from cbh.actions.station import load_station

    st = load_station(station) if station else None
    print(export(sessions, out, fmt, product=product, daily=daily, station=st, sites=site or (), leads=leads,
                 pyranometer=pyranometer))
