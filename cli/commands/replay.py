"""`cbh replay`: a recording back into Rerun on its original time line, optionally reprocessed."""
from __future__ import annotations

from pathlib import Path

import typer


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
) -> None:
    """Re-log a recorded session into Rerun with the default blueprint (images, cloud masks,
    matches, 3D points, histogram, layer heights over time)."""
    import logging
    import time

    from cbh.errors import ConfigError
    from cbh.outputs.record import McapRecorder, open_session
    from cbh.outputs.rerun_view import RerunSink, parse_rerun_spec

    log = logging.getLogger("cbh.replay")
    if (station or record or cameras) and not reprocess:
        raise ConfigError("--station, --cameras and --record need --reprocess")
    if reprocess and station is None:
        raise ConfigError("--reprocess needs --station STATION.toml")
    mode, tgt = parse_rerun_spec(rerun, target)
    s = open_session(session)
    pipeline = recorder = None
    st = s.station
    if reprocess:
        from cbh.pipeline import Pipeline, PipelineConfig
        from cbh.geometry.station import load_station

        st = load_station(station)
        cfg = None if "pipeline" in st.sections else PipelineConfig.from_dict(s.config, where="recorded pipeline config")
        first = next(s.pairs(layers_only=True), None)
        pair_names = cameras or (",".join(first.result.cameras) if first else None)
        pipeline = Pipeline(st, pair_names, cfg)
        probe = next(s.pairs(), None)
        if probe is not None:  # a size mismatch fails before any output file is opened
            from cbh.imageio import check_image_size

            for cam in pipeline.cameras:
                if cam in probe.images:
                    check_image_size(probe.images[cam].frame(probe.index).image, st.camera(cam).model, f"recorded {cam}")
        if record is not None:
            recorder = McapRecorder(record, st, pipeline.config.to_dict(), overwrite=overwrite, protect=s.paths)
    sink = None
    n = 0
    t0 = time.perf_counter()
    try:
        if not no_viewer:
            cams = pipeline.cameras if pipeline else None
            if cams is None:
                first = next(s.pairs(layers_only=True), None)
                cams = first.result.cameras if first else None
            sink = RerunSink(st, mode, tgt, cameras=cams, recording_name=session.stem, bind=bind)
            if sink.url:
                print(f"serving on {sink.url}: connect a viewer with `rerun --connect {sink.url}`")
        for pair in s.pairs():
            if pipeline is not None:
                f1, f2 = pair.frames()
                if (f1.camera, f2.camera) != pipeline.cameras:
                    f1, f2 = pair.images[pipeline.cameras[0]].frame(pair.index), pair.images[pipeline.cameras[1]].frame(pair.index)
                result = pipeline.process(f1.image, f2.image, pair.time_utc)
                if recorder is not None:
                    recorder.write((f1, f2), result)
                if sink is not None:
                    sink.write((f1, f2), result)
            elif sink is not None:
                sink.write_images({c: (im.data, im.format) for c, im in pair.images.items()}, pair.result)
            n += 1
        if sink is not None:
            for t, stats in s.statuses():
                sink.log_status(t, stats)
    finally:
        if sink is not None:
            sink.close()
        if recorder is not None:
            recorder.close()
    what = "reprocessed" if reprocess else "replayed"
    dest = {"save": f" into {tgt}", "connect": f" to {tgt or 'the local viewer'}"}.get(mode, "") if sink else ""
    print(f"{what} {n} pairs{dest} in {time.perf_counter() - t0:.1f} s" + (f"; recorded {record}" if recorder else ""))
    log.debug("replay done")
