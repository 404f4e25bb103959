"""Layer heights for solar forecasting: a live CSV/Parquet sink, session tables and CF NetCDF.

Table columns (one row per layer per pair; a pair with no layer, e.g. a clear sky, gives one
row with ``layer = -1`` and empty heights, so every processed time step appears):

=========================  ======================================================================
``time_utc``               capture time (CSV: ISO 8601 ``…Z``; Parquet: timestamp[us, UTC])
``layer``                  0 = lowest layer, -1 = none found
``cloud_base_height_m``    cloud-base height above ground (the ENU origin) [m]
``cloud_base_altitude_m``  the same above mean sea level (+ station altitude) [m]
``median_height_m``        median height of the layer's points [m]
``spread_m``               robust spread (1.4826 MAD) of the layer's heights [m]
``cover``                  fraction of the reference camera's sky covered by the layer, 0..1
``points``                 triangulated points supporting the layer
``confidence``             0..1
``cloud_fraction``         total cloud fraction of the reference camera, 0..1
``n_layers``               layers found in this pair
``flags``                  quality flags of the pair, ``;``-separated
=========================  ======================================================================

Both live formats are readable at any moment, also while ``cbh run`` writes them and after a
kill: CSV rows are flushed as they are written; the Parquet table is rewritten to a temporary
file and atomically renamed over the export after every pair.

The NetCDF file follows CF-1.8 in the style of ceilometer products (E-PROFILE, Vaisala CL61):
dimensions ``time`` and ``layer``; ``cloud_base_height`` [m above ground] and
``cloud_base_altitude`` [m above sea level] with ``_FillValue`` where a layer is missing.
"""
from __future__ import annotations

import csv
import logging
import math
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from cbh.errors import ConfigError, RecordingError
from cbh.interfaces import ResultSink
from cbh.result import Frame, PairResult, require_time

__all__ = ["LayerExporter", "COLUMNS", "PairRecord", "pair_record", "session_records", "layer_table",
           "netcdf_dataset", "write_netcdf", "export_sessions", "FORMATS", "FILL_VALUE", "KNOWN_FLAGS"]

log = logging.getLogger(__name__)

COLUMNS = ("time_utc", "layer", "cloud_base_height_m", "cloud_base_altitude_m", "median_height_m", "spread_m",
           "cover", "points", "confidence", "cloud_fraction", "n_layers", "flags")
FORMATS = ("csv", "parquet", "netcdf")
FILL_VALUE = -9999.0  # NetCDF _FillValue of the float layer variables
KNOWN_FLAGS = ("few_points", "sun_glare", "overcast_no_texture")  # fixed bits 0, 1, 2 of quality_flag


@dataclass
class PairRecord:
    """What the exports need from one pair."""

    time_utc: datetime
    height_m: list[float]
    altitude_m: list[float]
    median_height_m: list[float]
    spread_m: list[float]
    cover: list[float]
    points: list[int]
    confidence: list[float]
    cloud_fraction: float  # reference camera's, NaN if unknown
    flags: list[str] = field(default_factory=list)
    point_count: int = 0


def pair_record(result: PairResult, station_altitude_m: float, altitude_m: list[float] | None = None) -> PairRecord:
    """Pick the layer values of one result (``altitude_m`` defaults to height + station altitude)."""
    L = result.layers
    alt = altitude_m if altitude_m is not None else [float(l.height_m) + float(station_altitude_m) for l in L]
    cf = result.cloud_fraction.get(result.cameras[0], math.nan)
    return PairRecord(
        time_utc=result.time_utc,
        height_m=[float(l.height_m) for l in L], altitude_m=[float(a) for a in alt],
        median_height_m=[float(l.median_height_m) for l in L], spread_m=[float(l.spread_m) for l in L],
        cover=[float(l.cover) for l in L], points=[int(l.points) for l in L],
        confidence=[float(l.confidence) for l in L], cloud_fraction=float(cf), flags=list(result.flags),
        point_count=len(result.points),
    )


def record_rows(r: PairRecord) -> list[dict]:
    """Table rows (dicts keyed by :data:`COLUMNS`) of one pair."""
    common = {"time_utc": r.time_utc, "cloud_fraction": r.cloud_fraction, "n_layers": len(r.height_m),
              "flags": ";".join(r.flags)}
    if not r.height_m:
        nan = math.nan
        return [dict(common, layer=-1, cloud_base_height_m=nan, cloud_base_altitude_m=nan, median_height_m=nan,
                     spread_m=nan, cover=0.0, points=0, confidence=nan)]
    return [dict(common, layer=i, cloud_base_height_m=r.height_m[i], cloud_base_altitude_m=r.altitude_m[i],
                 median_height_m=r.median_height_m[i], spread_m=r.spread_m[i], cover=r.cover[i], points=r.points[i],
                 confidence=r.confidence[i]) for i in range(len(r.height_m))]


def _iso(t: datetime) -> str:
    return t.astimezone(timezone.utc).strftime("%Y-%m-%dT%H:%M:%S.%fZ")


def _csv_value(k: str, v) -> str:
    if k == "time_utc":
        return _iso(v)
    if isinstance(v, float):
        return "" if math.isnan(v) else repr(v)  # repr: shortest text that reads back to the same double
    return str(v)


def _arrow_schema():
    import pyarrow as pa

    return pa.schema([
        ("time_utc", pa.timestamp("us", tz="UTC")), ("layer", pa.int32()),
        ("cloud_base_height_m", pa.float64()), ("cloud_base_altitude_m", pa.float64()),
        ("median_height_m", pa.float64()), ("spread_m", pa.float64()), ("cover", pa.float64()),
        ("points", pa.int64()), ("confidence", pa.float64()), ("cloud_fraction", pa.float64()),
        ("n_layers", pa.int32()), ("flags", pa.string()),
    ])


def _arrow_table(rows: list[dict]):
    import pyarrow as pa

    schema = _arrow_schema()
    cols = {}
    for name in schema.names:
        vals = [r[name] for r in rows]
        if schema.field(name).type == pa.float64():
            cols[name] = pa.array(vals, pa.float64(), from_pandas=True)  # NaN → null
        else:
            cols[name] = pa.array(vals, schema.field(name).type)
    return pa.table(cols, schema=schema)


class LayerExporter(ResultSink):
    """Appends layer rows as pairs are produced (a :class:`cbh.interfaces.ResultSink`).

    Parameters
    ----------
    path : str or Path
        ``.csv`` (appended to if it exists with the same header) or ``.parquet`` (appended to if
        it is a cbh layer table).
    station : cbh.geometry.station.Station
        Gives the altitude for ``cloud_base_altitude_m``.
    max_rows : int
        Parquet only: after this many rows the export continues in ``<stem>-001.parquet``, … .

    Both formats are complete and readable after every pair, also while the service runs and
    after a kill: CSV rows are flushed as written; the Parquet file is rewritten to a temporary
    file and atomically renamed over the old one after each pair (layer rows are small: a day
    at a 10 s cadence is about 26 000 rows).
    """

    kind = "exported"

    def output_paths(self) -> list[Path]:
        return list(self.paths)


    def __init__(self, path, station, *, max_rows: int = 200_000, fmt: str | None = None):
        self.path = Path(path)
        self.paths = [self.path]
        self.altitude_m = float(station.altitude_m)
        self.rows_written = 0
        self._closed = False
        suffix = "." + fmt.lower() if fmt else self.path.suffix.lower()
        if suffix not in (".csv", ".parquet"):
            raise ConfigError(f"--export: {self.path.name}: unknown format {suffix or '(no suffix)'!r} (.csv or .parquet)")
        self.format = suffix[1:]
        if not self.path.parent.is_dir():
            raise RecordingError(f"export directory does not exist: {self.path.parent}")
        if self.format == "csv":
            header = ",".join(COLUMNS)
            exists = self.path.is_file() and self.path.stat().st_size > 0
            if exists:
                with open(self.path, newline="") as fh:
                    first = fh.readline().rstrip("\r\n")
                if first != header:
                    raise RecordingError(f"{self.path}: exists with other columns; cannot append layer rows to it")
            try:
                self._fh = open(self.path, "a", newline="")
            except OSError as exc:
                raise RecordingError(f"cannot write {self.path}: {exc.strerror}") from None
            self._csv = csv.writer(self._fh, lineterminator="\n")
            if not exists:
                try:
                    self._csv.writerow(COLUMNS)
                    self._fh.flush()
                except OSError:
                    self._fh.close()  # the caller reports the error (e.g. disk full)
                    raise
        else:
            if max_rows < 1:
                raise ConfigError(f"export.max_rows: must be >= 1, got {max_rows}")
            self.max_rows = int(max_rows)
            self.paths = [self.path]
            self._rows: list[dict] = []
            if self.path.exists():
                import pyarrow.parquet as pq

                try:
                    table = pq.read_table(self.path)
                except Exception as exc:  # pyarrow raises several types for a foreign file
                    raise RecordingError(f"{self.path}: exists and is not a readable Parquet file ({exc})") from None
                if table.schema.names != _arrow_schema().names:
                    raise RecordingError(f"{self.path}: exists with other columns; cannot append layer rows to it")
                self._rows = table.to_pylist()

    def write(self, frames: tuple[Frame, Frame] | None, result: PairResult) -> None:
        """Append the rows of one result (``frames`` are not used)."""
        require_time(result, f"exporting to {self.path}")
        self.write_record(pair_record(result, self.altitude_m))

    def write_record(self, rec: PairRecord) -> None:
        if self._closed:
            raise RecordingError(f"write to a closed LayerExporter ({self.path})")
        rows = record_rows(rec)
        if self.format == "csv":
            for r in rows:
                self._csv.writerow([_csv_value(k, r[k]) for k in COLUMNS])
            self._fh.flush()
        else:
            if len(self._rows) + len(rows) > self.max_rows:
                self.path = self.paths[0].with_name(f"{self.paths[0].stem}-{len(self.paths):03d}.parquet")
                self.paths.append(self.path)
                self._rows = []
            self._rows.extend(rows)
            self._write_parquet()
        self.rows_written += len(rows)

    def _write_parquet(self) -> None:
        """Write all rows to a temporary file and rename it over the export (atomic)."""
        import os

        import pyarrow.parquet as pq

        tmp = self.path.with_name(f".{self.path.name}.tmp")
        try:
            pq.write_table(_arrow_table(self._rows), str(tmp))
            os.replace(tmp, self.path)
        finally:
            if tmp.exists():
                tmp.unlink()

    def close(self) -> None:
        """Flush and close (writes the Parquet footer). Idempotent."""
        if self._closed:
            return
        self._closed = True
        if self.format == "csv":
            self._fh.close()
        elif not self.path.exists():
            self._write_parquet()  # a run with no pair still leaves a (header-only) table

    def __enter__(self) -> "LayerExporter":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


# --- from recordings ----------------------------------------------------------------------

def session_records(paths) -> tuple[list[PairRecord], dict]:
    """Pair records of one or more sessions (time order, duplicates removed) and station info.

    Returns
    -------
    records : list of PairRecord
    info : dict
        station name, latitude_deg, longitude_deg, altitude_m, cameras, cbh_version.
    """
    from cbh.outputs.record import open_session

    recs: list[PairRecord] = []
    info: dict | None = None
    for p in paths:
        s = open_session(p)
        st = s.station
        this = {"station": st.name, "latitude_deg": st.latitude_deg, "longitude_deg": st.longitude_deg,
                "altitude_m": st.altitude_m, "cbh_version": s.version}
        if info is None:
            info = this
        elif (this["station"], this["latitude_deg"], this["longitude_deg"], this["altitude_m"]) != (
                info["station"], info["latitude_deg"], info["longitude_deg"], info["altitude_m"]):
            raise RecordingError(f"{p}: station {this['station']!r} differs from {info['station']!r} of the first "
                                 "session; export one station at a time")
        for pair in s.pairs(layers_only=True):
            recs.append(pair_record(pair.result, st.altitude_m, altitude_m=pair.altitude_m))
            info.setdefault("cameras", pair.result.cameras)
    if info is None:
        raise RecordingError("no recording given")
    recs.sort(key=lambda r: r.time_utc)
    out: list[PairRecord] = []
    for r in recs:
        if out and r.time_utc == out[-1].time_utc:
            log.warning("dropping a second pair at %s (same session given twice?)", r.time_utc.isoformat())
            continue
        out.append(r)
    return out, info


def layer_table(records: list[PairRecord]):
    """pandas DataFrame with :data:`COLUMNS` (time_utc as datetime64[ns, UTC])."""
    import pandas as pd

    rows = [row for r in records for row in record_rows(r)]
    df = pd.DataFrame(rows, columns=list(COLUMNS))
    df["time_utc"] = pd.to_datetime(df["time_utc"], utc=True)
    return df


def _flag_bits(records: list[PairRecord]) -> list[str]:
    extra = sorted({f for r in records for f in r.flags} - set(KNOWN_FLAGS))
    return list(KNOWN_FLAGS) + extra


def netcdf_dataset(records: list[PairRecord], info: dict):
    """CF-1.8 xarray Dataset (dims time, layer) of the pair records."""
    import pandas as pd
    import xarray as xr

    n_t = len(records)
    n_l = max([3] + [len(r.height_m) for r in records])  # ceilometers report up to 3 layers; more if found
    shape = (n_t, n_l)

    def grid(attr: str, dtype=np.float64, fill=np.nan):
        a = np.full(shape, fill, dtype)
        for i, r in enumerate(records):
            v = getattr(r, attr)
            a[i, : len(v)] = v
        return a

    bits = _flag_bits(records)
    qf = np.array([sum(1 << bits.index(f) for f in set(r.flags)) for r in records], np.int32)
    times = pd.DatetimeIndex([r.time_utc for r in records]).tz_convert("UTC").tz_localize(None).values.astype("datetime64[ns]")
    ds = xr.Dataset(
        data_vars={
            "cloud_base_height": (("time", "layer"), grid("height_m"), {
                "long_name": "cloud base height above ground", "units": "m",
                "comment": "above the station reference point (ENU origin); layers ascending, missing layers are fill"}),
            "cloud_base_altitude": (("time", "layer"), grid("altitude_m"), {
                "standard_name": "cloud_base_altitude", "long_name": "cloud base altitude above mean sea level",
                "units": "m"}),
            "cloud_base_height_median": (("time", "layer"), grid("median_height_m"), {
                "long_name": "median height of the layer's points above ground", "units": "m"}),
            "cloud_base_height_spread": (("time", "layer"), grid("spread_m"), {
                "long_name": "robust spread (1.4826 MAD) of the layer's point heights", "units": "m"}),
            "cloud_layer_cover": (("time", "layer"), grid("cover"), {
                "long_name": "fraction of the reference camera's sky covered by the layer", "units": "1",
                "valid_range": np.array([0.0, 1.0])}),
            "cloud_layer_points": (("time", "layer"), grid("points", np.int32, -1), {
                "long_name": "triangulated points supporting the layer", "units": "1"}),
            "cloud_layer_confidence": (("time", "layer"), grid("confidence"), {
                "long_name": "layer confidence", "units": "1", "valid_range": np.array([0.0, 1.0])}),
            "cloud_fraction": (("time",), np.array([r.cloud_fraction for r in records], np.float64), {
                "standard_name": "cloud_area_fraction", "long_name": "total cloud fraction of the reference camera's sky",
                "units": "1"}),
            "n_layers": (("time",), np.array([len(r.height_m) for r in records], np.int32), {
                "long_name": "number of cloud layers detected", "units": "1"}),
            "point_count": (("time",), np.array([r.point_count for r in records], np.int32), {
                "long_name": "triangulated points in the pair", "units": "1"}),
            "quality_flag": (("time",), qf, {
                "long_name": "quality flags of the frame pair", "flag_masks": np.array([1 << i for i in range(len(bits))], np.int32),
                "flag_meanings": " ".join(bits), "valid_min": np.int32(0)}),
            "latitude": ((), float(info["latitude_deg"]), {"standard_name": "latitude", "units": "degrees_north"}),
            "longitude": ((), float(info["longitude_deg"]), {"standard_name": "longitude", "units": "degrees_east"}),
            "altitude": ((), float(info["altitude_m"]), {
                "standard_name": "altitude", "long_name": "station altitude above mean sea level", "units": "m"}),
        },
        coords={
            "time": ("time", times, {"standard_name": "time", "long_name": "capture time (UTC)", "axis": "T"}),
            "layer": ("layer", np.arange(1, n_l + 1, dtype=np.int32), {"long_name": "cloud layer, 1 = lowest", "units": "1"}),
        },
        attrs={
            "Conventions": "CF-1.8",
            "title": f"Cloud base height from fisheye stereo cameras, station {info['station']}",
            "source": f"cbh {info.get('cbh_version', '?')}: two upward fisheye cameras, ray triangulation",
            "history": f"{datetime.now(timezone.utc).strftime('%Y-%m-%dT%H:%M:%SZ')} created by cbh export",
            "references": "Scaramuzza OCamCalib fisheye model; closest-approach ray triangulation",
            "station_name": info["station"],
            "station_latitude": float(info["latitude_deg"]),
            "station_longitude": float(info["longitude_deg"]),
            "station_altitude": float(info["altitude_m"]),
            "cameras": ",".join(info.get("cameras", ())),
            "featureType": "timeSeries",
        },
    )
    return ds


def write_netcdf(records: list[PairRecord], info: dict, out) -> None:
    """Write :func:`netcdf_dataset` to ``out`` (netCDF4, compressed, CF time in µs since 1970)."""
    ds = netcdf_dataset(records, info)
    enc = {}
    for name, var in ds.data_vars.items():
        e = {}
        if var.ndim:
            e.update(zlib=True, complevel=4)
        if var.dtype.kind == "f" and var.ndim:
            e["_FillValue"] = FILL_VALUE
        elif var.dtype.kind == "i" and var.ndim == 2:
            e["_FillValue"] = np.int32(-1)
        else:
            e["_FillValue"] = None
        enc[name] = e
    enc["time"] = {"units": "microseconds since 1970-01-01 00:00:00", "calendar": "standard", "dtype": "int64",
                   "_FillValue": None}
    enc["layer"] = {"_FillValue": None}
    try:
        ds.to_netcdf(out, engine="netcdf4", encoding=enc)
    except OSError as exc:
        raise RecordingError(f"cannot write {out}: {exc.strerror or exc}") from None


def export_sessions(paths, fmt: str, out) -> tuple[int, int]:
    """Export sessions to ``out`` in ``fmt`` (csv, parquet, netcdf). Returns (rows, time steps)."""
    fmt = fmt.lower()
    if fmt not in FORMATS:
        raise ConfigError(f"--format: unknown {fmt!r} (valid: {', '.join(FORMATS)})")
    out = Path(out)
    if not out.parent.is_dir():
        raise RecordingError(f"output directory does not exist: {out.parent}")
    records, info = session_records(paths)
    if fmt == "netcdf":
        if not records:
            raise RecordingError("no complete pairs in the recording(s): nothing to export")
        write_netcdf(records, info, out)
        return sum(max(1, len(r.height_m)) for r in records), len(records)
    if out.exists():
        out.unlink()  # an explicit --out is replaced
    from types import SimpleNamespace

    with LayerExporter(out, SimpleNamespace(altitude_m=info["altitude_m"]), fmt=fmt) as exp:
        for r in records:
            exp.write_record(r)
        n = exp.rows_written
    return n, len(records)
