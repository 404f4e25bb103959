"""Issue 10, cases 3 and 6: sources that fail politely; memory and --duration bounded."""
from __future__ import annotations

import logging
import threading
import time

import numpy as np
import pytest

from cbh.errors import SourceError
from cbh.interfaces import FrameSource
from cbh.live.service import MemorySink, Service, ServiceConfig
from cbh.live.sources import HttpSource, MemorySource
from cbh.outputs.record import McapRecorder, open_session

from tests.faults.conftest import frame, process_fn, t

FAST = dict(backoff_initial_s=0.1, backoff_max_s=0.4, read_timeout_s=0.05, stall_timeout_s=2.0)


def _warnings(caplog) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]


def _run_against(cam_url: str, caplog, duration_s: float = 2.0, mode: str = "auto"):
    srcs = [HttpSource("cam1", cam_url, mode=mode, stall_timeout_s=2.0), MemorySource("cam2", [], live=True)]
    svc = Service(srcs, process_fn(), [MemorySink()], ServiceConfig(duration_s=duration_s, **FAST))
    with caplog.at_level(logging.DEBUG, logger="cbh"):
        with pytest.raises(SourceError, match="no pair processed"):
            svc.run(handle_signals=False)
    return svc.stats.sources["cam1"]


@pytest.mark.parametrize("mode", ["html", pytest.param("404", marks=pytest.mark.slow),
                                  pytest.param("500", marks=pytest.mark.slow)])  # (one code path for all three)
@pytest.mark.slow
def test_login_page_and_http_errors_back_off_with_few_warnings(camera, caplog, mode):
    """An HTML login page with status 200 used to be ~3450 warnings/s (a corrupt frame per
    poll, reconnected at once); now it is a source error with the same backoff as 404/500."""
    cam = camera(mode)
    st = _run_against(cam.url, caplog)
    # backoff 0.1, 0.2, 0.4, 0.4 … s over 2 s: at most ~8 attempts, not thousands
    assert 2 <= cam.requests <= 10, cam.requests
    assert st.state in ("backoff", "connecting") and st.reconnects >= cam.requests - 1
    warns = _warnings(caplog)
    assert 1 <= len(warns) <= 2, warns  # one per state change (+ a rate-limited repeat at most)
    expect = "Content-Type 'text/html'" if mode == "html" else f"HTTP {mode}"
    assert expect in warns[0]


@pytest.mark.slow
def test_junk_mjpeg_stream_is_a_source_error_with_backoff(camera, caplog):
    cam = camera("junk-mjpeg")
    st = _run_against(cam.url, caplog, mode="mjpeg")
    assert st.reconnects >= 2 and "junk" in st.error  # the state at the stop is wherever the cycle was
    warns = _warnings(caplog)
    assert 1 <= len(warns) <= 2 and "junk in the MJPEG stream" in warns[0], warns


@pytest.mark.slow
def test_corrupt_frames_in_a_row_from_a_live_source_back_off():
    class Garbage(FrameSource):
        camera, live = "cam1", True

        def __init__(self):
            self.opens = 0

        def open(self):
            self.opens += 1

        def read(self, timeout_s):
            from cbh.errors import ImageError

            time.sleep(0.001)
            raise ImageError("cam1 frame: corrupt image data")

    g = Garbage()
    svc = Service([g, MemorySource("cam2", [], live=True)], process_fn(), [MemorySink()],
                  ServiceConfig(duration_s=1.0, corrupt_limit=5, **FAST))
    with pytest.raises(SourceError, match="5 corrupt frames in a row"):
        svc.run(handle_signals=False)
    # backoff 0.1, 0.2, 0.4 … s: a handful of reconnects, each after 5 corrupt frames
    assert 2 <= g.opens <= 8
    assert 5 * (g.opens - 1) <= svc.stats.sources["cam1"].corrupt <= 5 * g.opens


@pytest.mark.slow
def test_outage_and_recovery_are_recorded_as_status_messages(camera, tmp_path, unb_station):
    cam1, cam2 = camera("snapshot"), camera("snapshot")
    srcs = [HttpSource("cam1", cam1.url, mode="snapshot", interval_s=0.1),
            HttpSource("cam2", cam2.url, mode="snapshot", interval_s=0.1)]
    rec = McapRecorder(tmp_path / "s.mcap", unb_station, {})

    def outage():
        time.sleep(0.8)
        cam2.mode = "404"
        time.sleep(1.0)
        cam2.mode = "snapshot"

    threading.Thread(target=outage, daemon=True).start()
    svc = Service(srcs, process_fn(), [rec], ServiceConfig(duration_s=3.5, pair_tolerance_s=5.0, **FAST))
    svc.run(handle_signals=False)
    events = [s["event"] for _, s in open_session(tmp_path / "s.mcap").statuses() if "event" in s]
    kinds = [(e["event"], e["camera"]) for e in events]
    assert ("outage", "cam2") in kinds and ("recovered", "cam2") in kinds, kinds
    out = next(e for e in events if e["event"] == "outage")
    assert "HTTP 404" in out["error"]
    assert kinds.index(("outage", "cam2")) < kinds.index(("recovered", "cam2"))


# --- case 6: bounded memory and --duration ----------------------------------------------------

class Endless(FrameSource):
    """A lossless (not live) endless source, like the simulator at --cadence-s 0; counts reads."""

    live = False

    def __init__(self, camera):
        self.camera, self.k = camera, 0

    def read(self, timeout_s):
        f = frame(self.camera, t(self.k), self.k)
        f.image = np.zeros((256, 256, 3), np.uint8)  # ~200 KB held per frame while waiting
        self.k += 1
        return f


def test_full_speed_lossless_source_keeps_memory_bounded():
    """Frames read ahead of processing are bounded by the queues and the pairer (they used to
    pile up in the pending list: 646 MB → 8.4 GB)."""
    cfg = ServiceConfig(frames=40, queue_frames=4)
    src = [Endless("cam1"), Endless("cam2")]
    st = Service(src, process_fn(delay_s=0.01), [MemorySink()], cfg).run(handle_signals=False)
    assert st.pairs_processed == 40
    ahead = max(s.k for s in src) - st.pairs_processed
    bound = cfg.queue_frames + max(2 * cfg.queue_frames, 8) + 2  # reader queue + pairer + in flight
    assert ahead <= bound, (ahead, bound)


@pytest.mark.slow
def test_duration_is_honoured_with_a_full_speed_source():
    svc = Service([Endless("cam1"), Endless("cam2")], process_fn(delay_s=0.01), [MemorySink()],
                  ServiceConfig(duration_s=1.0))
    done = threading.Event()
    th = threading.Thread(target=lambda: (svc.run(handle_signals=False), done.set()), daemon=True)
    t0 = time.monotonic()
    th.start()
    ok = done.wait(15.0)
    if not ok:
        svc.stop()
        th.join(10)
    assert ok, "--duration ignored: the run did not stop"
    assert time.monotonic() - t0 < 5.0 and svc.stats.stop_reason == "duration"
