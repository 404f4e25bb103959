"""One recorded pair on the ground: camera 1's pixels labelled by layer, clear or unknown, with the
sun and the layers' motion (what the ground maps, the aviation products and ``cbh validate`` share).

Its own module so that :mod:`cbh.actions.export` and :mod:`cbh.actions.aviation`, which both use it,
do not import each other (export hands the aviation products to aviation).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from cbh.errors import RecordingError
from cbh.flags import INVALIDATING
from cbh.geometry import ground

__all__ = ["PairGround", "pair_ground"]


@dataclass
class PairGround:
    """One pair on the ground (see :func:`pair_ground`)."""

    camera: object  # camera 1 (cbh.geometry.station.Camera) at the size of the recorded mask
    labels: np.ndarray  # (H, W) int16: layer index / ground.CLEAR / ground.UNKNOWN
    heights: list  # layer heights above the ENU origin [m]
    covers: list  # layer covers, 0..1
    motions: list  # (east, north) per layer [m/s], NaN = unknown
    sun_dir: np.ndarray | None  # (3,) unit vector to the sun in ENU, None below the horizon
    sun_zenith_deg: float
    cloud_fraction: float  # camera 1's, 0..1
    time_utc: object  # datetime
    valid: bool  # False when the pair carries an invalidating flag
    #: per layer, its motion's error [m/s] measured over the valid pairs of the last ENSEMBLE_S
    #: (:func:`cbh.outputs.nowcast.motion_errors`, set as the pair joins it); None: the prior
    motion_errors: list | None = None
    #: per layer, how far from camera 1's zenith its map is read [deg]
    #: (:func:`cbh.outputs.nowcast.map_reach_deg`, measured at the pair's first read); None: not yet
    map_reach_deg: list | None = None


def _sun(station, t):
    """(unit vector to the sun in ENU, apparent zenith [deg]) from the one sun function."""
    from cbh.geometry.sun import sun_position

    sp = sun_position(station.latitude_deg, station.longitude_deg, station.altitude_m, t)
    return sp.direction_enu, sp.zenith_deg


_STATIC: dict = {}  # (camera and mask settings) → its static usable sky: the same for every pair of a session
_SCALED: dict = {}  # (camera, width) → the camera at that width, its ray maps cached on its model


def _key(cam) -> tuple:
    return (cam.name, cam.model.width, cam.model.height, repr(cam.model.to_dict()),
            np.asarray(cam.R_world_from_cam).tobytes(), str(cam.mask))


def _scaled(cam, width: int):
    """``cam`` at ``width`` px, one object per camera and width (a new one per pair recomputed its
    ray map, 0.3 s at 1920 px, for every sun angle map)."""
    key = (_key(cam), int(width))
    if key not in _SCALED:
        if len(_SCALED) >= 8:
            _SCALED.clear()
        _SCALED[key] = cam.scaled(width / cam.model.width)
    return _SCALED[key]


def _static_usable(cam, masks_cfg) -> np.ndarray:
    """Camera ``cam``'s static usable sky (:func:`cbh.pipeline.masks.static_sky_mask`), computed
    once per camera and settings (0.5 s at 1920 px: it was most of an export's time, per pair)."""
    from cbh.pipeline.masks import static_sky_mask

    key = (_key(cam), repr(masks_cfg))
    if key not in _STATIC:
        if len(_STATIC) >= 8:
            _STATIC.clear()
        m = static_sky_mask(cam, masks_cfg)
        m.setflags(write=False)  # shared by every pair: never changed in place
        _STATIC[key] = m
    return _STATIC[key]


def pair_ground(station, masks_cfg, result) -> PairGround:
    """Labels of camera 1's pixels (cloud per layer / clear / unknown) for one recorded result."""
    from cbh.pipeline.masks import angle_map_deg

    name = result.cameras[0]
    mask = result.cloud_masks.get(name)
    if mask is None:
        raise RecordingError(f"pair at {result.time_utc}: no cloud mask of {name!r} recorded")
    H, W = mask.shape
    cam = _scaled(station.camera(name), W)
    if (cam.model.height, cam.model.width) != (H, W):
        raise RecordingError(f"{name}: recorded mask {W}x{H} does not match the station's image shape")
    usable = _static_usable(cam, masks_cfg)
    sun_dir, zen = _sun(station, result.time_utc)
    if masks_cfg.sun and zen < 90.0:
        usable = usable & (angle_map_deg(cam, sun_dir) > masks_cfg.sun_radius_deg)
    hm = np.asarray(result.height_map, np.float32)
    if hm.shape != (H, W):
        hm = np.full((H, W), np.nan, np.float32)
    L = result.layers
    heights = [float(l.height_m) for l in L]
    covers = [float(l.cover) for l in L]
    motions = [(float(l.motion_east_ms), float(l.motion_north_ms)) for l in L]
    labels = ground.layer_labels(mask, usable, hm, heights, covers)
    valid = not (set(result.flags) & INVALIDATING)
    return PairGround(cam, labels, heights, covers, motions, sun_dir if zen < 90.0 else None, zen,
                      float(result.cloud_fraction.get(name, math.nan)), result.time_utc, valid)
