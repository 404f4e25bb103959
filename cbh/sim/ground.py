"""The simulated scene's own cloud shadow on the ground: the truth of the irradiance nowcast (issue 35).

The cameras see the layers from below; the ground sees them against the sun. For a ground point
``g`` and the sun direction ``s`` at time ``t``, each scene layer ``k`` (its height ``h_k``, its
texture advected by its wind to ``t``) is crossed by the sun ray at ``g + s·(h_k − g_z)/s_z``;
the layer is cloud there when its shape field passes the layer's coverage threshold (as the
renderer decides cloud, :class:`cbh.sim.render._LayerState`). The point is in shade when any layer
is cloud on its sun ray: the direct beam is blocked whichever layer does it, including an upper
layer that the cameras cannot see behind a lower one. ``thickness`` is the renderer's own 0–1
cloud thickness of the blocking layers (the largest), for a transmittance if one is wanted.
"""
from __future__ import annotations

import math
from datetime import datetime

import numpy as np

__all__ = ["ground_shade"]


#: The sun's disk sampled as a centre and two rings (radius ⅓ and ⅔... of its own, equal areas):
#: a direct beam is the mean over the disk, not a point (at 3.5 km the disk spans 30–50 m on the layer).
_DISK = ((0.0, 1), (0.5, 6), (0.85, 12))


def _disk_rays(s: np.ndarray) -> np.ndarray:
    """Unit vectors over the sun's disk around the sun direction ``s`` (``_DISK``), (M, 3)."""
    from cbh.sim.sky import SUN_RADIUS_DEG

    u = np.cross(s, [0.0, 0.0, 1.0] if abs(s[2]) < 0.9 else [1.0, 0.0, 0.0])
    u /= np.linalg.norm(u)
    v = np.cross(s, u)
    r0 = math.tan(math.radians(SUN_RADIUS_DEG))
    out = []
    for frac, n in _DISK:
        for j in range(n):
            a = 2.0 * math.pi * (j + 0.5 * (frac > 0.5)) / n
            d = s + r0 * frac * (math.cos(a) * u + math.sin(a) * v)
            out.append(d / np.linalg.norm(d))
    return np.asarray(out)


def direct_beam(sim, time_utc: datetime, points_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The share of the sun's direct beam that reaches ground points through the scene's clouds.

    Each layer lets through 1 − α of what reaches it, α the renderer's own opacity (0.5 on the
    cloud's edge, where its mask begins, rising to 1 inside over the soft edge; 1 overcast), so a
    thin wisp dims the beam as it dims the sky behind it in the cameras; the share is the mean over
    the sun's disk (``_DISK``). Returns (share (N,), 0–1, NaN with the sun below the horizon; the
    thickest layer's 0–1 thickness where the disk's centre ray meets cloud, else 0).
    """
    from cbh.sim.sky import sun_direction

    p = np.asarray(points_m, np.float64).reshape(-1, 3)
    zs, az = sim.sun(time_utc)
    s = sun_direction(zs, az)
    if s[2] <= 0.0:
        nan = np.full(len(p), math.nan)
        return nan, nan
    dt_s = (time_utc - sim.scene.time_utc).total_seconds()
    rays = _disk_rays(np.asarray(s, np.float64))
    beam = np.ones((len(rays), len(p)))
    thick = np.zeros(len(p))
    for ls in sim._layers:
        layer = ls.layer.advected(dt_s)
        if layer.coverage <= 0.0:
            continue
        above = (layer.height_m - p[:, 2]) > 0
        for i, d in enumerate(rays):
            k = (layer.height_m - p[:, 2]) / d[2]
            if ls.threshold == -math.inf:  # overcast: cloud everywhere
                alpha, th = np.ones(len(p)), np.ones(len(p))
            else:
                field, _ = ls.tex.evaluate(p[:, 0] + d[0] * k - layer.offset_m[0], p[:, 1] + d[1] * k - layer.offset_m[1])
                field = field.astype(np.float64)
                alpha = np.clip(0.5 + (field - ls.threshold) / ls.edge, 0.0, 1.0)
                th = np.where(field > ls.threshold, np.clip((field - ls.thick_lo) / ls.thick_span, 0.0, 1.0), 0.0)
            beam[i] *= np.where(above, 1.0 - alpha, 1.0)
            if i == 0:
                thick = np.where(above, np.maximum(thick, th), thick)
    return beam.mean(axis=0), thick


def ground_shade(sim, time_utc: datetime, points_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The scene's shadow at ground points (the simulator's truth): shade where less than half of
    the sun's direct beam gets through (:func:`direct_beam`), the line the renderer draws its cloud
    masks on (α = 0.5).

    Parameters
    ----------
    sim : cbh.sim.SkySimulator
    time_utc : datetime
        When (the layers advected to it, the sun at the station).
    points_m : ndarray, shape (N, 3)
        Ground points in the station's ENU frame [m].

    Returns
    -------
    shade : ndarray, shape (N,), float64
        1 the sun's direct beam mostly blocked by cloud, 0 sunlit, NaN the sun below the horizon.
    thickness : ndarray, shape (N,), float64
        The thickest blocking layer's thickness (0–1; 0 where sunlit).
    """
    beam, thick = direct_beam(sim, time_utc, points_m)
    shade = np.where(np.isfinite(beam), (beam < 0.5).astype(np.float64), math.nan)
    return shade, np.where(shade == 1.0, thick, np.where(np.isfinite(beam), 0.0, math.nan))
