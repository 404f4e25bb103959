"""METAR cloud groups from cbh's results, with MeteoSwiss's ampycloud.

ampycloud turns ceilometer *hits* over a window (usually the 20 min before the METAR time) into
METAR layers: okta, base in hundreds of feet above the aerodrome, FEW/SCT/BKN/OVC, the ICAO
significance rules, NCD and NSC. cbh does not re-implement any of that: this module only turns
cbh's per-pair result into ampycloud's hit table (columns ``ceilo``, ``dt`` [s], ``height``
[ft above aerodrome level], ``type``: n-th hit from the ground, 0 = no detection) and calls
:func:`ampycloud.run`. Heights above cbh's ENU origin are taken as heights above the aerodrome
(put the origin at aerodrome level).

How cbh's result becomes hits (decision, measured)
--------------------------------------------------
Two samplers live behind one contract (:data:`HIT_METHODS`, :func:`get_hit_method`):

``virtual`` (default)
    ``n`` virtual ceilometers on the ground, on a sunflower pattern inside a disk of radius
    ``h₁ · tan(VC_ZENITH_DEG)`` around the station (``h₁`` = the pair's lowest layer, at most
    ``VC_MAX_RADIUS_M``), each looking straight up. For each layer k, the point above the
    ceilometer at the layer's height is looked up in camera 1's layer labels
    (:func:`cbh.geometry.ground.layer_labels`): cloud of layer k gives a hit, numbered from the
    ground; a ceilometer whose every layer is clear there reports "no detection" (type 0); one
    whose points are all outside the usable sky reports nothing. Because the camera sees the
    upper layer through the lower one's gaps *elsewhere*, a virtual ceilometer can report the
    upper layer above a lower cloud (as a ceilometer's 2nd hit); where the camera's ray to the
    upper point is blocked by a lower cloud, that layer counts as not hit there.
``map``
    The dense map sampled as hits: ``n`` sky directions on a sunflower pattern uniform in solid
    angle inside the usable zenith range, each one "ceilometer"; a direction that shows layer k
    is one hit of layer k, a clear one is "no detection". Each direction shows only the lowest
    cloud on it, and large zenith angles (which see far more ground per steradian) weigh as much
    as the zenith.

Hit heights are the layer's base (:attr:`cbh.result.Layer.height_m`, cbh's robust low
statistic), not the height map's pixel value: the per-pixel heights carry triangulation noise
(σ ≈ 60 m at 1000 m, 150–320 m at 4000 m on the simulated ``l1000-4000`` scene; their 5th
percentile is ~100 m below the base), and ampycloud takes a layer's base as the 5th percentile
of its hits, so pixel heights pull the base down. ``heights="pixel"`` keeps them for comparison.

Measured with ``python scripts/measure_metar_hits.py REC`` (last pair's window, n = 128 per pair):

* ``l1000-4000`` (a simulated recording, layers 1000 m / coverage 0.45 and 4000 m / 0.35,
  10 pairs 60 s apart, 640 px, scene and command in the commit message of this module):
  virtual+layer ``SCT032`` (3 okta, 3284 ft); virtual+pixel ``SCT032`` (3256 ft);
  map+layer ``SCT032`` (4 okta, 3284 ft); map+pixel ``SCT032`` (4 okta, 3228 ft).
  1000 m = 3281 ft: code 032 either way. The 4000 m deck is *not* in the METAR: seen through
  the lower deck's gaps it covers 21 % of the virtual ceilometers (n = 256: 55 of 256) and
  16 % of the sampled directions, ≤ 2 okta, and a second group must be ≥ SCT (3 okta) to be
  significant (ICAO, applied by ampycloud) — as a real ceilometer would report it.
* ``recordings/sample-two-layers.mcap`` (1200 m / 0.35 under 3500 m / 0.3, 8 pairs):
  virtual+layer ``SCT039`` (3934 ft; 1200 m = 3937 ft), virtual+pixel ``SCT038``,
  map+layer ``SCT039``.

The samplers agree on heights (both hit the layer bases); they differ in okta. ``virtual`` is
the default: a METAR's amounts are ground-projected covers, and a network of ceilometers under
the sky (several instruments, one measurement each per time step, and a 2nd hit where the
upper deck is seen above a lower cloud) is the input ampycloud is built for; ``map`` weighs
large zenith angles, where the lower deck hides the upper one, as much as the zenith.

pandas ≥ 3 and ampycloud 2.2.1: ampycloud casts the ``ceilo`` column to ``StringDtype()``,
which pandas 3 backs with pyarrow, whose boolean masks ampycloud's hit counting cannot
multiply. :func:`run_ampycloud` sets ampycloud's declared ``ceilo`` dtype to the
python-backed ``StringDtype("python")`` (pandas 2's default, what ampycloud is tested with)
before each call; no rule of ampycloud is touched. With it, ampycloud reproduces the expected
groups of all 17 of its own reference cases (tests/test_aviation.py).
"""
from __future__ import annotations

import csv
import logging
import math
import warnings
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from cbh.errors import ConfigError, RecordingError

__all__ = ["FT_PER_M", "WINDOW_S", "HIT_METHODS", "get_hit_method", "hits_virtual", "hits_map", "PairHits",
           "hit_table", "MetarGroup", "MetarReport", "run_ampycloud", "metar_report", "write_metar_csv",
           "sunflower_disk", "sunflower_cap", "METAR_COLUMNS"]

log = logging.getLogger(__name__)

FT_PER_M = 1.0 / 0.3048  # international foot
WINDOW_S = 1200.0  # ampycloud's usual window: the 20 min before the METAR time [s]
VC_ZENITH_DEG = 60.0  # virtual ceilometers: outermost zenith angle at the lowest layer [deg]
VC_MAX_RADIUS_M = 5000.0  # virtual ceilometers: largest radius of the network [m]
MAP_ZENITH_DEG = 70.0  # map sampler: largest zenith angle of the sampled directions [deg]
NO_LAYER_PROBE_M = 1000.0  # virtual ceilometers of a pair with no layer: height probed for clear sky [m]
MAX_HITS = 1500  # at most this many measurements (ceilometer × time) per ampycloud call
_GOLDEN = math.pi * (3.0 - math.sqrt(5.0))


def sunflower_disk(n: int, radius_m: float) -> np.ndarray:
    """``n`` points spread evenly over a disk (Vogel's sunflower), shape (n, 2), float64 [m]."""
    k = np.arange(n, dtype=np.float64)
    r = radius_m * np.sqrt((k + 0.5) / n)
    a = k * _GOLDEN
    return np.stack([r * np.sin(a), r * np.cos(a)], axis=1)


def sunflower_cap(n: int, max_zenith_deg: float) -> np.ndarray:
    """``n`` unit ENU directions uniform in solid angle over the cap zenith ≤ ``max_zenith_deg``,
    shape (n, 3), float64."""
    k = np.arange(n, dtype=np.float64)
    cmin = math.cos(math.radians(max_zenith_deg))
    cz = 1.0 - (1.0 - cmin) * (k + 0.5) / n
    sz = np.sqrt(1.0 - cz**2)
    a = k * _GOLDEN
    return np.stack([sz * np.sin(a), sz * np.cos(a), cz], axis=1)


def _pixel_labels(camera, labels: np.ndarray, pixels: np.ndarray) -> np.ndarray:
    """Labels at pixels (N, 2) (nearest), ground.UNKNOWN outside the image or the model."""
    from cbh.geometry.ground import UNKNOWN

    H, W = labels.shape
    out = np.full(pixels.shape[0], UNKNOWN, np.int16)
    ok = np.isfinite(pixels).all(axis=1)
    col = np.full(pixels.shape[0], -1, np.int64)
    row = np.full(pixels.shape[0], -1, np.int64)
    col[ok] = np.floor(pixels[ok, 0] + 0.5).astype(np.int64)
    row[ok] = np.floor(pixels[ok, 1] + 0.5).astype(np.int64)
    ok &= (col >= 0) & (col < W) & (row >= 0) & (row < H)
    out[ok] = labels[row[ok], col[ok]]
    return out


def _pixel_values(height_map: np.ndarray, pixels: np.ndarray) -> np.ndarray:
    H, W = height_map.shape
    out = np.full(pixels.shape[0], np.nan)
    ok = np.isfinite(pixels).all(axis=1)
    col = np.floor(np.where(ok, pixels[:, 0], 0) + 0.5).astype(np.int64)
    row = np.floor(np.where(ok, pixels[:, 1], 0) + 0.5).astype(np.int64)
    ok &= (col >= 0) & (col < W) & (row >= 0) & (row < H)
    out[ok] = height_map[row[ok], col[ok]]
    return out


@dataclass
class PairHits:
    """One pair's measurements: per virtual ceilometer, its hits (ascending) or none.

    ``ceilo`` (M,) int: ceilometer index; ``height_m`` (M,) float: hit height above the ENU
    origin [m], NaN for a no-detection row; ``type`` (M,) int: n-th hit from the ground, 0 =
    no detection. A ceilometer that cannot tell (outside the usable sky) has no row.
    """

    ceilo: np.ndarray
    height_m: np.ndarray
    type: np.ndarray

    @property
    def measurements(self) -> int:
        return int(np.unique(self.ceilo).size)


def _hits_from_layer_flags(is_cloud: np.ndarray, known: np.ndarray, heights: np.ndarray) -> PairHits:
    """Hits from (N ceilometers, L layers) cloud / known flags and (N, L) hit heights."""
    ce, hh, ty = [], [], []
    for i in range(is_cloud.shape[0]):
        if not known[i].any():
            continue
        ks = np.flatnonzero(is_cloud[i])
        if ks.size == 0:
            ce.append(i), hh.append(math.nan), ty.append(0)
            continue
        for n, k in enumerate(ks, start=1):
            ce.append(i), hh.append(float(heights[i, k])), ty.append(n)
    return PairHits(np.array(ce, np.int64), np.array(hh, np.float64), np.array(ty, np.int64))


def hits_virtual(camera, labels, height_map, layer_heights_m, n: int = 128, heights: str = "layer") -> PairHits:
    """Virtual ceilometers on the ground under the camera's sky (see the module docstring).

    Parameters
    ----------
    camera : cbh.geometry.station.Camera
        Camera 1 at the size of ``labels``.
    labels : ndarray, shape (H, W), int16
        :func:`cbh.geometry.ground.layer_labels` of the pair.
    height_map : ndarray, shape (H, W), float
        Dense cloud-base height [m], NaN = unknown (used with ``heights="pixel"`` only).
    layer_heights_m : sequence of float, length L
        The pair's layer bases, ascending [m above the ENU origin].
    n : int
        Number of virtual ceilometers.
    heights : {"layer", "pixel"}
        Hit height: the layer's base, or the height map at the pixel that shows the point.
    """
    from cbh.geometry.ground import CLEAR

    hs = np.asarray(layer_heights_m, np.float64)
    no_layer = hs.size == 0
    if no_layer:  # probe a nominal base: a clear sky there is "no detection" for every ceilometer
        hs = np.array([NO_LAYER_PROBE_M])
    L = hs.size
    radius = min(VC_MAX_RADIUS_M, float(hs[0]) * math.tan(math.radians(VC_ZENITH_DEG)))
    xy = sunflower_disk(n, radius) + np.asarray(camera.position_m[:2], np.float64)
    is_cloud = np.zeros((n, L), bool)
    known = np.zeros((n, L), bool)
    hit_h = np.tile(hs, (n, 1))
    for k, h in enumerate(hs):
        pts = np.column_stack([xy, np.full(n, h)])
        px = camera.world_to_pixel(pts)
        lab = _pixel_labels(camera, labels, px)
        is_cloud[:, k] = (lab == k) & (not no_layer)
        known[:, k] = (lab == CLEAR) | (lab >= 0)
        if heights == "pixel":
            v = _pixel_values(np.asarray(height_map, np.float64), px)
            hit_h[:, k] = np.where(np.isfinite(v), v, h)
    return _hits_from_layer_flags(is_cloud, known, hit_h)


def hits_map(camera, labels, height_map, layer_heights_m, n: int = 128, heights: str = "layer") -> PairHits:
    """The dense map sampled as hits: ``n`` sky directions (see the module docstring); same
    parameters as :func:`hits_virtual`."""
    from cbh.geometry.ground import CLEAR

    hs = np.asarray(layer_heights_m, np.float64)
    L = max(hs.size, 1)
    px = camera.direction_to_pixel(sunflower_cap(n, MAP_ZENITH_DEG))
    lab = _pixel_labels(camera, labels, px)
    is_cloud = np.zeros((n, L), bool)
    known = np.repeat(((lab == CLEAR) | (lab >= 0))[:, None], L, axis=1)
    hit_h = np.tile(hs if hs.size else np.array([np.nan]), (n, 1))
    for k in range(hs.size):
        is_cloud[:, k] = lab == k
    if heights == "pixel":
        v = _pixel_values(np.asarray(height_map, np.float64), px)
        hit_h = np.where(np.isfinite(v)[:, None], v[:, None], hit_h)
    return _hits_from_layer_flags(is_cloud, known, hit_h)


#: Hit samplers by name: (camera, labels, height_map, layer_heights_m, n, heights) → PairHits.
HIT_METHODS = {"virtual": hits_virtual, "map": hits_map}


def get_hit_method(name: str):
    """The sampler called ``name`` (case-insensitive); ConfigError listing the valid names."""
    try:
        return HIT_METHODS[str(name).lower()]
    except KeyError:
        raise ConfigError(f"METAR hit method: unknown {name!r} (valid: {', '.join(HIT_METHODS)})") from None


def hit_table(pairs, ref_time: datetime):
    """ampycloud's input table from ``(time_utc, PairHits)`` items.

    Returns a pandas DataFrame with columns ``ceilo`` (str ``vc<i>``), ``dt`` [s, ≤ 0 before
    ``ref_time``], ``height`` [ft above aerodrome level], ``type`` (int).
    """
    import pandas as pd

    ce, dt, hh, ty = [], [], [], []
    for t, ph in pairs:
        d = (t - ref_time).total_seconds()
        ce.extend(f"vc{int(c)}" for c in ph.ceilo)
        dt.extend([d] * len(ph.ceilo))
        hh.extend((ph.height_m * FT_PER_M).tolist())
        ty.extend(ph.type.tolist())
    return pd.DataFrame({"ceilo": pd.array(ce, dtype=pd.StringDtype("python")), "dt": np.array(dt, np.float64),
                         "height": np.array(hh, np.float64), "type": np.array(ty, np.int64)})


@dataclass(frozen=True)
class MetarGroup:
    """One significant METAR cloud group, from ampycloud's ``layers`` table."""

    okta: int
    height_ft: float  # base above aerodrome level [ft] (ampycloud's height_base)
    code: str  # e.g. "SCT032"


@dataclass
class MetarReport:
    time_utc: datetime
    metar: str  # ampycloud's METAR-like message, e.g. "FEW032 SCT130", "NCD", "NSC"
    groups: list[MetarGroup] = field(default_factory=list)
    hits: int = 0  # hit rows given to ampycloud
    measurements: int = 0  # ceilometer × time measurements behind them


def run_ampycloud(data, msa_ft: float | None = None):
    """:func:`ampycloud.run` on a hit table; returns its CeiloChunk.

    Sets ampycloud's declared ``ceilo`` dtype to ``StringDtype("python")`` (see the module
    docstring) and silences pandas' deprecation warnings raised inside ampycloud.
    """
    import pandas as pd
    import ampycloud
    from ampycloud.ceilo_data import CeiloChunk

    CeiloChunk.DATA_COLS["ceilo"] = pd.StringDtype("python")
    prms = {} if msa_ft is None else {"MSA": float(msa_ft)}
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", category=DeprecationWarning, module=r"ampycloud(\..*)?$")
        warnings.filterwarnings("ignore", category=FutureWarning, module=r"ampycloud(\..*)?$")
        try:
            return ampycloud.run(data, prms=prms)
        except ampycloud.errors.AmpycloudError as exc:
            raise RecordingError(f"ampycloud: {exc}") from None


def metar_report(time_utc: datetime, window, msa_ft: float | None = None) -> MetarReport:
    """METAR groups at ``time_utc`` from the ``(time_utc, PairHits)`` of its window."""
    window = list(window)
    meas = sum(ph.measurements for _, ph in window)
    data = hit_table(window, time_utc)
    if len(data) == 0:
        return MetarReport(time_utc, "", [], 0, 0)
    chunk = run_ampycloud(data, msa_ft)
    msg = chunk.metar_msg()
    groups = []
    lay = chunk.layers
    if lay is not None and len(lay):
        msa = math.inf if chunk.msa is None else float(chunk.msa)
        for _, row in lay.iterrows():
            if bool(row["significant"]) and float(row["height_base"]) < msa:
                groups.append(MetarGroup(int(row["okta"]), float(row["height_base"]), str(row["code"])))
    return MetarReport(time_utc, msg, groups, len(data), meas)


METAR_COLUMNS = ("time_utc", "metar", "n_groups", "okta_1", "height_ft_1", "code_1", "okta_2", "height_ft_2",
                 "code_2", "okta_3", "height_ft_3", "code_3", "hits", "measurements")
_MAX_GROUPS = 3  # a METAR has at most 3 groups of this kind (ICAO significance rules) — more get more columns


def write_metar_csv(reports: list[MetarReport], out) -> None:
    """One row per METAR time: time (ISO 8601 Z), the string, per group okta, height [ft], code."""
    from cbh.fileio import atomic_write
    from cbh.outputs.export import write_error

    ng = max([_MAX_GROUPS] + [len(r.groups) for r in reports])
    cols = ["time_utc", "metar", "n_groups"]
    for i in range(1, ng + 1):
        cols += [f"okta_{i}", f"height_ft_{i}", f"code_{i}"]
    cols += ["hits", "measurements"]
    try:
        with atomic_write(out) as tmp, open(tmp, "w", newline="") as fh:
            w = csv.writer(fh, lineterminator="\n")
            w.writerow(cols)
            for r in reports:
                row = [r.time_utc.astimezone(timezone.utc).strftime("%Y-%m-%dT%H:%M:%S.%fZ"), r.metar, len(r.groups)]
                for i in range(ng):
                    if i < len(r.groups):
                        g = r.groups[i]
                        row += [g.okta, f"{g.height_ft:.0f}", g.code]
                    else:
                        row += ["", "", ""]
                row += [r.hits, r.measurements]
                w.writerow(row)
    except OSError as exc:
        raise write_error(Path(out), exc) from None
