"""`cbh pair`: cloud-base heights from one synchronized image pair.

Capture time (used only for the sun's position, to mask it): ``--time`` if given; otherwise a
UTC stamp in camera 1's file name if it has one that says so (ends in ``Z``, e.g.
``cam1_20240621T140000Z.jpg`` or ``cam1-2024-06-21T14-00-00Z.png``); otherwise it is unknown:
the sun is then masked only where the image saturates, and the result carries the flag
``time_unknown``. A local-time stamp without ``Z`` (like the WAHRSIS files) is *not* guessed.
"""
from __future__ import annotations

import json
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
    device: str = typer.Option("cpu", "--device", help="Where the dense work runs: cpu (default) or a torch device, e.g. cuda."),
) -> None:
    """Cloud layers and point statistics from one image pair (heights above the ENU origin)."""
    import numpy as np

    from cbh.imageio import read_image
    from cbh.pipeline import Pipeline
    from cbh.geometry.station import load_station

    st = load_station(station)
    pipe = Pipeline(st, cameras, device=device)
    img1, _ = read_image(image1)
    img2, _ = read_image(image2)
    t = parse_time(time) if time else time_from_name(image1)
    result = pipe.process(img1, img2, t)
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
        print(f"{'layer':>5} {'base_m':>8} {'median_m':>9} {'spread_m':>9} {'cover':>6} {'points':>7} {'conf':>5}")
        for i, l in enumerate(s["layers"]):
            print(f"{i + 1:>5} {l['height_m']:8.0f} {l['median_height_m']:9.0f} {l['spread_m']:9.0f} "
                  f"{l['cover']:6.3f} {l['points']:7d} {l['confidence']:5.2f}")
    p = s["points"]
    if p["count"]:
        print(f"points: {p['count']}  mean {p['mean_height_m']:.0f} m  std {p['std_height_m']:.0f} m  "
              f"p5 {p['p5_height_m']:.0f} m  median ray miss {p['median_miss_m']:.1f} m")
    else:
        print("points: 0")
    print("cloud fraction: " + ", ".join(f"{k} {v:.2f}" for k, v in s["cloud_fraction"].items()))
    if s["flags"]:
        print("flags: " + ", ".join(s["flags"]))
