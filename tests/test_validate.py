"""Ceilometer readers on every real sample, the statistics, and `cbh validate` on a truth ceilometer."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
SAMPLES = REPO / ".." / "shared" / "data" / "ceilometer-samples"
FILES = sorted(p for p in SAMPLES.glob("*/*") if p.suffix in (".nc", ".dat")) if SAMPLES.is_dir() else []


@pytest.mark.skipif(not FILES, reason="real ceilometer samples not available")
@pytest.mark.parametrize("path", FILES, ids=lambda p: p.name)
def test_every_real_sample_reads(path):
    from cbh.outputs.ceilometer import read_ceilometer

    c = read_ceilometer(path)
    assert c.bases_m.shape == (c.time_utc.size, 3)
    assert c.time_utc.size + c.skipped >= 1
    if "sgpceil" in path.name:  # README: overcast low stratus all day, hourly median first base 430-810 m
        assert c.time_utc.size == 5401
        assert 430.0 <= np.nanmedian(c.bases_m[:, 0]) <= 810.0


def test_statistics_known_offsets():
    from cbh.actions.validate import statistics

    b = np.linspace(500.0, 5000.0, 100)
    s = statistics(b + 100.0, b)
    assert s["mae_m"] == pytest.approx(100.0) and s["bias_m"] == pytest.approx(100.0)
    assert s["within_150m"] == 1.0 and 0.99 < s["r2"] < 1.0
    s = statistics(b + np.where(np.arange(100) % 2, 200.0, -200.0), b)
    assert s["bias_m"] == pytest.approx(0.0, abs=1e-9) and s["rmse_m"] == pytest.approx(200.0)
    assert s["within_150m"] == 0.0


def test_product_round_trip(tmp_path):
    from datetime import datetime, timedelta, timezone

    from cbh.outputs.ceilometer import read_ceilometer, write_product
    from cbh.outputs.export import PairRecord

    t0 = datetime(2024, 1, 1, tzinfo=timezone.utc)
    recs = [PairRecord(t0 + timedelta(seconds=10 * i), [1000.0 + i, 4000.0][: 1 + i % 2], [0, 0][: 1 + i % 2],
                       [0, 0][: 1 + i % 2], [0, 0][: 1 + i % 2], [0.6, 0.3][: 1 + i % 2], [1, 1][: 1 + i % 2],
                       [1, 1][: 1 + i % 2], 0.7) for i in range(4)]
    info = {"station": "s", "latitude_deg": 1.0, "longitude_deg": 2.0, "altitude_m": 3.0,
            "metadata": {"wigos_station_id": "0-20000-0-12345"}}
    import netCDF4

    for product, var in (("cl61", "cloud_base_heights"), ("eprofile", "cloud_base_height")):
        out = tmp_path / f"{product}.nc"
        write_product(recs, info, out, product)
        c = read_ceilometer(out)
        assert np.allclose(c.bases_m[:, 0], [1000, 1001, 1002, 1003])
        assert np.isnan(c.bases_m[0, 1]) and c.bases_m[1, 1] == 4000.0
        with netCDF4.Dataset(out) as nc:
            nc.set_auto_mask(False)
            if product == "cl61":
                assert nc["cloud_base_heights"][0, 1] == -99.0 and nc["vertical_visibility"][0] == -99.0
                assert list(nc["sky_condition_cloud_layer_covers"][1]) == [5, 2]
                assert nc["sky_condition_total_cloud_cover"][0] == 6
            else:
                assert nc.wigos_station_id == "0-20000-0-12345" and float(nc["station_altitude"][...]) == 3.0


def test_bad_ceilometer_file_is_one_line_error(tmp_path):
    bad = tmp_path / "x.dat"
    bad.write_text("not a ceilometer\n")
    r = subprocess.run([sys.executable, "-m", "cbh.cli.main", "validate", "--ceilometer", str(bad),
                        str(REPO / "recordings" / "sample-two-layers.mcap")], capture_output=True, text=True, cwd=REPO)
    assert r.returncode == 2 and r.stderr.startswith("cbh: error:") and "Traceback" not in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1


@pytest.mark.slow
def test_validate_on_truth_ceilometer(tmp_path):
    """The simulator's truth above camera 1 as a CL61 file: cbh's column within 1 % (MAE) of it."""
    import json

    rec = REPO / "recordings" / "sample-two-layers.mcap"
    truth = tmp_path / "truth.nc"
    subprocess.run([sys.executable, "scripts/make_truth_ceilometer.py", str(rec),
                    "configs/scenes/two-layers.toml", str(truth)], check=True, cwd=REPO)
    out = tmp_path / "v.json"
    subprocess.run([sys.executable, "-m", "cbh.cli.main", "validate", "--ceilometer", str(truth), str(rec),
                    "--out", str(out), "--match-s", "5"], check=True, cwd=REPO)
    rep = json.loads(out.read_text())
    s = rep["all"]
    assert s["n"] >= 3
    assert s["mae_m"] <= 0.01 * 1200.0
    assert (tmp_path / "v-scatter.png").is_file() and (tmp_path / "v-timeseries.png").is_file()
