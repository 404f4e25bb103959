"""``cbh pair`` in library terms: cloud-base heights from one synchronized image pair, or
from one image per camera of a camera network (:mod:`cbh.pipeline.network`).

Capture time (used for the sun's position): the given one; otherwise the UTC stamp in camera
1's file name (file-name stamps are UTC: docs/conventions.md); otherwise unknown, and the
result carries the flag ``time_unknown`` (the sun is then masked only where it saturates).

Motion: ``previous`` names the pair captured before (its time: ``previous_time`` or the stamp
in its camera-1 file name); that pair is processed first and handed on as the state
(:mod:`cbh.pipeline.motion`), so each layer gets its motion over the ground [m/s] and camera
2's clock offset is estimated and compensated. Both capture times must be known.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path

import numpy as np

from cbh.result import PairResult
from cbh.timeutil import format_utc, time_from_name

__all__ = ["PairRun", "process_pair", "format_pair"]


@dataclass
class PairRun:
    """One processed frame set (a pair, or a network's N images) and the cameras it used."""

    cameras: tuple[str, ...]
    result: PairResult
    with_motion: bool = False  # processed with the previous set (motion columns in the table)


def process_pair(images, station, cameras: str | None = None, time_utc: datetime | None = None,
                 height_map_path=None, previous=None, previous_time: datetime | None = None,
                 device: str = "cpu") -> PairRun:
    """Process one synchronized set of image files: two cameras, or a network of N.

    Parameters
    ----------
    images : sequence of path-like
        One image (JPEG/PNG, at its calibration size) per camera, in the order of ``cameras``.
    station : path-like
        Station TOML (may carry a ``[pipeline]`` table).
    cameras : str, optional
        ``"cam1,cam2[,cam3…]"``: the cameras of ``images``, reference first (default: the
        station's first ``len(images)`` cameras, in file order).
    time_utc : datetime, optional
        Capture time (aware); default: the first image's file-name stamp, else unknown.
    height_map_path : path-like, optional
        Write the reference camera's dense height map there (float32 ``.npy``, NaN = unknown) [m].
    previous : sequence of path-like, optional
        The set captured before (one image per camera): with it, each layer's motion and the
        cameras' clock offsets.
    previous_time : datetime, optional
        Its capture time (aware); default: the stamp in its first file name.
    device : str
        Where the dense work runs: ``"cpu"`` or a torch device (``"cuda"``); see :class:`~cbh.pipeline.Pipeline`.

    Raises
    ------
    InputError
        ``previous`` without both capture times, not captured before this set, or with
        another number of images.
    ConfigError
        ``previous_time`` without ``previous``; fewer than two images, or more than the station
        has cameras.
    """
    from cbh.errors import ConfigError, InputError
    from cbh.actions.station import load_station
    from cbh.pipeline.network import StationPipeline
    from cbh.presets import station_path

    if height_map_path is not None and Path(height_map_path).suffix.lower() != ".npy":
        # any name was written over: `--height-map SESSION.mcap` (or an input image) was lost
        raise ConfigError(f"--height-map {height_map_path}: the map is a NumPy array; use a .npy file name")
    images = [Path(p) for p in images]
    st = load_station(station_path(str(station)))
    if cameras is None:
        if not 2 <= len(images) <= len(st.cameras):
            raise ConfigError(f"{len(images)} image(s) for station {st.name!r} of {len(st.cameras)} cameras "
                              f"({', '.join(st.cameras)}): give one image per camera, two at least")
        cameras = ",".join(list(st.cameras)[:len(images)])
    pipe = StationPipeline(st, cameras, device=device)
    if len(images) != len(pipe.names):
        raise ConfigError(f"{len(images)} images for {len(pipe.names)} cameras ({', '.join(pipe.names)})")
    t = time_utc if time_utc is not None else time_from_name(images[0].name)
    state = None
    if previous is not None:
        previous = [Path(p) for p in previous]
        if len(previous) != len(images):
            raise InputError(f"--previous: {len(previous)} images for {len(images)} cameras")
        tp = previous_time if previous_time is not None else time_from_name(previous[0].name)
        if t is None or tp is None:
            raise InputError("--previous: motion needs both capture times (--time and --previous-time, "
                             "or UTC stamps in the file names)")
        if not tp < t:
            raise InputError(f"--previous: the previous set ({format_utc(tp)}) must be captured before "
                             f"this one ({format_utc(t)})")
        state = pipe.process(previous, tp).state
    elif previous_time is not None:
        raise ConfigError("--previous-time needs --previous")
    result = pipe.process(images, t, previous=state)
    if height_map_path is not None:
        from cbh.actions.run import open_sink

        def write():
            with open(height_map_path, "wb") as fh:
                np.save(fh, result.height_map.astype(np.float32))
        open_sink(height_map_path, write)
    return PairRun(tuple(result.cameras), result, previous is not None)


def format_pair(run: PairRun) -> str:
    """The human-readable table of ``cbh pair``."""
    s = run.result.summary()
    out = [f"{' + '.join(run.cameras)}  {format_utc(run.result.time_utc)}"]
    if not s["layers"]:
        out.append("no cloud layer")
    else:
        mh = f" {'east_ms':>8} {'north_ms':>8} {'speed_ms':>8} {'dir_deg':>7}" if run.with_motion else ""
        out.append(f"{'layer':>5} {'base_m':>8} {'median_m':>9} {'spread_m':>9} {'cover':>6} {'points':>7} {'conf':>5}{mh}")
        for i, l in enumerate(s["layers"]):
            mv = ""
            if run.with_motion:
                e, n = l["motion_east_ms"], l["motion_north_ms"]
                mv = (f" {e:8.2f} {n:8.2f} {math.hypot(e, n):8.2f} {math.degrees(math.atan2(e, n)) % 360:7.1f}"
                      if e is not None and n is not None else f" {'-':>8} {'-':>8} {'-':>8} {'-':>7}")
            out.append(f"{i + 1:>5} {l['height_m']:8.0f} {l['median_height_m']:9.0f} {l['spread_m']:9.0f} "
                       f"{l['cover']:6.3f} {l['points']:7d} {l['confidence']:5.2f}{mv}")
    p = s["points"]
    if p["count"]:
        out.append(f"points: {p['count']}  mean {p['mean_height_m']:.0f} m  std {p['std_height_m']:.0f} m  "
                   f"p5 {p['p5_height_m']:.0f} m  median ray miss {p['median_miss_m']:.1f} m")
    else:
        out.append("points: 0")
    out.append("cloud fraction: " + ", ".join(f"{k} {v:.2f}" for k, v in s["cloud_fraction"].items()))
    if run.with_motion:
        off, dt = s["diagnostics"].get("clock_offset_s"), s["diagnostics"].get("motion_dt_s")
        out.append((f"motion over {dt:g} s (direction: where the layer goes, clockwise from north); " if dt
                    else "motion: none; ")
                   + f"clock offset {run.cameras[1]} - {run.cameras[0]}: "
                   + (f"{off:+.2f} s" if off is not None else "unknown"))
    out += _network_lines(run.result)
    if s["flags"]:
        out.append("flags: " + ", ".join(s["flags"]))
    return "\n".join(out)


def _network_lines(result: PairResult) -> list[str]:
    """A camera network's part of the table: each layer's support, each pair's verdict, the
    cameras that disagree (none for a two-camera pair)."""
    if not result.pairs:
        return []
    d = result.diagnostics
    out = []
    for i, L in enumerate(result.layers):
        out.append(f"layer {i + 1} support: " + ", ".join(f"{p} {100 * w:.0f} % ({h:.0f} m)" for p, _, h, w in
                                                          sorted(L.support, key=lambda e: -e[3])))
    parts = []
    for name, r in result.pairs.items():
        b = d.get(f"{name}.baseline_m", math.nan)
        verdict = ("disagrees" if "geometry_mismatch" in r.flags else
                   "agrees" if math.isfinite(d.get(f"{name}.geometry_residual_px", math.nan)) else "no verdict")
        parts.append(f"{name} ({b:.0f} m) {verdict}")
    out.append("pairs: " + "; ".join(parts))
    for skipped in d.get("skipped_pairs") or []:
        out.append(f"pair not used: {skipped}")
    bad = d.get("mismatched_cameras") or []
    if bad:
        out.append("cameras that disagree with the others (left out): " + ", ".join(bad))
    return out
