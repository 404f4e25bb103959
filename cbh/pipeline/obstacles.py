"""Static obstacle mask found automatically from a sequence of one camera's frames.

Buildings, trees and masts rise from the horizon and stay put; the sky above them is bright
(clear or cloudy) and changes as clouds drift. A pixel is an obstacle when, over the sequence,

1. its median brightness is well below the sky's at the same zenith angle (``dark_ratio`` of a
   high percentile of the ring's medians: sky brightness depends mostly on the angle from the
   zenith, so this is a per-ring threshold, robust to the brighter horizon and vignetting);
2. it barely changes (temporal standard deviation below ``static_dn``, or below half the sky's
   typical variability when clouds move), so a passing dark cloud base is not an obstacle;
3. it is connected to the horizon ring (the outer ``horizon_band_deg`` of the field of view):
   ground obstacles stand on the horizon; isolated dark blobs in the sky are not obstacles;

or it is the camera's on-screen text in any of the frames (:func:`~.overlay.overlay_text`: its
date and time change from frame to frame, so they are neither static nor dark).

The result uses the station's ``mask`` convention: uint8, 255 = usable sky, 0 = obstacle or
outside the image circle.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from cbh.geometry.camera import CameraModel
from cbh.geometry.station import Camera
from cbh.errors import ImageError, InputError
from cbh.pipeline.ccl import components_with_stats
from cbh.pipeline.overlay import overlay_text, search_area

__all__ = ["ObstacleMaskConfig", "obstacle_mask_from_frames", "FrameObstacleConfig", "obstacle_rings", "obstacles_in_frame",
           "HorizonGrid", "horizon_grid", "darkest_of_four"]


@dataclass(frozen=True)
class ObstacleMaskConfig:
    dark_ratio: float = 0.6  # obstacle median brightness < this × the ring's sky brightness
    ring_percentile: float = 80.0  # percentile of a zenith ring's medians taken as its sky brightness
    static_dn: float = 6.0  # temporal std below this [DN] counts as static
    horizon_band_deg: float = 3.0  # obstacles must touch the outer band of the field [deg]
    dilate_px: int = 2  # safety margin grown around obstacles [px]
    min_frames: int = 3  # fewer frames cannot tell static from moving


def obstacle_mask_from_frames(images, model: CameraModel, cfg: ObstacleMaskConfig = ObstacleMaskConfig()) -> np.ndarray:
    """Usable-sky mask of one camera from a sequence of its frames.

    Parameters
    ----------
    images : sequence of ndarray, each (H, W, 3) uint8 BGR
        Frames of one camera, ideally spread over minutes so that clouds move.
    model : CameraModel
        The camera's lens model (image circle).
    cfg : ObstacleMaskConfig

    Returns
    -------
    mask : ndarray, shape (H, W), uint8
        255 = usable sky, 0 = static obstacle or outside the image circle.
    """
    images = list(images)
    if len(images) < cfg.min_frames:
        raise InputError(f"obstacle mask: need at least {cfg.min_frames} frames, got {len(images)}")
    H, W = model.height, model.width
    for i, im in enumerate(images):
        if im.shape[:2] != (H, W):
            raise ImageError(f"obstacle mask: frame {i} is {im.shape[1]}x{im.shape[0]}, calibration is {W}x{H}")
    theta = model.theta_map()
    circle = theta <= model.max_theta_deg
    gray = np.stack([cv2.cvtColor(im, cv2.COLOR_BGR2GRAY) for im in images]).astype(np.float32)
    med = np.median(gray, axis=0)
    std = gray.std(axis=0)

    # 1. dark against the sky of the same zenith ring (1° rings)
    ring = np.clip(theta, 0, model.max_theta_deg).astype(np.int32)
    ref = np.zeros(int(model.max_theta_deg) + 2, np.float32)
    for r in np.unique(ring[circle]):
        sel = circle & (ring == r)
        ref[r] = np.percentile(med[sel], cfg.ring_percentile)
    dark = med < cfg.dark_ratio * ref[ring]

    # 2. static: the sky's own variability sets the scale when clouds move
    sky_std = np.median(std[circle & ~dark]) if (circle & ~dark).any() else 0.0
    static = std < max(cfg.static_dn, 0.5 * sky_std)

    cand = (dark & static & circle).astype(np.uint8)
    cand = cv2.morphologyEx(cand, cv2.MORPH_OPEN, np.ones((3, 3), np.uint8))
    cand = cv2.morphologyEx(cand, cv2.MORPH_CLOSE, np.ones((5, 5), np.uint8))

    # 3. keep components that reach the horizon band
    n, labels = cv2.connectedComponents(cand, connectivity=8)
    horizon = circle & (theta >= model.max_theta_deg - cfg.horizon_band_deg)
    touching = np.unique(labels[horizon & (cand > 0)])
    obstacle = np.isin(labels, touching[touching > 0])
    if cfg.dilate_px > 0 and obstacle.any():
        k = 2 * cfg.dilate_px + 1
        obstacle = cv2.dilate(obstacle.astype(np.uint8), np.ones((k, k), np.uint8)) > 0
    # 4. the camera's on-screen text (its clock, its name), wherever a frame shows it
    inside = search_area(circle)
    for im in images:
        text = overlay_text(im, inside)
        if text is not None:
            obstacle |= text
    return np.where(circle & ~obstacle, 255, 0).astype(np.uint8)


@dataclass(frozen=True)
class FrameObstacleConfig:
    """Thresholds of :func:`obstacles_in_frame` (one frame: no temporal cue)."""

    dark_ratio: float = 0.55  # obstacle brightness < this × the zenith ring's sky brightness [1]
    weak_ratio: float = 0.9  # its paler parts (hazy rows, trunks): < this × the sky above them in their azimuth [1]
    fill_px: int = 2  # gaps up to about twice this (sky between branches, notches' blur) are closed [px]
    grid_deg: float = 0.25  # cell of the (azimuth, elevation) grid on which "stands on the ground" is judged [deg]
    hue_drop: float = 0.1  # … or less blue than it by this in (B − R) / (B + R) [1]
    sky_fade_per_deg: float = 0.04  # … whose reference follows a darker or less blue sky below it by this per degree [1/deg]
    hue_fresh_deg: float = 3.0  # … judged on hue only this close below where that sky was seen [deg]
    seed_span_deg: float = 10.0  # … within this of azimuth of a dark obstacle that stands on the horizon [deg] (30° took
    # pale blocks 10-30° from their nearest dark one, but also walked up the whitened aureole of a sun low over tree
    # lines: its ring then read as cloud, a layer at 335 m on a clear sky, randomized seed 5)
    pale_rise_deg: float = 2.0  # … and rise at most this above the tallest of those within that span [deg]
    pale_rise_ratio: float = 0.6  # … or this fraction of its height, if more (a taller row behind a lower one) [1]
    gap_deg: float = 1.0  # a column's obstacle may have gaps (sky between branches) this high and still stand [deg]
    ring_percentile: float = 90.0  # percentile of a zenith ring's brightness taken as its sky [%]
    horizon_band_deg: float = 4.0  # obstacles must reach within this of the horizon (zenith 90°) [deg]
    max_elevation_deg: float = 45.0  # nothing higher above the horizon is taken for an obstacle [deg]
    min_area_px: int = 12  # smaller dark specks are left to the segmentation [px]
    hang_px: int = 0  # dark parts this close to an obstacle (above its thin trunk or mast) join it [px]
    hang_max_px: int = 0  # … when no larger than this (a crown, not a cloud base darkening towards the horizon; 0: any) [px]
    dilate_px: int = 2  # safety margin grown around obstacles (their edges blend with the sky) [px]


def obstacle_rings(zenith_deg: np.ndarray, circle: np.ndarray, cfg: FrameObstacleConfig = FrameObstacleConfig()):
    """The per-camera constants of :func:`obstacles_in_frame`: each pixel's 1° zenith ring
    (uint8; 255 = not looked at: outside the circle, beyond the horizon or higher than
    ``max_elevation_deg``) and the horizon band (bool)."""
    look = circle & (zenith_deg >= 90.0 - cfg.max_elevation_deg) & (zenith_deg <= 90.0)
    ring = np.where(look, np.clip(zenith_deg, 0.0, 90.0).astype(np.int32), 255).astype(np.uint8)
    return ring, look & (zenith_deg >= 90.0 - cfg.horizon_band_deg)


@dataclass(frozen=True)
class HorizonGrid:
    """A camera's (azimuth, elevation) grid up to ``max_elevation_deg``: row 0 at the horizon.

    Attributes
    ----------
    map_x, map_y : ndarray, shape (n_el, n_az), float32
        Image pixel (column, row) of each cell's centre (``cv2.remap`` maps; −1 off the image).
    cell : ndarray, shape (H, W), int32
        Each image pixel's cell (row · n_az + column); −1 below the horizon or above the grid.
    off : ndarray, shape (n_el, n_az), bool
        Cells off the image.
    pixels, cells : ndarray, shape (M,), int64
        The flat indices of the pixels on the grid and of their cells.
    """

    map_x: np.ndarray
    map_y: np.ndarray
    cell: np.ndarray
    off: np.ndarray
    pixels: np.ndarray
    cells: np.ndarray


def horizon_grid(cam: Camera, size: tuple[int, int], cfg: FrameObstacleConfig = FrameObstacleConfig()) -> HorizonGrid:
    """The :class:`HorizonGrid` of ``cam`` (its calibration at any size) for images of ``size``
    (width, height) [px]: cells of ``cfg.grid_deg``."""
    n_az = int(round(360.0 / cfg.grid_deg))
    n_el = int(round(cfg.max_elevation_deg / cfg.grid_deg))
    az = np.radians((np.arange(n_az) + 0.5) * cfg.grid_deg)
    el = np.radians((np.arange(n_el) + 0.5) * cfg.grid_deg)
    d = np.stack(np.broadcast_arrays(np.cos(el)[:, None] * np.sin(az)[None, :], np.cos(el)[:, None] * np.cos(az)[None, :],
                                     np.sin(el)[:, None]), axis=-1).reshape(-1, 3)
    fx, fy = size[0] / cam.model.width, size[1] / cam.model.height
    px = cam.direction_to_pixel(d)
    mx = np.nan_to_num((px[:, 0] + 0.5) * fx - 0.5, nan=-1.0).reshape(n_el, n_az).astype(np.float32)
    my = np.nan_to_num((px[:, 1] + 0.5) * fy - 0.5, nan=-1.0).reshape(n_el, n_az).astype(np.float32)
    xs = (np.arange(size[0]) + 0.5) / fx - 0.5
    ys = (np.arange(size[1]) + 0.5) / fy - 0.5
    grid = np.stack(np.meshgrid(xs, ys), axis=-1).reshape(-1, 2)
    rays = cam.pixel_to_world(grid)
    e = np.degrees(np.arcsin(np.clip(rays[:, 2], -1.0, 1.0)))
    a = np.degrees(np.arctan2(rays[:, 0], rays[:, 1])) % 360.0
    r, c = np.floor(e / cfg.grid_deg).astype(np.int64), np.floor(a / cfg.grid_deg).astype(np.int64) % n_az
    ok = np.isfinite(e) & (r >= 0) & (r < n_el)
    cell = np.where(ok, r * n_az + c, -1).reshape(size[1], size[0]).astype(np.int32)
    off = cv2.remap(np.zeros((size[1], size[0]), np.uint8), mx, my, cv2.INTER_NEAREST,
                    borderMode=cv2.BORDER_CONSTANT, borderValue=1) > 0
    pixels = np.flatnonzero(cell >= 0)
    return HorizonGrid(mx, my, cell, off, pixels, cell.ravel()[pixels].astype(np.int64))


def _standing(image_bgr: np.ndarray, grid: HorizonGrid, cfg: FrameObstacleConfig,
              seeds: np.ndarray | None = None) -> np.ndarray:
    """Pixels that stand on the ground. Walking each azimuth column of the horizon grid down from
    ``max_elevation_deg``, a cell is not sky when its brightest channel is below ``weak_ratio`` ×
    the sky last seen above it in the same column, or when it is less blue than that sky by
    ``hue_drop`` in (B − R) / (B + R) (a hazy distant row is nearly as bright as the sky, but
    keeps some of its own colour; the sky's brightness changes with azimuth round the sun and
    smoothly with elevation, so the reference is the column's own sky). A column's non-sky
    cells that reach down to the horizon (gaps up to ``gap_deg`` bridged; cells off the image
    pass) are kept, in the columns within ``seed_span_deg`` of azimuth of a ``seeds`` pixel (uint8:
    dark obstacles standing on the horizon themselves; a dark sky's columns never stand on
    anything) and at most ``pale_rise_deg`` or ``pale_rise_ratio`` of its height above the tallest
    of them there (grey cloud that stands on a tree line is not walked up the sky). (H, W) bool."""
    n_az = grid.off.shape[1]
    n_el = grid.off.shape[0]
    top = np.full(n_az, n_el, np.int32)  # highest row a column's paler part may reach
    if seeds is None:
        cols = np.arange(n_az)
    else:  # only the columns near a dark obstacle on the horizon, and not far above its top
        seen = cv2.remap(seeds, grid.map_x, grid.map_y, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT,
                         borderValue=0) > 0
        height = np.where(seen.any(axis=0), n_el - np.argmax(seen[::-1], axis=0), 0).astype(np.float32)
        k = int(round(cfg.seed_span_deg / cfg.grid_deg))
        wrapped = np.concatenate([height[-k:], height, height[:k]])[None, :]
        near = cv2.dilate(wrapped, np.ones((1, 2 * k + 1), np.uint8))[0, k:k + n_az]
        cols = np.flatnonzero(near > 0)
        top = (near + np.maximum(cfg.pale_rise_deg / cfg.grid_deg, cfg.pale_rise_ratio * near)).astype(np.int32)
    standing = np.zeros(grid.cell.shape, bool)
    if cols.size == 0:
        return standing
    mx, my = np.ascontiguousarray(grid.map_x[:, cols]), np.ascontiguousarray(grid.map_y[:, cols])
    polar = cv2.remap(cv2.blur(image_bgr, (3, 3)), mx, my, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT,
                      borderValue=(0, 0, 0))
    pv = cv2.max(cv2.max(polar[..., 0], polar[..., 1]), polar[..., 2]).astype(np.float32)
    b, rr = polar[..., 0].astype(np.float32), polar[..., 2].astype(np.float32)
    nbr = (b - rr) / (b + rr + 1.0)
    off = grid.off[:, cols]
    dark = np.zeros(pv.shape, bool)
    sky, sky_nbr = pv[-1].copy(), nbr[-1].copy()
    age = np.zeros(pv.shape[1], np.int32)  # cells walked since the sky reference was last seen
    r, dh = np.float32(cfg.weak_ratio), np.float32(cfg.hue_drop)
    fade = np.float32(1.0 - cfg.sky_fade_per_deg * cfg.grid_deg)
    fade_nbr = np.float32(cfg.sky_fade_per_deg * cfg.grid_deg)
    fresh = int(round(cfg.hue_fresh_deg / cfg.grid_deg))
    a = np.float32(0.3)  # the reference's smoothing along the column (noise, JPEG)
    for e in range(pv.shape[0] - 1, -1, -1):  # top down
        less_blue = (nbr[e] < sky_nbr - dh) & (pv[e] < sky) & (age <= fresh)  # (cloud is brighter)
        d = (pv[e] < r * sky) | less_blue
        dark[e] = d | off[e]
        # the sky reference follows what is as blue as the sky (not cloud), and only slowly what is
        # darker or less blue (a pale distant row right above a darker one is not taken for the
        # sky the latter is judged by)
        like = ~d & ~off[e] & (nbr[e] >= sky_nbr - 0.5 * dh)
        np.copyto(sky, np.maximum(sky + a * (pv[e] - sky), sky * fade), where=like)
        np.copyto(sky_nbr, np.maximum(sky_nbr + a * (nbr[e] - sky_nbr), sky_nbr - fade_nbr), where=like)
        age = np.where(like, 0, age + 1)
    g = max(int(round(cfg.gap_deg / cfg.grid_deg)), 1)
    dark = cv2.morphologyEx(dark.view(np.uint8), cv2.MORPH_CLOSE, np.ones((2 * g + 1, 1), np.uint8)) > 0
    up = np.zeros(grid.off.shape, bool)
    up[:, cols] = np.logical_and.accumulate(dark, axis=0) & ~off
    up &= np.arange(n_el)[:, None] < top[None, :]
    up[:int(round(1.0 / cfg.grid_deg))] = False  # the lowest degree only carries: the circle's blurred rim is dark
    standing.ravel()[grid.pixels] = up.ravel()[grid.cells]
    return standing


def darkest_of_four(image_bgr: np.ndarray) -> np.ndarray:
    """The brightest channel of ``image_bgr`` (H, W, 3) at half size, ((H + 1) // 2, (W + 1) // 2),
    each pixel the darkest of the 2 × 2 it stands for (uint8): a mast or trunk one pixel wide keeps
    its darkness, where the area average halves its contrast."""
    b, g, r = cv2.split(image_bgr)
    v = cv2.max(cv2.max(b, g), r)
    H, W = v.shape
    if H % 2 or W % 2:
        v = cv2.copyMakeBorder(v, 0, H % 2, 0, W % 2, cv2.BORDER_REPLICATE)
    # each pixel the least of itself and its right, lower and lower-right neighbours; every second kept
    low = cv2.erode(v, np.ones((2, 2), np.uint8), anchor=(0, 0), borderType=cv2.BORDER_REPLICATE)
    return np.ascontiguousarray(low[0::2, 0::2])


def _ring_percentile(value: np.ndarray, ring: np.ndarray, q: float) -> np.ndarray:
    """The ``q``-th percentile (nearest rank) of uint8 ``value`` in each ring 0..90, (256,) float32
    (0 for rings without pixels and for the 255 "not looked at" ring): one 2-D histogram."""
    counts = np.bincount(ring.ravel().astype(np.int64) * 256 + value.ravel(), minlength=256 * 256).reshape(256, 256)
    cum = np.cumsum(counts, axis=1)
    n = cum[:, -1]
    rank = np.ceil(n * (q / 100.0)).astype(np.int64)
    ref = np.argmax(cum >= np.maximum(rank, 1)[:, None], axis=1).astype(np.float32)
    ref[n == 0] = 0.0
    ref[255] = 0.0
    return ref


def obstacles_in_frame(image_bgr: np.ndarray, ring: np.ndarray, band: np.ndarray,
                       cfg: FrameObstacleConfig = FrameObstacleConfig(), grid: HorizonGrid | None = None,
                       darkest: np.ndarray | None = None) -> np.ndarray:
    """Horizon obstacles (buildings, trees, masts) of ONE frame, for a camera without a mask.

    Ground objects are dark against the sky of the same zenith angle (they are lit from above
    and seen against the bright horizon sky; even a dark cloud base near the horizon is seen
    through haze that brightens it), and they stand on the horizon. A pixel is an obstacle
    when its brightest channel is below ``dark_ratio`` × the ``ring_percentile`` percentile of
    its 1° zenith ring, it lies within ``max_elevation_deg`` of the horizon, and its dark
    component reaches the band within ``horizon_band_deg`` of the horizon.

    With the camera's ``grid``, paler parts that stand on the ground beside such dark obstacles
    join them (:func:`_standing`: hazy rows, blurred masts and trunks), and so do dark parts
    within ``hang_px`` of them (crowns above trunks too thin to see); gaps up to about
    2 × ``fill_px`` (sky between branches) are closed, and the whole is grown by ``dilate_px``.

    Parameters
    ----------
    image_bgr : ndarray, shape (H, W, 3), uint8
    ring, band : ndarray, shape (H, W)
        :func:`obstacle_rings` of the camera (uint8 ring index, bool horizon band).
    cfg : FrameObstacleConfig
    grid : HorizonGrid, optional
        :func:`horizon_grid` of the camera at the image's size.
    darkest : ndarray, shape (H, W), uint8, optional
        The brightest channel with each pixel the darkest of the full-size pixels it stands for
        (:func:`darkest_of_four` when ``image_bgr`` is the half-size frame): masts and trunks one
        full-size pixel wide are dark in it, where the area average halves their contrast. They
        join the obstacles (and reach the crowns that ``hang_px`` joins), not the walk's seeds.

    Returns
    -------
    obstacle : ndarray, shape (H, W), bool
    """
    value = cv2.max(cv2.max(image_bgr[..., 0], image_bgr[..., 1]), image_bgr[..., 2])
    ref = _ring_percentile(value, ring, cfg.ring_percentile)
    look = ring != 255
    thr = (cfg.dark_ratio * ref)[ring]
    wide = cv2.morphologyEx(((value < thr) & look).view(np.uint8), cv2.MORPH_OPEN, np.ones((2, 2), np.uint8))
    strong = wide
    if darkest is not None:  # masts and trunks one full-size pixel wide
        strong = wide | ((darkest < thr) & look).view(np.uint8)
    cand = strong
    if grid is not None:  # paler parts that stand on the ground below them, beside dark ones that do
        s_n, s_labels, stats, _ = components_with_stats(strong)
        s_area = stats[:, cv2.CC_STAT_AREA]
        # the walk's seeds (and the heights that cap it) from what is dark at this size only: a thin
        # mast's cables and tip would lift the cap on the cloud beside it (the real WAHRSIS pair)
        w_n, w_labels, w_stats, _ = (s_n, s_labels, stats, None) if strong is wide else \
            components_with_stats(wide)
        seed = np.zeros(w_n, bool)
        seed[w_labels[band & (wide > 0)]] = True
        seed &= w_stats[:, cv2.CC_STAT_AREA] >= cfg.min_area_px
        seed[0] = False
        if seed.any():
            cand = strong | (_standing(image_bgr, grid, cfg, seed[w_labels].view(np.uint8)) & look).view(np.uint8)
    n, labels = cv2.connectedComponents(cand, connectivity=8)
    touching = np.zeros(n, bool)
    touching[labels[band & (cand > 0)]] = True
    anchor = np.bincount(labels[strong > 0], minlength=n) >= cfg.min_area_px  # holds a dark part of its own
    keep = touching & anchor
    keep[0] = False
    if not keep.any():
        return np.zeros(value.shape, bool)
    obstacle = keep[labels].view(np.uint8)
    if cfg.hang_px > 0 and grid is not None:  # dark parts hanging just above it (crowns on trunks too thin to see)
        near = cv2.dilate(obstacle, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * cfg.hang_px + 1,) * 2))
        hang = np.zeros(s_n, bool)
        hang[s_labels[(near > 0) & (strong > 0)]] = True
        hang &= (s_area >= cfg.min_area_px) & ((s_area <= cfg.hang_max_px) if cfg.hang_max_px > 0 else True)
        hang[0] = False
        obstacle |= hang[s_labels].view(np.uint8)
    if cfg.fill_px > 0:  # sky seen between branches and in thin gaps belongs to the obstacle
        k = 2 * cfg.fill_px + 1
        obstacle = cv2.morphologyEx(obstacle, cv2.MORPH_CLOSE, np.ones((k, k), np.uint8))
    obstacle = obstacle > 0
    if cfg.dilate_px > 0:
        k = 2 * cfg.dilate_px + 1
        obstacle = cv2.dilate(obstacle.view(np.uint8), np.ones((k, k), np.uint8)) > 0
    return obstacle & (ring != 255)
