"""Issue 10, case 2: one bad time stamp never silences the station."""
from __future__ import annotations

import logging
import time
from datetime import datetime, timedelta, timezone

import cv2
import numpy as np
import pytest

from cbh.live.pairing import Pairer
from cbh.live.service import MemorySink, Service, ServiceConfig
from cbh.live.sources import DirectorySource, MemorySource

from tests.faults.conftest import frame, process_fn, t

Y2030 = datetime(2030, 1, 1, tzinfo=timezone.utc)


def _pairs(times_s):
    return ([frame("cam1", x if isinstance(x, datetime) else t(x), k) for k, x in enumerate(times_s)],
            [frame("cam2", x if isinstance(x, datetime) else t(x), k) for k, x in enumerate(times_s)])


def _run(times_s, caplog, cadence_s=10.0):
    a, b = _pairs(times_s)
    sink = MemorySink()
    with caplog.at_level(logging.WARNING, logger="cbh"):
        st = Service([MemorySource("cam1", a), MemorySource("cam2", b)], process_fn(), [sink],
                     ServiceConfig(cadence_s=cadence_s)).run(handle_signals=False)
    return st, sink


def test_one_pair_stamped_2030_does_not_silence_the_later_pairs(caplog):
    st, sink = _run([0, 10, 20, Y2030, 30, 40, 50], caplog)
    got = [r.time_utc for _, r in sink.items]
    assert got[-3:] == [t(30), t(40), t(50)]  # processed, not skipped by the cadence
    assert st.pairs_processed == 7 and st.pairs_skipped == 0
    flagged = [r.time_utc for _, r in sink.items if "time_jump" in r.flags]
    assert Y2030 in flagged and t(30) in flagged  # the jump and the jump back
    assert all("time_jump" not in r.flags for _, r in sink.items if r.time_utc in (t(0), t(10), t(40), t(50)))
    msgs = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert any("ahead of the wall clock" in m for m in msgs)
    assert any("stepped back" in m for m in msgs)
    jump = next(r for _, r in sink.items if r.time_utc == Y2030)
    assert jump.diagnostics["time_jump_s"] > 3e7  # years ahead (more than a year)


def test_a_clock_stepping_back_an_hour_resynchronizes(caplog):
    ts = [0, 10, 20, 30, 30 - 3600, 40 - 3600, 50 - 3600, 60 - 3600]
    st, sink = _run(ts, caplog)
    got = [r.time_utc for _, r in sink.items]
    assert got == [t(x) for x in ts]  # every pair, none skipped
    assert [r.time_utc for _, r in sink.items if "time_jump" in r.flags] == [t(30 - 3600)]
    assert any("stepped back 3600 s" in r.getMessage() for r in caplog.records if r.levelno == logging.WARNING)


def test_pairer_resynchronizes_when_one_camera_steps_back():
    p = Pairer(("cam1", "cam2"), 0.5, jump_s=60.0)
    p.push(frame("cam1", Y2030))  # one frame from the future blocks nothing
    for k in range(3):
        p.push(frame("cam2", t(k)))
        p.push(frame("cam1", t(k)))
    pairs = p.pop_pairs() + p.flush()
    # cam2's t0 came while only the 2030 frame waited (dropped, reported); cam1's t0 then
    # replaced the 2030 frame and was left without a partner; from t1 on every pair forms
    assert [(a.time_utc, b.time_utc) for a, b in pairs] == [(t(1), t(1)), (t(2), t(2))]
    assert p.stats.unpaired == {"cam1": 2, "cam2": 1}
    assert p.pop_disagreements()[0][:2] == ("cam2", "cam1")


@pytest.mark.slow
def test_watched_folder_with_a_2030_pair_keeps_processing(tmp_path, caplog):
    """The case of the issue: a `--watch` folder, one pair stamped 2030, later files used to be
    skipped at DEBUG ("late file") while the process kept running and exited 0."""
    img = cv2.imencode(".jpg", np.full((16, 16, 3), 90, np.uint8))[1].tobytes()
    now = datetime.now(timezone.utc).replace(microsecond=0) - timedelta(minutes=10)

    def put(ts: datetime):
        for cam in ("cam1", "cam2"):
            (tmp_path / f"{cam}_{ts.strftime('%Y%m%dT%H%M%S')}Z.jpg").write_bytes(img)

    later = [now + timedelta(seconds=10 * k) for k in (2, 3)]
    sequence = [now, now + timedelta(seconds=10), Y2030, *later]  # one pair after the other arrives
    put(sequence[0])

    def on_pair(stats, result):
        if result is not None:
            i = sequence.index(result.time_utc)
            if i + 1 < len(sequence):
                put(sequence[i + 1])

    sink = MemorySink()
    srcs = [DirectorySource(c, tmp_path, watch=True, poll_s=0.1, prefix=c) for c in ("cam1", "cam2")]
    svc = Service(srcs, process_fn(), [sink], ServiceConfig(cadence_s=10.0, frames=5, duration_s=30), on_pair=on_pair)
    t0 = time.monotonic()
    with caplog.at_level(logging.WARNING, logger="cbh"):
        st = svc.run(handle_signals=False)
    assert time.monotonic() - t0 < 20
    got = [r.time_utc for _, r in sink.items]
    assert got == sequence and st.pairs_processed == 5
    assert {r.time_utc for _, r in sink.items if "time_jump" in r.flags} >= {Y2030, later[0]}
    assert any(r.levelno == logging.WARNING and "time jump" in r.getMessage() for r in caplog.records)


def test_clock_disagreement_between_cameras_is_warned(caplog):
    a = [frame("cam1", t(10 * k), k) for k in range(6)]
    b = [frame("cam2", t(10 * k + 3600), k) for k in range(6)]  # cam2's clock an hour ahead
    with caplog.at_level(logging.WARNING, logger="cbh"):
        with pytest.raises(Exception, match="no pair processed"):
            Service([MemorySource("cam1", a), MemorySource("cam2", b)], process_fn(), [MemorySink()]).run(
                handle_signals=False)
    msgs = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert any("clock is 3600 s ahead" in m for m in msgs), msgs
    assert len(msgs) <= 3  # rate-limited, not one per frame
