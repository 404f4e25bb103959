"""``cbh pair`` in library terms: cloud-base heights from one synchronized image pair.

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
    """One processed pair and the pipeline that made it."""

    cameras: tuple[str, str]
    result: PairResult
    with_motion: bool = False  # processed with the previous pair (motion columns in the table)


def process_pair(image1, image2, station, cameras: str | None = None, time_utc: datetime | None = None,
                 height_map_path=None, previous=None, previous_time: datetime | None = None,
                 device: str = "cpu") -> PairRun:
    """Process one pair of image files.

    Parameters
    ----------
    image1, image2 : path-like
        Camera 1's and camera 2's images (JPEG/PNG) at their calibration size.
    station : path-like
        Station TOML (may carry a ``[pipeline]`` table).
    cameras : str, optional
        ``"cam1,cam2"`` (default: the station's first two).
    time_utc : datetime, optional
        Capture time (aware); default: camera 1's file-name stamp, else unknown.
    height_map_path : path-like, optional
        Write camera 1's dense height map there (float32 ``.npy``, NaN = unknown) [m].
    previous : (path-like, path-like), optional
        The pair captured before: with it, each layer's motion and camera 2's clock offset.
    previous_time : datetime, optional
        Its capture time (aware); default: the stamp in its camera-1 file name.
    device : str
        Where the dense work runs: ``"cpu"`` or a torch device (``"cuda"``); see :class:`~cbh.pipeline.Pipeline`.

    Raises
    ------
    InputError
        ``previous`` without both capture times, or not captured before this pair.
    ConfigError
        ``previous_time`` without ``previous``.
    """
    from cbh.geometry.station import load_station
    from cbh.presets import station_path
    from cbh.pipeline import Pipeline

    if height_map_path is not None and Path(height_map_path).suffix.lower() != ".npy":
        from cbh.errors import ConfigError

        # any name was written over: `--height-map SESSION.mcap` (or an input image) was lost
        raise ConfigError(f"--height-map {height_map_path}: the map is a NumPy array; use a .npy file name")
    pipe = Pipeline(load_station(station_path(str(station))), cameras, device=device)
    t = time_utc if time_utc is not None else time_from_name(Path(image1).name)
    state = None
    if previous is not None:
        from cbh.errors import InputError

        tp = previous_time if previous_time is not None else time_from_name(Path(previous[0]).name)
        if t is None or tp is None:
            raise InputError("--previous: motion needs both capture times (--time and --previous-time, "
                             "or UTC stamps in the file names)")
        if not tp < t:
            raise InputError(f"--previous: the previous pair ({format_utc(tp)}) must be captured before "
                             f"this one ({format_utc(t)})")
        state = pipe.process(Path(previous[0]), Path(previous[1]), tp).state
    elif previous_time is not None:
        from cbh.errors import ConfigError

        raise ConfigError("--previous-time needs --previous P1 P2")
    result = pipe.process(Path(image1), Path(image2), t, previous=state)
    if height_map_path is not None:
        from cbh.actions.run import open_sink

        def write():
            with open(height_map_path, "wb") as fh:
                np.save(fh, result.height_map.astype(np.float32))
        open_sink(height_map_path, write)
    return PairRun(pipe.cameras, result, previous is not None)


def format_pair(run: PairRun) -> str:
    """The human-readable table of ``cbh pair``."""
    s = run.result.summary()
    out = [f"{run.cameras[0]} + {run.cameras[1]}  {format_utc(run.result.time_utc)}"]
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
    if s["flags"]:
        out.append("flags: " + ", ".join(s["flags"]))
    return "\n".join(out)
