"""`cbh pair` in-process: JSON object, height map file, one-line errors with exit code 2."""
import json

import cv2
import numpy as np
import pytest

from cbh.cli.main import main


@pytest.fixture(scope="module")
def sim_pair(tmp_path_factory):
    from cbh.presets import station_path
    from cbh.sim import SkySimulator, parse_scene
    from cbh.geometry.station import load_station

    d = tmp_path_factory.mktemp("pair")
    scene = parse_scene({"name": "t", "time_utc": "2024-06-21T14:00:00Z",
                         "layers": [{"height_m": 1500.0, "coverage": 0.4, "texture_scale_m": 800.0, "seed": 3}]})
    sim = SkySimulator(load_station(station_path("unb-lea")), scene, size_px=480)
    shot = sim.render()
    (d / "station.toml").write_text(sim.station.to_toml())
    for cam in ("cam1", "cam2"):
        cv2.imwrite(str(d / f"{cam}_20240621T140000Z.png"), shot.views[cam].image)
    return d


def test_json_summary_and_height_map(sim_pair, tmp_path, capsys):
    d = sim_pair
    out = tmp_path / "h.npy"
    rc = main(["pair", str(d / "cam1_20240621T140000Z.png"), str(d / "cam2_20240621T140000Z.png"),
               "--station", str(d / "station.toml"), "--json", "--height-map", str(out)])
    assert rc == 0
    s = json.loads(capsys.readouterr().out)
    assert s["time_utc"] == "2024-06-21T14:00:00Z"  # from the file name's UTC stamp
    assert set(s) >= {"layers", "points", "cloud_fraction", "timing_ms"}
    assert [l["height_m"] for l in s["layers"]] == sorted(l["height_m"] for l in s["layers"])
    assert len(s["layers"]) == 1 and abs(s["layers"][0]["median_height_m"] - 1500) < 0.05 * 1500
    assert set(s["cloud_fraction"]) == {"cam1", "cam2"}
    hm = np.load(out)
    assert hm.dtype == np.float32 and hm.shape == (480, 480)
    assert np.isfinite(hm).any() and np.isnan(hm).any()


def test_table_output(sim_pair, capsys):
    d = sim_pair
    rc = main(["pair", str(d / "cam1_20240621T140000Z.png"), str(d / "cam2_20240621T140000Z.png"),
               "--station", str(d / "station.toml"), "--time", "2024-06-21T14:00:00Z"])
    assert rc == 0
    out = capsys.readouterr().out
    assert "base_m" in out and "points:" in out


@pytest.mark.parametrize("case", ["missing", "corrupt", "size", "camera", "time"])
def test_errors_are_one_line_exit_2(sim_pair, tmp_path, capsys, case):
    d = sim_pair
    a, b = str(d / "cam1_20240621T140000Z.png"), str(d / "cam2_20240621T140000Z.png")
    args = ["pair", a, b, "--station", str(d / "station.toml")]
    if case == "missing":
        args[1] = str(tmp_path / "nope.jpg")
    elif case == "corrupt":
        bad = tmp_path / "bad.jpg"
        bad.write_bytes(b"not a jpeg")
        args[2] = str(bad)
    elif case == "size":
        small = tmp_path / "small.png"
        cv2.imwrite(str(small), np.zeros((100, 100, 3), np.uint8))
        args[1] = str(small)
    elif case == "camera":
        args += ["--cameras", "cam1,cam9"]
    elif case == "time":
        args += ["--time", "yesterday"]
    rc = main(args)
    err = capsys.readouterr().err
    assert rc == 2
    assert err.startswith("cbh: error:") and err.count("\n") == 1
    assert "Traceback" not in err


def test_height_map_never_writes_over_a_non_npy_file(sim_pair, tmp_path, capsys):
    """``--height-map SESSION.mcap`` (or an input image's name) replaced that file with the array:
    the recording was lost. Now a .npy name is required: one error line, exit 2, file untouched."""
    d = sim_pair
    rec = tmp_path / "session.mcap"
    rec.write_bytes(b"\x89MCAP0\r\n recorded data")
    a, b = str(d / "cam1_20240621T140000Z.png"), str(d / "cam2_20240621T140000Z.png")
    for target in (rec, d / "cam2_20240621T140000Z.png"):
        before = target.read_bytes()
        rc = main(["pair", a, b, "--station", str(d / "station.toml"), "--height-map", str(target)])
        err = capsys.readouterr().err
        assert rc == 2 and err.startswith("cbh: error:") and err.count("\n") == 1 and ".npy" in err, err
        assert target.read_bytes() == before
