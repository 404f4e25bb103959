"""Stage 1: which pixels of a camera are usable sky.

Static part (cached per camera): image circle ∩ zenith ≤ ``max_zenith_deg`` ∩ the station's
obstacle mask image. Per frame: minus a disk around the sun (pvlib position for the station's
latitude/longitude and the frame's UTC time) and minus saturated blobs (sun, glare).
"""
from __future__ import annotations

from datetime import datetime
from pathlib import Path

import numpy as np

from ..errors import ImageError
from ..station import Camera
from .config import MasksConfig

__all__ = ["static_sky_mask", "load_obstacle_mask", "sun_direction_enu", "angle_map_deg", "saturation_mask"]


def load_obstacle_mask(path: Path, width: int, height: int) -> np.ndarray:
    """Read an obstacle mask image (non-zero = usable sky) resized to (height, width), bool."""
    import cv2

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


def sun_direction_enu(latitude_deg: float, longitude_deg: float, time_utc: datetime) -> tuple[np.ndarray, float]:
    """Unit vector towards the sun in ENU and its apparent zenith angle [deg] (pvlib SPA)."""
    import pandas as pd
    import pvlib

    pos = pvlib.solarposition.get_solarposition(pd.DatetimeIndex([time_utc]), latitude_deg, longitude_deg)
    zen = float(np.radians(pos["apparent_zenith"].iloc[0]))
    az = float(np.radians(pos["azimuth"].iloc[0]))  # clockwise from north
    d = np.array([np.sin(zen) * np.sin(az), np.sin(zen) * np.cos(az), np.cos(zen)])
    return d, float(np.degrees(zen))


def angle_map_deg(cam: Camera, direction_world: np.ndarray) -> np.ndarray:
    """Angle [deg] between every pixel's ray and an ENU direction, shape (H, W), float32."""
    d_cam = np.asarray(direction_world, np.float64) @ cam.R_world_from_cam  # into the camera frame
    rays = cam.model.ray_map()
    c = (rays[..., 0] * d_cam[0] + rays[..., 1] * d_cam[1] + rays[..., 2] * d_cam[2]).astype(np.float32)
    return np.degrees(np.arccos(np.clip(c, -1.0, 1.0)))


def saturation_mask(image_bgr: np.ndarray, cfg: MasksConfig) -> np.ndarray:
    """Saturated blobs (all channels ≥ level), grown by ``saturation_grow_px``, shape (H, W), bool."""
    import cv2

    sat = (image_bgr.min(axis=2) >= cfg.saturation_level).astype(np.uint8)
    if not sat.any():
        return sat.astype(bool)
    n, lab, stats, _ = cv2.connectedComponentsWithStats(sat, connectivity=8)
    keep = stats[:, cv2.CC_STAT_AREA] >= cfg.saturation_min_area_px
    keep[0] = False
    out = keep[lab].astype(np.uint8)
    if cfg.saturation_grow_px > 0 and out.any():
        k = 2 * cfg.saturation_grow_px + 1
        out = cv2.dilate(out, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k)))
    return out.astype(bool)
