"""Stage 1: which pixels of a camera are usable sky.

Static part (cached per camera): image circle ∩ zenith ≤ ``max_zenith_deg`` ∩ the station's
obstacle mask image. Per frame: minus a disk around the sun (:func:`cbh.geometry.sun.sun_position` for the
station and the frame's UTC time) and minus saturated blobs (sun, glare), saturated meaning
within a few DN of the image's own clip level (:mod:`cbh.pipeline.clip`).
"""
from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np

from cbh.errors import ImageError
from cbh.geometry.station import Camera
from cbh.pipeline.ccl import components_with_stats
from cbh.pipeline.clip import FULL_RANGE_WHITE_DN, ClipLevel, saturated_pixels
from cbh.pipeline.config import MasksConfig

__all__ = ["static_sky_mask", "load_obstacle_mask", "angle_map_deg", "saturation_mask", "glare_mask", "glare_and_sunlit",
           "near_clip"]


def load_obstacle_mask(path: Path, width: int, height: int) -> np.ndarray:
    """Read an obstacle mask image (non-zero = usable sky) resized to (height, width), bool."""
    img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if img is None:
        raise ImageError(f"obstacle mask: cannot read image {path}")
    if img.shape != (height, width):
        img = cv2.resize(img, (width, height), interpolation=cv2.INTER_NEAREST)
    return img > 0


def static_sky_mask(cam: Camera, cfg: MasksConfig, obstacle: np.ndarray | None = None) -> np.ndarray:
    """Usable sky that does not change from frame to frame.

    Parameters
    ----------
    cam : Camera
        Camera (at the size the mask is wanted).
    cfg : MasksConfig
    obstacle : ndarray, shape (H, W), bool, optional
        Obstacle mask (True = usable), already at the camera's size.

    Returns
    -------
    ndarray, shape (H, W), bool
        True where the pixel sees sky within ``cfg.max_zenith_deg`` of the zenith.
    """
    m = cam.model.image_circle_mask() & (cam.zenith_map() <= cfg.max_zenith_deg)
    if obstacle is not None and cfg.static_mask:
        m &= obstacle
    return m


def angle_map_deg(cam: Camera, direction_world: np.ndarray, rays_cam: np.ndarray | None = None) -> np.ndarray:
    """Angle [deg] between every pixel's ray and an ENU direction, shape (H, W), float32.

    ``rays_cam``: the camera's ray map (H, W, 3) as float32, if the caller caches one
    (default: ``cam.model.ray_map()``).
    """
    d_cam = np.asarray(direction_world, np.float64) @ cam.R_world_from_cam  # into the camera frame
    if rays_cam is None:
        rays_cam = cam.model.ray_map().astype(np.float32)
    c = cv2.min(cv2.max(cv2.transform(rays_cam, d_cam.reshape(1, 3)), -1.0), 1.0)  # cos, (H, W) float32
    sin = cv2.sqrt(cv2.max(cv2.subtract(1.0, cv2.multiply(c, c)), 0.0))
    return cv2.phase(c, sin, angleInDegrees=True)  # atan2(sin, cos): ≤ 0.01° from arccos, 8× faster


def saturation_mask(image_bgr: np.ndarray, cfg: MasksConfig, clip: ClipLevel | None = None) -> np.ndarray:
    """Saturated blobs of at least ``saturation_min_area_px``, grown by ``saturation_grow_px``.

    Saturated: every channel within ``255 − saturation_level`` DN of the image's clip level
    (:func:`cbh.pipeline.clip.saturated_pixels`): ``saturation_level`` is the threshold of a
    full-range image, and one that clips lower (limited-range video: 235; a sensor clipping
    early) has its threshold lowered with it.

    Parameters
    ----------
    image_bgr : ndarray, shape (H, W, 3), uint8
    cfg : MasksConfig
    clip : ClipLevel, optional
        The image's clip level when the caller has it (default: estimated on ``image_bgr``).

    Returns
    -------
    ndarray, shape (H, W), bool
    """
    sat = saturated_pixels(image_bgr, FULL_RANGE_WHITE_DN - int(cfg.saturation_level), clip)
    if not cv2.countNonZero(sat):
        return np.zeros(sat.shape, bool)
    x, y, w, h = cv2.boundingRect(sat)  # blobs and their growth: only around the saturated pixels
    g = max(int(cfg.saturation_grow_px), 0)
    y0, y1, x0, x1 = max(y - g, 0), min(y + h + g, sat.shape[0]), max(x - g, 0), min(x + w + g, sat.shape[1])
    n, lab, stats, _ = components_with_stats(sat[y0:y1, x0:x1])
    keep = stats[:, cv2.CC_STAT_AREA] >= cfg.saturation_min_area_px
    keep[0] = False
    out = np.zeros(sat.shape, bool)
    if not keep.any():
        return out
    blob = keep.astype(np.uint8)[lab]
    if g > 0:
        blob = cv2.dilate(blob, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * g + 1, 2 * g + 1)),
                          borderType=cv2.BORDER_CONSTANT, borderValue=0)
    out[y0:y1, x0:x1] = blob > 0
    return out


def glare_mask(image_bgr: np.ndarray, cfg: MasksConfig, sun_angle_deg: np.ndarray | None,
               clip: ClipLevel | None = None) -> np.ndarray:
    """The saturated pixels that are the sun's glare, not over-exposed cloud, (H, W) bool
    (:func:`glare_and_sunlit`'s first)."""
    return glare_and_sunlit(image_bgr, cfg, sun_angle_deg, clip)[0]


def glare_and_sunlit(image_bgr: np.ndarray, cfg: MasksConfig, sun_angle_deg: np.ndarray | None,
                     clip: ClipLevel | None = None) -> tuple[np.ndarray, np.ndarray | None]:
    """The saturated pixels that are the sun's glare, not over-exposed cloud, (H, W) bool; and the
    saturated cloud within ``glare_radius_deg`` of the sun, grown as the glare is (None: none).

    Clear sky saturates all three channels only in the aureole that spreads from the sun's own
    disk, so with a known sun (``sun_angle_deg``) a saturated blob (:func:`saturation_mask`,
    grown) is glare when it reaches the masked sun disk (``sun_radius_deg``) and lies within
    ``glare_radius_deg`` of the sun. A blob apart from the disk is sunlit cloud (a thin edge
    lit by forward scattering saturates 10–30° from the sun), and so is saturation farther out
    than ``glare_radius_deg``: both stay usable sky and segment as cloud (in simulation, 22 of
    23 saturated blobs 8–30° from the sun were cloud throughout; before, they were left out of
    the cloud mask and the irradiance nowcast read them as clear sky). Without a sun every
    saturated blob is glare.

    The second mask is that sunlit cloud: it segments as cloud, but its saturation contour is not
    the cloud's texture (it lies where each camera's exposure clips), so the matchers leave it out.
    """
    if sun_angle_deg is None or not cfg.sun:
        sat = saturation_mask(image_bgr, cfg, clip)
        if sun_angle_deg is None or cfg.glare_radius_deg >= 180.0:
            return sat, None
        return sat & (sun_angle_deg <= cfg.glare_radius_deg), None
    sat = saturation_mask(image_bgr, replace(cfg, saturation_grow_px=0), clip).view(np.uint8)  # blobs apart before they grow
    if not cv2.countNonZero(sat):
        return sat.view(bool), None
    ang = np.asarray(sun_angle_deg, np.float32)
    seeds = cv2.findNonZero(cv2.bitwise_and(sat, cv2.compare(ang, float(cfg.sun_radius_deg), cv2.CMP_LE)))
    x0 = y0 = 1 << 30
    x1 = y1 = -1
    seeds = seeds.reshape(-1, 2) if seeds is not None else np.zeros((0, 2), np.int32)
    while len(seeds):  # fill each blob that reaches the disk with 2 (one fill per blob)
        x, y = seeds[0]
        _, _, _, (rx, ry, rw, rh) = cv2.floodFill(sat, None, (int(x), int(y)), 2, 0, 0, 8)
        x0, y0, x1, y1 = min(x0, rx), min(y0, ry), max(x1, rx + rw), max(y1, ry + rh)
        seeds = seeds[sat[seeds[:, 1], seeds[:, 0]] == 1]
    g = max(int(cfg.saturation_grow_px), 0)  # grown as saturation_mask grows
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * g + 1, 2 * g + 1))
    limited = cfg.glare_radius_deg < 180.0
    sunlit = cv2.compare(sat, 1, cv2.CMP_EQ)  # the blobs that do not reach the disk
    if limited and cv2.countNonZero(sunlit):
        sunlit = cv2.bitwise_and(sunlit, cv2.compare(ang, float(cfg.glare_radius_deg), cv2.CMP_LE))
    sunlit = (cv2.dilate(sunlit, kernel) > 0 if g > 0 else sunlit > 0) if cv2.countNonZero(sunlit) else None
    out = np.zeros(sat.shape, bool)
    if x1 < 0:
        return out, sunlit
    H, W = sat.shape
    ya, yb, xa, xb = max(y0 - g, 0), min(y1 + g, H), max(x0 - g, 0), min(x1 + g, W)
    blob = cv2.compare(sat[ya:yb, xa:xb], 2, cv2.CMP_EQ)
    if g > 0:
        blob = cv2.dilate(blob, kernel, borderType=cv2.BORDER_CONSTANT, borderValue=0)
    if limited:
        blob = cv2.bitwise_and(blob, cv2.compare(ang[ya:yb, xa:xb], float(cfg.glare_radius_deg), cv2.CMP_LE))
    out[ya:yb, xa:xb] = blob > 0
    return out, sunlit


def near_clip(image_bgr: np.ndarray, cfg: MasksConfig, clip: ClipLevel | None, reach_px: int) -> np.ndarray | None:
    """The pixels within ``reach_px`` (a square) of a pixel at the image's clip level
    (:func:`~cbh.pipeline.clip.saturated_pixels`, the saturation mask's margin), (H, W) bool;
    None where nothing is clipped.

    A window that holds clipped pixels is not a measurement of where the sky's texture lies:
    its brightest part is cut where *this* camera's exposure clips, and two cameras clip the same
    cloud along different contours when their responses differ (``Pipeline`` then leaves such
    matches out of the geometry check). On an over-exposed randomized sky (16855: 24 % and 39 % of
    the two working images at white) every one of the 76 LK matches the geometry check had such
    a window in one camera or the other; their median miss of the epipolar curves, 1.9 px, flagged a
    correct station ``geometry_mismatch``.
    """
    sat = saturated_pixels(image_bgr, FULL_RANGE_WHITE_DN - int(cfg.saturation_level), clip)
    if not cv2.countNonZero(sat):
        return None
    k = 2 * max(int(reach_px), 0) + 1
    return cv2.dilate(sat, cv2.getStructuringElement(cv2.MORPH_RECT, (k, k))) > 0
