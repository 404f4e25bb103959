"""``cbh reprocess`` in library terms: archives of one station or a network, on Ray.

What happens
------------
1. **Plan** (:func:`plan_reprocess`, on the driver): each station's inputs are scanned
   (:mod:`cbh.actions.archive`: image folders, recordings, video files), frames are paired
   by nearest time within the pairing tolerance, and the pairs are partitioned by station and
   UTC day. A day whose output is already complete (its sidecar ``….json`` exists and names
   the same station configuration, the same pairs and the requested formats) is skipped:
   that is the resume; a crash or Ctrl-C loses at most the days in flight.
2. **Run** (:func:`run_plan`): Ray actors (:class:`PairWorker`, one CPU each, and a share of
   a GPU with ``device="cuda"``) each build a station's :class:`~cbh.pipeline.Pipeline`
   once (heavy tables: remap, rays, masks) and keep it for every later chunk of that station.
   Days are cut into chunks of at most ``chunk_pairs`` pairs, of equal size within a day
   (:func:`_chunk_bounds`), so that a few long days still keep every worker busy. Ray's
   :class:`~ray.util.ActorPool` streams the chunks to the actors, one in flight per actor
   (back-pressure: a chunk is handed out when an actor is free); which chunk is decided then,
   from that actor's stretch (:class:`_ChunkQueue`, below). An actor sends back only what the
   day files need (a :class:`~cbh.outputs.export.PairRecord` per pair: no images, no height
   maps). Fault tolerance is Ray's: an actor whose process dies is restarted (``max_restarts``)
   and the chunk it was on retried (``max_task_retries``); once Ray gives up on an actor, it
   leaves the pool, the others take over its work, and the day of its lost chunk is left
   unwritten for a rerun (the resume below).
3. **Output** (on the driver, as each day completes): per station and UTC day
   ``OUT/<station>/cbh_<station>_<YYYYMMDD>.nc`` (CF-1.8 NetCDF, the variables of
   ``cbh export``) and ``….parquet`` (the ``cbh export`` table), each written atomically
   (temporary file + rename), then the sidecar ``….json`` (pairs, failures, time span, hashes),
   also atomically: the sidecar is the "day finished" mark. At the end (also after Ctrl-C)
   ``OUT/index.json`` lists every day present, what was done in this run, failures and skipped
   inputs.

Faults: an unreadable image, a frame missing from a truncated video or recording, a wrong
image size are counted per pair (``failures`` with the reason) and logged; never fatal. A day
all of whose pairs failed gets a sidecar and no data files.

Engine: with ``address=None`` a private Ray instance starts on demand with ``num_cpus=workers``
on the loopback interface only, and stops at the end; ``address="auto"``, ``"HOST:PORT"`` or
``"ray://HOST:PORT"`` joins an existing cluster, whose nodes must have cbh installed and see the
input and output paths (a shared file system). Exactness: each pair is processed by exactly
the code of ``cbh pair`` (``Pipeline.process`` on the decoded images and camera 1's time).

Temporal state (cloud motion, camera 2's clock offset: :mod:`cbh.pipeline.motion`) is handed
from pair to pair in time order as ``cbh run`` does (:class:`cbh.actions.run.MotionChain`).
A chunk starts with a lead-in: the station's pair just before its first (possibly the previous
day's last) is processed again for its state only, so every pair gets its motion exactly as in
one sequential run. An actor that itself processed that pair last (it works through a
contiguous stretch of chunks, :class:`_ChunkQueue`) skips the re-processing and starts from
the state the lead-in would leave (:func:`_as_lead_in`: the same frames, no offset history),
so the results do not depend on which actor took which chunk, nor on an actor's restart (a
restarted actor has no such state: its retried chunk re-processes the lead-in), and the extra
pairs are one per stretch (about one per actor and station), not one per chunk. A lead pair
more than the pipeline's ``motion.max_gap_s`` before the chunk's first pair (a day's first
chunk after the night) hands on nothing the pipeline uses: it is not re-processed, and an
actor continuing across such a gap starts fresh too (:func:`_lead_in_reach`). The horizon
obstacles a pipeline learns over frames (:meth:`~cbh.pipeline.run.Pipeline.auto_obstacles`)
are learned within each chunk from its own pairs (``forget_learned`` at its lead and at its
first pair), so on a station without a mask a chunk's first 10 pairs go without them and the
results depend on ``chunk_pairs``, never on the actor. That affinity
is why the chunks go through an actor pool that asks the queue at hand-out time, not through
Ray Data: its ``map_batches`` over an actor pool gives a batch to whichever actor is free, so
every chunk would re-process a lead-in pair (1/``chunk_pairs`` more work on 2 or more workers).
The running clock-offset estimate (a median over the last pairs) restarts at each chunk; where
a clock offset is compensated, the heights of a chunk's first pairs can differ from a
sequential run's within the 0.5 % the issue allows.
Where no temporal information is used the heights are identical to ``cbh pair``'s.
"""
from __future__ import annotations

import hashlib
import json
import logging
import math
import os
import sys
import time
from collections import OrderedDict, defaultdict
from dataclasses import dataclass, field
from datetime import date, datetime, timezone
from pathlib import Path
from typing import Callable

import cv2

from cbh.actions.archive import Inventory, PairRef, by_day, load_images, scan_station
from cbh.errors import CbhError, ConfigError, RecordingError
from cbh.fileio import atomic_write

__all__ = ["StationJob", "ReprocessOptions", "Plan", "DayWork", "Summary", "load_jobs", "plan_reprocess",
           "run_plan", "reprocess", "PairWorker", "start_ray", "daily_paths", "FORMATS"]

log = logging.getLogger(__name__)

FORMATS = ("netcdf", "parquet")
_SUFFIX = {"netcdf": ".nc", "parquet": ".parquet"}
_PIPELINES_PER_WORKER = 4  # stations whose pipeline one actor keeps (LRU)


# --- what to process ----------------------------------------------------------------------------

@dataclass(frozen=True)
class StationJob:
    """One station of the run: its station file, camera pair and per-camera input paths."""

    name: str
    station: object  # cbh.geometry.station.Station
    cameras: tuple[str, ...]  # two, or a camera network's N
    specs: dict[str, str]  # camera → absolute input path


def _bind_source(text: str) -> tuple[str | None, str, str]:
    left, sep, spec = text.partition("=")
    if not sep or not left.strip() or not spec.strip():
        raise ConfigError(f"--source {text!r}: expected CAMERA=PATH or STATION/CAMERA=PATH")
    st, slash, cam = left.strip().rpartition("/")
    return (st.strip() or None) if slash else None, cam.strip(), spec.strip()


def _read_entries(path: Path) -> list[dict]:
    """Station file → [{station, cameras, sources, base}] (one entry; a network file: one per station).

    Network file (TOML; paths relative to it)::

        [[stations]]
        station = "site-a/station.toml"   # required
        cameras = "cam1,cam2"             # optional (default: every camera of the station; 3+: a network)
        [stations.sources]                # optional (default: the cameras' `source` keys)
        cam1 = "/archive/site-a/cam1"
        cam2 = "/archive/site-a/cam2"
    """
    from cbh.tomlio import read_toml

    data = read_toml(path, "station")
    if "stations" not in data or "station" in data:
        return [{"station": path, "cameras": None, "sources": {}, "base": Path.cwd()}]
    stations = data["stations"]
    if set(data) - {"stations"}:
        raise ConfigError(f"{path.name}: unknown key(s) {', '.join(sorted(set(data) - {'stations'}))} in a network file")
    if not isinstance(stations, list) or not all(isinstance(s, dict) for s in stations) or not stations:
        raise ConfigError(f"{path.name}: `stations` must be an array of tables ([[stations]])")
    out = []
    for i, s in enumerate(stations):
        where = f"{path.name}: stations[{i}]"
        bad = set(s) - {"station", "cameras", "sources"}
        if bad:
            raise ConfigError(f"{where}: unknown key(s) {', '.join(sorted(bad))} (station, cameras, sources)")
        if not isinstance(s.get("station"), str):
            raise ConfigError(f"{where}.station: the station file (a string) is required")
        srcs = s.get("sources", {})
        if not isinstance(srcs, dict) or not all(isinstance(v, str) for v in srcs.values()):
            raise ConfigError(f"{where}.sources: a table camera = \"path\"")
        cams = s.get("cameras")
        if cams is not None and not isinstance(cams, str):
            raise ConfigError(f"{where}.cameras: a string \"cam1,cam2\"")
        out.append({"station": path.parent / s["station"], "cameras": cams, "sources": dict(srcs), "base": path.parent})
    return out


def load_jobs(stations, sources=(), cameras: str | None = None) -> list[StationJob]:
    """Stations of the run with their inputs.

    Parameters
    ----------
    stations : list of str or Path
        Station TOML files, preset names, or network TOML files (``[[stations]]``, see
        :func:`_read_entries`).
    sources : list of str
        ``CAMERA=PATH`` (the station with that camera; ambiguous in a network whose stations
        share camera names) or ``STATION/CAMERA=PATH``. Relative paths: from the current folder.
    cameras : str or None
        ``"cam1,cam2"`` for every station given directly (default: every camera of the station; three or more are a camera network).
    """
    from cbh.actions.station import load_station
    from cbh.presets import station_path

    if not stations:
        raise ConfigError("--station: give at least one station (or network) file")
    entries = []
    for s in stations:
        entries.extend(_read_entries(Path(station_path(str(s)))))
    jobs: list[dict] = []
    for e in entries:
        from cbh.pipeline.network import station_cameras

        st = load_station(e["station"])
        cams = [st.camera(n) for n in station_cameras(st, e["cameras"] or cameras)]
        specs = {}
        for c in cams:
            if c.name in e["sources"]:
                src = e["sources"][c.name]
                specs[c.name] = src if "://" in src else str((e["base"] / src).resolve())
            elif c.source:
                base = st.path.parent if st.path is not None else Path.cwd()
                specs[c.name] = str((base / c.source).resolve()) if "://" not in c.source else c.source
        jobs.append({"station": st, "cameras": tuple(c.name for c in cams), "specs": specs})
    names = [j["station"].name for j in jobs]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise ConfigError(f"station name(s) {', '.join(dup)} given twice: outputs are per station name")
    for text in sources:
        st_name, cam, spec = _bind_source(text)
        hits = [j for j in jobs if (st_name is None or j["station"].name == st_name) and cam in j["cameras"]]
        if not hits:
            raise ConfigError(f"--source {text!r}: no station " + (f"{st_name!r} " if st_name else "") +
                              f"with camera {cam!r} in the pair being processed "
                              f"({'; '.join(j['station'].name + ': ' + ','.join(j['cameras']) for j in jobs)})")
        if len(hits) > 1:
            raise ConfigError(f"--source {text!r}: camera {cam!r} is in stations "
                              f"{', '.join(j['station'].name for j in hits)}; write STATION/{cam}=PATH")
        hits[0]["specs"][cam] = spec if "://" in spec else str(Path(spec).expanduser().resolve())  # URLs: refused by the scan
    return [StationJob(j["station"].name, j["station"], j["cameras"], j["specs"]) for j in jobs]


# --- plan ------------------------------------------------------------------------------------

@dataclass
class ReprocessOptions:
    """Settings of one reprocessing run (``cbh reprocess`` options)."""

    out: Path
    workers: int | None = None  # actors (None: the local CPU count, or the cluster's CPUs)
    address: str | None = None  # None: private local Ray; "auto" | "HOST:PORT" | "ray://HOST:PORT"
    t_from: datetime | None = None  # pairs at or after this UTC time
    t_to: datetime | None = None  # pairs before this UTC time
    device: str = "cpu"  # "cpu" | "cuda" (actors ask Ray for a GPU share)
    formats: tuple[str, ...] = FORMATS
    chunk_pairs: int = 32  # at most this many pairs per task (a day is cut into equal chunks, _chunk_bounds)
    pair_tolerance_s: float | None = None  # None: the station's [service] pair_tolerance_s (default 0.5 s)
    actor_restarts: int = 3  # Ray's max_restarts and max_task_retries of each actor (then its chunk's day is left for a rerun)

    def __post_init__(self):
        self.out = Path(self.out)
        self.formats = tuple(dict.fromkeys(f.strip().lower() for f in self.formats if f.strip()))
        bad = [f for f in self.formats if f not in FORMATS]
        if bad or not self.formats:
            raise ConfigError(f"--format: {', '.join(bad) or '(none)'}: choose from {', '.join(FORMATS)}")
        if self.device not in ("cpu", "cuda"):
            raise ConfigError(f"--device: {self.device!r}: cpu or cuda")
        if self.workers is not None and self.workers < 1:
            raise ConfigError(f"--workers: must be >= 1, got {self.workers}")
        if self.chunk_pairs < 1:
            raise ConfigError(f"chunk_pairs: must be >= 1, got {self.chunk_pairs}")
        if self.t_from and self.t_to and self.t_to <= self.t_from:
            raise ConfigError("--to must be later than --from")


@dataclass
class DayWork:
    """The pairs of one station on one UTC day and whether its output is already complete."""

    station: str
    day: date
    pairs: list[PairRef]
    work_hash: str
    done: dict | None = None  # the sidecar of a finished earlier run (resume), else None


@dataclass
class Plan:
    jobs: list[StationJob]
    inventories: dict[str, Inventory]
    days: list[DayWork]
    station_hash: dict[str, str]
    options: ReprocessOptions

    @property
    def todo(self) -> list[DayWork]:
        return [d for d in self.days if d.done is None]


def daily_paths(out: Path, station: str, day: date) -> dict[str, Path]:
    """Output files of one station-day: ``netcdf``, ``parquet`` and the ``sidecar`` JSON.

    E-PROFILE style, the names of ``cbh export --daily``
    (:func:`cbh.outputs.export.daily_file_name`), in a folder per station.
    """
    from cbh.outputs.export import daily_file_name

    d = Path(out) / station
    tag = f"{day:%Y%m%d}"
    return {"netcdf": d / daily_file_name(station, tag, "netcdf"), "parquet": d / daily_file_name(station, tag, "parquet"),
            "sidecar": d / daily_file_name(station, tag, "json")}


def _station_hash(job: StationJob) -> str:
    """Changes whenever the station's geometry, calibration or pipeline settings change."""
    return hashlib.sha256((job.station.to_toml() + "\n" + ",".join(job.cameras)).encode()).hexdigest()[:16]


def _work_hash(pairs: list[PairRef]) -> str:
    """Changes when a day's pairs change: their times and places, and each input file's size (and,
    for images and videos, its modification time), so a corrupt image replaced under the same name
    redoes its day instead of keeping the failure (recordings: size only, since a truncated one is
    read through a repaired copy that each run writes anew)."""
    stats: dict[str, str] = {}

    def stamp(f) -> str:
        if f.path not in stats:
            try:
                st = os.stat(f.path)
                stats[f.path] = f"{st.st_size}" + ("" if f.kind == "recording" else f":{st.st_mtime_ns}")
            except OSError:
                stats[f.path] = "missing"
        return stats[f.path]

    h = hashlib.sha256()
    for p in pairs:
        for f in p.present:
            h.update(f"{f.time_utc.isoformat()}|{f.kind}|{f.path}|{f.index}|{stamp(f)}\n".encode())
    return h.hexdigest()[:16]


def _finished(paths: dict[str, Path], station_hash: str, work_hash: str, formats) -> dict | None:
    try:
        side = json.loads(paths["sidecar"].read_text())
    except (OSError, json.JSONDecodeError):
        return None
    if side.get("station_hash") != station_hash or side.get("work_hash") != work_hash:
        return None
    if not set(formats) <= set(side.get("formats", ())):
        return None
    if side.get("records", 0) and not all(paths[f].is_file() for f in formats):
        return None
    return side


def plan_reprocess(jobs: list[StationJob], opts: ReprocessOptions) -> Plan:
    """Scan every station's inputs, pair, partition by UTC day and find the days already done."""
    from cbh.live.service import ServiceConfig

    invs, days, hashes = {}, [], {}
    for job in jobs:
        tol = opts.pair_tolerance_s
        if tol is None:
            tol = ServiceConfig.from_dict(dict(job.station.sections.get("service", {}))).pair_tolerance_s
        inv = scan_station(job.cameras, job.specs, float(tol), opts.out / ".work" / job.name,
                           opts.t_from, opts.t_to)
        invs[job.name] = inv
        hashes[job.name] = sh = _station_hash(job)
        for day, pairs in by_day(inv.pairs).items():
            wh = _work_hash(pairs)
            done = _finished(daily_paths(opts.out, job.name, day), sh, wh, opts.formats)
            days.append(DayWork(job.name, day, pairs, wh, done))
    return Plan(jobs, invs, days, hashes, opts)


# --- the worker (a Ray actor) ----------------------------------------------------------------------

@dataclass(frozen=True)
class Chunk:
    station: str
    day: date
    index: int  # chunk number within the day
    pairs: tuple[PairRef, ...]
    lead: PairRef | None = None  # the station's pair just before ``pairs[0]``: processed for its motion state only


@dataclass
class ChunkResult:
    station: str
    day: date
    index: int
    records: list  # cbh.outputs.export.PairRecord, time order
    failures: list[dict]  # {"time_utc", "frames", "reason"}
    pid: int  # the actor process
    elapsed_s: float  # wall time of the chunk in the actor [s]
    cpu_s: float = math.nan  # CPU time of the actor process over the chunk, all its threads [s]
    lead_in: int = 0  # pairs processed for their motion state only (0 or 1)
    restarted: bool = False  # the first chunk of an actor that Ray restarted (the chunk it retried)
    finished_unix: float = math.nan  # when the actor finished the chunk (time.time(): how long actors wait between chunks)
    error: str | None = None  # a bug, not an input problem (e.g. the pipeline could not be built): the day is not written


class PairWorker:
    """Processes chunks of pairs; run as a Ray actor (``ray.remote(PairWorker)``).

    Each station's :class:`~cbh.pipeline.Pipeline` is built on the first chunk of that
    station and kept (up to 4 stations, least recently used dropped), so its tables are built
    once per actor.

    Parameters
    ----------
    stations : dict of str → (str, (str, str))
        Station name → (self-contained station TOML, :meth:`Station.to_toml`; camera pair).
        Text, not objects: small constructor arguments travel inline with the actor (Ray
        restarts an actor from them), and any node parses them the same way.
    device : str
        "cpu" or "cuda".
    threads : int
        OpenCV threads in this process (1: Ray gives each actor one CPU).
    """

    def __init__(self, stations: dict, device: str = "cpu", threads: int = 1):
        cv2.setNumThreads(int(threads))
        import tomllib

        from cbh.geometry.station import parse_station

        self.stations = {k: (parse_station(tomllib.loads(text)), tuple(cams)) for k, (text, cams) in stations.items()}
        self.device = device
        self._pipes: OrderedDict = OrderedDict()
        # station → (the last pair this actor processed, the state a lead-in of that pair leaves);
        # a restarted actor starts without it, so its retried chunk re-processes its lead-in pair
        self._last: dict[str, tuple[PairRef, object]] = {}
        self._restarted = _restarted_by_ray()

    def pid(self) -> int:
        return os.getpid()

    def pipeline(self, station: str):
        if station in self._pipes:
            self._pipes.move_to_end(station)
            return self._pipes[station]
        from cbh.pipeline import Pipeline
        from cbh.pipeline.network import StationPipeline

        st, cams = self.stations[station]
        if len(cams) > 2:  # a camera network
            pipe = StationPipeline(st, list(cams), device=self.device)
        else:
            pipe = Pipeline(st, f"{cams[0]},{cams[1]}", device=self.device)  # the dense work on the worker's device
        self._pipes[station] = pipe
        while len(self._pipes) > _PIPELINES_PER_WORKER:
            self._last.pop(self._pipes.popitem(last=False)[0], None)  # its handed-on state too
        return pipe

    def process(self, chunk: Chunk) -> ChunkResult:
        """Every pair of the chunk: records of those processed, failures (with reasons) of the rest.

        An exception outside the pairs (a bug; a pipeline that cannot be built) comes back as
        ``error``, with the chunk it belongs to, rather than as Ray's task error: Ray does not
        retry it (``retry_exceptions`` off: it would fail the same way again), and the driver
        leaves the chunk's day unwritten."""
        restarted, self._restarted = self._restarted, False
        t0, c0 = time.perf_counter(), time.process_time()
        try:
            res = self._process(chunk)
        except Exception as exc:
            last = (str(exc).strip().splitlines() or [""])[-1]
            res = ChunkResult(chunk.station, chunk.day, chunk.index, [], [], os.getpid(), 0.0,
                              error=f"{type(exc).__name__}: {last}")
        res.restarted = restarted
        res.elapsed_s, res.cpu_s = time.perf_counter() - t0, time.process_time() - c0
        res.finished_unix = time.time()
        return res

    def _process(self, chunk: Chunk) -> ChunkResult:
        from cbh.outputs.export import pair_record

        from cbh.actions.run import MotionChain

        pipe = self.pipeline(chunk.station)
        st = self.stations[chunk.station][0]
        motion = MotionChain()  # the temporal state handed from pair to pair, as in `cbh run`
        last = self._last.pop(chunk.station, None)
        lead_pair = chunk.lead if _lead_in_reach(chunk, pipe.config.motion.max_gap_s) else None
        if lead_pair is not None and last is not None and last[0] == lead_pair:
            lead = ()  # this actor's previous chunk ended with the lead pair: its state, no re-processing
            motion.state = last[1]
        else:
            lead = (lead_pair,) if lead_pair is not None else ()
        images = load_images([f for p in lead + chunk.pairs for f in p.present])
        records, failures = [], []
        for k, p in enumerate(lead + chunk.pairs):
            if k in (0, len(lead)):  # the chunk's pairs learn from themselves alone, on any actor (a lead-in:
                pipe.forget_learned()  # nothing, as on the actor that carries its state over instead)
            imgs = {f.camera: images[f] for f in p.present}
            bad = next((v for v in imgs.values() if isinstance(v, Exception)), None)
            if bad is None:
                try:
                    prev = motion.previous(p.time_utc)
                    if len(p.frames) > 2:  # a camera network: one image per camera present
                        result = pipe.process(imgs, p.time_utc, channels="bgr", previous=prev)
                    else:
                        result = pipe.process(imgs[p.frame1.camera], imgs[p.frame2.camera], p.time_utc,
                                              channels="bgr", previous=prev)  # decoded by OpenCV
                    motion.keep(result)
                    if k >= len(lead):
                        records.append(pair_record(result, st.altitude_m))
                    continue
                except CbhError as exc:
                    bad = exc
                except Exception as exc:  # a bad input must not end a year-long run; counted and logged
                    bad = exc
            motion.lost()
            if k < len(lead):
                continue  # the lead-in pair is another chunk's: counted there
            reason = str(bad) if isinstance(bad, CbhError) else f"{type(bad).__name__}: {bad}"
            failures.append({"time_utc": _iso(p.time_utc), "frames": [f.describe() for f in p.present],
                             "reason": reason})
        if chunk.pairs:
            self._last[chunk.station] = (chunk.pairs[-1], _as_lead_in(motion.state))
        return ChunkResult(chunk.station, chunk.day, chunk.index, records, failures, os.getpid(), 0.0,
                           lead_in=len(lead))


def _lead_in_reach(chunk: Chunk, max_gap_s: float) -> bool:
    """Whether the chunk's lead pair can hand its first pair anything: it lies at most the
    pipeline's ``motion.max_gap_s`` before it (beyond, the pipeline takes no motion from it, and
    the lead-in's clock offsets are dropped anyway, :func:`_as_lead_in`). A day's first chunk
    after a night's gap then starts fresh, whichever actor takes it, without re-processing the
    previous evening's last pair; so does the chunk an actor continues into after such a gap."""
    if chunk.lead is None or not chunk.pairs:
        return False  # (no pair to hand a state to)
    lead, first = chunk.lead, chunk.pairs[0]
    if lead.time_utc is None or first.time_utc is None:
        return True  # (the pipeline decides what an untimed pair hands on)
    return (first.time_utc - lead.time_utc).total_seconds() <= max_gap_s


def _restarted_by_ray() -> bool:
    """True in an actor that Ray restarted after its process died (Ray's runtime context says so)."""
    try:
        import ray

        return bool(ray.is_initialized() and ray.get_runtime_context().was_current_actor_reconstructed)
    except Exception:  # not in an actor (a plain PairWorker), or no Ray
        return False


def _as_lead_in(state):
    """The state a lead-in of the same pair leaves (processed with no previous state): its frames
    and time, no clock-offset history, no layer motion; None where the pair failed (a lead-in of
    it fails again). So a chunk that follows on the same actor gets exactly the state its lead-in
    would give, and the heights do not depend on which actor took which chunk."""
    from dataclasses import replace

    from cbh.pipeline.network import NetworkState

    if state is None or state.gray is None:
        return None
    if isinstance(state, NetworkState):  # a camera network: each pair's own state, as above
        return NetworkState(state.time_utc, {k: _as_lead_in(v) for k, v in state.pairs.items()})
    return replace(state, offsets_s=(), layer_rates=())


# --- the engine -------------------------------------------------------------------------------------

def start_ray(workers: int | None = None, address: str | None = None, device: str = "cpu") -> tuple[bool, int]:
    """Connect to Ray: a private local instance (``address=None``) or a cluster.

    A private instance listens on the loopback interface only (Ray's single-machine mode) and
    gets ``num_cpus=workers``. If this process is already connected to Ray (a test session, a
    notebook), that connection is used and left open.

    Returns
    -------
    owned : bool
        True if this call connected (the caller shuts down at the end).
    cpus : int
        CPUs Ray offers (the default worker count).
    """
    if address is None and "ray" not in sys.modules:
        # Ray reads these when it is imported, so they are set only before that (set later, this
        # process would keep Ray's defaults and the processes it starts would get these: a token
        # that the driver does not send). This one: Ray binds 127.0.0.1, not the host's address
        os.environ.setdefault("RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER", "0")
        # token authentication on, as Ray >= 2.59 does by default for a local instance, but said
        # explicitly: Ray's documented switch, which also keeps its notice ("Token authentication
        # is enabled for this Ray cluster …") off every run (a user's own setting wins)
        os.environ.setdefault("RAY_AUTH_MODE", "token")
    old_path = os.environ.get("PYTHONPATH")
    if address is None:
        # local workers import the very cbh this process runs (Ray's worker processes do not
        # always see a virtual environment's site-packages, and another cbh may be installed
        # system-wide): its folder goes first on the path of the processes Ray starts now (its
        # raylet, whose environment its workers inherit); this process's own is put back below
        import cbh

        root = str(Path(cbh.__file__).resolve().parent.parent)
        paths = [p for p in (old_path or "").split(os.pathsep) if p]
        if root not in paths:
            os.environ["PYTHONPATH"] = os.pathsep.join([root] + paths)
    try:
        return _init_ray(workers, address, device)
    finally:  # the caller's later subprocesses see its own path (not the repository's `cli/`)
        if old_path is None:
            os.environ.pop("PYTHONPATH", None)
        else:
            os.environ["PYTHONPATH"] = old_path


def _init_ray(workers: int | None, address: str | None, device: str) -> tuple[bool, int]:
    """:func:`start_ray` once the environment is set: import Ray, start or join it."""
    try:
        import ray
    except ImportError:
        raise ConfigError("cbh reprocess needs Ray: python3.11 -m pip install ray") from None
    owned = False
    if not ray.is_initialized():
        kw = dict(include_dashboard=False, log_to_driver=False, configure_logging=False)
        gpus = 0
        if address is None and device == "cuda":
            import torch

            gpus = torch.cuda.device_count()
            if not gpus:  # say so before Ray's seconds of start-up
                raise ConfigError("--device cuda: no CUDA device on this machine")
        try:
            if address is None:
                # "local": always a new private instance, never a `ray start` cluster found on this machine
                ray.init(address="local", num_cpus=workers or os.cpu_count() or 1, num_gpus=gpus, **kw)
            else:
                ray.init(address=address, **kw)
        except (ConnectionError, ValueError, RuntimeError) as exc:
            where = f"--address {address}" if address else "local Ray"
            raise ConfigError(f"{where}: cannot start or connect to Ray: {exc}") from None
        except ImportError as exc:  # ray:// needs the client extra
            raise ConfigError(f"--address {address}: {exc} (for ray:// addresses: pip install 'ray[client]')") from None
        owned = True
    cpus = int(ray.cluster_resources().get("CPU", 1))
    if device == "cuda" and not ray.cluster_resources().get("GPU", 0):
        if owned:
            ray.shutdown()
        raise ConfigError("--device cuda: Ray sees no GPU (no CUDA device here or in the cluster)")
    return owned, cpus


@dataclass
class Summary:
    """What a run did."""

    pairs_total: int = 0  # pairs in the planned days
    pairs_processed: int = 0  # processed in this run (successfully or not)
    pairs_resumed: int = 0  # in days finished by an earlier run
    failures: int = 0  # pairs that failed in this run
    days_written: int = 0
    days_resumed: int = 0
    days_failed: int = 0  # days not finished (worker kept dying, interrupted): a rerun retries them
    worker_restarts: int = 0  # actor processes Ray restarted (the chunk each was on retried by Ray)
    lost_chunks: int = 0  # chunks whose actor Ray gave up on (restarts used up): their days are left for a rerun
    workers: int = 0
    elapsed_s: float = 0.0
    interrupted: bool = False
    index: Path | None = None
    files: list[str] = field(default_factory=list)

    @property
    def pairs_per_s(self) -> float:
        return self.pairs_processed / self.elapsed_s if self.elapsed_s > 0 else math.nan


def _iso(t: datetime) -> str:
    return t.astimezone(timezone.utc).isoformat().replace("+00:00", "Z")


def _write_json(path: Path, obj) -> None:
    try:
        with atomic_write(path) as tmp:
            tmp.write_text(json.dumps(obj, indent=1, default=str) + "\n")
    except OSError as exc:
        raise RecordingError(f"cannot write {path}: {exc.strerror or exc}") from None


def _write_day(plan: Plan, job: StationJob, work: DayWork, records: list, failures: list[dict]) -> dict:
    """Data files (atomically), then the sidecar (atomically): the day is finished."""
    import cbh
    from cbh.outputs.export import write_records

    opts = plan.options
    paths = daily_paths(opts.out, job.name, work.day)
    paths["sidecar"].parent.mkdir(parents=True, exist_ok=True)
    records = sorted(records, key=lambda r: r.time_utc)
    uniq = []
    for r in records:
        if uniq and r.time_utc == uniq[-1].time_utc:
            log.warning("%s %s: a second pair at %s dropped (same input given twice?)", job.name, work.day,
                        _iso(r.time_utc))
            continue
        uniq.append(r)
    st = job.station
    info = {"station": st.name, "latitude_deg": st.latitude_deg, "longitude_deg": st.longitude_deg,
            "altitude_m": st.altitude_m, "cameras": job.cameras, "cbh_version": cbh.__version__,
            "metadata": dict(st.metadata)}  # what cbh export's session_records gives write_netcdf
    files = []
    if uniq:
        for fmt in opts.formats:
            files.append(str(write_records(uniq, info, paths[fmt], fmt)))
    side = {
        "station": job.name, "day": work.day.isoformat(), "cameras": list(job.cameras),
        "pairs": len(work.pairs), "records": len(uniq), "failures": failures,
        "time_span_utc": [_iso(uniq[0].time_utc), _iso(uniq[-1].time_utc)] if uniq else None,
        "files": files, "formats": list(opts.formats), "station_hash": plan.station_hash[job.name],
        "work_hash": work.work_hash, "cbh_version": cbh.__version__,
        "written_utc": _iso(datetime.now(timezone.utc)),
    }
    _write_json(paths["sidecar"], side)
    return side


def _write_index(plan: Plan, sides: dict[tuple[str, date], dict], failed: dict[tuple[str, date], str],
                 summary: Summary) -> Path:
    opts = plan.options
    stations = {}
    spans = []
    for job in plan.jobs:
        inv = plan.inventories[job.name]
        days = []
        for w in plan.days:
            if w.station != job.name:
                continue
            key = (w.station, w.day)
            side = sides.get(key) or w.done
            if side is not None:
                days.append({"day": w.day.isoformat(), "status": "resumed" if key not in sides else "written",
                             "pairs": side["pairs"], "records": side["records"], "failures": side["failures"],
                             "time_span_utc": side["time_span_utc"], "files": side["files"],
                             "sidecar": str(daily_paths(opts.out, w.station, w.day)["sidecar"])})
                if side["time_span_utc"]:
                    spans.extend(side["time_span_utc"])
            else:
                days.append({"day": w.day.isoformat(), "status": "not finished", "pairs": len(w.pairs),
                             "reason": failed.get(key, "interrupted")})
        stations[job.name] = {
            "cameras": list(job.cameras), "inputs": job.specs, "frames": inv.frames, "unpaired": inv.unpaired,
            "pairs": len(inv.pairs), "skipped_inputs": inv.skipped, "repaired_recordings": inv.repaired,
            "days": days,
        }
    index = {
        "cbh_reprocess": 1, "written_utc": _iso(datetime.now(timezone.utc)), "out": str(opts.out),
        "from_utc": _iso(opts.t_from) if opts.t_from else None, "to_utc": _iso(opts.t_to) if opts.t_to else None,
        "formats": list(opts.formats), "device": opts.device, "workers": summary.workers,
        "interrupted": summary.interrupted,
        "time_span_utc": [min(spans), max(spans)] if spans else None,
        "totals": {"pairs": summary.pairs_total, "processed": summary.pairs_processed,
                   "resumed": summary.pairs_resumed, "failures": summary.failures,
                   "days_written": summary.days_written, "days_resumed": summary.days_resumed,
                   "days_not_finished": summary.days_failed, "worker_restarts": summary.worker_restarts,
                   "lost_chunks": summary.lost_chunks,
                   "elapsed_s": round(summary.elapsed_s, 3)},
        "stations": stations,
    }
    path = opts.out / "index.json"
    _write_json(path, index)
    return path


class _ChunkQueue:
    """Chunks waiting for an actor, handed out so that each actor works through a contiguous
    stretch of one station's chunks: the lead-in pair of its next chunk is then its own last
    pair, and :meth:`PairWorker.process` re-processes none (one lead-in per stretch, not per chunk).
    This is what Ray's pool cannot know: which actor already holds the motion state a chunk needs.

    An actor without a stretch takes one on the station it was on while that station has work
    (else the station with the most chunks left per actor on it): an unclaimed stretch whole,
    else the larger half, the later in time, of that station's largest stretch (its owner keeps
    the earlier half). So every actor stays busy to the end, at the price of one lead-in per
    split; the stretch of an actor that Ray gave up on is taken over the same way.

    Parameters
    ----------
    chunks : dict of str → list of Chunk
        Per station, the chunks in time order (each chunk's lead is the previous one's last pair).
    """

    def __init__(self, chunks: dict[str, list[Chunk]]):
        self._chunks = {k: list(v) for k, v in chunks.items() if v}
        self._stretches = [[k, 0, len(v)] for k, v in self._chunks.items()]  # [station, next, end)
        self._mine: dict[int, list] = {}  # slot → its stretch
        self._station: dict[int, str] = {}  # slot → the station it is on

    def __len__(self) -> int:
        return sum(hi - lo for _, lo, hi in self._stretches)

    def next(self, slot: int) -> Chunk | None:
        """The next chunk for actor ``slot``; None when nothing is left."""
        s = self._mine.get(slot)
        if s is None or s[1] >= s[2]:
            s = self._claim(slot)
            if s is None:
                return None
        s[1] += 1
        return self._chunks[s[0]][s[1] - 1]

    def _claim(self, slot: int) -> list | None:
        self._stretches = [s for s in self._stretches if s[1] < s[2]]
        if not self._stretches:
            return None
        left: dict[str, int] = {}
        for k, lo, hi in self._stretches:
            left[k] = left.get(k, 0) + hi - lo
        st = self._station.get(slot)
        if st not in left:
            on = [v for k, v in self._station.items() if k != slot]
            st = max(left, key=lambda k: left[k] / (1 + on.count(k)))
        big = max((s for s in self._stretches if s[0] == st), key=lambda s: s[2] - s[1])
        owners = [k for k, v in self._mine.items() if v is big]
        if not owners:
            mine = big
        else:  # split: the owner keeps the earlier half, this actor takes the later (larger) half
            cut = big[1] + (big[2] - big[1]) // 2
            mine = [st, cut, big[2]]
            big[2] = cut
            self._stretches.append(mine)
        self._mine[slot] = mine
        self._station[slot] = st
        return mine


def _chunk_bounds(n_pairs: int, chunk_pairs: int) -> list[int]:
    """Cut points of a day into the fewest chunks of at most ``chunk_pairs`` pairs, their sizes
    differing by at most one (50 pairs at 16: 12, 13, 12, 13, not 16, 16, 16, 2: no short
    chunk paying a whole lead-in pair and a task for two pairs, and a shorter tail).

    >>> _chunk_bounds(50, 16)
    [0, 12, 25, 37, 50]
    >>> _chunk_bounds(32, 16)
    [0, 16, 32]
    """
    n = max(1, -(-n_pairs // chunk_pairs))
    return [(k * n_pairs) // n for k in range(n + 1)]


def run_plan(plan: Plan, on_event: Callable[[dict], None] | None = None) -> Summary:
    """Process every unfinished day of the plan on Ray; write the days as they finish and the index.

    ``on_event(dict)`` is called on the driver with ``{"event": "start", "pairs", "days",
    "workers"}``, ``{"event": "workers", "pids"}``, ``{"event": "dispatch", "slot", "station",
    "day", "chunk", "pairs"}`` (a chunk handed to actor ``slot``), ``{"event": "chunk", "station",
    "day", "chunk", "pairs", "failures", "pid", "elapsed_s", "cpu_s", "finished_unix", "lead_in", "restarted"}`` (the
    actor's wall and CPU time for the chunk and when it finished it, whether it re-processed a
    lead-in pair, whether Ray had restarted the actor and retried this chunk) and
    ``{"event": "day", …sidecar…}``.
    KeyboardInterrupt stops the run: finished days stay, the index is written, and the
    summary says ``interrupted``.
    """
    run = _Run(plan, on_event or (lambda e: None))
    plan.options.out.mkdir(parents=True, exist_ok=True)
    if not plan.todo:
        run.emit({"event": "start", "pairs": 0, "days": 0, "workers": 0})
        return run.finish()
    owned, cpus = start_ray(plan.options.workers, plan.options.address, plan.options.device)
    try:
        run.start_workers(cpus)
        run.stream()
    except KeyboardInterrupt:
        run.summary.interrupted = True
        log.warning("interrupted: finished days are kept; a rerun resumes the rest")
    finally:
        run.stop_workers(owned)
        run.finish()
    return run.summary


def _plan_chunks(plan: Plan) -> tuple[dict[str, list[Chunk]], dict[tuple[str, date], int]]:
    """The unfinished days cut into chunks (:func:`_chunk_bounds`), per station in time order,
    each with its lead-in pair (the pair before it, possibly the previous day's last), and the
    number of chunks per day."""
    by_station: dict[str, list[Chunk]] = defaultdict(list)
    expected: dict[tuple[str, date], int] = {}
    before: dict[tuple[str, date], PairRef | None] = {}  # the previous day's last pair: the day's lead-in
    last: dict[str, PairRef] = {}
    for w in sorted(plan.days, key=lambda d: (d.station, d.day)):
        before[(w.station, w.day)] = last.get(w.station)
        last[w.station] = w.pairs[-1]
    for w in plan.todo:
        bounds = _chunk_bounds(len(w.pairs), plan.options.chunk_pairs)
        for n, (i, j) in enumerate(zip(bounds, bounds[1:])):
            lead = w.pairs[i - 1] if i else before[(w.station, w.day)]
            by_station[w.station].append(Chunk(w.station, w.day, n, tuple(w.pairs[i:j]), lead))
        expected[(w.station, w.day)] = len(bounds) - 1
    return by_station, expected


class _Run:
    """The driver's state of one :func:`run_plan`: the actors, the chunks still to hand out,
    the days' results so far, the summary; each step of the run is a method."""

    def __init__(self, plan: Plan, emit: Callable[[dict], None]):
        self.plan, self.opts, self.emit = plan, plan.options, emit
        self.t_start = time.perf_counter()
        self.summary = s = Summary(pairs_total=sum(len(d.pairs) for d in plan.days))
        for d in plan.days:
            if d.done is not None:
                s.days_resumed += 1
                s.pairs_resumed += len(d.pairs)
        self.todo = plan.todo
        self.jobs = {j.name: j for j in plan.jobs}
        self.works = {(w.station, w.day): w for w in self.todo}
        self.by_station, self.expected = _plan_chunks(plan)
        self.queue = _ChunkQueue(self.by_station)  # handed out in contiguous stretches
        self.got: dict[tuple[str, date], list[ChunkResult]] = defaultdict(list)
        self.sides: dict[tuple[str, date], dict] = {}
        self.failed: dict[tuple[str, date], str] = {}
        self.actors: list = []

    # --- the workers ---------------------------------------------------------------------------

    def start_workers(self, cpus: int) -> None:
        """One actor per worker (at most Ray's CPUs and the chunks to do), each asked its pid.

        Ray restarts an actor whose process dies (``max_restarts``) and retries the chunk it was
        on (``max_task_retries``), up to ``actor_restarts`` times each; the restarted actor
        rebuilds its pipeline from the same constructor arguments."""
        import ray

        opts, s = self.opts, self.summary
        n = opts.workers or cpus
        if n > cpus:
            log.warning("%d workers asked, Ray offers %d CPUs: using %d", n, cpus, cpus)
            n = cpus
        n_workers = s.workers = max(1, min(n, len(self.queue)))
        gpu_share = 0.0
        if opts.device == "cuda":
            gpu_share = min(1.0, float(ray.cluster_resources().get("GPU", 0)) / n_workers)
        actor_cls = ray.remote(PairWorker).options(num_cpus=1, num_gpus=gpu_share, max_restarts=opts.actor_restarts,
                                                   max_task_retries=opts.actor_restarts)
        stations = {j.name: (j.station.to_toml(), j.cameras) for j in self.plan.jobs if j.name in self.by_station}
        self.emit({"event": "start", "pairs": sum(len(w.pairs) for w in self.todo), "days": len(self.todo),
                   "workers": n_workers})
        self.actors = [actor_cls.remote(stations, opts.device) for _ in range(n_workers)]
        self.emit({"event": "workers", "pids": ray.get([a.pid.remote() for a in self.actors])})

    def stop_workers(self, owned: bool) -> None:
        """A private Ray instance is shut down (its actors with it); on a shared cluster this
        run's actors are killed, freeing their CPUs and GPUs."""
        import ray

        if owned:
            ray.shutdown()
            return
        for a in self.actors:
            try:
                ray.kill(a, no_restart=True)
            except Exception:
                pass

    # --- chunks out and results in -------------------------------------------------------------

    def stream(self) -> None:
        """Every chunk through Ray's :class:`~ray.util.ActorPool`: a chunk goes to an actor when
        that actor is free (one in flight per actor: back-pressure, nothing queues up in Ray), and
        which chunk is decided then, from that actor's stretch (:class:`_ChunkQueue`). A result is
        counted, and its day written once complete, as it arrives. An actor that Ray gave up on
        (its restarts used up) leaves the pool, its chunk is lost and its day left for a rerun;
        the others take over its stretch."""
        import ray
        from ray.util import ActorPool

        pool = ActorPool(self.actors)
        slots = {id(a): k for k, a in enumerate(self.actors)}

        def submit(actor, _):
            slot = slots[id(actor)]
            chunk = self.queue.next(slot)  # not None: one submit per chunk
            ref = actor.process.remote(chunk)
            self.emit({"event": "dispatch", "slot": slot, "station": chunk.station, "day": chunk.day.isoformat(),
                       "chunk": chunk.index, "pairs": len(chunk.pairs)})
            return ref

        for _ in range(len(self.queue)):
            pool.submit(submit, None)  # an idle actor now, else queued in the pool until one is free
        while pool.has_next():
            try:
                res: ChunkResult = pool.get_next_unordered(timeout=1.0)  # the timeout: Ctrl-C is seen
            except TimeoutError:
                continue
            except ray.exceptions.RayError as exc:  # RayActorError: Ray's restarts and retries used up
                self.summary.lost_chunks += 1
                log.error("a chunk was lost (%s: %s); its day is left for a rerun", type(exc).__name__,
                          (str(exc).strip().splitlines() or [""])[-1])
                continue
            self._chunk_done(res)
        for key in list(self.expected):  # days short of a chunk: its worker is gone
            self._day_failed(key, "a chunk was lost: its worker died and Ray had used up its "
                                  f"{self.opts.actor_restarts} restarts (max_restarts), or Ray lost its result",
                             "; the day is left for a rerun")

    def _day_failed(self, key: tuple[str, date], reason: str, advice: str = "") -> None:
        self.failed[key] = reason
        log.error("%s %s: %s%s", key[0], key[1], reason, advice)
        self.got.pop(key, None)
        self.expected.pop(key, None)

    def _chunk_done(self, res: ChunkResult) -> None:
        """Count a chunk's pairs and failures; write its day once all the day's chunks are in."""
        s, key = self.summary, (res.station, res.day)
        s.worker_restarts += res.restarted  # Ray restarted this actor (its process died) and retried this chunk
        if key not in self.expected:
            return  # the day already failed
        if res.error is not None:  # a bug, not an input problem: the day is not written
            self._day_failed(key, f"error in worker: {res.error}")
            return
        self.got[key].append(res)
        s.pairs_processed += len(res.records) + len(res.failures)
        s.failures += len(res.failures)
        for f in res.failures:
            log.warning("pair failed: %s %s: %s", res.station, f["time_utc"], f["reason"],
                        extra={"cbh_station": res.station, "cbh_time": f["time_utc"]})
        self.emit({"event": "chunk", "station": res.station, "day": res.day.isoformat(), "chunk": res.index,
                   "pairs": len(res.records) + len(res.failures), "failures": len(res.failures), "pid": res.pid,
                   "elapsed_s": res.elapsed_s, "cpu_s": res.cpu_s, "finished_unix": res.finished_unix,
                   "lead_in": res.lead_in, "restarted": res.restarted})
        if len(self.got[key]) == self.expected[key]:
            self.expected.pop(key)
            self._write_day(key)

    def _write_day(self, key: tuple[str, date]) -> None:
        parts = sorted(self.got.pop(key), key=lambda r: r.index)
        recs = [r for p in parts for r in p.records]
        fails = [f for p in parts for f in p.failures]
        side = _write_day(self.plan, self.jobs[key[0]], self.works[key], recs, fails)
        self.sides[key] = side
        self.summary.days_written += 1
        self.summary.files.extend(side["files"])
        log.info("day written", extra={"cbh_station": key[0], "cbh_day": side["day"],
                                       "cbh_pairs": side["pairs"], "cbh_failures": len(fails)})
        self.emit(dict(side, event="day"))

    def finish(self) -> Summary:
        """The summary's last counts and the index (also after Ctrl-C)."""
        s = self.summary
        s.days_failed = len(self.todo) - s.days_written
        s.elapsed_s = time.perf_counter() - self.t_start
        s.index = _write_index(self.plan, self.sides, self.failed, s)
        return s


def reprocess(stations, sources=(), *, cameras: str | None = None, on_event=None, **options) -> tuple[Plan, Summary]:
    """Plan and run (see the module docstring); ``options`` are :class:`ReprocessOptions` fields."""
    from cbh.fileio import refuse_inputs

    opts = ReprocessOptions(**options)
    refuse_inputs([opts.out], [*(stations if isinstance(stations, (list, tuple)) else [stations]),
                               *(s.partition("=")[2] or s for s in sources)], "--out")
    plan = plan_reprocess(load_jobs(stations, sources, cameras), opts)
    if not plan.days:  # as `cbh run` over the same folders: an error, and nothing written
        raise _nothing_found(plan)
    return plan, run_plan(plan, on_event)


def _nothing_found(plan: Plan) -> CbhError:
    """The one-line error of inputs that hold no pair at all (per station: frames found, unpaired)."""
    from cbh.errors import InputError

    opts = plan.options
    window = ""
    if opts.t_from or opts.t_to:
        window = f" between {_iso(opts.t_from) if opts.t_from else 'the start'} and {_iso(opts.t_to) if opts.t_to else 'the end'}"
    parts = []
    for job in plan.jobs:
        inv = plan.inventories[job.name]
        got = ", ".join(f"{c} {inv.frames.get(c, 0)} frames" for c in job.cameras)
        extra = f", {sum(inv.unpaired.values())} without a partner" if sum(inv.unpaired.values()) else ""
        extra += f", {len(inv.skipped)} inputs skipped" if inv.skipped else ""
        parts.append(f"{job.name}: {got}{extra}")
    return InputError(f"no pair to process{window}: found {'; '.join(parts)}")
