"""Irradiance nowcast at ground sites: from recorded layers to global horizontal irradiance.

For each recorded pair (the issue time t), each site and each lead time L:

1. **The sun** at ``t + L`` from cbh's one sun function (:func:`cbh.geometry.sun.sun_position`).
2. **Clear-sky GHI** at the site from pvlib: Ineichen–Perez with pvlib's climatological Linke
   turbidity for the place and month (``Location.get_clearsky(model="ineichen")``, pvlib's default).
3. **Shade** (:func:`shade_probability`): the cloud that will be on the sun ray from the site at
   ``t + L`` is, now, on each layer k at ``site + s_xy·(h_k − z_site)/s_z − v_k·L`` (frozen cloud
   carried by the layer's motion v_k; ``s`` the sun direction at ``t + L``). Camera 1's layer labels
   (:func:`cbh.geometry.ground.layer_labels`: each cloud pixel on its layer, clear sky, unknown)
   are read on a disk around that point, Gaussian-weighted with a radius that grows with the lead
   (the motion's error, ``MOTION_ERROR``, times L, plus ``EDGE_M`` and ``EDGE_RANGE`` of the slant
   range: the sun's width and a 1 % height error): the weighted cloud share of
   the known samples is the layer's probability of shading the site, and the layers combine as
   independent screens, ``1 − Π(1 − p_k)``. Where the disk is mostly unknown (the masked sun
   itself at short leads), it widens (``WIDEN``) to the nearest sky the camera sees around it.
   Where the point leaves the camera's view, or lies beyond ``MAX_ZENITH_DEG`` (low sun, long
   leads, fast wind), the lead has no forecast and says so (flag ``beyond_view``), as it does
   without the layer's motion (``motion_unknown``).
4. **GHI** = clear-sky GHI × the clear-sky index of the shade state:
   ``k = k_sun + (k_shade − k_sun)·p``. The two levels default to ``K_SUN`` and ``K_SHADE``; with
   a pyranometer they are learned online (:class:`Levels`): a least-squares line of the measured
   index against the lead-0 shade probability over the issue times so far (never a later one),
   drawn towards the defaults with the weight of ``PRIOR_WEIGHT`` observations.

The measure of the field is skill against *smart persistence*: the clear-sky index measured at
the issue time, carried forward (``benchmarks/eval_irradiance.py``).
"""
from __future__ import annotations

import csv
import math
import re
from dataclasses import dataclass, field
from datetime import datetime, timedelta, timezone
from pathlib import Path

import numpy as np

from cbh.errors import ConfigError, InputError

__all__ = ["Site", "parse_site", "parse_leads", "clear_sky_ghi", "shade_probability", "Levels", "read_pyranometer",
           "LEADS_S", "K_SUN", "K_SHADE"]

#: Default lead times: 0 to 20 min every minute [s].
LEADS_S = tuple(float(s) for s in range(0, 1201, 60))
K_SUN = 1.0  # clear-sky index with the sun unobstructed (default level)
K_SHADE = 0.45  # clear-sky index in a cloud's shadow (default level; thin altocumulus lets more through)
PRIOR_WEIGHT = 3.0  # the default levels count as this many pyranometer observations
EDGE_M = 10.0  # the shade disk's radius at lead 0 [m] ...
EDGE_RANGE = 0.01  # ... plus this share of the slant range to the layer: the sun's width (0.5°) and a 1 % height error
MOTION_ERROR = (0.05, 0.2)  # a layer's motion is known to 5 % + 0.2 m/s: the disk grows by this × lead
WIDEN = (2.0, 4.0, 8.0, 16.0)  # the disk widens by these factors until a third of it is known
MIN_KNOWN = 0.3  # known share of the disk's weight needed for a probability
#: The map ends here [deg from camera 1's zenith]: further out a layer is seen edge-on, its gaps
#: close up in perspective and the cloud mask reads every sky overcast (on the real Fehmarn deck the
#: shade probability went to 1 at 15–20 min leads, 20–24 km upwind, while the sun shone).
MAX_ZENITH_DEG = 65.0
_RINGS = ((0.0, 1), (0.5, 6), (1.0, 12), (1.5, 18), (2.0, 24))  # (radius in σ, points): 61 samples


def _pattern() -> tuple[np.ndarray, np.ndarray]:
    pts, w = [], []
    for r, n in _RINGS:
        for j in range(n):
            a = 2.0 * math.pi * (j + 0.5 * (r > 0)) / n
            pts.append((r * math.cos(a), r * math.sin(a)))
            w.append(math.exp(-0.5 * r * r))
    return np.asarray(pts), np.asarray(w)


_UNIT, _WEIGHT = _pattern()


@dataclass(frozen=True)
class Site:
    """A ground site: its name, WGS 84 position and ENU position about the station [m]."""

    name: str
    latitude_deg: float
    longitude_deg: float
    altitude_m: float
    enu_m: np.ndarray = field(compare=False)


def parse_site(text: str, station, index: int = 0) -> Site:
    """``LAT,LON[,ALT_M]`` or ``NAME=LAT,LON[,ALT_M]`` (ALT above sea level; default the
    station's) → :class:`Site` in the station's ENU frame (pymap3d, WGS 84)."""
    import pymap3d

    name, sep, rest = str(text).partition("=")
    if not sep:
        name, rest = f"site{index + 1}", name
    try:
        vals = [float(v) for v in rest.split(",")]
    except ValueError:
        raise ConfigError(f"--site {text!r}: expected LAT,LON[,ALT_M] in degrees and metres") from None
    if len(vals) not in (2, 3) or not all(math.isfinite(v) for v in vals):
        raise ConfigError(f"--site {text!r}: expected LAT,LON[,ALT_M] in degrees and metres")
    lat, lon = vals[0], vals[1]
    alt = vals[2] if len(vals) == 3 else float(station.altitude_m)
    if not (-90.0 <= lat <= 90.0 and -180.0 <= lon <= 360.0 and -500.0 <= alt <= 9000.0):
        raise ConfigError(f"--site {text!r}: latitude -90..90, longitude -180..360, altitude -500..9000 m")
    e, n, u = pymap3d.geodetic2enu(lat, lon, alt, station.latitude_deg, station.longitude_deg, station.altitude_m)
    enu = np.array([float(e), float(n), float(u)])
    if float(np.hypot(enu[0], enu[1])) > 50_000.0:
        raise ConfigError(f"--site {text!r}: {np.hypot(enu[0], enu[1]) / 1000:.0f} km from the station; its "
                          "cameras do not see the sky over it")
    return Site(name.strip() or f"site{index + 1}", lat, lon, alt, enu)


def parse_leads(text: str | None) -> tuple[float, ...]:
    """``--leads`` as minutes: ``0,1,5,10`` or ``0:20`` (every minute) or ``0:20:5``; default 0–20 min."""
    if not text:
        return LEADS_S
    out = []
    try:
        for part in str(text).split(","):
            if ":" in part:
                a, b, *st = (float(x) for x in part.split(":"))
                step = st[0] if st else 1.0
                if step <= 0:
                    raise ValueError
                out += list(np.arange(a, b + 1e-9, step))
            else:
                out.append(float(part))
    except ValueError:
        raise ConfigError(f"--leads {text!r}: minutes, e.g. 0,1,5,10 or 0:20 or 0:20:5") from None
    if not out or not all(math.isfinite(v) and 0.0 <= v <= 120.0 for v in out):
        raise ConfigError(f"--leads {text!r}: lead times of 0 to 120 minutes")
    return tuple(sorted({round(v * 60.0, 3) for v in out}))


def clear_sky_ghi(site: Site, times) -> np.ndarray:
    """pvlib's Ineichen clear-sky GHI [W/m²] at ``site`` for UTC ``times`` (climatological Linke
    turbidity of the place and month, pvlib's default)."""
    import pandas as pd
    import pvlib

    idx = pd.DatetimeIndex([t.astimezone(timezone.utc).replace(tzinfo=None) for t in times], tz="UTC")
    loc = pvlib.location.Location(site.latitude_deg, site.longitude_deg, altitude=site.altitude_m)
    return np.asarray(loc.get_clearsky(idx, model="ineichen")["ghi"], np.float64)


def _in_view(camera, pts: np.ndarray, shape) -> np.ndarray:
    px = camera.world_to_pixel(pts)
    H, W = shape
    return np.isfinite(px).all(axis=1) & (px[:, 0] >= 0) & (px[:, 0] < W) & (px[:, 1] >= 0) & (px[:, 1] < H)


def _layer_share(pg, k: int, centre: np.ndarray, sigma_m: float) -> tuple[float, bool]:
    """Layer k's weighted cloud share on a disk about ``centre`` (3,) on the layer, widened until
    ``MIN_KNOWN`` of it is known (NaN when never); and whether it had to widen."""
    from cbh.geometry.ground import lookup_layer

    for f in (1.0, *WIDEN):
        pts = np.column_stack([centre[0] + _UNIT[:, 0] * sigma_m * f, centre[1] + _UNIT[:, 1] * sigma_m * f,
                               np.full(len(_UNIT), centre[2])])
        v = lookup_layer(pg.camera, pg.labels, k, pts)
        known = np.isfinite(v)
        if _WEIGHT[known].sum() >= MIN_KNOWN * _WEIGHT.sum():
            return float((_WEIGHT[known] * v[known]).sum() / _WEIGHT[known].sum()), f > 1.0
    return math.nan, True


def shade_probability(pg, site_enu: np.ndarray, sun_dir: np.ndarray | None, lead_s: float) -> tuple[float, str]:
    """:func:`shade_at` without its ``widened``."""
    p, why, _ = shade_at(pg, site_enu, sun_dir, lead_s)
    return p, why


def shade_at(pg, site_enu: np.ndarray, sun_dir: np.ndarray | None, lead_s: float) -> tuple[float, str, bool]:
    """Probability that the sun is behind cloud at ``site_enu`` ``lead_s`` after the pair ``pg``
    (:class:`cbh.actions.pairground.PairGround`), with ``sun_dir`` the unit vector to the sun at
    that time; and why it is NaN (``""`` when it is not): ``night``, ``no_layer`` (cloud but no
    layer height), ``motion_unknown``, ``beyond_view`` (see the module docstring); and whether a
    layer's disk had to widen (the sun's own glare, masked, covered the point)."""
    if sun_dir is None or float(sun_dir[2]) <= 0.02:
        return math.nan, "night", False
    if not pg.heights:
        return ((0.0, "", False) if pg.cloud_fraction == 0 else (math.nan, "no_layer", False))
    s = np.asarray(sun_dir, np.float64)
    p_clear, unknown, widened = 1.0, "", False
    for k, h in enumerate(pg.heights):
        ve, vn = pg.motions[k]
        if lead_s and not (math.isfinite(ve) and math.isfinite(vn)):
            unknown = unknown or "motion_unknown"
            continue
        if not lead_s:
            ve = vn = 0.0
        t = (float(h) - float(site_enu[2])) / s[2]
        if t <= 0:
            continue
        centre = np.array([site_enu[0] + s[0] * t - ve * lead_s, site_enu[1] + s[1] * t - vn * lead_s, float(h)])
        rel = centre - np.asarray(pg.camera.position_m, np.float64)
        if (math.degrees(math.atan2(math.hypot(rel[0], rel[1]), rel[2])) > MAX_ZENITH_DEG
                or not _in_view(pg.camera, centre[None, :], pg.labels.shape)[0]):
            unknown = unknown or "beyond_view"
            continue
        speed = math.hypot(ve, vn)
        slant = float(np.linalg.norm(centre - np.asarray(site_enu, np.float64)))
        sigma = EDGE_M + EDGE_RANGE * slant + (MOTION_ERROR[0] * speed + MOTION_ERROR[1]) * lead_s
        p, wide = _layer_share(pg, k, centre, sigma)
        widened |= wide
        if not math.isfinite(p):
            unknown = unknown or "beyond_view"
            continue
        p_clear *= 1.0 - p
    shade = 1.0 - p_clear
    if unknown and shade < 0.9:  # a known layer that shades it decides; otherwise it is not known
        return math.nan, unknown, widened
    return shade, "", widened


class Levels:
    """The clear-sky index in sun and in shade, learned online from a pyranometer (see the module
    docstring); the defaults without one."""

    def __init__(self, k_sun: float = K_SUN, k_shade: float = K_SHADE, prior_weight: float = PRIOR_WEIGHT):
        self.prior = (float(k_sun), float(k_shade))
        self.w0 = float(prior_weight)
        self._p: list[float] = []
        self._k: list[float] = []

    def add(self, shade_p: float, k_measured: float) -> None:
        """A shade probability forecast for a time now past, and the clear-sky index measured then."""
        if math.isfinite(shade_p) and math.isfinite(k_measured) and 0.0 < k_measured < 2.0:
            self._p.append(float(shade_p))
            self._k.append(float(k_measured))

    @property
    def n(self) -> int:
        return len(self._k)

    def levels(self) -> tuple[float, float]:
        """(k_sun, k_shade): the prior's two points and the observations, one weighted line."""
        ks, kd = self.prior
        p = np.concatenate([[0.0, 1.0], self._p])
        k = np.concatenate([[ks, kd], self._k])
        w = np.concatenate([[self.w0, self.w0], np.ones(len(self._p))])
        X = np.column_stack([np.ones_like(p), p]) * np.sqrt(w)[:, None]
        a, b = np.linalg.lstsq(X, k * np.sqrt(w), rcond=None)[0]
        return float(np.clip(a, 0.7, 1.5)), float(np.clip(a + b, 0.05, 1.2))


_ZONE = re.compile(r"utc(?:([pm])(\d{1,2}))?$", re.IGNORECASE)


def read_pyranometer(path) -> tuple[list[datetime], np.ndarray]:
    """A pyranometer's record: (UTC times, GHI [W/m²]). CSV with a header, comma or semicolon:
    a ``time_utc`` column (ISO 8601), or ``date`` + ``time_utc`` / ``time_utcp1`` / ``time_utcm2``
    (``DD.MM.YYYY`` and ``HH:MM[:SS]``, the zone in the column's name, as the LEX 2016 logger
    writes it); the GHI in ``ghi_wm2``, ``G_wm2``, ``ghi`` or ``G``. Missing or negative GHI: NaN."""
    from cbh.timeutil import parse_utc

    path = Path(path)
    if not path.is_file():
        raise InputError(f"pyranometer file not found: {path}")
    text = path.read_text(encoding="utf-8", errors="replace")
    dialect = ";" if text.split("\n", 1)[0].count(";") > text.split("\n", 1)[0].count(",") else ","
    rows = list(csv.reader(text.splitlines(), delimiter=dialect))
    if len(rows) < 2:
        raise InputError(f"{path}: no pyranometer records")
    head = [h.strip() for h in rows[0]]
    low = [h.lower() for h in head]
    gcol = next((low.index(c) for c in ("ghi_wm2", "g_wm2", "ghi", "g") if c in low), None)
    if gcol is None:
        seen = ", ".join(head)
        seen = seen[:120] if seen.isprintable() and "\ufffd" not in seen else "a header that is not text: is it a CSV file?"
        raise InputError(f"{path}: no GHI column (ghi_wm2, G_wm2, ghi or G) in {seen}")
    tcol = low.index("time_utc") if "time_utc" in low else None
    zcol = next((i for i, h in enumerate(low) if h.startswith("time_utc") and _ZONE.search(h[5:])), None)
    dcol = low.index("date") if "date" in low else None
    if tcol is None and (zcol is None or dcol is None):
        raise InputError(f"{path}: no time column (time_utc, or date with time_utc/time_utcp1/…)")
    shift = timedelta(0)
    if tcol is None:
        m = _ZONE.search(low[zcol][5:])
        if m.group(1):
            shift = timedelta(hours=int(m.group(2)) * (1 if m.group(1).lower() == "p" else -1))
    times, ghi = [], []
    for r in rows[1:]:
        if len(r) <= max(gcol, tcol if tcol is not None else zcol):
            continue
        try:
            if tcol is not None:
                t = parse_utc(r[tcol].strip(), "pyranometer time", InputError)
            else:
                fmt = "%d.%m.%Y %H:%M:%S" if r[zcol].count(":") == 2 else "%d.%m.%Y %H:%M"
                t = datetime.strptime(f"{r[dcol].strip()} {r[zcol].strip()}", fmt).replace(tzinfo=timezone.utc) - shift
            g = float(r[gcol])
        except (ValueError, InputError):
            continue
        times.append(t)
        ghi.append(g if g >= 0 and math.isfinite(g) else math.nan)
    if not times:
        raise InputError(f"{path}: no readable pyranometer record")
    order = np.argsort(np.array([t.timestamp() for t in times]))
    return [times[i] for i in order], np.asarray(ghi, np.float64)[order]


def measured_at(times: list[datetime], ghi: np.ndarray, t: datetime, tolerance_s: float = 90.0) -> float:
    """The pyranometer's GHI nearest to ``t`` within ``tolerance_s`` (NaN otherwise)."""
    if not times:
        return math.nan
    ts = np.array([x.timestamp() for x in times])
    i = int(np.argmin(np.abs(ts - t.timestamp())))
    return float(ghi[i]) if abs(ts[i] - t.timestamp()) <= tolerance_s else math.nan
