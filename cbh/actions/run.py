"""``cbh run`` in library terms: station, sources, pipeline and sinks wired into one service.

The live wing (:mod:`cbh.live`) knows neither the pipeline nor any output; this action builds
them and hands the service a processor and sinks.
"""
from __future__ import annotations

import errno
import logging
import math
from dataclasses import replace
from pathlib import Path
from typing import Callable

import numpy as np

from cbh.errors import ConfigError, RecordingError
from cbh.live.service import Service, ServiceConfig
from cbh.pipeline.motion import PairState
from cbh.result import Frame, PairResult

_log = logging.getLogger(__name__)

__all__ = ["RunSetup", "MotionChain", "build_run", "open_sink", "check_writable", "summary_lines", "DEFAULT_ROTATE_S"]

#: A recording starts a new file after this much capture time unless --rotate-s/--rotate-mb
#: say otherwise (bounds the writer's in-memory index; one file per hour) [s].
DEFAULT_ROTATE_S = 3600.0


def open_sink(path, make):
    """Create a sink; an OS error (disk full, permission) becomes one RecordingError naming ``path``."""
    try:
        return make()
    except OSError as exc:
        if exc.errno == errno.ENOSPC:
            raise RecordingError(f"disk full while creating {path}") from None
        raise RecordingError(f"cannot write {path}: {exc.strerror or exc}") from None


def check_writable(path) -> None:
    """:class:`RecordingError` (one line, naming ``path``) unless a file can be created at ``path``.

    Used before handing a path to a writer that would fail later, or only in a background
    thread (Rerun's ``.rrd`` writer). A probe file that did not exist before is removed again.
    """
    p = Path(path)
    if p.is_dir():
        raise RecordingError(f"{p}: is a directory; give a file name")
    if not p.parent.is_dir():
        raise RecordingError(f"{p}: directory {p.parent} does not exist")
    existed = p.exists()
    try:
        with open(p, "ab"):
            pass
    except OSError as exc:
        raise RecordingError(f"cannot write {p}: {exc.strerror or exc}") from None
    if not existed:
        p.unlink(missing_ok=True)


class MotionChain:
    """The temporal state a run hands from one processed pair to the next
    (:class:`cbh.pipeline.motion.PairState`).

    Motion is computed only between pairs that follow each other: after a failed pair
    (:meth:`lost`) or a gap of more than ``gap_factor`` × the usual time between processed
    pairs (the cadence, or the median of the recent gaps when that is longer: frames were
    lost, dropped or corrupt), the next pair has no motion; the clock-offset history is kept
    across (a camera's offset is near-constant).

    Parameters
    ----------
    cadence_s : float
        The run's cadence [s] (0 = every pair).
    gap_factor : float
        A gap is a hole above this many usual intervals [1].
    """

    def __init__(self, cadence_s: float = 0.0, gap_factor: float = 2.5, start: PairState | None = None):
        self.cadence_s, self.gap_factor = float(cadence_s), float(gap_factor)
        self.state = None
        self.start = start if start is not None else PairState.start()  # (a resumed clock: PairState.resumed)
        self._gaps: list[float] = []

    def previous(self, time_utc):
        """The state to pass as ``previous`` for a pair captured at ``time_utc``."""
        s = self.state
        if s is None:  # a run's first pair: nothing known yet, or a recorded session's clock if recent
            st = self.start
            if st.offsets_s and st.time_utc is not None and time_utc is not None:
                # either way in time: an archive reprocessed, or a simulated run, may start before it
                age = abs((time_utc - st.time_utc).total_seconds())
                if age > RESUME_MAX_AGE_S:
                    _log.warning("the resumed clock offset was measured %.0f h from the run's first pair: not used "
                                 "(a camera without NTP drifts seconds a day)", age / 3600.0)
                    self.start = PairState.start()  # (said once)
                    return self.start
            return replace(st, time_utc=None)
        if s.gray is None or time_utc is None or s.time_utc is None:
            return s
        gap = (time_utc - s.time_utc).total_seconds()
        recent = sorted(self._gaps[-5:])
        usual = max(self.cadence_s, recent[len(recent) // 2] if recent else 0.0)
        if usual > 0 and gap > self.gap_factor * usual:
            return s.without_frames()
        return s

    def keep(self, result: PairResult) -> None:
        """Remember a processed pair's state (and the gap to the one before)."""
        s = self.state
        if s is not None and s.time_utc is not None and result.time_utc is not None:
            gap = (result.time_utc - s.time_utc).total_seconds()
            if gap > 0:
                self._gaps = (self._gaps + [gap])[-5:]
        self.state = result.state

    def lost(self) -> None:
        """A pair failed: no motion across it."""
        if self.state is not None:
            self.state = self.state.without_frames()


#: A recorded clock offset older than this is not resumed [s]: a camera without NTP drifts seconds a day.
RESUME_MAX_AGE_S = 86400.0


def resumed_clock(path, cameras: tuple[str, str], history: int):
    """The clock-offset history a run resumes from a recording (a ``.mcap`` file or a directory
    of them): (the last ``history`` finite per-pair estimates, ``clock_offset_pair_s``, of the
    same camera pair; the capture time of the last; a note for the run). Nothing (and a note
    saying why) when no pair of these cameras has an estimate."""
    from cbh.outputs.record import open_session

    session = open_session(path)
    offs, last = [], None
    for rp in session.pairs(layers_only=True):
        if tuple(rp.result.cameras[:2]) != tuple(cameras):
            continue
        o = rp.result.diagnostics.get("clock_offset_pair_s")
        if isinstance(o, (int, float)) and math.isfinite(o):
            offs.append(float(o))
            last = rp.time_utc
    if not offs:
        return (), None, f"{path}: no clock offset of {cameras[0]} + {cameras[1]} recorded: not resumed"
    kept = tuple(offs[-history:])
    return kept, last, (f"clock offset {cameras[1]} - {cameras[0]} resumed from {path}: "
                        f"{float(np.median(kept)):+.1f} s ({len(kept)} pairs up to {last:%Y-%m-%dT%H:%M:%SZ}; "
                        f"used if the run's first pair is within {RESUME_MAX_AGE_S / 3600:.0f} h of it)")


class RunSetup:
    """A ready-to-run service with its station, sources, pipeline and sinks (see :func:`build_run`)."""

    def __init__(self, station, cameras, sources, pipeline, sinks, config: ServiceConfig, recorder, notes):
        self.station, self.cameras, self.sources = station, cameras, sources
        self.pipeline, self.sinks, self.config = pipeline, sinks, config
        self.recorder = recorder  # McapRecorder or None
        self.notes = notes
        self.motion = MotionChain(config.cadence_s)

    @property
    def network(self) -> bool:
        """Three or more cameras (:class:`~cbh.pipeline.network.StationPipeline`)."""
        return len(self.cameras) > 2

    def prepare(self, f1: Frame, f2: Frame):
        """The part of a pair that does not need the pair before (:meth:`Pipeline.prepare`)."""
        return self.pipeline.prepare(f1.image, f2.image, f1.time_utc, channels="bgr")

    def process(self, *frames: Frame | None, prepared=None) -> PairResult:
        """One pair (or a network's frame set, None for a missing camera) through the pipeline,
        with the previous one's state (motion, clock offset). ``prepared``: a future of
        :meth:`prepare` for this pair (the service's look-ahead; pairs only)."""
        t = next(f.time_utc for f in frames if f is not None)
        try:
            if self.network:
                result = self.pipeline.process({f.camera: f.image for f in frames if f is not None}, t,
                                               channels="bgr", previous=self.motion.previous(t))
            else:
                prep = prepared.result() if prepared is not None else self.prepare(*frames)
                result = self.pipeline.finish(prep, previous=self.motion.previous(t))
        except Exception:
            self.motion.lost()
            raise
        self.motion.keep(result)
        return result

    def service(self, on_pair: Callable | None = None) -> Service:
        """The :class:`Service` for this run; ``on_pair(stats, result)`` is called after each pair."""
        return Service(self.sources, self.process, self.sinks, self.config, on_pair=on_pair,
                       prepare=None if self.network else self.prepare)

    def outputs(self) -> list[tuple[str, str]]:
        """What this run writes: ("recorded" | "exported", path) pairs."""
        return [(s.kind, str(p)) for s in self.sinks if s.kind in ("recorded", "exported")
                for p in s.output_paths()]


def _rerun_args(spec: str) -> tuple[str, str | None]:
    """``--rerun`` value → (mode, target): ``MODE``, ``MODE=TARGET`` (``connect=URL``,
    ``save=PATH.rrd``), or a bare URL / PATH.rrd (validated by :func:`cbh.outputs.rerun_view.parse_rerun_spec`)."""
    s = spec.strip()
    for mode in ("spawn", "serve", "connect", "save"):
        for sep in ("=", ":"):
            if s.lower().startswith(mode + sep):
                return mode, s[len(mode) + 1:] or None
    return s, None


def build_run(*, station=None, scene=None, sources=(), cameras=None, record=None, rerun=None, export=None,
              cadence_s=None, frames=None, duration_s=None, size_px=None, pair_tolerance_s=None, watch=False,
              realtime=False, rotate_mb=None, rotate_s=None, demo_frames: int = 6, overwrite: bool = False,
              bind: str | None = None, device: str = "cpu", resume_clock=None) -> RunSetup:
    """Assemble ``cbh run``: station, sources, pipeline, sinks, service config (no thread started).

    Cameras without a ``--source`` use their station ``source`` key; cameras with neither are
    simulated (``--scene``, default ``two-layers``). A run whose sources are all simulated and
    that has neither ``frames`` nor ``duration_s`` processes ``demo_frames`` pairs.
    ``record``: None (off), True (``recordings/<station>-<UTC>.mcap``; if that exists, the
    first free ``…_2.mcap``, ``…_3.mcap``, noted in :attr:`RunSetup.notes`) or a path (a
    ``.mcap`` file, refused if it exists unless ``overwrite``; or a directory, in which every
    file is created exclusively). ``bind``: address of ``--rerun serve`` (default 127.0.0.1).
    ``device``: where the pipeline's dense work runs (``cpu``, ``cuda`` …). ``resume_clock``: a
    recording whose clock-offset history the run starts from (default: the newest earlier one
    where it records, if any; :func:`resumed_clock`).
    """
    from cbh.presets import station_path
    from cbh.actions.station import load_station

    from cbh.fileio import refuse_inputs

    st = load_station(station_path(station) if station else station_path())
    names, specs, simulated = _camera_specs(st, cameras, _source_overrides(st, sources))
    srcs_in = [v for v in specs.values() if isinstance(v, (str, Path))] if isinstance(specs, dict) else []
    _check_shared_folders(names, specs)
    refuse_inputs([record if record is not True else None], srcs_in, "--record")
    refuse_inputs([export], srcs_in, "--export")
    cfg_dict = dict(st.sections.get("service", {}))
    over = {"cadence_s": cadence_s, "frames": frames, "duration_s": duration_s, "pair_tolerance_s": pair_tolerance_s}
    cfg_dict.update({k: v for k, v in over.items() if v is not None})
    ServiceConfig.from_dict(cfg_dict)  # cheap checks first: errors before the simulator is built
    rerun_args = _check_outputs(rerun, export, record, rotate_mb, rotate_s, overwrite)
    if record is not None and rotate_mb is None and rotate_s is None:
        # an MCAP writer keeps an index entry per message until the file is finished (~3 KB
        # per pair): an unrotated recording grows the process without bound
        rotate_s = DEFAULT_ROTATE_S
    notes: list[str] = []
    sim, start = None, None
    if simulated:
        sim, start = _simulator(st, scene, size_px, cfg_dict, demo_frames, notes)
        st = sim.station
    elif size_px is not None:
        raise ConfigError("an image size applies to simulated cameras only (real frames must match the calibration)")
    elif scene is not None:
        raise ConfigError("a scene applies to simulated cameras only, but both cameras have a source")
    config = ServiceConfig.from_dict(cfg_dict)
    srcs = _open_sources(st, names, specs, sim, config, start, watch=watch, realtime=realtime)
    pipeline, pcfg = _pipeline(st, names, config, device)
    start = _resume(st, names, record, resume_clock, pcfg.motion.offset_history, notes)
    sinks, recorder = _open_sinks(st, pcfg, record=record, export=export, rerun_args=rerun_args, bind=bind,
                                  rotate_mb=rotate_mb, rotate_s=rotate_s, overwrite=overwrite, notes=notes)
    setup = RunSetup(st, names, srcs, pipeline, sinks, config, recorder, notes)
    if start is not None:
        setup.motion.start = start
    return setup


def _resume(st, names, record, resume_clock, history: int, notes: list[str]) -> PairState | None:
    """The first pair's state when the run resumes a recorded clock offset (:func:`resumed_clock`):
    from ``--resume-clock REC``, or else from the newest earlier recording where this one goes
    (``--record`` to ``recordings/`` or to a directory). None: nothing to resume. A pair only:
    a network's offsets are each camera's against the reference, estimated afresh."""
    if len(names) != 2:
        return None
    src = Path(resume_clock) if resume_clock is not None else _previous_recording(st, record)
    if src is None:
        return None
    if resume_clock is not None and not src.exists():
        raise RecordingError(f"--resume-clock {src}: not found")
    try:
        offs, last, note = resumed_clock(src, tuple(names), history)
    except RecordingError as exc:
        if resume_clock is not None:
            raise
        notes.append(f"clock offset not resumed: {exc}")
        return None
    notes.append(note)
    return PairState.resumed(tuple(names), offs, last) if offs else None


def _previous_recording(st, record) -> Path | None:
    """The newest ``.mcap`` of this station where the run records (``recordings/<station>-*``
    for ``--record`` alone, any in a ``--record DIR``); None elsewhere."""
    if record is True:
        files = list(Path("recordings").glob(f"{st.name}-*.mcap"))
    elif record is not None and Path(record).is_dir():
        files = list(Path(record).glob("*.mcap"))
    else:
        return None
    files = [f for f in files if f.is_file() and f.stat().st_size > 0]
    return max(files, key=lambda f: f.stat().st_mtime) if files else None


def _check_shared_folders(names, specs: dict) -> None:
    """Two cameras on one image folder read the same frames unless its files are named by camera
    (``cam1_…``, ``cam2_…``): refused, as is a camera whose folder holds only another camera's
    images (cam2 pointed at cam1's folder ran to the end with identical "pairs" and no word)."""
    from cbh.live.sources import IMAGE_SUFFIXES, camera_prefixed

    folders: dict[Path, list[str]] = {}
    for n in names:
        spec = specs.get(n)
        if isinstance(spec, (str, Path)) and "://" not in str(spec) and Path(spec).is_dir():
            folders.setdefault(Path(spec).resolve(), []).append(n)
    for folder, cams in folders.items():
        try:
            files = [p.name for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES]
        except OSError:
            continue
        for c in cams:
            own = any(camera_prefixed(f, c) for f in files)
            others = [o for o in names if o != c and any(camera_prefixed(f, o) for f in files)]
            if not own and others:
                raise ConfigError(f"{c}: its folder {folder} holds {others[0]}'s images ({others[0]}_…), none named "
                                  f"{c}_…: give {c} its own camera's folder")
            if not own and len(cams) > 1:
                raise ConfigError(f"{', '.join(cams)}: one folder {folder} for several cameras, its images not named "
                                  f"by camera: they would all read the same frames (name them {cams[0]}_…, "
                                  f"{cams[1]}_…, or give each camera its own folder)")


def _source_overrides(st, sources) -> dict[str, str]:
    """``--source CAMERA=SPEC`` values → camera → spec (each camera of the station, once)."""
    overrides: dict[str, str] = {}
    for s in sources:
        cam, sep, spec = s.partition("=")
        if not sep or not cam.strip() or not spec.strip():
            raise ConfigError(f"camera source {s!r}: expected CAMERA=SPEC, e.g. cam1=rtsp://host/stream")
        if cam.strip() not in st.cameras:
            raise ConfigError(f"camera source {s!r}: no camera {cam.strip()!r} in station {st.name!r} "
                              f"(cameras: {', '.join(st.cameras)})")
        if cam.strip() in overrides:  # the second one silently won
            raise ConfigError(f"camera {cam.strip()} has two --source: {overrides[cam.strip()]!r} and "
                              f"{spec.strip()!r} (give each camera one)")
        overrides[cam.strip()] = spec.strip()
    return overrides


def _camera_specs(st, cameras, overrides: dict[str, str]):
    """(the cameras' names, camera → source spec, the simulated ones): a ``--source``, else the
    station's ``source`` key, else the simulator; every camera simulated or none. The cameras:
    ``--cameras`` (two, or a network's N), default every camera of the station."""
    from cbh.live.sources import is_sim_spec
    from cbh.pipeline.network import station_cameras

    names = tuple(station_cameras(st, cameras))
    specs = {n: overrides.get(n) or st.cameras[n].source or "sim" for n in names}
    simulated = [n for n in names if is_sim_spec(specs[n])]
    if simulated and len(simulated) != len(names):
        raise ConfigError(f"camera {simulated[0]} would be simulated and another not: give every camera a source, "
                          "or none")
    return names, specs, simulated


def _check_outputs(rerun, export, record, rotate_mb, rotate_s, overwrite):
    """The output options checked before anything is built; returns the parsed ``--rerun``."""
    rerun_args = None
    if rerun is not None:
        from cbh.outputs.rerun_view import parse_rerun_spec

        rerun_args = parse_rerun_spec(*_rerun_args(rerun))
    if export is not None and Path(export).suffix.lower() not in (".csv", ".parquet"):
        raise ConfigError(f"export file {export}: the name must end in .csv or .parquet")
    if record is None and (rotate_mb is not None or rotate_s is not None):
        raise ConfigError("file rotation (rotate_mb, rotate_s) needs a recording")
    if record is None and overwrite:  # `--export x.csv --overwrite` appended, silently
        raise ConfigError("--overwrite replaces an existing --record PATH and needs --record "
                          "(an --export file is always appended to)")
    return rerun_args


def _simulator(st, scene, size_px, cfg_dict: dict, demo_frames: int, notes: list[str]):
    """(the sky simulator of ``scene`` over the station, the scene's start time, UTC); a run
    without frames or duration gets ``demo_frames`` pairs (said in ``notes``)."""
    from datetime import timezone

    from cbh.presets import scene_path
    from cbh.sim import SkySimulator, load_scene

    sc = load_scene(scene_path(scene) if scene else scene_path())
    sim = SkySimulator(st, sc, size_px=size_px)
    if "frames" not in cfg_dict and "duration_s" not in cfg_dict:
        cfg_dict["frames"] = demo_frames
        notes.append(f"simulated station {sim.station.name} (scene {sc.name}): {demo_frames} pairs")
    return sim, sc.time_utc.astimezone(timezone.utc)


def _open_sources(st, names, specs, sim, config: ServiceConfig, start, *, watch: bool, realtime: bool) -> list:
    """One frame source per camera: simulated, or opened from its spec (relative paths from the
    station file's folder; one folder for both cameras: told apart by file-name prefix)."""
    from cbh.live.sources import open_source

    step = config.cadence_s if config.cadence_s > 0 else 10.0
    base_dir = st.path.parent if st.path is not None else None
    shared = {spec for spec in specs.values() if list(specs.values()).count(spec) > 1}
    srcs = []
    for n in names:
        if sim is not None:
            from cbh.sim import SimSource

            srcs.append(SimSource(n, sim, step_s=step, start_utc=start, realtime=realtime))
        else:
            srcs.append(open_source(
                st.cameras[n], specs[n], watch=watch, decode=False, interval_s=config.snapshot_interval_s,
                stall_timeout_s=config.stall_timeout_s, base_dir=base_dir, prefix=n if specs[n] in shared else None))
    return srcs


def _pipeline(st, names, config: ServiceConfig, device: str):
    """(the pair pipeline, or a network's :class:`~cbh.pipeline.network.StationPipeline`, and
    its config): the station's ``[pipeline]``, with the clock-offset tolerance of the pairing
    (an offset above it is what the clock_offset flag reports)."""
    from cbh.pipeline import Pipeline, PipelineConfig
    from cbh.pipeline.network import StationPipeline

    pcfg = PipelineConfig.from_dict(st.sections.get("pipeline", {}))
    pcfg = pcfg.replace(motion=replace(pcfg.motion, offset_tolerance_s=config.pair_tolerance_s))
    if len(names) > 2:
        return StationPipeline(st, list(names), pcfg, device=device), pcfg
    return Pipeline(st, f"{names[0]},{names[1]}", pcfg, device=device), pcfg


def _open_sinks(st, pcfg, *, record, export, rerun_args, bind, rotate_mb, rotate_s, overwrite: bool,
                notes: list[str]):
    """(the sinks, the recorder or None): MCAP recorder, layer export, Rerun view, in that
    order; if one cannot be opened, those already open are closed again."""
    sinks: list = []
    recorder = None
    try:
        if record is not None:
            recorder = _open_recorder(st, pcfg, record, rotate_mb, rotate_s, overwrite, notes)
            sinks.append(recorder)
        if export is not None:
            from cbh.outputs.export import LayerExporter

            sinks.append(open_sink(export, lambda: LayerExporter(export, st)))
        if rerun_args is not None:
            from cbh.outputs.rerun_view import RerunSink

            if rerun_args[0] == "save":
                check_writable(rerun_args[1])
            sinks.append(RerunSink(st, mode=rerun_args[0], target=rerun_args[1], bind=bind))
    except BaseException:
        for s in sinks:
            try:
                s.close()
            except Exception:
                pass
        raise
    return sinks, recorder


def _open_recorder(st, pcfg, record, rotate_mb, rotate_s, overwrite: bool, notes: list[str]):
    """The MCAP recorder: ``record`` True → ``recordings/<station>-<UTC>.mcap`` (the first free
    ``…_2.mcap`` … if taken, said in ``notes``), else the path given."""
    from datetime import datetime, timezone

    from cbh.outputs.record import McapRecorder

    if record is True:
        stamp = datetime.now(timezone.utc).strftime("%Y%m%dT%H%M%SZ")
        out = Path("recordings") / f"{st.name}-{stamp}.mcap"
        try:
            out.parent.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise RecordingError(f"cannot create {out.parent}: {exc.strerror}") from None
    else:
        out = Path(record)
    recorder = open_sink(out, lambda: McapRecorder(out, st, pcfg.to_dict(), rotate_mb=rotate_mb,
                                                     rotate_s=rotate_s, overwrite=overwrite,
                                                     unique=record is True))
    if recorder.path != out:
        notes.append(f"{out} exists: recording to {recorder.path}")
    return recorder


#: What each invalidating flag means, for the end-of-run summary.
_INVALID_CAUSE = {
    "geometry_mismatch": "disagreed with the station geometry (geometry_mismatch)",
    "clock_unknown": ("disagreed with the geometry, or had too few matches to judge it, while the cameras' clock "
                      "offset was not known yet, or had layers that an offset too small for the check to see would "
                      "move (clock_unknown)"),
    "clock_too_far": "could not be carried over the cameras' clock offset: the sky moved too far (clock_too_far)",
    "below_range": "had cloud below the lowest height searched (below_range)",
    "identical_images": "had both cameras deliver the same image (identical_images)",
    "night": "were taken at night, the sky too dark to tell cloud from clear sky (night)",
}


def summary_lines(setup: RunSetup, stats) -> list[str]:
    """The end-of-run summary: counts, stop reason, latest layers, files written."""
    lines = [f"processed {stats.pairs_processed} pairs ({stats.pairs_dropped} dropped, "
             f"{stats.pairs_skipped} skipped by cadence, {stats.pairs_failed} failed, "
             f"{sum(stats.unpaired.values())} unpaired frames); stopped: {stats.stop_reason}"]
    if stats.pairs_invalid:
        lines.append(f"{stats.pairs_invalid} pairs not valid ("
                     + ", ".join(f"{n} {_INVALID_CAUSE.get(f, f)}" for f, n in stats.invalid_counts.items())
                     + "): their layers are flagged, not reported as valid"
                     + (f" (last pair: {', '.join(stats.last_invalid)})" if stats.last_invalid else ""))
    silent = [n for n, src in stats.sources.items() if src.frames == 0]
    if silent and stats.pairs_processed:  # (none at all is an error of its own)
        lines.append(f"camera(s) {', '.join(silent)} delivered no frame: every result is from the others "
                     "(flag camera_missing)")
    corrupt = {n: src.corrupt for n, src in stats.sources.items() if src.corrupt}
    if corrupt:
        lines.append("unreadable frames skipped: " + ", ".join(f"{n} {k}" for n, k in corrupt.items()))
    if stats.last_layers_m:
        lines.append("latest layers: " + ", ".join(f"{h:.0f} m" for h in stats.last_layers_m)
                     + f" above the station ({setup.station.altitude_m:.0f} m a.s.l.)")
    lines += [f"{what}: {path}" for what, path in setup.outputs()]
    return lines
