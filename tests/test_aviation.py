"""METAR groups through ampycloud (reference cases: MeteoSwiss/ampycloud test/ampycloud/ref_data, copied in
../shared/data/ceilometer-samples/ampycloud-reference-hits, expected groups in each file name) and the
hit samplers on labels with known covers."""
from __future__ import annotations

import subprocess
import sys
from datetime import datetime, timedelta, timezone
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
REF = REPO / ".." / "shared" / "data" / "ceilometer-samples" / "ampycloud-reference-hits"
CASES = sorted(REF.glob("*.csv")) if REF.is_dir() else []
FAST = {"debug107_2020.01.01-00.01.01_SCT024-SCT031", "Geneva_2021.09.19-11.50.00_OVC032"}


def _case(path: Path):
    parts = path.stem.split("_")
    msa = int(parts[3][3:]) if len(parts) > 3 and parts[3].startswith("MSA") else None
    return parts[2].replace("-", " "), msa


def _run(path: Path) -> str:
    import pandas as pd

    from cbh.outputs.aviation import run_ampycloud

    d = pd.read_csv(path)
    d = d.astype({"ceilo": pd.StringDtype("python"), "dt": float, "height": float, "type": int})
    return run_ampycloud(d, _case(path)[1]).metar_msg()


@pytest.mark.skipif(len(CASES) != 17, reason="ampycloud reference hits not available")
@pytest.mark.parametrize("path", [p for p in CASES if p.stem in FAST], ids=lambda p: p.stem)
def test_reference_cases_fast(path):
    assert _run(path) == _case(path)[0]


@pytest.mark.slow
@pytest.mark.skipif(len(CASES) != 17, reason="ampycloud reference hits not available")
@pytest.mark.parametrize("path", CASES, ids=lambda p: p.stem)
def test_reference_cases_all(path):
    assert _run(path) == _case(path)[0]



def _camera(size=400):
    from cbh.geometry.station import parse_station

    st = parse_station({"station": {"name": "t", "latitude_deg": 0.0, "longitude_deg": 0.0, "altitude_m": 0.0},
                        "cameras": [{"name": "c1", "position_m": [0, 0, 0], "intrinsics": {
                            "model": "equidistant", "radius_px": size / 2, "center_xy": [size / 2, size / 2],
                            "width": size, "height": size}},
                                    {"name": "c2", "position_m": [100, 0, 0], "intrinsics": {
                            "model": "equidistant", "radius_px": size / 2, "center_xy": [size / 2, size / 2],
                            "width": size, "height": size}}]})
    return st.camera("c1")


def _labels(cam, cover_fn):
    """Labels of a single layer at 1000 m whose cloud is where cover_fn(x, y) (ENU, m) is True."""
    from cbh.geometry.ground import CLEAR, UNKNOWN

    H, W = cam.model.height, cam.model.width
    yy, xx = np.mgrid[0:H, 0:W]
    rays = cam.pixel_to_world(np.column_stack([xx.ravel() + 0.0, yy.ravel() + 0.0]))
    up = rays[:, 2] > 0.2
    t = np.where(up, 1000.0 / np.where(up, rays[:, 2], 1), np.nan)
    x, y = rays[:, 0] * t, rays[:, 1] * t
    lab = np.where(up, np.where(cover_fn(x, y), 0, CLEAR), UNKNOWN).astype(np.int16)
    return lab.reshape(H, W)


@pytest.mark.parametrize("method", ["virtual", "map"])
def test_samplers_overcast_and_clear(method):
    from cbh.outputs.aviation import get_hit_method

    cam = _camera()
    f = get_hit_method(method)
    over = f(cam, _labels(cam, lambda x, y: np.ones_like(x, bool)), np.full((400, 400), np.nan), [1000.0], n=50)
    assert (over.type == 1).all() and over.measurements == 50 and np.allclose(over.height_m, 1000.0)
    clear = f(cam, _labels(cam, lambda x, y: np.zeros_like(x, bool)), np.full((400, 400), np.nan), [], n=50)
    assert (clear.type == 0).all() and clear.measurements == 50


@pytest.mark.slow
def test_virtual_half_cover_and_metar():
    """Half the layer (east of the station) cloudy: about half the ceilometers hit; ampycloud gives
    SCT or BKN at 1000 m = 3280 ft -> 032 (floored to 100 ft)."""
    from cbh.outputs.aviation import hits_virtual, metar_report

    cam = _camera()
    lab = _labels(cam, lambda x, y: x > 0)
    ph = hits_virtual(cam, lab, np.full((400, 400), np.nan), [1000.0], n=128)
    frac = (ph.type == 1).sum() / ph.measurements
    assert 0.4 < frac < 0.6
    t0 = datetime(2024, 1, 1, tzinfo=timezone.utc)
    win = [(t0 + timedelta(seconds=60 * k), ph) for k in range(5)]
    r = metar_report(win[-1][0], win)
    assert len(r.groups) == 1 and r.groups[0].code[3:] == "032" and r.groups[0].code[:3] in ("SCT", "BKN")
    assert r.metar == r.groups[0].code


def test_unknown_method_lists_valid():
    from cbh.errors import ConfigError
    from cbh.outputs.aviation import get_hit_method

    with pytest.raises(ConfigError, match="valid: virtual, map"):
        get_hit_method("dense")


@pytest.mark.slow
def test_export_metar_cl61_eprofile_cli(tmp_path):
    import xarray as xr

    rec = REPO / "recordings" / "sample-two-layers.mcap"
    m = tmp_path / "m.csv"
    subprocess.run([sys.executable, "-m", "cbh.cli.main", "export", str(rec), "--product", "metar", "--out", str(m)],
                   check=True, cwd=REPO)
    rows = m.read_text().splitlines()
    assert rows[0].startswith("time_utc,metar,n_groups,okta_1,height_ft_1,code_1")
    last = rows[-1].split(",")
    assert last[1].split()[0][3:] in ("038", "039", "040")  # 1200 m = 3937 ft
    for product, var in (("cl61", "cloud_base_heights"), ("eprofile", "cloud_base_height")):
        out = tmp_path / f"{product}.nc"
        subprocess.run([sys.executable, "-m", "cbh.cli.main", "export", str(rec), "--product", product, "--out",
                        str(out)], check=True, cwd=REPO)
        with xr.open_dataset(out) as ds:
            h = ds[var].values
            assert np.nanmin(np.abs(h[:, 0] - 1200.0)) < 0.02 * 1200.0
            assert np.nanmin(np.abs(h[:, 1] - 3500.0)) < 0.02 * 3500.0
