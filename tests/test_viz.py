"""Rerun sink: modes, .rrd files that `rerun rrd verify` accepts, the default blueprint."""
from __future__ import annotations

import re

import numpy as np
import pytest

from cbh.errors import ConfigError

from .conftest import needs_cli, rrd_print, rrd_verify, small_station, synthetic_pair

def test_parse_rerun_spec():
    from cbh.outputs.rerun_view import parse_rerun_spec

    assert parse_rerun_spec("spawn") == ("spawn", None)
    assert parse_rerun_spec("save", "out.rrd") == ("save", "out.rrd")
    assert parse_rerun_spec("out.rrd") == ("save", "out.rrd")
    assert parse_rerun_spec("connect") == ("connect", None)
    assert parse_rerun_spec("save=out.rrd") == ("save", "out.rrd")
    assert parse_rerun_spec("connect=rerun+http://h:9876/proxy") == ("connect", "rerun+http://h:9876/proxy")
    assert parse_rerun_spec("rerun+http://127.0.0.1:9876/proxy") == ("connect", "rerun+http://127.0.0.1:9876/proxy")
    for bad, tgt, msg in [("show", None, "unknown mode"), ("save", None, "needs an output"),
                          ("save", "x.png", "end in .rrd"), ("spawn", "x.rrd", "takes no target")]:
        with pytest.raises(ConfigError, match=msg):
            parse_rerun_spec(bad, tgt)


def test_height_colors_follow_the_scale_and_mark_nan():
    from cbh.outputs.rerun_view import height_colors

    c = height_colors(np.array([0.0, 5000.0, 10000.0, np.nan, 20000.0]))
    assert c.shape == (5, 3) and c.dtype == np.uint8
    assert tuple(c[3]) == (128, 128, 128)
    np.testing.assert_array_equal(c[2], c[4])  # clipped at the top of the scale
    assert not np.array_equal(c[0], c[2])  # turbo: blue-ish low, red-ish high
    assert c[0, 2] > c[0, 0] and c[2, 0] > c[2, 2]


@needs_cli
def test_save_mode_writes_a_verified_rrd_with_the_default_blueprint(tmp_path):
    from cbh.outputs.rerun_view import RerunSink

    st = small_station()
    out_a, out_b = tmp_path / "a.rrd", tmp_path / "b.rrd"
    # two sinks at once: each has its own RecordingStream
    with RerunSink(st, "save", str(out_a)) as a, RerunSink(st, "save", str(out_b)) as b:
        for k in range(3):
            frames, res = synthetic_pair(st, k)
            a.write(frames, res)
        b.write(*synthetic_pair(st, 7))
        a.write_status(res.time_utc, {"pairs_processed": 3, "pairs_dropped": 0})
    for p in (out_a, out_b):
        r = rrd_verify(p)
        assert r.returncode == 0, r.stderr
    summary = rrd_print(out_a)
    for entity in ("/cam1/image", "/cam1/cloud_mask", "/cam2/matches", "/world/points", "/world/cameras",
                   "/histogram", "/layers/0", "/layers/1", "/height_map", "/cloud_fraction/cam1", "/service/pairs_processed"):
        assert re.search(rf" - {re.escape(entity)} - ", summary), entity
    assert rrd_print(out_a) != rrd_print(out_b)
    full = rrd_print(out_a, "-vvv")
    for view in ("[2D]", "[3D]", "[BarChart]", "[TimeSeries]", "[/cam1]", "[/cam2]", "[/world]", "[/histogram]",
                 "[/layers]"):
        assert view in full, view
    assert "capture_time" in full


def test_bad_save_target(tmp_path):
    from cbh.errors import RecordingError
    from cbh.outputs.rerun_view import RerunSink

    with pytest.raises(RecordingError, match="does not exist"):
        RerunSink(small_station(), "save", str(tmp_path / "missing" / "x.rrd"))


def test_serve_and_connect_modes_start_and_close_cleanly():
    """A served stream on a free port and a second sink connected to it (no viewer is spawned)."""
    import socket

    from cbh.outputs.rerun_view import RerunSink

    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    st = small_station()
    with RerunSink(st, "serve", grpc_port=port) as server:
        assert server.url is not None and f":{port}/" in server.url
        server.write(*synthetic_pair(st, 0))
        with RerunSink(st, "connect", server.url) as client:
            client.write(*synthetic_pair(st, 1))
