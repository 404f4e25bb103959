"""`cbh triangulate`: the paper's drone validation as a command."""
from __future__ import annotations

import json
from pathlib import Path

import typer


def register(app: typer.Typer) -> None:
    app.command("triangulate")(triangulate_cmd)


def triangulate_cmd(
    station: Path = typer.Option(..., "--station", help="Station TOML."),
    pixels: Path = typer.Option(..., "--pixels", help="CSV with x1,y1,x2,y2[,true_height_m]."),
    cameras: str = typer.Option(None, "--cameras", help="Two camera names, e.g. cam1,cam2 (default: first two)."),
    as_json: bool = typer.Option(False, "--json", help="Print one JSON object."),
) -> None:
    """Triangulate pixel pairs; print heights, ray-miss distances and, given true heights, MAE/MAPE/RMSE."""
    import numpy as np

    from cbh.geometry.station import load_station
    from cbh.geometry.validation import height_metrics, read_pixel_pairs, triangulate_pixel_pairs

    st = load_station(station)
    cam1, cam2 = st.pair(cameras)
    pairs = read_pixel_pairs(pixels)
    tri = triangulate_pixel_pairs(cam1, cam2, pairs)
    metrics = None
    if pairs.true_height_m is not None:
        h = np.where(tri.valid, tri.height_m, np.nan)
        metrics = height_metrics(h, pairs.true_height_m)
    if as_json:
        pts = [
            {"height_m": float(p[2]), "east_m": float(p[0]), "north_m": float(p[1]), "up_m": float(p[2]),
             "miss_m": float(m), "valid": bool(v)}
            for p, m, v in zip(tri.point_m, tri.miss_m, tri.valid)
        ]
        print(json.dumps({"points": pts, "metrics": metrics or {}}, indent=None))
        return
    print(f"{'height_m':>10} {'east_m':>10} {'north_m':>10} {'up_m':>10} {'miss_m':>8} valid")
    for p, m, v in zip(tri.point_m, tri.miss_m, tri.valid):
        print(f"{p[2]:10.2f} {p[0]:10.2f} {p[1]:10.2f} {p[2]:10.2f} {m:8.3f} {str(bool(v)).lower()}")
    if metrics:
        print(f"n={metrics['n']}  MAE={metrics['mae_m']:.2f} m  MAPE={metrics['mape_pct']:.2f} %  RMSE={metrics['rmse_m']:.2f} m")
