"""Layer exports: live CSV/Parquet sink, session tables, CF NetCDF; exact round trips."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from cbh.errors import ConfigError, RecordingError
from .conftest import small_station, synthetic_pair, write_session

REPO = Path(__file__).resolve().parents[1]
SAMPLE = REPO / "recordings" / "sample-two-layers.mcap"


@pytest.fixture(scope="module")
def station():
    return small_station()


def _clear(res):
    """The same pair with no layer (clear sky)."""
    from dataclasses import replace

    from cbh.result import PointSet

    return replace(res, layers=[], points=PointSet.empty(), flags=["few_points"])


@pytest.mark.parametrize("suffix", [".csv", ".parquet"])
def test_live_exporter_round_trip_is_exact(tmp_path, station, suffix):
    import pandas as pd

    from cbh.outputs.export import COLUMNS, LayerExporter

    out = tmp_path / f"layers{suffix}"
    made = []
    with LayerExporter(out, station) as exp:
        for k in range(4):
            frames, res = synthetic_pair(station, k)
            if k == 3:
                res = _clear(res)
            exp.write(frames, res)
            made.append(res)
            if suffix == ".csv":  # rows are on disk as soon as write() returns
                assert len(pd.read_csv(out)) == sum(max(1, len(r.layers)) for r in made)
    df = pd.read_parquet(out) if suffix == ".parquet" else pd.read_csv(out, keep_default_na=True)
    assert list(df.columns) == list(COLUMNS)
    want = [(r.time_utc, i, l) for r in made for i, l in enumerate(r.layers)]
    got = df[df.layer >= 1]
    assert len(got) == len(want)
    # CSV: rounded to 0.1 m and 3 decimals (half a unit of the last digit); Parquet: exact float64
    tol_m, tol_frac = (0.05 + 1e-9, 5e-4 + 1e-12) if suffix == ".csv" else (0.0, 0.0)
    for (t, i, l), (_, row) in zip(want, got.iterrows()):
        assert pd.Timestamp(row.time_utc) == pd.Timestamp(t)
        assert row.layer == i + 1  # layers numbered from 1
        assert abs(row.cloud_base_height_m - l.height_m) <= tol_m
        assert abs(row.cloud_base_altitude_m - (l.height_m + station.altitude_m)) <= tol_m
        assert abs(row.cover - l.cover) <= tol_frac and row.points == l.points
        assert abs(row.confidence - l.confidence) <= tol_frac
    clear = df[df.layer == 0]
    assert len(clear) == 1 and math.isnan(clear.cloud_base_height_m.iloc[0]) and clear.n_layers.iloc[0] == 0
    assert clear["flags"].iloc[0] == "few_points"


def test_csv_appends_to_its_own_file_only(tmp_path, station):
    import pandas as pd

    from cbh.outputs.export import LayerExporter

    out = tmp_path / "l.csv"
    for k in range(2):
        with LayerExporter(out, station) as exp:
            exp.write(*synthetic_pair(station, k))
    assert len(pd.read_csv(out)) == 1 + 2  # pair 0: one layer, pair 1: two layers; one header
    other = tmp_path / "other.csv"
    other.write_text("a,b\n1,2\n")
    with pytest.raises(RecordingError, match="other columns"):
        LayerExporter(other, station)
    pq = tmp_path / "l.parquet"
    pq.write_bytes(b"x")
    with pytest.raises(RecordingError, match="not a readable Parquet file"):
        LayerExporter(pq, station)
    other.unlink()
    pd.DataFrame({"a": [1]}).to_parquet(tmp_path / "o.parquet")
    with pytest.raises(RecordingError, match="other columns"):
        LayerExporter(tmp_path / "o.parquet", station)
    with pytest.raises(ConfigError, match="unknown format"):
        LayerExporter(tmp_path / "l.txt", station)


@pytest.fixture(scope="module")
def two_sessions(tmp_path_factory, station):
    d = tmp_path_factory.mktemp("ex")
    _, made_a = write_session(d / "a.mcap", station, n=3)
    # second session continues 60 s later
    from cbh.outputs.record import McapRecorder

    rec = McapRecorder(d / "b.mcap", station, {})
    made_b = []
    for k in range(3, 5):
        frames, res = synthetic_pair(station, k, dt_s=30.0)
        rec.write(frames, res)
        made_b.append(res)
    rec.close()
    return d / "a.mcap", d / "b.mcap", [r for _, r in made_a] + made_b


@pytest.mark.parametrize("fmt", ["csv", "parquet", "netcdf"])
def test_export_of_sessions_gives_exactly_the_recorded_heights(tmp_path, two_sessions, fmt, station):
    import pandas as pd
    import xarray as xr

    from cbh.outputs.export import export_sessions

    a, b, made = two_sessions
    out = tmp_path / {"csv": "x.csv", "parquet": "x.parquet", "netcdf": "x.nc"}[fmt]
    rows, steps = export_sessions([b, a], fmt, out)  # given out of order: sorted by time
    assert steps == len(made) and rows == sum(len(r.layers) for r in made)
    made = sorted(made, key=lambda r: r.time_utc)
    if fmt == "netcdf":
        with xr.open_dataset(out) as ds:
            h = ds.cloud_base_height.values
            for i, r in enumerate(made):
                assert pd.Timestamp(ds.time.values[i]).tz_localize("UTC") == pd.Timestamp(r.time_utc)
                assert list(h[i, : len(r.layers)]) == [l.height_m for l in r.layers]
                assert np.isnan(h[i, len(r.layers):]).all()
        return
    df = pd.read_csv(out) if fmt == "csv" else pd.read_parquet(out)
    tol = 0.05 + 1e-9 if fmt == "csv" else 0.0  # CSV heights to 0.1 m; Parquet exact
    np.testing.assert_allclose(df.cloud_base_height_m, [l.height_m for r in made for l in r.layers], rtol=0, atol=tol)
    np.testing.assert_allclose(df.cloud_base_altitude_m, [l.height_m + station.altitude_m for r in made for l in r.layers],
                               rtol=0, atol=tol)


def test_netcdf_is_cf_with_expected_variables_units_and_fill_values(tmp_path, two_sessions, station):
    import netCDF4
    import xarray as xr

    from cbh.outputs.export import FILL_VALUE, export_sessions

    a, b, made = two_sessions
    out = tmp_path / "cbh.nc"
    export_sessions([a, b], "netcdf", out)
    with netCDF4.Dataset(out) as nc:  # raw file: fill values and CF time as written
        assert nc.Conventions == "CF-1.8"
        assert dict(nc.dimensions)["time"].size == 5 and dict(nc.dimensions)["layer"].size == 3
        v = nc.variables["cloud_base_height"]
        assert v.dimensions == ("time", "layer") and v.units == "m" and v._FillValue == FILL_VALUE
        raw = v[:].filled(np.nan) if np.ma.isMaskedArray(v[:]) else v[:]
        assert "standard_name" not in nc.variables["cloud_base_altitude"].ncattrs()  # CF: lowest cloud only
        assert nc.variables["lowest_cloud_base_altitude"].standard_name == "cloud_base_altitude"
        assert nc.variables["time"].units.startswith("seconds since 1970-01-01")  # CF time, UTC epoch
        assert nc.variables["time"].dtype == np.float64
        assert nc.variables["time"].calendar == "standard"
        assert nc.variables["cloud_fraction"].standard_name == "cloud_area_fraction"
        qf = nc.variables["quality_flag"]
        from cbh.flags import Flag

        assert qf.flag_meanings.split() == [f.name for f in Flag]  # the whole enumeration, fixed bits
        assert list(qf.flag_masks) == [int(f) for f in Flag]
        v.set_auto_mask(False)
        assert (v[:][:, 2] == FILL_VALUE).all()  # nobody has a third layer: stored as the fill value
    with xr.open_dataset(out) as ds:
        for name in ("cloud_base_height", "cloud_base_altitude", "cloud_layer_cover", "cloud_fraction", "quality_flag",
                     "n_layers", "station_latitude", "station_longitude", "station_altitude",
                     "cloud_motion_east", "cloud_motion_north", "cloud_layer_okta", "total_cloud_okta",
                     "ceiling_height"):
            assert name in ds, name
        assert float(ds.station_latitude) == station.latitude_deg
        assert float(ds.station_altitude) == station.altitude_m and ds.station_altitude.attrs["positive"] == "up"
        assert ds.cloud_base_altitude.attrs["units"] == "m"
        assert ds.cloud_base_height.encoding["_FillValue"] == FILL_VALUE
        np.testing.assert_array_equal(ds.cloud_base_altitude.values - ds.cloud_base_height.values,
                                      np.where(np.isnan(raw), np.nan, station.altitude_m))
        assert list(ds.n_layers.values) == [len(r.layers) for r in made]
        # pair 2 (k=2) carries the few_points flag → its fixed bit
        assert list(ds.quality_flag.values) == [int(Flag.few_points) if r.flags else 0 for r in made]
        assert ds.time.dt.year.values[0] == 2024


def test_export_cli_and_errors(tmp_path, two_sessions, capsys):
    from cbh.cli.main import main

    a, b, _ = two_sessions
    assert main(["export", str(a), str(b), "--out", str(tmp_path / "o.nc")]) == 0
    assert "5 time steps" in capsys.readouterr().out
    assert main(["export", str(a), "--format", "csv", "--out", str(tmp_path / "o.txt")]) == 0
    capsys.readouterr()
    assert main(["export", str(a), "--out", str(tmp_path / "o.xyz")]) == 2
    assert "--format" in capsys.readouterr().err
    assert main(["export", str(a), "--format", "hdf", "--out", str(tmp_path / "o.h5")]) == 2
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"\x00" * 100)
    capsys.readouterr()
    assert main(["export", str(junk), "--out", str(tmp_path / "j.csv")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("cbh: error:") and "not an MCAP file" in err and "\n" not in err


def test_export_never_replaces_a_recording(tmp_path, station, capsys):
    """``-o SESSION.mcap -f csv`` (or -o another recording) overwrote the recording with its own
    export: the recorded data were gone. Now one error line, exit 2, both files byte-identical."""
    from cbh.cli.main import main

    write_session(tmp_path / "a.mcap", station, n=2)
    write_session(tmp_path / "b.mcap", station, n=1)
    before = {n: (tmp_path / n).read_bytes() for n in ("a.mcap", "b.mcap")}
    for out, fmt in (("a.mcap", "csv"), ("b.mcap", "parquet"), ("a.mcap", "netcdf")):
        assert main(["export", str(tmp_path / "a.mcap"), "--format", fmt, "--out", str(tmp_path / out)]) == 2
        err = capsys.readouterr().err.strip()
        assert err.startswith("cbh: error:") and "\n" not in err, err
        assert ("one of the command's own inputs" if out == "a.mcap" else "is a recording") in err, err
    assert main(["export", str(tmp_path / "a.mcap"), "--product", "cloudmap", "--format", "npz",
                 "--out", str(tmp_path / "b.mcap")]) == 2
    assert {n: (tmp_path / n).read_bytes() for n in ("a.mcap", "b.mcap")} == before


def test_sessions_of_different_stations_are_refused(tmp_path, station):
    from dataclasses import replace

    from cbh.outputs.export import export_sessions

    write_session(tmp_path / "a.mcap", station, n=1)
    write_session(tmp_path / "b.mcap", replace(station, name="elsewhere"), n=1)
    with pytest.raises(RecordingError, match="differs"):
        export_sessions([tmp_path / "a.mcap", tmp_path / "b.mcap"], "csv", tmp_path / "x.csv")


def test_sample_recording_exports_its_layer_heights():
    """The repository's sample session: exported heights equal those in its /pair/layers."""
    import xarray as xr

    from cbh.outputs.export import export_sessions
    from cbh.outputs.record import open_session

    s = open_session(SAMPLE)
    recorded = [[l.height_m for l in p.result.layers] for p in s.pairs(layers_only=True)]
    assert len(recorded) == s.pair_count >= 6
    import tempfile

    with tempfile.TemporaryDirectory() as d:
        out = Path(d) / "s.nc"
        export_sessions([SAMPLE], "netcdf", out)
        with xr.open_dataset(out) as ds:
            for i, hs in enumerate(recorded):
                assert list(ds.cloud_base_height.values[i, : len(hs)]) == hs


def test_parquet_is_complete_after_every_pair_appends_and_rolls_over(tmp_path, station):
    import pandas as pd

    from cbh.outputs.export import LayerExporter

    out = tmp_path / "live.parquet"
    exp = LayerExporter(out, station, max_rows=4)
    exp.write(*synthetic_pair(station, 0))  # one layer
    # readable while the writer is still open (a forecaster polling the file, or after a kill)
    assert len(pd.read_parquet(out)) == 1
    exp.write(*synthetic_pair(station, 1))  # two layers
    assert len(pd.read_parquet(out)) == 3
    exp.write(*synthetic_pair(station, 1))  # 3 + 2 > 4 rows: continues in live-001.parquet
    exp.close()
    assert [p.name for p in exp.paths] == ["live.parquet", "live-001.parquet"]
    assert len(pd.read_parquet(tmp_path / "live-001.parquet")) == 2
    assert not list(tmp_path.glob(".*.tmp"))
    with LayerExporter(out, station) as again:  # appends to the series' last cbh table
        again.write(*synthetic_pair(station, 0))
    df = pd.read_parquet(tmp_path / "live-001.parquet")
    assert len(pd.read_parquet(out)) == 3
    assert len(df) == 3 and df["cloud_base_height_m"].iloc[2] == pd.read_parquet(out)["cloud_base_height_m"].iloc[0]


def test_parquet_export_widens_for_a_new_diagnostic_and_keeps_every_row(tmp_path, station, monkeypatch):
    """The table is kept in Arrow between pairs (only new rows are converted): a diagnostic that
    appears later becomes a column, empty for the earlier rows, and nothing is lost when the
    per-pair chunks are combined."""
    import dataclasses

    import pandas as pd

    import cbh.outputs.export as E

    monkeypatch.setattr(E, "_COMBINE_EVERY", 2)
    out = tmp_path / "d.parquet"
    exp = E.LayerExporter(out, station)
    frames, r0 = synthetic_pair(station, 0)
    exp.write(frames, r0)
    frames, r1 = synthetic_pair(station, 1)
    exp.write(frames, dataclasses.replace(r1, diagnostics={**r1.diagnostics, "zz_new_px": 2.5}))
    for k in range(2, 5):
        exp.write(*synthetic_pair(station, k))
    exp.close()
    df = pd.read_parquet(out)
    n0, n1 = len(E.record_rows(E.pair_record(r0, 0.0))), len(E.record_rows(E.pair_record(r1, 0.0)))
    assert "zz_new_px" in df.columns and len(df) == exp.rows_written
    assert df["zz_new_px"].iloc[:n0].isna().all() and (df["zz_new_px"].iloc[n0: n0 + n1] == 2.5).all()
    assert df["zz_new_px"].iloc[n0 + n1:].isna().all()
    assert list(df["time_utc"]) == sorted(df["time_utc"])


def test_parquet_export_restarted_after_a_rollover_continues_its_series(tmp_path, station):
    """A run that rolled over to live-001.parquet, stopped, and started again appends to
    live-001 (then rolls to live-002), never over it: no recorded row is lost."""
    import pandas as pd

    from cbh.outputs.export import LayerExporter

    out = tmp_path / "live.parquet"
    with LayerExporter(out, station, max_rows=3) as exp:
        for _ in range(2):
            exp.write(*synthetic_pair(station, 1))  # 2 rows, then 2 more: live-001
    before = {p.name: len(pd.read_parquet(p)) for p in sorted(tmp_path.glob("*.parquet"))}
    assert before == {"live.parquet": 2, "live-001.parquet": 2}
    with LayerExporter(out, station, max_rows=3) as again:
        again.write(*synthetic_pair(station, 0))  # 2 + 1 rows: fits in live-001
        again.write(*synthetic_pair(station, 1))  # 3 + 2 > 3: live-002
    after = {p.name: len(pd.read_parquet(p)) for p in sorted(tmp_path.glob("*.parquet"))}
    assert after == {"live.parquet": 2, "live-001.parquet": 3, "live-002.parquet": 2}
    assert [p.name for p in again.paths] == ["live.parquet", "live-001.parquet", "live-002.parquet"]
