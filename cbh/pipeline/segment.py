"""Stage 2: classical cloud segmentation on the normalized blue-red ratio.

Contract of every method in :data:`SEGMENTERS`::

    method(nbr, usable, zenith_deg, sun_angle_deg, cfg, chroma=None) -> cloud (H, W) bool

``nbr`` = (B − R)/(B + R) (float32, (H, W)); clear sky is blue (NBR ≈ 0.2 … 0.6), clouds are
white or grey (NBR ≈ 0). ``usable`` is the sky mask, ``zenith_deg`` the zenith angle of each
pixel and ``sun_angle_deg`` its angle from the sun (None when unknown). ``chroma`` =
(max − min)/max of the three channels (float32, (H, W); 0 = grey; None = unknown). Pixels
outside ``usable`` are never cloud.

- ``nbr``: fixed threshold.
- ``nbr_adaptive``: the threshold falls towards the sun and the horizon, where clear sky is
  whiter (forward scattering, longer air path): t = t0 + (t_sun − t0)·exp(−ψ/ψ0) +
  (t_hor − t0)·ramp(zenith), so that bright clear sky there is not taken for cloud.
  The sun term is *not* applied to grey pixels (``chroma < grey_chroma``): sunlit cloud near
  the sun is bright and colourless (chroma ≈ 0.02–0.05), while clear sky, even in the bright
  aureole just outside the masked sun disk, keeps a blue tint (chroma ≥ 0.1; ≥ 0.2 in the
  simulator). Lowering the threshold there called most sunlit cloud within 25° of the sun clear
  (cloud NBR ≈ 0 ± 0.015 against a threshold of ≈ 0 at ψ = 10°).
- ``otsu``: Otsu's threshold on the usable NBR histogram, clamped to [otsu_min, otsu_max]
  (copes with a global colour shift of the camera).

Everything per pixel runs through OpenCV (multi-threaded; ≈ 5 ms per 960² image).
"""
from __future__ import annotations

import cv2
import numpy as np

from cbh.errors import ConfigError
from cbh.pipeline.config import SegmentationConfig

__all__ = ["SEGMENTERS", "normalized_blue_red", "chroma", "segment", "get_segmenter"]


def normalized_blue_red(image_bgr: np.ndarray) -> np.ndarray:
    """NBR = (B − R)/(B + R) of a BGR uint8 image, shape (H, W), float32 (0 where B + R = 0)."""
    b, _, r = cv2.split(image_bgr)
    s = cv2.add(b, r, dtype=cv2.CV_32F)
    d = cv2.subtract(b, r, dtype=cv2.CV_32F)
    return cv2.divide(d, cv2.max(s, 1.0))  # s = 0 only where d = 0


def chroma(image_bgr: np.ndarray) -> np.ndarray:
    """(max − min)/max of the channels of a BGR uint8 image, (H, W) float32 (0 where black)."""
    b, g, r = cv2.split(image_bgr)
    mx = cv2.max(cv2.max(b, g), r)
    mn = cv2.min(cv2.min(b, g), r)
    return cv2.divide(cv2.subtract(mx, mn, dtype=cv2.CV_32F), cv2.max(mx, 1).astype(np.float32))


def _nbr(nbr, usable, zenith_deg, sun_angle_deg, cfg: SegmentationConfig, chroma=None):
    return (nbr < cfg.threshold) & usable


def _nbr_adaptive(nbr, usable, zenith_deg, sun_angle_deg, cfg: SegmentationConfig, chroma=None):
    span = max(90.0 - cfg.horizon_start_deg, 1e-6)
    ramp = cv2.min(cv2.max(cv2.subtract(np.asarray(zenith_deg, np.float32), cfg.horizon_start_deg), 0.0), span)
    t = cv2.add(cv2.multiply(ramp, (cfg.horizon_threshold - cfg.threshold) / span), cfg.threshold)
    cloud = cv2.compare(nbr, t, cv2.CMP_LT)
    if sun_angle_deg is not None:
        sun = cv2.exp(cv2.multiply(np.asarray(sun_angle_deg, np.float32), -1.0 / cfg.sun_scale_deg))
        ts = cv2.add(t, cv2.multiply(sun, cfg.sun_threshold - cfg.threshold))
        sun_cloud = cv2.compare(nbr, ts, cv2.CMP_LT)
        if chroma is not None:  # grey pixels keep the threshold without the sun term
            grey = cv2.compare(chroma, cfg.grey_chroma, cv2.CMP_LT)
            sun_cloud = cv2.bitwise_or(sun_cloud, cv2.bitwise_and(cloud, grey))
        cloud = sun_cloud
    return (cloud > 0) & usable


def _otsu(nbr, usable, zenith_deg, sun_angle_deg, cfg: SegmentationConfig, chroma=None):
    v = nbr[usable]
    if v.size < 16:
        return np.zeros_like(usable)
    # map [-1, 1] to 0..255 for cv2's Otsu
    q = np.clip((v + 1.0) * 127.5, 0, 255).astype(np.uint8).reshape(-1, 1)
    t8, _ = cv2.threshold(q, 0, 255, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
    # Otsu puts values <= t8 in the low (cloud) class: the boundary is half a level above t8
    t = float(np.clip((t8 + 1.0) / 127.5 - 1.0, cfg.otsu_min, cfg.otsu_max))
    return (nbr < t) & usable


SEGMENTERS = {"nbr": _nbr, "nbr_adaptive": _nbr_adaptive, "otsu": _otsu}


def get_segmenter(name: str):
    """The segmentation function registered as ``name`` (case-insensitive)."""
    try:
        return SEGMENTERS[name.lower()]
    except KeyError:
        raise ConfigError(f"unknown segmentation method {name!r} (valid: {', '.join(SEGMENTERS)})") from None


def segment(image_bgr, usable, zenith_deg, sun_angle_deg, cfg: SegmentationConfig) -> tuple[np.ndarray, float]:
    """Cloud mask (H, W) bool and cloud fraction of the usable sky (0..1, 0 if none usable)."""
    nbr = normalized_blue_red(image_bgr)
    b, g, r = cv2.split(image_bgr)
    bright = cv2.max(cv2.max(b, g), r) >= cfg.min_brightness
    usable = usable & bright
    cloud = get_segmenter(cfg.method)(nbr, usable, zenith_deg, sun_angle_deg, cfg, chroma=chroma(image_bgr))
    n = int(np.count_nonzero(usable))
    return cloud, (float(np.count_nonzero(cloud)) / n if n else 0.0)
