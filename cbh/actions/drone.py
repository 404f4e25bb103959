"""`cbh validate --drone LOG`: commission a station by flying a drone (the paper's section 4 as a command).

1. The flight log (DJI SRT or CSV, :mod:`cbh.geometry.flightlog`) goes to the station's ENU
   frame; its hovers are where it stands still (:func:`cbh.pipeline.dronetrack.find_hovers`).
2. Every camera's frames (image folders or recordings) are searched for compact sources,
   bright at night and dark by day; stars and hot pixels, which stay put, are set aside
   (:mod:`cbh.pipeline.pointsources`).
3. The log's clock against the cameras' is found from the agreement of the two tracks
   (:func:`cbh.pipeline.dronetrack.clock_offset`), reported and used.
4. At each hover, each camera's median pixel of the drone; each camera pair's rays are
   triangulated (the ray miss is the quality) and compared with the log: per position, and
   MAE, MAPE, RMSE overall, by sector, by height and by the point on each camera's ray (as the
   paper's Tables 3 and 4). Each camera's turn against the log's directions says whether it
   needs levelling or `cbh calibrate`.
"""
from __future__ import annotations

import csv
import io
import itertools
import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cbh.errors import ConfigError, InputError

__all__ = ["DroneOptions", "validate_drone"]

WEAK_SNR = 4.0  # sources down to this signal-to-noise are kept, used only near the drone's known place
FIT_MAPE_PCT = 2.0  # above this MAPE [%] a station is not called fit for use (a GPS's 0.5 m at 90 m is 0.6 %)
DAY_LEVEL = 60  # in twilight, a frame whose median sky is brighter than this [grey level] is a day frame


@dataclass(frozen=True)
class DroneOptions:
    takeoff: object = None  # cbh.geometry.flightlog.Takeoff or None
    log_tz: str | None = None  # the log's time zone (DJI stamps local time); None = UTC
    search_s: float = 120.0  # the largest clock offset looked for [s]


@dataclass
class _Camera:
    cam: object
    times: list
    points: list
    stack: np.ndarray | None = None
    frames: int = 0


def _frames(station, sources: dict | None, recordings: list | None):
    """{camera name: iterator of Frame} for the cameras that have frames."""
    from cbh.actions.calibrate import _recording_frames, _source_frames

    base = station.path.parent if station.path else Path(".")
    if sources:
        unknown = [c for c in sources if c not in station.cameras]
        if unknown:
            raise ConfigError(f"--source {unknown[0]}=…: no camera {unknown[0]!r} in station {station.name!r} "
                              f"(cameras: {', '.join(station.cameras)})")
        if len(sources) < 2:
            raise ConfigError("--source: give at least two cameras' frames (CAM=DIR for each)")
        return {n: _source_frames(station.cameras[n], s, base, None) for n, s in sources.items()}
    def recorded(name: str):
        for r in recordings:
            yield from _recording_frames(name, Path(r))

    return {n: recorded(n) for n in station.cameras}


def _valid_mask(cam) -> np.ndarray:
    from cbh.pipeline.masks import load_obstacle_mask

    m = cam.model.image_circle_mask(88.0)
    if cam.mask is not None:
        m &= load_obstacle_mask(cam.mask, cam.model.width, cam.model.height)
    return m


def _polarity(station, t, grey: np.ndarray, valid: np.ndarray) -> str:
    """``bright`` (a light at night) or ``dark`` (a speck by day): by the sun (below -6 deg: night,
    above +6 deg: day), in twilight by the frame's median sky."""
    from cbh.geometry.sun import sun_position

    elev = 90.0 - sun_position(station.latitude_deg, station.longitude_deg, station.altitude_m, t).zenith_deg
    if elev < -6.0 or elev > 6.0:
        return "bright" if elev < -6.0 else "dark"
    return "dark" if float(np.median(grey[valid])) > DAY_LEVEL else "bright"


def _detect_all(station, frames: dict, span: tuple[np.datetime64, np.datetime64]) -> dict[str, _Camera]:
    """Each camera's sources in its frames within ``span`` (the log's, widened by the clock
    search): a night's recording is read, but only the flight's frames are decoded."""
    import cv2

    from cbh.imageio import check_image_size, decode_image
    from cbh.pipeline.pointsources import detect_points

    out, skipped = {}, []
    for name, it in frames.items():
        cam = station.cameras[name]
        valid, polarity = _valid_mask(cam), None
        c = _Camera(cam, [], [])
        for f in it:
            t = np.datetime64(f.time_utc.replace(tzinfo=None), "ns")
            if not span[0] <= t <= span[1]:
                skipped.append(t)
                continue
            img = f.image if f.image is not None else decode_image(f.encoded, f"{name} frame {f.time_utc:%H:%M:%S}")
            check_image_size(img, cam.model, f"{name} frame {f.time_utc:%Y-%m-%dT%H:%M:%S}Z")
            g = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY) if img.ndim == 3 else img
            if polarity is None:
                polarity = _polarity(station, f.time_utc, g, valid)
            c.times.append(t)
            c.points.append(detect_points(g, valid, polarity, k_sigma=WEAK_SNR))
            c.stack = g.copy() if c.stack is None else (np.maximum(c.stack, g) if polarity == "bright" else np.minimum(c.stack, g))
            c.frames += 1
        if c.frames:
            out[name] = c
    if not out and skipped:
        raise InputError(f"no overlap: the frames span {_span(np.array(skipped))}, the flight log "
                         f"{_span(np.array(span))} with the clock search (a DJI log stamps local time: --log-tz)")
    if len(out) < 2:
        have = ", ".join(out) or "none"
        raise InputError(f"frames from fewer than two cameras during the flight (with frames: {have}): a drone check "
                         "needs two")
    return out


def _tracks(cams: dict[str, _Camera], t0: np.datetime64, latitude_deg: float):
    from cbh.pipeline.dronetrack import CameraTrack
    from cbh.pipeline.pointsources import persistent_sources, sky_turn

    tracks = []
    for c in cams.values():
        order = np.argsort(np.array(c.times))
        t = (np.array(c.times)[order] - t0).astype("timedelta64[ns]").astype(np.float64) * 1e-9
        pts = [c.points[i] for i in order]
        keep = persistent_sources(t, pts, sky_turn(c.cam, latitude_deg))
        tracks.append(CameraTrack(c.cam, t, [p[~k] for p, k in zip(pts, keep)]))
    return tracks


def _span(t: np.ndarray) -> str:
    t = np.sort(t.astype("datetime64[s]"))
    return f"{t[0]}Z .. {t[-1]}Z"


def validate_drone(log_path, out, *, station_path=None, sources: dict | None = None, recordings: list | None = None,
                   opts: DroneOptions = DroneOptions()) -> tuple[dict, str]:
    """Run the drone check; write the per-position CSV ``out`` and its figure ``<stem>.png``.

    Returns (report, text): the report has ``rows`` (one per hover and camera pair) and
    ``summary`` (``mae_m``, ``mape_pct``, ``rmse_m``, ``n_positions``, ``clock_offset_s``, …).
    """
    from cbh.fileio import refuse_inputs
    from cbh.geometry.flightlog import log_enu, parse_tz, read_flight_log
    from cbh.pipeline.dronetrack import clock_offset, find_hovers

    station, out = _station(station_path, recordings), Path(out)
    png = out.with_suffix(".png")
    if not out.parent.is_dir():
        raise InputError(f"output directory does not exist: {out.parent}")
    refuse_inputs([out, png], [log_path, station_path, *(sources or {}).values(), *(recordings or [])], "--out")
    log = read_flight_log(log_path, parse_tz(opts.log_tz))
    enu, notes = log_enu(log, station, opts.takeoff)
    pad = np.timedelta64(int(opts.search_s * 1e9), "ns")
    cams = _detect_all(station, _frames(station, sources, recordings), (log.time_utc[0] - pad, log.time_utc[-1] + pad))
    t0 = np.concatenate([np.array(c.times) for c in cams.values()]).min()
    tracks = _tracks(cams, t0, station.latitude_deg)
    log_t = log.seconds(t0)
    hovers = find_hovers(log_t, enu, log.up_m)
    if not hovers:
        raise InputError(f"flight log {Path(log_path).name}: the drone never hovers (standing still 5 s or more, "
                         "5 m or more above the take-off): nothing to compare")
    clock = clock_offset(tracks, log_t, enu, opts.search_s)
    if not math.isfinite(clock["offset_s"]):
        raise InputError("the drone was not found near the log's positions in any camera's frames at any clock offset "
                         f"within ±{opts.search_s:g} s (a wrong log, station or take-off point?)")
    rep = _measure(station, tracks, hovers, log_t, enu, clock)
    rep["summary"]["notes"] = notes
    rep["summary"]["log"] = {"file": str(log_path), "kind": log.kind, "fixes": int(log.time_utc.size)}
    _write(rep, out, png, cams, tracks, log_t, enu, clock["offset_s"])
    return rep, _text(rep, out, png)


def _station(station_path, recordings):
    from cbh.actions.station import load_station
    from cbh.outputs.record import open_session

    if station_path is not None:
        return load_station(station_path)
    if not recordings:
        raise ConfigError("--station: needed with --source (or give recordings, which carry their station)")
    return open_session(recordings[0]).station


def _measure(station, tracks, hovers, log_t, enu, clock) -> dict:
    from cbh.pipeline.dronetrack import measure_hovers

    off = clock["offset_s"]
    margin = 1.0 + 3.0 * (clock["stderr_s"] if math.isfinite(clock["stderr_s"]) else 1.0)
    seen = measure_hovers(tracks, hovers, log_t, enu, off, margin, gate_deg=8.0)
    turns = {tr.camera.name: _turn(tr.camera, hovers, seen) for tr in tracks}
    fix = {n: t["R"] for n, t in turns.items() if t is not None}
    if fix:  # again, each camera's found turn taken out of the log's directions: a tighter gate, kept
        again = measure_hovers(tracks, hovers, log_t, enu, off, margin, gate_deg=2.0, R_fix=fix)
        if _seen_count(again) >= _seen_count(seen):  # when it loses nothing (a log that is off is no turn)
            seen = again
            turns = {tr.camera.name: _turn(tr.camera, hovers, seen) for tr in tracks}
    seen = _faint(tracks, hovers, log_t, enu, off, margin, fix, seen)
    for tr in tracks:
        never = all(s[tr.camera.name]["n"] == 0 for s in seen)
        if never:
            others = [t.camera.name for t in tracks if any(s[t.camera.name]["n"] for s in seen)]
            raise InputError(f"the drone is seen by {', '.join(others) or 'no camera'} only: camera "
                             f"{tr.camera.name} has no sight of it at any hover (its frames, its orientation, a mask?)")
    names = [tr.camera.name for tr in tracks]
    rows = [_row(station, k, h, seen[k], a, b) for a, b in itertools.combinations(names, 2) for k, h in enumerate(hovers)]
    return {"rows": rows, "summary": _summary(rows, names, clock, turns, len(hovers))}


def _faint(tracks, hovers, log_t, enu, off: float, margin: float, fix: dict, seen: list[dict]) -> list[dict]:
    """Where a camera has no detection in a hover, its faint sources (down to WEAK_SNR) within
    2 deg of where the log (and the camera's found turn) put the drone: a faint light over a few
    frames, which a 6-sigma detection misses."""
    from cbh.pipeline.dronetrack import measure_hovers

    if all(v["n"] for s in seen for v in s.values()):
        return seen
    faint = measure_hovers(tracks, hovers, log_t, enu, off, margin, gate_deg=2.0, R_fix=fix or None, min_snr=WEAK_SNR)
    for s, f in zip(seen, faint):
        for name, v in s.items():
            if not v["n"] and f[name]["n"]:
                s[name] = {**f[name], "faint": True}
    return seen


def _seen_count(seen: list[dict]) -> int:
    return sum(v["n"] > 0 for s in seen for v in s.values())


def _turn(cam, hovers, seen) -> dict | None:
    """A camera's rotation from the log's directions to the seen ones (>= 3 hovers), with its
    size [deg], tilt [deg] toward an azimuth, yaw [deg] and the scatter left after it [deg]."""
    from cbh.pipeline.dronetrack import rotation_between

    m, p = [], []
    for h, s in zip(hovers, seen):
        if s[cam.name]["n"]:
            d = h.position_m - cam.position_m
            m.append(s[cam.name]["ray"]), p.append(d / np.linalg.norm(d))
    if len(m) < 3:
        return None
    m, p = np.array(m), np.array(p)
    R = rotation_between(m, p)
    w = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]]) / 2  # small rotation vector [rad]
    res = np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", p @ R.T, m), -1, 1)))
    scatter = float(np.sqrt(np.mean(res**2)))
    return {"R": R, "angle_deg": float(np.degrees(np.linalg.norm(w))), "yaw_deg": float(np.degrees(w[2])),
            "tilt_deg": float(np.degrees(math.hypot(w[0], w[1]))),
            "tilt_toward_az_deg": float(math.degrees(math.atan2(w[1], -w[0])) % 360.0),
            "scatter_deg": scatter, "uncertainty_deg": scatter / math.sqrt(max(len(m) - 3, 1)), "positions": len(m)}


def _row(station, k: int, h, seen: dict, a: str, b: str) -> dict:
    from cbh.geometry.triangulate import triangulate
    from cbh.pipeline.dronetrack import sector_of

    ca, cb = station.cameras[a], station.cameras[b]
    centre = (ca.position_m + cb.position_m) / 2  # the pair's sectors: over it, and N, E, S, W of it
    half = float(np.hypot(*(ca.position_m - cb.position_m)[:2])) / 2
    d = h.position_m - centre
    row = {"position": k + 1, "cameras": f"{a}-{b}", "sector": sector_of(h.position_m, centre, max(40.0, half)),
           "logged_east_m": h.position_m[0], "logged_north_m": h.position_m[1], "logged_height_m": h.position_m[2],
           "off_zenith_deg": math.degrees(math.atan2(math.hypot(d[0], d[1]), d[2])),
           f"frames_{a}": seen[a]["n"], f"frames_{b}": seen[b]["n"]}
    nan = {key: math.nan for key in ("measured_east_m", "measured_north_m", "measured_height_m", "error_m", "error_pct",
                                     "ray_miss_m", f"height_{a}_m", f"height_{b}_m", "spread_px")}
    if not (seen[a]["n"] and seen[b]["n"]):
        row.update(nan, note="not seen by " + " and ".join(c for c in (a, b) if not seen[c]["n"]))
        return row
    tri = triangulate(ca.position_m[None], seen[a]["ray"][None], cb.position_m[None], seen[b]["ray"][None])
    if not bool(tri.valid[0]):
        row.update(nan, note="rays do not meet in front of both cameras")
        return row
    p = tri.point_m[0]
    err = float(p[2] - h.position_m[2])
    row.update({"measured_east_m": p[0], "measured_north_m": p[1], "measured_height_m": p[2], "error_m": err,
                "error_pct": 100 * err / h.position_m[2], "ray_miss_m": float(tri.miss_m[0]),
                f"height_{a}_m": float(ca.position_m[2] + tri.range1_m[0] * seen[a]["ray"][2]),
                f"height_{b}_m": float(cb.position_m[2] + tri.range2_m[0] * seen[b]["ray"][2]),
                "spread_px": max(seen[a]["spread_px"], seen[b]["spread_px"]), "note": ""})
    return row


def _metrics(meas, true) -> dict:
    from cbh.geometry.validation import height_metrics

    m = height_metrics(np.asarray(meas, np.float64), np.asarray(true, np.float64))
    err = np.asarray(meas, np.float64) - np.asarray(true, np.float64)
    ok = np.isfinite(err)
    m["bias_m"] = float(err[ok].mean()) if ok.any() else None
    m["bias_pct"] = float((100 * err[ok] / np.asarray(true, np.float64)[ok]).mean()) if ok.any() else None
    return m


def _levels(heights: np.ndarray, gap_m: float = 20.0) -> np.ndarray:
    """A label per logged height: the flight's height levels (heights within ``gap_m`` grouped)."""
    order = np.argsort(heights)
    lab = np.zeros(heights.size, int)
    lab[order] = np.concatenate([[0], np.cumsum(np.diff(heights[order]) > gap_m)])
    return np.array([f"{heights[lab == i].mean():.0f} m" for i in lab])


def _summary(rows: list[dict], names: list[str], clock: dict, turns: dict, n_hovers: int) -> dict:
    meas = np.array([r["measured_height_m"] for r in rows], np.float64)
    true = np.array([r["logged_height_m"] for r in rows], np.float64)
    pairs = sorted({r["cameras"] for r in rows})
    sectors = np.array([r["sector"] for r in rows])
    levels = _levels(true)
    s = _metrics(meas, true)
    s.update({"n_positions": len({r["position"] for r in rows if np.isfinite(r["measured_height_m"])}),
              "n_comparisons": int(np.isfinite(meas).sum()), "hover_positions": n_hovers,
              "clock_offset_s": clock["offset_s"], "clock_offset_stderr_s": clock["stderr_s"],
              "clock_offset_spread_s": clock["spread_s"], "clock_moving_frames": clock["moving_frames"],
              "clock_convention": "the flight log's clock minus the cameras' [s]"})
    s["by_pair"] = {p: _metrics(meas[[r["cameras"] == p for r in rows]], true[[r["cameras"] == p for r in rows]]) for p in pairs}
    s["by_sector"] = {k: _metrics(meas[sectors == k], true[sectors == k]) for k in ("centre", "N", "E", "S", "W") if (sectors == k).any()}
    s["by_height"] = {k: _metrics(meas[levels == k], true[levels == k]) for k in dict.fromkeys(levels[np.argsort(true)])}
    s["by_camera_ray"] = {}
    for n in names:
        sel = np.array([f"height_{n}_m" in r for r in rows])
        h = np.array([r.get(f"height_{n}_m", math.nan) for r in rows], np.float64)
        s["by_camera_ray"][n] = _metrics(h[sel], true[sel])
    s["orientation"] = {n: ({k: v for k, v in t.items() if k != "R"} if t else None) for n, t in turns.items()}
    s["advice"] = _advice(rows, s["orientation"], s)
    return s


def _advice(rows: list[dict], orient: dict, overall: dict | None = None) -> list[str]:
    """What the errors suggest: a camera turned (tilt: levelling; yaw), errors growing away from
    the centre (levelling or the lens), a sector's bias (a tilt)."""
    out = []
    for n, t in orient.items():
        if t is None:
            continue
        bar = max(0.2, 3 * t["uncertainty_deg"])
        if t["angle_deg"] > bar:
            out.append(f"{n} sees the drone {t['angle_deg']:.2f} deg from where its stated orientation puts it "
                       f"({t['tilt_deg']:.2f} deg of tilt, the sky leaning toward azimuth {t['tilt_toward_az_deg']:.0f} deg; "
                       f"{t['yaw_deg']:+.2f} deg of yaw; the log can tell {bar:.2f} deg): level it again and run "
                       "`cbh calibrate` to refit its orientation")
    err = np.array([r["error_pct"] for r in rows], np.float64)
    zen = np.array([r["off_zenith_deg"] for r in rows], np.float64)
    ok = np.isfinite(err)
    if ok.sum() >= 6 and np.nanmean(np.abs(err)) > 1.0:
        from scipy.stats import spearmanr

        rho, pval = spearmanr(zen[ok], np.abs(err[ok]))
        if rho > 0.5 and pval < 0.05:
            out.append(f"height errors grow with the distance from the centre (Spearman {rho:.2f} against the angle from "
                       "the zenith): a camera out of level, or a lens model that is off at large angles "
                       "(`cbh calibrate`, `cbh calibrate-lens`)")
    sect = np.array([r["sector"] for r in rows])
    for k in ("N", "E", "S", "W"):
        e = err[(sect == k) & ok]
        if e.size >= 2 and abs(e.mean()) > 1.0 and abs(e.mean()) > 2 * e.std(ddof=1) / math.sqrt(e.size):
            out.append(f"heights in sector {k} read {abs(e.mean()):.1f} % {'high' if e.mean() > 0 else 'low'} on "
                       f"average ({e.size} positions): a tilt of the cameras along that direction (level them; "
                       "`cbh calibrate`)")
    out += _constant_offset(rows)
    mape = (overall or {}).get("mape_pct")
    if mape is not None and mape > FIT_MAPE_PCT and not out:
        out.append(f"the heights are off by {mape:.1f} % on average (bias {overall['bias_pct']:+.1f} %) and no single "
                   "cause stands out: check the take-off height (--takeoff), the station's camera positions and "
                   "orientation (`cbh calibrate`) and the lens models (`cbh calibrate-lens`)")
    if not out:
        out.append("no sign of a tilt, a turn or a lens error beyond what the log can tell: the station is fit for use")
    return out


def _constant_offset(rows: list[dict]) -> list[str]:
    """A height error that is the same at every height (``error = a + b * height`` with ``a``
    significant and ``b`` not): the take-off height or the log's altitude, not the cameras."""
    e = np.array([r["error_m"] for r in rows], np.float64)
    h = np.array([r["logged_height_m"] for r in rows], np.float64)
    ok = np.isfinite(e)
    if ok.sum() < 4 or np.ptp(h[ok]) < 50.0:
        return []
    A = np.stack([np.ones(ok.sum()), h[ok]], axis=1)
    coef, *_ = np.linalg.lstsq(A, e[ok], rcond=None)
    resid = e[ok] - A @ coef
    cov = np.linalg.inv(A.T @ A) * max(float(resid @ resid) / max(ok.sum() - 2, 1), 1e-6)
    a, b = coef
    if abs(a) > max(1.0, 3 * math.sqrt(cov[0, 0])) and abs(b) * h[ok].max() < 0.5 * abs(a):
        return [f"every position reads about {abs(a):.1f} m {'high' if a > 0 else 'low'} whatever its height: the take-off "
                "point's height (--takeoff LAT,LON,UP_M) or the log's altitude reference is off, not the cameras"]
    return []


def _write(rep: dict, out: Path, png: Path, cams, tracks, log_t, enu, offset_s: float) -> None:
    from cbh.fileio import atomic_write
    from cbh.outputs.drone_figure import drone_figure
    from cbh.outputs.export import write_error

    cols = list(dict.fromkeys(k for r in rep["rows"] for k in r))
    buf = io.StringIO()
    w = csv.DictWriter(buf, cols, extrasaction="ignore")
    w.writeheader()
    for r in rep["rows"]:
        w.writerow({k: (f"{v:.3f}" if isinstance(v, float) and math.isfinite(v) else ("" if isinstance(v, float) else v))
                    for k, v in r.items()})
    try:
        with atomic_write(out) as tmp:
            tmp.write_text(buf.getvalue())
    except OSError as exc:
        raise write_error(out, exc) from None
    stacks = {n: c.stack for n, c in cams.items()}
    drone_figure(png, rep, stacks, tracks, log_t, enu, offset_s)
    rep["summary"]["figure"] = str(png)
    rep["summary"]["report"] = str(out)


def _fmt(name: str, m: dict) -> str:
    if not m["n"]:
        return f"  {name:14s} n=0"
    return (f"  {name:14s} n={m['n']:<3d} MAE {m['mae_m']:6.2f} m  MAPE {m['mape_pct']:5.2f} %  RMSE {m['rmse_m']:6.2f} m"
            f"  bias {m['bias_m']:+6.2f} m")


def _text(rep: dict, out: Path, png: Path) -> str:
    s = rep["summary"]
    lines = [f"drone check: {s['hover_positions']} hover positions in {Path(s['log']['file']).name} ({s['log']['kind']}, "
             f"{s['log']['fixes']} fixes); {s['n_positions']} measured by {len(s['by_pair'])} camera pair(s)",
             f"log clock minus the cameras': {s['clock_offset_s']:+.2f} s (± {s['clock_offset_stderr_s']:.2f} s from "
             f"{s['clock_moving_frames']} frames of the drone moving)", *[f"note: {n}" for n in s["notes"]],
             "  pos  pair       sector  logged E, N, height [m]     measured [m]  error             miss"]
    for r in rep["rows"]:
        meas = "      -" if not math.isfinite(r["measured_height_m"]) else f"{r['measured_height_m']:7.1f}"
        err = r.get("note") or f"{r['error_m']:+6.1f} m ({r['error_pct']:+5.1f} %)  {r['ray_miss_m']:5.2f} m"
        lines.append(f"  {r['position']:3d}  {r['cameras']:9s}  {r['sector']:6s}  {r['logged_east_m']:7.1f} "
                     f"{r['logged_north_m']:7.1f} {r['logged_height_m']:7.1f}      {meas}      {err}")
    lines += ["overall:", _fmt("all", s)] + ["by camera pair:"] + [_fmt(k, v) for k, v in s["by_pair"].items()]
    lines += ["by sector:"] + [_fmt(k, v) for k, v in s["by_sector"].items()]
    lines += ["by height:"] + [_fmt(k, v) for k, v in s["by_height"].items()]
    lines += ["height on each camera's ray (the paper's Table 3):"] + [_fmt(k, v) for k, v in s["by_camera_ray"].items()]
    lines += [f"advice: {a}" for a in s["advice"]] + [f"wrote {out} and {png}"]
    return "\n".join(lines)


def report_json(rep: dict) -> str:
    """The report as JSON (NaN as null)."""
    def clean(v):
        if isinstance(v, float):
            return v if math.isfinite(v) else None
        if isinstance(v, np.generic):
            return clean(v.item())
        if isinstance(v, np.ndarray):
            return [clean(x) for x in v.tolist()]
        if isinstance(v, dict):
            return {k: clean(x) for k, x in v.items()}
        if isinstance(v, (list, tuple)):
            return [clean(x) for x in v]
        return v

    return json.dumps(clean(rep), indent=1)
