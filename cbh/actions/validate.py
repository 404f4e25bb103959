"""`cbh validate --ceilometer FILE… REC…`: cbh's cloud base above a co-located ceilometer against it.

For every recorded pair, cbh's base *in the column above the ceilometer* is the lowest layer k
whose cloud map is cloud at the ceilometer's ground point (:func:`cbh.geometry.ground.lookup_layer`
at the layer's height, camera 1's layer labels); a column known clear at every layer is "no
cloud", one outside the usable sky is skipped. The ceilometer's position (ENU, m) is
``[ceilometer] position_m`` in the station file, default the ENU origin. Each pair is matched
with the ceilometer profiles within ``match_s`` seconds of it (the median of their first bases;
heights above the instrument, taken as above the ENU origin).

Statistics of the matched pairs where both see a base: MAE, RMSE, bias (cbh − ceilometer),
R², and the fraction within 150 m (the GOA-SCAN measure), for all, by height band
(:data:`BANDS_M`) and by sky type (``broken/overcast``: cbh total cover ≥ 5 okta, else
``few/scattered``). Written as JSON, with a scatter plot and a time series (PNG).
"""
from __future__ import annotations

import json
import logging
import math
from pathlib import Path

import numpy as np

from cbh.errors import ConfigError, InputError, RecordingError
from cbh.fileio import atomic_write

__all__ = ["BANDS_M", "column_bases", "match", "statistics", "validate"]

log = logging.getLogger(__name__)

BANDS_M = ((0.0, 2000.0), (2000.0, 5000.0), (5000.0, math.inf))  # height bands of the statistics [m]
WITHIN_M = 150.0  # GOA-SCAN agreement threshold [m]


def ceilometer_position(station) -> np.ndarray:
    """ENU position [m] of the ceilometer: ``[ceilometer] position_m`` (default the origin)."""
    sec = station.sections.get("ceilometer", {}) if hasattr(station, "sections") else {}
    unknown = set(sec) - {"position_m"}
    if unknown:
        raise ConfigError(f"ceilometer.{sorted(unknown)[0]}: unknown key (valid: position_m)")
    p = sec.get("position_m", [0.0, 0.0, 0.0])
    try:
        v = np.asarray([float(x) for x in p], np.float64)
    except (TypeError, ValueError):
        raise ConfigError(f"ceilometer.position_m: expected 3 numbers [m], got {p!r}") from None
    if v.shape != (3,):
        raise ConfigError(f"ceilometer.position_m: expected 3 numbers [m], got {p!r}")
    return v


def column_bases(sessions, position_m=None):
    """(times datetime64[ns] (T,), cbh base above the ceilometer [m] (T,), NaN = clear, total okta (T,),
    known (T,) bool) of every valid pair."""
    from cbh.actions.pairground import pair_ground
    from cbh.geometry.ground import lookup_layer
    from cbh.outputs.export import okta
    from cbh.outputs.record import open_session
    from cbh.pipeline.config import PipelineConfig

    T, B, O, K = [], [], [], []
    for path in sessions:
        s = open_session(path)
        st = s.station
        pos = ceilometer_position(st) if position_m is None else np.asarray(position_m, np.float64)
        cfg = PipelineConfig.from_dict(s.config, where="recorded pipeline config")
        for pair in s.pairs():
            pg = pair_ground(st, cfg.masks, pair.result)
            if not pg.valid:
                continue
            base, known = math.nan, bool(pg.cloud_fraction == 0)
            for k, h in enumerate(pg.heights):
                v = float(lookup_layer(pg.camera, pg.labels, k, np.array([[pos[0], pos[1], h]]))[0])
                if v == 1.0:
                    base, known = h - pos[2], True
                    break
                if v == 0.0:
                    known = True
            T.append(np.datetime64(pg.time_utc.replace(tzinfo=None), "ns"))
            B.append(base)
            O.append(okta(pg.cloud_fraction))
            K.append(known)
    if not T:
        raise RecordingError("no complete pairs in the recording(s): nothing to validate")
    order = np.argsort(np.array(T))
    return (np.array(T)[order], np.array(B, np.float64)[order], np.array(O)[order], np.array(K, bool)[order])


def match(cbh_t, cbh_b, ceilo_t, ceilo_b, match_s: float):
    """Ceilometer first base matched to each cbh time: median of those within ``match_s`` s
    (NaN = no cloud seen; also NaN with ``n == 0`` = no profile). Returns (bases (T,), n (T,))."""
    ci = np.argsort(ceilo_t)
    ct, cb = ceilo_t[ci], ceilo_b[ci]
    dt = np.timedelta64(int(match_s * 1e9), "ns")
    out = np.full(cbh_t.size, np.nan)
    n = np.zeros(cbh_t.size, int)
    for i, t in enumerate(cbh_t):
        a, b = np.searchsorted(ct, t - dt), np.searchsorted(ct, t + dt, side="right")
        n[i] = b - a
        if b > a:
            v = cb[a:b]
            v = v[np.isfinite(v)]
            if v.size * 2 >= (b - a) and v.size:  # cloud in at least half of the profiles
                out[i] = float(np.median(v))
    return out, n


def statistics(cbh_m, ceilo_m) -> dict:
    """MAE, RMSE, bias (cbh − ceilometer), R², fraction within 150 m, n [m]."""
    a, b = np.asarray(cbh_m, np.float64), np.asarray(ceilo_m, np.float64)
    ok = np.isfinite(a) & np.isfinite(b)
    a, b = a[ok], b[ok]
    if a.size == 0:
        return {"n": 0, "mae_m": None, "rmse_m": None, "bias_m": None, "r2": None, "within_150m": None}
    d = a - b
    ss = float(((b - b.mean()) ** 2).sum())
    r2 = 1.0 - float((d**2).sum()) / ss if ss > 0 else None
    return {"n": int(a.size), "mae_m": float(np.abs(d).mean()), "rmse_m": float(np.sqrt((d**2).mean())),
            "bias_m": float(d.mean()), "r2": r2, "within_150m": float((np.abs(d) <= WITHIN_M).mean())}


def detection(cbh_m, ceilo_m, matched) -> dict:
    """The detection table of a comparison (the matched pairs): both cloudy (hits), the ceilometer
    cloudy and cbh clear above it (misses), cbh cloudy and the ceilometer clear (false alarms),
    both clear; with the probability of detection and the false-alarm ratio (None: undefined)."""
    a, b, m = np.asarray(cbh_m, np.float64), np.asarray(ceilo_m, np.float64), np.asarray(matched, bool)
    ca, cb = np.isfinite(a) & m, np.isfinite(b) & m
    hits, misses = int((ca & cb).sum()), int((~ca & cb & m).sum())
    fa, clear = int((ca & ~cb).sum()), int((m & ~ca & ~cb).sum())
    return {"hits": hits, "misses": misses, "false_alarms": fa, "both_clear": clear,
            "pod": hits / (hits + misses) if hits + misses else None,
            "far": fa / (hits + fa) if hits + fa else None}


def _save(fig, path: Path) -> None:
    """A figure written whole or not at all (a full disk leaves the older file)."""
    import matplotlib.pyplot as plt

    from cbh.outputs.figures import save_figure

    try:
        save_figure(fig, path)
    finally:
        plt.close(fig)


def _span(t) -> str:
    t = np.sort(np.asarray(t).astype("datetime64[s]"))
    return f"{t[0]}Z .. {t[-1]}Z" if t.size else "nothing"


def _plots(t, a, b, out_dir: Path, stem: str) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    paths = []
    ok = np.isfinite(a) & np.isfinite(b)
    fig, ax = plt.subplots(figsize=(5, 5))
    ax.scatter(b[ok], a[ok], s=8)
    hi = float(np.nanmax(np.concatenate([a[ok], b[ok], [1.0]]))) * 1.05
    ax.plot([0, hi], [0, hi], "k--", lw=0.8)
    ax.set_xlabel("ceilometer base [m]"), ax.set_ylabel("cbh base above the ceilometer [m]")
    p = out_dir / f"{stem}-scatter.png"
    _save(fig, p)
    paths.append(p)
    fig, ax = plt.subplots(figsize=(8, 3.5))
    ax.plot(t, b, ".", ms=3, label="ceilometer")
    ax.plot(t, a, "x", ms=4, label="cbh")
    ax.set_ylabel("cloud base [m]"), ax.legend()
    fig.autofmt_xdate()
    p = out_dir / f"{stem}-timeseries.png"
    _save(fig, p)
    paths.append(p)
    return paths


#: The largest --match-s: a day [s] (a window beyond it pairs everything with everything).
MAX_MATCH_S = 86400.0


def _session_paths(sessions) -> list:
    return list(sessions) if isinstance(sessions, (list, tuple)) else [sessions]


def validate(ceilometer_files, sessions, out, match_s: float = 30.0) -> tuple[dict, str]:
    """Compare; write ``out`` (JSON) and its two PNGs beside it. Returns (report, text)."""
    from cbh.outputs.ceilometer import read_ceilometer

    from cbh.fileio import refuse_inputs

    out = Path(out)
    if not out.parent.is_dir():
        raise RecordingError(f"output directory does not exist: {out.parent}")
    if not (math.isfinite(match_s) and 0 < match_s <= MAX_MATCH_S):
        raise ConfigError(f"--match-s: a time window in seconds, > 0 and at most {MAX_MATCH_S:g} (a day), got {match_s}")
    beside = [out.parent / f"{out.stem}-{k}.png" for k in ("scatter", "timeseries")]
    refuse_inputs([out, *beside], [*ceilometer_files, *_session_paths(sessions)], "--out")
    files = []
    ct, cb = [], []
    for f in ceilometer_files:
        c = read_ceilometer(f)
        files.append({"file": str(f), "kind": c.kind, "profiles": int(c.time_utc.size), "skipped": c.skipped})
        ct.append(c.time_utc), cb.append(c.bases_m[:, 0])
    ct, cb = np.concatenate(ct), np.concatenate(cb)
    if not ct.size:
        raise InputError(f"no time-stamped profile in {', '.join(str(f) for f in ceilometer_files)}: nothing to "
                         "compare with (CL31/CL51 messages need their time stamps)")
    t, a, okt, known = column_bases(sessions)
    b, n = match(t, a, ct, cb, match_s)
    if not (n > 0).any():
        raise InputError(f"no overlap: the recording(s) span {_span(t)}, the ceilometer file(s) {_span(ct)} "
                         f"(pairs are matched to profiles within ±{match_s:g} s)")
    det = detection(a, b, known & (n > 0))
    a = np.where(known & (n > 0), a, np.nan)
    rep = {"ceilometer_files": files, "pairs": int(t.size), "matched_pairs": int((n > 0).sum()),
           "detection": det, "all": statistics(a, b), "by_height_band": {}, "by_sky_type": {}}
    for lo, hi in BANDS_M:
        sel = (b >= lo) & (b < hi)
        rep["by_height_band"][f"{lo:.0f}-{hi:.0f} m" if math.isfinite(hi) else f">={lo:.0f} m"] = statistics(a[sel], b[sel])
    for name, sel in (("broken/overcast", okt >= 5), ("few/scattered", (okt >= 0) & (okt < 5))):
        rep["by_sky_type"][name] = statistics(a[sel], b[sel])
    rep["plots"] = [str(p) for p in _plots(t.astype("datetime64[ms]").astype(object), a, b, out.parent, out.stem)]
    with atomic_write(out) as tmp:
        tmp.write_text(json.dumps(rep, indent=2))
    lines = [f"{rep['matched_pairs']} of {rep['pairs']} pairs matched to {ct.size} ceilometer profiles",
             f"  detection: {det['hits']} both cloudy, {det['misses']} missed (the ceilometer saw cloud over it, cbh "
             f"none), {det['false_alarms']} false alarms (cbh cloud, the ceilometer clear), {det['both_clear']} both "
             "clear; heights compared on the first"]

    def fmt(name, s):
        if not s["n"]:
            return f"  {name:18s} n=0"
        r2 = "-" if s["r2"] is None else f"{s['r2']:.3f}"
        return (f"  {name:18s} n={s['n']:<5d} MAE {s['mae_m']:7.1f} m  RMSE {s['rmse_m']:7.1f} m  bias {s['bias_m']:+7.1f} m"
                f"  R² {r2}  within 150 m {100 * s['within_150m']:5.1f} %")

    lines.append(fmt("all", rep["all"]))
    lines += [fmt(k, v) for k, v in rep["by_height_band"].items()]
    lines += [fmt(k, v) for k, v in rep["by_sky_type"].items()]
    lines.append(f"wrote {out} and {', '.join(rep['plots'])}")
    return rep, "\n".join(lines)
