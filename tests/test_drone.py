"""`cbh validate --drone`: the paper's drone check as a command (issue 37).

Truth comes from `cbh simulate --drone-flight` (a night flight with stars, an aircraft and hot
pixels, its log on a clock 3 s ahead of the cameras'). Tolerances:

- heights: MAPE <= 1 % (the issue's target). The centroid of a clipped 1 px spot is good to
  ~0.05 px, the parallax of a 490 m drone over the 50 m baseline is ~25 px at 480 px, so the
  method's own error is ~0.2 %; 1 % leaves room for JPEG and the star field.
- the log's clock: within 0.5 s (the target); a moving drone crosses a pixel in ~0.1 s.
"""
from __future__ import annotations

import json
import math
import subprocess
from datetime import timedelta, timezone
from pathlib import Path

import numpy as np
import pytest

from cbh.errors import ConfigError, InputError
from cbh.geometry.flightlog import log_enu, parse_takeoff, parse_tz, read_flight_log
from cbh.geometry.station import load_station
from cbh.pipeline.pointsources import detect_points, persistent_sources

from .conftest import REPO

def _cbh(*args, cwd=None):
    """`cbh ARGS` in this process (the CLI's own main: its exit status, stdout and stderr)."""
    import contextlib
    import io
    import os

    from cbh.cli.main import main

    out, err = io.StringIO(), io.StringIO()
    here = os.getcwd()
    try:
        if cwd is not None:
            os.chdir(cwd)
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            rc = main([str(a) for a in args])
    finally:
        os.chdir(here)
    return subprocess.CompletedProcess(args, rc, out.getvalue(), err.getvalue())


def _render(out: Path, positions: int, size: int, **kw):
    from cbh.sim.drone import paper_plan, render_flight

    st = load_station(REPO / "configs" / "unb-lea.toml").scaled(size)
    gen = render_flight(st, out, paper_plan(positions, hover_s=kw.pop("hover_s", 12.0)), **kw)
    while True:
        try:
            next(gen)
        except StopIteration as stop:
            return stop.value


@pytest.fixture(scope="module")
def flight(tmp_path_factory):
    out = tmp_path_factory.mktemp("drone") / "flight"
    _render(out, 3, 400, cadence_s=1.0, log_offset_s=3.0, seed=7, n_stars=300, hover_s=10.0)
    return out


def _run(d: Path, *extra, log="flight.csv", out=None):
    truth = json.loads((d / "truth.json").read_text())
    return _cbh("validate", "--drone", d / log, f"--takeoff={truth['takeoff_arg']}", "--station", d / "station.toml",
                "--source", f"cam1={d / 'cam1'}", "--source", f"cam2={d / 'cam2'}", "--out",
                out or d.parent / "check.csv", *extra)


@pytest.mark.slow  # (the suite's time: 6.4 s; the flight's CLI, its report and the flight's fixes run by default below)
def test_simulated_flight_end_to_end(flight):
    """All positions reported, MAPE <= 1 %, the log's clock within 0.5 s, no star or aircraft
    taken for the drone (every measured position within 2 m of the log's)."""
    r = _run(flight, "--json")
    assert r.returncode == 0, r.stderr
    rep = json.loads(r.stdout)
    s = rep["summary"]
    truth = json.loads((flight / "truth.json").read_text())
    assert s["n_positions"] == len(truth["hover_positions_m"]) == 3
    assert s["mape_pct"] <= 1.0
    assert abs(s["clock_offset_s"] - 3.0) <= 0.5
    for row, p in zip(rep["rows"], truth["hover_positions_m"]):
        meas = np.array([row["measured_east_m"], row["measured_north_m"], row["measured_height_m"]])
        assert np.linalg.norm(meas - np.array(p)) < 2.0
        assert row["ray_miss_m"] < 1.0
    assert "fit for use" in s["advice"][0]
    assert (flight.parent / "check.csv").read_text().startswith("position,cameras,sector")
    assert (flight.parent / "check.png").stat().st_size > 10_000


def test_log_without_overlap_is_one_line(flight, tmp_path):
    log = read_flight_log(flight / "flight.csv")
    lines = ["time_utc,latitude,longitude,altitude_m"]
    for t, a, o, u in zip(log.time_utc + np.timedelta64(1, "D"), log.latitude_deg, log.longitude_deg, log.up_m):
        lines.append(f"{str(t)[:23]}Z,{a:.8f},{o:.8f},{u:.2f}")
    late = tmp_path / "late.csv"
    late.write_text("\n".join(lines) + "\n")
    r = _cbh("validate", "--drone", late, "--station", flight / "station.toml", "--source", f"cam1={flight / 'cam1'}",
             "--source", f"cam2={flight / 'cam2'}", "--out", tmp_path / "x.csv")
    assert r.returncode == 2
    assert r.stderr.startswith("cbh: error: no overlap") and r.stderr.count("\n") == 1


def test_unreadable_log_is_one_line(flight, tmp_path):
    bad = tmp_path / "log.bin"
    bad.write_bytes(bytes(range(256)) * 4)
    r = _cbh("validate", "--drone", bad, "--station", flight / "station.toml", "--source", f"cam1={flight / 'cam1'}",
             "--source", f"cam2={flight / 'cam2'}", "--out", tmp_path / "x.csv")
    assert r.returncode == 2 and r.stderr.startswith("cbh: error: flight log log.bin: not a text file")
    assert not (tmp_path / "x.csv").exists()


@pytest.mark.slow  # (the default suite's time; the flight end to end runs by default)
def test_drone_seen_by_one_camera_only(tmp_path):
    out = tmp_path / "f"
    _render(out, 1, 240, cadence_s=1.0, n_stars=100, hidden_from=("cam2",), hover_s=8.0)
    r = _run(out)
    assert r.returncode == 2, r.stdout
    assert r.stderr.startswith("cbh: error: the drone is seen by cam1 only") and r.stderr.count("\n") == 1


def test_night_or_day_by_the_sun_and_in_twilight_by_the_sky():
    """A light at night, a dark speck by day: chosen by the sun's elevation at the station, and in
    twilight (within 6 deg of the horizon) by the frame's median sky."""
    from datetime import datetime

    from cbh.actions.drone import _polarity

    st = load_station(REPO / "configs" / "unb-lea.toml")  # Brasilia: UTC-3
    dark, bright = np.full((10, 10), 10, np.uint8), np.full((10, 10), 200, np.uint8)
    valid = np.ones((10, 10), bool)
    noon, midnight = datetime(2022, 7, 15, 15, tzinfo=timezone.utc), datetime(2022, 7, 15, 3, tzinfo=timezone.utc)
    assert _polarity(st, noon, dark, valid) == "dark" and _polarity(st, midnight, bright, valid) == "bright"
    dusk = datetime(2022, 7, 15, 21, 5, tzinfo=timezone.utc)  # the sun about 2 deg below the horizon
    assert _polarity(st, dusk, bright, valid) == "dark" and _polarity(st, dusk, dark, valid) == "bright"


@pytest.mark.slow
def test_by_day_a_dark_speck(tmp_path):
    """With the sun up the drone is looked for as a dark speck against the bright sky (an
    aircraft's speck beside it); the same answer as at night."""
    from datetime import datetime

    out = tmp_path / "day"
    _render(out, 2, 320, cadence_s=1.0, log_offset_s=-2.0, seed=4, hover_s=8.0, day=True, drone_spot=(1.0, 70.0),
            start_utc=datetime(2022, 7, 15, 15, 0, tzinfo=timezone.utc))
    r = _run(out, "--json")
    assert r.returncode == 0, r.stderr
    s = json.loads(r.stdout)["summary"]
    assert s["n_positions"] == 2 and s["mape_pct"] <= 1.0 and abs(s["clock_offset_s"] + 2.0) <= 0.5


def test_report_never_overwrites_the_log(flight):
    r = _run(flight, out=flight / "flight.csv")
    assert r.returncode == 2 and "own inputs" in r.stderr


# --- the parts ---------------------------------------------------------------------------------

def test_csv_and_srt_writers_read_back(tmp_path):
    from datetime import datetime

    from cbh.sim.drone import write_flight_log_csv, write_flight_log_srt

    t0 = datetime(2022, 7, 15, 1, 0, tzinfo=timezone.utc)
    stamps = [t0 + timedelta(seconds=0.1 * i) for i in range(30)]
    lat, lon, up = np.linspace(-15.76, -15.7601, 30), np.full(30, -47.87), np.linspace(0, 29, 30)
    write_flight_log_csv(tmp_path / "a.csv", stamps, lat, lon, up)
    write_flight_log_srt(tmp_path / "a.SRT", stamps, lat, lon, up)
    for name, tol in (("a.csv", 1e-8), ("a.SRT", 1e-6)):
        log = read_flight_log(tmp_path / name)
        assert log.time_utc.size == 30
        assert log.time_utc[5] == np.datetime64("2022-07-15T01:00:00.500")
        assert np.allclose(log.latitude_deg, lat, atol=tol) and np.allclose(log.up_m, up, atol=1e-3)


def test_airdata_csv_in_feet_with_milliseconds(tmp_path):
    """AirData: one-second datetimes refined by time(millisecond), heights in feet."""
    rows = ["time(millisecond),datetime(utc),latitude,longitude,height_above_takeoff(feet)"]
    for i in range(25):  # 10 Hz from 12:00:00.700
        ms = 100 * i
        t = np.datetime64("2022-07-15T12:00:00.700") + np.timedelta64(ms, "ms")
        rows.append(f"{ms},{str(t.astype('datetime64[s]')).replace('T', ' ')},-15.76,-47.87,{10.0 * i}")
    (tmp_path / "airdata.csv").write_text("\n".join(rows) + "\n")
    log = read_flight_log(tmp_path / "airdata.csv")
    assert log.time_utc[0] == np.datetime64("2022-07-15T12:00:00.700")
    assert np.isclose(log.up_m[3], 30 * 0.3048)


def test_older_dji_layout_and_local_time(tmp_path):
    srt = ("1\n00:00:00,000 --> 00:00:01,000\nHOME(-47.8700,-15.7630) 2017.08.05 14:11:51\n"
           "GPS(-47.8701,-15.7631,16) BAROMETER:12.5\nISO:100 Shutter:60 EV:0 Fnum:2.2\n\n"
           "2\n00:00:01,000 --> 00:00:02,000\nHOME(-47.8700,-15.7630) 2017.08.05 14:11:52\n"
           "GPS(-47.8702,-15.7632,16) BAROMETER:13.0\nISO:100 Shutter:60 EV:0 Fnum:2.2\n")
    (tmp_path / "old.SRT").write_text(srt)
    log = read_flight_log(tmp_path / "old.SRT", parse_tz("-03:00"))
    assert log.time_utc[0] == np.datetime64("2017-08-05T17:11:51")
    assert np.allclose(log.longitude_deg, [-47.8701, -47.8702]) and np.allclose(log.latitude_deg, [-15.7631, -15.7632])
    assert np.allclose(log.up_m, [12.5, 13.0])


def test_bad_logs_and_options(tmp_path):
    (tmp_path / "nodate.SRT").write_text("1\n00:00:00,000 --> 00:00:01,000\n[latitude: 1.0] [longitude: 2.0]\n")
    with pytest.raises(InputError, match="no subtitle with a date"):
        read_flight_log(tmp_path / "nodate.SRT")
    (tmp_path / "cols.csv").write_text("a,b,c,d\n1,2,3,4\n")
    with pytest.raises(InputError, match="no time column"):
        read_flight_log(tmp_path / "cols.csv")
    with pytest.raises(InputError, match="not found"):
        read_flight_log(tmp_path / "missing.csv")
    for bad in ("1,2", "a,b,c", "91,0,0"):
        with pytest.raises(ConfigError, match="--takeoff"):
            parse_takeoff(bad)
    with pytest.raises(ConfigError, match="--log-tz"):
        parse_tz("+25:00")


def test_positions_go_through_pymap3d_above_the_takeoff():
    """A fix over the station's origin, 100 m above a take-off 10 m below the cameras: ENU (0, 0, 90)."""
    st = load_station(REPO / "configs" / "unb-lea.toml")
    from cbh.geometry.flightlog import FlightLog

    log = FlightLog(np.array(["2022-01-01T00:00:00", "2022-01-01T00:00:01"], "datetime64[ns]"),
                    np.array([st.latitude_deg] * 2), np.array([st.longitude_deg] * 2), np.array([100.0, 100.0]), "csv")
    enu, notes = log_enu(log, st, parse_takeoff(f"{st.latitude_deg},{st.longitude_deg},-10"))
    assert np.allclose(enu[0], [0, 0, 90], atol=1e-6) and not notes
    enu, notes = log_enu(log, st, None)
    assert np.isclose(enu[0, 2], 100.0) and "no --takeoff" in notes[0]


def _spot(img, x, y, amp, sigma=1.0):
    yy, xx = np.mgrid[: img.shape[0], : img.shape[1]]
    img += amp * np.exp(-((xx - x) ** 2 + (yy - y) ** 2) / (2 * sigma**2))


def test_detect_points_subpixel_bright_and_dark():
    """A 1 px Gaussian light found to 0.05 px in noise of 1.5 grey levels; a dark speck by day."""
    rng = np.random.default_rng(1)
    night = 10 + rng.normal(0, 1.5, (120, 160))
    _spot(night, 60.3, 40.7, 120)
    p = detect_points(np.clip(night, 0, 255).astype(np.uint8))
    assert len(p) == 1 and np.hypot(p[0, 0] - 60.3, p[0, 1] - 40.7) < 0.05
    day = 180 + rng.normal(0, 1.5, (120, 160))
    _spot(day, 100.6, 80.2, -60)
    p = detect_points(np.clip(day, 0, 255).astype(np.uint8), polarity="dark")
    assert len(p) == 1 and np.hypot(p[0, 0] - 100.6, p[0, 1] - 80.2) < 0.1
    assert len(detect_points(np.clip(day, 0, 255).astype(np.uint8), polarity="bright")) == 0


def test_clipped_broad_light_centroid():
    """A light clipped at 255 over a plateau 4 px wide (sigma 1.9 px, peak 376 before clipping:
    eval_drone's flight 5, whose first maximum sat 2 px off the centre and gave 2.2 % MAPE)
    found to 0.05 px."""
    rng = np.random.default_rng(3)
    for x, y in ((60.45, 40.8), (61.2, 41.5), (59.9, 40.05)):
        img = 8 + rng.normal(0, 1.5, (100, 120))
        _spot(img, x, y, 376, sigma=1.9)
        p = detect_points(np.clip(img, 0, 255).astype(np.uint8))
        assert len(p) == 1 and np.hypot(p[0, 0] - x, p[0, 1] - y) < 0.05, (x, y, p[:, :2])


def test_stars_and_hot_pixels_persist_a_hovering_drone_does_not():
    """Stars turn with the sky (predicted to the pixel), hot pixels stay; a drone hovering a
    minute 2 px beside a star (eval_drone seed 1 flight 9, where a radius grown with the time
    apart took the drone for the star) is neither."""
    from cbh.pipeline.pointsources import sky_turn

    st = load_station(REPO / "configs" / "unb-lea.toml").scaled(960)
    cam = st.cameras["cam2"]
    move = sky_turn(cam, st.latitude_deg)
    star0 = np.array([[354.4, 494.8], [600.0, 300.0]])
    t = np.arange(0.0, 600.0, 5.0)
    pts = []
    for s in t:
        stars = move(star0, s)
        drone = [[354.1, 492.7]] if 300 <= s < 360 else [[200.0 + s / 3, 120.0]]  # a 60 s hover, then flying
        pts.append(np.vstack([stars, [[7.0, 9.0]], drone]))
    keep = persistent_sources(t, pts, move)
    for k, s in zip(keep, t):
        assert k[0] and k[1] and k[2] and not k[3], s


def test_clock_offset_from_tracks_without_images():
    """The log's clock found to 0.05 s from projected detections alone, stars beside them."""
    from cbh.pipeline.dronetrack import CameraTrack, clock_offset, find_hovers
    from cbh.sim.drone import Flight, paper_plan

    st = load_station(REPO / "configs" / "unb-lea.toml").scaled(480)
    plan = paper_plan(3, hover_s=10.0)
    fl = Flight(plan, None, 2.3, np.arange(0.0, plan.waypoints()[0][-1], 1.0))
    log_cam_t = np.arange(0.0, fl.duration_s, 0.1)
    log_t, enu = log_cam_t + 2.3, fl.position(log_cam_t)
    tracks = []
    for cam in st.cameras.values():
        px = cam.world_to_pixel(fl.position(fl.times_s))
        stars = np.array([[100.0, 100.0], [300.0, 200.0]])
        tracks.append(CameraTrack(cam, fl.times_s, [np.vstack([stars, p[None]]) if np.all(np.isfinite(p)) else stars
                                                    for p in px]))
    c = clock_offset(tracks, log_t, enu, search_s=30.0)
    assert abs(c["offset_s"] - 2.3) < 0.05 and c["moving_frames"] > 20
    hov = find_hovers(log_t, enu, enu[:, 2] - plan.takeoff_m[2])
    assert len(hov) == 3 and all(abs(h.end_s - h.start_s - 10.0) < 1.5 for h in hov)
    assert np.allclose([h.position_m for h in hov], plan.positions_m, atol=1e-6)
    assert math.isfinite(c["stderr_s"])
    # a GPS's fix-to-fix jitter (0.5 m horizontally, 0.17 m vertically, white at 10 Hz): still 3 hovers
    noisy = enu + np.random.default_rng(0).normal(0, 1, enu.shape) * np.array([0.5, 0.5, 0.17])
    hov = find_hovers(log_t, noisy, noisy[:, 2] - plan.takeoff_m[2])
    assert len(hov) == 3 and np.allclose([h.position_m for h in hov], plan.positions_m, atol=0.2)


@pytest.mark.slow
def test_paper_flight_twenty_positions_and_a_misoriented_camera(tmp_path):
    """The paper's 20 positions at 960 px, 1000 stars, the log (DJI SRT) 3 s behind: MAPE <= 1 %, clock
    within 0.5 s; the same frames checked against a station whose camera 2 is stated 1 deg
    tilted and 0.5 deg turned: the turn found (within 0.15 deg) and pointed to `cbh calibrate`."""
    from dataclasses import replace

    from cbh.geometry.station import rot_x, rot_z

    d = tmp_path / "f"
    _render(d, 20, 960, cadence_s=2.0, log_offset_s=-3.0, seed=5, n_stars=1000, hover_s=20.0)
    r = _run(d, "--json", log="flight.SRT")
    assert r.returncode == 0, r.stderr
    s = json.loads(r.stdout)["summary"]
    assert s["n_positions"] == 20 and s["mape_pct"] <= 1.0 and abs(s["clock_offset_s"] + 3.0) <= 0.5
    st = load_station(d / "station.toml")
    c2 = st.cameras["cam2"]
    bad = replace(st, cameras={**st.cameras, "cam2": replace(
        c2, R_world_from_cam=rot_z(math.radians(0.5)) @ rot_x(math.radians(1.0)) @ c2.R_world_from_cam)})
    (tmp_path / "bad.toml").write_text(bad.to_toml())
    truth = json.loads((d / "truth.json").read_text())
    r = _cbh("validate", "--drone", d / "flight.csv", f"--takeoff={truth['takeoff_arg']}", "--station",
             tmp_path / "bad.toml", "--source", f"cam1={d / 'cam1'}", "--source", f"cam2={d / 'cam2'}",
             "--out", tmp_path / "bad.csv", "--json")
    assert r.returncode == 0, r.stderr
    s = json.loads(r.stdout)["summary"]
    turn = s["orientation"]["cam2"]
    assert abs(turn["tilt_deg"] - 1.0) < 0.15 and abs(abs(turn["yaw_deg"]) - 0.5) < 0.15
    assert s["orientation"]["cam1"]["angle_deg"] < 0.1
    assert any("cam2 sees the drone" in a and "cbh calibrate" in a for a in s["advice"])


@pytest.mark.slow
def test_recordings_in_place_of_sources(tmp_path):
    """`cbh run --record` over the flight's folders, then the check on the recording alone (its
    station read from it): the same answer as on the folders."""
    d = tmp_path / "f"
    _render(d, 2, 320, cadence_s=1.0, log_offset_s=3.0, seed=2, n_stars=150, hover_s=8.0)
    rec = tmp_path / "night.mcap"
    r = _cbh("run", "--station", d / "station.toml", "--source", f"cam1={d / 'cam1'}", "--source",
             f"cam2={d / 'cam2'}", "--record", rec, "--quiet")
    assert r.returncode == 0, r.stderr
    truth = json.loads((d / "truth.json").read_text())
    r = _cbh("validate", rec, "--drone", d / "flight.csv", f"--takeoff={truth['takeoff_arg']}",
             "--out", tmp_path / "rec.csv", "--json")
    assert r.returncode == 0, r.stderr
    s = json.loads(r.stdout)["summary"]
    assert s["n_positions"] == 2 and s["mape_pct"] <= 1.0 and abs(s["clock_offset_s"] - 3.0) <= 0.5


def test_validate_needs_one_reference(tmp_path):
    """--ceilometer or --drone, one of them; --drone with recordings or --source, one of them."""
    log = tmp_path / "f.csv"
    log.write_text("time_utc,latitude,longitude,altitude_m\n")
    for args, said in ((["x.mcap"], "give either --ceilometer"),
                       (["x.mcap", "--drone", log, "--ceilometer", log], "give either --ceilometer"),
                       (["--drone", log], "--drone: give either recordings or --source"),
                       (["--drone", log, "--source", "cam1=a", "--source", "cam2=b"], "--station: needed with --source")):
        r = _cbh("validate", *args, cwd=tmp_path)
        assert r.returncode == 2 and r.stderr.startswith("cbh: error: ") and said in r.stderr, (args, r.stderr)
        assert r.stderr.count("\n") == 1


@pytest.mark.slow
def test_three_camera_network_reports_every_pair(tmp_path):
    """A network of three cameras (unb-lea-network: 50 m and 630 m baselines): every position
    measured by each of the three pairs, MAPE <= 1 % on each."""
    from cbh.sim.drone import paper_plan, render_flight

    st = load_station(REPO / "configs" / "unb-lea-network.toml").scaled(480)
    d = tmp_path / "f"
    for _ in render_flight(st, d, paper_plan(3, hover_s=10.0), cadence_s=1.0, n_stars=200):
        pass
    truth = json.loads((d / "truth.json").read_text())
    r = _cbh("validate", "--drone", d / "flight.csv", f"--takeoff={truth['takeoff_arg']}", "--station",
             d / "station.toml", *[a for c in ("cam1", "cam2", "cam3") for a in ("--source", f"{c}={d / c}")],
             "--out", tmp_path / "net.csv", "--json")
    assert r.returncode == 0, r.stderr
    s = json.loads(r.stdout)["summary"]
    assert s["n_positions"] == 3 and s["n_comparisons"] == 9
    assert set(s["by_pair"]) == {"cam1-cam2", "cam1-cam3", "cam2-cam3"}
    assert all(m["n"] == 3 and m["mape_pct"] <= 1.0 for m in s["by_pair"].values())


def test_a_night_pair_is_flagged_night_not_geometry():
    """At night (the sun 50 deg below the horizon) the frames hold stars, a drone's light and
    noise: the pipeline says `night` (layers not valid), never `geometry_mismatch`."""
    from cbh.flags import INVALIDATING
    from cbh.pipeline import Pipeline
    from cbh.sim.drone import DEFAULT_START, _frame, _Sky

    st = load_station(REPO / "configs" / "unb-lea.toml").scaled(320)
    sky = _Sky(st, 3, 400, 600.0)
    rng = np.random.default_rng(0)
    pipe = Pipeline(st)
    for t in (0.0, 10.0, 20.0):
        imgs = [_frame(c, sky, t, np.array([25.0, 30.0, 150.0]), rng, 1.5) for c in st.cameras.values()]
        r = pipe.process(imgs[0], imgs[1], DEFAULT_START + timedelta(seconds=t), channels="bgr")
        assert "night" in r.flags and "geometry_mismatch" not in r.flags, r.flags
        assert set(r.flags) & INVALIDATING
