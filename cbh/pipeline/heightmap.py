"""Stage 4b: the dense cloud-base height map on camera 1's pixel grid (NaN = unknown).

Triangulated correspondences are splatted onto camera 1's grid (mean of the heights that land
in a pixel); holes are filled only inside camera 1's cloud mask and only within
``fill_max_px`` of a measured pixel, by copying the *nearest* measured height (no averaging,
so two layers meeting at an edge are never blended into a height that exists in neither).

Coverage. The map can only cover camera 1's *analysed field of view*: the usable sky of
stage 1, i.e. zenith ≤ ``masks.max_zenith_deg`` (default 80°; beyond it the air path, haze
and the ground make both segmentation and matching unreliable, and the parallax of a cloud
seen that low is small), minus the sun disk, glare and obstacles. The coverage bar (≥ 70 % of
the pixels that are cloud in truth) is therefore measured over true-cloud pixels inside that
zenith limit: a scene whose cloud lies largely beyond 80° (e.g. sun-behind-clouds, 27 % of its
cloud) is not under-covered by the map but outside the analysed sky by design.
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import cv2
import numpy as np

from cbh.result import Enlarged
from cbh.pipeline.ccl import components_with_stats


__all__ = ["HeightMap", "dense_height_map", "rasterize_heights", "nearest_fill"]


@dataclass(frozen=True)
class HeightMap:
    """Stage 6: camera 1's dense cloud-base height map (NaN = unknown)."""

    working_m: np.ndarray  # (h, w) float32 at working size [m]
    nearest_m: np.ndarray  # (h, w) float32: height of each pixel's nearest measured pixel [m]
    full_size: tuple[int, int]  # camera 1's full (width, height) [px]: :meth:`full` is the map there
    measured_fraction: float = float("nan")  # share of the cloud mask's pixels measured (before the fill)
    measured: np.ndarray | None = None  # (h, w) bool: the cloud pixels measured (before the fill)

    def full(self) -> Enlarged:
        """The working map standing for camera 1's full-size one (enlarged only when read)."""
        return Enlarged(self.working_m, *self.full_size)

    @cached_property
    def largest_patch_px(self) -> int:
        """Area of the largest 8-connected patch of measured cloud pixels, at working size [px]
        (0: none measured, or no mask kept; found once, for the layers and the flags alike)."""
        if self.measured is None or not self.measured.any():
            return 0
        _, _, stats, _ = components_with_stats(self.measured.view(np.uint8))
        return int(stats[1:, cv2.CC_STAT_AREA].max())


def dense_height_map(shape: tuple[int, int], px: np.ndarray, height_m: np.ndarray, cloud: np.ndarray,
                     cfg, full_size: tuple[int, int], grids=(), nearest=None) -> HeightMap:
    """Splat heights onto camera 1's working grid, fill holes inside the cloud mask (see module doc).

    Parameters
    ----------
    shape : (h, w)
        Working grid size.
    px : ndarray, shape (N, 2), float
        Camera 1 working-size pixels of the heights.
    height_m : ndarray, shape (N,)
    cloud : ndarray, shape (h, w), bool
        Camera 1's cloud mask: holes are filled only there.
    cfg : HeightMapConfig
    full_size : (W, H)
        Camera 1's full image size.
    grids : sequence of ndarray, shape (h, w), float32
        Height maps measured per pixel (a plane sweep's field, NaN = none), merged with the
        splatted points by the mean of what each pixel has (each grid counts as one height).
    nearest : callable or None
        The hole fill's ``hmap → (nearest, dist)``; None: :func:`nearest_fill` (OpenCV). The
        torch backend hands in :func:`cbh.pipeline.torch_heightmap.nearest_fill_torch`.
    """
    hmap = rasterize_heights(shape, px, height_m)
    if grids:
        if len(px) == 0 and len(grids) == 1:
            hmap = grids[0]
        else:
            with np.errstate(invalid="ignore"):
                stack = np.stack([hmap, *grids])
                n = np.isfinite(stack).sum(axis=0)
                hmap = np.where(n > 0, np.nansum(stack, axis=0) / np.maximum(n, 1), np.nan).astype(np.float32)
    known = np.isfinite(hmap)
    n_cloud = int(np.count_nonzero(cloud))
    on_cloud = known & cloud
    measured = float(np.count_nonzero(on_cloud)) / n_cloud if n_cloud else float("nan")
    nearest, dist = (nearest or nearest_fill)(hmap)
    if cfg.fill == "nearest":
        fill = cloud & ~known & (dist <= cfg.fill_max_px)
        hmap = hmap.copy()
        hmap[fill] = nearest[fill]
    return HeightMap(working_m=hmap, nearest_m=nearest, full_size=(int(full_size[0]), int(full_size[1])),
                     measured_fraction=measured, measured=on_cloud)


def rasterize_heights(shape: tuple[int, int], px: np.ndarray, height_m: np.ndarray) -> np.ndarray:
    """Mean height per pixel.

    Parameters
    ----------
    shape : (H, W)
    px : ndarray, shape (N, 2), float
        Pixel coordinates (x, y); rounded to the nearest pixel centre.
    height_m : ndarray, shape (N,), float [m]

    Returns
    -------
    ndarray, shape (H, W), float32
        NaN where no point landed.
    """
    h, w = shape
    out = np.full(h * w, np.nan, np.float32)
    if len(px) == 0:
        return out.reshape(h, w)
    xi = np.rint(px[:, 0]).astype(np.int64)
    yi = np.rint(px[:, 1]).astype(np.int64)
    ok = (xi >= 0) & (xi < w) & (yi >= 0) & (yi < h) & np.isfinite(height_m)
    idx = yi[ok] * w + xi[ok]
    c = np.bincount(idx, minlength=h * w)
    if c.max(initial=0) <= 1:  # one height per pixel (a dense matcher): no mean to take
        out[idx] = height_m[ok]
        return out.reshape(h, w)
    s = np.bincount(idx, weights=height_m[ok], minlength=h * w)
    has = c > 0
    out[has] = (s[has] / c[has]).astype(np.float32)
    return out.reshape(h, w)


def nearest_fill(hmap: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Nearest measured height and the distance to it, for every pixel.

    Parameters
    ----------
    hmap : ndarray, shape (H, W), float32
        Height map, NaN where unknown.

    Returns
    -------
    nearest : ndarray, shape (H, W), float32
        Height of the nearest measured pixel (NaN everywhere if nothing is measured).
    dist_px : ndarray, shape (H, W), float32
        Distance to it [px] (0 on measured pixels, inf if nothing is measured).
    """
    known = np.isfinite(hmap)
    if not known.any():
        return np.full_like(hmap, np.nan), np.full(hmap.shape, np.inf, np.float32)
    dist, lab = cv2.distanceTransformWithLabels((~known).astype(np.uint8), cv2.DIST_L2, 5,
                                                labelType=cv2.DIST_LABEL_PIXEL)
    values = np.empty(int(lab.max()) + 1, np.float32)
    values[0] = np.nan
    n = int(np.count_nonzero(known))
    if _raster_labels(known, lab, n):  # label i = the i-th measured pixel in raster order: no index gather
        values[1:] = hmap[known]
    else:
        ky, kx = np.nonzero(known)
        values[:] = np.nan
        values[lab[ky, kx]] = hmap[ky, kx]
    return np.take(values, lab), dist


def _raster_labels(known: np.ndarray, lab: np.ndarray, n: int) -> bool:
    """Whether OpenCV numbered the ``n`` zero pixels 1 … n in raster order (its behaviour with
    ``DIST_LABEL_PIXEL``, which the tests check on random maps; here, cheaply: the label count,
    and the first and last measured pixel of up to 32 rows)."""
    if int(lab.max()) != n:
        return False
    rows = np.count_nonzero(known, axis=1)
    before = np.concatenate([[0], np.cumsum(rows)])  # measured pixels above each row
    ys = np.flatnonzero(rows)
    for y in ys[np.linspace(0, len(ys) - 1, min(32, len(ys))).astype(int)]:
        xs = np.flatnonzero(known[y])
        if lab[y, xs[0]] != before[y] + 1 or lab[y, xs[-1]] != before[y + 1]:
            return False
    return True
