"""Static obstacle mask found automatically from a sequence of one camera's frames.

Buildings, trees and masts rise from the horizon and stay put; the sky above them is bright
(clear or cloudy) and changes as clouds drift. A pixel is an obstacle when, over the sequence,

1. its median brightness is well below the sky's at the same zenith angle (``dark_ratio`` of a
   high percentile of the ring's medians: sky brightness depends mostly on the angle from the
   zenith, so this is a per-ring threshold, robust to the brighter horizon and vignetting);
2. it barely changes (temporal standard deviation below ``static_dn``, or below half the sky's
   typical variability when clouds move), so a passing dark cloud base is not an obstacle;
3. it is connected to the horizon ring (the outer ``horizon_band_deg`` of the field of view):
   ground obstacles stand on the horizon; isolated dark blobs in the sky are not obstacles.

The result uses the station's ``mask`` convention: uint8, 255 = usable sky, 0 = obstacle or
outside the image circle.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from cbh.geometry.camera import CameraModel
from cbh.errors import ImageError, InputError

__all__ = ["ObstacleMaskConfig", "obstacle_mask_from_frames", "FrameObstacleConfig", "obstacles_in_frame"]


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
    return np.where(circle & ~obstacle, 255, 0).astype(np.uint8)


@dataclass(frozen=True)
class FrameObstacleConfig:
    """Thresholds of :func:`obstacles_in_frame` (one frame: no temporal cue)."""

    dark_ratio: float = 0.55  # obstacle brightness < this × the zenith ring's sky brightness [1]
    ring_percentile: float = 90.0  # percentile of a zenith ring's brightness taken as its sky [%]
    horizon_band_deg: float = 4.0  # obstacles must reach within this of the horizon (zenith 90°) [deg]
    max_elevation_deg: float = 45.0  # nothing higher above the horizon is taken for an obstacle [deg]
    min_area_px: int = 12  # smaller dark specks are left to the segmentation [px]
    dilate_px: int = 2  # safety margin grown around obstacles (their edges blend with the sky) [px]


def obstacles_in_frame(image_bgr: np.ndarray, zenith_deg: np.ndarray, circle: np.ndarray,
                       cfg: FrameObstacleConfig = FrameObstacleConfig()) -> np.ndarray:
    """Horizon obstacles (buildings, trees, masts) of ONE frame, for a camera without a mask.

    Ground objects are dark against the sky of the same zenith angle (they are lit from above
    and seen against the bright horizon sky; even a dark cloud base near the horizon is seen
    through haze that brightens it), and they stand on the horizon. A pixel is an obstacle
    when its brightest channel is below ``dark_ratio`` × the ``ring_percentile`` percentile of
    its 1° zenith ring, it lies within ``max_elevation_deg`` of the horizon, and its dark
    component reaches the band within ``horizon_band_deg`` of the horizon.

    Parameters
    ----------
    image_bgr : ndarray, shape (H, W, 3), uint8
    zenith_deg : ndarray, shape (H, W), float32
        Zenith angle of each pixel in the world frame [deg].
    circle : ndarray, shape (H, W), bool
        The camera's image circle (pixels that see the sky or the ground).

    Returns
    -------
    obstacle : ndarray, shape (H, W), bool
    """
    value = image_bgr.max(axis=2)
    look = circle & (zenith_deg >= 90.0 - cfg.max_elevation_deg) & (zenith_deg <= 90.0)
    if not look.any():
        return np.zeros(value.shape, bool)
    ring = np.clip(zenith_deg, 0.0, 90.0).astype(np.int32)
    ref = np.zeros(92, np.float32)
    rs, vs = ring[look], value[look]
    order = np.argsort(rs, kind="stable")
    rs, vs = rs[order], vs[order]
    bounds = np.searchsorted(rs, np.arange(93))
    for r in range(92):
        a, b = bounds[r], bounds[r + 1]
        if b > a:
            ref[r] = np.percentile(vs[a:b], cfg.ring_percentile)
    dark = look & (value < cfg.dark_ratio * ref[ring])
    cand = cv2.morphologyEx(dark.astype(np.uint8), cv2.MORPH_OPEN, np.ones((2, 2), np.uint8))
    n, labels, stats, _ = cv2.connectedComponentsWithStats(cand, connectivity=8)
    band = look & (zenith_deg >= 90.0 - cfg.horizon_band_deg)
    touching = np.unique(labels[band & (cand > 0)])
    touching = touching[(touching > 0)]
    touching = touching[stats[touching, cv2.CC_STAT_AREA] >= cfg.min_area_px]
    obstacle = np.isin(labels, touching)
    if cfg.dilate_px > 0 and obstacle.any():
        k = 2 * cfg.dilate_px + 1
        obstacle = cv2.dilate(obstacle.astype(np.uint8), np.ones((k, k), np.uint8)) > 0
    return obstacle & circle
