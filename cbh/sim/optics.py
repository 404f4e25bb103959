"""What a real sky camera's optics add to its frames: lens-flare ghosts of the sun, and dust and
drops on the dome.

Neither is in the sky; both are in one camera's frame only, fixed to that camera, so the other
camera sees the same sky without them (or with its own, elsewhere):

- a **ghost** (:class:`Ghost`) is the sun imaged again by reflections between the lens's
  surfaces (and the dome's): a soft, tinted disk on the line through the sun's image and the
  optical centre, mostly on the other side of the centre, its place set by the sun's place in the
  frame and its tint by the coatings (green or magenta, the colours that anti-reflection
  coatings reflect most). All-sky cameras show one to a few whenever the sun is up and no
  shade ring hides it; the brightest reach tens of grey levels above the sky.
- a **dome spot** (:class:`DomeSpot`) is a speck of dust, a dried drop or a bird dropping on the
  dome: out of focus (the dome is a few centimetres from a lens focused at infinity), it blurs
  and dims the sky behind a patch of the frame.

Both are drawn onto the finished frames (after the renderer's noise, colour response and JPEG,
as :mod:`cbh.sim.contrail` draws its trails): the truth is unchanged (a ghost is not cloud; the
cloud behind a dome spot is still cloud).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

__all__ = ["Ghost", "DomeSpot", "draw_ghost", "draw_dome_spot", "GHOST_TINTS_BGR"]

GHOST_TINTS_BGR = {"green": (0.55, 1.0, 0.45), "magenta": (1.0, 0.45, 0.9), "amber": (0.35, 0.75, 1.0),
                   "white": (1.0, 1.0, 1.0)}


@dataclass(frozen=True)
class Ghost:
    ratio: float  # its centre at c − ratio · (sun − c) (c: the optical centre): > 0 across the centre [1]
    radius_frac: float  # radius as a share of the image circle's radius [1]
    brightness_dn: float  # added at its centre [DN]
    tint: str  # a key of GHOST_TINTS_BGR
    edge_frac: float = 0.3  # the soft edge's width, as a share of the radius [1]


@dataclass(frozen=True)
class DomeSpot:
    centre_frac: tuple[float, float]  # (x, y) from the optical centre, as shares of the image circle's radius [1]
    radius_frac: float  # as a share of the image circle's radius [1]
    blur_frac: float  # σ of the blur, as a share of the image circle's radius [1]
    transmission: float  # the light it lets through, 0..1 [1]


def _disk(shape, cx: float, cy: float, r: float, edge: float) -> np.ndarray:
    """A soft disk (H, W) float32: 1 inside ``r − edge``, 0 outside ``r``, a cosine ramp between."""
    H, W = shape
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float32)
    d = np.hypot(xx - np.float32(cx), yy - np.float32(cy))
    t = np.clip((r - d) / max(edge, 1e-3), 0.0, 1.0)
    return (0.5 - 0.5 * np.cos(np.pi * t)).astype(np.float32)


def _circle(camera) -> tuple[float, float, float]:
    """The camera's optical centre (x, y) [px] and the radius [px] of its image circle (90° off axis)."""
    m = camera.model
    cx, cy = m.center_xy
    return float(cx), float(cy), float(np.asarray(m.r_from_theta(np.array([math.pi / 2.0])))[0])


def draw_ghost(image: np.ndarray, camera, sun_dir_enu, ghost: Ghost, white_dn=255.0) -> np.ndarray:
    """``image`` (H, W, 3) uint8 with ``ghost`` of the sun (unit ENU vector ``sun_dir_enu``) drawn
    in as ``camera`` (a station camera at the image's size) images it, clipped at ``white_dn``
    (a number or (3,) BGR). The image itself when the sun is not in the frame."""
    p = camera.direction_to_pixel(np.asarray(sun_dir_enu, np.float64)[None, :])[0]
    if not np.all(np.isfinite(p)):
        return image
    cx, cy, rad = _circle(camera)
    gx, gy = cx - ghost.ratio * (p[0] - cx), cy - ghost.ratio * (p[1] - cy)
    r = ghost.radius_frac * rad
    w = _disk(image.shape[:2], gx, gy, r, ghost.edge_frac * r)
    add = w[..., None] * (ghost.brightness_dn * np.asarray(GHOST_TINTS_BGR[ghost.tint], np.float32))[None, None, :]
    im = image.astype(np.float32)
    # the ghost's light clips at the camera's white; a pixel already above it (JPEG's ringing
    # round a clipped sun) keeps its value
    out = np.minimum(im + add, np.maximum(im, np.asarray(white_dn, np.float32)))
    return out.round().clip(0, 255).astype(np.uint8)


def draw_dome_spot(image: np.ndarray, camera, spot: DomeSpot) -> np.ndarray:
    """``image`` (H, W, 3) uint8 with ``spot`` on ``camera``'s dome: the frame there blurred and
    dimmed by its transmission, fading in over its edge."""
    cx, cy, rad = _circle(camera)
    x, y = cx + spot.centre_frac[0] * rad, cy + spot.centre_frac[1] * rad
    r = spot.radius_frac * rad
    a = _disk(image.shape[:2], x, y, r, 0.5 * r)[..., None]
    sigma = max(spot.blur_frac * rad, 0.5)
    blurred = cv2.GaussianBlur(image, (0, 0), sigma).astype(np.float32) * np.float32(spot.transmission)
    out = image.astype(np.float32) * (1.0 - a) + blurred * a
    return out.round().clip(0, 255).astype(np.uint8)
