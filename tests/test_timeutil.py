"""One UTC time reader (cbh/timeutil.py), one policy (docs/conventions.md): a time without a zone
is an error everywhere, naming the expected form; file-name stamps are UTC."""
from __future__ import annotations

from datetime import datetime, timezone

import pytest

from cbh.errors import ConfigError, InputError
from cbh.timeutil import EXAMPLE, format_utc, parse_time_header, parse_utc, time_from_name

T0 = datetime(2015, 10, 29, 4, 58, 1, tzinfo=timezone.utc)


def test_times_with_a_zone_are_read_as_utc():
    assert parse_utc("2015-10-29T04:58:01Z") == T0
    assert parse_utc("2015-10-29T04:58:01z") == T0
    assert parse_utc("2015-10-29T06:58:01+02:00") == T0
    assert parse_utc(datetime(2015, 10, 29, 12, 58, 1, tzinfo=timezone.utc).astimezone()) == datetime(
        2015, 10, 29, 12, 58, 1, tzinfo=timezone.utc)
    assert format_utc(T0) == "2015-10-29T04:58:01Z" and format_utc(None) == "unknown"


@pytest.mark.parametrize("text", ["2015-10-29T04:58:01", "2015-10-29 04:58", "2015-10-29"])
def test_a_time_without_a_zone_is_an_error_naming_the_expected_form(text):
    with pytest.raises(InputError, match="has no zone") as e:
        parse_utc(text, "--time")
    assert EXAMPLE in str(e.value) and str(e.value).startswith("--time: ")
    with pytest.raises(ConfigError, match="has no zone"):
        parse_utc(text, "scene: time_utc", error=ConfigError)


def test_everywhere_a_time_is_read_the_policy_is_the_same(tmp_path, capsys):
    from cbh.cli.main import main
    from cbh.sim import parse_scene

    with pytest.raises(ConfigError, match="time_utc: time '2024-06-21T14:00:00' has no zone"):
        parse_scene({"time_utc": "2024-06-21T14:00:00"})
    assert main(["simulate", "--out", str(tmp_path / "o"), "--start", "2024-06-21T14:00:00"]) == 2
    assert "--start: time '2024-06-21T14:00:00' has no zone" in capsys.readouterr().err
    img = tmp_path / "x.png"
    assert main(["pair", str(img), str(img), "--station", "configs/unb-lea.toml", "--time", "2024-06-21 14:00"]) == 2
    assert "--time: time '2024-06-21 14:00' has no zone" in capsys.readouterr().err
    # a camera header without a zone is not read (the frame keeps its receive time)
    assert parse_time_header("2015-10-29T04:58:01") is None
    assert parse_time_header("2015-10-29T04:58:01Z") == T0


@pytest.mark.parametrize("name", ["cam1_20151029T045801Z.jpg", "cam1_20151029T045801.jpg",
                                  "2015-10-29_04-58-01.png", "img-20151029045801.jpg"])
def test_file_name_stamps_are_utc_with_or_without_z(name):
    assert time_from_name(name) == T0


def test_pair_takes_the_file_name_stamp_as_utc(tmp_path):
    """`cbh pair` without --time uses camera 1's file-name stamp (UTC) for the sun."""
    from cbh.actions.pair import process_pair
    from cbh.presets import station_path
    from cbh.sim import SkySimulator, parse_scene
    from cbh.geometry.station import load_station
    import cv2

    sim = SkySimulator(load_station(station_path("unb-lea")),
                       parse_scene({"name": "t", "time_utc": "2024-06-21T14:00:00Z",
                                    "layers": [{"height_m": 1500.0, "coverage": 0.4, "seed": 3}]}), size_px=160)
    shot = sim.render()
    (tmp_path / "station.toml").write_text(sim.station.to_toml())
    for cam in ("cam1", "cam2"):
        cv2.imwrite(str(tmp_path / f"{cam}_20240621T140000.png"), shot.views[cam].image)
    run = process_pair([tmp_path / "cam1_20240621T140000.png", tmp_path / "cam2_20240621T140000.png"],
                       tmp_path / "station.toml")
    assert run.result.time_utc == datetime(2024, 6, 21, 14, 0, tzinfo=timezone.utc)
    assert "time_unknown" not in run.result.flags
