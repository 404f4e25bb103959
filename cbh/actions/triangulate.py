"""``cbh triangulate`` in library terms: the paper's drone validation (pixel pairs → heights, metrics)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cbh.errors import InputError
from cbh.geometry.triangulate import Triangulation

__all__ = ["PixelTriangulation", "triangulate_pixels", "format_triangulation", "check_metrics"]


@dataclass
class PixelTriangulation:
    tri: Triangulation
    metrics: dict | None  # height_metrics over rows with a true height; None without true heights

    def to_dict(self) -> dict:
        pts = [{"height_m": float(p[2]), "east_m": float(p[0]), "north_m": float(p[1]), "up_m": float(p[2]),
                "miss_m": float(m), "valid": bool(v)}
               for p, m, v in zip(self.tri.point_m, self.tri.miss_m, self.tri.valid)]
        return {"points": pts, "metrics": self.metrics or {}}


def triangulate_pixels(station, pixels, cameras: str | None = None) -> PixelTriangulation:
    """Triangulate the pixel pairs of a CSV (``x1,y1,x2,y2[,true_height_m]``) with a station's cameras.

    Metrics (MAE, MAPE, RMSE; paper Table 3) use only rows that are valid and have a true height.
    """
    from cbh.actions.station import load_station
    from cbh.geometry.validation import height_metrics, read_pixel_pairs, triangulate_pixel_pairs

    cam1, cam2 = load_station(station).pair(cameras)
    pairs = read_pixel_pairs(pixels)
    tri = triangulate_pixel_pairs(cam1, cam2, pairs)
    metrics = None
    if pairs.true_height_m is not None:
        metrics = height_metrics(np.where(tri.valid, tri.height_m, np.nan), pairs.true_height_m)
    return PixelTriangulation(tri, metrics)


def format_triangulation(r: PixelTriangulation) -> str:
    """The table ``cbh triangulate`` prints, and the metrics line."""
    out = [f"{'height_m':>10} {'east_m':>10} {'north_m':>10} {'up_m':>10} {'miss_m':>8} valid"]
    for p, m, v in zip(r.tri.point_m, r.tri.miss_m, r.tri.valid):
        out.append(f"{p[2]:10.2f} {p[0]:10.2f} {p[1]:10.2f} {p[2]:10.2f} {m:8.3f} {str(bool(v)).lower()}")
    if r.metrics is not None and r.metrics["n"]:
        out.append(f"n={r.metrics['n']}  MAE={r.metrics['mae_m']:.2f} m  MAPE={r.metrics['mape_pct']:.2f} %  "
                   f"RMSE={r.metrics['rmse_m']:.2f} m")
    return "\n".join(out)


def check_metrics(r: PixelTriangulation) -> None:
    """:class:`InputError` when true heights were given but no row is valid and has one (no metrics)."""
    if r.metrics is not None and r.metrics["n"] == 0:
        n = len(r.tri.valid)
        raise InputError(f"true heights given, but none of the {n} rows triangulated to a valid point with a true "
                         "height: no MAE/MAPE/RMSE (see the miss_m and valid columns)")
