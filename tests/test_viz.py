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
    for entity in ("/cam1/image", "/cam1/cloud_mask", "/cam1/cloud_outline", "/cam2/matches", "/world/points",
                   "/world/cameras", "/histogram", "/layers/0", "/layers/1", "/height_map", "/cloud_fraction/cam1",
                   "/service/pairs_processed", "/legend"):
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


def test_display_histogram_has_visible_bars_and_keeps_every_count():
    """The pipeline's ~500 log bins become ≤ 60 linear bars from 0 to the top of the data."""
    from cbh.outputs.rerun_view import HIST_BARS, display_histogram

    edges = np.exp(np.linspace(np.log(50.0), np.log(15000.0), 503))
    rng = np.random.default_rng(0)
    h = np.concatenate([rng.normal(1200, 40, 6000), rng.normal(3500, 90, 2000)])
    counts, _ = np.histogram(h, bins=edges)
    centres, bars, width = display_histogram(edges, counts)
    assert 10 <= len(bars) <= HIST_BARS
    assert bars.sum() == counts.sum()  # re-binned, nothing lost
    assert centres[-1] + width / 2 == 4000.0  # the range ends at the next whole km above the data
    top_two = sorted(centres[np.argsort(bars)[-2:]])
    assert abs(top_two[0] - 1200) <= width and abs(top_two[1] - 1200) <= width or abs(top_two[1] - 3500) <= 2 * width
    assert display_histogram(edges, np.zeros(502))[1].size == 0


def test_cloud_outline_traces_the_mask_boundary_in_full_size_pixels():
    from cbh.outputs.rerun_view import cloud_outline

    mask = np.zeros((960, 960), bool)
    mask[200:400, 300:700] = True  # a 200 x 400 px cloud
    lines = cloud_outline(mask, max_px=480)  # traced at half size
    assert len(lines) == 1
    xy = lines[0]
    np.testing.assert_array_equal(xy[0], xy[-1])  # closed
    # boundary pixels of the decimated mask, mapped back: within one decimation step of the true edge
    assert abs(xy[:, 0].min() - 300) <= 1 and abs(xy[:, 0].max() - 699) <= 1
    assert abs(xy[:, 1].min() - 200) <= 1 and abs(xy[:, 1].max() - 399) <= 1
    assert cloud_outline(np.zeros((10, 10), bool)) == []


def test_legend_uses_the_height_colour_map():
    from cbh.outputs.rerun_view import height_colors, legend_image

    img = legend_image((0.0, 10000.0), width_px=600)
    row = img[10, 12:612]  # the colour bar's first row
    np.testing.assert_array_equal(row[0], height_colors(np.array([0.0]))[0])
    np.testing.assert_array_equal(row[-1], height_colors(np.array([10000.0]))[0])


@needs_cli
def test_default_view_hides_matches_and_shows_motion_arrows(tmp_path):
    """Matches are a small subsample, hidden by default; a layer with motion gets an arrow."""
    from dataclasses import replace

    from cbh.outputs.rerun_view import RerunSink

    st = small_station()
    frames, res = synthetic_pair(st, 0)
    res.layers[0] = replace(res.layers[0], motion_east_ms=8.0, motion_north_ms=-3.0)
    out = tmp_path / "v.rrd"
    with RerunSink(st, "save", str(out)) as sink:
        sink.write(frames, res)
    assert rrd_verify(out).returncode == 0
    full = rrd_print(out, "-vvv")
    assert "/world/motion" in full and "8.5 m/s towards 111" in full  # hypot(8, 3) = 8.54, bearing atan2(8, -3)
    assert "EntityBehavior" in full or "Visible" in full  # the blueprint hides matches/flow/fill


def test_matches_are_a_small_subsample():
    """3600 match dots buried the clouds: at most MAX_SHOWN_MATCHES per camera are logged."""
    from cbh.outputs.rerun_view import MAX_SHOWN_MATCHES, log_pair
    from cbh.result import PointSet

    class Rec:  # records what log_pair logs
        def __init__(self):
            self.logged = {}

        def set_time(self, *a, **k):
            pass

        def log(self, path, *archetypes, **k):
            self.logged[path] = archetypes

    st = small_station()
    frames, res = synthetic_pair(st, 0)
    n = 3600
    rng = np.random.default_rng(1)
    xyz = rng.uniform(0, 3000, (n, 3)).astype(np.float32)
    px = rng.uniform(0, 100, (n, 2)).astype(np.float32)
    res.points = PointSet(xyz, np.zeros(n, np.float32), px, px.copy(), np.zeros(n, np.int16))
    rec = Rec()
    log_pair(rec, {f.camera: (f.encoded, f.format) for f in frames}, res)
    shown = rec.logged["/cam1/matches"][0].positions.as_arrow_array()
    assert 0 < len(shown) <= MAX_SHOWN_MATCHES
    assert len(rec.logged["/world/points"][0].positions.as_arrow_array()) == n  # 3D keeps every point


def test_a_flagged_pair_looks_flagged_and_says_why(tmp_path):
    """Issue 32: on the real station's first pair the viewer drew three layers and nothing said
    they were invalid. An invalid pair's points and layer samples are grey (layers as crosses),
    and the flag panel names each flag and its meaning; a valid pair says so and keeps its colours."""
    from dataclasses import replace

    from cbh.outputs.rerun_view import FLAGGED_RGB, RerunSink, flag_text

    st = small_station()
    frames, res = synthetic_pair(st, 0)
    bad = replace(res, flags=list(res.flags) + ["clock_unknown"],
                  diagnostics={**res.diagnostics, "clock_offset_s": float("nan")})
    text = flag_text(bad)
    assert text.startswith("**Not valid** (clock_unknown)") and "clock offset, which could explain a disagreement" in text
    good = replace(res, flags=[f for f in res.flags if f not in ("clock_unknown", "geometry_mismatch")],
                   diagnostics={**res.diagnostics, "clock_offset_s": -31.04, "clock_offset_pair_s": -30.8})
    gtext = flag_text(good)
    assert gtext.startswith("**Valid.**") and "−" in gtext and "-31.0 s" in gtext
    out, ok = tmp_path / "f.rrd", tmp_path / "ok.rrd"
    with RerunSink(st, "save", str(out)) as sink:
        sink.write(frames, bad)
    with RerunSink(st, "save", str(ok)) as sink:
        sink.write(frames, good)
    assert rrd_verify(out).returncode == 0 and rrd_verify(ok).returncode == 0
    grey = int.from_bytes(bytes(FLAGGED_RGB) + b"\xff", "big")  # Rerun's packed RGBA
    bad_cols, ok_cols = _components(out), _components(ok)
    assert set(bad_cols["/world/points", "Points3D:colors"]) == {grey}
    assert grey not in set(ok_cols["/world/points", "Points3D:colors"])
    assert set(bad_cols["/layers/0", "SeriesPoints:colors"]) == {grey}
    assert bad_cols["/layers/0", "SeriesPoints:markers"] != ok_cols["/layers/0", "SeriesPoints:markers"]
    assert bad_cols["/flags", "TextDocument:text"][0].startswith("**Not valid** (clock_unknown)")
    assert ok_cols["/flags", "TextDocument:text"][0].startswith("**Valid.**")


def _components(path) -> dict:
    """(entity, component) → the flattened values logged on the capture time line, read back from
    the .rrd with Rerun's own reader."""
    from rerun.chunk import RrdReader

    out = {}
    for ch in RrdReader(str(path)).stream().to_chunks():
        t = ch.to_record_batch()
        if "capture_time" not in t.schema.names:
            continue
        for name in t.schema.names:
            if ":" in name:
                vals = [v for row in t.column(name).to_pylist() for v in (row if isinstance(row, list) else [row])]
                out.setdefault((str(ch.entity_path), name), []).extend(vals)
    return out
