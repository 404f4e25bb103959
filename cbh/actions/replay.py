"""``cbh replay`` in library terms: a recording back into Rerun, or reprocessed by the service loop.

- Plain replay: every recorded pair (images as received, recorded results) is logged to a
  :class:`~cbh.outputs.rerun_view.RerunSink` on its original time line, then the recorded
  service status.
- Reprocess: the same :class:`cbh.live.service.Service` loop as ``cbh run``, over two
  :class:`~cbh.outputs.record.RecordingSource` (one per camera, non-live: nothing dropped),
  a pipeline for the new station, and the sinks asked for (MCAP recorder, Rerun). Recorded
  frames are paired again by time with the station's ``[service] pair_tolerance_s``.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cbh.actions.run import RunSetup, check_writable, open_sink
from cbh.errors import RecordingError
from cbh.interfaces import ResultSink
from cbh.live.service import OPERATOR_STOPS, ServiceConfig

__all__ = ["ReplayReport", "replay"]


@dataclass
class ReplayReport:
    """What a replay did."""

    pairs: int  # pairs logged (replay) or processed (reprocess)
    reprocessed: bool
    mode: str | None  # Rerun mode, None without a viewer
    target: str | None  # Rerun target (PATH.rrd, URL)
    url: str | None  # the serve URL, if serving
    recorded: Path | None  # the new recording (reprocess)
    seconds: float
    failed: int = 0  # pairs the pipeline rejected (reprocess)


def replay(session, *, rerun: tuple[str, str | None] | None = ("spawn", None), station=None, cameras=None,
           record=None, on_viewer=None, on_end=None, overwrite: bool = False, bind: str | None = None,
           device: str = "cpu", sites=None, pyranometer=None) -> ReplayReport:
    """Replay (``station`` None) or reprocess (``station`` given) a recorded session.

    Parameters
    ----------
    session : path-like
        SESSION.mcap or a directory of rotated files.
    rerun : (mode, target) or None
        A validated Rerun spec (:func:`cbh.outputs.rerun_view.parse_rerun_spec`); None: no viewer.
    station : path-like or Station, optional
        Reprocess with this station (e.g. a new calibration).
    cameras : str, optional
        Camera pair for reprocessing, ``"cam1,cam2"`` (default: the recorded pair).
    record : path-like, optional
        Reprocess only: record the new results to this MCAP file.
    on_viewer : callable (RerunSink) → None, optional
        Called once the viewer is open (e.g. to print the serve URL).
    on_end : callable (RerunSink) → None, optional
        Called once everything is logged, before the viewer's stream closes (not after a
        reprocess stopped by a signal): e.g. to keep a ``serve`` server up for viewers that
        connect later, until Ctrl-C.
    overwrite : bool
        Replace an existing ``record`` file (never one of the session's own files).
    bind : str, optional
        Address of ``serve`` (default 127.0.0.1).
    device : str
        Reprocess only: where the pipeline's dense work runs (``"cpu"``, ``"cuda"`` …).
    sites : list of str, optional
        Replay only: ground sites (``--site`` as in ``cbh export --product irradiance``) whose
        GHI nowcast (5 and 10 min ahead), clear sky and, with ``pyranometer`` (or the recorded
        ``[station] pyranometer``), measured GHI are shown over time beside each pair's cloud
        shadow on the ground with the sites marked.
    """
    from cbh.fileio import refuse_inputs
    from cbh.outputs.record import open_session

    refuse_inputs([rerun[1] if rerun and rerun[0] == "save" else None], [session, station, pyranometer], "--rerun save")
    if (sites or pyranometer is not None) and station is not None:
        raise RecordingError("--site and --pyranometer show a recording's nowcast: not with --reprocess")
    # (--record onto the session: refused by _reprocess_setup, which says how)
    s = open_session(session)
    t0 = time.perf_counter()
    if station is None:
        if record is not None or cameras is not None:
            raise RecordingError("a new recording or camera pair needs reprocessing with a station")
        nowcast = _Nowcast(session, s, sites, pyranometer) if sites and rerun is not None else None
        n = _replay_recorded(s, rerun, Path(session).stem, on_viewer, bind, on_end, nowcast)
        return ReplayReport(n, False, rerun[0] if rerun else None, rerun[1] if rerun else None,
                            None, None, time.perf_counter() - t0)
    setup, viewer = _reprocess_setup(s, station, cameras, rerun, record, Path(session).stem, overwrite, bind, device)
    if viewer is not None and on_viewer is not None:
        on_viewer(viewer)
    try:
        stats = setup.service().run()
        if viewer is not None and on_end is not None and stats.stop_reason not in OPERATOR_STOPS:
            on_end(viewer)
    except BaseException:
        if viewer is not None:
            try:
                viewer.close()
            except Exception:
                pass  # the first error is the one to report
        raise
    if viewer is not None:
        viewer.close()
    return ReplayReport(stats.pairs_processed, True, rerun[0] if rerun else None, rerun[1] if rerun else None,
                        viewer.url if viewer is not None else None, Path(record) if record is not None else None,
                        time.perf_counter() - t0, failed=stats.pairs_failed)


class _Nowcast:
    """A recording's nowcast at sites for the viewer: the GHI series and each pair's shadow map."""

    def __init__(self, session, s, sites, pyranometer):
        from cbh.actions.nowcast import ghi_series
        from cbh.outputs.nowcast import parse_sites
        from cbh.pipeline.config import PipelineConfig

        st = s.station
        if pyranometer is None and st.pyranometer is not None and Path(st.pyranometer).is_file():
            pyranometer = st.pyranometer
        self.series = ghi_series([session], list(sites), pyranometer)
        self.station, self.grid = st, st.ground
        self.masks = PipelineConfig.from_dict(s.config, where="recorded pipeline config").masks
        places = parse_sites(list(sites), st)
        cells = {p.name: self.grid.index(float(p.enu_m[0]), float(p.enu_m[1])) for p in places}
        self.cells = {k: v for k, v in cells.items() if v is not None}

    def log(self, sink, result) -> None:
        from cbh.actions.pairground import pair_ground
        from cbh.geometry import ground

        pg = pair_ground(self.station, self.masks, result)
        shade = (ground.shadow_map(pg.camera, pg.labels, pg.heights, pg.sun_dir, self.grid,
                                   cloud_fraction=pg.cloud_fraction) if pg.valid else
                 np.full((self.grid.n, self.grid.n), np.nan, np.float32))
        sink.log_shadow(result.time_utc, shade, self.cells)


def _replay_recorded(s, rerun, name: str, on_viewer, bind=None, on_end=None, nowcast: "_Nowcast | None" = None) -> int:
    from cbh.outputs.rerun_view import RerunSink

    if rerun is None:
        return sum(1 for _ in s.pairs(layers_only=True))
    first = next(s.pairs(layers_only=True), None)
    cams = first.result.cameras if first else None
    if rerun[0] == "save":
        check_writable(rerun[1])
    n = 0
    with RerunSink(s.station, rerun[0], rerun[1], cameras=cams, recording_name=name, bind=bind,
                   nowcast=nowcast is not None) as sink:
        if on_viewer is not None:
            on_viewer(sink)
        if nowcast is not None:
            sink.log_ghi(nowcast.series)
        for pair in s.pairs():
            sink.write_images({c: (im.data, im.format) for c, im in pair.images.items()}, pair.result)
            if nowcast is not None and pair.result.time_utc is not None:
                nowcast.log(sink, pair.result)
            n += 1
        for t, stats in s.statuses():
            sink.write_status(t, stats)
        if on_end is not None:
            on_end(sink)
    return n


class _Lent(ResultSink):
    """The viewer as the service sees it: written to, flushed, but closed by :func:`replay`
    (after ``on_end``), not by the service."""

    kind = "viewer"

    def __init__(self, sink):
        self.sink = sink

    def write(self, frames, result) -> None:
        self.sink.write(frames, result)

    def write_status(self, time_utc, stats: dict) -> None:
        self.sink.write_status(time_utc, stats)

    def close(self) -> None:
        """Nothing: :func:`replay` closes the viewer."""


def _reprocess_setup(s, station, cameras, rerun, record, name: str, overwrite: bool = False,
                     bind: str | None = None, device: str = "cpu"):
    """(RunSetup over the recording's frames, the RerunSink or None)."""
    from cbh.actions.station import load_station
    from cbh.geometry.station import Station
    from cbh.presets import station_path
    from cbh.imageio import check_image_size
    from cbh.outputs.record import McapRecorder, RecordingSource
    from cbh.pipeline import Pipeline, PipelineConfig

    st = station if isinstance(station, Station) else load_station(station_path(str(station)))
    cfg = None if "pipeline" in st.sections else PipelineConfig.from_dict(s.config, where="recorded pipeline config")
    first = next(s.pairs(layers_only=True), None)
    pair_names = cameras or (",".join(first.result.cameras) if first else None)
    if pair_names is not None and len(pair_names.split(",")) > 2:  # a camera network's recording
        from cbh.pipeline.network import StationPipeline

        pipeline = StationPipeline(st, pair_names, cfg, device=device)
    else:
        pipeline = Pipeline(st, pair_names, cfg, device=device)
    probe = next(s.pairs(), None)
    if probe is not None:  # a size mismatch fails before any output file is opened
        for cam in pipeline.cameras:
            if cam in probe.images:
                check_image_size(probe.images[cam].decode(), st.camera(cam).model, f"recorded {cam}")
    if record is not None and Path(record).resolve() in {p.resolve() for p in s.paths}:
        raise RecordingError(f"{record}: is the recording being reprocessed; record to a new file")
    sources = [RecordingSource(s, c) for c in pipeline.cameras]
    service_cfg = {k: v for k, v in st.sections.get("service", {}).items() if k == "pair_tolerance_s"}
    config = ServiceConfig.from_dict(service_cfg)
    sinks, recorder, viewer = [], None, None
    try:
        if record is not None:
            recorder = open_sink(record, lambda: McapRecorder(record, st, pipeline.config.to_dict(),
                                                              overwrite=overwrite, protect=s.paths))
            sinks.append(recorder)
        if rerun is not None:
            from cbh.outputs.rerun_view import RerunSink

            if rerun[0] == "save":
                check_writable(rerun[1])
            viewer = RerunSink(st, rerun[0], rerun[1], cameras=pipeline.cameras, recording_name=name, bind=bind)
            sinks.append(_Lent(viewer))
    except BaseException:
        for k in sinks:
            k.close()
        raise
    return RunSetup(st, pipeline.cameras, sources, pipeline, sinks, config, recorder, []), viewer
