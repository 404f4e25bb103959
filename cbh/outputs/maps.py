"""Cloud and shadow maps on the ground, written as CF NetCDF grids or pysteps-ready NPZ.

The maps themselves are computed by :mod:`cbh.geometry.ground` (wired by
:mod:`cbh.actions.export`); this module only holds them (:class:`GroundMaps`) and writes them.

NetCDF (``--format netcdf``), CF-1.8:

=================================  ==================================================================
``cloud_map(time, y, x)``          byte: 1 cloud overhead in some layer, 0 clear, fill −1 unknown
                                   (product ``cloudmap``)
``layer_cloud_map(time, layer,     byte: the same per layer (each layer drawn at its own height)
y, x)``                            (product ``cloudmap``)
``shadow_map(time, y, x)``         byte: 1 cloud shadow on the ground, 0 sunlit, fill −1 unknown
                                   (product ``shadow``)
``sun_blocked(time, lead_time)``   byte: is the sun behind cloud at the station now and after
                                   ``lead_time`` = 0, 60, 300, 600 s if the layers' motion holds
``layer_height(time, layer)``      m above ground; ``layer_motion_east/north`` [m s-1]
``sun_zenith``, ``sun_azimuth``    degree, per time
``x``, ``y``                       projection_x/y_coordinate [m] east/north of the station;
                                   ``lat(y, x)``, ``lon(y, x)``; grid mapping ``crs``
                                   (azimuthal equidistant about the station)
=================================  ==================================================================

NPZ (``--format npz``), for pysteps-style nowcasting (``pysteps.extrapolation``):
``field`` (time, m, n) float32 (1 / 0 / NaN unknown; rows = y ascending, i.e. ``yorigin =
"lower"``), ``motion`` (2, m, n) float32 in grid cells per time step at the last time
(``motion[0]`` along x = east = columns, ``motion[1]`` along y = north = rows), ``timestep_s``,
``x_m``, ``y_m``, ``lat``, ``lon``, ``time_unix_s``, ``sun_blocked`` (time, 4), ``lead_s`` and
``metadata`` (a JSON string with pysteps' keys: ``projection``, ``x1``, ``x2``, ``y1``, ``y2``,
``xpixelsize``, ``ypixelsize``, ``yorigin``, ``unit``, plus ``product`` and ``motion_known``).
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from cbh.errors import ConfigError
from cbh.fileio import atomic_write
from cbh.geometry.ground import GroundGrid
from cbh.outputs.export import write_error

__all__ = ["GroundMaps", "to_byte", "to_float", "PRODUCTS", "MAP_FORMATS", "LEAD_TIMES_S", "write_maps_netcdf", "write_maps_npz",
           "pysteps_motion"]

PRODUCTS = ("cloudmap", "shadow")
MAP_FORMATS = ("netcdf", "npz")
LEAD_TIMES_S = (0.0, 60.0, 300.0, 600.0)


@dataclass
class GroundMaps:
    """Cloud and shadow maps of T pairs with up to L layers on an n × n grid.

    Attributes
    ----------
    grid : GroundGrid
    times : list of datetime (T,)
    layer_cloud : ndarray (T, L, n, n) int8 — 1 / 0 / −1 unknown per layer (−1 also for absent
        layers); shape (T, 0, 0, 0) when the cloud map was not computed
    cloud : ndarray (T, n, n) int8 — cloud overhead in any layer (or (T, 0, 0))
    shadow : ndarray (T, n, n) int8 — 1 shaded, 0 sunlit, −1 unknown (or (T, 0, 0))
    layer_height_m : ndarray (T, L) float64, NaN = no such layer
    layer_cover : ndarray (T, L) float64
    motion_ms : ndarray (T, L, 2) float64 — (east, north) [m/s], NaN = unknown
    sun_zenith_deg, sun_azimuth_deg : ndarray (T,) float64
    sun_blocked : ndarray (T, len(LEAD_TIMES_S)) float32 — 1 / 0 / NaN
    shadow_layer : ndarray (T, n, n) int8 — lowest layer shading the cell, −1 none
    station : str
    attrs : dict — global attributes (institution … from [station.metadata])
    """

    grid: GroundGrid
    times: list
    layer_cloud: np.ndarray
    cloud: np.ndarray
    shadow: np.ndarray
    layer_height_m: np.ndarray
    layer_cover: np.ndarray
    motion_ms: np.ndarray
    sun_zenith_deg: np.ndarray
    sun_azimuth_deg: np.ndarray
    sun_blocked: np.ndarray
    shadow_layer: np.ndarray
    station: str
    attrs: dict


def to_byte(a: np.ndarray) -> np.ndarray:
    """1 / 0 / NaN float map → int8 1 / 0 / −1 (unknown); int8 input is returned as is."""
    a = np.asarray(a)
    if a.dtype == np.int8:
        return a
    out = np.full(a.shape, -1, np.int8)
    out[a == 0] = 0
    out[a == 1] = 1
    return out


def to_float(a: np.ndarray) -> np.ndarray:
    """int8 1 / 0 / −1 map → float32 1 / 0 / NaN."""
    out = np.asarray(a, np.float32).copy()
    out[out < 0] = np.nan
    return out


def write_maps_netcdf(maps: GroundMaps, product: str, out) -> None:
    """CF-1.8 grids (time, y, x) of ``product`` (cloudmap or shadow) to ``out``."""
    import pandas as pd
    import xarray as xr

    if product not in PRODUCTS:
        raise ConfigError(f"--product: unknown {product!r} (valid: layers, {', '.join(PRODUCTS)})")
    g = maps.grid
    lat, lon = g.lat_lon()
    T, L = maps.layer_height_m.shape
    times = pd.DatetimeIndex(maps.times).tz_convert("UTC").tz_localize(None).values.astype("datetime64[ns]")
    flag = {"flag_values": np.array([0, 1], np.int8), "units": "1"}
    gm = {"grid_mapping": "crs"}
    data_vars = {
        "crs": ((), np.int32(0), {
            "grid_mapping_name": "azimuthal_equidistant", "latitude_of_projection_origin": g.latitude_deg,
            "longitude_of_projection_origin": g.longitude_deg, "false_easting": 0.0, "false_northing": 0.0,
            "comment": "local east/north metres about the station's ENU origin (tangent plane; within ~3 m of "
                       "azimuthal equidistant at 6 km)"}),
        "sun_blocked": (("time", "lead_time"), to_byte(maps.sun_blocked), dict(
            long_name="sun behind cloud at the station, now and after lead_time if the layer motion holds",
            flag_meanings="sun_visible sun_blocked", **flag)),
        "layer_height": (("time", "layer"), maps.layer_height_m, {
            "long_name": "cloud layer base height above ground used for the maps", "units": "m"}),
        "layer_motion_east": (("time", "layer"), maps.motion_ms[..., 0], {
            "long_name": "eastward motion of the cloud layer over the ground", "units": "m s-1"}),
        "layer_motion_north": (("time", "layer"), maps.motion_ms[..., 1], {
            "long_name": "northward motion of the cloud layer over the ground", "units": "m s-1"}),
        "sun_zenith": (("time",), maps.sun_zenith_deg, {"standard_name": "solar_zenith_angle", "units": "degree"}),
        "sun_azimuth": (("time",), maps.sun_azimuth_deg, {"standard_name": "solar_azimuth_angle", "units": "degree"}),
    }
    if product == "cloudmap":
        data_vars["cloud_map"] = (("time", "y", "x"), to_byte(maps.cloud), dict(
            long_name="cloud overhead in any layer (camera 1's cloud mask projected to each layer's height)",
            flag_meanings="clear cloud", **flag, **gm))
        data_vars["layer_cloud_map"] = (("time", "layer", "y", "x"), to_byte(maps.layer_cloud), dict(
            long_name="cloud of the layer overhead (drawn at the layer's height)", flag_meanings="clear cloud",
            **flag, **gm))
    else:
        data_vars["shadow_map"] = (("time", "y", "x"), to_byte(maps.shadow), dict(
            long_name="cloud shadow on the ground (along the sun direction)", flag_meanings="sunlit shaded",
            **flag, **gm))
    coords = {
        "time": ("time", times, {"standard_name": "time", "long_name": "capture time (UTC)", "axis": "T"}),
        "layer": ("layer", np.arange(1, L + 1, dtype=np.int32), {"long_name": "cloud layer, 1 = lowest", "units": "1"}),
        "lead_time": ("lead_time", np.array(LEAD_TIMES_S), {"standard_name": "forecast_period", "units": "s"}),
        "y": ("y", g.y_m, {"standard_name": "projection_y_coordinate", "long_name": "north of the station",
                           "units": "m", "axis": "Y"}),
        "x": ("x", g.x_m, {"standard_name": "projection_x_coordinate", "long_name": "east of the station",
                           "units": "m", "axis": "X"}),
        "lat": (("y", "x"), lat, {"standard_name": "latitude", "units": "degrees_north"}),
        "lon": (("y", "x"), lon, {"standard_name": "longitude", "units": "degrees_east"}),
    }
    attrs = {
        "Conventions": "CF-1.8",
        "title": f"Cloud {'map' if product == 'cloudmap' else 'shadow map'} on the ground, station {maps.station}",
        "history": f"{datetime.now(timezone.utc).strftime('%Y-%m-%dT%H:%M:%SZ')} created by cbh export --product {product}",
        "source": "cbh: camera 1's cloud mask projected per layer (cbh.geometry.ground)",
        "station_name": maps.station,
        **maps.attrs,
    }
    ds = xr.Dataset(data_vars=data_vars, coords=coords, attrs=attrs)
    enc = {name: {"_FillValue": None} for name in ("crs", "layer", "lead_time", "x", "y", "lat", "lon",
                                                    "sun_zenith", "sun_azimuth")}
    for name in ("cloud_map", "sun_blocked", "layer_cloud_map", "shadow_map"):
        if name in ds:
            enc[name] = {"_FillValue": np.int8(-1), "zlib": True, "complevel": 4}
    for name in ("layer_height", "layer_motion_east", "layer_motion_north"):
        enc[name] = {"_FillValue": -9999.0}
    enc["time"] = {"units": "seconds since 1970-01-01 00:00:00", "calendar": "standard", "dtype": "float64",
                   "_FillValue": None}
    try:
        with atomic_write(out) as tmp:
            ds.to_netcdf(tmp, engine="netcdf4", encoding=enc)
    except OSError as exc:
        raise write_error(out, exc) from None


def pysteps_motion(maps: GroundMaps, product: str, i: int, timestep_s: float) -> tuple[np.ndarray, bool]:
    """Motion field (2, n, n) in grid cells per time step at time index ``i``.

    Each cell moves with the layer that makes it cloudy (cloudmap: the lowest layer with cloud
    overhead; shadow: the lowest layer casting the shadow); other cells with the cover-weighted
    mean motion of the layers whose motion is known. Unknown motion everywhere gives zeros and
    ``known = False``.
    """
    n = maps.grid.n
    v = maps.motion_ms[i]  # (L, 2)
    cov = np.nan_to_num(maps.layer_cover[i])
    ok = np.isfinite(v).all(axis=1) & np.isfinite(maps.layer_height_m[i])
    out = np.zeros((2, n, n), np.float32)
    if not ok.any():
        return out, False
    w = cov[ok] if cov[ok].sum() > 0 else np.ones(int(ok.sum()))
    mean = (v[ok] * w[:, None]).sum(axis=0) / w.sum()
    field = np.broadcast_to(mean[:, None, None], (2, n, n)).copy()
    if product == "shadow":
        owner = maps.shadow_layer[i]
    else:
        owner = np.full((n, n), -1, np.int16)
        for k in range(maps.layer_cloud.shape[1] - 1, -1, -1):  # lowest layer last: it wins
            owner[maps.layer_cloud[i, k] == 1] = k
    for k in np.flatnonzero(ok):
        sel = owner == k
        field[0][sel], field[1][sel] = v[k, 0], v[k, 1]
    scale = timestep_s / maps.grid.resolution_m
    return (field * scale).astype(np.float32), True


def write_maps_npz(maps: GroundMaps, product: str, out) -> None:
    """pysteps-ready arrays of ``product`` to ``out`` (see the module docstring)."""
    if product not in PRODUCTS:
        raise ConfigError(f"--product: unknown {product!r} (valid: layers, {', '.join(PRODUCTS)})")
    g = maps.grid
    t = np.array([tt.timestamp() for tt in maps.times], np.float64)
    timestep_s = float(np.median(np.diff(t))) if len(t) > 1 else 60.0
    if not timestep_s > 0 or not math.isfinite(timestep_s):
        timestep_s = 60.0
    field = to_float(maps.cloud if product == "cloudmap" else maps.shadow)
    motion, known = pysteps_motion(maps, product, len(t) - 1, timestep_s)
    lat, lon = g.lat_lon()
    half = g.resolution_m / 2
    meta = {
        "projection": f"+proj=aeqd +lat_0={g.latitude_deg} +lon_0={g.longitude_deg} +x_0=0 +y_0=0 +ellps=WGS84 +units=m",
        "x1": float(g.x_m[0] - half), "x2": float(g.x_m[-1] + half),
        "y1": float(g.y_m[0] - half), "y2": float(g.y_m[-1] + half),
        "xpixelsize": g.resolution_m, "ypixelsize": g.resolution_m, "yorigin": "lower",
        "unit": "1 = cloud" if product == "cloudmap" else "1 = shadow", "product": product,
        "timestep_s": timestep_s, "motion_units": "grid cells per time step", "motion_known": known,
        "station": maps.station,
    }
    try:
        with atomic_write(out) as tmp, open(tmp, "wb") as fh:
            np.savez_compressed(
                fh, field=field.astype(np.float32), motion=motion, timestep_s=np.float64(timestep_s),
                x_m=g.x_m, y_m=g.y_m, lat=lat, lon=lon, time_unix_s=t,
                sun_blocked=maps.sun_blocked.astype(np.float32), lead_s=np.array(LEAD_TIMES_S),
                layer_height_m=maps.layer_height_m, motion_ms=maps.motion_ms, metadata=np.array(json.dumps(meta)))
    except OSError as exc:
        raise write_error(out, exc) from None
