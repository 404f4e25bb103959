"""Clear-sky radiance, the sun, and horizon obstacles for the simulator (per-pixel maps).

Colours are BGR in digital numbers (DN, 0–255 before clipping); angles in degrees.
"""
from __future__ import annotations

from datetime import datetime

import numpy as np

from cbh.geometry.sun import direction_enu, sun_position as _sun
from cbh.sim.scene import Obstacle, Scene

__all__ = ["sun_position", "sun_direction", "obstacle_profile", "OBSTACLE_BGR", "SUN_RADIUS_DEG"]

SUN_RADIUS_DEG = 0.267  # apparent solar radius [deg]
SUN_BGR = np.array([250.0, 253.0, 255.0], np.float32)  # colour of the sun's glow [DN]
OBSTACLE_BGR = {"buildings": (72.0, 74.0, 80.0), "trees": (38.0, 62.0, 42.0)}
GROUND_BGR = (60.0, 68.0, 72.0)  # below the horizon (tilted cameras)


def sun_position(scene: Scene, latitude_deg: float, longitude_deg: float, altitude_m: float,
                 time_utc: datetime) -> tuple[float, float]:
    """(zenith_deg, azimuth_deg) of the sun: the scene's fixed one, or :func:`cbh.geometry.sun.sun_position`."""
    if scene.sun.position == "fixed":
        return float(scene.sun.zenith_deg), float(scene.sun.azimuth_deg)
    sp = _sun(latitude_deg, longitude_deg, altitude_m, time_utc)
    return sp.zenith_deg, sp.azimuth_deg


sun_direction = direction_enu  # (zenith_deg, azimuth_deg) → unit ENU vector: the geometry's one function


def obstacle_profile(obstacles: tuple[Obstacle, ...], bins_per_deg: int = 10) -> tuple[np.ndarray, np.ndarray]:
    """Silhouette elevation [deg] by azimuth bin, and its kind index (−1 = none).

    Returns
    -------
    elevation_deg : ndarray, shape (360 · bins_per_deg,), float32
        Top of the silhouette; −90 where there is none.
    shade : ndarray, shape (360 · bins_per_deg, 3), float32
        BGR colour of the silhouette in that azimuth bin [DN].
    """
    nb = 360 * bins_per_deg
    az = (np.arange(nb) + 0.5) / bins_per_deg
    elev = np.full(nb, -90.0)
    shade = np.zeros((nb, 3))
    for ob in obstacles:
        rng = np.random.default_rng(np.random.SeedSequence([ob.seed, 0x0B57]))
        a0, a1 = ob.azimuth_deg
        span = (a1 - a0) % 360.0 or 360.0
        rel = (az - a0) % 360.0  # azimuth from the range start
        prof = np.full(nb, -90.0)
        col = np.array(OBSTACLE_BGR[ob.kind])
        cols = np.zeros((nb, 3))
        if ob.kind == "buildings":
            x = 0.0
            while x < span:
                w = rng.uniform(2.0, 9.0)
                if rng.random() < 0.25:  # gap
                    x += rng.uniform(1.0, 4.0)
                    continue
                h = rng.uniform(0.35, 1.0) * ob.max_elevation_deg
                sel = (rel >= x) & (rel < min(x + w, span))
                prof[sel] = np.maximum(prof[sel], h)
                cols[sel] = col * rng.uniform(0.8, 1.2)
                x += w
        else:  # trees: round crowns
            x = 0.0
            while x < span:
                r = rng.uniform(1.0, 3.5)
                c = x + r * rng.uniform(0.3, 1.0)
                h = rng.uniform(0.4, 1.0) * ob.max_elevation_deg
                d = np.abs(rel - c)
                inside = (d < r) & (rel < span)
                top = h - r * 0.6 + r * 0.6 * np.sqrt(np.clip(1 - (d / r) ** 2, 0, 1))
                upd = inside & (top > prof)
                prof[upd] = top[upd]
                cols[upd] = col * rng.uniform(0.8, 1.2)
                x = c + r * rng.uniform(0.4, 1.0)
        better = prof > elev
        elev[better] = prof[better]
        shade[better] = cols[better]
    return elev.astype(np.float32), shade.astype(np.float32)
