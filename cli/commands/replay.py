"""`cbh replay`: a recording back into Rerun on its original time line, optionally reprocessed."""
from __future__ import annotations

import sys
from pathlib import Path

import typer

from cbh.errors import ConfigError


def register(app: typer.Typer) -> None:
    app.command("replay")(replay_cmd)


def replay_cmd(
    session: Path = typer.Argument(..., help="SESSION.mcap (or a directory of rotated files)."),
    target: str = typer.Argument(None, help="OUT.rrd for `--rerun save`, URL for `--rerun connect`."),
    rerun: str = typer.Option("spawn", "--rerun", help="spawn | serve | connect [URL] | save OUT.rrd (or just OUT.rrd)."),
    reprocess: bool = typer.Option(False, "--reprocess", help="Run the pipeline again on the recorded images."),
    station: Path = typer.Option(None, "--station", help="Station TOML for --reprocess (e.g. a new calibration)."),
    cameras: str = typer.Option(None, "--cameras", help="Camera pair for --reprocess (default: the recorded pair)."),
    record: Path = typer.Option(None, "--record", help="With --reprocess: record the new results to NEW.mcap."),
    no_viewer: bool = typer.Option(False, "--no-rerun", help="Do not log to Rerun (e.g. only --reprocess --record)."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace an existing --record file (never the input)."),
    bind: str = typer.Option(None, "--bind", metavar="ADDR",
                             help="Address of the --rerun serve server (default 127.0.0.1; 0.0.0.0: every interface)."),
    device: str = typer.Option("cpu", "--device", help="With --reprocess: where the dense work runs (cpu, or a torch device, e.g. cuda)."),
    site: list[str] = typer.Option(None, "--site", metavar="[NAME=]LAT,LON[,ALT_M]", help="Show the GHI nowcast at this "
                                   "site (repeatable; plants and @sites.csv as in `cbh export --product irradiance`) "
                                   "beside each pair's cloud shadow on the ground."),
    pyranometer: Path = typer.Option(None, "--pyranometer", help="With --site: the measured GHI (CSV) beside the nowcast "
                                     "(default: the recorded [station] pyranometer)."),
) -> None:
    """Re-log a recorded session into Rerun with the default blueprint (images, cloud masks,
    matches, 3D points, histogram, layer heights over time).

    With --rerun serve the server stays up after the replay ends, so a viewer that connects
    later still gets everything: stop it with Ctrl-C."""
    if (station or record or cameras) and not reprocess:
        raise ConfigError("--station, --cameras and --record need --reprocess")
    if reprocess and station is None:
        raise ConfigError("--reprocess needs --station STATION.toml")
    from cbh.actions.replay import replay  # on use (cold start of the other commands)
    from cbh.outputs.rerun_view import parse_rerun_spec

    spec = None if no_viewer else parse_rerun_spec(rerun, target)
    if pyranometer is not None and not site:
        raise ConfigError("--pyranometer needs --site (the place whose nowcast it is compared with)")
    r = replay(session, rerun=spec, station=station, cameras=cameras, record=record, overwrite=overwrite, bind=bind,
               device=device, sites=site or None, pyranometer=pyranometer,
               on_viewer=lambda s: s.url and print(f"serving on {s.url}: connect a viewer with `rerun --connect {s.url}`"),
               on_end=_serve_until_interrupted if spec is not None and spec[0] == "serve" else None)
    dest = {"save": f" into {r.target}", "connect": f" to {r.target or 'the local viewer'}"}.get(r.mode, "")
    print(f"{'reprocessed' if r.reprocessed else 'replayed'} {r.pairs} pairs{dest} in {r.seconds:.1f} s"
          + (f" ({r.failed} failed)" if r.failed else "") + (f"; recorded {r.recorded}" if r.recorded else ""))


def _serve_until_interrupted(sink) -> None:
    """Keep the ``serve`` server up for viewers that connect after the replay, until Ctrl-C
    (or SIGTERM / SIGHUP); then return normally, so the replay ends cleanly."""
    import signal
    import time

    def stop(signum, frame):
        raise KeyboardInterrupt

    old = {sig: signal.signal(sig, stop) for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)}
    try:  # the handlers first: a Ctrl-C right after the line below is a clean stop too
        print(f"replay ended; still serving on {sink.url} for viewers that connect later: press Ctrl-C to stop",
              file=sys.stderr, flush=True)
        while True:
            time.sleep(1.0)
    except KeyboardInterrupt:
        pass
    finally:
        for sig, handler in old.items():
            signal.signal(sig, handler)
