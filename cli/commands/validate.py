"""`cbh validate`: cbh against a co-located ceilometer (cbh/actions/validate.py) or a drone's
flight log (cbh/actions/drone.py)."""
from __future__ import annotations

from pathlib import Path

import typer


def register(app: typer.Typer) -> None:
    app.command("validate")(validate_cmd)


def validate_cmd(
    recordings: list[Path] = typer.Argument(None, help="SESSION.mcap recordings to check (or --source with --drone)."),
    ceilometer: list[Path] = typer.Option([], "--ceilometer", help="Ceilometer file(s): CL31/CL51 messages, CL61, "
                                          "CHM15k, ARM ceil or E-PROFILE NetCDF (repeat the option)."),
    drone: Path = typer.Option(None, "--drone", help="A drone's flight log (DJI .SRT or CSV of time_utc, latitude, "
                               "longitude, altitude_m above the take-off): the paper's drone check."),
    takeoff: str = typer.Option(None, "--takeoff", metavar="LAT,LON,UP_M", help="--drone: the take-off point and its "
                                "height [m] above the station's origin (camera 1), e.g. --takeoff=-15.76,-47.87,-10."),
    station: Path = typer.Option(None, "--station", help="--drone with --source: the station TOML."),
    source: list[str] = typer.Option([], "--source", metavar="CAM=DIR", help="--drone: a camera's image folder "
                                     "(repeat for each camera) in place of recordings."),
    log_tz: str = typer.Option(None, "--log-tz", help="--drone: the log's time zone when it is not UTC (DJI stamps "
                               "local time), e.g. +02:00."),
    json_out: bool = typer.Option(False, "--json", help="--drone: print the per-position rows and the summary as JSON."),
    out: Path = typer.Option(None, "--out", "-o", help="Report: JSON for --ceilometer (default validation.json), CSV "
                             "for --drone (default drone-check.csv); PNGs are written beside it."),
    match_s: float = typer.Option(30.0, "--match-s", help="--ceilometer: profiles within this many seconds of a pair."),
) -> None:
    """Check cbh against a ceilometer (MAE, RMSE, bias, R², within 150 m) or a drone flight (MAE, MAPE, RMSE per hover)."""
    from cbh.errors import ConfigError

    if bool(ceilometer) == (drone is not None):
        raise ConfigError("give either --ceilometer FILE… with recordings, or --drone LOG (with recordings or --source)")
    if drone is None:
        from cbh.actions.validate import validate

        if not recordings:
            raise ConfigError("--ceilometer: give the recordings (SESSION.mcap) to compare")
        print(validate(ceilometer, recordings, out or Path("validation.json"), match_s)[1])
        return
    _drone(drone, recordings, takeoff, station, source, log_tz, json_out, out)


def _drone(log, recordings, takeoff, station, source, log_tz, json_out, out) -> None:
    from cbh.actions.calibrate import parse_sources
    from cbh.actions.drone import DroneOptions, report_json, validate_drone
    from cbh.errors import ConfigError
    from cbh.geometry.flightlog import parse_takeoff

    if bool(recordings) == bool(source):
        raise ConfigError("--drone: give either recordings or --source CAM=DIR for each camera (with --station)")
    opts = DroneOptions(takeoff=None if takeoff is None else parse_takeoff(takeoff), log_tz=log_tz)
    rep, text = validate_drone(log, out or Path("drone-check.csv"), station_path=station,
                               sources=parse_sources(source) if source else None, recordings=recordings or None, opts=opts)
    print(report_json(rep) if json_out else text)
