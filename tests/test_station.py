"""Station TOML: the documented keys, rotations from angles, and one clear error per bad key."""
from __future__ import annotations

import shutil

import numpy as np
import pytest

from cbh.errors import ConfigError
from cbh.geometry.station import load_station, parse_station, rotation_from_angles

from .conftest import OCAM_FILE

ISSUE_EXAMPLE = """
[station]
name = "unb-lea"
latitude_deg = -15.7634
longitude_deg = -47.8703
altitude_m = 1050.0                      # ENU origin above mean sea level

[[cameras]]
name = "cam1"
calibration = "cam1_calib_results.txt"   # OCamCalib file, relative to this TOML
position_m = [0.0, 0.0, 0.0]             # east, north, up of the projection centre
yaw_deg = 0.0
pitch_deg = 0.0
roll_deg = 0.0

[[cameras]]
name = "cam2"
calibration = "cam1_calib_results.txt"
position_m = [40.0, 5.0, 0.5]
rotation = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]
"""


@pytest.fixture
def station_dir(tmp_path):
    shutil.copy(OCAM_FILE, tmp_path / "cam1_calib_results.txt")
    (tmp_path / "station.toml").write_text(ISSUE_EXAMPLE)
    return tmp_path


def test_issue_example_loads(station_dir):
    st = load_station(station_dir / "station.toml")
    assert st.name == "unb-lea" and st.altitude_m == 1050.0
    assert list(st.cameras) == ["cam1", "cam2"]
    c2 = st.camera("cam2")
    np.testing.assert_allclose(c2.position_m, [40, 5, 0.5])
    np.testing.assert_allclose(c2.R_world_from_cam, np.eye(3))
    assert st.camera("cam1").model.width == 1920


def test_level_north_camera_axes():
    R = rotation_from_angles(0, 0, 0)
    np.testing.assert_allclose(R @ [1, 0, 0], [-1, 0, 0])  # camera x → west
    np.testing.assert_allclose(R @ [0, 1, 0], [0, -1, 0])  # camera y (rows) → south
    np.testing.assert_allclose(R @ [0, 0, 1], [0, 0, 1])  # optical axis → up
    # the image top (−y) faces north
    np.testing.assert_allclose(R @ [0, -1, 0], [0, 1, 0])


@pytest.mark.parametrize("yaw, facing", [(90, [1, 0, 0]), (180, [0, -1, 0]), (-90, [-1, 0, 0]), (45, [0.70710678, 0.70710678, 0])])
def test_yaw_is_azimuth_of_image_top(yaw, facing):
    R = rotation_from_angles(yaw, 0, 0)
    np.testing.assert_allclose(R @ [0, -1, 0], facing, atol=1e-12)


def test_pitch_and_roll_tilt_about_camera_axes():
    R = rotation_from_angles(0, 10, 0)  # about camera x: the optical axis tips towards camera −y … rows
    up = R @ [0, 0, 1]
    assert np.degrees(np.arccos(up[2])) == pytest.approx(10)
    np.testing.assert_allclose(R @ [1, 0, 0], [-1, 0, 0], atol=1e-12)  # x axis unchanged by Rx
    R = rotation_from_angles(0, 0, 7)
    np.testing.assert_allclose(R @ [0, 1, 0], [0, -1, 0], atol=1e-12)  # y axis unchanged by Ry
    assert np.degrees(np.arccos((R @ [0, 0, 1])[2])) == pytest.approx(7)


def test_unb_preset_loads_and_round_trips_through_toml(unb_station, tmp_path):
    st = unb_station
    assert st.camera("cam1").model.poly[0] == pytest.approx(630.939)
    p = tmp_path / "again.toml"
    p.write_text(st.to_toml())
    again = load_station(p)
    for name in st.cameras:
        a, b = st.camera(name), again.camera(name)
        np.testing.assert_allclose(a.R_world_from_cam, b.R_world_from_cam, atol=1e-12)
        px = np.array([[100.0, 900.0], [960.0, 960.0], [1500.0, 300.0]])
        np.testing.assert_allclose(a.pixel_to_world(px), b.pixel_to_world(px), atol=1e-12)


def test_scaled_station_keeps_geometry(unb_station):
    small = unb_station.scaled(480)
    c, s = unb_station.camera("cam2"), small.camera("cam2")
    assert s.model.width == 480
    px = np.array([[700.0, 1200.0]])
    np.testing.assert_allclose(s.pixel_to_world((px + 0.5) / 4 - 0.5), c.pixel_to_world(px), atol=1e-9)


def _base():
    return {
        "station": {"name": "s", "latitude_deg": 1.0, "longitude_deg": 2.0, "altitude_m": 3.0},
        "cameras": [
            {"name": n, "position_m": [i * 50.0, 0, 0],
             "intrinsics": {"model": "equisolid", "center_xy": [99.5, 99.5], "radius_px": 90.0, "width": 200, "height": 200}}
            for i, n in enumerate(("a", "b"))
        ],
    }


def test_inline_equisolid_station():
    st = parse_station(_base())
    assert st.camera("b").model.kind == "equisolid"


@pytest.mark.parametrize("mutate, match", [
    (lambda d: d["station"].update(colour="red"), r"station\.colour: unknown key"),
    (lambda d: d["cameras"][0].update(yaw="x"), r"cameras\[0\]\.yaw: unknown key"),
    (lambda d: d["cameras"][1].update(yaw_deg="north"), r"cameras\[b\]\.yaw_deg: expected a number"),
    (lambda d: d["cameras"][1].update(rotation=[[1, 0, 0], [0, 2, 0], [0, 0, 1]]), r"cameras\[b\]\.rotation: not a rotation"),
    (lambda d: d["cameras"][1].update(rotation=[[-1, 0, 0], [0, 1, 0], [0, 0, 1]]), r"cameras\[b\]\.rotation: not a rotation"),
    (lambda d: d["cameras"][0]["intrinsics"].update(model="pinhole"), r"cameras\[a\]\.intrinsics\.model: unknown model"),
    (lambda d: d["cameras"][0]["intrinsics"].pop("radius_px"), r"cameras\[a\]\.intrinsics\.radius_px: missing"),
    (lambda d: d["cameras"][0].update(calibration="x.txt"), r"cameras\[a\]: give exactly one"),
    (lambda d: d["cameras"][1].update(name="a"), r"duplicate camera name"),
    (lambda d: d["station"].pop("altitude_m"), r"station\.altitude_m: missing"),
    (lambda d: d["cameras"].pop(), r"at least two"),
    (lambda d: d.update(extra={}), r"extra: unknown key"),
    (lambda d: d["station"].update(latitude_deg=95.0), r"latitude_deg"),
])
def test_bad_station_names_the_key(mutate, match):
    d = _base()
    mutate(d)
    with pytest.raises(ConfigError, match=match):
        parse_station(d)


def test_missing_calibration_file_names_camera(tmp_path):
    (tmp_path / "s.toml").write_text(ISSUE_EXAMPLE)
    with pytest.raises(ConfigError, match=r"cameras\[cam1\]\.calibration: calibration file not found"):
        load_station(tmp_path / "s.toml")


def test_malformed_toml(tmp_path):
    (tmp_path / "s.toml").write_text("[station\nname=")
    with pytest.raises(ConfigError, match="malformed TOML"):
        load_station(tmp_path / "s.toml")


def test_unknown_camera_lists_names(unb_station):
    with pytest.raises(ConfigError, match="cam3.*cam1, cam2"):
        unb_station.pair("cam1,cam3")


def test_station_with_multiline_metadata_and_odd_keys_round_trips(unb_station, tmp_path):
    """``cbh simulate`` and ``cbh calibrate --out`` write the station back with to_toml: a
    multi-line ``comment`` (legal TOML in the file read) and a section key that is not a bare
    TOML key must come back unchanged, not as a file cbh cannot read."""
    import dataclasses

    import tomllib

    from cbh.tomlio import dumps_toml

    st = dataclasses.replace(unb_station, sections={**unb_station.sections, "scene": {"note": "tab\there\nline 2 \"q\" \\ end"}})
    p = tmp_path / "st.toml"
    p.write_text(st.to_toml())
    back = load_station(p)
    assert back.sections["scene"] == st.sections["scene"]
    data = {"a b": 1, "t": {"x.y": "s\u0001", "plain-key_1": [1.5, 2]}, "arr": [{"n": 1, "sub": {"é": 2}}]}
    assert tomllib.loads(dumps_toml(data)) == data


@pytest.mark.parametrize("table, says", [
    ("[service]\nbogus_key = 1\n", "service.bogus_key: unknown key"),
    ("[service]\npair_tolerance_s = -1.0\n", "service.pair_tolerance_s: must be > 0"),
    ("[pipeline]\nbogus_key = 1\n", "pipeline.bogus_key: unknown key"),
])
@pytest.mark.parametrize("command", [
    ["pair", "a.jpg", "b.jpg"], ["run", "--frames", "1"], ["triangulate", "--pixels", "p.csv"],
    ["segment", "x.png", "--out", "m.png"], ["simulate", "--out", "sim", "--frames", "1"],
    ["reprocess", "--out", "o"], ["mask", "frames", "--camera", "cam1", "--out", "m.png"],
    ["validate", "--drone", "flight.csv", "--source", "cam1=f1", "--source", "cam2=f2"],
    ["simulate", "--drone-flight", "--out", "sim"],
])
def test_every_command_reads_a_station_file_the_same_way(command, table, says, repo, tmp_path, capsys,
                                                         monkeypatch):
    """`cbh pair` took an unknown [service] key that `cbh run` refused (issue 26): every command
    refuses the same station with the same line, before touching any other input."""
    import cbh
    from cbh.actions.station import load_station as load_station_checked
    from cbh.cli.main import main

    monkeypatch.chdir(tmp_path)
    st = tmp_path / "station.toml"
    st.write_text((repo / "configs" / "unb-lea.toml").read_text() + "\n" + table)
    for read in (load_station_checked, cbh.load_station):  # the commands' reader and the library's
        with pytest.raises(ConfigError, match=says):
            read(st)
    name = table.split("]")[0].lstrip("[")
    assert name in load_station(st).sections  # the geometry layer keeps the table raw (its owner checks it)
    assert main([*command, "--station", str(st)]) == 2
    out, err = capsys.readouterr()
    assert err.startswith(f"cbh: error: {says}") and err.count("\n") == 1 and out == "", err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["station.toml"]  # nothing written
