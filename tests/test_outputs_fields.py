"""Every output carries the same facts: fixed flag bits, altitude, layer motion, diagnostics,
okta and ceiling; files read back with the real readers (MCAP reader, pandas, netCDF4/xarray)."""
from __future__ import annotations

import json
import math
import shutil
import subprocess
from dataclasses import replace
from datetime import timedelta

import numpy as np
import pytest

from tests.test_record import small_station, synthetic_pair

MOTION = [(6.25, 2.0), (-3.0, 8.5)]  # (east, north) [m/s] of layer 1 and 2


@pytest.fixture(scope="module")
def station():
    return small_station()


def _results(station):
    """Four pairs: motion on the first, diagnostics appearing from the second, an invalidating
    flag on the third, a clear sky on the fourth."""
    from cbh.result import PointSet

    out = []
    for k in range(4):
        frames, res = synthetic_pair(station, k)
        layers = [replace(l, motion_east_ms=MOTION[i][0], motion_north_ms=MOTION[i][1]) if k == 0 else l
                  for i, l in enumerate(res.layers)]
        diag = {} if k == 0 else {"clock_offset_s": 3.04 + k, "sun_residual_deg": 0.5}
        flags = list(res.flags) + (["geometry_mismatch"] if k == 2 else [])
        res = replace(res, layers=layers, diagnostics=diag, flags=flags)
        if k == 3:
            res = replace(res, layers=[], points=PointSet.empty(), flags=["clear_sky"])
        out.append((frames, res))
    return out


@pytest.fixture(scope="module")
def recorded(tmp_path_factory, station):
    from cbh.outputs.record import McapRecorder

    path = tmp_path_factory.mktemp("f") / "s.mcap"
    made = _results(station)
    with McapRecorder(path, station, {}) as rec:
        for frames, res in made:
            rec.write(frames, res)
    return path, [r for _, r in made]


def test_mcap_round_trip_of_motion_diagnostics_and_flag_bits(recorded):
    from mcap.reader import make_reader

    from cbh.flags import flag_bits
    from cbh.outputs.record import open_session
    from cbh.outputs.record.schemas import cbh_types

    path, made = recorded
    got = [p.result for p in open_session(path).pairs()]
    assert len(got) == len(made)
    for g, r in zip(got, made):
        assert g.diagnostics == r.diagnostics and g.flags == r.flags
        for a, b in zip(g.layers, r.layers):
            for name in ("motion_east_ms", "motion_north_ms"):
                va, vb = getattr(a, name), getattr(b, name)
                assert va == vb or (math.isnan(va) and math.isnan(vb))  # unknown stays unknown, not 0
    # the raw message carries the fixed bits beside the names
    with open(path, "rb") as fh:
        raw = [cbh_types()["PairLayers"].FromString(m.data)
               for _s, _c, m in make_reader(fh).iter_messages(topics=["/pair/layers"])]
    assert [m.flag_bits for m in raw] == [flag_bits(r.flags) for r in made]


@pytest.mark.parametrize("fmt", ["csv", "parquet"])
def test_table_columns_motion_flags_diagnostics_okta_ceiling(tmp_path, recorded, station, fmt):
    import pandas as pd

    from cbh.flags import Flag
    from cbh.outputs.export import COLUMNS, export_sessions

    path, made = recorded
    out = tmp_path / f"t.{fmt}"
    export_sessions([path], fmt, out)
    df = pd.read_csv(out) if fmt == "csv" else pd.read_parquet(out)
    assert list(df.columns) == list(COLUMNS) + ["clock_offset_s", "sun_residual_deg"]
    first = df[df.time_utc == df.time_utc.iloc[0]]
    assert list(first.layer) == [1]  # layers from 1
    assert first.motion_east_ms.iloc[0] == MOTION[0][0] and first.motion_north_ms.iloc[0] == MOTION[0][1]
    assert math.isnan(first.clock_offset_s.iloc[0])  # the first pair has no diagnostics
    assert list(df.clock_offset_s.dropna().unique()) == pytest.approx([4.04, 5.04, 6.04])
    # a pair with an invalidating flag keeps its rows, flagged with the fixed bit
    bad = df[df["flags"].str.contains("geometry_mismatch", na=False)]
    assert len(bad) == len(made[2].layers) and (bad.quality_flag & int(Flag.geometry_mismatch)).all()
    clear = df[df.layer == 0]
    assert len(clear) == 1 and clear.quality_flag.iloc[0] == int(Flag.clear_sky) and clear.total_okta.iloc[0] >= 0
    # okta per layer: cover 0.3 → round(2.4) = 2; cover 0.15 → 1
    assert list(df[df.layer == 1].cover_okta) == [2, 2, 2] and list(df[df.layer == 2].cover_okta) == [1]
    assert df.ceiling_m.isna().all()  # 0.3 + 0.15 = 3.6 okta: nothing broken, no ceiling


def test_csv_numbers_are_rounded_by_the_stated_rule(tmp_path, recorded):
    import csv

    from cbh.outputs.export import export_sessions

    path, _ = recorded
    out = tmp_path / "t.csv"
    export_sessions([path], "csv", out)
    with open(out, newline="") as fh:
        rows = list(csv.DictReader(fh))
    for r in rows:
        for k in ("cloud_base_height_m", "cloud_base_altitude_m", "median_height_m", "spread_m"):
            assert r[k] == "" or len(r[k].split(".")[1]) == 1, (k, r[k])  # 0.1 m
        for k in ("cover", "confidence", "cloud_fraction"):
            assert r[k] == "" or len(r[k].split(".")[1]) == 3, (k, r[k])
        assert r["motion_east_ms"] == "" or len(r["motion_east_ms"].split(".")[1]) == 2
    assert rows[0]["motion_east_ms"] == "6.25" and rows[0]["layer"] == "1"


def test_live_csv_widens_its_header_when_a_diagnostic_appears(tmp_path, station):
    import pandas as pd

    from cbh.outputs.export import COLUMNS, LayerExporter

    out = tmp_path / "live.csv"
    with LayerExporter(out, station) as exp:
        for frames, res in _results(station):
            exp.write(frames, res)
            df = pd.read_csv(out)  # readable after every pair
    assert list(df.columns) == list(COLUMNS) + ["clock_offset_s", "sun_residual_deg"]
    assert df.clock_offset_s.isna().sum() == 1 and len(df) == 1 + 2 + 1 + 1
    with LayerExporter(out, station) as again:  # appends with the wider header
        again.write(*_results(station)[1])
    assert len(pd.read_csv(out)) == 5 + 2


def test_okta_and_ceiling_rules():
    from cbh.outputs.export import ceiling_index, okta

    assert [okta(c) for c in (0.0, 0.01, 0.0625, 0.5, 0.94, 0.99, 1.0, math.nan)] == [0, 1, 1, 4, 7, 7, 8, -1]
    assert ceiling_index([0.2, 0.5, 0.3]) == 1  # 0.7 → 6 okta at layer 2 (summation principle)
    assert ceiling_index([0.7]) == 0 and ceiling_index([0.2, 0.2]) is None


def test_netcdf_has_motion_okta_ceiling_diagnostics_and_station_variables(tmp_path, recorded, station):
    import netCDF4

    from cbh.flags import Flag
    from cbh.outputs.export import export_sessions

    path, made = recorded
    out = tmp_path / "l.nc"
    export_sessions([path], "netcdf", out)
    with netCDF4.Dataset(out) as nc:
        v = nc.variables
        assert v["cloud_motion_east"].units == "m s-1" and v["cloud_motion_east"].dimensions == ("time", "layer")
        assert v["cloud_motion_east"][0, 0] == MOTION[0][0] and v["cloud_motion_north"][0, 0] == MOTION[0][1]
        assert np.ma.is_masked(v["cloud_motion_east"][1, 0])  # unknown → fill
        assert v["cloud_motion_direction"][0, 0] == pytest.approx(math.degrees(math.atan2(6.25, 2.0)))
        assert v["clock_offset_s"].units == "s" and v["sun_residual_deg"].units == "degree"
        assert np.ma.is_masked(v["clock_offset_s"][0]) and v["clock_offset_s"][1] == pytest.approx(4.04)
        assert list(v["layer"][:]) == [1, 2, 3]
        assert float(v["station_latitude"][...]) == station.latitude_deg and v["station_altitude"].positive == "up"
        assert v["quality_flag"][2] & int(Flag.geometry_mismatch)
        assert v["cloud_layer_okta"][0, 0] == 2 and np.ma.is_masked(v["cloud_layer_okta"][0, 1])  # 1 layer
        assert v["total_cloud_okta"].dimensions == ("time",) and v["ceiling_height"].units == "m"


def _checker():
    exe = shutil.which("compliance-checker")
    if exe is None:
        pytest.skip("compliance-checker is not installed (python3.11 -m pip install compliance-checker)")
    return exe


def _cf_errors(exe, path, tmp_path) -> list:
    report = tmp_path / (path.name + ".json")
    subprocess.run([exe, "--test=cf:1.8", "-f", "json", "-o", str(report), str(path)], capture_output=True,
                   timeout=300)
    res = json.loads(report.read_text())["cf:1.8"]
    return [(p["name"], p["msgs"]) for p in res["high_priorities"] if p["msgs"]]


@pytest.mark.slow
def test_netcdf_exports_pass_the_cf_18_compliance_checker(tmp_path, recorded, moving):
    """IOOS compliance checker, CF-1.8: 0 errors for the layer file and both ground-map files."""
    from cbh.actions.export import export

    exe = _checker()
    path, _ = recorded
    layers = tmp_path / "layers.nc"
    export([path], layers)
    assert _cf_errors(exe, layers, tmp_path) == []
    for product in ("shadow", "cloudmap"):
        grids = tmp_path / f"{product}.nc"
        export([moving[0]], grids, product=product)
        assert _cf_errors(exe, grids, tmp_path) == []


def _write(path, station, results):
    from cbh.outputs.record import McapRecorder

    with McapRecorder(path, station, {}) as rec:
        for frames, res in results:
            rec.write(frames, res)


def test_daily_files_split_at_utc_midnight(tmp_path, station):
    import pandas as pd

    from cbh.cli.main import main

    base = synthetic_pair(station, 0)[1].time_utc.replace(hour=23, minute=59, second=40)
    made = []
    for k in range(4):  # 23:59:40, 23:59:50, 00:00:00, 00:00:10
        frames, res = synthetic_pair(station, k)
        made.append((frames, replace(res, time_utc=base + timedelta(seconds=10 * k))))
    _write(tmp_path / "a.mcap", station, made[:3])
    _write(tmp_path / "b.mcap", station, made[3:])
    out = tmp_path / "daily"
    assert main(["export", str(tmp_path / "a.mcap"), str(tmp_path / "b.mcap"), "--daily", "--format", "csv",
                 "--out", str(out)]) == 0
    files = sorted(p.name for p in out.iterdir())
    d0 = base.strftime("%Y%m%d")
    d1 = (base + timedelta(days=1)).strftime("%Y%m%d")
    assert files == [f"cbh_unb-lea_{d0}.csv", f"cbh_unb-lea_{d1}.csv"]
    day0 = pd.read_csv(out / files[0])
    assert pd.to_datetime(day0.time_utc).dt.day.nunique() == 1 and day0.time_utc.nunique() == 2
    assert main(["export", str(tmp_path / "a.mcap"), "--daily", "--out", str(out)]) == 0  # NetCDF by default
    assert len(list(out.glob("*.nc"))) == 2


@pytest.fixture(scope="module")
def moving(tmp_path_factory, station):
    """Three pairs 10 s apart, every layer with motion MOTION, on a coarse ground grid."""
    d = tmp_path_factory.mktemp("mv")
    st = replace(station, sections={"ground": {"resolution_m": 200.0, "extent_m": 3000.0}})
    made = []
    for k in range(3):
        frames, res = synthetic_pair(station, k)
        res = replace(res, layers=[replace(l, motion_east_ms=MOTION[i][0], motion_north_ms=MOTION[i][1])
                                   for i, l in enumerate(res.layers)])
        made.append((frames, res))
    _write(d / "m.mcap", st, made)
    return d / "m.mcap", [r for _, r in made]


def test_map_exports_read_back_as_cf_grids_and_pysteps_arrays(tmp_path, moving):
    import xarray as xr

    from cbh.cli.main import main

    path, made = moving
    nc = tmp_path / "cloud.nc"
    assert main(["export", str(path), "--product", "cloudmap", "--out", str(nc)]) == 0
    with xr.open_dataset(nc) as ds:
        assert ds.cloud_map.dims == ("time", "y", "x") and ds.cloud_map.shape == (3, 31, 31)
        assert ds.layer_cloud_map.dims == ("time", "layer", "y", "x")
        assert ds.x.attrs["units"] == "m" and ds.lat.dims == ("y", "x")
        assert ds.sun_blocked.dims == ("time", "lead_time") and list(ds.lead_time.values) == [0, 60, 300, 600]
        cm = ds.cloud_map.values
        assert np.nanmax(cm) == 1 and np.nanmin(cm) == 0  # the recorded mask has cloud and clear sky
        np.testing.assert_allclose(ds.layer_height.values[0, :1], [made[0].layers[0].height_m])
    npz = tmp_path / "shadow.npz"
    assert main(["export", str(path), "--product", "shadow", "--format", "npz", "--out", str(npz)]) == 0
    with np.load(npz) as z:
        meta = json.loads(str(z["metadata"]))
        assert z["field"].shape == (3, 31, 31) and z["motion"].shape == (2, 31, 31)
        assert meta["yorigin"] == "lower" and meta["xpixelsize"] == 200.0 and meta["motion_known"]
        assert float(z["timestep_s"]) == 10.0
        # last pair has one layer (k=2): every cell moves with it, in cells per 10 s step
        np.testing.assert_allclose(z["motion"][0], MOTION[0][0] * 10.0 / 200.0, rtol=1e-6)
        np.testing.assert_allclose(z["motion"][1], MOTION[0][1] * 10.0 / 200.0, rtol=1e-6)
    assert main(["export", str(path), "--product", "rain", "--out", str(tmp_path / "x.nc")]) == 2
    assert main(["export", str(path), "--product", "shadow", "--format", "csv", "--out", str(tmp_path / "x.csv")]) == 2


def test_motion_quality_goes_through_mcap_and_tables(tmp_path, station):
    import pandas as pd

    from cbh.outputs.export import export_sessions
    from cbh.outputs.record import open_session
    frames, res = synthetic_pair(station, 1)
    res = replace(res, layers=[replace(l, motion_east_ms=4.0, motion_north_ms=1.0, motion_spread_ms=0.25 * (i + 1),
                                       motion_tracks=40 + i) for i, l in enumerate(res.layers)])
    _write(tmp_path / "q.mcap", station, [(frames, res)])
    got = next(open_session(tmp_path / "q.mcap").pairs(layers_only=True)).result.layers
    assert [(l.motion_spread_ms, l.motion_tracks) for l in got] == [(0.25, 40), (0.5, 41)]
    export_sessions([tmp_path / "q.mcap"], "parquet", tmp_path / "q.parquet")
    df = pd.read_parquet(tmp_path / "q.parquet")
    assert list(df.motion_spread_ms) == [0.25, 0.5] and list(df.motion_tracks) == [40, 41]


def test_a_layers_band_goes_through_mcap_and_tables(tmp_path, station):
    """``height_lo_m`` / ``height_hi_m`` (the heights a layer stands for) read back from MCAP and
    reach the tables; a band unknown (NaN) stays unknown (absent, empty), never 0 m."""
    import pandas as pd

    from cbh.outputs.export import export_sessions
    from cbh.outputs.record import open_session
    frames, res = synthetic_pair(station, 1)
    bands = [(2052.0, 15141.0), (math.nan, math.nan)]
    res = replace(res, layers=[replace(l, height_lo_m=b[0], height_hi_m=b[1]) for l, b in zip(res.layers, bands)])
    _write(tmp_path / "b.mcap", station, [(frames, res)])
    got = next(open_session(tmp_path / "b.mcap").pairs(layers_only=True)).result.layers
    assert (got[0].height_lo_m, got[0].height_hi_m) == (2052.0, 15141.0)
    assert math.isnan(got[1].height_lo_m) and math.isnan(got[1].height_hi_m)
    export_sessions([tmp_path / "b.mcap"], "parquet", tmp_path / "b.parquet")
    df = pd.read_parquet(tmp_path / "b.parquet")
    assert list(df.height_lo_m)[0] == 2052.0 and df.height_hi_m.isna().tolist() == [False, True]
    assert got[0].to_dict()["height_hi_m"] == 15141.0 and got[1].to_dict()["height_lo_m"] is None


def test_npz_drives_pysteps_extrapolation(tmp_path, moving):
    """The NPZ is what pysteps takes: its semi-Lagrangian extrapolation moves the field by the
    exported motion (east = columns, north = rows, cells per time step)."""
    pytest.importorskip("pysteps", reason="pysteps is not installed (python3.11 -m pip install pysteps)")
    from scipy import ndimage
    from pysteps.extrapolation.semilagrangian import extrapolate

    from cbh.actions.export import export

    path, _ = moving
    out = tmp_path / "c.npz"
    export([path], out, product="cloudmap")
    with np.load(out) as z:
        field = np.nan_to_num(z["field"][-1].astype(np.float64))
        motion = z["motion"].astype(np.float64)
    steps = 16  # 16 steps x (0.3125, 0.1) cells = (5, 1.6) cells
    moved = extrapolate(field, motion, steps)[-1]
    want = steps * np.array([motion[1, 0, 0], motion[0, 0, 0]])  # (rows, columns)
    # the same field translated by the motion (linear interpolation), NaN where it left the grid
    expected = ndimage.shift(field, want, order=1, mode="constant", cval=np.nan)
    both = np.isfinite(moved) & np.isfinite(expected)
    assert both.mean() > 0.7 and field.sum() > 20  # 26 x 29 of 31 x 31 cells stay on the grid
    assert np.abs(moved[both] - expected[both]).max() < 0.05


def test_map_grid_from_a_given_station_file(tmp_path, moving, repo):
    import xarray as xr

    from cbh.cli.main import main

    path, _ = moving
    st = tmp_path / "station.toml"
    st.write_text((repo / "configs" / "unb-lea.toml").read_text() + "\n[ground]\nresolution_m = 500.0\nextent_m = 2000.0\n")
    out = tmp_path / "s.nc"
    assert main(["export", str(path), "--product", "shadow", "--station", str(st), "--out", str(out)]) == 0
    with xr.open_dataset(out) as ds:
        assert ds.shadow_map.shape == (3, 9, 9) and float(ds.x[-1]) == 2000.0
    st.write_text((repo / "configs" / "unb-lea.toml").read_text() + "\n[ground]\nresolution = 500.0\n")
    assert main(["export", str(path), "--product", "shadow", "--station", str(st), "--out", str(out)]) == 2
