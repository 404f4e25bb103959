"""``cbh pair`` in library terms: cloud-base heights from one synchronized image pair.

Capture time (used for the sun's position): the given one; otherwise the UTC stamp in camera
1's file name (file-name stamps are UTC: docs/conventions.md); otherwise unknown, and the
result carries the flag ``time_unknown`` (the sun is then masked only where it saturates).
"""
from __future__ import annotations

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


def process_pair(image1, image2, station, cameras: str | None = None, time_utc: datetime | None = None,
                 height_map_path=None, device: str = "cpu") -> PairRun:
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
    device : str
        Where the dense work runs: ``"cpu"`` or a torch device (``"cuda"``); see :class:`~cbh.pipeline.Pipeline`.
    """
    from cbh.geometry.station import load_station
    from cbh.pipeline import Pipeline

    pipe = Pipeline(load_station(station), cameras, device=device)
    t = time_utc if time_utc is not None else time_from_name(Path(image1).name)
    result = pipe.process(Path(image1), Path(image2), t)
    if height_map_path is not None:
        from cbh.actions.run import open_sink

        def write():
            with open(height_map_path, "wb") as fh:
                np.save(fh, result.height_map.astype(np.float32))
        open_sink(height_map_path, write)
    return PairRun(pipe.cameras, result)


def format_pair(run: PairRun) -> str:
    """The human-readable table of ``cbh pair``."""
    s = run.result.summary()
    out = [f"{run.cameras[0]} + {run.cameras[1]}  {format_utc(run.result.time_utc)}"]
    if not s["layers"]:
        out.append("no cloud layer")
    else:
        out.append(f"{'layer':>5} {'base_m':>8} {'median_m':>9} {'spread_m':>9} {'cover':>6} {'points':>7} {'conf':>5}")
        for i, l in enumerate(s["layers"]):
            out.append(f"{i + 1:>5} {l['height_m']:8.0f} {l['median_height_m']:9.0f} {l['spread_m']:9.0f} "
                       f"{l['cover']:6.3f} {l['points']:7d} {l['confidence']:5.2f}")
    p = s["points"]
    if p["count"]:
        out.append(f"points: {p['count']}  mean {p['mean_height_m']:.0f} m  std {p['std_height_m']:.0f} m  "
                   f"p5 {p['p5_height_m']:.0f} m  median ray miss {p['median_miss_m']:.1f} m")
    else:
        out.append("points: 0")
    out.append("cloud fraction: " + ", ".join(f"{k} {v:.2f}" for k, v in s["cloud_fraction"].items()))
    if s["flags"]:
        out.append("flags: " + ", ".join(s["flags"]))
    return "\n".join(out)
