"""`cbh segment`: cloud masks of sky images (PNG, 255 cloud / 0 clear or unusable)."""
from __future__ import annotations

import json
from pathlib import Path

import typer


def register(app: typer.Typer) -> None:
    app.command("segment")(segment_cmd)


def segment_cmd(
    images: list[Path] = typer.Argument(..., help="Colour sky images (JPEG/PNG); crops are fine without --station."),
    out: Path = typer.Option(..., "--out", help="Mask file NAME.png (one image), or a folder (created if missing) "
                             "that gets <image stem>.png per image; an existing folder works for one image too."),
    station: str = typer.Option(None, "--station", help="Station TOML or preset: apply its masks (image circle, zenith, obstacles, sun)."),
    camera: str = typer.Option(None, "--camera", help="The station camera that took the images (default: its first)."),
    time: str = typer.Option(None, "--time", help="Capture time, ISO 8601 (with --station: masks the sun, sun-aware regions)."),
    as_json: bool = typer.Option(False, "--json", help="Print the cloud fraction per image as one JSON object."),
) -> None:
    """Classify every pixel as cloud or clear sky (default method: hybrid; refuses greyscale).

    Masks are 8-bit PNG (255 cloud, 0 clear or unusable). --out ending in .png is the mask of
    the one image; any other --out is a folder, and each mask is <image stem>.png in it (so
    `--out masks/` with one image writes masks/<stem>.png). Refused before any work: a .png
    name for several images, another image suffix (x.jpg), two images with the same stem, and
    a mask that would overwrite an input image. An existing mask of the same name is replaced."""
    from cbh.actions.segment import segment_files
    from cbh.timeutil import parse_utc

    rows = segment_files(images, out, station, camera, parse_utc(time, "--time") if time else None)
    if as_json:
        print(json.dumps({"images": rows}, indent=2))
    else:
        for r in rows:
            print(f"{r['image']}: cloud fraction {r['cloud_fraction']:.3f} -> {r['mask']}")
