"""`cbh pair`: cloud-base heights from one synchronized image pair.

Capture time (used only for the sun's position, to mask it): ``--time`` if given; otherwise a
UTC stamp in camera 1's file name if it has one that says so (ends in ``Z``, e.g.
``cam1_20240621T140000Z.jpg`` or ``cam1-2024-06-21T14-00-00Z.png``); otherwise it is unknown:
the sun is then masked only where the image saturates, and the result carries the flag
``time_unknown``. A local-time stamp without ``Z`` (like the WAHRSIS files) is *not* guessed.

Motion: ``--previous P1 P2`` names the pair captured before (its time: ``--previous-time`` or
the stamp in P1's name); that pair is processed first and handed on as the state
(:mod:`cbh.pipeline.motion`), so each layer gets its motion over the ground [m/s] and camera
2's clock offset is estimated and compensated. Both capture times must be known.
"""
from __future__ import annotations

import json
import math
import re
from pathlib import Path

import typer

_STAMP = re.compile(
    r"(\d{4})-?(\d{2})-?(\d{2})[T_-]?(\d{2})[-:]?(\d{2})[-:]?(\d{2})(?:[.,](\d{1,6}))?Z", re.IGNORECASE
)


def register(app: typer.Typer) -> None:
    app.command("pair")(pair_cmd)


def time_from_name(path: Path):
    """UTC datetime from a file name's ``…YYYYMMDDTHHMMSSZ`` stamp, or None."""
    from datetime import datetime, timezone

    m = _STAMP.search(path.name)
    if not m:
        return None
    y, mo, d, h, mi, s, frac = m.groups()
    try:
        us = int((frac or "0").ljust(6, "0"))
        return datetime(int(y), int(mo), int(d), int(h), int(mi), int(s), us, tzinfo=timezone.utc)
    except ValueError:
        return None


def parse_time(text: str):
    """ISO 8601 → aware UTC datetime (naive = UTC); InputError on bad text."""
    from datetime import datetime, timezone

    from cbh.errors import InputError

    try:
        t = datetime.fromisoformat(text.strip().replace("Z", "+00:00").replace("z", "+00:00"))
    except ValueError:
        raise InputError(f"--time: not an ISO 8601 time: {text!r} (e.g. 2015-10-29T04:58:01Z)") from None
    return (t if t.tzinfo else t.replace(tzinfo=timezone.utc)).astimezone(timezone.utc)


def pair_cmd(
    image1: Path = typer.Argument(..., help="Camera 1 image (JPEG/PNG) at its calibration size."),
    image2: Path = typer.Argument(..., help="Camera 2 image."),
    station: Path = typer.Option(..., "--station", help="Station TOML (may carry a [pipeline] table)."),
    cameras: str = typer.Option(None, "--cameras", help="Two camera names, e.g. cam1,cam2 (default: first two)."),
    time: str = typer.Option(None, "--time", help="Capture time, ISO 8601 (default: UTC stamp in the file name, else unknown)."),
    as_json: bool = typer.Option(False, "--json", help="Print one JSON object."),
    height_map: Path = typer.Option(None, "--height-map", help="Write camera 1's height map (float32 .npy, NaN unknown)."),
    previous: tuple[Path, Path] = typer.Option(None, "--previous", help="The pair before (P1 P2): adds each layer's motion and the clock offset."),
    previous_time: str = typer.Option(None, "--previous-time", help="Capture time of --previous, ISO 8601 (default: UTC stamp in P1's name)."),
) -> None:
    """Cloud layers and point statistics from one image pair (heights above the ENU origin)."""
    import numpy as np

    from cbh.imageio import read_image
    from cbh.pipeline import Pipeline
    from cbh.geometry.station import load_station

    st = load_station(station)
    pipe = Pipeline(st, cameras)
    img1, _ = read_image(image1)
    img2, _ = read_image(image2)
    t = parse_time(time) if time else time_from_name(image1)
    state = None
    with_motion = bool(previous) and previous[0] is not None
    if with_motion:
        from cbh.errors import InputError

        tp = parse_time(previous_time) if previous_time else time_from_name(previous[0])
        if t is None or tp is None:
            raise InputError("--previous: motion needs both capture times (--time and --previous-time, "
                             "or UTC stamps ending in Z in the file names)")
        if not tp < t:
            raise InputError(f"--previous: the previous pair ({tp.isoformat()}) must be captured before this one ({t.isoformat()})")
        state = pipe.process(read_image(previous[0])[0], read_image(previous[1])[0], tp).state
    elif previous_time:
        from cbh.errors import ConfigError

        raise ConfigError("--previous-time needs --previous P1 P2")
    result = pipe.process(img1, img2, t, previous=state)
    if height_map is not None:
        with open(height_map, "wb") as fh:
            np.save(fh, result.height_map.astype(np.float32))
    s = result.summary()
    if as_json:
        print(json.dumps(s))
        return
    print(f"{pipe.cameras[0]} + {pipe.cameras[1]}  {s['time_utc']}")
    if not s["layers"]:
        print("no cloud layer")
    else:
        mh = f" {'east_ms':>8} {'north_ms':>8} {'speed_ms':>8} {'dir_deg':>7}" if with_motion else ""
        print(f"{'layer':>5} {'base_m':>8} {'median_m':>9} {'spread_m':>9} {'cover':>6} {'points':>7} {'conf':>5}{mh}")
        for i, l in enumerate(s["layers"]):
            mv = ""
            if with_motion:
                e, n = l["motion_east_ms"], l["motion_north_ms"]
                mv = (f" {e:8.2f} {n:8.2f} {math.hypot(e, n):8.2f} {math.degrees(math.atan2(e, n)) % 360:7.1f}"
                      if e is not None and n is not None else f" {'-':>8} {'-':>8} {'-':>8} {'-':>7}")
            print(f"{i + 1:>5} {l['height_m']:8.0f} {l['median_height_m']:9.0f} {l['spread_m']:9.0f} "
                  f"{l['cover']:6.3f} {l['points']:7d} {l['confidence']:5.2f}{mv}")
    p = s["points"]
    if p["count"]:
        print(f"points: {p['count']}  mean {p['mean_height_m']:.0f} m  std {p['std_height_m']:.0f} m  "
              f"p5 {p['p5_height_m']:.0f} m  median ray miss {p['median_miss_m']:.1f} m")
    else:
        print("points: 0")
    print("cloud fraction: " + ", ".join(f"{k} {v:.2f}" for k, v in s["cloud_fraction"].items()))
    if with_motion:
        off, dt = s["diagnostics"].get("clock_offset_s"), s["diagnostics"].get("motion_dt_s")
        print(f"motion over {dt:g} s (direction: where the layer goes, clockwise from north); " if dt else "motion: none; ",
              end="")
        print(f"clock offset {pipe.cameras[1]} - {pipe.cameras[0]}: " + (f"{off:+.2f} s" if off is not None else "unknown"))
    if s["flags"]:
        print("flags: " + ", ".join(s["flags"]))
