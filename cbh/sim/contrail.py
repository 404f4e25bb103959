"""Aircraft contrails drawn into rendered frames: long, thin, straight clouds at cruise level.

Real sky cameras see them most days near air routes (the real Fehmarn hour has several, across
the whole sky), and they are the hardest texture a stereo matcher meets: a line has no texture
along itself, so where a contrail runs along the baseline (its epipolar direction) every plane
of the sweep finds it somewhere (the aperture problem), and it is a new, narrow cloud class in a
clear sky's colour statistics.

A :class:`Contrail` is a horizontal line in the plane ``height_m`` above the ENU origin (metres),
drawn per camera by intersecting each pixel's ray with that plane (so the two cameras see it
with its true parallax), with a Gaussian cross-section of ``width_m``. It adds
``brightness_dn`` at its axis, up to the camera's white (``white_dn``, per channel: a camera
clips it where it clips the rest, white balance and all; not the frame's brightest pixel, which
JPEG's ringing round a clipped sun lifts to 255 above a 230 clip: randomized 17477, a contrail
through the sun drawn at 255 beside an aureole clipped at 228, made that ringing the clip
level), and hides behind lower cloud: it is drawn only where the true height map is clear or
higher, and there it becomes the true height. It is drawn onto the finished frames, after the
renderer's noise, colour response and JPEG: a trail is cleaner than the sky around it (no noise
or compression of its own), which makes it easier to segment than a real one, not harder to match.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["Contrail", "draw_contrail"]

_MIN_UP = 0.05  # rays closer to the horizon than this (z-component) do not reach the trail's plane in view
_TRUTH_WEIGHT = 0.3  # where the trail adds at least this share of its axis brightness, it is the visible cloud


@dataclass(frozen=True)
class Contrail:
    height_m: float  # above the ENU origin (camera 1 in the randomized stations) [m]
    point_m: tuple[float, float]  # a point of its axis, east and north of camera 1 [m]
    azimuth_deg: float  # direction of its axis, clockwise from north [deg]
    width_m: float  # Gaussian σ of its cross-section [m]
    brightness_dn: float  # added at its axis [DN]
    length_m: float = 60000.0  # along its axis, centred on ``point_m`` [m]


def draw_contrail(image: np.ndarray, height_m: np.ndarray, camera, trail: Contrail,
                  white_dn=255.0) -> tuple[np.ndarray, np.ndarray]:
    """``image`` (H, W, 3) uint8 and its true ``height_m`` map (H, W; NaN = clear) with ``trail``
    drawn in as ``camera`` (a station camera at the image's size) sees it, clipped at the camera's
    output white ``white_dn`` [DN] (a number, or (3,) BGR: ``SkySimulator.output_white``).
    Returns new arrays."""
    H, W = image.shape[:2]
    yy, xx = np.mgrid[0:H, 0:W]
    d = camera.pixel_to_world(np.stack([xx.ravel(), yy.ravel()], -1).astype(np.float64))
    o = np.asarray(camera.position_m, np.float64)
    up = d[:, 2]
    with np.errstate(invalid="ignore", divide="ignore"):
        t = (trail.height_m - o[2]) / up
    xy = o[None, :2] + d[:, :2] * t[:, None] - np.asarray(trail.point_m, np.float64)[None, :]
    a = math.radians(trail.azimuth_deg)
    along = xy @ np.array([math.sin(a), math.cos(a)])
    across = xy @ np.array([math.cos(a), -math.sin(a)])
    w = np.exp(-0.5 * (across / trail.width_m) ** 2) * (np.abs(along) <= trail.length_m / 2) * (up > _MIN_UP)
    w = np.nan_to_num(w).reshape(H, W).astype(np.float32)
    h_trail = trail.height_m  # the plane crossed above: ENU z, as the true height maps
    seen = ~(height_m < h_trail)  # clear (NaN) or higher cloud: the trail is in front
    w *= seen
    img = image.astype(np.float32)  # (a pixel already above the white, JPEG's ringing, is not darkened)
    out = np.minimum(img + trail.brightness_dn * w[..., None], np.maximum(img, np.asarray(white_dn, np.float32)))
    truth = np.where(w >= _TRUTH_WEIGHT, np.float32(h_trail), height_m).astype(height_m.dtype)
    return np.rint(out).astype(np.uint8), truth
