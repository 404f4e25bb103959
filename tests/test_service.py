"""The service loop (cbh.live.service): pairing, cadence, backpressure, faults, sinks.

These tests exercise the loop's mechanics with a light ``process`` callable standing in
for the pipeline (the end-to-end runs with the real simulator and pipeline are in
test_run_cli.py), so each stays well under a second or two.
"""
from __future__ import annotations

import errno
import time
from datetime import datetime, timedelta, timezone

import cv2
import numpy as np
import pytest

from cbh.errors import ConfigError, RecordingError, SourceError
from cbh.interfaces import FrameSource
from cbh.result import Frame, Histogram, Layer, PairResult, PointSet
from cbh.live.service import MemorySink, Service, ServiceConfig
from cbh.live.sources import DirectorySource, MemorySource

T0 = datetime(2015, 10, 29, 4, 58, 1, tzinfo=timezone.utc)
JPEG = cv2.imencode(".jpg", np.full((16, 16, 3), 90, np.uint8))[1].tobytes()


def frames(cam: str, n: int, step_s: float = 1.0, offset_s: float = 0.0, lazy: bool = False):
    img = None if lazy else np.full((16, 16, 3), 90, np.uint8)
    return [Frame(cam, T0 + timedelta(seconds=offset_s + k * step_s), img, JPEG, "jpeg", k) for k in range(n)]


def process_fn(delay_s: float = 0.0, fail_at: set | None = None):
    """Stand-in for Pipeline.process: one layer whose height is the pair's index in seconds."""
    def process(f1: Frame, f2: Frame) -> PairResult:
        assert f1.image is not None and f2.image is not None, "the service must hand decoded frames"
        k = (f1.time_utc - T0).total_seconds()
        if fail_at and round(k) in fail_at:
            raise ValueError(f"synthetic failure at {k}")
        if delay_s:
            time.sleep(delay_s)
        layer = Layer(1000.0 + k, 1000.0 + k, 1.0, 0.5, 10, 1.0)
        return PairResult(f1.time_utc, (f1.camera, f2.camera), [layer], Histogram(np.zeros(2), np.zeros(1)),
                          PointSet.empty(), np.zeros((2, 2), np.float32), {}, {})
    return process


def times(sink: MemorySink) -> list[float]:
    return [(fr[0].time_utc - T0).total_seconds() for fr, _ in sink.items]


def test_finite_sources_process_every_pair_in_order_and_close_sinks():
    sink = MemorySink()
    src = [MemorySource("cam1", frames("cam1", 8)), MemorySource("cam2", frames("cam2", 8, offset_s=0.2))]
    st = Service(src, process_fn(), [sink]).run()
    assert times(sink) == [float(k) for k in range(8)]
    assert all(fr[1].camera == "cam2" and abs((fr[1].time_utc - fr[0].time_utc).total_seconds() - 0.2) < 1e-9
               for fr, _ in sink.items)
    assert st.pairs_processed == 8 and st.pairs_dropped == 0 and st.stop_reason == "sources ended"
    assert sink.closed
    # per-pair status for the recorder: counters after each pair
    assert [s["pairs_processed"] for _, s in sink.status if "event" not in s] == list(range(1, 9))
    # and one status message per source event (both files ended)
    assert sorted(s["event"]["camera"] for _, s in sink.status if "event" in s) == ["cam1", "cam2"]
    assert sink.status[-1][1]["sources"] == {"cam1": "ended", "cam2": "ended"}
    assert st.last_layers_m == [1007.0]


def test_frames_limit_and_cadence_by_frame_time():
    sink = MemorySink()
    src = [MemorySource("cam1", frames("cam1", 20)), MemorySource("cam2", frames("cam2", 20))]
    st = Service(src, process_fn(), [sink], ServiceConfig(cadence_s=3.0, frames=4)).run()
    assert times(sink) == [0.0, 3.0, 6.0, 9.0]
    # 1, 2, 4, 5, 7, 8 skipped; pairs already read past 9 may be counted too before the stop
    assert 6 <= st.pairs_skipped <= 20 - 4 and st.pairs_dropped == 0 and st.stop_reason == "frames"


def test_unpaired_frames_are_counted_not_processed():
    sink = MemorySink()
    # cam2 only at 0, 2, 4 s (and one at 10 s): cam1's 1, 3, 5 s frames have no partner within 0.5 s
    f2 = [f for f in frames("cam2", 11) if f.sequence in (0, 2, 4, 10)]
    st = Service([MemorySource("cam1", frames("cam1", 6)), MemorySource("cam2", f2)], process_fn(), [sink]).run()
    assert times(sink) == [0.0, 2.0, 4.0]
    assert st.unpaired["cam1"] == 3 and st.unpaired["cam2"] == 1


def test_live_sources_falling_behind_drop_old_pairs_and_keep_the_newest():
    n = 60
    sink = MemorySink()
    src = [MemorySource("cam1", frames("cam1", n), live=True, pace_s=0.01),
           MemorySource("cam2", frames("cam2", n), live=True, pace_s=0.01)]
    cfg = ServiceConfig(queue_frames=2)
    st = Service(src, process_fn(delay_s=0.08), [sink], cfg).run()
    t = times(sink)
    # 100 frames/s against 12 pairs/s: most pairs must be dropped, never processed out of order
    assert st.pairs_dropped + sum(s.dropped for s in st.sources.values()) > n / 2
    assert t == sorted(t) and len(set(t)) == len(t)
    assert len(t) < n / 2
    # the newest pair is always the one processed: the last one is the end of the streams
    assert t[-1] >= n - 1 - 3


def test_corrupt_frame_is_counted_and_skipped():
    f1 = frames("cam1", 4, lazy=True)
    f1[1] = Frame("cam1", f1[1].time_utc, None, b"\xff\xd8 truncated garbage", "jpeg", 1)
    sink = MemorySink()
    st = Service([MemorySource("cam1", f1), MemorySource("cam2", frames("cam2", 4, lazy=True))],
                 process_fn(), [sink]).run()
    assert times(sink) == [0.0, 2.0, 3.0]
    assert st.sources["cam1"].corrupt == 1 and "corrupt" in st.sources["cam1"].error


def test_pipeline_failure_on_one_pair_does_not_stop_the_service():
    sink = MemorySink()
    st = Service([MemorySource("cam1", frames("cam1", 4)), MemorySource("cam2", frames("cam2", 4))],
                 process_fn(fail_at={1}), [sink]).run()
    assert times(sink) == [0.0, 2.0, 3.0]
    assert st.pairs_failed == 1 and "synthetic failure" in st.last_error


class FullDisk(MemorySink):
    def __init__(self, ok: int):
        super().__init__()
        self.ok = ok

    def write(self, frames, result):
        if len(self.items) >= self.ok:
            raise OSError(errno.ENOSPC, "No space left on device")
        super().write(frames, result)


def test_full_disk_stops_with_one_error_and_keeps_what_was_recorded(tmp_path):
    from cbh.presets import station_path
    from cbh.outputs.record import McapRecorder, open_session
    from cbh.geometry.station import load_station

    rec = McapRecorder(tmp_path / "kept.mcap", load_station(station_path()), {})
    good, full = MemorySink(), FullDisk(ok=2)
    svc = Service([MemorySource("cam1", frames("cam1", 10)), MemorySource("cam2", frames("cam2", 10))],
                  process_fn(), [rec, good, full])
    with pytest.raises(RecordingError, match="disk full"):
        svc.run()
    assert good.closed and full.closed
    # the third pair reached the sinks before the full one: recorded and kept, nothing after it
    assert len(full.items) == 2 and len(good.items) == 3
    s = open_session(tmp_path / "kept.mcap")  # closed properly: summary and footer present
    assert s.pair_count == 3 and [p.time_utc for p in s.pairs()] == [T0 + timedelta(seconds=k) for k in range(3)]


class Flaky(FrameSource):
    """A live source whose first opens fail (a camera still booting), then streams."""

    live = True

    def __init__(self, camera, n_fail, frames_):
        self.camera, self.n_fail, self.frames, self.opens = camera, n_fail, list(frames_), 0

    def open(self):
        self.opens += 1
        if self.opens <= self.n_fail:
            raise SourceError(f"{self.camera}: connection refused")

    def read(self, timeout_s):
        if not self.frames:
            from cbh.live.sources import EndOfStream

            raise EndOfStream(self.camera)
        return self.frames.pop(0)

    def close(self):
        pass


def test_reconnect_with_exponential_backoff():
    sink = MemorySink()
    flaky = Flaky("cam2", 3, frames("cam2", 3))
    cfg = ServiceConfig(backoff_initial_s=0.05, backoff_max_s=0.1)
    t0 = time.monotonic()
    st = Service([MemorySource("cam1", frames("cam1", 3)), flaky], process_fn(), [sink], cfg).run()
    waited = time.monotonic() - t0
    assert flaky.opens == 4 and st.sources["cam2"].reconnects == 3
    assert waited >= 0.05 + 0.1 + 0.1  # 0.05 doubling, capped at 0.1
    # a live source makes the service keep the newest pair: cam1's list was read meanwhile
    assert times(sink)[-1] == 2.0 and st.pairs_processed + st.pairs_dropped == 3


def test_missing_directory_is_one_error_at_start(tmp_path):
    svc = Service([DirectorySource("cam1", tmp_path / "none"), MemorySource("cam2", frames("cam2", 2))],
                  process_fn(), [MemorySink()])
    with pytest.raises(SourceError, match="not found"):
        svc.run()
    assert svc.sinks[0].closed


def test_duration_ends_a_run_with_silent_cameras():
    sink = MemorySink()
    src = [MemorySource("cam1", [], live=True), Flaky("cam2", 10**6, [])]
    t0 = time.monotonic()
    svc = Service(src, process_fn(), [sink], ServiceConfig(duration_s=0.5, backoff_initial_s=0.05))
    # no pair in the whole run: the run could not do its job and says why (exit 2 in the CLI)
    with pytest.raises(SourceError, match=r"no pair processed within --duration 0.5 s: cam2: connection refused"):
        svc.run()
    assert 0.5 <= time.monotonic() - t0 < 5.0
    assert svc.stats.stop_reason == "duration" and sink.closed
    assert svc.stats.sources["cam2"].state == "backoff"


def test_service_config_from_table():
    cfg = ServiceConfig.from_dict({"cadence_s": 10, "frames": 3})
    assert cfg.cadence_s == 10.0 and cfg.frames == 3
    with pytest.raises(ConfigError, match="service.cadense_s: unknown key"):
        ServiceConfig.from_dict({"cadense_s": 10})
    with pytest.raises(ConfigError, match="service.pair_tolerance_s"):
        ServiceConfig.from_dict({"pair_tolerance_s": 0})
    with pytest.raises(ConfigError, match="service.frames: expected an integer"):
        ServiceConfig.from_dict({"frames": "3"})
    with pytest.raises(ConfigError, match="service.duration_s: must be finite"):
        ServiceConfig.from_dict({"duration_s": float("inf")})


def test_lossless_run_waits_for_a_slow_camera_instead_of_dropping():
    n = 40  # more than the pairer's waiting list: cam1's reader must be held back, not dropped
    sink = MemorySink()
    src = [MemorySource("cam1", frames("cam1", n)), MemorySource("cam2", frames("cam2", n), pace_s=0.005)]
    st = Service(src, process_fn(), [sink], ServiceConfig(queue_frames=2)).run()
    assert times(sink) == [float(k) for k in range(n)]
    assert st.unpaired == {"cam1": 0, "cam2": 0}


def _ahead_fns(fail_prepare_at: set | None = None):
    """(prepare, process) as RunSetup gives them: the first half ahead, the second with the future."""
    calls: list[tuple[str, float]] = []
    base = process_fn()

    def prepare(f1, f2):
        k = (f1.time_utc - T0).total_seconds()
        calls.append(("prepare", k))
        if fail_prepare_at and round(k) in fail_prepare_at:
            raise ValueError(f"synthetic prepare failure at {k}")
        assert f1.image is not None and f2.image is not None, "decoded before the first half"
        return k

    def process(f1, f2, prepared=None):
        k = prepared.result() if prepared is not None else prepare(f1, f2)
        time.sleep(0.05)  # a second half long enough for the next pair's first half to start beside it
        calls.append(("finish", k))
        return base(f1, f2)
    return prepare, process, calls


def test_look_ahead_prepares_the_next_pair_and_keeps_the_order():
    """Finite sources: the next pair's first half (decoding, prepare) runs beside this pair's
    second half; results, status and the second halves stay in capture order."""
    prepare, process, calls = _ahead_fns()
    sink = MemorySink()
    src = [MemorySource("cam1", frames("cam1", 6, lazy=True)), MemorySource("cam2", frames("cam2", 6, lazy=True))]
    st = Service(src, process, [sink], prepare=prepare).run()
    assert times(sink) == [float(k) for k in range(6)] and st.pairs_processed == 6
    assert [k for what, k in calls if what == "finish"] == [float(k) for k in range(6)]
    assert sorted(k for what, k in calls if what == "prepare") == [float(k) for k in range(6)]  # each once
    # and ahead: pair k + 1's first half ran before pair k's second half ended
    assert all(calls.index(("prepare", k + 1.0)) < calls.index(("finish", float(k))) for k in range(5)), calls


def test_look_ahead_corrupt_frame_and_failed_first_half():
    """A frame that does not decode in a looked-ahead pair is a corrupt frame (as without
    look-ahead); a first half that fails is that pair's failure, raised where it is processed."""
    f1 = frames("cam1", 5, lazy=True)
    f1[1] = Frame("cam1", f1[1].time_utc, None, b"\xff\xd8 truncated garbage", "jpeg", 1)
    prepare, process, calls = _ahead_fns(fail_prepare_at={3})
    sink = MemorySink()
    st = Service([MemorySource("cam1", f1), MemorySource("cam2", frames("cam2", 5, lazy=True))], process, [sink],
                 prepare=prepare).run()
    assert times(sink) == [0.0, 2.0, 4.0]
    assert st.sources["cam1"].corrupt == 1 and st.pairs_failed == 1 and "prepare failure at 3" in st.last_error


def test_live_sources_get_no_look_ahead():
    prepare, process, calls = _ahead_fns()
    sink = MemorySink()
    n = 6
    src = [MemorySource("cam1", frames("cam1", n), live=True, pace_s=0.01),
           MemorySource("cam2", frames("cam2", n), live=True, pace_s=0.01)]
    Service(src, process, [sink], ServiceConfig(cadence_s=0), prepare=prepare).run()
    # each pair prepared when its turn comes: prepare and finish alternate
    assert [w for w, _ in calls] == ["prepare", "finish"] * len(sink.items)


@pytest.mark.slow
def test_events_before_any_frame_wait_for_one_but_not_for_ever(monkeypatch):
    """A camera down at start-up: its outage waits to be placed on the cameras' time line by
    their first frame, but a run whose cameras never deliver must not stay silent: after
    ``_EVENT_WAIT_S`` (60 s; 0.3 s here) the events are written on the wall clock, during the run."""
    import cbh.live.service as S

    class Stamping(MemorySink):
        def write_status(self, time_utc, stats):
            super().write_status(time_utc, stats)
            self.when = getattr(self, "when", []) + [time.monotonic()]

    monkeypatch.setattr(S, "_EVENT_WAIT_S", 0.3)
    sink = Stamping()
    src = [MemorySource("cam1", [], live=True), Flaky("cam2", 10**6, [])]
    svc = Service(src, process_fn(), [sink], ServiceConfig(duration_s=1.5, backoff_initial_s=0.05))
    t0 = time.monotonic()
    with pytest.raises(SourceError):
        svc.run()
    t_end = time.monotonic()
    outages = [(t, st) for t, st in sink.status if st.get("event", {}).get("event") == "outage"]
    assert outages, sink.status
    first_written = sink.when[0]
    assert t0 + 0.3 <= first_written < t_end - 0.5  # after the wait, well before the end of the run
    assert abs((outages[0][0] - datetime.now(timezone.utc)).total_seconds()) < 30  # the wall clock


def test_a_camera_clock_ahead_of_the_wall_clock_is_one_event_not_one_per_frame():
    """Every frame of a camera stamped in the future is flagged time_jump (its pairs), but the
    recording gets one status event when that starts: one per frame filled it (635 statuses in
    a 500-frame run, held in memory until the first pair)."""
    future = datetime.now(timezone.utc) + timedelta(days=365)
    f1 = [Frame("cam1", future + timedelta(seconds=k), np.full((16, 16, 3), 90, np.uint8), JPEG, "jpeg", k)
          for k in range(20)]
    f2 = [Frame("cam2", future + timedelta(seconds=k), np.full((16, 16, 3), 90, np.uint8), JPEG, "jpeg", k)
          for k in range(20)]
    sink = MemorySink()
    Service([MemorySource("cam1", f1), MemorySource("cam2", f2)], process_fn_at(future), [sink]).run()
    assert len(sink.items) == 20 and all("time_jump" in r.flags for _, r in sink.items)
    jumps = [st for _, st in sink.status if st.get("event", {}).get("event") == "time_jump"]
    assert len(jumps) == 2, jumps  # one per camera


def process_fn_at(t0):
    def process(f1, f2):
        return PairResult(f1.time_utc, (f1.camera, f2.camera), [], Histogram(np.zeros(2), np.zeros(1)),
                          PointSet.empty(), np.zeros((2, 2), np.float32), {}, {})
    return process


@pytest.mark.parametrize("ratio, said", [(1.08, True), (1.005, False), (float("nan"), False)])
def test_a_carry_blurred_by_frames_off_their_stamps_says_so(ratio, said):
    """``clock_too_far`` is one warning per change of state; where the pair's two cameras' frame
    intervals differ by more than 2 % (``clock_interval_ratio``), it also says that the frames are
    captured off their stamps, which setting the clocks does not mend."""
    import logging

    from cbh.live import service

    def process(f1, f2):
        return PairResult(f1.time_utc, (f1.camera, f2.camera), [], Histogram(np.zeros(2), np.zeros(1)),
                          PointSet.empty(), np.zeros((2, 2), np.float32), {}, {}, flags=["clock_too_far"],
                          diagnostics={"clock_offset_s": 90.0, "clock_interval_ratio": ratio})
    warned = []
    handler = logging.Handler(logging.WARNING)

    def emit(rec):
        if getattr(rec, "cbh_event", None) == "clock_too_far":
            warned.append(rec.getMessage())
    handler.emit = emit
    service.log.addHandler(handler)
    try:
        Service([MemorySource("cam1", frames("cam1", 3)), MemorySource("cam2", frames("cam2", 3))], process,
                [MemorySink()]).run()
    finally:
        service.log.removeHandler(handler)
    assert len(warned) == 1, warned
    assert ("frames captured off their stamps" in warned[0]) is said, warned[0]
    assert ("differ by 8 %" in warned[0]) is said
