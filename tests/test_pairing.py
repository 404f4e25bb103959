"""Pairing two cameras' frames by nearest time stamp within a tolerance (cbh.live.pairing)."""
from __future__ import annotations

from datetime import datetime, timedelta, timezone

import pytest

from cbh.errors import ConfigError
from cbh.live.pairing import Pairer
from cbh.result import Frame

T0 = datetime(2015, 10, 29, 4, 58, 1, tzinfo=timezone.utc)


def fr(cam: str, t_s: float) -> Frame:
    return Frame(cam, T0 + timedelta(seconds=t_s), None)


def secs(pairs):
    return [(round((a.time_utc - T0).total_seconds(), 3), round((b.time_utc - T0).total_seconds(), 3)) for a, b in pairs]


def feed(p: Pairer, events):
    out = []
    for cam, t in events:
        p.push(fr(cam, t))
        out += p.pop_pairs()
    return out + p.flush()


def test_simultaneous_frames_pair_at_once_in_camera_order():
    p = Pairer(("cam1", "cam2"), 0.5)
    p.push(fr("cam2", 0.0))
    p.push(fr("cam1", 0.0))
    pairs = p.pop_pairs()
    assert secs(pairs) == [(0.0, 0.0)]
    assert pairs[0][0].camera == "cam1" and pairs[0][1].camera == "cam2"


def test_nearest_frame_wins_over_an_earlier_one_within_tolerance():
    # cam1 frames 0.4 and 0.8 are both within 0.5 s of cam2's 0.75: 0.8 is nearest.
    p = Pairer(("cam1", "cam2"), 0.5)
    pairs = feed(p, [("cam1", 0.4), ("cam2", 0.75), ("cam1", 0.8), ("cam1", 1.6)])
    assert secs(pairs) == [(0.8, 0.75)]
    assert p.stats.unpaired == {"cam1": 2, "cam2": 0}  # 0.4 lost to 0.8; 1.6 has no partner


def test_frames_farther_apart_than_tolerance_are_never_paired():
    p = Pairer(("cam1", "cam2"), 0.5)
    pairs = feed(p, [("cam1", 0.0), ("cam2", 0.6), ("cam1", 1.2), ("cam2", 1.8)])
    assert pairs == []
    assert p.stats.unpaired == {"cam1": 2, "cam2": 2}


def test_offset_cameras_pair_one_to_one_with_tolerance_respected():
    # cam2 runs 0.3 s late at 1 fps: every frame pairs with its own partner, |dt| = 0.3
    p = Pairer(("cam1", "cam2"), 0.5)
    ev = []
    for k in range(6):
        ev += [("cam1", k), ("cam2", k + 0.3)]
    pairs = feed(p, ev)
    assert secs(pairs) == [(k, k + 0.3) for k in range(6)]
    assert p.stats.max_dt_s == pytest.approx(0.3)
    assert sum(p.stats.unpaired.values()) == 0


def test_tighter_tolerance_drops_the_same_stream():
    p = Pairer(("cam1", "cam2"), 0.25)
    ev = []
    for k in range(4):
        ev += [("cam1", k), ("cam2", k + 0.3)]
    assert feed(p, ev) == []
    assert p.stats.unpaired == {"cam1": 4, "cam2": 4}


def test_out_of_order_frame_is_dropped_and_buffers_are_bounded():
    p = Pairer(("cam1", "cam2"), 0.5, max_waiting=4)
    p.push(fr("cam1", 5.0))
    p.push(fr("cam1", 4.0))  # older than the newest: dropped
    assert p.stats.unpaired["cam1"] == 1
    for k in range(10):
        p.push(fr("cam1", 10.0 + k))  # cam2 silent: the waiting list stays bounded
    assert p.waiting()["cam1"] == 4
    assert p.stats.unpaired["cam1"] == 1 + 7


def test_bad_configuration_is_rejected():
    with pytest.raises(ConfigError, match="tolerance"):
        Pairer(("cam1", "cam2"), 0.0)
    with pytest.raises(ConfigError, match="different"):
        Pairer(("cam1", "cam1"), 0.5)
    p = Pairer(("cam1", "cam2"), 0.5)
    with pytest.raises(ConfigError, match="cam3"):
        p.push(fr("cam3", 0.0))


def _frames(cam, times_s, t0=None):
    from datetime import datetime, timedelta, timezone

    from cbh.result import Frame

    t0 = t0 or datetime(2024, 1, 1, tzinfo=timezone.utc)
    return [Frame(cam, t0 + timedelta(seconds=s), None) for s in times_s]


def _names(sets):
    return [tuple(None if f is None else (f.camera, f.time_utc.second) for f in s) for s in sets]


def test_grouper_sets_frames_of_three_cameras_and_goes_on_without_one_that_went_away():
    """A camera network's sets (issue 24): nearest frames within the tolerance; live, a camera
    that stops is presumed gone once the others are more than `patience` (2) frames ahead of
    it, and the sets go on without it (None in its place)."""
    from cbh.live.pairing import Grouper

    g = Grouper(("a", "b", "c"), tolerance_s=0.5, patience=2)
    for k in range(5):
        for cam, off in (("a", 0.0), ("b", 0.1), ("c", 0.2)):
            if cam == "c" and k >= 2:
                continue  # c goes away after two frames
            for f in _frames(cam, [10 * k + off]):
                g.push(f)
    got = _names(g.pop_pairs())
    assert got[:2] == [(("a", 0), ("b", 0), ("c", 0)), (("a", 10), ("b", 10), ("c", 10))]
    assert got[2] == (("a", 20), ("b", 20), None)  # emitted while a and b kept coming, before the end
    assert _names(g.flush())[-1] == (("a", 40), ("b", 40), None)
    assert g.stats.unpaired == {"a": 0, "b": 0, "c": 0}


def test_grouper_of_files_waits_for_a_slower_camera_until_its_source_ends():
    """Files are read as fast as they can be: a camera behind is not gone (patience None) until
    its source ends (`end`)."""
    from cbh.live.pairing import Grouper

    g = Grouper(("a", "b", "c"), tolerance_s=0.5, patience=None)
    for f in _frames("a", [0, 10, 20, 30]) + _frames("b", [0.1, 10.1, 20.1, 30.1]):
        g.push(f)
    assert g.pop_pairs() == []  # c has delivered nothing yet: waited for
    for f in _frames("c", [0.2, 10.2]):
        g.push(f)
    assert _names(g.pop_pairs()) == [(("a", 0), ("b", 0), ("c", 0))]  # 10 s: c's next may be nearer
    g.end("c")
    got = _names(g.pop_pairs())  # c ended: 10 s with its frame, 20 s without; 30 s waits for b's next
    assert got == [(("a", 10), ("b", 10), ("c", 10)), (("a", 20), ("b", 20), None)]
