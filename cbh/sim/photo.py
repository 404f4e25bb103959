"""Stereo pairs built from a real sky photograph: real texture, known truth.

Camera 1 is the photograph's own calibrated camera. Camera 2 is a virtual camera (any pose)
that sees the photograph's sky as a horizontal plane at a chosen height: each camera-2 pixel's
ray meets the plane, and that point is looked up in the photograph. Every pixel of camera 1
then lies at that height, so a matcher's heights can be scored exactly on real cloud texture,
JPEG noise and lens vignetting, which the procedural sky (:mod:`cbh.sim.render`) does not have.

Caveats, as for any pair made this way: camera 2 is resampled (bilinear: a little smoother
than camera 1), black where camera 1 does not see the plane, and its sun is the photograph's
sun moved onto the plane rather than where the station's geometry puts it.
"""
from __future__ import annotations

import math
from dataclasses import replace

import cv2
import numpy as np

from cbh.geometry.station import Camera, rot_z

__all__ = ["virtual_camera", "plane_view"]


def virtual_camera(cam1: Camera, position_m, yaw_deg: float = 0.0, name: str = "virtual") -> Camera:
    """Camera 1's lens at ``position_m`` (ENU [m]), turned ``yaw_deg`` about the vertical from it."""
    return replace(cam1, name=name, position_m=np.asarray(position_m, np.float64).reshape(3),
                   R_world_from_cam=rot_z(-math.radians(yaw_deg)) @ cam1.R_world_from_cam)


def plane_view(photo: np.ndarray, cam1: Camera, cam2: Camera, height_m: float) -> np.ndarray:
    """Camera 2's image of ``photo`` (camera 1's, at its model's size) seen as a horizontal plane
    at ``height_m`` above the ENU origin; 0 where camera 1 does not see the point (or the ray
    does not rise to the plane). Same dtype and channels as ``photo``."""
    if photo.shape[:2] != (cam1.model.height, cam1.model.width):
        raise ValueError(f"photo is {photo.shape[1]}x{photo.shape[0]}, camera 1's model "
                         f"{cam1.model.width}x{cam1.model.height}")
    h, w = cam2.model.height, cam2.model.width
    d = cam2.pixel_to_world(cam2.model.pixel_grid().reshape(-1, 2))  # (N, 3) ENU rays
    with np.errstate(invalid="ignore", divide="ignore"):
        t = np.where(d[:, 2] > 1e-3, (height_m - cam2.position_m[2]) / d[:, 2], np.nan)
    px1 = cam1.world_to_pixel(cam2.position_m + d * t[:, None])
    m = np.nan_to_num(px1, nan=-1e5).reshape(h, w, 2).astype(np.float32)
    return cv2.remap(photo, m[..., 0], m[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
