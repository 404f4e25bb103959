"""`cbh quicklook`: a PNG drawn from real recordings, read back."""
from __future__ import annotations

from dataclasses import replace

import numpy as np

import pytest

from tests.test_record import small_station, synthetic_pair


def _session(path, station, motion: bool):
    from cbh.outputs.record import McapRecorder

    with McapRecorder(path, station, {}) as rec:
        for k in range(6):
            frames, res = synthetic_pair(station, k)
            if motion:
                res = replace(res, layers=[replace(l, motion_east_ms=5.0 + i, motion_north_ms=-2.0 * i)
                                           for i, l in enumerate(res.layers)])
            if k == 4:
                res = replace(res, flags=res.flags + ["geometry_mismatch"])
            rec.write(frames, res)


@pytest.mark.slow
def test_quicklook_png_from_recordings(tmp_path):
    import cv2

    from cbh.cli.main import main

    st = small_station()
    _session(tmp_path / "m.mcap", st, motion=True)
    _session(tmp_path / "n.mcap", st, motion=False)
    for name in ("m", "n"):
        assert main(["quicklook", str(tmp_path / f"{name}.mcap"), "--out", str(tmp_path / f"{name}.png")]) == 0
    a = cv2.imread(str(tmp_path / "m.png"))
    b = cv2.imread(str(tmp_path / "n.png"))
    assert a is not None and a.shape == (1140, 1320, 3)  # 11 x 9.5 in at 120 dpi
    # same heights, covers and fractions: the upper half is identical; the motion panels differ
    h = a.shape[0]
    assert np.array_equal(a[: int(0.45 * h)], b[: int(0.45 * h)])
    assert not np.array_equal(a[int(0.6 * h):], b[int(0.6 * h):])


def test_quicklook_errors_are_one_line(tmp_path, capsys):
    from cbh.cli.main import main

    assert main(["quicklook", str(tmp_path / "missing.mcap"), "--out", str(tmp_path / "x.png")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("cbh: error:") and "\n" not in err


def test_gaps_between_sessions_are_not_bridged():
    from cbh.actions.quicklook import _break_gaps

    t0 = np.datetime64("2024-06-21T14:00:00", "us")
    times = t0 + np.array([0, 10, 20, 30, 7200, 7210], "timedelta64[s]")
    cf = np.array([0.1, 0.2, 0.3, 0.4, 0.5, 0.6])
    t2, (cf2,), bad = _break_gaps(times, (cf,), np.zeros(6, bool))
    assert len(t2) == 7 and np.isnan(cf2[4]) and t2[4] == t0 + np.timedelta64(3615, "s")
    assert list(cf2[~np.isnan(cf2)]) == list(cf) and not bad.any()
    t3, (cf3,), _ = _break_gaps(times[:4], (cf[:4],), np.zeros(4, bool))  # a regular cadence: unchanged
    assert len(t3) == 4 and np.array_equal(cf3, cf[:4])


def test_quicklook_to_an_unknown_suffix_is_one_error_line_and_keeps_the_recording(tmp_path, capsys):
    """``-o x.mcap`` (or .txt) was a matplotlib ValueError traceback; now one line, exit 2, and the
    recording given as --out is untouched."""
    from cbh.cli.main import main

    _session(tmp_path / "m.mcap", small_station(), motion=False)
    before = (tmp_path / "m.mcap").read_bytes()
    for out in ("m.mcap", "q.txt"):
        assert main(["quicklook", str(tmp_path / "m.mcap"), "--out", str(tmp_path / out)]) == 2
        err = capsys.readouterr().err.strip()
        assert err.startswith("cbh: error:") and "\n" not in err, err
        assert ("one of the command's own inputs" if out == "m.mcap" else "cannot draw") in err, err
    assert (tmp_path / "m.mcap").read_bytes() == before and not (tmp_path / "q.txt").exists()
