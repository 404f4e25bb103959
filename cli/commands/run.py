"""`cbh run`: the live service (camera streams → pairs → heights → MCAP / Rerun / export)."""
from __future__ import annotations

from pathlib import Path

import typer

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
    cameras: str = typer.Option(None, "--cameras", help="The two cameras, e.g. cam1,cam2 (default: first two)."),
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
    rotate_s: float = typer.Option(None, "--rotate-s", help="Start a new MCAP file after this many seconds."),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="No status line."),
    device: str = typer.Option("cpu", "--device", help="Where the dense work runs: cpu (default) or a torch device, e.g. cuda."),
) -> None:
    """Run the service: pair the two cameras' frames, compute cloud-base heights, record/view/export.

    With no station and no source it runs the simulated default station (unb-lea, scene
    two-layers) for 6 pairs; `cbh run --record` records that to recordings/. Ends on
    --frames/--duration, when finite sources end, or on Ctrl-C/SIGTERM (finishes the pair in
    flight, closes every file, exit 0).
    """
    from cbh.errors import ConfigError
    from cbh.actions.run import build_run

    if record_path is not None and not record:
        raise ConfigError(f"unexpected argument {record_path!r} (a recording path goes after --record)")
    setup = build_run(
        station=station, scene=scene, sources=source or [], cameras=cameras,
        record=(record_path or True) if record else None, rerun=rerun, export=export,
        cadence_s=cadence_s, frames=frames, duration_s=duration, size_px=size,
        pair_tolerance_s=pair_tolerance_s, watch=watch, realtime=realtime,
        rotate_mb=rotate_mb, rotate_s=rotate_s, demo_frames=DEMO_FRAMES, device=device,
    )
    stats = _run_with_status(setup, status=not quiet)
    _report(setup, stats)


def _run_with_status(setup, status: bool):
    """Run the service; a live status line on a terminal, one line per pair otherwise."""
    import sys

    for n in setup.notes:
        print(n, file=sys.stderr)
    if not status:
        return setup.service().run()
    from rich.console import Console

    console = Console(stderr=True)
    if console.is_terminal:
        from rich.live import Live
        from rich.text import Text

        with Live(Text("starting…"), console=console, refresh_per_second=4, transient=False) as live:
            return setup.service(on_pair=lambda st, result: live.update(Text(st.line()))).run()

    def plain(st, result):
        if result is not None:
            print(f"{result.time_utc.isoformat().replace('+00:00', 'Z')}  {st.line()}", file=sys.stderr, flush=True)

    return setup.service(on_pair=plain).run()


def _report(setup, stats) -> None:
    """The end-of-run summary (stdout)."""
    print(f"processed {stats.pairs_processed} pairs ({stats.pairs_dropped} dropped, "
          f"{stats.pairs_skipped} skipped by cadence, {stats.pairs_failed} failed, "
          f"{sum(stats.unpaired.values())} unpaired frames); stopped: {stats.stop_reason}")
    if stats.last_layers_m:
        print("latest layers: " + ", ".join(f"{h:.0f} m" for h in stats.last_layers_m)
              + f" above the station ({setup.station.altitude_m:.0f} m a.s.l.)")
    for what, path in setup.outputs():
        print(f"{what}: {path}")
