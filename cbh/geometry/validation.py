"""Point validation as in the paper's drone experiment: pixel pairs in, heights and metrics out."""
from __future__ import annotations

import csv
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cbh.errors import InputError
from cbh.geometry.station import Camera
from cbh.geometry.triangulate import Triangulation, TriangulationLimits, triangulate

__all__ = ["PixelPairs", "read_pixel_pairs", "triangulate_pixel_pairs", "height_metrics"]

REQUIRED = ("x1", "y1", "x2", "y2")


@dataclass(frozen=True)
class PixelPairs:
    px1: np.ndarray  # (N, 2) float64 [px] in camera 1
    px2: np.ndarray  # (N, 2) float64 [px] in camera 2
    true_height_m: np.ndarray | None  # (N,) float64 [m] above the ENU origin, NaN where blank


def read_pixel_pairs(path: str | Path) -> PixelPairs:
    """Read a CSV with columns x1,y1,x2,y2[,true_height_m]. Errors name the row and column."""
    import io

    from cbh.fileio import read_input

    path = Path(path)
    raw = read_input(path, "pixels file", InputError)
    try:
        rows, has_truth = _read_rows(csv.DictReader(io.StringIO(raw.decode("utf-8"), newline="")), path.name)
    except UnicodeDecodeError as exc:
        raise InputError(f"{path.name}: not a UTF-8 text CSV file (undecodable byte at offset {exc.start})") from None
    except csv.Error as exc:
        raise InputError(f"{path.name}: malformed CSV: {exc}") from None
    if not rows:
        raise InputError(f"{path.name}: no data rows")
    a = np.array(rows, dtype=np.float64)
    return PixelPairs(a[:, 0:2], a[:, 2:4], a[:, 4] if has_truth else None)


def _read_rows(reader: csv.DictReader, name: str) -> tuple[list[list[float]], bool]:
    cols = [c.strip() for c in (reader.fieldnames or [])]
    reader.fieldnames = cols
    missing = [c for c in REQUIRED if c not in cols]
    if missing:
        raise InputError(f"{name}: missing column {missing[0]!r} (need x1,y1,x2,y2[,true_height_m])")
    has_truth = "true_height_m" in cols
    rows = []
    for i, row in enumerate(reader, start=2):  # row 1 is the header
        vals = []
        for c in REQUIRED + (("true_height_m",) if has_truth else ()):
            cell = (row.get(c) or "").strip()
            if c == "true_height_m" and cell == "":
                vals.append(math.nan)
                continue
            try:
                v = float(cell)
            except ValueError:
                raise InputError(f"{name}: row {i}, column {c}: not a number: {cell!r}") from None
            if not math.isfinite(v):
                raise InputError(f"{name}: row {i}, column {c}: not finite: {cell!r}")
            vals.append(v)
        rows.append(vals)
    return rows, has_truth


def triangulate_pixel_pairs(
    cam1: Camera, cam2: Camera, pairs: PixelPairs, limits: TriangulationLimits = TriangulationLimits()
) -> Triangulation:
    """Triangulate pixel pairs; raises :class:`InputError` for a pixel outside an image circle."""
    for cam, px, k in ((cam1, pairs.px1, 1), (cam2, pairs.px2, 2)):
        bad = np.flatnonzero(~cam.model.contains(px))
        if bad.size:
            i = int(bad[0])
            raise InputError(
                f"row {i + 2}: pixel ({px[i, 0]:g}, {px[i, 1]:g}) is outside camera {cam.name!r}'s image circle "
                f"({cam.model.width}x{cam.model.height}, up to {cam.model.max_theta_deg:g} deg off-axis)"
            )
    return triangulate(cam1.position_m, cam1.pixel_to_world(pairs.px1), cam2.position_m, cam2.pixel_to_world(pairs.px2), limits)


def height_metrics(height_m: np.ndarray, true_height_m: np.ndarray) -> dict:
    """MAE [m], MAPE [%] and RMSE [m] over the pairs with a true height (paper Table 3)."""
    ok = np.isfinite(true_height_m) & np.isfinite(height_m)
    err = height_m[ok] - true_height_m[ok]
    if not ok.any():
        return {"n": 0, "mae_m": None, "mape_pct": None, "rmse_m": None}
    return {
        "n": int(ok.sum()),
        "mae_m": float(np.mean(np.abs(err))),
        "mape_pct": float(100 * np.mean(np.abs(err) / np.abs(true_height_m[ok]))),
        "rmse_m": float(np.sqrt(np.mean(err**2))),
    }
