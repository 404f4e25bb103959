"""`cbh triangulate`: the paper's drone validation, repeated in simulation, and its input errors."""
from __future__ import annotations

import json

import numpy as np
import pytest

from cbh.cli.main import main

from .conftest import REPO

STATION = str(REPO / "configs" / "unb-lea.toml")


def drone_pixels(station, noise_px=0.5, seed=0):
    """The paper's experiment (Figure 7): drone at 90–490 m in five sectors around the cameras.

    Sectors 1–4 lie to the NE, SE, SW and NW at a horizontal distance of 0.6× the height;
    sector 5 is above the middle of the baseline (paper: the most accurate one).
    """
    rng = np.random.default_rng(seed)
    cam1, cam2 = station.pair()
    rows = []
    mid = 0.5 * (cam1.position_m + cam2.position_m)
    for h in (90.0, 190.0, 290.0, 390.0, 490.0):
        for az in (45.0, 135.0, 225.0, 315.0, None):
            dist = 0.0 if az is None else 0.6 * h
            a = np.radians(az or 0.0)
            p = mid + [dist * np.sin(a), dist * np.cos(a), 0.0]
            p[2] = h
            px1 = cam1.world_to_pixel(p)[0] + rng.normal(0, noise_px, 2)
            px2 = cam2.world_to_pixel(p)[0] + rng.normal(0, noise_px, 2)
            rows.append((*px1, *px2, h))
    return np.array(rows)


def write_csv(path, rows, header="x1,y1,x2,y2,true_height_m"):
    path.write_text(header + "\n" + "\n".join(",".join(f"{v:.4f}" for v in r) for r in rows) + "\n")
    return path


def test_drone_experiment_mape_below_one_percent(tmp_path, capsys, unb_station):
    # 0.5 px at the zenith is 0.5/630 rad; with a 50 m baseline the height error at 490 m is
    # about h²/B·σ·√2 ≈ 5 m (1 %), and much less lower down: the MAPE over 90–490 m stays < 1 %.
    rows = np.vstack([drone_pixels(unb_station, seed=s) for s in range(4)])
    csv = write_csv(tmp_path / "drone.csv", rows)
    assert main(["triangulate", "--station", STATION, "--pixels", str(csv), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert len(out["points"]) == len(rows)
    assert all(p["valid"] for p in out["points"])
    m = out["metrics"]
    assert m["n"] == len(rows)
    assert 0.05 < m["mape_pct"] < 1.0  # noise was injected: not zero, but below the bar
    # and the noise-free rays meet: miss distance only from the injected noise
    assert np.median([p["miss_m"] for p in out["points"]]) < 1.0


def test_noise_free_drone_is_exact(tmp_path, capsys, unb_station):
    rows = drone_pixels(unb_station, noise_px=0.0)
    csv = write_csv(tmp_path / "drone.csv", rows)
    assert main(["triangulate", "--station", STATION, "--pixels", str(csv), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    h = np.array([p["height_m"] for p in out["points"]])
    # the CSV keeps 4 decimals of a pixel (5e-5 px ≈ 5e-4 m at 490 m with a 50 m baseline)
    np.testing.assert_allclose(h, rows[:, 4], rtol=1e-5)
    assert out["metrics"]["mape_pct"] < 1e-3


def test_table_output_and_metrics_line(tmp_path, capsys, unb_station):
    rows = drone_pixels(unb_station, noise_px=0.0)[:3]
    csv = write_csv(tmp_path / "d.csv", rows)
    assert main(["triangulate", "--station", STATION, "--pixels", str(csv)]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert lines[0].split() == ["height_m", "east_m", "north_m", "up_m", "miss_m", "valid"]
    assert len(lines) == 1 + 3 + 1 and lines[-1].startswith("n=3")
    assert float(lines[1].split()[0]) == pytest.approx(90.0, abs=0.01)


def test_without_truth_no_metrics(tmp_path, capsys, unb_station):
    rows = drone_pixels(unb_station, noise_px=0.0)[:2, :4]
    csv = write_csv(tmp_path / "d.csv", rows, header="x1,y1,x2,y2")
    assert main(["triangulate", "--station", STATION, "--pixels", str(csv), "--json", "--cameras", "cam1,cam2"]) == 0
    assert json.loads(capsys.readouterr().out)["metrics"] == {}


@pytest.mark.parametrize("text, match", [
    ("x1,y1,x2\n1,2,3\n", "missing column 'y2'"),
    ("x1,y1,x2,y2\n960,960,960,960\n960,abc,960,960\n", "row 3, column y1: not a number"),
    ("x1,y1,x2,y2\n960,960,960,960\n3,3,960,960\n", "row 3: pixel .* outside camera 'cam1'"),
    ("x1,y1,x2,y2\n", "no data rows"),
])
def test_bad_pixels_file(tmp_path, capsys, text, match):
    import re

    csv = tmp_path / "bad.csv"
    csv.write_text(text)
    assert main(["triangulate", "--station", STATION, "--pixels", str(csv)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("cbh: error:") and re.search(match, err) and "\n" not in err


def test_missing_files_exit_2(tmp_path, capsys):
    assert main(["triangulate", "--station", str(tmp_path / "none.toml"), "--pixels", "x.csv"]) == 2
    assert "station file not found" in capsys.readouterr().err
    assert main(["triangulate", "--station", STATION, "--pixels", str(tmp_path / "none.csv")]) == 2
    assert "pixels file not found" in capsys.readouterr().err
    assert main(["triangulate", "--station", STATION, "--pixels", "x.csv", "--cameras", "cam1,camX"]) == 2
    assert "camX" in capsys.readouterr().err


def test_version_flag(capsys):
    import cbh

    assert main(["--version"]) == 0
    assert capsys.readouterr().out.strip() == f"cbh {cbh.__version__}"
