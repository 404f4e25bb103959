"""`cbh reprocess`: archives of a station or a network, per station and UTC day, on Ray."""
from __future__ import annotations

import sys
from pathlib import Path

import typer


def register(app: typer.Typer) -> None:
    app.command("reprocess")(reprocess_cmd)


def _utc(text: str | None, what: str):
    from cbh.errors import ConfigError
    from cbh.timeutil import parse_utc

    return None if text is None else parse_utc(text, what, ConfigError)


def reprocess_cmd(
    station: list[str] = typer.Option(..., "--station", help="Station TOML (repeat for a network), or a network TOML ([[stations]])."),
    source: list[str] = typer.Option([], "--source", help="CAM=PATH or STATION/CAM=PATH: image folder, recording (.mcap) or video."),
    out: Path = typer.Option(..., "--out", "-o", help="Output folder: OUT/<station>/cbh_<station>_<YYYYMMDD>.nc|.parquet, OUT/index.json."),
    workers: int = typer.Option(None, "--workers", "-j", help="Ray actors (default: all CPUs)."),
    address: str = typer.Option(None, "--address", help="Join a Ray cluster: auto | HOST:PORT | ray://HOST:PORT (default: a private local Ray)."),
    t_from: str = typer.Option(None, "--from", help="First time to process, ISO 8601 with a zone (2024-06-21T00:00:00Z)."),
    t_to: str = typer.Option(None, "--to", help="Process pairs before this time (ISO 8601 with a zone)."),
    device: str = typer.Option("cpu", "--device", help="cpu | cuda (each actor asks Ray for a GPU share)."),
    fmt: str = typer.Option("netcdf,parquet", "--format", help="netcdf, parquet or both (comma-separated)."),
    cameras: str = typer.Option(None, "--cameras", help="Cameras, e.g. cam1,cam2 or a network's cam1,cam2,cam3 (default: every camera of the station)."),
    pair_tolerance_s: float = typer.Option(None, "--pair-tolerance-s", help="Largest |t1 - t2| of a pair [s] (default: the station's, 0.5)."),
    chunk_pairs: int = typer.Option(32, "--chunk-pairs", help="At most this many pairs per Ray task (a day is cut into equal chunks)."),
) -> None:
    """Reprocess archives (image folders, recordings, videos): per station and UTC day, on Ray."""
    from cbh.actions.reprocess import reprocess
    from cbh.cli.progress import ReprocessProgress

    progress = ReprocessProgress()
    try:
        plan, s = reprocess(station, source, cameras=cameras, on_event=progress, out=out, workers=workers,
                            address=address, t_from=_utc(t_from, "--from"), t_to=_utc(t_to, "--to"), device=device,
                            formats=tuple(fmt.split(",")), chunk_pairs=chunk_pairs, pair_tolerance_s=pair_tolerance_s)
    finally:
        progress.stop()
    if not s.workers:
        print(f"nothing to do: {s.days_resumed} days ({s.pairs_resumed} pairs) already done; index: {s.index}")
        return
    print(f"{s.pairs_processed} pairs processed ({s.failures} failed) in {s.elapsed_s:.1f} s "
          f"({s.pairs_per_s:.2f} pairs/s, {s.workers} worker{'s' if s.workers != 1 else ''}); days: {s.days_written} written, "
          f"{s.days_resumed} already done, {s.days_failed} not finished; index: {s.index}")
    if s.interrupted:
        print("cbh: interrupted: finished days kept; run the same command again to resume", file=sys.stderr)
        raise typer.Exit(130)
    if s.pairs_processed and s.failures == s.pairs_processed:
        print(f"cbh: error: every pair failed ({s.failures} of {s.pairs_processed}: unreadable images, or images "
              "that do not match the station's calibration?); see the log lines above", file=sys.stderr)
        raise typer.Exit(2)
