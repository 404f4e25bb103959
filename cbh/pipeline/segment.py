"""Stage 2: classical cloud segmentation on the normalized blue-red ratio.

Contract of every method in :data:`SEGMENTERS`::

    method(nbr, usable, zenith_deg, sun_angle_deg, cfg) -> cloud (H, W) bool

``nbr`` = (B − R)/(B + R) (float32, (H, W)); clear sky is blue (NBR ≈ 0.2 … 0.6), clouds are
white or grey (NBR ≈ 0). ``usable`` is the sky mask, ``zenith_deg`` the zenith angle of each
pixel and ``sun_angle_deg`` its angle from the sun (None when unknown). Pixels outside
``usable`` are never cloud.

- ``nbr``: fixed threshold.
- ``nbr_adaptive``: the threshold falls towards the sun and the horizon, where clear sky is
  whiter (forward scattering, longer air path): t = t0 + (t_sun − t0)·exp(−ψ/ψ0) +
  (t_hor − t0)·ramp(zenith), so that bright clear sky there is not taken for cloud.
- ``otsu``: Otsu's threshold on the usable NBR histogram, clamped to [otsu_min, otsu_max]
  (copes with a global colour shift of the camera).
"""
from __future__ import annotations

import numpy as np

from ..errors import ConfigError
from .config import SegmentationConfig

__all__ = ["SEGMENTERS", "normalized_blue_red", "segment", "get_segmenter"]


def normalized_blue_red(image_bgr: np.ndarray) -> np.ndarray:
    """NBR = (B − R)/(B + R) of a BGR uint8 image, shape (H, W), float32 (0 where B + R = 0)."""
    b = image_bgr[..., 0].astype(np.float32)
    r = image_bgr[..., 2].astype(np.float32)
    s = b + r
    s[s == 0] = 1.0
    return (b - r) / s


def _nbr(nbr, usable, zenith_deg, sun_angle_deg, cfg: SegmentationConfig):
    return (nbr < cfg.threshold) & usable


def _nbr_adaptive(nbr, usable, zenith_deg, sun_angle_deg, cfg: SegmentationConfig):
    t = np.full(nbr.shape, cfg.threshold, np.float32)
    if sun_angle_deg is not None:
        t += (cfg.sun_threshold - cfg.threshold) * np.exp(-sun_angle_deg / cfg.sun_scale_deg)
    ramp = np.clip((zenith_deg - cfg.horizon_start_deg) / max(90.0 - cfg.horizon_start_deg, 1e-6), 0, 1)
    t += (cfg.horizon_threshold - cfg.threshold) * ramp
    return (nbr < t) & usable


def _otsu(nbr, usable, zenith_deg, sun_angle_deg, cfg: SegmentationConfig):
    import cv2

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
    usable = usable & (image_bgr.max(axis=2) >= cfg.min_brightness)
    cloud = get_segmenter(cfg.method)(nbr, usable, zenith_deg, sun_angle_deg, cfg)
    n = int(usable.sum())
    return cloud, (float(cloud.sum()) / n if n else 0.0)
