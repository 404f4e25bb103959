"""`cbh segment`: cloud masks of sky images (PNG, 255 cloud / 0 clear or unusable)."""
from __future__ import annotations

import json
from pathlib import Path

import typer


def register(app: typer.Typer) -> None:
    app.command("segment")(segment_cmd)


def segment_cmd(
    images: list[Path] = typer.Argument(..., help="Colour sky images (JPEG/PNG); crops are fine without --station."),
    out: Path = typer.Option(..., "--out", help="Mask PNG (one image) or folder (several: <stem>.png each)."),
    station: str = typer.Option(None, "--station", help="Station TOML or preset: apply its masks (image circle, zenith, obstacles, sun)."),
    camera: str = typer.Option(None, "--camera", help="The station camera that took the images (default: its first)."),
    time: str = typer.Option(None, "--time", help="Capture time, ISO 8601 (with --station: masks the sun, sun-aware regions)."),
    as_json: bool = typer.Option(False, "--json", help="Print the cloud fraction per image as one JSON object."),
) -> None:
    """Classify every pixel as cloud or clear sky (default method: hybrid; refuses greyscale)."""
    from cbh.actions.segment import segment_files
    from cbh.timeutil import parse_utc

    rows = segment_files(images, out, station, camera, parse_utc(time, "--time") if time else None)
    if as_json:
        print(json.dumps({"images": rows}, indent=2))
    else:
        for r in rows:
            print(f"{r['image']}: cloud fraction {r['cloud_fraction']:.3f} -> {r['mask']}")
