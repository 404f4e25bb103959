"""`cbh triangulate`: the paper's drone validation as a command."""
from __future__ import annotations

import json
from pathlib import Path

import typer

from cbh.actions.triangulate import check_metrics, format_triangulation, triangulate_pixels


def register(app: typer.Typer) -> None:
    app.command("triangulate")(triangulate_cmd)


def triangulate_cmd(
    station: Path = typer.Option(..., "--station", help="Station TOML."),
    pixels: Path = typer.Option(..., "--pixels", help="CSV with x1,y1,x2,y2[,true_height_m]."),
    cameras: str = typer.Option(None, "--cameras", help="Two camera names, e.g. cam1,cam2 (default: first two)."),
    as_json: bool = typer.Option(False, "--json", help="Print one JSON object."),
) -> None:
    """Triangulate pixel pairs; print heights, ray-miss distances and, given true heights, MAE/MAPE/RMSE."""
    r = triangulate_pixels(station, pixels, cameras)
    print(json.dumps(r.to_dict()) if as_json else format_triangulation(r))
    check_metrics(r)
