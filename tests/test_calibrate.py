"""`cbh calibrate` and its numerics: orientation from the sun track and the clouds (issue 12).

The simulated day: the station file configs/unb-lea-level.toml says both cameras are level with
yaw 0; the scene `misoriented-day` renders camera 1 at (yaw, pitch, roll) = (2.0, 0.3, −0.2)°
and camera 2 at (−5.6, −0.4, 0.25)°. Tests use a short day at 480 px (a working pixel is
0.38° at 45° off axis); the full 960 px day of 100 pairs is the `slow` test and
benchmarks/bench_calibrate.py.
"""
from __future__ import annotations

import json
import math
from datetime import datetime, timedelta, timezone

import numpy as np
import pytest

from cbh.cli.main import main
from cbh.errors import CalibrationError
from cbh.geometry.calibrate import (
    PairObservations, SunObservations, SunPairObservations, epipolar_angle_rad, fit_orientations,
    rotation_from_far_matches,
)
from cbh.geometry.station import angles_from_rotation, load_station, rotation_from_angles

TRUE = {"cam1": (2.0, 0.3, -0.2), "cam2": (-5.6, -0.4, 0.25)}
DAY_START = datetime(2024, 6, 21, 10, 0, tzinfo=timezone.utc)  # the simulated days' first frame


def angle_between_deg(A, B) -> float:
    return math.degrees(math.acos(min(1.0, (np.trace(A.T @ B) - 1.0) / 2.0)))


# --- numerics ------------------------------------------------------------------------------------

@pytest.mark.parametrize("angles", [(2.0, 0.3, -0.2), (-5.6, -0.4, 0.25), (170.0, 30.0, -40.0), (-120.0, -10.0, 60.0)])
def test_angles_from_rotation_inverts_rotation_from_angles(angles):
    assert np.allclose(angles_from_rotation(rotation_from_angles(*angles)), angles, atol=1e-9)


def _sun_track(n=40):
    """A day's sun directions (ENU): an arc 120° of azimuth long, zenith 70° → 40° → 70°."""
    az = np.radians(np.linspace(60.0, 300.0, n))
    zen = np.radians(40.0 + 30.0 * np.abs(np.linspace(-1, 1, n)))
    return np.stack([np.sin(zen) * np.sin(az), np.sin(zen) * np.cos(az), np.cos(zen)], axis=-1)


def _cloud_rays(R1, R2, p2, n=2000, height_m=2000.0, seed=0):
    """Camera-frame rays of both cameras to points of a cloud base at ``height_m``."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(-4000, 4000, (n, 2))
    pts = np.concatenate([xy, np.full((n, 1), height_m)], axis=1)
    d1 = pts / np.linalg.norm(pts, axis=1, keepdims=True)
    d2 = pts - p2
    d2 /= np.linalg.norm(d2, axis=1, keepdims=True)
    return d1 @ R1, d2 @ R2


def _noisy(rays, sigma_rad, rng):
    r = rays + rng.normal(0.0, sigma_rad, rays.shape)
    return r / np.linalg.norm(r, axis=1, keepdims=True)


def test_joint_fit_recovers_both_orientations_from_sun_and_clouds():
    rng = np.random.default_rng(1)
    R1, R2 = rotation_from_angles(*TRUE["cam1"]), rotation_from_angles(*TRUE["cam2"])
    p2 = np.array([50.0, 0.0, 0.0])
    sun = _sun_track()
    # sun detections with 0.05° noise; cloud rays with 0.1 px-equivalent noise at 306 px/rad
    s1, s2 = _noisy(sun @ R1, math.radians(0.05), rng), _noisy(sun @ R2, math.radians(0.05), rng)
    r1, r2 = _cloud_rays(R1, R2, p2)
    r2 = _noisy(r2, 0.1 / 306.0, rng)
    r2[:200] = _noisy(r2[:200], 0.05, rng)  # 10 % mismatches
    level = rotation_from_angles(0, 0, 0)
    fit = fit_orientations({"cam1": level, "cam2": level},
                           {"cam1": SunObservations(s1, sun), "cam2": SunObservations(s2, sun)},
                           [PairObservations("cam1", "cam2", r1, r2, p2, 0.1 / 306.0)], reference="cam1")
    # 40 detections at 0.05° each: the mean direction is good to ~0.01°; the clouds fix the
    # relative rotation to ~0.1 px / √1800 ≈ 0.0005°
    assert angle_between_deg(fit.cameras["cam1"].R_world_from_cam, R1) < 0.03
    assert angle_between_deg(fit.cameras["cam2"].R_world_from_cam, R2) < 0.03
    rel = fit.cameras["cam1"].R_world_from_cam.T @ fit.cameras["cam2"].R_world_from_cam
    assert angle_between_deg(rel, R1.T @ R2) < 0.005
    assert fit.absolute and max(fit.cameras["cam1"].sigma_deg) < 0.05


def test_relative_fit_with_clouds_only_holds_the_reference_camera():
    R1, R2 = rotation_from_angles(*TRUE["cam1"]), rotation_from_angles(*TRUE["cam2"])
    p2 = np.array([50.0, 0.0, 0.0])
    r1, r2 = _cloud_rays(R1, R2, p2)
    Rr, inl = rotation_from_far_matches(r1, r2, threshold_deg=6.0)  # 50 m at 2 km: ≤ 1.4° parallax
    assert inl.mean() > 0.9
    start2 = R1 @ Rr
    fit = fit_orientations({"cam1": R1, "cam2": start2}, {}, [PairObservations("cam1", "cam2", r1, r2, p2, 1e-4)],
                           reference="cam1")
    assert not fit.absolute
    assert np.allclose(fit.cameras["cam1"].R_world_from_cam, R1)
    assert angle_between_deg(fit.cameras["cam2"].R_world_from_cam, R2) < 0.001


def test_sun_in_both_cameras_is_a_relative_constraint():
    R1, R2 = rotation_from_angles(*TRUE["cam1"]), rotation_from_angles(*TRUE["cam2"])
    sun = _sun_track(3)
    sp = SunPairObservations("cam1", "cam2", sun @ R1, sun @ R2)
    p2 = np.array([50.0, 0.0, 0.0])
    r1, r2 = _cloud_rays(R1, R2, p2, n=300)
    fit = fit_orientations({"cam1": R1, "cam2": rotation_from_angles(0, 0, 0)}, {},
                           [PairObservations("cam1", "cam2", r1, r2, p2, 1e-3)], reference="cam1", sun_pairs=[sp])
    assert angle_between_deg(fit.cameras["cam2"].R_world_from_cam, R2) < 0.01


def test_a_single_sun_direction_cannot_fix_a_rotation():
    sun = np.repeat(_sun_track(1), 10, axis=0)
    R = rotation_from_angles(*TRUE["cam1"])
    with pytest.raises(CalibrationError, match="cannot determine"):
        fit_orientations({"cam1": rotation_from_angles(0, 0, 0)}, {"cam1": SunObservations(sun @ R, sun)}, [],
                         reference="cam1")


def test_epipolar_angle_is_zero_for_coplanar_rays_and_grows_with_rotation():
    R = rotation_from_angles(0, 0, 0)
    r1, r2 = _cloud_rays(R, R, np.array([50.0, 0, 0]), n=50)
    d1, d2 = r1 @ R.T, r2 @ R.T
    assert np.abs(epipolar_angle_rad(d1, d2, np.array([50.0, 0, 0]))).max() < 1e-9
    tilt = rotation_from_angles(0.0, 0.5, 0.0) @ R.T  # camera 2 tilted 0.5° about the baseline
    e = epipolar_angle_rad(d1, d2 @ tilt.T, np.array([50.0, 0, 0]))
    assert 0.1 < math.degrees(np.median(np.abs(e))) <= 0.5


# --- the command on a simulated day --------------------------------------------------------------

@pytest.fixture(scope="module")
def day(tmp_path_factory, repo):
    """14 frame pairs at 480 px from 10:00 to 18:40 UTC (every 40 min) of the misoriented day."""
    from cbh.sim import SkySimulator, load_scene

    out = tmp_path_factory.mktemp("day")
    st = load_station(repo / "configs" / "unb-lea-level.toml")
    sim = SkySimulator(st, load_scene(repo / "configs" / "scenes" / "misoriented-day.toml"), size_px=480)
    _render_day(sim, out, 14, 40 * 60.0, "# installation day: both cameras level, yaw 0\n")
    return out


def _render_day(sim, out, frames: int, step_s: float, header: str = "") -> None:
    """``out/station.toml`` (the simulator's station, after ``header``) and ``frames`` time steps
    of every camera from ``DAY_START``, ``step_s`` apart."""
    from cbh.sim.io import write_shot

    (out / "station.toml").write_text(header + sim.station.to_toml())
    for i in range(frames):
        write_shot(sim.render(DAY_START + timedelta(seconds=step_s * i)), out, 92)


def _run(args, capsys):
    code = main(args)
    cap = capsys.readouterr()
    return code, cap.out, cap.err


@pytest.mark.slow
def test_calibrate_recovers_each_camera_and_the_relative_rotation(day, tmp_path, capsys):
    out = tmp_path / "calibrated.toml"
    code, stdout, err = _run(["calibrate", "--station", str(day / "station.toml"), "--source", f"cam1={day / 'cam1'}",
                              "--source", f"cam2={day / 'cam2'}", "--out", str(out), "--json"], capsys)
    assert code == 0, err
    rep = json.loads(stdout)
    st = load_station(out)
    R1, R2 = rotation_from_angles(*TRUE["cam1"]), rotation_from_angles(*TRUE["cam2"])
    c1, c2 = st.cameras["cam1"].R_world_from_cam, st.cameras["cam2"].R_world_from_cam
    # Absolute: a handful of sun detections per camera at 480 px (0.2° per pixel near the sun),
    # each biased by up to ~0.2° towards the brighter sky: 0.2° here (0.1° is the 960 px target).
    assert angle_between_deg(c1, R1) < 0.2
    assert angle_between_deg(c2, R2) < 0.2
    # Relative: thousands of LK matches at 0.05 px: far below the 0.05° target
    assert angle_between_deg(c1.T @ c2, R1.T @ R2) < 0.02
    assert rep["absolute"] is True
    for cam in ("cam1", "cam2"):
        c = rep["cameras"][cam]
        assert c["frames"] == 14 and c["sun_used"] and c["sun_detections"] >= 5
        # RMS of the detections within 1° (outliers, e.g. a saturated cloud taken for the sun, counted apart)
        assert c["sun_rms_deg"] < 0.3 and c["sun_outliers"] <= 2 and len(c["sun_residuals"]) == c["sun_detections"]
    assert rep["pairs"] and rep["pairs"][0]["matches_used"] > 100
    text = out.read_text()
    assert "# Calibrated by `cbh calibrate`" in text and "# installation day: both cameras level, yaw 0" in text


def test_calibrate_writes_nothing_over_its_input_and_reports_one_line_errors(day, tmp_path, capsys):
    st_file = day / "station.toml"
    before = st_file.read_bytes()
    empty1, empty2 = tmp_path / "e1", tmp_path / "e2"
    empty1.mkdir()
    empty2.mkdir()
    out = tmp_path / "o.toml"
    cases = {
        "no frames": ["--source", f"cam1={empty1}", "--source", f"cam2={empty2}"],
        "no --source": ["--source", f"cam1={day / 'cam1'}"],
        "not a station camera": ["--source", f"cam1={day / 'cam1'}", "--source", f"cam2={day / 'cam2'}",
                                 "--source", f"cam9={day / 'cam2'}"],
        "no frames between": ["--source", f"cam1={day / 'cam1'}", "--source", f"cam2={day / 'cam2'}",
                              "--from", "2030-01-01T00:00:00Z"],
    }
    for what, args in cases.items():
        code, _, err = _run(["calibrate", "--station", str(st_file), "--out", str(out), *args], capsys)
        assert code == 2, what
        assert err.startswith("cbh: error:") and err.count("\n") == 1, (what, err)
        assert what.split()[-1] in err or what == "not a station camera" and "cam9" in err, (what, err)
    assert not out.exists()
    assert st_file.read_bytes() == before


@pytest.mark.slow
def test_unreadable_image_is_one_line(day, tmp_path, capsys):
    import shutil

    bad1, bad2 = tmp_path / "c1", tmp_path / "c2"
    shutil.copytree(day / "cam1", bad1)
    shutil.copytree(day / "cam2", bad2)
    victim = sorted(bad1.glob("*.jpg"))[3]
    victim.write_bytes(b"this is not a jpeg")
    code, _, err = _run(["calibrate", "--station", str(day / "station.toml"), "--source", f"cam1={bad1}",
                         "--source", f"cam2={bad2}", "--out", str(tmp_path / "o.toml")], capsys)
    assert code == 2 and err.startswith("cbh: error:") and err.count("\n") == 1


@pytest.mark.slow
def test_no_sun_needs_relative_only_which_then_keeps_camera_1(day, tmp_path, capsys):
    """Two frames 40 min apart (--from/--to): the sun track is too short to fix any camera, so
    the command asks for --relative-only, which then keeps camera 1 and fits camera 2 to it."""
    out = tmp_path / "rel.toml"
    args = ["calibrate", "--station", str(day / "station.toml"), "--source", f"cam1={day / 'cam1'}",
            "--source", f"cam2={day / 'cam2'}", "--out", str(out), "--from", "2024-06-21T12:00:00Z",
            "--to", "2024-06-21T12:45:00Z"]
    code, _, err = _run(args, capsys)
    assert code == 2 and "--relative-only" in err and err.count("\n") == 1
    code, stdout, err = _run(args + ["--relative-only", "--json"], capsys)
    assert code == 0, err
    rep = json.loads(stdout)
    assert rep["absolute"] is False
    st = load_station(out)
    level = rotation_from_angles(0, 0, 0)
    assert np.allclose(st.cameras["cam1"].R_world_from_cam, level, atol=1e-6)
    R1, R2 = rotation_from_angles(*TRUE["cam1"]), rotation_from_angles(*TRUE["cam2"])
    # camera 2 relative to camera 1 as the station holds camera 1
    assert angle_between_deg(st.cameras["cam2"].R_world_from_cam, level @ R1.T @ R2) < 0.05


@pytest.mark.slow
def test_swapped_sources_are_refused(day, tmp_path, capsys):
    """Camera 1's folder given for camera 2 and vice versa (two frames, --relative-only): the
    fit would put camera 2 7.6° off (its residual 1.2 px where 0.1 is expected). Each cloud
    ray pair then meets at the cloud's mirror image through the baseline, below the station:
    most matches meet behind both cameras (412 of 616 here; 8 of 625 with the right folders)."""
    out = tmp_path / "swapped.toml"
    code, stdout, err = _run(["calibrate", "--station", str(day / "station.toml"), "--source", f"cam1={day / 'cam2'}",
                              "--source", f"cam2={day / 'cam1'}", "--out", str(out), "--relative-only",
                              "--from", "2024-06-21T12:00:00Z", "--to", "2024-06-21T12:45:00Z"], capsys)
    assert code == 2 and err.startswith("cbh: error:") and err.count("\n") == 1, err
    assert "swapped" in err and "behind both cameras" in err
    assert not out.exists() and stdout == ""


@pytest.mark.parametrize("relative_only", [True, False])
def test_the_same_folder_for_both_cameras_is_refused(day, tmp_path, capsys, relative_only):
    """The same images for both cameras have no parallax: no station can be fitted from them
    (before, one was written). Refused as soon as three pairs are all identical, with or
    without the sun."""
    out = tmp_path / "same.toml"
    args = ["calibrate", "--station", str(day / "station.toml"), "--source", f"cam1={day / 'cam1'}",
            "--source", f"cam2={day / 'cam1'}", "--out", str(out)] + (["--relative-only"] if relative_only else [])
    code, stdout, err = _run(args, capsys)
    assert code == 2 and err.startswith("cbh: error:") and err.count("\n") == 1, err
    assert "same images" in err and "3 of 3 pairs" in err and "same folder" in err
    assert not out.exists() and stdout == ""


def test_rewrite_keeps_comments_and_replaces_a_rotation_matrix(repo):
    import tomllib

    from cbh.actions.calibrate import rewrite_station_angles
    from cbh.geometry.station import parse_station

    text = (repo / "configs" / "wahrsis-2015-10-29.toml").read_text()
    new = rewrite_station_angles(text, {"wahrsis4": (-160.0, 1.0, 2.0)}, ["Calibrated by `cbh calibrate` (test)"])
    st = parse_station(tomllib.loads(new))
    assert np.allclose(angles_from_rotation(st.cameras["wahrsis4"].R_world_from_cam), (-160.0, 1.0, 2.0), atol=1e-4)
    old = parse_station(tomllib.loads(text))
    assert np.allclose(st.cameras["wahrsis3"].R_world_from_cam, old.cameras["wahrsis3"].R_world_from_cam)
    assert "# Canon EOS 750D" in new and "max_miss_ratio = 0.05" in new
    again = rewrite_station_angles(new, {"wahrsis4": (-161.0, 1.0, 2.0)}, ["Calibrated by `cbh calibrate` (2)"])
    assert again.count("Calibrated by `cbh calibrate`") == 1


@pytest.mark.slow
@pytest.mark.parametrize("levels", ["full-range", "limited-range"])
def test_full_day_at_960px_meets_the_issue_targets(tmp_path, repo, capsys, levels):
    """Issue 12's targets: 100 pairs at 960 px; each camera within 0.1°, relative within 0.05°,
    the 2000 m layer within 1 % after calibration. Also as limited-range video of a sensor
    clipping at 235 (issue 22: white at 16 + 235 · 219/255 = 218 DN; before, the sun was
    found in none of the frames). Measured: full range 0.054° / 0.054°, relative 0.0006°, the
    layer at 1998-1999 m; limited range 0.090° / 0.090° (−0.09° of pitch in both, against
    −0.05° at full range: a sensor clipping at 92 % of full scale saturates more of the glow,
    which is brighter towards the horizon), relative 0.002°, the layer at 1995-1997 m."""
    from dataclasses import replace

    from cbh.imageio import read_image
    from cbh.pipeline import Pipeline
    from cbh.sim import SkySimulator, load_scene

    st = load_station(repo / "configs" / "unb-lea-level.toml")
    scene = load_scene(repo / "configs" / "scenes" / "misoriented-day.toml")
    if levels == "limited-range":
        scene = replace(scene, image=replace(scene.image, white_level=235, limited_range=True))
    sim = SkySimulator(st, scene, size_px=960)
    _render_day(sim, tmp_path, 100, 360.0)
    out = tmp_path / "cal.toml"
    code, _, err = _run(["calibrate", "--station", str(tmp_path / "station.toml"), "--source",
                         f"cam1={tmp_path / 'cam1'}", "--source", f"cam2={tmp_path / 'cam2'}", "--out", str(out)], capsys)
    assert code == 0, err
    cal = load_station(out)
    R1, R2 = rotation_from_angles(*TRUE["cam1"]), rotation_from_angles(*TRUE["cam2"])
    c1, c2 = cal.cameras["cam1"].R_world_from_cam, cal.cameras["cam2"].R_world_from_cam
    assert angle_between_deg(c1, R1) < 0.1 and angle_between_deg(c2, R2) < 0.1
    assert angle_between_deg(c1.T @ c2, R1.T @ R2) < 0.05
    pipe = Pipeline(cal)
    for i in (10, 50, 90):
        t = DAY_START + timedelta(seconds=360 * i)
        tag = t.strftime("%Y%m%dT%H%M%S.000Z")
        i1, _ = read_image(tmp_path / "cam1" / f"cam1_{tag}.jpg")
        i2, _ = read_image(tmp_path / "cam2" / f"cam2_{tag}.jpg")
        r = pipe.process(i1, i2, t, channels="bgr")
        assert "geometry_mismatch" not in r.flags
        main_layer = max(r.layers, key=lambda l: l.cover)
        assert abs(main_layer.height_m - 2000.0) <= 20.0


@pytest.mark.slow
def test_calibrate_reads_a_recording_of_cbh_run(tmp_path, repo, capsys):
    """A .mcap from `cbh run --record` as the source of both cameras; the station is already
    right, so the relative fit must leave camera 2 where it is (within 0.05°)."""
    from cbh.sim import SkySimulator, load_scene

    st = load_station(repo / "configs" / "unb-lea.toml")
    sim = SkySimulator(st, load_scene(repo / "configs" / "scenes" / "two-layers.toml"), size_px=480)
    (tmp_path / "st.toml").write_text(sim.station.to_toml())
    rec = tmp_path / "s.mcap"
    code, _, err = _run(["run", "--station", str(tmp_path / "st.toml"), "--frames", "3", "--record", str(rec), "-q"], capsys)
    assert code == 0, err
    out = tmp_path / "cal.toml"
    code, stdout, err = _run(["calibrate", "--station", str(tmp_path / "st.toml"), "--source", f"cam1={rec}",
                              "--source", f"cam2={rec}", "--out", str(out), "--relative-only", "--json"], capsys)
    assert code == 0, err
    rep = json.loads(stdout)
    assert rep["cameras"]["cam1"]["frames"] == 3 and rep["cameras"]["cam2"]["frames"] == 3
    cal = load_station(out)
    assert angle_between_deg(cal.cameras["cam2"].R_world_from_cam, sim.station.cameras["cam2"].R_world_from_cam) < 0.05


def test_out_must_be_a_toml_name(tmp_path, capsys):
    """``--out SESSION.mcap`` wrote the station TOML over the recording (after minutes of work);
    now it is refused up front: one error line, exit 2, the file untouched."""
    from .conftest import REPO

    rec = tmp_path / "session.mcap"
    rec.write_bytes(b"\x89MCAP0\r\n recorded data")
    code, _, err = _run(["calibrate", "--station", str(REPO / "configs" / "unb-lea.toml"), "--source",
                         f"cam1={tmp_path}", "--source", f"cam2={tmp_path}", "--out", str(rec)], capsys)
    assert code == 2 and err.startswith("cbh: error:") and err.count("\n") == 1 and ".toml" in err, err
    assert rec.read_bytes() == b"\x89MCAP0\r\n recorded data"


@pytest.mark.slow  # slow: 14 frames of a three-camera network (8.6 s); the two-camera fit stays in the default suite
def test_calibrate_a_camera_network_fits_every_pair_consistently(tmp_path, repo, capsys):
    """Three cameras (the level station plus cam3 630 m north, stated level, really at
    (1.0, −0.3, 0.4)°), 14 frames at 480 px: every pair's cloud matches (cam1-cam2, cam1-cam3,
    cam2-cam3) go into the one joint fit, so the three relative rotations are consistent by
    construction (one rotation per camera). Bars: absolute 0.2° as the two-camera test (cam3
    has too short a sun track of its own: it is fixed by the clouds); relative 0.02° for the
    50 m pair and 0.15° for the 630 m pairs, whose LK matches, between views 17° apart at
    2000 m, leave 0.22 px of epipolar residual against 0.06 px (a working pixel is 0.38°)."""
    from dataclasses import replace

    from cbh.geometry.station import parse_station
    from cbh.sim import SkySimulator, load_scene
    from cbh.sim.scene import Imperfection
    from cbh.tomlio import read_toml

    d = read_toml(repo / "configs" / "unb-lea-level.toml", "station")
    d["cameras"].append({**d["cameras"][0], "name": "cam3", "position_m": [0.0, 630.0, 0.0]})
    st = parse_station(d, base_dir=repo / "configs")
    sc = load_scene(repo / "configs" / "scenes" / "misoriented-day.toml")
    true = {**TRUE, "cam3": (1.0, -0.3, 0.4)}
    sc = replace(sc, imperfections={**sc.imperfections, "cam3": Imperfection(camera="cam3", rotation_error_deg=true["cam3"])})
    sim = SkySimulator(st, sc, size_px=480)
    _render_day(sim, tmp_path, 14, 40 * 60.0)
    out = tmp_path / "calibrated.toml"
    code, stdout, err = _run(["calibrate", "--station", str(tmp_path / "station.toml"), "--out", str(out), "--json",
                              *[a for c in true for a in ("--source", f"{c}={tmp_path / c}")]], capsys)
    assert code == 0, err
    rep = json.loads(stdout)
    assert {tuple(p["cameras"]) for p in rep["pairs"]} == {("cam1", "cam2"), ("cam1", "cam3"), ("cam2", "cam3")}
    fitted = load_station(out)
    C = {c: fitted.cameras[c].R_world_from_cam for c in true}
    R = {c: rotation_from_angles(*v) for c, v in true.items()}
    for c in true:
        assert angle_between_deg(C[c], R[c]) < 0.2, c
    assert angle_between_deg(C["cam1"].T @ C["cam2"], R["cam1"].T @ R["cam2"]) < 0.02
    for a, b in (("cam1", "cam3"), ("cam2", "cam3")):
        assert angle_between_deg(C[a].T @ C[b], R[a].T @ R[b]) < 0.15, (a, b)
