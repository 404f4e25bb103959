"""`cbh run`: the live service (camera streams → pairs → heights → MCAP / Rerun / export)."""
from __future__ import annotations

from pathlib import Path

import typer

from cbh.errors import ConfigError

#: Pairs a simulated run processes when neither --frames nor --duration is given (the demo).
DEMO_FRAMES = 6


def register(app: typer.Typer) -> None:
    app.command("run")(run_cmd)


def run_cmd(
    record_path: str = typer.Argument(
        None, metavar="[PATH]", show_default=False,
        help="With --record: the .mcap file or directory to record to."),
    station: str = typer.Option(None, "--station", help="Station TOML or preset name (default: unb-lea, simulated)."),
    scene: str = typer.Option(None, "--scene", help="Simulated scene TOML or preset for cameras without a source (default: two-layers)."),
    source: list[str] = typer.Option(None, "--source", metavar="CAM=SPEC",
                                     help="Camera source: rtsp://…, http(s)://… (MJPEG or snapshot), mjpeg+http://…, "
                                          "snapshot+http://…, a video file, an image directory, or sim. Repeatable."),
    cameras: str = typer.Option(None, "--cameras", help="The cameras, reference first: two (cam1,cam2) or a network's N (default: every camera of the station)."),
    record: bool = typer.Option(False, "--record", help="Record MCAP to PATH (default recordings/<station>-<UTC>.mcap)."),
    rerun: str = typer.Option(None, "--rerun", metavar="MODE",
                              help="Live Rerun view: spawn | serve | connect[=URL] | save=PATH.rrd (or just URL / PATH.rrd)."),
    export: Path = typer.Option(None, "--export", help="Append layer heights to PATH.csv or PATH.parquet."),
    cadence_s: float = typer.Option(None, "--cadence-s", help="Process one pair per this many seconds of frame time (0: every pair)."),
    frames: int = typer.Option(None, "--frames", help="Stop after N processed pairs."),
    duration: float = typer.Option(None, "--duration", help="Stop after S wall seconds."),
    size: int = typer.Option(None, "--size", help="Simulator image width [px] (default: the station's)."),
    pair_tolerance_s: float = typer.Option(None, "--pair-tolerance-s", help="Largest time difference of a pair [s] (default 0.5)."),
    watch: bool = typer.Option(False, "--watch", help="Image directories: keep polling for new files."),
    realtime: bool = typer.Option(False, "--realtime", help="Simulator: deliver frames at the cadence in wall time, like cameras."),
    rotate_mb: float = typer.Option(None, "--rotate-mb", help="Start a new MCAP file after this many MB."),
    rotate_s: float = typer.Option(None, "--rotate-s", help="Start a new MCAP file after this many seconds of capture time (default 3600)."),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="No status line."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace an existing --record PATH (default: refuse)."),
    bind: str = typer.Option(None, "--bind", metavar="ADDR",
                             help="Address of the --rerun serve server (default 127.0.0.1; 0.0.0.0: every interface)."),
    device: str = typer.Option("cpu", "--device", help="Where the dense work runs: cpu (default) or a torch device, e.g. cuda."),
    resume_clock: Path = typer.Option(None, "--resume-clock", metavar="REC",
                                      help="Start from the cameras' clock offset recorded in REC (.mcap or directory; "
                                           "default: the newest earlier recording where --record writes)."),
) -> None:
    """Run the service: pair the two cameras' frames, compute cloud-base heights, record/view/export.

    With no station and no source it runs the simulated default station (unb-lea, scene
    two-layers) for 6 pairs; `cbh run --record` records that to recordings/. Ends on
    --frames/--duration, when finite sources end, or on Ctrl-C/SIGTERM (finishes the pair in
    flight, closes every file, exit 0).
    """
    if record_path is not None and not record:
        raise ConfigError(f"unexpected argument {record_path!r} (a recording path goes after --record)")
    from cbh.actions.run import build_run, summary_lines  # on use: the live service's imports (cold start)
    from cbh.cli.status import run_with_status

    setup = build_run(
        station=station, scene=scene, sources=source or [], cameras=cameras,
        record=(record_path or True) if record else None, rerun=rerun, export=export,
        cadence_s=cadence_s, frames=frames, duration_s=duration, size_px=size,
        pair_tolerance_s=pair_tolerance_s, watch=watch, realtime=realtime,
        rotate_mb=rotate_mb, rotate_s=rotate_s, demo_frames=DEMO_FRAMES, overwrite=overwrite, bind=bind, device=device,
        resume_clock=resume_clock,
    )
    print("\n".join(summary_lines(setup, run_with_status(setup, status=not quiet))))
