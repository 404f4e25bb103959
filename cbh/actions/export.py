"""`cbh export`: layer tables (CSV, Parquet, CF NetCDF, daily files) and ground maps of sessions.

Products:

* ``layers`` (default): :mod:`cbh.outputs.export` (one file, or one per UTC day with ``daily``).
* ``cloudmap`` / ``shadow``: camera 1's cloud mask of every recorded pair projected onto the
  station's ground grid (:mod:`cbh.geometry.ground`; grid from the ``[ground]`` table of the
  recorded station, or of ``station`` when given), with the sun from the one sun function
  (:func:`cbh.geometry.sun.sun_position`); written by :mod:`cbh.outputs.maps`.

Usable sky for the maps is rebuilt from the recorded pipeline config: image circle, zenith
limit and the masked sun disk (the obstacle mask is not recorded with the pairs, so horizon
obstacles count as sky; they lie beyond the zenith limit in most stations). Pairs with an
invalidating flag (:data:`cbh.flags.INVALIDATING`) get unknown (NaN) maps: their layer heights
are not to be trusted. The sun-blocking answer "now" comes from the pair itself; when the sun's
ray crosses the masked sun disk (usual: the disk is masked), it is taken from the most recent
earlier pair that can tell, advected by the layer motion to now (at most ``MAX_FALLBACK_S``).
"""
from __future__ import annotations

import logging
import math
from collections import deque
from datetime import timedelta
from pathlib import Path

import numpy as np

from cbh.errors import ConfigError, RecordingError
from cbh.flags import INVALIDATING
from cbh.geometry import ground
from cbh.actions.pairground import PairGround, _sun, pair_ground  # noqa: F401  (re-exported)
from cbh.outputs import export as layer_export
from cbh.outputs.record.reader import _mcap_state
from cbh.outputs.maps import (LEAD_TIMES_S, MAP_FORMATS, PRODUCTS, GroundMaps, to_byte, write_maps_netcdf,
                              write_maps_npz)

__all__ = ["export", "format_from_suffix", "ground_maps", "PairGround", "pair_ground", "SUFFIX_FORMATS",
           "MAX_FALLBACK_S"]

log = logging.getLogger(__name__)

SUFFIX_FORMATS = {".csv": "csv", ".parquet": "parquet", ".nc": "netcdf", ".nc4": "netcdf", ".netcdf": "netcdf",
                  ".npz": "npz"}
MAX_FALLBACK_S = 300.0  # oldest earlier pair the "now" sun-blocking answer may come from [s]


def format_from_suffix(out) -> str | None:
    """csv | parquet | netcdf | npz from the output's suffix; None for an unknown suffix."""
    return SUFFIX_FORMATS.get(Path(out).suffix.lower())


def _sun_blocked(station, pg: PairGround, history=(), at_m=(0.0, 0.0)) -> list[float]:
    """Sun blocked at ground point ``at_m`` (default: the station) now and at LEAD_TIMES_S.

    "Now" falls back on the earlier pairs in ``history`` (most recent first, at most
    ``MAX_FALLBACK_S`` old) advected to now, when the pair itself cannot tell: the cloud on the
    sun ray is inside the masked sun disk until it has moved a disk radius (8° at the slant
    range: about 230 m at 1.2 km with the sun 43° off the zenith, i.e. ~40 s at 6 m/s).
    """
    out = []
    for lead in LEAD_TIMES_S:
        if not pg.valid:
            out.append(math.nan)
            continue
        sd, zen = _sun(station, pg.time_utc + timedelta(seconds=lead))
        sd = sd if zen < 90.0 else None
        v = ground.sun_blocked(pg.camera, pg.labels, pg.heights, pg.motions, sd, lead, at_m=at_m,
                               cloud_fraction=pg.cloud_fraction)
        if lead == 0:
            for prev in history:
                age = (pg.time_utc - prev.time_utc).total_seconds()
                if not math.isnan(v) or not 0 < age <= MAX_FALLBACK_S:
                    break
                if prev.valid:  # an earlier pair, advected to now
                    v = ground.sun_blocked(prev.camera, prev.labels, prev.heights, prev.motions, sd, age, at_m=at_m,
                                           cloud_fraction=prev.cloud_fraction)
        out.append(v)
    return out


def ground_maps(sessions, station=None, products=PRODUCTS) -> GroundMaps:
    """Cloud and/or shadow maps of every pair of the sessions (time order).

    Pairs are streamed (one pair's images and height map in memory at a time); the maps are
    held as int8 (1 / 0 / −1 unknown): about T × (L + 1) × n² bytes per product, e.g. 175 MB
    for a day at a 60 s cadence on the default 201 × 201 grid with two layers. Only the maps of
    ``products`` are computed (the others stay empty, shape (T, 0, 0)).
    """
    from cbh.outputs.record import open_session
    from cbh.pipeline.config import PipelineConfig

    opened = []
    st0 = None
    for path in sessions:
        s = open_session(path)
        st = station if station is not None else s.station
        if st0 is None:
            st0 = st
        elif st.name != st0.name:
            raise RecordingError(f"{path}: station {st.name!r} differs from {st0.name!r}; one station at a time")
        cfg = PipelineConfig.from_dict(s.config, where="recorded pipeline config")
        heads = [(p.time_utc, len(p.result.layers)) for p in s.pairs(layers_only=True)]  # cheap first pass
        opened.append((s, st, cfg, heads))
    times = sorted({t for *_, heads in opened for t, _ in heads})
    if not times:
        raise RecordingError("no complete pairs in the recording(s): nothing to export")
    index = {t: i for i, t in enumerate(times)}
    grid = st0.ground
    T, n = len(times), grid.n
    Lmax = max(1, max(k for *_, heads in opened for _, k in heads))
    want_cloud, want_shadow = "cloudmap" in products, "shadow" in products
    cn, sn = (n if want_cloud else 0), (n if want_shadow else 0)
    layer_cloud = np.full((T, Lmax if want_cloud else 0, cn, cn), -1, np.int8)
    cloud = np.full((T, cn, cn), -1, np.int8)
    shadow = np.full((T, sn, sn), -1, np.int8)
    shadow_layer = np.full((T, sn, sn), -1, np.int8)
    heights = np.full((T, Lmax), np.nan)
    covers = np.full((T, Lmax), np.nan)
    motion = np.full((T, Lmax, 2), np.nan)
    zen = np.full(T, np.nan)
    az = np.full(T, np.nan)
    blocked = np.full((T, len(LEAD_TIMES_S)), np.nan, np.float32)
    done = np.zeros(T, bool)
    history: deque = deque()  # earlier pairs, most recent first, within MAX_FALLBACK_S
    for s, st, cfg, heads in sorted(opened, key=lambda o: o[3][0][0] if o[3] else times[0]):
        for pair in s.pairs():
            res = pair.result
            i = index[res.time_utc]
            if done[i]:
                log.warning("dropping a second pair at %s (same session given twice?)", res.time_utc.isoformat())
                continue
            done[i] = True
            pg = pair_ground(st, cfg.masks, res)
            k = len(pg.heights)
            heights[i, :k], covers[i, :k] = pg.heights, pg.covers
            motion[i, :k] = np.array(pg.motions).reshape(k, 2)
            zen[i] = pg.sun_zenith_deg
            if pg.sun_dir is not None:
                az[i] = math.degrees(math.atan2(pg.sun_dir[0], pg.sun_dir[1])) % 360.0
            if pg.valid and want_cloud:
                lc = ground.cloud_maps(pg.camera, pg.labels, pg.heights, grid)
                layer_cloud[i, :k] = to_byte(lc)
                if k:
                    cloud[i] = to_byte(ground.combine_layers(list(lc), (n, n)))
                elif pg.cloud_fraction == 0:
                    cloud[i] = 0
            if pg.valid and want_shadow:
                sm, owner = _shadow(pg, grid)
                shadow[i], shadow_layer[i] = to_byte(sm), owner
            while history and (history[0].time_utc >= res.time_utc
                               or (res.time_utc - history[-1].time_utc).total_seconds() > MAX_FALLBACK_S):
                history.popleft() if history[0].time_utc >= res.time_utc else history.pop()
            blocked[i] = _sun_blocked(st, pg, history)
            history.appendleft(pg)
    return GroundMaps(grid=grid, times=times, layer_cloud=layer_cloud, cloud=cloud, shadow=shadow,
                      layer_height_m=heights, layer_cover=covers, motion_ms=motion, sun_zenith_deg=zen,
                      sun_azimuth_deg=az, sun_blocked=blocked, shadow_layer=shadow_layer, station=st0.name,
                      attrs=dict(st0.metadata))


def _shadow(pg: PairGround, grid) -> tuple[np.ndarray, np.ndarray]:
    """Shadow map and the lowest layer casting each shadow (−1 none)."""
    by_layer = ground.layer_shadows(pg.camera, pg.labels, pg.heights, pg.sun_dir, grid)
    sm = ground.shadow_map(pg.camera, pg.labels, pg.heights, pg.sun_dir, grid, cloud_fraction=pg.cloud_fraction,
                           by_layer=by_layer)
    owner = np.full(sm.shape, -1, np.int8)
    for k in range(by_layer.shape[0] - 1, -1, -1):  # lowest layer last: it wins
        owner[by_layer[k] == 1] = k
    return sm, owner


def export(sessions, out, fmt: str | None = None, *, product: str = "layers", daily: bool = False,
           station=None, sites=(), leads: str | None = None, pyranometer=None) -> str:
    """Export sessions; returns the one-line summary the CLI prints.

    Parameters
    ----------
    sessions : list of path
    out : path
        Output file, or a directory with ``daily``.
    fmt : str or None
        csv | parquet | netcdf | npz (default: from the suffix of ``out``; netcdf for ``daily``
        and a suffix-less directory).
    product : {"layers", "cloudmap", "shadow"}
    daily : bool
        Layers only: one file per UTC day in directory ``out``.
    station : Station or None
        Ground grid and camera geometry for the maps (default: the recorded station).
    """
    from cbh.actions import aviation
    from cbh.fileio import refuse_inputs

    out = Path(out)
    refuse_inputs([out], list(sessions) if isinstance(sessions, (list, tuple)) else [sessions], "--out")

    if product == "irradiance":  # GHI nowcasts at sites: cbh/actions/nowcast.py
        from cbh.actions.nowcast import export_irradiance

        if daily:
            raise ConfigError("--daily is for --product layers, not irradiance")
        pyranometer = pyranometer or (station.pyranometer if station is not None else None)
        refuse_inputs([out], [pyranometer], "--out")
        return export_irradiance(sessions, out, list(sites), leads, pyranometer, fmt)
    if sites or leads or pyranometer:
        raise ConfigError("--site, --leads and --pyranometer are for --product irradiance")
    if product in aviation.PRODUCTS:  # metar | cl61 | eprofile: cbh/actions/aviation.py
        if not daily and out.is_file() and _mcap_state(out) != "foreign":
            raise RecordingError(f"{out} is a recording: an export never replaces one (give another --out)")
        if daily:
            raise ConfigError(f"--daily is for --product layers, not {product}")
        return aviation.export_product(sessions, out, product, fmt)
    if fmt is None:
        fmt = format_from_suffix(out)
        if fmt is None and daily:
            fmt = "netcdf"
        if fmt is None:
            raise ConfigError(f"--format: not given and {out.name!r} has no known suffix (.csv, .parquet, .nc, .npz)")
    fmt = fmt.lower()
    if not daily and out.is_file() and _mcap_state(out) != "foreign":
        # `-o SESSION.mcap -f csv` replaced the recording with its own export
        raise RecordingError(f"{out} is a recording: an export never replaces one (give another --out)")
    if product == "layers":
        if fmt == "npz":
            raise ConfigError("--format npz is for --product cloudmap|shadow (layers: csv, parquet, netcdf)")
        if daily:
            done = layer_export.export_daily(sessions, fmt, out)
            return "\n".join(f"wrote {steps} time steps ({rows} rows) to {p}" for p, rows, steps in done)
        rows, steps = layer_export.export_sessions(sessions, fmt, out)
        return f"wrote {steps} time steps ({rows} rows) to {out}"
    if product not in PRODUCTS:
        raise ConfigError(f"--product: unknown {product!r} (valid: layers, irradiance, {', '.join(PRODUCTS)}, "
                          f"{', '.join(aviation.PRODUCTS)})")
    if daily:
        raise ConfigError("--daily is for --product layers")
    if fmt not in MAP_FORMATS:
        raise ConfigError(f"--format: {fmt!r} is not a map format (valid: {', '.join(MAP_FORMATS)})")
    if out.is_dir():
        raise RecordingError(f"--out {out}: is a directory; give a file name")
    if not out.parent.is_dir():
        raise RecordingError(f"output directory does not exist: {out.parent}")
    maps = ground_maps(sessions, station, products=(product,))
    (write_maps_netcdf if fmt == "netcdf" else write_maps_npz)(maps, product, out)
    g = maps.grid
    return (f"wrote {product} of {len(maps.times)} time steps on a {g.n}x{g.n} grid "
            f"({g.resolution_m:g} m cells) to {out}")
