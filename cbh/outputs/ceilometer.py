"""Ceilometer-shaped files: cbh's layers as a Vaisala CL61 or an E-PROFILE file, and readers of
real ceilometer files for ``cbh validate``.

Products (:func:`write_product`)
--------------------------------
``cl61`` (Vaisala CL61 NetCDF naming)
    ``cloud_base_heights(time, layer)`` [m above ground, fill −99], ``vertical_visibility(time)``
    [m, −99: cbh sees no obscuration, so always fill], ``sky_condition_total_cloud_cover(time)``,
    ``sky_condition_cloud_layer_covers(time, layer)`` [okta, fill −99] and
    ``sky_condition_cloud_layer_heights(time, layer)`` [m, fill −99], station attributes
    (``latitude``, ``longitude``, ``altitude``, ``site_name``, ``instrument``) as scalars and global
    attributes.
``eprofile`` (E-PROFILE ceilometer naming)
    ``cloud_base_height(time, layer)`` [m above ground], ``cloud_amount(time)`` [okta],
    ``cloud_layer_amount(time, layer)`` [okta], ``station_latitude``, ``station_longitude``,
    ``station_altitude``, ``wigos_station_id`` (global attribute and variable; from
    ``[station.metadata] wigos_station_id``, "" when not given).

Readers (:func:`read_ceilometer`) give :class:`CeiloBases`: times and up to three cloud bases
[m above the instrument], whatever the format:

* ARM ``ceil`` b1 NetCDF (``first_cbh`` …), CL61 NetCDF (``cloud_base_heights``), CHM15k NetCDF
  (``cbh``), E-PROFILE and cbh's own products — read with xarray (netCDF4); these are
  self-describing files, and their variables are taken by their documented names.
* Vaisala CL31/CL51 data messages (``CL01…``/``CL02…`` text, optionally preceded by a
  ``YYYY-MM-DD hh:mm:ss`` time stamp line, as logged by FMI/ACTRIS): ceilopyter (PyPI) frames
  and decodes these messages but keeps only the backscatter profile; the cloud bases are in the
  message's second line (detection status, then three 5-digit bases), parsed here. Bases are
  taken in metres (the research networks' setting); messages without a time stamp cannot be
  placed in time and are skipped (their count is reported).
"""
from __future__ import annotations

import logging
import math
import re
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from cbh.errors import InputError, RecordingError

__all__ = ["PRODUCTS", "FILL", "product_dataset", "write_product", "CeiloBases", "read_ceilometer"]

log = logging.getLogger(__name__)

PRODUCTS = ("cl61", "eprofile")
FILL = -99.0  # CL61 fill value of heights and covers


def _grid(records, attr):
    L = max([1] + [len(getattr(r, attr)) for r in records])
    a = np.full((len(records), L), np.nan)
    for i, r in enumerate(records):
        v = getattr(r, attr)
        a[i, : len(v)] = v
    return a


def _times(records):
    import pandas as pd

    return pd.DatetimeIndex([r.time_utc for r in records]).tz_convert("UTC").tz_localize(None).values.astype(
        "datetime64[ns]")


def product_dataset(records, info: dict, product: str):
    """The xarray Dataset of ``product`` ("cl61" or "eprofile") from layer export records
    (:func:`cbh.outputs.export.session_records`)."""
    import xarray as xr

    from cbh.outputs.export import okta

    if product not in PRODUCTS:
        raise InputError(f"ceilometer product: unknown {product!r} (valid: {', '.join(PRODUCTS)})")
    H = _grid(records, "height_m")
    C = _grid(records, "cover")
    L = H.shape[1]
    ok = np.vectorize(lambda c: okta(c) if math.isfinite(c) else -99)(C).astype(np.int32)
    total = np.array([okta(r.cloud_fraction) if math.isfinite(r.cloud_fraction) else -99 for r in records], np.int32)
    md = info.get("metadata", {}) or {}
    coords = {"time": ("time", _times(records), {"standard_name": "time", "long_name": "time (UTC)", "axis": "T"}),
              "layer": ("layer", np.arange(1, L + 1, dtype=np.int32), {"long_name": "cloud layer, 1 = lowest"})}
    lat, lon, alt = float(info["latitude_deg"]), float(info["longitude_deg"]), float(info["altitude_m"])
    src = f"cbh {info.get('cbh_version', '?')}: two upward fisheye cameras, ray triangulation"
    if product == "cl61":
        Hf = np.where(np.isfinite(H), H, FILL)
        dv = {
            "cloud_base_heights": (("time", "layer"), Hf, {"long_name": "cloud base heights", "units": "m",
                                                          "_FillValue": FILL, "comment": "above ground; layer 1 = lowest"}),
            "vertical_visibility": (("time",), np.full(len(records), FILL), {
                "long_name": "vertical visibility", "units": "m", "_FillValue": FILL,
                "comment": "a sky camera reports no obscuration: always fill"}),
            "sky_condition_total_cloud_cover": (("time",), total, {"long_name": "total cloud cover", "units": "okta",
                                                                   "_FillValue": np.int32(-99)}),
            "sky_condition_cloud_layer_covers": (("time", "layer"), ok, {"long_name": "cloud layer covers",
                                                                        "units": "okta", "_FillValue": np.int32(-99)}),
            "sky_condition_cloud_layer_heights": (("time", "layer"), Hf, {"long_name": "cloud layer heights",
                                                                         "units": "m", "_FillValue": FILL}),
            "latitude": ((), lat, {"units": "degrees_north", "long_name": "latitude"}),
            "longitude": ((), lon, {"units": "degrees_east", "long_name": "longitude"}),
            "altitude": ((), alt, {"units": "m", "long_name": "altitude above mean sea level"}),
        }
        attrs = {"Conventions": "CF-1.8", "title": f"cbh cloud base heights, CL61 naming, station {info['station']}",
                 "instrument": md.get("instrument", "two upward-looking fisheye sky cameras (cbh)"),
                 "site_name": md.get("site", str(info["station"])), "source": src,
                 "latitude": lat, "longitude": lon, "altitude": alt}
    else:
        Hn = np.where(np.isfinite(H), H, np.nan)
        wigos = str(md.get("wigos_station_id", ""))
        dv = {
            "cloud_base_height": (("time", "layer"), Hn, {"long_name": "cloud base height above ground", "units": "m"}),
            "cloud_amount": (("time",), total, {"long_name": "total cloud amount", "units": "okta",
                                                "_FillValue": np.int32(-99)}),
            "cloud_layer_amount": (("time", "layer"), ok, {"long_name": "cloud amount per layer", "units": "okta",
                                                          "_FillValue": np.int32(-99)}),
            "station_latitude": ((), lat, {"units": "degrees_north", "standard_name": "latitude"}),
            "station_longitude": ((), lon, {"units": "degrees_east", "standard_name": "longitude"}),
            "station_altitude": ((), alt, {"units": "m", "standard_name": "altitude"}),
            "wigos_station_id": ((), wigos, {"long_name": "WIGOS station identifier"}),
        }
        attrs = {"Conventions": "CF-1.8", "title": f"cbh cloud base heights, E-PROFILE naming, station {info['station']}",
                 "wigos_station_id": wigos, "site_location": md.get("site", str(info["station"])),
                 "instrument_type": "sky camera pair (cbh)", "source": src}
    ds = xr.Dataset(dv, coords=coords, attrs=attrs)
    return ds


def write_product(records, info: dict, out, product: str) -> None:
    """Write :func:`product_dataset` to ``out`` (NetCDF4, atomically)."""
    from cbh.fileio import atomic_write
    from cbh.outputs.export import write_error

    ds = product_dataset(records, info, product)
    enc = {"time": {"units": "seconds since 1970-01-01 00:00:00", "calendar": "standard", "dtype": "float64"}}
    for name, var in ds.data_vars.items():
        if "_FillValue" in var.attrs:
            enc[name] = {"_FillValue": var.attrs.pop("_FillValue")}
        elif var.dtype.kind == "f":
            enc[name] = {"_FillValue": None if var.ndim == 0 else np.nan}
    try:
        with atomic_write(out) as tmp:
            ds.to_netcdf(tmp, engine="netcdf4", encoding=enc)
    except OSError as exc:
        raise write_error(Path(out), exc) from None


# --- readers ---------------------------------------------------------------------------

@dataclass
class CeiloBases:
    """Cloud bases of a ceilometer file: ``time_utc`` (T,) datetime64[ns] UTC, ``bases_m``
    (T, 3) float64 above the instrument [m], NaN = no base; ``obscured`` (T,) bool (vertical
    visibility reported instead of a base); ``kind``: the format read."""

    time_utc: np.ndarray
    bases_m: np.ndarray
    obscured: np.ndarray
    kind: str
    skipped: int = 0  # messages that could not be placed in time


def _classic_complete(path: Path) -> None:
    """A classic (CDF-1/2) NetCDF file holds every byte its header declares, or InputError.

    A classic file cut short still opens: the missing data read back as fill (time 00:00, base
    0), and a half file was "0 of 6 pairs matched" instead of an error. scipy's reader checks
    each variable's extent against the bytes present."""
    from scipy.io import netcdf_file

    try:
        with netcdf_file(path, "r", mmap=False):
            pass
    except ValueError as exc:
        raise InputError(f"{path}: a truncated NetCDF file: its header declares more data than the file holds "
                         f"({exc}); was it cut short in a copy or a download?") from None
    except (OSError, TypeError) as exc:  # not classic after all: xarray judges it
        log.debug("classic NetCDF check skipped for %s: %s", path, exc)


def _nc_bases(path: Path) -> CeiloBases:
    import xarray as xr

    with open(path, "rb") as fh:
        if fh.read(3) == b"CDF":
            _classic_complete(path)
    try:
        ds = xr.open_dataset(path, decode_timedelta=False)
    except Exception as exc:  # xarray/netCDF4 raise many kinds for a foreign file
        raise InputError(f"{path}: not a readable NetCDF file ({type(exc).__name__}: {exc})") from None
    with ds:
        t = np.asarray(ds["time"].values).astype("datetime64[ns]") if "time" in ds else None
        if t is None:
            raise InputError(f"{path}: no time variable: not a ceilometer file")
        obsc = np.zeros(t.size, bool)
        if "first_cbh" in ds:  # ARM ceil b1
            cols = [np.asarray(ds[v].values, np.float64) for v in ("first_cbh", "second_cbh", "third_cbh") if v in ds]
            b = np.column_stack(cols)
            if "detection_status" in ds:
                ds_ = np.asarray(ds["detection_status"].values)
                obsc = (ds_ == 4)
            kind = "ARM ceil NetCDF"
        elif "cloud_base_heights" in ds:  # CL61 (and cbh's cl61)
            b = np.asarray(ds["cloud_base_heights"].values, np.float64).reshape(t.size, -1)
            kind = "CL61 NetCDF"
        elif "cloud_base_height" in ds:  # E-PROFILE (and cbh's eprofile)
            b = np.asarray(ds["cloud_base_height"].values, np.float64).reshape(t.size, -1)
            kind = "E-PROFILE NetCDF"
        elif "cbh" in ds:  # Lufft CHM15k
            b = np.asarray(ds["cbh"].values, np.float64).reshape(t.size, -1)
            kind = "CHM15k NetCDF"
        else:
            raise InputError(f"{path}: no cloud base variable (first_cbh, cloud_base_heights, cloud_base_height, cbh)")
    b = np.where(np.isfinite(b) & (b > 0), b, np.nan)
    out = np.full((t.size, 3), np.nan)
    k = min(3, b.shape[1])
    out[:, :k] = b[:, :k]
    return CeiloBases(t, out, obsc, kind)


_STAMP = re.compile(rb"^-?(\d{4}-\d\d-\d\d[ T]\d\d:\d\d:\d\d(?:\.\d+)?)")
_HEADER = re.compile(rb"\x01?CL\d{3}\d\d\d")
_LINE2 = re.compile(rb"^\s*([0-9/])([0-9A-Z/])\s+([0-9/]{5})\s+([0-9/]{5})\s+([0-9/]{5})")


def _cl_bases(path: Path) -> CeiloBases:
    """CL31/CL51 data messages (see the module docstring)."""
    try:
        lines = path.read_bytes().splitlines()
    except OSError as exc:
        raise InputError(f"{path}: cannot read ({exc.strerror})") from None
    times, rows, obsc = [], [], []
    skipped = 0
    stamp = None
    for i, line in enumerate(lines):
        m = _STAMP.match(line.strip())
        if m:
            stamp = m.group(1).decode()
        hdr = _HEADER.search(line)
        if not hdr or i + 1 >= len(lines):
            continue
        m2 = _LINE2.match(lines[i + 1])
        if not m2:
            continue
        if stamp is None:
            skipped += 1
            continue
        status = m2.group(1).decode()
        vals = [float(v) if v.isdigit() else math.nan for v in (g.decode() for g in m2.group(3, 4, 5))]
        if status == "4":  # full obscuration: vertical visibility, then highest signal
            row = [math.nan] * 3
        elif status in "123":
            row = [vals[j] if j < int(status) else math.nan for j in range(3)]
        else:
            row = [math.nan] * 3
        times.append(np.datetime64(stamp.replace(" ", "T"), "ns"))
        rows.append(row)
        obsc.append(status == "4")
        stamp = None
    if not rows and not skipped:
        raise InputError(f"{path}: no CL31/CL51 data message found")
    return CeiloBases(np.array(times, "datetime64[ns]"), np.array(rows, np.float64).reshape(-1, 3),
                      np.array(obsc, bool), "Vaisala CL message", skipped)


def read_ceilometer(path) -> CeiloBases:
    """Cloud bases of one ceilometer file, NetCDF (by its variables) or CL31/CL51 messages."""
    path = Path(path)
    if path.is_dir():
        raise InputError(f"ceilometer file {path}: is a directory; give the files in it (e.g. {path}/*.nc)")
    if not path.is_file():
        raise InputError(f"ceilometer file not found: {path}")
    with open(path, "rb") as fh:
        head = fh.read(8)
    if head[:3] == b"CDF" or head[:8] == b"\x89HDF\r\n\x1a\n":
        return _nc_bases(path)
    return _cl_bases(path)
