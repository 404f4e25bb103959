"""`cbh calibrate`: each camera's orientation from the sun track and the clouds → a new station file."""
from __future__ import annotations

import json
from pathlib import Path

import typer


def register(app: typer.Typer) -> None:
    app.command("calibrate")(calibrate_cmd)


def calibrate_cmd(
    station: Path = typer.Option(..., "--station", help="Station TOML to calibrate (not modified unless --out names it)."),
    source: list[str] = typer.Option(..., "--source", help="CAM=SPEC for every station camera: image folder, video, stream URL or .mcap recording."),
    out: Path = typer.Option(..., "--out", help="Write the calibrated station TOML here."),
    json_out: bool = typer.Option(False, "--json", help="Print the full report as JSON."),
    from_t: str = typer.Option(None, "--from", help="Use frames from this UTC time (ISO 8601, ends in Z)."),
    to_t: str = typer.Option(None, "--to", help="Use frames up to this UTC time."),
    duration_s: float = typer.Option(None, "--duration", help="Live sources: read for this many seconds."),
    relative_only: bool = typer.Option(False, "--relative-only", help="No sun: keep the first camera, fit the others to it from the clouds."),
) -> None:
    """Fit yaw, pitch and roll of every camera (sun track: absolute; clouds: relative) and write a station."""
    from cbh.actions.calibrate import CalibrateOptions, calibrate, parse_sources
    from cbh.timeutil import parse_utc

    opts = CalibrateOptions(from_utc=None if from_t is None else parse_utc(from_t, "--from"),
                            to_utc=None if to_t is None else parse_utc(to_t, "--to"),
                            duration_s=duration_s, relative_only=relative_only)
    rep = calibrate(station, parse_sources(source), out, opts)
    if json_out:
        print(json.dumps(rep, indent=1))
        return
    for line in rep["summary"]:
        print(line)
