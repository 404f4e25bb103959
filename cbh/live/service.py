"""The live service behind ``cbh run``: camera readers, pairing, processing, sinks, faults.

Threads: one reader per camera pulls frames from its :class:`~cbh.interfaces.FrameSource`
into a bounded queue; the calling thread pairs them (:class:`cbh.live.pairing.Pairer`), processes
one pair at a time and hands the result to every :class:`~cbh.interfaces.ResultSink`.

- **Cadence** (``cadence_s``): a pair is processed only if its time is at least
  ``cadence_s`` after the last processed pair's (frame time, so a video file or directory is
  subsampled the same way as a live camera); the pairs in between are *skipped*. 0 = every pair.
- **Falling behind** (any live source): when several pairs are waiting, the newest is processed
  and the older ones are *dropped* (counted); reader queues drop their oldest frame when full.
  With only finite sources (files, directories, lists, the simulator as fast as possible)
  nothing is dropped: readers wait for the processing.
- **Bounded**: frames are taken from the reader queues only when no accepted pair waits, so
  memory is bounded by ``queue_frames`` per camera and the pairer's ``max_waiting``, also at
  full speed; ``duration_s`` is checked on every pass of the loop.
- **Faults**: a source that raises :class:`SourceError` (or an OS error/timeout) is closed and
  reopened with exponential backoff (``backoff_initial_s`` doubling up to ``backoff_max_s``);
  a corrupt frame (:class:`ImageError`) is counted and skipped, and ``corrupt_limit`` of them in
  a row from a live source count as a source error. A pair the pipeline rejects is counted as
  failed. None of these stop the service. Per-source state: ``connecting``, ``streaming``,
  ``backoff``, ``ended`` (finite source done), ``failed`` (a finite source that cannot be read).
  An outage is warned about once when it begins (or its cause changes) and once when the source
  recovers; repeated warnings are rate-limited (``log_repeat_s``). Outages, recoveries, ends,
  failures and time jumps are written to every sink as status messages (``event`` in the stats).
- **Time**: see :class:`Service` (``time_jump_s``): a jump is flagged ``time_jump``, warned and
  resynchronized; it never silences the station.
- **Stopping**: ``frames`` processed pairs, ``duration_s`` wall seconds, every source ended,
  :meth:`Service.stop`, or SIGINT/SIGTERM/SIGHUP (the pair in flight is finished, every sink
  closed). A run that ends with no processed pair for any other reason raises a one-line
  error saying why. A sink that fails to write (disk full, unwritable) stops the service with
  :class:`RecordingError` after closing every sink, so what was written is kept.
"""
from __future__ import annotations

import copy
import errno
from pathlib import Path
import math
import logging
import queue
import signal
import threading
import time
from collections import OrderedDict, deque
from dataclasses import asdict, dataclass, field
from datetime import datetime, timedelta, timezone
from typing import Callable

from cbh.errors import CbhError, ConfigError, ImageError, RecordingError, SourceError
from cbh.flags import HIDDEN_OFFSET_SHARE, INVALIDATING
from cbh.interfaces import ResultSink
from cbh.result import Frame, PairResult
from cbh.tomlio import dataclass_from_table
from cbh.live.sources import EndOfStream, decode_frame

__all__ = ["ServiceConfig", "ServiceStats", "SourceStatus", "Service", "MemorySink", "STATES", "OPERATOR_STOPS"]

log = logging.getLogger(__name__)

#: A pair's two frame intervals this far apart (``clock_interval_ratio``) say so in the
#: ``clock_too_far`` warning: frames captured off their stamps (the real Fehmarn hour 0.989–1.014,
#: randomized skies on their stamps 0.995–1.002, frames up to ±1 s off 0.97–1.18).
FRAME_TIMING_SHARE = 0.02

STATES = ("connecting", "streaming", "backoff", "ended", "failed")


@dataclass(frozen=True)
class ServiceConfig:
    """Settings of the service loop (station file table ``[service]``)."""

    cadence_s: float = 0.0  # frame time between processed pairs [s]; 0 = every pair
    pair_tolerance_s: float = 0.5  # largest |t1 - t2| of a pair [s]
    queue_frames: int = 4  # frames buffered per camera between reader and pairing
    read_timeout_s: float = 0.25  # one source read blocks at most this long [s]
    stall_timeout_s: float = 10.0  # a live source silent this long is reconnected [s]
    backoff_initial_s: float = 0.5  # first reconnect delay [s]
    backoff_max_s: float = 30.0  # reconnect delay cap [s]
    snapshot_interval_s: float = 1.0  # HTTP snapshot polling period [s]
    frames: int | None = None  # stop after this many processed pairs
    duration_s: float | None = None  # stop after this many wall seconds [s]
    time_jump_s: float = 60.0  # a frame time this far off its camera's previous frame / the wall clock is a jump [s]
    corrupt_limit: int = 5  # this many corrupt frames in a row from a live source: reconnect with backoff
    log_repeat_s: float = 300.0  # an identical warning is repeated at most this often (with a count) [s]

    def __post_init__(self):
        for f in ("pair_tolerance_s", "read_timeout_s", "stall_timeout_s", "backoff_initial_s",
                  "backoff_max_s", "snapshot_interval_s", "time_jump_s", "log_repeat_s"):
            if not getattr(self, f) > 0:
                raise ConfigError(f"service.{f}: must be > 0, got {getattr(self, f)!r}")
        if self.cadence_s < 0:
            raise ConfigError(f"service.cadence_s: must be >= 0, got {self.cadence_s!r}")
        if self.queue_frames < 1:
            raise ConfigError(f"service.queue_frames: must be >= 1, got {self.queue_frames!r}")
        if self.corrupt_limit < 1:
            raise ConfigError(f"service.corrupt_limit: must be >= 1, got {self.corrupt_limit!r}")
        if self.time_jump_s <= self.pair_tolerance_s:
            raise ConfigError(f"service.time_jump_s: must exceed pair_tolerance_s ({self.pair_tolerance_s:g} s), "
                              f"got {self.time_jump_s!r}")
        if self.frames is not None and self.frames < 1:
            raise ConfigError(f"service.frames: must be >= 1, got {self.frames!r}")
        if self.duration_s is not None and not self.duration_s > 0:
            raise ConfigError(f"service.duration_s: must be > 0, got {self.duration_s!r}")

    @classmethod
    def from_dict(cls, d: dict | None, where: str = "service") -> "ServiceConfig":
        """From a TOML table; unknown keys, wrong types and non-finite numbers raise
        :class:`ConfigError` naming the key (:func:`cbh.tomlio.dataclass_from_table`)."""
        return dataclass_from_table(cls, dict(d or {}), where)

    def to_dict(self) -> dict:
        return {k: v for k, v in asdict(self).items() if v is not None}


@dataclass
class SourceStatus:
    """Live state of one camera's reader."""

    state: str = "connecting"
    frames: int = 0  # frames received
    corrupt: int = 0  # frames that could not be decoded (skipped)
    dropped: int = 0  # frames dropped because the queue was full (processing behind)
    reconnects: int = 0
    error: str | None = None  # last error message

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass
class ServiceStats:
    """Counters of one run (what the status line shows and the recorder stores)."""

    pairs_processed: int = 0
    pairs_dropped: int = 0  # newer pairs were waiting: processing fell behind
    pairs_skipped: int = 0  # closer than the cadence to the last processed pair
    pairs_failed: int = 0  # the pipeline rejected the pair
    unpaired: dict[str, int] = field(default_factory=dict)
    sources: dict[str, SourceStatus] = field(default_factory=dict)
    latency_s: float | None = None  # frame received → result written, last pair [s]
    process_s: float | None = None  # pipeline time of the last pair [s]
    last_time_utc: datetime | None = None
    last_layers_m: list[float] = field(default_factory=list)  # latest VALID layer heights above the ENU origin [m]
    pairs_invalid: int = 0  # pairs whose flags invalidate their layers (cbh.flags.INVALIDATING)
    last_invalid: list[str] = field(default_factory=list)  # invalidating flags of the last pair ([] = valid)
    invalid_counts: dict[str, int] = field(default_factory=dict)  # pairs carrying each invalidating flag
    sun_misaligned: bool = False  # the last pair that saw the sun saw it off (flag sun_misaligned)
    started_monotonic: float = field(default_factory=time.monotonic)
    stop_reason: str | None = None
    last_error: str | None = None

    def to_dict(self) -> dict:
        return {
            "pairs_processed": self.pairs_processed,
            "pairs_dropped": self.pairs_dropped,
            "pairs_skipped": self.pairs_skipped,
            "pairs_failed": self.pairs_failed,
            "unpaired": dict(self.unpaired),
            "corrupt": {c: s.corrupt for c, s in self.sources.items()},
            "reconnects": {c: s.reconnects for c, s in self.sources.items()},
            "sources": {c: s.state for c, s in self.sources.items()},
            "latency_s": self.latency_s,
            "process_s": self.process_s,
            "layers_m": list(self.last_layers_m),
            "pairs_invalid": self.pairs_invalid,
            "invalid_flags": list(self.last_invalid),
            "elapsed_s": round(time.monotonic() - self.started_monotonic, 3),
        }

    def line(self) -> str:
        """One-line status text."""
        layers = ", ".join(f"{h:.0f} m" for h in self.last_layers_m) or "-"
        if self.last_invalid:
            layers = f"- (not valid: {', '.join(self.last_invalid)})"
        src = " ".join(f"{c}:{s.state}" for c, s in self.sources.items())
        lat = f"{self.latency_s:.2f} s" if self.latency_s is not None else "-"
        extra = ""
        corrupt = sum(s.corrupt for s in self.sources.values())
        if corrupt:
            extra += f" corrupt {corrupt}"
        if self.pairs_failed:
            extra += f" failed {self.pairs_failed}"
        return (f"pairs {self.pairs_processed} dropped {self.pairs_dropped} skipped {self.pairs_skipped}"
                f" unpaired {sum(self.unpaired.values())}{extra} | latency {lat} | layers {layers} | {src}")


class MemorySink(ResultSink):
    """A :class:`~cbh.interfaces.ResultSink` that keeps everything in a list (tests)."""

    def __init__(self):
        self.items: list[tuple[tuple[Frame, Frame], PairResult]] = []
        self.status: list[tuple[datetime, dict]] = []
        self.closed = False

    def write(self, frames, result) -> None:
        if self.closed:
            raise RecordingError("MemorySink: write after close")
        self.items.append((frames, result))

    def write_status(self, time_utc, stats: dict) -> None:
        self.status.append((time_utc, stats))

    def close(self) -> None:
        self.closed = True


class _Throttle:
    """Rate limit for repeated warnings: the first of a kind is logged, repeats at most every
    ``interval_s`` with the count of the ones held back (a broken camera at 30 fps would
    otherwise write tens of gigabytes of log a day)."""

    def __init__(self, interval_s: float):
        self.interval_s = float(interval_s)
        self._last: dict[str, float] = {}
        self._held: dict[str, int] = {}
        self._lock = threading.Lock()

    def __call__(self, key: str, level: int, msg: str, **extra) -> bool:
        now = time.monotonic()
        with self._lock:
            last = self._last.get(key)
            if last is not None and now - last < self.interval_s:
                self._held[key] = self._held.get(key, 0) + 1
                log.debug(msg, extra=extra)
                return False
            held = self._held.pop(key, 0)
            self._last[key] = now
        if held:
            msg += f" ({held} more like this in the last {now - last:.0f} s)"
        log.log(level, msg, extra=extra)
        return True

    def reset(self, key: str) -> None:
        with self._lock:
            self._last.pop(key, None)
            self._held.pop(key, None)


class _Reader(threading.Thread):
    """Pulls one source into a bounded queue; reconnects with backoff; never raises.

    State changes that matter to an operator (an outage begins or changes cause, the source
    recovers, ends or fails) are logged once at WARNING and queued on ``events`` for the
    service to record as status messages; repeats of the same warning are rate-limited.
    """

    def __init__(self, source, cfg: ServiceConfig, status: SourceStatus, stop: threading.Event,
                 wake: threading.Event, opened: bool, events: queue.SimpleQueue, throttle: _Throttle):
        super().__init__(name=f"cbh-reader-{source.camera}", daemon=True)
        self.src, self.cfg, self.status = source, cfg, status
        self.live = bool(source.live)
        self.q: queue.Queue = queue.Queue(maxsize=cfg.queue_frames)
        self._stop_ev, self._wake = stop, wake
        self._opened = opened
        self._events, self._throttle = events, throttle
        self._outage_since: float | None = None  # monotonic start of the current outage
        self.done = False

    def _set(self, state: str, error: str | None = None) -> None:
        if state != self.status.state:
            log.debug(f"{self.src.camera}: {state}" + (f" ({error})" if error else ""),
                      extra={"cbh_camera": self.src.camera, "cbh_state": state, "cbh_error": error})
        self.status.state = state
        if error is not None:
            self.status.error = error

    def _event(self, event: str, error: str | None = None, **more) -> None:
        self._events.put({"event": event, "camera": self.src.camera, "state": self.status.state,
                          "error": error, **_event_clock(), **more})
        self._wake.set()

    def _outage(self, msg: str, backoff_s: float) -> None:
        """One warning when an outage begins (or its cause changes); repeats are rate-limited."""
        cam = self.src.camera
        text = msg if msg.startswith(cam) else f"{cam}: {msg}"
        key = f"outage:{cam}:{msg}"
        if self._outage_since is None:
            self._outage_since = time.monotonic()
            self._throttle.reset(key)
            self._event("outage", msg)
        self._throttle(key, logging.WARNING, f"{text}; reconnecting with backoff (now {backoff_s:.2g} s)",
                       cbh_camera=cam, cbh_event="reconnect", cbh_backoff_s=backoff_s)

    def _recovered(self) -> None:
        if self._outage_since is not None:
            down = time.monotonic() - self._outage_since
            self._outage_since = None
            log.warning(f"{self.src.camera}: streaming again after {down:.0f} s outage",
                        extra={"cbh_camera": self.src.camera, "cbh_event": "recovered", "cbh_outage_s": down})
            self._event("recovered", None, outage_s=round(down, 3))

    def run(self) -> None:
        backoff = self.cfg.backoff_initial_s
        cam = self.src.camera
        corrupt_run = 0  # corrupt frames in a row
        try:
            while not self._stop_ev.is_set():
                try:
                    if not self._opened:
                        self._set("connecting")
                        try:
                            self.src.open()
                        except ImageError as exc:  # e.g. a snapshot URL that serves no image
                            raise SourceError(str(exc)) from None
                        self._opened = True
                        self._set("streaming")
                    frame = self.src.read(self.cfg.read_timeout_s)
                    if frame is None:
                        continue
                    corrupt_run = 0
                    backoff = self.cfg.backoff_initial_s
                    self._recovered()
                    self.status.frames += 1
                    frame.received_s = time.monotonic()  # for the latency figure
                    self._put(frame)
                except ImageError as exc:
                    self.status.corrupt += 1
                    self.status.error = str(exc)
                    corrupt_run += 1
                    if self.live and corrupt_run >= self.cfg.corrupt_limit:
                        # a source that delivers only junk is broken, not unlucky: back off
                        corrupt_run = 0
                        self._fail_live(f"{cam}: {self.cfg.corrupt_limit} corrupt frames in a row ({exc})", backoff)
                        backoff = min(backoff * 2.0, self.cfg.backoff_max_s)
                        continue
                    self._throttle(f"corrupt:{cam}", logging.WARNING, f"{cam}: corrupt frame skipped: {exc}",
                                   cbh_camera=cam, cbh_event="corrupt")
                except EndOfStream:
                    self._set("ended")
                    self._event("ended")
                    return
                except (SourceError, OSError, TimeoutError) as exc:
                    msg = str(exc) if isinstance(exc, CbhError) else f"{type(exc).__name__}: {exc}"
                    if not self.live:
                        self._close_src()
                        self._opened = False
                        self._set("failed", msg)
                        self._event("failed", msg)
                        return
                    self._fail_live(msg, backoff)
                    backoff = min(backoff * 2.0, self.cfg.backoff_max_s)
                except Exception as exc:  # a bug in a source must not take the service down silently
                    log.error(f"{cam}: source error: {exc!r}", exc_info=True, extra={"cbh_camera": cam})
                    self._close_src()
                    self._opened = False
                    self._set("failed", f"{type(exc).__name__}: {exc}")
                    self._event("failed", f"{type(exc).__name__}: {exc}")
                    return
        finally:
            self.done = True
            self._wake.set()

    def _fail_live(self, msg: str, backoff: float) -> None:
        """Close a live source, log/record the outage, wait ``backoff`` seconds (or until stopped)."""
        self._close_src()
        self._opened = False
        self.status.reconnects += 1
        self._set("backoff", msg)
        self._outage(msg, backoff)
        self._stop_ev.wait(backoff)

    def _put(self, frame: Frame) -> None:
        if self.live:
            while True:
                try:
                    self.q.put_nowait(frame)
                    break
                except queue.Full:
                    try:
                        self.q.get_nowait()
                        self.status.dropped += 1
                    except queue.Empty:
                        pass
        else:
            while not self._stop_ev.is_set():
                try:
                    self.q.put(frame, timeout=0.1)
                    break
                except queue.Full:
                    continue
        self._wake.set()

    def _close_src(self) -> None:
        try:
            self.src.close()
        except Exception:  # closing a broken connection may fail again; nothing to keep
            pass


#: Stop reasons that mean the operator ended the run (no error when no pair was processed).
OPERATOR_STOPS = ("SIGINT", "SIGTERM", "SIGHUP", "stopped")


class _Corrupt(Exception):
    """A frame of a looked-ahead pair did not decode (handled as a corrupt frame, not a failed pair)."""

    def __init__(self, frame: Frame, exc: ImageError):
        super().__init__(str(exc))
        self.frame, self.exc = frame, exc


class _SinkWriter(threading.Thread):
    """Writes to the sinks on a thread of its own, in order: a pair's recording (PNG masks, zstd
    height map, protobuf) overlaps the next pair's processing instead of following it. At most
    ``depth`` items wait (the loop blocks beyond: memory stays bounded when the disk is slower
    than the pipeline). The first sink failure is kept (``error``) and every later item is
    dropped: the loop raises it at its next write, or at the end; nothing written before is lost.
    """

    def __init__(self, sinks, depth: int = 2):
        super().__init__(name="cbh-sinks", daemon=True)
        self.sinks = sinks
        self.q: queue.Queue = queue.Queue(maxsize=max(1, depth))
        self.error: RecordingError | None = None
        self.start()

    def put(self, kind: str, *args) -> None:
        """Queue ``write`` (pair, result) or ``write_status`` (time, stats) for every sink, or
        ``call`` (fn): run fn once everything queued before it is written."""
        self.q.put((kind, args))

    def run(self) -> None:
        while True:
            item = self.q.get()
            try:
                if item is None:
                    return
                if self.error is not None:
                    continue
                kind, args = item
                if kind == "call":  # after the items before it are written (the status line: pair flushed)
                    try:
                        args[0]()
                    except Exception as exc:  # a status line that cannot be shown never stops the recording
                        log.debug(f"status callback failed: {exc}")
                    continue
                for sink in self.sinks:
                    try:
                        getattr(sink, kind)(*args)
                    except Exception as exc:
                        self.error = _sink_error(sink, exc, "writing" if kind == "write" else "writing status to")
                        log.debug(str(self.error), extra={"cbh_event": "sink_failed"})
                        break
            finally:
                self.q.task_done()

    def drain(self) -> RecordingError | None:
        """Wait until everything queued is written; the first failure, if any."""
        self.q.join()
        return self.error

    def close(self) -> RecordingError | None:
        """Write what is queued, end the thread; the first failure, if any."""
        self.q.put(None)
        self.join()
        return self.error


class Service:
    """Run the sources → pairing → processing → sinks loop.

    Parameters
    ----------
    sources : sequence of FrameSource
        One per camera: camera 1's and camera 2's (pairs come out in this order), or a camera
        network's N (frame sets grouped by :class:`~cbh.live.pairing.Grouper`; a camera that
        delivers nothing is ``None`` in its set, and the set goes on without it).
    process : callable (Frame, Frame[, Frame …]) → PairResult
        Usually ``lambda f1, f2: pipeline.process(f1.image, f2.image, f1.time_utc, channels="bgr")``.
        Frames arrive decoded (``image`` set).
    sinks : sequence of ResultSink
        Each gets ``write((f1, f2), result)`` per pair, ``write_status(time_utc, stats)`` after
        each pair and on every source event (outage, recovery, end, failure, time jump; the
        stats then carry ``event``), and ``close()`` at the end.
    config : ServiceConfig
    on_pair : callable (ServiceStats, PairResult | None) → None, optional
        Called after every processed (or failed) pair and now and then while idle (status line).
    prepare : callable (Frame, Frame) → object, optional
        The part of a pair's processing that does not depend on the pair before. Given, and the
        sources not live (files, recordings: frames as fast as they can be processed), the next
        pair is decoded and prepared on a thread of its own while this one finishes; ``process``
        is then called as ``process(f1, f2, prepared=future)``. Live sources are processed one
        latest pair at a time (no look-ahead: the next pair has not been captured yet).

    Time checks (``time_jump_s`` = J): a frame is a *time jump* when it is stamped more than J
    ahead of the wall clock, more than J before its camera's previous frame, or (live cameras)
    J further ahead of its previous frame than the wall clock advanced. The jump is warned
    about at WARNING (rate-limited), the pair that contains it carries the flag ``time_jump``
    (and ``time_jump_s`` in its diagnostics), the pairer forgets the frames queued before a
    backward jump and the cadence restarts at the new time: a single bad time stamp never
    silences the station. Simulated sources are exempt from the wall-clock checks (their time
    is the scene's). Frames of one camera that cannot be paired because the other camera's
    clock is more than J away are warned about too (``clock disagreement``).
    """

    def __init__(self, sources, process: Callable[[Frame, Frame], PairResult], sinks=(),
                 config: ServiceConfig | None = None, on_pair: Callable | None = None,
                 prepare: Callable[[Frame, Frame], object] | None = None):
        sources = list(sources)
        if len(sources) < 2:
            raise ConfigError(f"the service needs two sources at least (one per camera), got {len(sources)}")
        self.sources, self.process, self.sinks = sources, process, list(sinks)
        self.cfg = config or ServiceConfig()
        self.on_pair = on_pair
        self.cameras = tuple(s.camera for s in sources)
        self.stats = ServiceStats(sources={s.camera: SourceStatus() for s in sources})
        self._stop = threading.Event()
        self._wake = threading.Event()
        self._signals = 0
        self._events: queue.SimpleQueue = queue.SimpleQueue()
        self._throttle = _Throttle(self.cfg.log_repeat_s)
        self._last_frame: dict[str, tuple[datetime, float | None]] = {}
        self._ahead_of_wall: dict[str, bool] = {}  # camera → its last frame was stamped in the future
        self._jumps: OrderedDict[tuple, float] = OrderedDict()  # (camera, seq, time) → jump [s]
        self._writer: _SinkWriter | None = None  # started by run()
        self.prepare = prepare
        self._ahead: tuple | None = None  # (pair, future of its decoding + prepare): the look-ahead
        self._ahead_pool = None

    # -- control ------------------------------------------------------------------------------
    def stop(self, reason: str = "stopped") -> None:
        """Ask the loop to end after the pair in flight (thread- and signal-safe)."""
        if self.stats.stop_reason is None:
            self.stats.stop_reason = reason
        self._stop.set()
        self._wake.set()

    def _on_signal(self, signum, _frame) -> None:
        self._signals += 1
        if self._signals > 1:
            raise KeyboardInterrupt  # second signal: stop now
        self.stop(signal.Signals(signum).name)

    # -- main loop ----------------------------------------------------------------------------
    def run(self, handle_signals: bool = True) -> ServiceStats:
        """Run until a stop condition; returns the counters. Every sink is closed on return.

        SIGINT, SIGTERM and SIGHUP (a closed SSH session) finish the pair in flight and close
        every file. A run that ends without one processed pair for any other reason (every
        source failed, ``duration_s`` passed with no pair, the files held no pair) raises
        :class:`SourceError` / :class:`InputError` saying why (after closing the sinks).
        """
        from cbh.live.pairing import make_pairer

        old = {}
        if handle_signals and threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
                old[sig] = signal.signal(sig, self._on_signal)
        readers: list[_Reader] = []
        try:
            # finite sources are opened now, so a missing file is one clear error at start
            opened = []
            for s in self.sources:
                if not s.live:
                    s.open()
                    self.stats.sources[s.camera].state = "streaming"
                opened.append(not s.live)
            pairer = make_pairer(self.cameras, self.cfg.pair_tolerance_s, max(2 * self.cfg.queue_frames, 8),
                                 self.cfg.time_jump_s, live=any(s.live for s in self.sources))
            self.stats.unpaired = pairer.stats.unpaired
            self.stats.started_monotonic = time.monotonic()
            readers = [_Reader(s, self.cfg, self.stats.sources[s.camera], self._stop, self._wake, o,
                               self._events, self._throttle)
                       for s, o in zip(self.sources, opened)]
            for r in readers:
                r.start()
            self._writer = _SinkWriter(self.sinks) if self.sinks else None
            self._loop(readers, pairer)
        finally:
            self._stop.set()
            if self._ahead_pool is not None:  # a looked-ahead pair not processed is dropped (not waited
                # for: the sinks close first, and a second Ctrl-C must not come between)
                self._ahead_pool.shutdown(wait=False, cancel_futures=True)
                self._ahead_pool, self._ahead = None, None
            for r in readers:
                r.join(timeout=2.0 + self.cfg.read_timeout_s)
            for s in self.sources:
                try:
                    s.close()
                except Exception as exc:
                    log.warning(f"{s.camera}: close failed: {exc}")
            try:
                self._record_events(final=True)
            except RecordingError:
                pass  # the sink error is raised below (or was already)
            close_err = self._close_sinks()
            for sig, h in old.items():
                signal.signal(sig, h)
        if close_err is not None:
            raise close_err
        if self.stats.pairs_processed == 0 and self.stats.stop_reason not in OPERATOR_STOPS:
            raise self._nothing_done()
        return self.stats

    def _nothing_done(self) -> CbhError:
        """The one-line error of a run that processed no pair."""
        from cbh.errors import InputError

        st = self.stats
        if st.stop_reason == "duration":
            why = f"within --duration {self.cfg.duration_s:g} s"
        elif st.stop_reason == "sources ended":
            why = "before the sources ended"
        else:
            why = f"(stopped: {st.stop_reason})"
        failed = [s.error if s.error.startswith(c) else f"{c}: {s.error}"
                  for c, s in st.sources.items() if s.error]  # the last error, also when the run
        # ended while the source was reconnecting
        if failed:
            return SourceError(f"no pair processed {why}: " + "; ".join(failed))
        if st.pairs_failed and st.last_error:
            return ImageError(f"no pair processed {why}: {st.pairs_failed} failed, last: {st.last_error}")
        got = ", ".join(f"{c} {s.frames} frames" + (f" ({s.corrupt} corrupt)" if s.corrupt else "")
                        for c, s in st.sources.items())
        unpaired = sum(st.unpaired.values())
        return InputError(f"no pair processed {why}: received {got}; {unpaired} frames without a partner "
                          f"within {self.cfg.pair_tolerance_s:g} s")

    def _close_sinks(self) -> Exception | None:
        err = self._writer.close() if self._writer is not None else None  # what is queued is written first
        for sink in self.sinks:
            try:
                sink.close()
            except Exception as exc:
                # raised below (the CLI prints it once): only the structured log gets it here
                log.debug(f"closing {type(sink).__name__} failed: {exc}", extra={"cbh_sink": type(sink).__name__})
                if err is None:
                    err = _sink_error(sink, exc, "closing")
        return err

    def _record_events(self, final: bool = False) -> None:
        """Source events (outage, recovery, end, failure, time jump) → status messages of every sink.

        Before any camera frame has arrived the cameras' time line is unknown: events wait in
        their queue until the first frame places them, for at most ``_EVENT_WAIT_S`` (a camera
        down for hours at start-up must not leave the recording silent), or until the run ends
        (``final``); then they are written on the wall clock, the only time there is."""
        waited = time.monotonic() - self.stats.started_monotonic
        if not self._last_frame and not final and waited < _EVENT_WAIT_S:
            return
        while True:
            try:
                ev = self._events.get_nowait()
            except queue.Empty:
                return
            t = self._session_time(ev.pop("mono"), ev["wall_utc"])
            ev["wall_utc"] = _iso(ev["wall_utc"])
            status = self.stats.to_dict()
            status["event"] = {k: v for k, v in ev.items() if v is not None}
            self._write_status(t, status)

    def _session_time(self, mono: float, wall: datetime) -> datetime:
        """An event's time on the cameras' time line (the pairs'): the newest camera frame's time
        plus the wall time between its arrival and the event (negative for an event before it:
        an outage at start-up is placed before the first frame); the wall clock without frames.

        Why: the pairs are stamped by the cameras' clocks, which may be far from this machine's
        (a camera without NTP, a replayed or simulated stream). Events stamped with the wall
        clock landed hours or years away from the pairs around them: out of order in the
        recording, and a jump past the file's time span rotated it (8 pairs were split 2 + 6
        over two files by one outage).
        """
        seen = [t + timedelta(seconds=mono - rs) for t, rs in self._last_frame.values() if rs is not None]
        return max(seen) if seen else wall

    def _write_status(self, t: datetime, status: dict) -> None:
        self._to_sinks("write_status", t, status)

    def _to_sinks(self, kind: str, *args) -> None:
        """Hand one item to the sink writer; an earlier sink failure stops the run here (raised:
        printed once by the caller). Without a writer (before run() starts it, or after it
        ended) the sinks are written directly."""
        w = self._writer
        if w is not None and w.error is not None:
            self.stop("sink failed")
            raise w.error
        if w is not None and w.is_alive():
            w.put(kind, *args)
            return
        for sink in self.sinks:
            try:
                getattr(sink, kind)(*args)
            except Exception as exc:
                err = _sink_error(sink, exc, "writing" if kind == "write" else "writing status to")
                log.debug(str(err), extra={"cbh_event": "sink_failed"})
                self.stop("sink failed")
                raise err from None

    def _check_time(self, r: _Reader, f: Frame) -> None:
        """Flag a frame whose time jumped (see the class docstring)."""
        cam, tol = f.camera, self.cfg.time_jump_s
        prev = self._last_frame.get(cam)
        self._last_frame[cam] = (f.time_utc, f.received_s)
        clocked = r.src.clock  # simulated time is the scene's, not a clock
        why, jump, kind = None, 0.0, ""
        was_ahead = self._ahead_of_wall.get(cam, False)
        if clocked:
            ahead = (f.time_utc - datetime.now(timezone.utc)).total_seconds()
            self._ahead_of_wall[cam] = ahead > tol
            if ahead > tol:
                why, jump, kind = f"stamped {_iso(f.time_utc)}, {ahead:.0f} s ahead of the wall clock", ahead, "future"
        if why is None and prev is not None:
            dt = (f.time_utc - prev[0]).total_seconds()
            if dt < -tol:
                why, jump, kind = f"time stepped back {-dt:.0f} s ({_iso(prev[0])} → {_iso(f.time_utc)})", dt, "back"
            elif clocked and r.live and prev[1] is not None and f.received_s is not None:
                drift = dt - (f.received_s - prev[1])
                if drift > tol:
                    why, jump, kind = (f"time jumped {drift:.0f} s ahead of the wall clock's advance "
                                       f"({_iso(prev[0])} → {_iso(f.time_utc)})", drift, "ahead")
        if why is None:
            return
        self._jumps[(cam, f.sequence, f.time_utc)] = jump
        while len(self._jumps) > 256:
            self._jumps.popitem(last=False)
        self._throttle(f"jump:{cam}:{kind}", logging.WARNING, f"{cam}: time jump: {why}; pairs resynchronized",
                       cbh_camera=cam, cbh_event="time_jump", cbh_jump_s=jump)
        if kind != "future" or not was_ahead:  # a clock ahead is one event when it starts, not one per frame
            self._events.put({"event": "time_jump", "camera": cam, "jump_s": round(jump, 3),
                              "frame_time_utc": _iso(f.time_utc), **_event_clock()})

    def _pull(self, readers: list[_Reader], pairer, live: bool) -> None:
        """Move frames from the reader queues into the pairer (time-checked), one camera's
        frame after the other's, so both time lines advance together (also across a jump)."""
        moved = True
        while moved:
            moved = False
            for r in readers:
                others = [o for o in readers if o is not r]
                # lossless: leave frames with a reader that is ahead of the other cameras
                # (it waits) instead of overflowing the pairer, unless the others have ended
                if (not live and pairer.waiting()[r.src.camera] >= pairer.max_waiting - 1
                        and not all(o.done and o.q.empty() for o in others)):
                    continue
                try:
                    f = r.q.get_nowait()
                except queue.Empty:
                    continue
                self._check_time(r, f)
                pairer.push(f)
                moved = True
        if hasattr(pairer, "end"):  # a network: a source that ended is not waited for
            for r in readers:
                if r.done and r.q.empty():
                    pairer.end(r.src.camera)
        for a, b, dt in pairer.pop_disagreements():
            self._throttle(f"disagree:{a}", logging.WARNING,
                           f"{a} frame dropped: {b}'s clock is {abs(dt):.0f} s {'ahead' if dt > 0 else 'behind'} "
                           f"(no partner within {self.cfg.pair_tolerance_s:g} s); check both cameras' clocks",
                           cbh_camera=a, cbh_event="clock_disagreement", cbh_dt_s=dt)

    def _loop(self, readers: list[_Reader], pairer) -> None:
        cfg, st = self.cfg, self.stats
        live = any(r.live for r in readers)
        t_end = None if cfg.duration_s is None else st.started_monotonic + cfg.duration_s
        # pairs accepted for processing; frames are pulled from the readers only when it is
        # empty, so memory is bounded by the reader queues and the pairer (also at full speed)
        pending: deque[tuple[Frame, Frame]] = deque()
        last_t: datetime | None = None  # time of the last pair accepted for processing
        last_status = 0.0
        while not self._stop.is_set():
            self._wake.clear()
            self._record_events()
            if t_end is not None and time.monotonic() >= t_end:
                self.stop("duration")
                break
            finished = False
            ahead = self.prepare is not None and not live
            if not pending or (ahead and len(pending) < 2):  # look-ahead: a second pair to prepare
                self._pull(readers, pairer, live)
                finished = all(r.done and r.q.empty() for r in readers)
                new = pairer.flush() if finished else pairer.pop_pairs()
                for p in new:
                    t = p[0].time_utc
                    if last_t is not None and (t - last_t).total_seconds() < -cfg.time_jump_s:
                        last_t = None  # a clock stepped back: the cadence restarts here
                    if last_t is not None and cfg.cadence_s > 0 and (t - last_t).total_seconds() < cfg.cadence_s - 1e-6:
                        st.pairs_skipped += 1
                        continue
                    if last_t is not None and cfg.cadence_s > 0:
                        gap = (t - last_t).total_seconds()
                        missed = int(gap / cfg.cadence_s + 1e-6) - 1
                        if live and missed > 0 and gap <= cfg.time_jump_s:
                            st.pairs_dropped += missed
                    pending.append(p)
                    last_t = t
                if live and len(pending) > 1:
                    if cfg.cadence_s == 0:
                        st.pairs_dropped += len(pending) - 1
                    while len(pending) > 1:
                        pending.popleft()
            if pending:
                pair = pending.popleft()
                self._handle(pair, nxt=pending[0] if (ahead and pending) else None)
                if cfg.frames is not None and st.pairs_processed >= cfg.frames:
                    self.stop("frames")
                continue
            if finished:
                self.stop("sources ended")
                break
            now = time.monotonic()
            if self.on_pair is not None and now - last_status > 1.0:
                last_status = now
                self.on_pair(st, None)
            wait = 0.5 if t_end is None else max(0.0, min(0.5, t_end - now))
            self._wake.wait(wait)

    def _prepare_job(self, pair: tuple[Frame, Frame]):
        for f in pair:
            if f is None:
                continue
            try:
                decode_frame(f)
            except ImageError as exc:
                raise _Corrupt(f, exc) from None
        return self.prepare(*pair)

    def _note_validity(self, result: PairResult, f1: Frame) -> list[str]:
        """Count and say (once per change of state) what invalidates this pair's layers, and when
        they are valid again; the same for a sun seen off its place. Returns the invalidating flags."""
        st = self.stats
        invalid = [f for f in result.flags if f in INVALIDATING]
        geometric = [f for f in invalid if f not in ("below_range", "clock_unknown", "clock_too_far", "night")]
        if invalid and not st.last_invalid:  # one warning per change of state, not per pair
            if invalid == ["night"]:
                log.warning(f"pair at {f1.time_utc.isoformat()}: night: the sun is below the horizon and the sky too "
                            "dark to tell cloud from clear sky; no layers are reported until it is light again",
                            extra={"cbh_event": "night", "cbh_flags": invalid})
            elif not geometric and "clock_too_far" in invalid:
                off = abs(result.diagnostics.get("clock_interval_ratio", math.nan) - 1.0)
                timing = (f"; their frames' intervals differ by {100 * off:.0f} %: frames captured off their stamps "
                          "(capture on the camera's own timer, not on request)" if off > FRAME_TIMING_SHARE else "")
                log.warning(f"pair at {f1.time_utc.isoformat()}: clock_too_far: the cameras' clocks differ by "
                            f"{result.diagnostics.get('clock_offset_s', math.nan):.0f} s and the clouds moved too far "
                            "between the two captures for this pair to be matched at one time; layers are not "
                            f"reported as valid until a pair is (set the cameras' clocks: NTP{timing})",
                            extra={"cbh_event": "clock_too_far", "cbh_flags": invalid})
            elif not geometric and "clock_unknown" in invalid:
                own, run = (result.diagnostics.get(k, math.nan) for k in ("clock_offset_pair_s", "clock_offset_s"))
                moved = math.isfinite(result.diagnostics.get("motion_dt_s", math.nan))
                why = (f"a clock that jumped? this pair's own estimate {own:.1f} s against {run:.1f} s"
                       if math.isfinite(own) and math.isfinite(run)
                       else "the sky maps did not measure it" if moved else "no motion yet to measure it")
                hidden = result.diagnostics.get("clock_hidden_share", math.nan)
                what = ("the cameras' matches disagree with the station geometry, or are too few to judge it, while "
                        "their clock offset, which would look the same, is not known"
                        if not hidden > HIDDEN_OFFSET_SHARE else
                        f"the cameras' clock offset is not known, and one the geometry check cannot see would move a "
                        f"layer by up to {100 * hidden:.0f} % (a wind along the baseline, or a slow one over a high "
                        "deck; a station whose clocks are right states clock_offset_s)")
                log.warning(f"pair at {f1.time_utc.isoformat()}: clock_unknown: {what} "
                            f"({why}); layers are not reported as valid until the offset is measured",
                            extra={"cbh_event": "clock_unknown", "cbh_flags": invalid})
            elif geometric:
                diag = ", ".join(f"{k} {v:.3g}" for k, v in result.diagnostics.items()
                                 if k.startswith(("geometry_", "sun_")))
                log.warning(f"pair at {f1.time_utc.isoformat()}: {', '.join(geometric)}: the cameras disagree with the "
                            f"station geometry ({diag}); layers are not reported as valid until they agree again "
                            "(check the sources and the orientation: `cbh calibrate`; on the first pairs of a run, "
                            "cameras whose clocks differ look the same until the offset is estimated)",
                            extra={"cbh_event": "geometry_invalid", "cbh_flags": invalid})
            else:
                d = result.diagnostics
                log.warning(f"pair at {f1.time_utc.isoformat()}: below_range: "
                            f"{100 * d.get('below_range_fraction', float('nan')):.0f} % of the measured cloud on the "
                            f"lowest height searched, {100 * d.get('measured_fraction', float('nan')):.0f} % of the cloud "
                            "measured at all: cloud at or below that height (fog, lifting stratus); layers are not "
                            "reported as valid until the cloud base is above it (to search lower: `min_height_m` in "
                            "[pipeline.matching.sweep] and [pipeline.filtering])",
                            extra={"cbh_event": "below_range", "cbh_flags": invalid})
        elif not invalid and st.last_invalid:
            log.warning(f"pair at {f1.time_utc.isoformat()}: layers valid again ({', '.join(st.last_invalid)} cleared)",
                        extra={"cbh_event": "geometry_valid"})
        st.pairs_invalid += bool(invalid)
        for f in invalid:
            st.invalid_counts[f] = st.invalid_counts.get(f, 0) + 1
        st.last_invalid = invalid
        if "sun_misaligned" in result.flags and not st.sun_misaligned:  # once per change, like the above
            log.warning(f"pair at {f1.time_utc.isoformat()}: the sun is "
                        f"{result.diagnostics.get('sun_residual_deg', float('nan')):.2f} deg from where the station's "
                        "orientation puts it (sun_misaligned): a camera may have moved; `cbh calibrate` fits it again",
                        extra={"cbh_event": "sun_misaligned"})
            st.sun_misaligned = True
        elif math.isfinite(result.diagnostics.get("sun_residual_deg", math.nan)) and "sun_misaligned" not in result.flags:
            st.sun_misaligned = False  # the sun was seen where expected
        return invalid

    def _handle(self, pair: tuple[Frame, Frame], nxt: tuple[Frame, Frame] | None = None) -> None:
        st = self.stats
        present = tuple(f for f in pair if f is not None)  # a network's set may lack a camera
        f1 = present[0]
        fut = None
        if self._ahead is not None and self._ahead[0] is pair:
            fut = self._ahead[1]
            self._ahead = None
            exc = fut.exception()  # waits for it
            if isinstance(exc, _Corrupt):
                return self._corrupt(exc.frame, exc.exc)
        else:
            for f in present:
                try:
                    decode_frame(f)
                except ImageError as exc:
                    self._corrupt(f, exc)
                    if len(pair) == 2 or len(present) <= 2:
                        return None  # a pair (or what is left of a set) needs two frames
                    # a network's set goes on without the camera (camera_missing): one bad frame of
                    # cam3 dropped cam1's and cam2's good ones with it
                    pair = tuple(None if g is f else g for g in pair)
                    return self._handle(pair, nxt)
        if nxt is not None and self._ahead is None:  # the next pair's first half beside this one's second
            if self._ahead_pool is None:
                from concurrent.futures import ThreadPoolExecutor

                self._ahead_pool = ThreadPoolExecutor(1, thread_name_prefix="cbh-ahead")
            self._ahead = (nxt, self._ahead_pool.submit(self._prepare_job, nxt))
        t0 = time.monotonic()
        try:
            result = self.process(*pair, prepared=fut) if fut is not None else self.process(*pair)
        except Exception as exc:  # a bad pair never stops the service
            st.pairs_failed += 1
            st.last_error = str(exc) if isinstance(exc, CbhError) else f"{type(exc).__name__}: {exc}"
            self._throttle("pair_failed", logging.WARNING, f"pair at {f1.time_utc.isoformat()} failed: {st.last_error}",
                           cbh_event="pair_failed")
            if not isinstance(exc, CbhError):
                log.debug("pair failure traceback", exc_info=True)
            self._notify(None)
            return
        st.process_s = time.monotonic() - t0
        jumps = [self._jumps.pop((f.camera, f.sequence, f.time_utc), None) for f in present]
        jumps = [j for j in jumps if j is not None]
        if jumps:
            if "time_jump" not in result.flags:
                result.flags.append("time_jump")
            result.diagnostics["time_jump_s"] = float(max(jumps, key=abs))
        self._to_sinks("write", present, result)
        st.pairs_processed += 1
        st.last_time_utc = result.time_utc
        invalid = self._note_validity(result, f1)
        st.last_layers_m = [] if invalid else [float(l.height_m) for l in result.layers]
        recv = max(f.received_s if f.received_s is not None else t0 for f in present)
        st.latency_s = time.monotonic() - recv
        self._write_status(result.time_utc, st.to_dict())
        log.info("pair processed", extra={
            "cbh_time_utc": result.time_utc.isoformat(), "cbh_layers_m": st.last_layers_m,
            "cbh_process_s": round(st.process_s, 3), "cbh_latency_s": round(st.latency_s, 3),
            "cbh_pairs": st.pairs_processed, "cbh_dropped": st.pairs_dropped,
        })
        self._notify(result)

    def _notify(self, result: PairResult | None) -> None:
        """``on_pair`` with a snapshot of the counters, once what was queued before is written
        (a printed pair is a recorded pair; a failed pair's line keeps its place in the order)."""
        if self.on_pair is None:
            return
        snap = copy.deepcopy(self.stats)
        w = self._writer
        if w is not None and w.is_alive():
            w.put("call", lambda: self.on_pair(snap, result))
        else:
            self.on_pair(snap, result)

    def _corrupt(self, frame: Frame, exc: ImageError) -> None:
        s = self.stats.sources[frame.camera]
        s.corrupt += 1
        s.error = str(exc)
        self._throttle(f"corrupt:{frame.camera}", logging.WARNING, f"{frame.camera}: corrupt frame skipped: {exc}",
                       cbh_camera=frame.camera, cbh_event="corrupt")


#: Source events wait this long for a first camera frame to place them on the cameras' time line [s].
_EVENT_WAIT_S = 60.0


def _event_clock() -> dict:
    """When a source event happened: wall clock (kept in the record) and monotonic (to place it
    on the cameras' time line, :meth:`Service._session_time`)."""
    return {"wall_utc": datetime.now(timezone.utc), "mono": time.monotonic()}


def _iso(t: datetime) -> str:
    return t.isoformat().replace("+00:00", "Z")


def _kept(name) -> str:
    """What a stopped writer leaves: a recording that could not be finished (no room for its
    summary and index) holds every complete pair but is not a readable MCAP file until repaired;
    any other file is whole up to its last complete row."""
    p = Path(str(name))
    if p.suffix.lower() == ".mcap":
        return (f"every complete pair is in it; if there was no room left to finish it (its index), it reads "
                f"only after `cbh inspect {p} --repair {p.with_name(p.stem + '-repaired.mcap')}` (with room on "
                "the disk)")
    return "everything written before is kept"


def _sink_error(sink, exc: Exception, doing: str) -> RecordingError:
    paths = sink.output_paths()
    name = paths[-1] if paths else type(sink).__name__
    kept = _kept(name)
    if isinstance(exc, OSError) and exc.errno == errno.ENOSPC:
        return RecordingError(f"disk full while {doing} {name}: stopped; {kept}")
    if isinstance(exc, OSError):
        return RecordingError(f"cannot write {name}: {exc.strerror or exc}; stopped; {kept}")
    if isinstance(exc, RecordingError) and "disk full" in str(exc):
        return exc
    return RecordingError(f"{doing} {name} failed: {exc}; stopped")
