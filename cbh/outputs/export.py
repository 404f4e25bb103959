"""Layer heights for solar forecasting: a live CSV/Parquet sink, session tables and CF NetCDF.

Table columns (one row per layer per pair; a pair with no layer, e.g. a clear sky, gives one
row with ``layer = 0`` and empty heights, so every processed time step appears). Layers are
numbered from 1 (the lowest) in every output: table, NetCDF ``layer`` coordinate, quicklook.

=========================  ======================================================================
``time_utc``               capture time (CSV: ISO 8601 ``…Z``; Parquet: timestamp[us, UTC])
``layer``                  1 = lowest layer, 2 = next …; 0 = no layer found in this pair
``cloud_base_height_m``    cloud-base height above ground (the ENU origin) [m]
``cloud_base_altitude_m``  the same above mean sea level (+ station altitude) [m]
``median_height_m``        median height of the layer's points [m]
``spread_m``               robust spread (1.4826 MAD) of the layer's heights [m]
``height_lo_m``            lowest height the layer stands for [m]: its band (its points' 10–90 %,
                           widened to what the pair cannot tell apart from it: a second layer in
                           ``height_lo_m`` … ``height_hi_m`` is reported as this one); empty = unknown
``height_hi_m``            highest height the layer stands for [m] (the band's top); empty = unknown
``cover``                  fraction of the reference camera's sky covered by the layer, 0..1
``cover_okta``             the layer's cover in okta, 0..8 (:func:`okta`)
``motion_east_ms``         layer motion over the ground, east component [m/s]; empty = unknown
``motion_north_ms``        layer motion over the ground, north component [m/s]; empty = unknown
``motion_spread_ms``       robust spread of the layer's track velocities [m/s]; empty = unknown
``motion_tracks``          feature tracks behind the layer's motion; 0 = no motion
``points``                 triangulated points supporting the layer
``confidence``             0..1
``cloud_fraction``         total cloud fraction of the reference camera, 0..1
``total_okta``             the total cloud fraction in okta, 0..8
``ceiling_m``              ceiling of the pair (:func:`ceiling_index`) above ground [m]; empty = none
``n_layers``               layers found in this pair
``quality_flag``           quality flags of the pair as fixed bits (:class:`cbh.flags.Flag`)
``flags``                  the same flags by name, ``;``-separated
``<diagnostic>``           one column per ``PairResult.diagnostics`` key (e.g. ``clock_offset_s``),
                           after the fixed columns, in sorted order; empty where a pair lacks it
=========================  ======================================================================

A pair with an invalidating flag (:data:`cbh.flags.INVALIDATING`, e.g. ``geometry_mismatch``)
keeps its rows: the flag is in ``quality_flag`` / ``flags``, and the reader decides.

CSV numbers are rounded to what the measurement supports (Parquet and NetCDF keep full
float64): lengths (``*_m``) to 0.1 m, speeds (``*_ms``) to 0.01 m/s, fractions (cover,
cloud fraction, confidence) to 3 decimals, diagnostics to 6 significant digits.

Both live formats are readable at any moment, also while ``cbh run`` writes them and after a
kill: CSV rows are flushed as they are written; the Parquet table is rewritten to a temporary
file and atomically renamed over the export after every pair. A diagnostic key that appears
only later in a live CSV rewrites the file once with the wider header (atomically).

The NetCDF file follows CF-1.8 (0 errors from the IOOS compliance checker) in the style of
ceilometer products (E-PROFILE, Vaisala CL61): see :func:`netcdf_dataset`.
"""
from __future__ import annotations

import csv
import errno
import io
import logging
import math
import os
import re
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from cbh.errors import ConfigError, RecordingError
from cbh.flags import INVALIDATING, Flag, flag_bits
from cbh.interfaces import ResultSink
from cbh.result import Frame, PairResult, numeric_diagnostics, require_time
from cbh.fileio import atomic_write

__all__ = ["LayerExporter", "COLUMNS", "PairRecord", "pair_record", "session_records", "layer_table",
           "netcdf_dataset", "write_netcdf", "export_sessions", "FORMATS", "FILL_VALUE", "okta",
           "ceiling_index", "diagnostic_units", "daily_groups", "write_error"]

log = logging.getLogger(__name__)

COLUMNS = ("time_utc", "layer", "cloud_base_height_m", "cloud_base_altitude_m", "median_height_m", "spread_m",
           "height_lo_m", "height_hi_m", "cover", "cover_okta", "motion_east_ms", "motion_north_ms", "motion_spread_ms",
           "motion_tracks", "points", "confidence", "cloud_fraction",
           "total_okta", "ceiling_m", "n_layers", "quality_flag", "flags")
FORMATS = ("csv", "parquet", "netcdf")
FILL_VALUE = -9999.0  # NetCDF _FillValue of the float layer variables
CEILING_OKTA = 5  # a ceiling is the base of the lowest layer at which the sky is ≥ 5/8 covered (broken)


def okta(cover: float) -> int:
    """Cloud cover (0..1) in okta (WMO code 2700): 0 only for no cloud, 8 only for a full
    cover, otherwise round(8 · cover) kept within 1..7; -1 for an unknown (NaN) cover."""
    c = float(cover)
    if not math.isfinite(c):
        return -1
    if c <= 0.0:
        return 0
    if c >= 1.0:
        return 8
    return int(min(max(round(8.0 * c), 1), 7))


def ceiling_index(covers) -> int | None:
    """Index of the ceiling layer in layers ascending by height, or None.

    Summation principle (as in METAR and ceilometer sky-condition reports): the ceiling is the
    lowest layer at which the cover of that layer and every layer below it adds up to at least
    5 okta (``CEILING_OKTA``); a single layer of ≥ 5 okta is its own ceiling.
    """
    total = 0.0
    for i, c in enumerate(covers):
        total += float(c) if math.isfinite(float(c)) else 0.0
        if okta(min(total, 1.0)) >= CEILING_OKTA:
            return i
    return None


#: Unit suffix of a diagnostics key → (CF units, long-name note).
_DIAG_UNITS = (("_deg", "degree"), ("_px", "1"), ("_ms", "m s-1"), ("_m", "m"), ("_s", "s"))


def diagnostic_units(key: str) -> str:
    """CF units of a ``PairResult.diagnostics`` key from its suffix (docs/conventions.md):
    ``_deg`` degree, ``_px`` pixels (units ``1``), ``_ms`` m s-1 (as in ``motion_east_ms``),
    ``_m`` m, ``_s`` s; any other key is dimensionless (``1``)."""
    for suffix, units in _DIAG_UNITS:
        if key.endswith(suffix):
            return units
    return "1"


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
    motion_east_ms: list[float] = field(default_factory=list)
    motion_north_ms: list[float] = field(default_factory=list)
    motion_spread_ms: list[float] = field(default_factory=list)
    motion_tracks: list[int] = field(default_factory=list)
    diagnostics: dict[str, float] = field(default_factory=dict)
    height_lo_m: list[float] = field(default_factory=list)  # each layer's band [m] (Layer.height_lo_m), NaN = unknown
    height_hi_m: list[float] = field(default_factory=list)

    @property
    def ceiling(self) -> int | None:
        """Index of the ceiling layer (:func:`ceiling_index`)."""
        return ceiling_index(self.cover)


def pair_record(result: PairResult, station_altitude_m: float, altitude_m: list[float] | None = None) -> PairRecord:
    """Pick the layer values of one result.

    ``altitude_m`` per layer: given, else the layer's own ``altitude_m``, else height + station altitude.
    """
    L = result.layers
    if altitude_m is None:
        altitude_m = [float(l.altitude_m) if math.isfinite(float(l.altitude_m))
                      else float(l.height_m) + float(station_altitude_m) for l in L]
    cf = result.cloud_fraction.get(result.cameras[0], math.nan)
    return PairRecord(
        time_utc=result.time_utc,
        height_m=[float(l.height_m) for l in L], altitude_m=[float(a) for a in altitude_m],
        median_height_m=[float(l.median_height_m) for l in L], spread_m=[float(l.spread_m) for l in L],
        cover=[float(l.cover) for l in L], points=[int(l.points) for l in L],
        confidence=[float(l.confidence) for l in L], cloud_fraction=float(cf), flags=list(result.flags),
        point_count=len(result.points),
        motion_east_ms=[float(l.motion_east_ms) for l in L], motion_north_ms=[float(l.motion_north_ms) for l in L],
        # the motion's quality (getattr: layers made before the motion estimator carry none)
        motion_spread_ms=[float(getattr(l, "motion_spread_ms", math.nan)) for l in L],
        motion_tracks=[int(getattr(l, "motion_tracks", 0)) for l in L],
        diagnostics=numeric_diagnostics(result.diagnostics),
        height_lo_m=[float(getattr(l, "height_lo_m", math.nan)) for l in L],
        height_hi_m=[float(getattr(l, "height_hi_m", math.nan)) for l in L],
    )


def record_rows(r: PairRecord, diagnostics: tuple[str, ...] = ()) -> list[dict]:
    """Table rows (dicts keyed by :data:`COLUMNS` + ``diagnostics``) of one pair."""
    nan = math.nan
    ceil = r.ceiling
    common = {"time_utc": r.time_utc, "cloud_fraction": r.cloud_fraction, "total_okta": okta(r.cloud_fraction),
              "ceiling_m": r.height_m[ceil] if ceil is not None else nan, "n_layers": len(r.height_m),
              "quality_flag": flag_bits(r.flags), "flags": ";".join(r.flags)}
    common.update({k: float(r.diagnostics.get(k, nan)) for k in diagnostics})
    if not r.height_m:
        return [dict(common, layer=0, cloud_base_height_m=nan, cloud_base_altitude_m=nan, median_height_m=nan,
                     spread_m=nan, height_lo_m=nan, height_hi_m=nan, cover=0.0, cover_okta=0, motion_east_ms=nan, motion_north_ms=nan,
                     motion_spread_ms=nan, motion_tracks=0, points=0,
                     confidence=nan)]
    n = len(r.height_m)
    me = r.motion_east_ms or [nan] * n
    mn = r.motion_north_ms or [nan] * n
    ms = r.motion_spread_ms or [nan] * n
    mt = r.motion_tracks or [0] * n
    lo, hi = r.height_lo_m or [nan] * n, r.height_hi_m or [nan] * n
    return [dict(common, layer=i + 1, cloud_base_height_m=r.height_m[i], cloud_base_altitude_m=r.altitude_m[i],
                 median_height_m=r.median_height_m[i], spread_m=r.spread_m[i], height_lo_m=lo[i],
                 height_hi_m=hi[i], cover=r.cover[i],
                 cover_okta=okta(r.cover[i]), motion_east_ms=me[i], motion_north_ms=mn[i],
                 motion_spread_ms=ms[i], motion_tracks=mt[i], points=r.points[i],
                 confidence=r.confidence[i]) for i in range(n)]


def _iso(t: datetime) -> str:
    return t.astimezone(timezone.utc).strftime("%Y-%m-%dT%H:%M:%S.%fZ")


_FRACTIONS = {"cover", "cloud_fraction", "confidence"}


def _csv_value(k: str, v) -> str:
    """One CSV cell, rounded by the rule of the module docstring."""
    if k == "time_utc":
        return _iso(v)
    if isinstance(v, (float, np.floating)):
        v = float(v)
        if math.isnan(v):
            return ""
        if k in COLUMNS:
            if k in _FRACTIONS:
                return f"{v:.3f}"
            if k.endswith("_ms"):
                return f"{v:.2f}"
            if k.endswith("_m"):
                return f"{v:.1f}"
        return f"{v:.6g}"
    return str(v)


def _arrow_schema(diagnostics: tuple[str, ...] = ()):
    import pyarrow as pa

    f64 = pa.float64()
    return pa.schema([
        ("time_utc", pa.timestamp("us", tz="UTC")), ("layer", pa.int32()),
        ("cloud_base_height_m", f64), ("cloud_base_altitude_m", f64),
        ("median_height_m", f64), ("spread_m", f64), ("height_lo_m", f64), ("height_hi_m", f64), ("cover", f64), ("cover_okta", pa.int8()),
        ("motion_east_ms", f64), ("motion_north_ms", f64), ("motion_spread_ms", f64), ("motion_tracks", pa.int32()),
        ("points", pa.int64()), ("confidence", f64), ("cloud_fraction", f64), ("total_okta", pa.int8()),
        ("ceiling_m", f64), ("n_layers", pa.int32()), ("quality_flag", pa.int64()), ("flags", pa.string()),
        *[(k, f64) for k in diagnostics],
    ])


_COMBINE_EVERY = 64  # Parquet export: the per-pair chunks of the table are combined this often


def _arrow_table(rows: list[dict], diagnostics: tuple[str, ...] = ()):
    import pyarrow as pa

    schema = _arrow_schema(diagnostics)
    cols = {}
    for name in schema.names:
        vals = [r.get(name, math.nan) for r in rows]
        if schema.field(name).type == pa.float64():
            cols[name] = pa.array(vals, pa.float64(), from_pandas=True)  # NaN → null
        else:
            cols[name] = pa.array(vals, schema.field(name).type)
    return pa.table(cols, schema=schema)


def _diag_keys(names) -> tuple[str, ...]:
    """Diagnostics columns of an existing table header (None if it is not a cbh layer table)."""
    names = list(names)
    if names[: len(COLUMNS)] != list(COLUMNS):
        return None
    return tuple(names[len(COLUMNS):])


class LayerExporter(ResultSink):
    """Appends layer rows as pairs are produced (a :class:`cbh.interfaces.ResultSink`).

    Parameters
    ----------
    path : str or Path
        ``.csv`` (appended to if it exists with cbh's columns) or ``.parquet`` (appended to if
        it is a cbh layer table).
    station : cbh.geometry.station.Station
        Gives the altitude for ``cloud_base_altitude_m`` where a layer carries none.
    max_rows : int
        Parquet only: after this many rows the export continues in ``<stem>-001.parquet``, … ;
        a later run continues in the series' last file (never over one).
    diagnostics : tuple of str
        Diagnostics columns a new file starts with (keys seen later are added).

    Both formats are complete and readable after every pair, also while the service runs and
    after a kill: a pair's CSV rows are appended with one unbuffered write, a write that fails
    part-way (disk full) is cut back to the last complete row, and a torn last row left by an
    earlier crash is removed (with a warning) when the file is opened again; the Parquet file is rewritten to a temporary
    file and atomically renamed over the old one after each pair (layer rows are small: a day
    at a 10 s cadence is about 26 000 rows; the rows are held as an Arrow table and only a pair's
    own are converted, so a pair costs 7 ms at 26 000 rows and 9 ms at 50 000, against 170 ms
    and 1.5 s at 200 000 when every row was rebuilt from Python each time).
    """

    kind = "exported"

    def output_paths(self) -> list[Path]:
        return list(self.paths)

    def __init__(self, path, station, *, max_rows: int = 200_000, fmt: str | None = None,
                 diagnostics: tuple[str, ...] = ()):
        self.path = Path(path)
        self.paths = [self.path]
        self.altitude_m = float(station.altitude_m)
        self.rows_written = 0
        self.diagnostics: tuple[str, ...] = tuple(diagnostics)  # columns of a new file (more join later)
        self._closed = False
        suffix = "." + fmt.lower() if fmt else self.path.suffix.lower()
        if suffix not in (".csv", ".parquet"):
            raise ConfigError(f"--export: {self.path.name}: unknown format {suffix or '(no suffix)'!r} (.csv or .parquet)")
        self.format = suffix[1:]
        if not self.path.parent.is_dir():
            raise RecordingError(f"export directory does not exist: {self.path.parent}")
        if self.format == "csv":
            self._repair_csv_tail()
            exists = self.path.is_file() and self.path.stat().st_size > 0
            if exists:
                with open(self.path, newline="") as fh:
                    first = next(csv.reader([fh.readline()]), [])
                keys = _diag_keys(first)
                if keys is None:
                    raise RecordingError(f"{self.path}: exists with other columns; cannot append layer rows to it")
                self.diagnostics = keys
            self._open_csv(write_header=not exists)
        else:
            if max_rows < 1:
                raise ConfigError(f"export.max_rows: must be >= 1, got {max_rows}")
            self.max_rows = int(max_rows)
            self._table = None  # the file's rows as an Arrow table (a chunk per pair, combined now and then)
            self._pairs_since_combine = 0
            # an earlier run's series (<stem>-001.parquet …): continue in its last file, so that a
            # rollover never starts over a file that exists
            while self._series_name(len(self.paths)).exists():
                self.paths.append(self._series_name(len(self.paths)))
            self.path = self.paths[-1]
            if self.path.exists():
                import pyarrow.parquet as pq

                try:
                    table = pq.read_table(self.path)
                except Exception as exc:  # pyarrow raises several types for a foreign file
                    raise RecordingError(f"{self.path}: exists and is not a readable Parquet file ({exc})") from None
                keys = _diag_keys(table.schema.names)
                if keys is None:
                    raise RecordingError(f"{self.path}: exists with other columns; cannot append layer rows to it")
                self.diagnostics = keys
                self._table = _arrow_table(table.to_pylist(), keys)  # once, in our schema

    def _widen_csv(self, keys: tuple[str, ...]) -> None:
        """Rewrite the CSV with ``keys`` as its diagnostics columns (atomic rename)."""
        self._fh.close()
        with open(self.path, newline="") as fh:
            old = list(csv.reader(fh))
        width = len(COLUMNS) + len(keys)
        try:
            with atomic_write(self.path) as tmp, open(tmp, "w", newline="") as fh:
                w = csv.writer(fh, lineterminator="\n")
                w.writerow(COLUMNS + keys)
                index = {k: i for i, k in enumerate(old[0])} if old else {}
                for row in old[1:]:
                    w.writerow([row[index[k]] if k in index and index[k] < len(row) else ""
                                for k in (COLUMNS + keys)][:width])
        except OSError as exc:
            self._open_csv(write_header=False)  # the old table is intact: keep appending to it
            raise write_error(self.path, exc) from None
        self.diagnostics = keys
        self._open_csv(write_header=False)

    def write(self, frames: tuple[Frame, Frame] | None, result: PairResult) -> None:
        """Append the rows of one result (``frames`` are not used)."""
        require_time(result, f"exporting to {self.path}")
        self.write_record(pair_record(result, self.altitude_m))

    def write_record(self, rec: PairRecord) -> None:
        if self._closed:
            raise RecordingError(f"write to a closed LayerExporter ({self.path})")
        new = sorted(set(rec.diagnostics) - set(self.diagnostics))
        if new:
            keys = self.diagnostics + tuple(new)
            if self.format == "csv":
                self._widen_csv(keys)
            else:
                self.diagnostics = keys
        rows = record_rows(rec, self.diagnostics)
        if self.format == "csv":
            cols = COLUMNS + self.diagnostics
            buf = io.StringIO()
            w = csv.writer(buf, lineterminator="\n")
            for r in rows:
                w.writerow([_csv_value(k, r[k]) for k in cols])
            self._append_whole(buf.getvalue().encode("utf-8"))
        else:
            held = 0 if self._table is None else self._table.num_rows
            if held + len(rows) > self.max_rows:
                k = len(self.paths)
                while self._series_name(k).exists():  # (written meanwhile by someone else: never over it)
                    k += 1
                self.path = self._series_name(k)
                self.paths.append(self.path)
                self._table = None
            self._append_rows(rows)
            self._write_parquet()
        self.rows_written += len(rows)

    # --- CSV: whole rows or nothing ------------------------------------------------------

    def _repair_csv_tail(self) -> None:
        """Cut a torn last row (no final newline) left by a crash or a full disk of an earlier
        run, with a warning. Only a file that starts like a cbh layer table is touched."""
        try:
            fd = os.open(self.path, os.O_RDWR)
        except FileNotFoundError:
            return
        except OSError as exc:
            raise RecordingError(f"cannot write {self.path}: {exc.strerror}") from None
        try:
            size = os.fstat(fd).st_size
            head = os.pread(fd, 4096, 0).split(b"\n", 1)[0]
            ours = ",".join(COLUMNS).encode()
            if not size or not (head.startswith(ours) or ours.startswith(head)):
                return  # empty, or not ours: the header check reports it
            keep = _complete_length(fd, size)
            if keep != size:
                os.ftruncate(fd, keep)
                log.warning(f"{self.path}: removed a torn last row ({size - keep} bytes) left by an "
                            "interrupted earlier run", extra={"cbh_event": "csv_repaired"})
        finally:
            os.close(fd)

    def _open_csv(self, write_header: bool) -> None:
        """Open for appending, unbuffered (rows go out whole, see :meth:`_append_whole`)."""
        try:
            self._fh = open(self.path, "ab", buffering=0)
        except OSError as exc:
            raise RecordingError(f"cannot write {self.path}: {exc.strerror}") from None
        if write_header:
            try:
                self._append_whole((",".join(COLUMNS + self.diagnostics) + "\n").encode())
            except OSError:
                self._fh.close()  # the caller reports the error (e.g. disk full)
                raise

    def _append_whole(self, data: bytes) -> None:
        """Append ``data`` (whole rows) with one write; if it fails part-way (disk full), cut the
        file back to the last complete row and re-raise: a reader never sees a torn row."""
        fd = self._fh.fileno()
        start = os.lseek(fd, 0, os.SEEK_END)
        view = memoryview(data)
        try:
            while view:
                n = os.write(fd, view)  # O_APPEND: at the end; short only when the disk fills
                view = view[n:]
        except OSError:
            try:
                os.ftruncate(fd, start)
            except OSError:  # pragma: no cover - truncating never needs space
                pass
            raise

    def _series_name(self, k: int) -> Path:
        """File ``k`` of the Parquet export series: the path itself, then ``<stem>-001.parquet`` …"""
        first = self.paths[0]
        return first if k == 0 else first.with_name(f"{first.stem}-{k:03d}.parquet")

    def _append_rows(self, rows: list[dict]) -> None:
        """Only the new rows are converted (Python → Arrow); the table so far is kept as Arrow,
        widened with empty columns when a diagnostics key appears. Rebuilding every row from
        Python each pair took 170 ms at a day's 26 000 rows and 1.5 s at 200 000, with the write."""
        import pyarrow as pa

        new = _arrow_table(rows, self.diagnostics)
        old = self._table
        if old is not None and old.schema != new.schema:
            for name in new.schema.names[old.num_columns:]:
                old = old.append_column(new.schema.field(name), pa.nulls(old.num_rows, new.schema.field(name).type))
        self._table = new if old is None else pa.concat_tables([old, new])
        self._pairs_since_combine += 1
        if self._pairs_since_combine >= _COMBINE_EVERY:  # a chunk per pair would make each write slower
            self._table = self._table.combine_chunks()
            self._pairs_since_combine = 0

    def _write_parquet(self) -> None:
        """Write all rows to a temporary file and rename it over the export (atomic)."""
        import pyarrow.parquet as pq

        table = self._table if self._table is not None else _arrow_table([], self.diagnostics)
        try:
            with atomic_write(self.path) as tmp:
                pq.write_table(table, str(tmp))
        except OSError as exc:
            raise write_error(self.path, exc) from None

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


def _complete_length(fd: int, size: int) -> int:
    """Bytes of the file up to and including its last newline (0 if none)."""
    pos = size
    while pos > 0:
        n = min(65536, pos)
        os.lseek(fd, pos - n, os.SEEK_SET)
        chunk = os.read(fd, n)
        i = chunk.rfind(b"\n")
        if i >= 0:
            return pos - n + i + 1
        pos -= n
    return 0


# --- from recordings ----------------------------------------------------------------------

def session_records(paths) -> tuple[list[PairRecord], dict]:
    """Pair records of one or more sessions (time order, duplicates removed) and station info.

    Returns
    -------
    records : list of PairRecord
    info : dict
        station name, latitude_deg, longitude_deg, altitude_m, metadata ([station.metadata]),
        cameras, cbh_version.
    """
    from cbh.outputs.record import open_session

    recs: list[PairRecord] = []
    info: dict | None = None
    for p in paths:
        s = open_session(p)
        st = s.station
        this = {"station": st.name, "latitude_deg": st.latitude_deg, "longitude_deg": st.longitude_deg,
                "altitude_m": st.altitude_m, "cbh_version": s.version, "metadata": dict(st.metadata)}
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
    return dedupe(recs), info


def dedupe(recs: list[PairRecord]) -> list[PairRecord]:
    """Time order; a second pair at the same time (a session given twice) is dropped with a warning."""
    recs = sorted(recs, key=lambda r: r.time_utc)
    out: list[PairRecord] = []
    for r in recs:
        if out and r.time_utc == out[-1].time_utc:
            log.warning("dropping a second pair at %s (same session given twice?)", r.time_utc.isoformat())
            continue
        out.append(r)
    return out


def _all_diagnostics(records) -> tuple[str, ...]:
    return tuple(sorted({k for r in records for k in r.diagnostics}))


def layer_table(items, station_altitude_m: float = math.nan):
    """One table for every consumer: pair results or export records as a pandas DataFrame.

    The same rows and columns as the CSV/Parquet export (:data:`COLUMNS` + one column per
    diagnostics key): one row per layer (``layer`` 1 = lowest; ``cloud_base_height_m`` above
    the ENU origin, ``cloud_base_altitude_m`` above mean sea level, cover and okta, motion
    [m/s], points, confidence, cloud fraction, ceiling, ``quality_flag`` bits and ``flags``
    names); a pair without a layer gives one row with ``layer = 0``. ``time_utc`` is
    datetime64[ns, UTC] (NaT where unknown). This is ``cbh.layer_table``.

    Parameters
    ----------
    items : iterable of PairResult or PairRecord
    station_altitude_m : float
        Used for a result's layer altitude only where the layer does not carry one [m].
    """
    import pandas as pd

    records = [it if isinstance(it, PairRecord) else pair_record(it, station_altitude_m) for it in items]
    diags = _all_diagnostics(records)
    rows = [row for r in records for row in record_rows(r, diags)]
    df = pd.DataFrame(rows, columns=list(COLUMNS + diags))
    df["time_utc"] = pd.to_datetime(df["time_utc"], utc=True)
    return df


def daily_groups(records: list[PairRecord]) -> dict[str, list[PairRecord]]:
    """Records grouped by UTC day (``YYYYMMDD`` → records, in time order)."""
    out: dict[str, list[PairRecord]] = {}
    for r in records:
        out.setdefault(r.time_utc.astimezone(timezone.utc).strftime("%Y%m%d"), []).append(r)
    return out


_NC_NAME = re.compile(r"^[A-Za-z][A-Za-z0-9_]*$")


def netcdf_dataset(records: list[PairRecord], info: dict):
    """CF-1.8 xarray Dataset (dims ``time``, ``layer``) of the pair records.

    Ceilometer conventions (E-PROFILE / Vaisala CL61):

    * ``station_latitude``, ``station_longitude``, ``station_altitude`` scalar coordinate
      variables; ``station_name`` (``cf_role = timeseries_id``), ``featureType = timeSeries``;
      ``institution``, ``instrument``, ``site`` … global attributes from ``[station.metadata]``.
    * ``time``: float64 seconds since 1970-01-01 UTC (µs resolution kept).
    * ``layer``: 1 = lowest. ``cloud_base_height`` [m above ground] and ``cloud_base_altitude``
      [m above sea level] per layer; the CF standard name ``cloud_base_altitude`` (the base of
      the lowest cloud) only on ``lowest_cloud_base_altitude(time)``.
    * ``cloud_layer_cover`` (0..1) and ``cloud_layer_okta``, ``cloud_fraction`` and
      ``total_cloud_okta``; ``ceiling_height`` (:func:`ceiling_index`).
    * ``cloud_motion_east`` / ``cloud_motion_north`` (time, layer) [m s-1], plus speed and the
      direction the layer moves towards [degree clockwise from north].
    * ``quality_flag``: bits of :class:`cbh.flags.Flag` (``flag_masks``/``flag_meanings`` list
      the whole enumeration, so bits never depend on the file's content).
    * every ``PairResult.diagnostics`` key as a (time) variable of that name, units from its
      suffix (:func:`diagnostic_units`), fill where a pair lacks it.
    """
    import xarray as xr

    n_l = max([3] + [len(r.height_m) for r in records])  # ceilometers report up to 3 layers; more if found
    g = _RecordArrays(records, n_l)
    data_vars = _layer_vars(g)
    data_vars.update(_time_vars(g))
    data_vars.update(_diagnostic_vars(records, set(data_vars) | set(_STATION_COORDS)))
    return xr.Dataset(data_vars=data_vars, coords=_coords(records, info, n_l), attrs=_global_attrs(info))


_STATION_COORDS = ("time", "layer", "station_latitude", "station_longitude", "station_altitude", "station_name")


def _var(dims, data, **attrs):
    """An xarray variable spec: (dims, data, attrs)."""
    return dims, data, attrs


class _RecordArrays:
    """Arrays of T pair records for :func:`netcdf_dataset`: (T, L) per layer, (T,) per pair."""

    def __init__(self, records: list[PairRecord], n_layers: int):
        self.records, self.shape = records, (len(records), n_layers)

    def grid(self, attr: str, dtype=np.float64, fill=np.nan) -> np.ndarray:
        """(T, L) of the records' per-layer ``attr``; ``fill`` where a pair has fewer layers."""
        a = np.full(self.shape, fill, dtype)
        for i, r in enumerate(self.records):
            v = getattr(r, attr)
            a[i, : len(v)] = v
        return a

    def per_time(self, fn, dtype=np.float64) -> np.ndarray:
        """(T,) of ``fn(record)``."""
        return np.array([fn(r) for r in self.records], dtype)

    def okta(self) -> np.ndarray:
        """(T, L) int32 layer cover in okta; -1 where there is no layer."""
        a = np.full(self.shape, -1, np.int32)
        for i, r in enumerate(self.records):
            a[i, : len(r.cover)] = [okta(c) for c in r.cover]
        return a


def _layer_vars(g: _RecordArrays) -> dict:
    """The (time, layer) variables: heights and altitudes (and the lowest layer's, per time),
    cover, support and motion."""
    TL = ("time", "layer")
    H, A = g.grid("height_m"), g.grid("altitude_m")
    ve, vn = g.grid("motion_east_ms"), g.grid("motion_north_ms")
    return {
        "cloud_base_height": _var(TL, H, long_name="cloud base height above ground", units="m",
                                  comment="above the station reference point (ENU origin); layer 1 = lowest; "
                                          "missing layers are fill"),
        "cloud_base_altitude": _var(TL, A, long_name="cloud base altitude above mean sea level", units="m"),
        "lowest_cloud_base_height": _var(("time",), H[:, 0].copy(),
                                         long_name="height of the lowest cloud base above ground", units="m"),
        "lowest_cloud_base_altitude": _var(("time",), A[:, 0].copy(), standard_name="cloud_base_altitude",
                                           long_name="altitude of the lowest cloud base above mean sea level", units="m"),
        "cloud_base_height_median": _var(TL, g.grid("median_height_m"),
                                         long_name="median height of the layer's points above ground", units="m"),
        "cloud_base_height_spread": _var(TL, g.grid("spread_m"),
                                         long_name="robust spread (1.4826 MAD) of the layer's point heights", units="m"),
        "cloud_base_height_band_low": _var(TL, g.grid("height_lo_m"),
                                           long_name="lowest height above ground the layer stands for: its band, what "
                                                     "the pair cannot tell apart from it", units="m"),
        "cloud_base_height_band_high": _var(TL, g.grid("height_hi_m"),
                                            long_name="highest height above ground the layer stands for", units="m"),
        "cloud_layer_cover": _var(TL, g.grid("cover"),
                                  long_name="fraction of the reference camera's sky covered by the layer", units="1",
                                  valid_range=np.array([0.0, 1.0])),
        "cloud_layer_okta": _var(TL, g.okta(), long_name="cloud cover of the layer in okta (eighths)",
                                 units="1", valid_range=np.array([0, 8], np.int32)),
        "cloud_layer_points": _var(TL, g.grid("points", np.int32, -1),
                                   long_name="triangulated points supporting the layer", units="1"),
        "cloud_layer_confidence": _var(TL, g.grid("confidence"), long_name="layer confidence", units="1",
                                       valid_range=np.array([0.0, 1.0])),
        "cloud_motion_east": _var(TL, ve, long_name="eastward motion of the cloud layer over the ground",
                                  units="m s-1"),
        "cloud_motion_north": _var(TL, vn, long_name="northward motion of the cloud layer over the ground",
                                   units="m s-1"),
        "cloud_motion_spread": _var(TL, g.grid("motion_spread_ms"),
                                    long_name="robust spread (1.4826 MAD) of the layer's track velocities",
                                    units="m s-1"),
        "cloud_motion_tracks": _var(TL, g.grid("motion_tracks", np.int32, -1),
                                    long_name="feature tracks behind the layer's motion", units="1"),
        "cloud_motion_speed": _var(TL, np.hypot(ve, vn), long_name="speed of the cloud layer over the ground",
                                   units="m s-1"),
        "cloud_motion_direction": _var(TL, np.degrees(np.arctan2(ve, vn)) % 360.0,
                                       long_name="direction the cloud layer moves towards, clockwise from north",
                                       units="degree"),
    }


def _time_vars(g: _RecordArrays) -> dict:
    """The (time) variables of the whole pair: cloud fraction, okta, ceiling, counts, flags."""
    H = g.grid("height_m")
    all_bits = np.array([int(f) for f in Flag], np.int32)
    ceiling = np.array([H[i, r.ceiling] if r.ceiling is not None else math.nan for i, r in enumerate(g.records)])
    return {
        "cloud_fraction": _var(("time",), g.per_time(lambda r: r.cloud_fraction), standard_name="cloud_area_fraction",
                               long_name="total cloud fraction of the reference camera's sky", units="1"),
        "total_cloud_okta": _var(("time",), g.per_time(lambda r: okta(r.cloud_fraction), np.int32),
                                 long_name="total cloud cover in okta (eighths)", units="1",
                                 valid_range=np.array([0, 8], np.int32)),
        "ceiling_height": _var(("time",), ceiling,
                               long_name="ceiling above ground: base of the lowest layer at which the summed "
                                         f"layer cover reaches {CEILING_OKTA} okta", units="m"),
        "n_layers": _var(("time",), g.per_time(lambda r: len(r.height_m), np.int32),
                         long_name="number of cloud layers detected", units="1"),
        "point_count": _var(("time",), g.per_time(lambda r: r.point_count, np.int32),
                            long_name="triangulated points in the pair", units="1"),
        "quality_flag": _var(("time",), g.per_time(lambda r: flag_bits(r.flags), np.int32), standard_name="status_flag",
                             long_name="quality flags of the frame pair",
                             flag_masks=all_bits, flag_meanings=" ".join(f.name for f in Flag),
                             valid_range=np.array([0, int(all_bits.sum())], np.int32),
                             comment="bits of cbh.flags.Flag; layers of a pair with "
                                     f"{', '.join(sorted(INVALIDATING))} are not valid"),
    }


def _diagnostic_vars(records: list[PairRecord], taken: set) -> dict:
    """Every diagnostics key as a (time) variable: its own name where that is a valid NetCDF
    name not already taken, else ``diagnostic_<key>``; fill where a pair lacks it."""
    out = {}
    for key in _all_diagnostics(records):
        used = taken | set(out)
        name = key if _NC_NAME.match(key) and key not in used else "diagnostic_" + re.sub(r"\W", "_", key)
        out[name] = _var(("time",), np.array([r.diagnostics.get(key, math.nan) for r in records], np.float64),
                         long_name=f"pair diagnostic {key}", units=diagnostic_units(key))
    return out


def _coords(records: list[PairRecord], info: dict, n_layers: int) -> dict:
    """Time (UTC, ns), layer (1 = lowest) and the station's scalar coordinates."""
    import pandas as pd

    times = pd.DatetimeIndex([r.time_utc for r in records]).tz_convert("UTC").tz_localize(None).values.astype("datetime64[ns]")
    return {
        "time": ("time", times, {"standard_name": "time", "long_name": "capture time (UTC)", "axis": "T"}),
        "layer": ("layer", np.arange(1, n_layers + 1, dtype=np.int32),
                  {"long_name": "cloud layer, 1 = lowest", "units": "1"}),
        "station_latitude": ((), float(info["latitude_deg"]), {
            "standard_name": "latitude", "long_name": "station latitude", "units": "degrees_north"}),
        "station_longitude": ((), float(info["longitude_deg"]), {
            "standard_name": "longitude", "long_name": "station longitude", "units": "degrees_east"}),
        "station_altitude": ((), float(info["altitude_m"]), {
            "standard_name": "altitude", "long_name": "station altitude above mean sea level", "units": "m",
            "positive": "up", "axis": "Z"}),
        "station_name": ((), str(info["station"]), {"long_name": "station name", "cf_role": "timeseries_id"}),
    }


def _global_attrs(info: dict) -> dict:
    """CF and E-PROFILE global attributes; ``[station.metadata]`` strings where given."""
    md = info.get("metadata", {}) or {}
    attrs = {
        "Conventions": "CF-1.8",
        "title": f"Cloud base height from fisheye stereo cameras, station {info['station']}",
        "institution": md.get("institution", "unknown"),
        "source": f"cbh {info.get('cbh_version', '?')}: two upward fisheye cameras, ray triangulation",
        "instrument": md.get("instrument", "two upward-looking fisheye sky cameras"),
        "site": md.get("site", str(info["station"])),
        "history": f"{datetime.now(timezone.utc).strftime('%Y-%m-%dT%H:%M:%SZ')} created by cbh export",
        "references": md.get("references", "Scaramuzza OCamCalib fisheye model; closest-approach ray triangulation"),
        "featureType": "timeSeries",
        "station_name": str(info["station"]),
        "cameras": ",".join(info.get("cameras", ())),
    }
    for k in ("contact", "comment", "wigos_station_id"):
        if k in md:
            attrs[k] = md[k]
    return attrs


def write_netcdf(records: list[PairRecord], info: dict, out) -> None:
    """Write :func:`netcdf_dataset` to ``out`` (netCDF4, compressed, CF time in s since 1970)."""
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
    enc["time"] = {"units": "seconds since 1970-01-01 00:00:00", "calendar": "standard", "dtype": "float64",
                   "_FillValue": None}
    for c in ("layer", "station_latitude", "station_longitude", "station_altitude"):
        enc[c] = {"_FillValue": None}
    try:
        with atomic_write(out) as tmp:
            ds.to_netcdf(tmp, engine="netcdf4", encoding=enc)
    except OSError as exc:
        raise write_error(out, exc) from None


def _disk_full(path) -> bool:
    """Whether ``path``'s folder is writable but its file system has no room left: the NetCDF/HDF5
    library reports a full disk as "Permission denied" (EACCES)."""
    folder = Path(path).parent
    try:
        st = os.statvfs(folder)
    except OSError:
        return False
    writable = os.access(folder, os.W_OK) and not st.f_flag & os.ST_RDONLY
    return writable and st.f_blocks > 0 and st.f_bavail * st.f_frsize < 64 * 1024  # (sysfs & co: 0 blocks)


def write_error(path, exc: OSError) -> RecordingError:
    """The one-line error of a failed write of ``path``: disk full, or the OS's reason, and never
    the temporary file beside ``path`` that the writer actually had open (:func:`atomic_write`;
    pyarrow's own messages name it)."""
    if exc.errno == errno.ENOSPC or (exc.errno in (errno.EACCES, errno.EPERM) and _disk_full(path)):
        return RecordingError(f"disk full while writing {path}")
    why = os.strerror(exc.errno) if exc.errno else " ".join(str(exc).split())
    return RecordingError(f"cannot write {path}: {why}")


def _check_format(fmt: str) -> str:
    fmt = fmt.lower()
    if fmt not in FORMATS:
        raise ConfigError(f"--format: unknown {fmt!r} (valid: {', '.join(FORMATS)})")
    return fmt


def _write_records(records: list[PairRecord], info: dict, fmt: str, out: Path) -> tuple[int, int]:
    if fmt == "netcdf":
        if not records:
            raise RecordingError("no complete pairs in the recording(s): nothing to export")
        write_netcdf(records, info, out)
        return sum(max(1, len(r.height_m)) for r in records), len(records)
    from types import SimpleNamespace

    # an explicit --out is replaced, whole: written beside it and renamed over it (a full disk
    # or Ctrl-C leaves the older file; it was unlinked first and then written in place)
    try:
        with atomic_write(out) as tmp:
            with LayerExporter(tmp, SimpleNamespace(altitude_m=info["altitude_m"]), fmt=fmt,
                               diagnostics=_all_diagnostics(records)) as exp:
                for r in records:
                    exp.write_record(r)
                n = exp.rows_written
    except OSError as exc:
        raise write_error(out, exc) from None
    except RecordingError as exc:  # the exporter names its file: the temporary one
        raise RecordingError(str(exc).replace(str(tmp), str(out))) from None
    return n, len(records)


def export_sessions(paths, fmt: str, out) -> tuple[int, int]:
    """Export sessions to ``out`` in ``fmt`` (csv, parquet, netcdf). Returns (rows, time steps)."""
    fmt = _check_format(fmt)
    out = Path(out)
    if out.is_dir():
        raise RecordingError(f"--out {out}: is a directory; give a file name (or --daily for one file per "
                             "UTC day in it)")
    if not out.parent.is_dir():
        raise RecordingError(f"output directory does not exist: {out.parent}")
    records, info = session_records(paths)
    return _write_records(records, info, fmt, out)


SUFFIXES = {"csv": ".csv", "parquet": ".parquet", "netcdf": ".nc"}


def daily_file_name(station: str, day: str, fmt: str) -> str:
    """E-PROFILE-style daily file name ``cbh_<station>_<YYYYMMDD>.<ext>`` (station name made file-safe).

    ``day`` is ``YYYYMMDD`` (the keys of :func:`daily_groups`); ``fmt`` a key of :data:`SUFFIXES`
    (``"json"`` gives the sidecar name ``cbh reprocess`` writes next to the data files).
    """
    safe = re.sub(r"[^A-Za-z0-9_.-]", "_", str(station))
    return f"cbh_{safe}_{day}{SUFFIXES.get(fmt, '.' + fmt)}"


def export_daily(paths, fmt: str, out_dir) -> list[tuple[Path, int, int]]:
    """One file per UTC day, like E-PROFILE's daily files: ``OUT_DIR/cbh_<station>_<YYYYMMDD>.<ext>``.

    Sessions may span midnight or several days; every pair goes to the file of its capture day
    (existing files of those days are replaced). Returns (path, rows, time steps) per file.
    """
    fmt = _check_format(fmt)
    out_dir = Path(out_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise RecordingError(f"--daily needs a directory for --out, got the file {out_dir}")
    if not out_dir.parent.is_dir():
        raise RecordingError(f"output directory does not exist: {out_dir.parent}")
    out_dir.mkdir(exist_ok=True)
    records, info = session_records(paths)
    if not records:
        raise RecordingError("no complete pairs in the recording(s): nothing to export")
    done = []
    for day, recs in daily_groups(records).items():
        path = out_dir / daily_file_name(info["station"], day, fmt)
        rows, steps = _write_records(recs, info, fmt, path)
        done.append((path, rows, steps))
    return done


# --- one batch of records, atomically (cbh reprocess: one file per station and day) -------

def write_records(records: list[PairRecord], info: dict, out, fmt: str) -> Path:
    """Write pair records (e.g. one station-day) to ``out`` as ``parquet`` or ``netcdf``, atomically.

    The file is written under a temporary name in the same folder and renamed over ``out``
    (``os.replace``), so ``out`` is either absent, the previous file, or complete: a crash or
    Ctrl-C never leaves a half-written export. The contents are those of ``cbh export``
    (:func:`layer_table` columns with the records' diagnostics; :func:`netcdf_dataset`), written
    in one go. NetCDF needs at least one record (:class:`RecordingError` otherwise); an empty
    Parquet table has the columns and no rows.

    Returns
    -------
    Path
        ``out``.
    """
    fmt = _check_format(fmt)
    if fmt not in ("parquet", "netcdf"):
        raise ConfigError(f"write_records: format {fmt!r} (parquet or netcdf)")
    if fmt == "netcdf" and not records:
        raise RecordingError("write_records: no pair records: nothing to write to NetCDF")
    out = Path(out)
    if fmt == "netcdf":
        write_netcdf(records, info, out)  # atomic itself
        return out
    import pyarrow.parquet as pq

    diag = _all_diagnostics(records)
    try:
        with atomic_write(out) as tmp:
            pq.write_table(_arrow_table([row for r in records for row in record_rows(r, diag)], diag), str(tmp))
    except OSError as exc:
        raise write_error(out, exc) from None
    return out
