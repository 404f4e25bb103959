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

__all__ = ["ObstacleMaskConfig", "obstacle_mask_from_frames", "FrameObstacleConfig", "obstacle_rings", "obstacles_in_frame"]


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


def obstacle_rings(zenith_deg: np.ndarray, circle: np.ndarray, cfg: FrameObstacleConfig = FrameObstacleConfig()):
    """The per-camera constants of :func:`obstacles_in_frame`: each pixel's 1° zenith ring
    (uint8; 255 = not looked at: outside the circle, beyond the horizon or higher than
    ``max_elevation_deg``) and the horizon band (bool)."""
    look = circle & (zenith_deg >= 90.0 - cfg.max_elevation_deg) & (zenith_deg <= 90.0)
    ring = np.where(look, np.clip(zenith_deg, 0.0, 90.0).astype(np.int32), 255).astype(np.uint8)
    return ring, look & (zenith_deg >= 90.0 - cfg.horizon_band_deg)


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
    ring, band : ndarray, shape (H, W)
        :func:`obstacle_rings` of the camera (uint8 ring index, bool horizon band).

    Returns
    -------
    obstacle : ndarray, shape (H, W), bool
    """
    value = cv2.max(cv2.max(image_bgr[..., 0], image_bgr[..., 1]), image_bgr[..., 2])
    ref = _ring_percentile(value, ring, cfg.ring_percentile)
    dark = (value < (cfg.dark_ratio * ref)[ring]) & (ring != 255)
    cand = cv2.morphologyEx(dark.view(np.uint8), cv2.MORPH_OPEN, np.ones((2, 2), np.uint8))
    n, labels, stats, _ = cv2.connectedComponentsWithStats(cand, connectivity=8)
    touching = np.unique(labels[band & (cand > 0)])
    touching = touching[(touching > 0)]
    touching = touching[stats[touching, cv2.CC_STAT_AREA] >= cfg.min_area_px]
    if touching.size == 0:
        return np.zeros(value.shape, bool)
    keep = np.zeros(n, bool)
    keep[touching] = True
    obstacle = keep[labels]
    if cfg.dilate_px > 0:
        k = 2 * cfg.dilate_px + 1
        obstacle = cv2.dilate(obstacle.view(np.uint8), np.ones((k, k), np.uint8)) > 0
    return obstacle & (ring != 255)
