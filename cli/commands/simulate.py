"""`cbh simulate`: render a synthetic stereo sky sequence with exact ground truth to a folder."""
from __future__ import annotations

from pathlib import Path

import typer

from cbh.actions.simulate import simulate_to_folder
from cbh.timeutil import parse_utc


def register(app: typer.Typer) -> None:
    app.command("simulate")(simulate_cmd)


def simulate_cmd(
    station: str = typer.Option(None, "--station", help="Station TOML or preset name (default: unb-lea)."),
    scene: str = typer.Option("two-layers", "--scene", help="Scene TOML or preset name (configs/scenes)."),
    out: Path = typer.Option(..., "--out", help="Output folder (created)."),
    frames: int = typer.Option(1, "--frames", help="Number of frames."),
    cadence_s: float = typer.Option(None, "--cadence-s", help="Seconds between frames (default 10; a drone flight 1)."),
    start: str = typer.Option(None, "--start", help="Start time, ISO 8601 with a zone (default: the scene's time_utc)."),
    size: int = typer.Option(None, "--size", help="Render this many pixels wide (calibration scaled; at most 8192)."),
    clock_offset: list[str] = typer.Option([], "--clock-offset", help="CAMERA=SECONDS: the camera captures this late "
                                                                      "(files stamped on time); overrides the scene's."),
    drone_flight: bool = typer.Option(False, "--drone-flight", help="Render a night drone flight with its log "
                                      "(stars, an aircraft, hot pixels) for `cbh validate --drone` instead of clouds."),
    positions: int = typer.Option(20, "--positions", help="--drone-flight: hover positions (the paper's 20: five "
                                  "sectors at four heights from 90 to 490 m)."),
    log_offset_s: float = typer.Option(3.0, "--log-offset-s", help="--drone-flight: the log's clock ahead of the cameras' [s]."),
    seed: int = typer.Option(0, "--seed", help="--drone-flight: the stars', hot pixels' and aircraft's seed."),
) -> None:
    """Render N frames of every camera of a station looking at a scene; write images, truth, station.

    Writes OUT/<camera>/<camera>_<YYYYmmddTHHMMSS.fffZ>.jpg, OUT/truth/<time>.npz (per camera
    height_m, cloud_mask) and .json (layers, sun), OUT/station.toml (the scaled station: OUT can
    be processed as it is) and OUT/scene.toml.
    """
    t0 = parse_utc(start, "--start") if start is not None else None
    if drone_flight:
        from cbh.actions.simulate import simulate_drone_to_folder

        for line in simulate_drone_to_folder(out, station=station, positions=positions, cadence_s=cadence_s or 1.0,
                                             start_utc=t0, size_px=size, log_offset_s=log_offset_s, seed=seed):
            print(line, flush=True)
        return
    cadence_s = 10.0 if cadence_s is None else cadence_s
    for step in simulate_to_folder(out, station=station, scene=scene, frames=frames, cadence_s=cadence_s,
                                   start_utc=t0, size_px=size, clock_offsets=clock_offset):
        print(step.line(), flush=True)
