"""A drone's flight log, as drones write it, in the station's ENU frame (``cbh validate --drone``).

Two formats are read:

- **DJI's SRT subtitle telemetry**, one subtitle per video frame (parsed with the ``srt``
  library), in the two layouts DJI has written: the bracketed one of the Mavic Air 2 / Mini
  family (a ``YYYY-MM-DD HH:MM:SS.fff`` line and ``[latitude: …] [longitude: …] [rel_alt: …
  abs_alt: …]``) and the older ``GPS(lon,lat,alt) BAROMETER:h`` one with ``YYYY.MM.DD
  HH:MM:SS``. DJI stamps the drone's local time: give its zone (``tz``) when it is not UTC.
- **A CSV** of ``time_utc, latitude, longitude, altitude_m`` (altitude above the take-off
  point), with the column names AirData and Litchi export accepted too (``datetime(utc)``,
  ``altitude(m)``, ``height_above_takeoff(feet)``, …). AirData's one-second ``datetime(utc)``
  is refined with its ``time(millisecond)`` column.

Altitudes are above the take-off point (``rel_alt``, ``BAROMETER``, ``altitude_m``); a log
with only absolute altitudes is taken relative to its first record. Positions go to the
station's ENU frame through ``pymap3d.geodetic2enu`` with the take-off point ``up_m`` metres
above the station's origin (camera 1).
"""
from __future__ import annotations

import csv
import math
import re
from dataclasses import dataclass
from datetime import datetime, timedelta, timezone
from pathlib import Path

import numpy as np

from cbh.errors import ConfigError, InputError

__all__ = ["FlightLog", "Takeoff", "read_flight_log", "parse_takeoff", "parse_tz", "log_enu"]

FEET_M = 0.3048  # [m per ft]


@dataclass(frozen=True)
class FlightLog:
    """A flight log: time-ordered fixes (unique times).

    Attributes
    ----------
    time_utc : ndarray, shape (N,), datetime64[ns]
        The log's own clock, taken as UTC (it may differ from the cameras' by seconds).
    latitude_deg, longitude_deg : ndarray, shape (N,), float64
        WGS 84 [deg].
    up_m : ndarray, shape (N,), float64
        Height above the take-off point [m].
    kind : str
        ``"dji-srt"`` or ``"csv"``.
    """

    time_utc: np.ndarray
    latitude_deg: np.ndarray
    longitude_deg: np.ndarray
    up_m: np.ndarray
    kind: str
    path: Path | None = None

    def seconds(self, t0: np.datetime64) -> np.ndarray:
        """Fix times [s] after ``t0`` (float64)."""
        return (self.time_utc - t0).astype("timedelta64[ns]").astype(np.float64) * 1e-9


@dataclass(frozen=True)
class Takeoff:
    """The take-off point: WGS 84 [deg] and its height above the station's origin [m]."""

    latitude_deg: float
    longitude_deg: float
    up_m: float


def parse_takeoff(text: str) -> Takeoff:
    """``LAT,LON,UP_M`` (``--takeoff``) → :class:`Takeoff`; ConfigError naming what is wrong."""
    parts = [p.strip() for p in str(text).split(",")]
    if len(parts) != 3:
        raise ConfigError(f"--takeoff {text!r}: expected LAT,LON,UP_M (e.g. --takeoff=-15.76,-47.87,-10)")
    try:
        lat, lon, up = (float(p) for p in parts)
    except ValueError:
        raise ConfigError(f"--takeoff {text!r}: LAT,LON,UP_M must be numbers") from None
    if not (-90 <= lat <= 90 and -180 <= lon <= 360 and math.isfinite(up) and abs(up) < 10_000):
        raise ConfigError(f"--takeoff {text!r}: latitude in -90..90, longitude in -180..180, UP_M a height in metres")
    return Takeoff(lat, lon, up)


def parse_tz(text: str | None) -> timezone:
    """``Z``, ``UTC``, ``+02:00``, ``-0530`` → a fixed zone (the log clock's, for DJI's local stamps)."""
    if text is None or text.strip().upper() in ("", "Z", "UTC"):
        return timezone.utc
    m = re.fullmatch(r"([+-])(\d{1,2}):?(\d{2})?", text.strip())
    if not m or int(m.group(2)) > 14 or int(m.group(3) or 0) >= 60:
        raise ConfigError(f"--log-tz {text!r}: expected Z or an offset from UTC such as +02:00")
    sign = 1 if m.group(1) == "+" else -1
    return timezone(sign * timedelta(hours=int(m.group(2)), minutes=int(m.group(3) or 0)))


def read_flight_log(path: str | Path, tz: timezone = timezone.utc) -> FlightLog:
    """Read a DJI SRT or a CSV flight log (by content, not by name); InputError when unreadable."""
    from cbh.fileio import read_input

    path = Path(path)
    raw = read_input(path, "flight log", InputError)
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise InputError(f"flight log {path.name}: not a text file (undecodable byte at offset {exc.start}); "
                         "expected a DJI .SRT or a CSV of time_utc,latitude,longitude,altitude_m") from None
    if "-->" in text[:2000]:
        t, lat, lon, up = _read_srt(text, path.name, tz)
        kind = "dji-srt"
    else:
        t, lat, lon, up = _read_csv(text, path.name, tz)
        kind = "csv"
    return _ordered(FlightLog(t, lat, lon, up, kind, path), path.name)


def _ordered(log: FlightLog, name: str) -> FlightLog:
    if log.time_utc.size < 2:
        raise InputError(f"flight log {name}: {log.time_utc.size} time-stamped fix(es); a flight needs many")
    order = np.argsort(log.time_utc, kind="stable")
    t = log.time_utc[order]
    keep = np.concatenate([[True], np.diff(t) > np.timedelta64(0, "ns")])
    sel = order[keep]
    ok = np.isfinite(log.latitude_deg[sel]) & np.isfinite(log.longitude_deg[sel]) & np.isfinite(log.up_m[sel])
    sel = sel[ok]
    if sel.size < 2:
        raise InputError(f"flight log {name}: no usable fixes (latitude, longitude and altitude all needed)")
    if np.any(np.abs(log.latitude_deg[sel]) > 90) or np.any(np.abs(log.longitude_deg[sel]) > 360):
        raise InputError(f"flight log {name}: latitude or longitude out of range")
    return FlightLog(log.time_utc[sel], log.latitude_deg[sel], log.longitude_deg[sel], log.up_m[sel], log.kind, log.path)


_NUM = r"(-?\d+(?:\.\d+)?)"
_SRT_TIME = re.compile(r"(\d{4})[-./](\d{2})[-./](\d{2})[ T](\d{2}):(\d{2}):(\d{2})(?:[.,:](\d{1,6}))?")
_SRT_FIELDS = {
    "lat": re.compile(r"\[\s*(?:latitude|lat)\s*:\s*" + _NUM, re.I),
    "lon": re.compile(r"\[\s*(?:longitude|longtitude|lon)\s*:\s*" + _NUM, re.I),
    "rel": re.compile(r"rel_alt\s*:\s*" + _NUM, re.I),
    "abs": re.compile(r"(?:abs_alt|\[\s*altitude)\s*:\s*" + _NUM, re.I),
    "gps": re.compile(r"GPS\s*\(\s*" + _NUM + r"\s*,\s*" + _NUM + r"(?:\s*,\s*" + _NUM + r")?\s*\)", re.I),
    "baro": re.compile(r"BAROMETER\s*:\s*" + _NUM, re.I),
}


def _srt_time(text: str, tz: timezone) -> datetime | None:
    m = _SRT_TIME.search(text)
    if not m:
        return None
    y, mo, d, h, mi, s = (int(g) for g in m.groups()[:6])
    us = int((m.group(7) or "0").ljust(6, "0"))
    try:
        return datetime(y, mo, d, h, mi, s, us, tzinfo=tz).astimezone(timezone.utc)
    except ValueError:
        return None


def _srt_fix(content: str) -> tuple[float, float, float, float]:
    """(lat, lon, height above take-off, absolute altitude) of one subtitle; NaN where absent."""
    g = {k: r.search(content) for k, r in _SRT_FIELDS.items()}
    lat = float(g["lat"].group(1)) if g["lat"] else math.nan
    lon = float(g["lon"].group(1)) if g["lon"] else math.nan
    rel = float(g["rel"].group(1)) if g["rel"] else math.nan
    ab = float(g["abs"].group(1)) if g["abs"] else math.nan
    if g["gps"] and not (g["lat"] and g["lon"]):  # GPS(lon, lat, alt) of the older layout
        lon, lat = float(g["gps"].group(1)), float(g["gps"].group(2))
    if g["baro"] and not g["rel"]:
        rel = float(g["baro"].group(1))
    return lat, lon, rel, ab


def _read_srt(text: str, name: str, tz: timezone):
    import srt

    try:
        subs = list(srt.parse(text))
    except (srt.SRTParseError, ValueError) as exc:
        raise InputError(f"flight log {name}: malformed SRT ({type(exc).__name__}: {str(exc)[:80]})") from None
    T, rows = [], []
    for s in subs:
        t = _srt_time(s.content, tz)
        if t is None:
            continue
        T.append(np.datetime64(t.replace(tzinfo=None), "ns"))
        rows.append(_srt_fix(s.content))
    if not rows:
        raise InputError(f"flight log {name}: no subtitle with a date and time: not DJI telemetry "
                         "(expected e.g. '2021-09-05 12:58:09.140 … [latitude: …] [longitude: …] [rel_alt: …]')")
    a = np.array(rows, np.float64)
    up = a[:, 2]
    if np.all(np.isnan(up)):  # only absolute altitudes: above the first record (the take-off)
        first = a[np.isfinite(a[:, 3]), 3]
        if not first.size:
            raise InputError(f"flight log {name}: no altitude (rel_alt, abs_alt or BAROMETER) in the telemetry")
        up = a[:, 3] - first[0]
    return np.array(T), a[:, 0], a[:, 1], up


_CSV_TIME = ("time_utc", "datetime(utc)", "datetime_utc", "datetime", "time", "timestamp")
_CSV_LAT = ("latitude", "lat", "latitude_deg")
_CSV_LON = ("longitude", "lon", "lng", "longitude_deg")
_CSV_ALT = {"altitude_m": 1.0, "altitude(m)": 1.0, "height_above_takeoff(m)": 1.0,
            "height_above_takeoff(meters)": 1.0, "rel_alt": 1.0, "altitude(feet)": FEET_M,
            "height_above_takeoff(feet)": FEET_M, "altitude(ft)": FEET_M}


def _pick(cols: list[str], names, name: str, what: str) -> str:
    low = {c.strip().lower(): c for c in cols}
    for n in names:
        if n in low:
            return low[n]
    raise InputError(f"flight log {name}: no {what} column (expected one of {', '.join(names)}; "
                     f"the columns are {', '.join(cols[:8])})")


def _csv_time(cell: str, tz: timezone) -> datetime:
    s = cell.strip().replace("Z", "+00:00").replace("z", "+00:00")
    t = datetime.fromisoformat(s)
    return (t if t.tzinfo else t.replace(tzinfo=tz)).astimezone(timezone.utc)


def _read_csv(text: str, name: str, tz: timezone):
    try:
        rows = list(csv.reader(text.splitlines()))
    except csv.Error as exc:
        raise InputError(f"flight log {name}: malformed CSV: {exc}") from None
    if len(rows) < 2 or len(rows[0]) < 4:
        raise InputError(f"flight log {name}: not a DJI .SRT nor a CSV of time_utc,latitude,longitude,altitude_m")
    head = [c.strip() for c in rows[0]]
    ct, cla, clo = (_pick(head, n, name, w) for n, w in ((_CSV_TIME, "time"), (_CSV_LAT, "latitude"),
                                                         (_CSV_LON, "longitude")))
    ca = _pick(head, tuple(_CSV_ALT), name, "altitude above take-off")
    scale = _CSV_ALT[ca.strip().lower()]
    idx = {c: head.index(c) for c in (ct, cla, clo, ca)}
    ms_col = next((i for i, c in enumerate(head) if c.lower() == "time(millisecond)"), None)
    T, V, MS = [], [], []
    for i, r in enumerate(rows[1:], start=2):
        if not any(x.strip() for x in r):
            continue
        try:
            T.append(np.datetime64(_csv_time(r[idx[ct]], tz).replace(tzinfo=None), "ns"))
            V.append([float(r[idx[cla]]), float(r[idx[clo]]), float(r[idx[ca]]) * scale])
            if ms_col is not None:
                MS.append(float(r[ms_col]))
        except (ValueError, IndexError):
            raise InputError(f"flight log {name}: row {i}: not a time, latitude, longitude and altitude") from None
    T = np.array(T)
    if MS:  # AirData: whole-second datetimes refined by the running milliseconds
        ms = np.array(MS) * 1e6
        start = (T.astype(np.int64) - ms.astype(np.int64)).max()
        T = (start + ms.astype(np.int64)).astype("datetime64[ns]")
    v = np.array(V, np.float64)
    return T, v[:, 0], v[:, 1], v[:, 2]


def log_enu(log: FlightLog, station, takeoff: Takeoff | None) -> tuple[np.ndarray, list[str]]:
    """The log's fixes in the station's ENU frame [m], (N, 3), and notes on what was assumed.

    Without a take-off point the take-off is taken at the height of the station's origin and the
    note says so; with one, a log that starts far from it is noted (a wrong point or log).
    """
    import pymap3d

    notes = []
    up0 = 0.0 if takeoff is None else takeoff.up_m
    if takeoff is None:
        notes.append("no --takeoff: the take-off point taken at the height of the station's origin (camera 1)")
    e, n, u = pymap3d.geodetic2enu(log.latitude_deg, log.longitude_deg, station.altitude_m + up0 + log.up_m,
                                   station.latitude_deg, station.longitude_deg, station.altitude_m)
    enu = np.stack([np.asarray(e, np.float64), np.asarray(n, np.float64), np.asarray(u, np.float64)], axis=1)
    if takeoff is not None:
        te, tn, _ = pymap3d.geodetic2enu(takeoff.latitude_deg, takeoff.longitude_deg, station.altitude_m,
                                         station.latitude_deg, station.longitude_deg, station.altitude_m)
        d = float(np.hypot(enu[0, 0] - te, enu[0, 1] - tn))
        if d > 50.0:
            notes.append(f"the log starts {d:.0f} m from the --takeoff point: check the point or the log")
    return enu, notes
