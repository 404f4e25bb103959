"""`cbh run` end to end: simulator and loopback HTTP cameras → real pipeline → MCAP / export.

Images are rendered at 320 px so one pair takes a fraction of a second on two cores.
"""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from datetime import datetime, timedelta
from pathlib import Path

import pytest

from cbh.cli.main import main

SIZE = 320
LOW_LAYER_M = 1200.0  # the default scene (two-layers): broken cumulus at 1200 m under altocumulus at 3500 m
# At 320 px the zenith parallax of the 1200 m layer over the 50 m baseline is about
# 102 px/rad · 50 / 1200 ≈ 4.2 px. At this size the layer's JPEG texture is coarse and its
# aggregated disparity is good to ≈ 0.3–0.4 px, 7–10 % of the height: the lower layer's base
# must come out within 10 % (measured on the simulator's frames over 24 sky states 2.5 s
# apart: 1219–1269 m, +1.6…+5.7 %; once 1311 m, +9.2 %, through the loopback HTTP camera).
LOW_LAYER_TOL = 0.10


def assert_low_layer(result) -> None:
    """The lowest reported layer is the scene's 1200 m cumulus, to the resolution of 320 px."""
    assert result.layers, "no layer found"
    low = min(l.height_m for l in result.layers)
    assert abs(low - LOW_LAYER_M) <= LOW_LAYER_TOL * LOW_LAYER_M, [l.height_m for l in result.layers]


@pytest.fixture(scope="module")
def sim320():
    from cbh.presets import scene_path, station_path
    from cbh.sim import SkySimulator, load_scene
    from cbh.geometry.station import load_station

    return SkySimulator(load_station(station_path()), load_scene(scene_path()), size_px=SIZE)


@pytest.fixture(scope="module")
def station320(sim320, tmp_path_factory) -> Path:
    p = tmp_path_factory.mktemp("station") / "station320.toml"
    p.write_text(sim320.station.to_toml())
    return p


def test_default_simulated_run_records_six_pairs_that_all_read_back(tmp_path, capsys):
    from cbh.outputs.record import open_session

    out = tmp_path / "demo.mcap"
    rc = main(["run", "--size", str(SIZE), "--record", str(out)])
    captured = capsys.readouterr()
    assert rc == 0, captured.err
    assert f"recorded: {out}" in captured.out
    assert "processed 6 pairs" in captured.out
    s = open_session(out)
    assert s.pair_count == 6
    pairs = list(s.pairs())
    assert len(pairs) == 6
    for p in pairs:
        f1, f2 = p.frames()
        assert f1.image.shape == (SIZE, SIZE, 3) and f2.image.shape == (SIZE, SIZE, 3)
        assert p.result.height_map.shape[0] > 0
        assert_low_layer(p.result)
    # simulator frames 10 s apart (default step), starting at the scene's time
    dts = [(b.time_utc - a.time_utc).total_seconds() for a, b in zip(pairs, pairs[1:])]
    assert dts == [10.0] * 5
    statuses = list(s.statuses())
    assert len(statuses) == 6 and statuses[-1][1]["pairs_processed"] == 6


def test_record_without_path_goes_to_recordings(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    rc = main(["run", "--size", str(SIZE), "--frames", "1", "--record", "--export", "layers.csv",
               "--rerun", "save=view.rrd"])
    out = capsys.readouterr().out
    assert rc == 0
    assert (tmp_path / "view.rrd").stat().st_size > 1000
    files = list((tmp_path / "recordings").glob("unb-lea-*.mcap"))
    assert len(files) == 1 and f"recorded: {Path('recordings') / files[0].name}" in out
    lines = (tmp_path / "layers.csv").read_text().strip().splitlines()
    assert len(lines) >= 2  # header + at least one layer row


@pytest.mark.slow
def test_http_cameras_with_a_drop_and_corrupt_frames(sim320, station320, tmp_path, capsys):
    """MJPEG camera 1 and snapshot camera 2 on loopback; cam2 goes offline, cam1 sends garbage.
    The cameras' clocks are the scene's (2024), far from this machine's: the outage's status
    records go on the pairs' time line, and the recording stays one file (stamped with the wall
    clock, they rotated it: 2 pairs in one file, 6 in the next)."""
    from cbh.sim.camera_server import CameraServer, sim_frames
    from cbh.outputs.record import open_session

    out = tmp_path / "live.mcap"
    with CameraServer(sim_frames(sim320), ["cam1", "cam2"], fps=4, step_s=10.0,
                      start_utc=sim320.scene.time_utc) as srv:
        srv.drop("cam2", 1.0)  # down at start-up: its outage comes before any frame

        def faults():
            deadline = time.monotonic() + 30
            while srv.frames_sent["cam2"] < 3 and time.monotonic() < deadline:
                time.sleep(0.05)
            srv.drop("cam2", 1.0)
            srv.corrupt("cam1", 2)

        th = threading.Thread(target=faults, daemon=True)
        th.start()
        rc = main(["run", "--station", str(station320), "--source", f"cam1={srv.url('cam1')}",
                   "--source", f"cam2={srv.url('cam2', 'snapshot')}", "--frames", "8", "--record", str(out)])
        th.join()
    cap = capsys.readouterr()
    assert rc == 0, cap.err
    assert sorted(p.name for p in tmp_path.glob("*.mcap")) == ["live.mcap"], cap.out
    s = open_session(out)
    assert s.pair_count == 8
    pairs = list(s.pairs())
    statuses = list(s.statuses())
    events = [(t, st["event"]) for t, st in statuses if "event" in st]
    assert {e["event"] for _, e in events} >= {"outage", "recovered"}, events
    assert sum(e["event"] == "outage" for _, e in events) >= 2, events  # at start-up and after 3 frames
    t_first, t_last = sim320.scene.time_utc, pairs[-1].time_utc  # the cameras' first frame … the last pair
    for t, e in events:  # on the cameras' time line (within a frame step of it), wall clock kept
        assert t_first - timedelta(seconds=20) <= t <= t_last + timedelta(seconds=20), (t, e)
        assert abs((datetime.fromisoformat(e["wall_utc"].replace("Z", "+00:00")) - t).days) > 300
    # both cameras' frames of a pair carry the same camera time stamp (X-Timestamp)
    assert all(p.images["cam1"].time_utc == p.images["cam2"].time_utc for p in pairs)
    times = [p.time_utc for p in pairs]
    assert times == sorted(times) and len(set(times)) == 8
    last = list(s.statuses())[-1][1]
    assert last["reconnects"]["cam2"] >= 1, last
    assert last["corrupt"]["cam1"] >= 1, last
    assert last["sources"] == {"cam1": "streaming", "cam2": "streaming"}


@pytest.mark.slow  # two FFmpeg RTSP handshakes and stream probes: ~10 s
def test_two_rtsp_cameras_pair_on_their_stream_clocks(sim320, station320, tmp_path, capsys):
    from cbh.sim.camera_server import RtspCameraServer, sim_frames
    from cbh.outputs.record import open_session

    out = tmp_path / "rtsp.mcap"
    with RtspCameraServer(sim_frames(sim320), ["cam1", "cam2"], fps=4, step_s=10.0,
                          start_utc=sim320.scene.time_utc) as srv:  # the scene's time, not tonight's dark sky
        rc = main(["run", "--station", str(station320), "--source", f"cam1={srv.url('cam1')}",
                   "--source", f"cam2={srv.url('cam2')}", "--frames", "3", "--record", str(out)])
    assert rc == 0, capsys.readouterr().err
    pairs = list(open_session(out).pairs())
    assert len(pairs) == 3
    for p in pairs:
        # the same frame index of both streams: well within half the 0.25 s frame interval
        dt = abs((p.images["cam1"].time_utc - p.images["cam2"].time_utc).total_seconds())
        assert dt < 0.125
        # and therefore the same simulated sky: a layer at the scene's lower base is found
        assert_low_layer(p.result)


def test_directories_of_timestamped_images(sim320, station320, tmp_path, capsys):
    from datetime import timedelta

    d = tmp_path / "images"
    d.mkdir()
    t0 = sim320.scene.time_utc
    for k in range(3):
        t = t0 + timedelta(seconds=30 * k)
        for cam in ("cam1", "cam2"):
            f = sim320.frame(cam, t)
            (d / f"{cam}_{t:%Y%m%dT%H%M%S}.000Z.jpg").write_bytes(f.encoded)
    rc = main(["run", "--station", str(station320), "--source", f"cam1={d}", "--source", f"cam2={d}",
               "--export", str(tmp_path / "l.csv")])
    out = capsys.readouterr().out
    assert rc == 0
    assert "processed 3 pairs" in out and "stopped: sources ended" in out


@pytest.mark.parametrize("argv, message", [
    (["--source", "cam9=x"], "no camera 'cam9'"),
    (["--source", "cam1"], "expected CAMERA=SPEC"),
    (["--source", "cam1=/nonexistent/dir", "--source", "cam2=/nonexistent/dir"], "no such file or directory"),
    (["--source", "cam1=sim", "--source", "cam2=ftp://x"], "would be simulated"),
    # the same camera twice: the second silently won, and the error then blamed cam2
    (["--source", "cam1=/a", "--source", "cam1=/b"], "cam1 has two --source"),
    # --overwrite is for --record: with only --export the file was silently appended to
    (["--export", "/proc/cbh-no-such-dir/x.csv", "--overwrite", "--frames", "1", "--size", "64"], "needs --record"),
    (["out.mcap"], "goes after --record"),
    (["--rerun", "bogus"], "--rerun"),
    (["--frames", "0"], "service.frames"),
    (["--record", "/proc/cbh-no-such-dir/x.mcap", "--frames", "1", "--size", "64"], "/proc/cbh-no-such-dir"),
])
def test_bad_input_is_one_line_and_exit_2(argv, message, capsys):
    rc = main(["run", *argv])
    err = capsys.readouterr().err
    assert rc == 2
    assert message in err and err.count("\n") == 1 and "Traceback" not in err


@pytest.mark.skipif(not Path("/dev/full").exists(), reason="needs Linux /dev/full")
def test_full_disk_is_one_error_and_the_recording_stays_valid(tmp_path, capsys):
    from cbh.outputs.record import open_session

    (tmp_path / "full.csv").symlink_to("/dev/full")  # every write: ENOSPC
    rc = main(["run", "--size", "64", "--frames", "2", "--record", str(tmp_path / "ok.mcap"),
               "--export", str(tmp_path / "full.csv")])
    err = capsys.readouterr().err
    assert rc == 2 and err.strip() == f"cbh: error: disk full while creating {tmp_path / 'full.csv'}"
    assert open_session(tmp_path / "ok.mcap").pair_count == 0  # closed properly, valid, empty


# --- signals (subprocesses) -----------------------------------------------------------------

SIGNAL_SIZE = 160  # px: these tests are about the process's life cycle, not about heights


def _start(tmp_path, *extra):
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    cmd = [sys.executable, "-m", "cbh.cli.main", "run", "--size", str(SIGNAL_SIZE), "--frames", "100000",
           "--record", str(tmp_path / "run.mcap"), "--export", str(tmp_path / "run.csv"), *extra]
    p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env,
                         cwd=Path(__file__).resolve().parents[1])
    lines: list[str] = []

    def pump():
        for ln in p.stderr:
            lines.append(ln)

    th = threading.Thread(target=pump, daemon=True)
    th.start()
    return p, lines, th


def _wait_pairs(p, lines, n, timeout_s=60.0):
    deadline = time.monotonic() + timeout_s
    while sum(" pairs " in ln for ln in lines) < n:
        assert p.poll() is None, "".join(lines)
        assert time.monotonic() < deadline, "".join(lines)
        time.sleep(0.05)


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
@pytest.mark.slow
def test_signal_finishes_the_pair_closes_files_and_exits_0(tmp_path, sig):
    from cbh.outputs.record import open_session

    p, lines, th = _start(tmp_path)
    _wait_pairs(p, lines, 2)
    p.send_signal(sig)
    rc = p.wait(timeout=60)
    th.join(5)
    out = p.stdout.read()
    p.stdout.close()
    p.stderr.close()
    assert rc == 0, "".join(lines)
    reported = sum(" pairs " in ln for ln in lines)
    s = open_session(tmp_path / "run.mcap")  # needs the summary: written by a proper close
    assert s.pair_count == reported >= 2
    assert f"stopped: {sig.name}" in out
    rows = (tmp_path / "run.csv").read_text().strip().splitlines()
    assert len(rows) >= 1 + reported  # header + at least one layer per pair in this scene


@pytest.mark.slow
def test_sigkill_loses_at_most_the_pair_in_flight(tmp_path):
    from cbh.outputs.record import open_session, recover

    p, lines, th = _start(tmp_path)
    _wait_pairs(p, lines, 3)
    p.kill()
    p.wait(timeout=30)
    th.join(5)
    p.stdout.close()
    p.stderr.close()
    reported = sum(" pairs " in ln for ln in lines)  # each line is printed after its pair was flushed
    rep = recover(tmp_path / "run.mcap", tmp_path / "fixed.mcap")
    assert reported <= rep.pairs <= reported + 1
    s = open_session(tmp_path / "fixed.mcap")
    assert s.pair_count == rep.pairs and len(list(s.pairs())) == rep.pairs
