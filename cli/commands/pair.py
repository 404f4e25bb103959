"""`cbh pair`: cloud-base heights from one synchronized image pair (see :mod:`cbh.actions.pair`)."""
from __future__ import annotations

import json
from pathlib import Path

import typer

from cbh.actions.pair import format_pair, process_pair
from cbh.timeutil import parse_utc


def register(app: typer.Typer) -> None:
    app.command("pair")(pair_cmd)


def pair_cmd(
    images: list[Path] = typer.Argument(..., help="One image (JPEG/PNG, at its calibration size) per camera, in the "
                                                  "station's order: two for a pair, N for a camera network."),
    station: Path = typer.Option(..., "--station", help="Station TOML (may carry a [pipeline] table)."),
    cameras: str = typer.Option(None, "--cameras", help="The images' cameras, reference first, e.g. cam1,cam2 "
                                                        "(default: the station's first N)."),
    time: str = typer.Option(None, "--time", help="Capture time, ISO 8601 with a zone (default: the UTC stamp "
                                                  "in the file name, else unknown)."),
    as_json: bool = typer.Option(False, "--json", help="Print one JSON object."),
    height_map: Path = typer.Option(None, "--height-map", help="Write camera 1's height map (float32 .npy, NaN unknown)."),
    previous: tuple[Path, Path] = typer.Option(None, "--previous", help="The pair before (P1 P2): adds each layer's motion and the clock offset."),
    previous_images: str = typer.Option(None, "--previous-images", help="The set before, one image per camera, "
                                                                        "comma-separated (a network's --previous)."),
    previous_time: str = typer.Option(None, "--previous-time", help="Capture time of --previous, ISO 8601 with a zone (default: the stamp in P1's name)."),
    device: str = typer.Option("cpu", "--device", help="Where the dense work runs: cpu (default) or a torch device, e.g. cuda."),
) -> None:
    """Cloud layers and point statistics from one image pair, or one image per camera of a
    network (heights above the ENU origin)."""
    from cbh.errors import ConfigError

    t = parse_utc(time, "--time") if time else None
    tp = parse_utc(previous_time, "--previous-time") if previous_time else None
    prev = tuple(previous) if previous and previous[0] is not None else None
    if previous_images:
        if prev is not None:
            raise ConfigError("give --previous or --previous-images, not both")
        prev = tuple(Path(p.strip()) for p in previous_images.split(","))
    run = process_pair(images, station, cameras, t, height_map_path=height_map, previous=prev, previous_time=tp,
                       device=device)
    print(json.dumps(run.result.summary()) if as_json else format_pair(run))
