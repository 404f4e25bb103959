"""`cbh export --product irradiance`: GHI nowcasts at ground sites from recorded sessions
(:mod:`cbh.outputs.nowcast` has the physics)."""
from __future__ import annotations

import csv
import logging
import math
from datetime import timedelta
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from cbh.errors import ConfigError, RecordingError
from cbh.fileio import atomic_write

__all__ = ["export_irradiance", "nowcast_rows", "COLUMNS"]

log = logging.getLogger(__name__)

COLUMNS = ["time_utc", "site", "lead_s", "valid_time_utc", "ghi_wm2", "clear_sky_ghi_wm2", "clear_sky_index",
           "shade_probability", "k_sun", "k_shade", "flags"]


def _iso(t) -> str:
    return t.strftime("%Y-%m-%dT%H:%M:%SZ")


def nowcast_rows(sessions, sites: list[str], leads_s, pyranometer=None) -> tuple[list[dict], dict]:
    """The nowcast rows (dicts of :data:`COLUMNS`, numbers as floats) of every recorded pair, site
    and lead, in time order; and a summary (pairs, sites, the levels learned)."""
    from cbh.actions.pairground import pair_ground
    from cbh.flags import INVALIDATING
    from cbh.outputs import nowcast as nc
    from cbh.outputs.record import open_session
    from cbh.pipeline.config import PipelineConfig

    if not sites:
        raise ConfigError("--product irradiance needs at least one --site LAT,LON[,ALT_M]")
    pyr = nc.read_pyranometer(pyranometer) if pyranometer else None
    rows, seen, station, places = [], set(), None, None
    levels: dict[str, nc.Levels] = {}
    pending: dict[str, list] = {}  # site → (valid time, shade probability) of forecasts not yet verified
    k_record: dict = {}  # site → the pyranometer's clear-sky index over its record
    reads: dict = {}  # the ensemble members' reads, each made once (nowcast.lagged_shade's cache)
    history: list = []  # the recent valid pairs on the ground (one per ENSEMBLE_STEP_S), oldest first
    recent: list = []  # every valid pair's layer motions of the last ENSEMBLE_S (the motion errors)
    for path in sessions:
        s = open_session(path)
        st = s.station
        if station is None:
            station = st
            places = nc.parse_sites(sites, st)
            levels = {p.name: nc.Levels() for p in places}
            if pyr is None and st.pyranometer is not None:  # the recorded station's [station] pyranometer
                if Path(st.pyranometer).is_file():
                    pyr = nc.read_pyranometer(st.pyranometer)
                else:
                    log.warning("the station's pyranometer %s is not here: default levels", st.pyranometer)
        elif (st.latitude_deg, st.longitude_deg) != (station.latitude_deg, station.longitude_deg):
            raise RecordingError(f"{path}: another station ({st.name}) than the first session's ({station.name})")
        cfg = PipelineConfig.from_dict(s.config, where="recorded pipeline config")
        for pair in s.pairs():
            res = pair.result
            if res.time_utc is None or res.time_utc in seen:
                continue
            seen.add(res.time_utc)
            bad = sorted(set(res.flags) & INVALIDATING)
            pg = pair_ground(st, cfg.masks, res)
            history = _ensemble(history, pg, recent) if not bad else history
            nc.prune_cache(reads, history)
            for site in places:
                if pyr is not None:  # the forecasts now verified (valid up to this issue time) teach the levels
                    _learn(levels[site.name], pending, site, pyr, res.time_utc)
                    _sunny_prior(levels[site.name], site, pyr, res.time_utc, k_record)
                ks, kd = levels[site.name].levels(res.time_utc)
                got = _forecasts(history, site, res.time_utc, leads_s, bad, pyr is not None, reads)
                for lead, (tv, p, why) in got.items():
                    if lead in LEARN_LEADS_S and math.isfinite(p):
                        pending.setdefault(site.name, []).append((tv, p))
                for lead in leads_s:
                    tv, p, why = got[float(lead)]
                    rows.append({"time_utc": res.time_utc, "site": site.name, "lead_s": float(lead), "valid_time_utc": tv,
                                 "shade_probability": p, "k_sun": ks, "k_shade": kd, "flags": why, "_site": site})
    if not rows:
        raise RecordingError("no complete pairs in the recording(s): nothing to nowcast")
    _fill_ghi(rows, places)
    summary = {"pairs": len(seen), "sites": [p.name for p in places], "leads_s": list(leads_s),
               "levels": {n: {"k_sun": round(lv.levels()[0], 3), "k_shade": round(lv.levels()[1], 3),
                              "observations": lv.n} for n, lv in levels.items()}}
    return rows, summary


def ghi_series(sessions, sites: list[str], pyranometer=None, leads_s=(300.0, 600.0)) -> dict:
    """Per site, its GHI series over the recording, each at its valid time: ``clear`` (pvlib's
    clear sky), ``nowcast N min ahead`` for each of ``leads_s``, and ``measured`` (the
    pyranometer, when given). {site: {name: (times datetime64[us] (T,), values [W/m²] (T,))}}."""
    from cbh.outputs import nowcast as nc

    rows, summary = nowcast_rows(sessions, sites, (0.0, *leads_s), pyranometer)
    t64 = lambda ts: np.array([np.datetime64(x.replace(tzinfo=None), "us") for x in ts])  # noqa: E731
    measured = nc.read_pyranometer(pyranometer) if pyranometer is not None else None
    out = {}
    for name in summary["sites"]:
        mine = [r for r in rows if r["site"] == name]
        series = {"clear": (t64([r["valid_time_utc"] for r in mine if r["lead_s"] == 0]),
                            np.array([r["clear_sky_ghi_wm2"] for r in mine if r["lead_s"] == 0]))}
        for lead in leads_s:
            sel = [r for r in mine if r["lead_s"] == lead]
            series[f"nowcast {lead / 60:.0f} min ahead"] = (t64([r["valid_time_utc"] for r in sel]),
                                                            np.array([r["ghi_wm2"] for r in sel], np.float64))
        if measured is not None:
            times, g = measured
            lo, hi = min(r["time_utc"] for r in mine), max(r["valid_time_utc"] for r in mine)
            keep = [i for i, x in enumerate(times) if lo <= x <= hi]
            series["measured"] = (t64([times[i] for i in keep]), np.asarray(g)[keep])
        out[name] = series
    return out


#: The levels learn from the forecasts at these leads once verified, whichever leads are asked
#: for (every minute over the ensemble's 10 min) [s].
LEARN_LEADS_S = tuple(float(s) for s in range(0, 601, 60))


def _forecasts(history: list, site, issue, leads_s, bad: list, learn: bool, cache: dict | None = None) -> dict:
    """{lead [s]: (valid time, shade probability, reason)} of ``site`` at the asked ``leads_s``
    and, when ``learn``, at :data:`LEARN_LEADS_S`: the time-lagged ensemble of ``history``
    (:func:`cbh.outputs.nowcast.lagged_shade`); NaN with ``pair_invalid:…`` for an invalid pair."""
    from cbh.geometry.sun import sun_position
    from cbh.outputs import nowcast as nc

    out = {}
    for lead in sorted({float(x) for x in leads_s} | (set(LEARN_LEADS_S) if learn else set())):
        tv = issue + timedelta(seconds=lead)
        if bad:
            out[lead] = (tv, math.nan, "pair_invalid:" + "+".join(bad))
            continue
        sp = sun_position(site.latitude_deg, site.longitude_deg, site.altitude_m, tv)
        out[lead] = (tv, *nc.lagged_shade(history, site, sp.direction_enu if sp.zenith_deg < 90 else None, tv, cache))
    return out


def _ensemble(history: list, pg, recent: list) -> list:
    """``history`` with ``pg`` (a valid pair) as its newest member: the older ones kept one per
    ``ENSEMBLE_STEP_S`` and at most ``ENSEMBLE_S`` old (:func:`cbh.outputs.nowcast.lagged_shade`).
    ``recent`` (updated in place: ``pg``'s layers join, those older than ``ENSEMBLE_S`` leave) holds
    every valid pair's layer heights and motions, not only the members': ``pg`` gets its layers'
    motion errors measured over them (:func:`cbh.outputs.nowcast.motion_errors`), from the second
    motion on rather than after a minute of pairs at a cadence under ``ENSEMBLE_STEP_S``."""
    from cbh.outputs import nowcast as nc

    recent[:] = [r for r in recent if 0 < (pg.time_utc - r.time_utc).total_seconds() <= nc.ENSEMBLE_S]
    recent.append(SimpleNamespace(time_utc=pg.time_utc, heights=list(pg.heights), motions=list(pg.motions)))
    pg.motion_errors = nc.motion_errors(recent)
    kept = [h for h in history if 0 < (pg.time_utc - h.time_utc).total_seconds() <= nc.ENSEMBLE_S]
    out: list = []
    for h in kept:
        if not out or (h.time_utc - out[-1].time_utc).total_seconds() >= nc.ENSEMBLE_STEP_S - 1.0:
            out.append(h)
    return [*out, pg]


def _learn(levels, pending: dict, site, pyr, now) -> None:
    """Every forecast of ``site`` (at :data:`LEARN_LEADS_S`) valid by ``now``,
    with the clear-sky index the pyranometer measured at its valid time, into ``levels`` (one
    pvlib call for them all)."""
    due = [(tv, p) for tv, p in pending.get(site.name, []) if tv <= now]
    pending[site.name] = [(tv, p) for tv, p in pending.get(site.name, []) if tv > now]
    if due:
        for (tv, p), k in zip(due, _measured_index(pyr, site, [tv for tv, _ in due])):
            levels.add(p, k, tv)


def _sunny_prior(levels, site, pyr, now, k_record: dict) -> None:
    """The levels' prior from the pyranometer's last hour before ``now`` (its sunny level,
    :func:`cbh.outputs.nowcast.sunny_level`; the shade level scaled with it); unchanged when the
    record says too little. ``k_record`` caches each site's clear-sky index over the record."""
    from cbh.outputs import nowcast as nc

    if site.name not in k_record:
        ts = np.array([t.timestamp() for t in pyr[0]])
        k_record[site.name] = (ts, _measured_index(pyr, site, list(pyr[0]), exact=True))
    ts, k = k_record[site.name]
    t = now.timestamp()
    ks = nc.sunny_level(k[(ts < t) & (ts >= t - nc.SUNNY_HISTORY_S)])
    if math.isfinite(ks):
        levels.set_prior(ks, nc.K_SHADE / nc.K_SUN * ks)


def _measured_index(pyr, site, times, exact: bool = False) -> np.ndarray:
    """The clear-sky index the pyranometer measured at ``times`` (NaN: no record, or night);
    ``exact``: ``times`` are the record's own."""
    from cbh.outputs import nowcast as nc

    g = np.asarray(pyr[1], np.float64) if exact else np.array([nc.measured_at(pyr[0], pyr[1], t) for t in times])
    cs = nc.clear_sky_ghi(site, times)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where((cs > 50.0) & np.isfinite(g), g / cs, np.nan)


def _fill_ghi(rows: list[dict], places) -> None:
    """Clear-sky GHI (one pvlib call per site), the clear-sky index and GHI of every row."""
    from cbh.outputs import nowcast as nc

    for site in places:
        mine = [r for r in rows if r["_site"] is site]
        cs = nc.clear_sky_ghi(site, [r["valid_time_utc"] for r in mine])
        for r, c in zip(mine, cs):
            p = r["shade_probability"]
            k = r["k_sun"] + (r["k_shade"] - r["k_sun"]) * p if math.isfinite(p) else math.nan
            r["clear_sky_ghi_wm2"] = float(c)
            r["clear_sky_index"] = k
            r["ghi_wm2"] = k * float(c) if c > 0 else (0.0 if math.isfinite(k) else math.nan)
            if c <= 0 and not r["flags"]:
                r["flags"] = "night"


def _fmt(v) -> str:
    if isinstance(v, float):
        return "" if not math.isfinite(v) else f"{v:.4g}" if abs(v) < 10 else f"{v:.1f}"
    if hasattr(v, "strftime"):
        return _iso(v)
    return str(v)


def export_irradiance(sessions, out, sites: list[str], leads: str | None = None, pyranometer=None,
                      fmt: str | None = None) -> str:
    """Write the nowcast to ``out``: CSV (one row per issue time, site and lead: :data:`COLUMNS`)
    or NetCDF (an xarray dataset on (time, lead, site), what pvlib and pysteps users read); returns
    the CLI's summary line."""
    from cbh.outputs import nowcast as nc

    out = Path(out)
    kind = (fmt or out.suffix.lstrip(".") or "csv").lower()
    if kind in ("nc", "netcdf"):
        kind = "netcdf"
    if kind not in ("csv", "netcdf"):
        raise ConfigError(f"--product irradiance: csv or netcdf, not {kind!r}")
    if out.is_dir() or not out.parent.is_dir():
        raise RecordingError(f"--out {out}: give a file in an existing folder")
    rows, summary = nowcast_rows(sessions, sites, nc.parse_leads(leads), pyranometer)
    try:
        with atomic_write(out) as tmp:
            if kind == "csv":
                with open(tmp, "w", newline="") as fh:
                    w = csv.writer(fh)
                    w.writerow(COLUMNS)
                    for r in rows:
                        w.writerow([_fmt(r[c]) for c in COLUMNS])
            else:
                _dataset(rows, summary).to_netcdf(tmp)
    except OSError as exc:
        from cbh.outputs.export import write_error

        raise write_error(out, exc) from None
    lv = "; ".join(f"{n}: k_sun {v['k_sun']:.2f}, k_shade {v['k_shade']:.2f} from {v['observations']} measurements"
                   for n, v in summary["levels"].items())
    return (f"wrote {len(rows)} nowcast rows ({summary['pairs']} issue times x {len(summary['sites'])} site(s) x "
            f"{len(summary['leads_s'])} leads) to {out}"
            + (f" (levels {lv})" if any(v["observations"] for v in summary["levels"].values()) else ""))


def _dataset(rows: list[dict], summary: dict):
    """The nowcast as an xarray dataset on (time, lead_time, site)."""
    import xarray as xr

    times = sorted({r["time_utc"] for r in rows})
    leads, sites = summary["leads_s"], summary["sites"]
    ti = {t: i for i, t in enumerate(times)}
    li = {float(v): i for i, v in enumerate(leads)}
    si = {n: i for i, n in enumerate(sites)}
    shape = (len(times), len(leads), len(sites))
    data = {k: np.full(shape, np.nan) for k in ("ghi_wm2", "clear_sky_ghi_wm2", "clear_sky_index", "shade_probability")}
    for r in rows:
        j = (ti[r["time_utc"]], li[r["lead_s"]], si[r["site"]])
        for k in data:
            data[k][j] = r[k]
    units = {"ghi_wm2": "W m-2", "clear_sky_ghi_wm2": "W m-2", "clear_sky_index": "1", "shade_probability": "1"}
    t64 = np.array([np.datetime64(t.replace(tzinfo=None), "ns") for t in times])
    ds = xr.Dataset({k: (("time", "lead_time", "site"), v, {"units": units[k]}) for k, v in data.items()},
                    coords={"time": t64, "lead_time": ("lead_time", np.asarray(leads, np.float64), {"units": "s"}),
                            "site": np.asarray(sites, dtype=object)},
                    attrs={"title": "cbh irradiance nowcast", "source": "cbh export --product irradiance",
                           "Conventions": "CF-1.8"})
    return ds
