"""Irradiance nowcast at ground sites: from recorded layers to global horizontal irradiance.

For each recorded pair (the issue time t), each site and each lead time L:

1. **The sun** at ``t + L`` from cbh's one sun function (:func:`cbh.geometry.sun.sun_position`).
2. **Clear-sky GHI** at the site from pvlib: Ineichen–Perez with pvlib's climatological Linke
   turbidity for the place and month (``Location.get_clearsky(model="ineichen")``, pvlib's default).
3. **Shade** (:func:`shade_probability`): the cloud that will be on the sun ray from the site at
   ``t + L`` is, now, on each layer k at ``site + s_xy·(h_k − z_site)/s_z − v_k·L`` (frozen cloud
   carried by the layer's motion v_k; ``s`` the sun direction at ``t + L``). Camera 1's layer labels
   (:func:`cbh.geometry.ground.layer_labels`: each cloud pixel on its layer, clear sky, unknown)
   are read on a disk around that point, Gaussian-weighted with a σ that grows with the lead
   (:func:`read_sigma_m`: independent errors added in quadrature: the map's own ``EDGE_M``, the
   sun's disk, the height error, which moves the read by ``HEIGHT_ERROR`` of the site's distance
   from camera 1 whatever the lead, and the motion's error times L, measured as the scatter of the
   layer's motion over every valid pair of the last ``ENSEMBLE_S``, :func:`motion_errors`, else
   the prior ``MOTION_ERROR``): the weighted cloud share of
   the known samples is the layer's probability of shading the site, and the layers combine as
   independent screens, ``1 − Π(1 − p_k)``. Where the disk is mostly unknown (the masked sun
   itself at short leads), it widens (``WIDEN``, ``WIDEN_FROM``) to the nearest sky the camera
   sees around it.
   Where the point leaves the camera's view, or lies beyond the layer's map (``MAX_ZENITH_DEG``
   from camera 1's zenith, or further where the pair's map of the layer reads the same cloud share
   there as overhead, :func:`map_reach_deg`; low sun, long leads, fast wind), the lead has no
   forecast and says so (flag ``beyond_view``), as it does without the layer's motion
   (``motion_unknown``: a station's first pair has no motion, and one pair's cloud field holds none;
   no forecast is made up for it).
   What is issued is a time-lagged ensemble (:func:`lagged_shade`): the pairs of the last
   ``ENSEMBLE_S`` forecast the same valid time at their own leads, and those read outside the
   sun's aureole (``GLARE_DEG``) are averaged.
4. **GHI** = clear-sky GHI × the clear-sky index of the shade state:
   ``k = k_sun + (k_shade − k_sun)·p``. The two levels default to ``K_SUN`` and ``K_SHADE``; with
   a pyranometer they are learned online (:class:`Levels`): a least-squares line of the measured
   index against the shade probability of the forecasts already verified (every minute of lead
   from 0 to 10 min, whichever leads are asked for; never a later one), drawn towards a prior with
   the weight of ``PRIOR_WEIGHT`` observations: the defaults, or with a pyranometer record of the
   hour before, its sunny level (:func:`sunny_level`) and the shade level scaled with it. An
   observation's weight halves every ``LEVELS_HALF_LIFE_S`` of its age: the shade level is the
   cloud's optical depth, which changes with the cloud (a thin altocumulus deck lets 0.85 of the
   clear sky through, the thick deck that followed it at Fehmarn half an hour later 0.5).

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
           "LEADS_S", "K_SUN", "K_SHADE", "lagged_shade", "glare_angle_deg", "motion_errors",
           "read_sigma_m", "map_reach_deg"]

#: Default lead times: 0 to 20 min every minute [s].
LEADS_S = tuple(float(s) for s in range(0, 1201, 60))
K_SUN = 1.0  # clear-sky index with the sun unobstructed (default level)
K_SHADE = 0.45  # clear-sky index in a cloud's shadow (default level; thin altocumulus lets more through)
PRIOR_WEIGHT = 3.0  # the default levels count as this many pyranometer observations
#: An observation's weight in the levels halves with each this much age [s]: the levels are the
#: transmission of the cloud there now, which changes as a deck's thick and thin parts pass (Fehmarn
#: 09:37: 0.85 → 0.5 of the clear sky within a minute, under a deck the camera sees overcast
#: throughout). Real first half hour, lead 0 / skill at 5 / 10 min: 600 s 0.700× / +0.218 / +0.268,
#: 300 s 0.647× / +0.226 / +0.255, 180 s 0.607× / +0.213 / +0.249. On the pyranometer's second
#: half hour (not imaged) with the shade at 1 from 09:23 (the camera reads the deck over the sun
#: from then; the worst case: the map tells nothing, the levels alone follow the deck;
#: ``benchmarks/eval_levels.py``), the 5 / 10 min skill is −0.07 / −0.03 at 600 s, −0.02 / +0.01
#: at 300 s, +0.03 / +0.05 at 180 s. 300 s keeps about 80 verified forecasts in the fit (11 a
#: minute); shorter drifts towards persistence.
LEVELS_HALF_LIFE_S = 300.0
#: With a pyranometer the prior's sunny level is its record's upper quantile (:func:`sunny_level`)
#: over the last hour, and the shade level scales with it (``K_SHADE``/``K_SUN`` of it).
SUNNY_QUANTILE, SUNNY_HISTORY_S, SUNNY_MIN = 0.9, 3600.0, 20
#: The read disk's σ (:func:`read_sigma_m`), its independent parts added in quadrature:
EDGE_M = 10.0  # the map's own error at lead 0 [m]: a pixel's footprint and the mask's edge ...
#: ... the sun's disk (radius 0.25°) along the sun ray to the layer, as a Gaussian of the same
#: second moment (σ = radius / 2) [per metre of the ray] ...
SUN_SIGMA = math.tan(math.radians(0.25)) / 2.0
#: ... a relative height error [1]: the map and the motion are both scaled by the height from
#: camera 1's pixels, so a height off by ε moves the read against the truth by ε × the site's
#: horizontal distance from camera 1, at every lead (nothing at the camera itself) ...
HEIGHT_ERROR = 0.01
#: ... and a layer's motion error [m/s, per axis] × lead. Measured where the valid pairs of the last
#: ``ENSEMBLE_S`` have the layer's motion from ``MOTION_MEMBERS`` pairs or more (:func:`motion_errors`:
#: their scatter, at least ``MOTION_FLOOR`` of the speed, as a few pairs can agree by chance); else
#: this prior, 5 % of the speed + 0.2 m/s.
MOTION_ERROR = (0.05, 0.2)
MOTION_MEMBERS = 2
MOTION_FLOOR = 0.01
WIDEN = (2.0, 4.0, 8.0, 16.0)  # the disk widens by these factors until a third of it is known ...
#: ... of its σ, or of this share of the range from camera 1 when σ is smaller [rad]: widening looks
#: for the nearest sky the camera sees across what hides the layer (the masked sun, a lower cloud:
#: patches of the camera's view: the widest, 16 × 0.01 rad with the pattern's outer ring at 2 σ, reaches about 18°), which a precise read's small σ
#: says nothing about (with the σ alone the simulated 8 km deck behind cumulus, low-and-high, had
#: 16 % fewer lead-0 forecasts, and the real Fehmarn deck 2 of 29)
WIDEN_FROM = 0.01
MIN_KNOWN = 0.3  # known share of the disk's weight needed for a probability
#: A time-lagged ensemble (:func:`lagged_shade`): the forecasts for one valid time issued by the
#: pairs of the last ``ENSEMBLE_S`` (one per ``ENSEMBLE_STEP_S``) are averaged ...
ENSEMBLE_S = 600.0
ENSEMBLE_STEP_S = 60.0
#: ... leaving out those read within this angle of the sun [deg]: the aureole, where the camera
#: saturates and the cloud mask is least certain (Fehmarn: 1–57 % of the pixels 10–20° from the
#: sun saturated at every pair, 0–9 % at 20–35°).
GLARE_DEG = 20.0
LAYER_MATCH = 0.15  # a member pair's layer is the issue pair's layer k within this share of its height
#: The map is read out to this angle from camera 1's zenith [deg] whatever it shows: further out a
#: layer is seen ever more edge-on and through ever more air, and its map can go wrong either way.
#: On the real Fehmarn deck (7.7 km) the gaps closed up in perspective and the cloud mask read the
#: sky overcast (the layer's cloud share 0.72–0.85 at 65–75° against 0.40–0.45 within 60° at 09:03
#: and 09:09; the shade probability went to 1 at 15–20 min leads, 20–24 km upwind, while the sun
#: shone); in the simulator distant cloud fades into the haze and reads clear (the two-layer
#: scene's 1200 m deck: 0.28–0.33 at 70–75° against 0.42 within 60°).
MAX_ZENITH_DEG = 65.0
#: Beyond it, each pair's map of each layer reaches as far as it still agrees with itself overhead
#: (:func:`map_reach_deg`): band by band of ``REACH_STEP_DEG``, up to ``MAX_REACH_DEG``, while the
#: layer's cloud share in the band is within ``REACH_TOLERANCE`` of its share within
#: ``REACH_INNER_DEG`` of the zenith (with at least ``REACH_MIN_PX`` known pixels in the band).
#: Both failures above change the share the map reads with the angle, which a layer's own cloud
#: does not (a cloud field is no cloudier for being seen from further off); the first band that
#: disagrees, and every band beyond it, is off the map. The tolerance is the share's scatter from
#: band to band within 60° in the simulated decks (0.05–0.1). Measured reach: the simulated 1200 m
#: deck 70–75°, its 3500 m deck 65–72.5° (seed 5); the real Fehmarn deck 65° in 15 of its 31 pairs
#: (09:01–09:12 among them, where it read the sky overcast far out), 70–75° in the others.
#: Only the issue pair's own read reaches past ``MAX_ZENITH_DEG``; the older members of the lagged
#: ensemble stop there (:func:`lagged_shade`): their reads at 60–70° of the simulated low deck,
#: made 3–6 min before for the same valid time, read 0.02–0.24 cloud where the issue pair read 0.55
#: and the shadow came (faded or coarse far cloud), and letting them reach on lost 5 of 106 edges at
#: 2 min and 6 of 72 at 3 min in the simulation while gaining none; the issue pair's own far read is
#: the one that a forecast with no other read needs (5 min leads upwind of a site 1.4 km out).
REACH_STEP_DEG = 2.5
MAX_REACH_DEG = 75.0
REACH_INNER_DEG = 60.0
REACH_TOLERANCE = 0.1
REACH_MIN_PX = 200
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
    """A ground site: its name, WGS 84 position (a plant's centroid) and ENU position about the
    station [m]; a plant (a list of points or a polygon) has its points in ``points_m`` (K, 3),
    whose shade is averaged (:func:`shade_at_site`)."""

    name: str
    latitude_deg: float
    longitude_deg: float
    altitude_m: float
    enu_m: np.ndarray = field(compare=False)
    points_m: np.ndarray | None = field(default=None, compare=False)


PLANT_POINTS = 64  # a polygon is sampled on a square grid of about this many points


def _latlon(text: str, where: str) -> list[float]:
    try:
        vals = [float(v) for v in text.split(",")]
    except ValueError:
        raise ConfigError(f"--site {where!r}: expected LAT,LON[,ALT_M] in degrees and metres") from None
    if len(vals) not in (2, 3) or not all(math.isfinite(v) for v in vals):
        raise ConfigError(f"--site {where!r}: expected LAT,LON[,ALT_M] in degrees and metres")
    return vals


def _enu(lat: float, lon: float, alt: float, station, where: str) -> np.ndarray:
    import pymap3d

    if not (-90.0 <= lat <= 90.0 and -180.0 <= lon <= 360.0 and -500.0 <= alt <= 9000.0):
        raise ConfigError(f"--site {where!r}: latitude -90..90, longitude -180..360, altitude -500..9000 m")
    e, n, u = pymap3d.geodetic2enu(lat, lon, alt, station.latitude_deg, station.longitude_deg, station.altitude_m)
    enu = np.array([float(e), float(n), float(u)])
    if float(np.hypot(enu[0], enu[1])) > 50_000.0:
        raise ConfigError(f"--site {where!r}: {np.hypot(enu[0], enu[1]) / 1000:.0f} km from the station; its "
                          "cameras do not see the sky over it")
    return enu


def parse_site(text: str, station, index: int = 0) -> Site:
    """``LAT,LON[,ALT_M]`` or ``NAME=LAT,LON[,ALT_M]`` (ALT above sea level; default the
    station's) → :class:`Site` in the station's ENU frame (pymap3d, WGS 84). A plant:
    ``NAME=LAT,LON;LAT,LON;…`` (its points, averaged) or ``NAME=polygon:LAT,LON;LAT,LON;…``
    (the area inside, sampled on a grid of about :data:`PLANT_POINTS` points)."""
    name, sep, rest = str(text).partition("=")
    if not sep:
        name, rest = f"site{index + 1}", name
    name = name.strip() or f"site{index + 1}"
    polygon = rest.strip().lower().startswith("polygon:")
    parts = [p for p in (rest.split(":", 1)[1] if polygon else rest).split(";") if p.strip()]
    if not parts:
        raise ConfigError(f"--site {text!r}: expected LAT,LON[,ALT_M] in degrees and metres")
    vals = [_latlon(p, text) for p in parts]
    alts = [v[2] if len(v) == 3 else float(station.altitude_m) for v in vals]
    pts = np.array([_enu(v[0], v[1], a, station, text) for v, a in zip(vals, alts)])
    if polygon:
        if len(pts) < 3:
            raise ConfigError(f"--site {text!r}: a polygon needs at least 3 corners")
        pts = _inside(pts, text)
    lat, lon = float(np.mean([v[0] for v in vals])), float(np.mean([v[1] for v in vals]))
    centre = pts.mean(axis=0)
    return Site(name, lat, lon, float(np.mean(alts)), centre, pts if len(pts) > 1 else None)


def _inside(corners: np.ndarray, where: str) -> np.ndarray:
    """Points of a square grid inside the polygon ``corners`` (ENU [m], (K, 3)), about
    :data:`PLANT_POINTS` of them, at the corners' mean height."""
    from matplotlib.path import Path as MplPath

    xy = corners[:, :2]
    area = 0.5 * abs(float(np.dot(xy[:, 0], np.roll(xy[:, 1], 1)) - np.dot(xy[:, 1], np.roll(xy[:, 0], 1))))
    if area < 1.0:
        raise ConfigError(f"--site {where!r}: the polygon encloses no area")
    step = math.sqrt(area / PLANT_POINTS)
    lo, hi = xy.min(axis=0), xy.max(axis=0)
    gx, gy = np.meshgrid(np.arange(lo[0] + step / 2, hi[0], step), np.arange(lo[1] + step / 2, hi[1], step))
    g = np.stack([gx.ravel(), gy.ravel()], axis=1)
    g = g[MplPath(xy).contains_points(g)]
    if not len(g):
        g = xy.mean(axis=0, keepdims=True)
    return np.column_stack([g, np.full(len(g), float(corners[:, 2].mean()))])


def read_sites(path, station) -> list[Site]:
    """A CSV of sites: ``name, latitude, longitude[, altitude_m]``; rows sharing a name are one
    plant's points (averaged)."""
    try:
        with open(path, newline="", encoding="utf-8") as fh:
            rows = list(csv.DictReader(fh))
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise InputError(f"sites file {path}: cannot read ({type(exc).__name__}: {exc})") from None
    groups: dict[str, list[str]] = {}
    for i, r in enumerate(rows, start=2):
        r = {(k or "").strip().lower(): (v or "").strip() for k, v in r.items()}
        if not {"name", "latitude", "longitude"} <= set(r):
            raise InputError(f"sites file {path}: needs columns name, latitude, longitude[, altitude_m]")
        alt = f",{r['altitude_m']}" if r.get("altitude_m") else ""
        groups.setdefault(r["name"] or f"site{i - 1}", []).append(f"{r['latitude']},{r['longitude']}{alt}")
    if not groups:
        raise InputError(f"sites file {path}: no rows")
    return [parse_site(f"{n}={';'.join(p)}", station, i) for i, (n, p) in enumerate(groups.items())]


def parse_sites(texts: list[str], station) -> list[Site]:
    """Every ``--site``: a site or plant (:func:`parse_site`), or ``@FILE.csv`` (:func:`read_sites`);
    names must differ."""
    out: list[Site] = []
    for t in texts:
        out += read_sites(t[1:], station) if str(t).startswith("@") else [parse_site(t, station, len(out))]
    names = [s.name for s in out]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise ConfigError(f"--site: the name {dup[0]!r} is given twice")
    return out


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
    """Layer k's weighted cloud share on a disk about ``centre`` (3,) on the layer, widened
    (``WIDEN`` × max(σ, ``WIDEN_FROM`` × its range from camera 1)) until ``MIN_KNOWN`` of it is
    known (NaN when never); and whether it had to widen."""
    from cbh.geometry.ground import lookup_layer

    reach = WIDEN_FROM * float(np.linalg.norm(centre - np.asarray(pg.camera.position_m, np.float64)))
    for f in (1.0, *WIDEN):
        r = sigma_m if f == 1.0 else max(sigma_m, reach) * f
        pts = np.column_stack([centre[0] + _UNIT[:, 0] * r, centre[1] + _UNIT[:, 1] * r,
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


def shade_at_site(pg, site: Site, sun_dir: np.ndarray | None, lead_s: float) -> tuple[float, str, bool]:
    """:func:`shade_at` of a site, or a plant's mean over its points (the share of the plant in
    shade): known when at least half its points are, else NaN with the commonest reason."""
    if site.points_m is None:
        return shade_at(pg, site.enu_m, sun_dir, lead_s)
    got = [shade_at(pg, p, sun_dir, lead_s) for p in site.points_m]
    return (*_plant_mean([g[:2] for g in got]), any(g[2] for g in got))


def _plant_mean(got: list) -> tuple[float, str]:
    """A plant's shade from its points' (probability, reason): the mean, known when at least half
    of them are (the reason ``seen_earlier`` when it is every known point's), else NaN with the
    commonest reason."""
    ok = [g[0] for g in got if math.isfinite(g[0])]
    if 2 * len(ok) < len(got):
        whys = [g[1] for g in got if not math.isfinite(g[0])]
        return math.nan, max(set(whys), key=whys.count)
    whys = {g[1] for g in got if math.isfinite(g[0])}
    return float(np.mean(ok)), ("seen_earlier" if whys == {"seen_earlier"} else "")


def _layer_centre(pg, k: int, site_enu: np.ndarray, s: np.ndarray, lead_s: float, reach: bool = True):
    """Where the cloud that will be on the sun ray from ``site_enu`` ``lead_s`` after the pair is
    now on layer k: (centre (3,), the disk's σ [m]) or the reason it is not known
    (``motion_unknown``, ``beyond_view``), or None when the layer is not above the site. The map
    ends at the layer's :func:`map_reach_deg`, or at ``MAX_ZENITH_DEG`` without ``reach``."""
    h = float(pg.heights[k])
    ve, vn = pg.motions[k]
    if lead_s and not (math.isfinite(ve) and math.isfinite(vn)):
        return "motion_unknown"
    if not lead_s:
        ve = vn = 0.0
    t = (h - float(site_enu[2])) / s[2]
    if t <= 0:
        return None
    centre = np.array([site_enu[0] + s[0] * t - ve * lead_s, site_enu[1] + s[1] * t - vn * lead_s, h])
    rel = centre - np.asarray(pg.camera.position_m, np.float64)
    if (math.degrees(math.atan2(math.hypot(rel[0], rel[1]), rel[2])) > (_reach_deg(pg, k) if reach else MAX_ZENITH_DEG)
            or not _in_view(pg.camera, centre[None, :], pg.labels.shape)[0]):
        return "beyond_view"
    errs = getattr(pg, "motion_errors", None)
    err = errs[k] if errs and math.isfinite(errs[k]) else MOTION_ERROR[0] * math.hypot(ve, vn) + MOTION_ERROR[1]
    d_cam = math.hypot(float(site_enu[0] - pg.camera.position_m[0]), float(site_enu[1] - pg.camera.position_m[1]))
    return centre, read_sigma_m(t, d_cam, err, lead_s)


_ZENITH_BANDS: dict = {}  # (camera, label size) → each pixel's band of REACH_STEP_DEG from the zenith


def _zenith_bands(camera, shape) -> np.ndarray:
    """Each of camera 1's pixels' band of ``REACH_STEP_DEG`` from the zenith (0: 0 to one step, …),
    -1 for a ray below the horizon or none, (H, W) int16; computed once per camera and size."""
    H, W = shape
    key = (camera.name, H, W, np.asarray(camera.R_world_from_cam, np.float64).tobytes(), repr(camera.model.to_dict()))
    got = _ZENITH_BANDS.get(key)
    if got is None:  # (made and returned locally: another thread may clear the cache meanwhile)
        yy, xx = np.mgrid[0:H, 0:W]
        up = camera.pixel_to_world(np.column_stack([xx.ravel(), yy.ravel()]).astype(np.float64))[:, 2]
        with np.errstate(invalid="ignore"):
            zen = np.degrees(np.arccos(np.clip(up, -1.0, 1.0)))
            band = np.where(np.isfinite(zen) & (zen < 90.0), np.floor(zen / REACH_STEP_DEG), -1)
        got = band.astype(np.int16).reshape(H, W)
        got.setflags(write=False)  # shared by every caller
        if len(_ZENITH_BANDS) >= 4:
            _ZENITH_BANDS.clear()
        _ZENITH_BANDS[key] = got
    return got


def map_reach_deg(pg) -> list[float]:
    """Per layer of the pair ``pg`` (anything with ``camera``, ``labels`` and ``heights``): how far
    from camera 1's zenith its map is read [deg], at least ``MAX_ZENITH_DEG``: out to the last band
    of ``REACH_STEP_DEG`` (up to ``MAX_REACH_DEG``) before the first whose cloud share of the layer
    (its cloud against clear sky or a higher layer, as :func:`cbh.geometry.ground.lookup_layer`
    reads it) differs by more than ``REACH_TOLERANCE`` from the share within ``REACH_INNER_DEG``, or
    has fewer than ``REACH_MIN_PX`` such pixels (see ``MAX_ZENITH_DEG``)."""
    from cbh.geometry.ground import CLEAR

    band = _zenith_bands(pg.camera, pg.labels.shape)
    lab = pg.labels
    nb = int(round(90.0 / REACH_STEP_DEG)) + 1
    inner = int(round(REACH_INNER_DEG / REACH_STEP_DEG))
    first, last = int(round(MAX_ZENITH_DEG / REACH_STEP_DEG)), int(round(MAX_REACH_DEG / REACH_STEP_DEG))
    up = band >= 0
    out = []
    for k in range(len(pg.heights)):
        cloud = np.bincount(band[up & (lab == k)], minlength=nb)
        known = cloud + np.bincount(band[up & ((lab == CLEAR) | (lab > k))], minlength=nb)
        reach = MAX_ZENITH_DEG
        if known[:inner].sum() >= REACH_MIN_PX:
            share0 = cloud[:inner].sum() / known[:inner].sum()
            for b in range(first, last):
                if known[b] < REACH_MIN_PX or abs(cloud[b] / known[b] - share0) > REACH_TOLERANCE:
                    break
                reach = (b + 1) * REACH_STEP_DEG
        out.append(float(reach))
    return out


def _reach_deg(pg, k: int) -> float:
    """Layer k's :func:`map_reach_deg` of ``pg``, measured at its first read and kept on it
    (``PairGround.map_reach_deg``)."""
    if getattr(pg, "map_reach_deg", None) is None:
        pg.map_reach_deg = map_reach_deg(pg)
    return pg.map_reach_deg[k]


def read_sigma_m(ray_m: float, site_from_camera_m: float, motion_error_ms: float, lead_s: float) -> float:
    """σ of a layer's read disk [m]: the map's ``EDGE_M``, the sun's disk over the sun ray
    (``SUN_SIGMA`` × ``ray_m``, the ray's length from the site to the layer [m]), the height error
    (``HEIGHT_ERROR`` × ``site_from_camera_m``, the site's horizontal distance from camera 1 [m])
    and the motion's (``motion_error_ms`` [m/s] × ``lead_s`` [s]): independent errors, added in
    quadrature."""
    return math.sqrt(EDGE_M ** 2 + (SUN_SIGMA * ray_m) ** 2 + (HEIGHT_ERROR * site_from_camera_m) ** 2
                     + (motion_error_ms * lead_s) ** 2)


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
    for k in range(len(pg.heights)):
        got = _layer_centre(pg, k, site_enu, s, lead_s)
        if got is None:
            continue
        if isinstance(got, str):
            unknown = unknown or got
            continue
        p, wide = _layer_share(pg, k, *got)
        widened |= wide
        if not math.isfinite(p):
            unknown = unknown or "beyond_view"
            continue
        p_clear *= 1.0 - p
    shade = 1.0 - p_clear
    if unknown and shade < 0.9:  # a known layer that shades it decides; otherwise it is not known
        return math.nan, unknown, widened
    return shade, "", widened


def _sun_angle_deg(pg, centre: np.ndarray) -> float:
    """Angle between ``centre`` seen from camera 1 and the sun as the pair saw it [deg]."""
    if pg.sun_dir is None:
        return 180.0
    rel = centre - np.asarray(pg.camera.position_m, np.float64)
    c = float(rel @ np.asarray(pg.sun_dir, np.float64)) / float(np.linalg.norm(rel))
    return math.degrees(math.acos(max(-1.0, min(1.0, c))))


def _layer_reads(pg, site_enu: np.ndarray, s: np.ndarray, lead_s: float, reach: bool = True) -> list:
    """Per layer of ``pg``: (height [m], cloud share, widened, angle from the sun [deg], disk σ
    [m]) of its read for ``site_enu`` ``lead_s`` ahead, or why it has none (a reason, or None when
    the layer is not above the site); ``reach`` as :func:`_layer_centre`'s."""
    out: list = []
    for k in range(len(pg.heights)):
        got = _layer_centre(pg, k, site_enu, s, lead_s, reach)
        if got is None or isinstance(got, str):
            out.append(got)
            continue
        p, wide = _layer_share(pg, k, *got)
        out.append((float(pg.heights[k]), p, wide, _sun_angle_deg(pg, got[0]), got[1]) if math.isfinite(p)
                   else "beyond_view")
    return out


def glare_angle_deg(pg, site_enu: np.ndarray, sun_dir: np.ndarray | None, lead_s: float) -> float:
    """How near the sun, as camera 1 saw it at the pair's time, the cloud map is read for this
    forecast: the smallest angle over the layers [deg] (180 without a sun or a layer)."""
    if sun_dir is None or not pg.heights:
        return 180.0
    reads = _layer_reads(pg, site_enu, np.asarray(sun_dir, np.float64), lead_s)
    return min([r[3] for r in reads if isinstance(r, tuple)], default=180.0)


def _same_layer(heights, h: float) -> int | None:
    """The issue pair's layer that a height belongs to: the nearest within ``LAYER_MATCH`` of it."""
    d = [abs(h - float(x)) / max(float(x), 1.0) for x in heights]
    k = int(np.argmin(d))
    return k if d[k] <= LAYER_MATCH else None


def motion_errors(pgs: list) -> list[float]:
    """Per layer of the newest pair of ``pgs`` (the recent valid pairs, oldest first: anything with
    ``heights`` and ``motions``; the export takes every pair of the last ``ENSEMBLE_S``): its motion's
    error [m/s, per axis], measured as the scatter of that layer's motion over the pairs (a
    pair's layer within ``LAYER_MATCH`` of its height): the RMS over both axes of the sample
    standard deviation, at least ``MOTION_FLOOR`` of the speed; NaN (the prior ``MOTION_ERROR``)
    with fewer than ``MOTION_MEMBERS`` motions. The scatter holds what each pair's motion gets wrong
    (its tracks, its height) and what the wind itself changed over the ensemble's 10 min."""
    own = pgs[-1]
    out = []
    for k, h in enumerate(own.heights):
        v = [m for pg in pgs for hj, m in zip(pg.heights, pg.motions)
             if abs(float(hj) - float(h)) <= LAYER_MATCH * max(float(h), 1.0) and all(map(math.isfinite, m))]
        if len(v) < MOTION_MEMBERS or not all(map(math.isfinite, own.motions[k])):
            out.append(math.nan)
            continue
        sd = np.std(np.asarray(v, np.float64), axis=0, ddof=1)
        out.append(max(float(np.sqrt(np.mean(sd ** 2))), MOTION_FLOOR * math.hypot(*own.motions[k])))
    return out


def _lagged_point(pgs: list, site_enu: np.ndarray, sun_dir: np.ndarray | None, valid_time,
                  cache: dict | None = None) -> tuple[float, str]:
    """:func:`lagged_shade` at one point."""
    own = pgs[-1]
    if sun_dir is None or float(sun_dir[2]) <= 0.02:
        return math.nan, "night"
    if not own.heights:
        return (0.0, "") if own.cloud_fraction == 0 else (math.nan, "no_layer")
    s = np.asarray(sun_dir, np.float64)
    lead = (valid_time - own.time_utc).total_seconds()
    mine = _layer_reads(own, site_enu, s, lead)
    reads: list[list] = [[] for _ in own.heights]  # per issue-pair layer: (member, share, far, weight)
    for j, pg in enumerate(reversed(pgs)):
        lj = (valid_time - pg.time_utc).total_seconds()
        if j and lj > lead + ENSEMBLE_S:
            break
        if j == 0:
            got = mine
        elif cache is None:  # an older member reads its map within MAX_ZENITH_DEG only (see lagged_shade)
            got = _layer_reads(pg, site_enu, s, lj, reach=False)
        else:  # a member's read of one valid time is the same whichever later issue asks for it
            key = (pg.time_utc, valid_time, np.asarray(site_enu, np.float64).tobytes())
            if key not in cache:
                cache[key] = _layer_reads(pg, site_enu, s, lj, reach=False)
            got = cache[key]
        for r in got:
            k = _same_layer(own.heights, r[0]) if isinstance(r, tuple) and not r[2] else None
            if k is not None:
                reads[k].append((j, r[1], r[3] >= GLARE_DEG, 1.0 / r[4] ** 2))
    p_clear, unknown, own_used = 1.0, "", False
    for k, r_own in enumerate(mine):
        use = [x for x in reads[k] if x[2]] or reads[k][:1]
        if use:
            p = sum(x[3] * x[1] for x in use) / sum(x[3] for x in use)
            own_used |= any(x[0] == 0 for x in use)
        elif isinstance(r_own, tuple):  # only the issue pair's read, widened around the masked sun
            p, own_used = r_own[1], True
        else:
            unknown = unknown or (r_own or "")
            continue
        p_clear *= 1.0 - p
    shade = 1.0 - p_clear
    if unknown and shade < 0.9:  # a known layer that shades it decides; otherwise it is not known
        return math.nan, unknown
    return shade, ("" if own_used or not any(reads) else "seen_earlier")


def lagged_shade(pgs: list, site: Site, sun_dir: np.ndarray | None, valid_time,
                 cache: dict | None = None) -> tuple[float, str]:
    """The shade probability at ``site`` at ``valid_time`` from a time-lagged ensemble: every pair
    of ``pgs`` (oldest first; the last is the issue time's own, the others at most
    ``ENSEMBLE_S`` older) reads each layer's cloud for that valid time at its own lead. Per layer
    of the issue pair (a member's layer within ``LAYER_MATCH`` of its height), the reads made at
    least ``GLARE_DEG`` from the sun as that pair saw it, and not widened around the masked sun,
    are averaged with weights 1/σ² (σ the read's disk: a fresh read outweighs an old one); without
    one, the freshest unwidened read, else the issue pair's own; the layers combine as in
    :func:`shade_at`. The reason is ``seen_earlier`` when no read of the issue pair's own is used,
    else as :func:`shade_at`'s. A plant: the mean over its points, known when half of them are.
    ``cache``: a dict kept across issue times (:func:`prune_cache` drops pairs that left the
    ensemble): each member's reads are made once per valid time. An older member reads its map
    within ``MAX_ZENITH_DEG`` only; the issue pair's own read reaches to :func:`map_reach_deg`
    (see ``REACH_STEP_DEG``). The edges found have no timing bias to correct (simulated two-layer
    scene, seeds 3, 5, 7, 11 and the default, leads 0–5 min: the mean signed error of the edges
    within 60 s −4 to +4 s, the median |error| 0–10 s, the 10 s cadence)."""
    if site.points_m is None:
        return _lagged_point(pgs, site.enu_m, sun_dir, valid_time, cache)
    return _plant_mean([_lagged_point(pgs, p, sun_dir, valid_time, cache) for p in site.points_m])


def prune_cache(cache: dict, pgs: list) -> None:
    """Drop from a :func:`lagged_shade` cache the reads of pairs no longer in ``pgs``."""
    keep = {pg.time_utc for pg in pgs}
    for key in [k for k in cache if k[0] not in keep]:
        del cache[key]


class Levels:
    """The clear-sky index in sun and in shade, learned online from a pyranometer (see the module
    docstring); the defaults without one. Observations older than 8 half-lives (weight < 0.4 %)
    are dropped, so a station that runs for months keeps a bounded memory."""

    def __init__(self, k_sun: float = K_SUN, k_shade: float = K_SHADE, prior_weight: float = PRIOR_WEIGHT,
                 half_life_s: float = LEVELS_HALF_LIFE_S):
        self.prior = (float(k_sun), float(k_shade))
        self.w0 = float(prior_weight)
        self.half_life_s = float(half_life_s)
        self._p: list[float] = []
        self._k: list[float] = []
        self._t: list[float] = []  # each observation's time [s since the epoch]
        self._now = -math.inf

    def set_prior(self, k_sun: float, k_shade: float) -> None:
        """Move the prior's two points (the pyranometer's sunny level of the last hour:
        :func:`sunny_level`)."""
        self.prior = (float(k_sun), float(k_shade))

    def add(self, shade_p: float, k_measured: float, when: datetime | None = None) -> None:
        """A shade probability forecast for a time now past (``when``, its valid time; None: now,
        i.e. the latest time seen), and the clear-sky index measured then."""
        if math.isfinite(shade_p) and math.isfinite(k_measured) and 0.0 < k_measured < 2.0:
            t = (self._now if math.isfinite(self._now) else 0.0) if when is None else when.timestamp()
            self._now = max(self._now, t)
            self._p.append(float(shade_p))
            self._k.append(float(k_measured))
            self._t.append(t)
            self._forget()

    def _forget(self) -> None:
        if not math.isfinite(self.half_life_s) or not self._t or self._now - min(self._t) <= 8.0 * self.half_life_s:
            return
        keep = [i for i, t in enumerate(self._t) if self._now - t <= 8.0 * self.half_life_s]
        self._p, self._k, self._t = ([x[i] for i in keep] for x in (self._p, self._k, self._t))

    @property
    def n(self) -> int:
        return len(self._k)

    def levels(self, now: datetime | None = None) -> tuple[float, float]:
        """(k_sun, k_shade): the prior's two points and the observations (each weighted by its age
        at ``now``, the issue time, or at the newest observation if later or None: halved every
        ``half_life_s``; so after a gap in the record, a night or a new session, the old ones
        count little against the prior), one weighted line."""
        if now is not None and now.timestamp() > self._now:
            self._now = now.timestamp()
            self._forget()
        ks, kd = self.prior
        p = np.concatenate([[0.0, 1.0], self._p])
        k = np.concatenate([[ks, kd], self._k])
        age = self._now - np.asarray(self._t, np.float64)
        decay = np.exp2(-age / self.half_life_s) if math.isfinite(self.half_life_s) else np.ones(len(age))
        w = np.concatenate([[self.w0, self.w0], decay])
        X = np.column_stack([np.ones_like(p), p]) * np.sqrt(w)[:, None]
        a, b = np.linalg.lstsq(X, k * np.sqrt(w), rcond=None)[0]
        return float(np.clip(a, 0.7, 1.5)), float(np.clip(a + b, 0.05, 1.2))


def sunny_level(k_recent) -> float:
    """The clear-sky index in sun that a pyranometer's recent record says (NaN when it says too
    little): the ``SUNNY_QUANTILE`` quantile of its clear-sky index over the last
    ``SUNNY_HISTORY_S`` (at least ``SUNNY_MIN`` minutes), within 0.8–1.4. In sun the index is the
    clear-sky model's own error for the place and day (Ineichen with a climatological turbidity:
    Fehmarn's clean air reads 1.07–1.12 through a cloudless morning) and the cloud enhancement at
    edges; cloud pulls the index down, rarely up, so an upper quantile is the sunny state."""
    k = np.asarray(k_recent, np.float64)
    k = k[np.isfinite(k) & (k > 0.0) & (k < 2.0)]
    if len(k) < SUNNY_MIN:
        return math.nan
    return float(np.clip(np.quantile(k, SUNNY_QUANTILE), 0.8, 1.4))


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
