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


def ground_shade(sim, time_utc: datetime, points_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The scene's shadow at ground points (the simulator's truth).

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
        1 the sun's direct beam blocked by cloud, 0 sunlit, NaN the sun below the horizon.
    thickness : ndarray, shape (N,), float64
        The thickest blocking layer's thickness (0–1; 0 where sunlit).
    """
    from cbh.sim.sky import sun_direction

    p = np.asarray(points_m, np.float64).reshape(-1, 3)
    zs, az = sim.sun(time_utc)
    s = sun_direction(zs, az)
    if s[2] <= 0.0:
        nan = np.full(len(p), math.nan)
        return nan, nan
    dt_s = (time_utc - sim.scene.time_utc).total_seconds()
    shade = np.zeros(len(p), bool)
    thick = np.zeros(len(p))
    for ls in sim._layers:
        layer = ls.layer.advected(dt_s)
        if layer.coverage <= 0.0:
            continue
        k = (layer.height_m - p[:, 2]) / s[2]
        above = k > 0
        if ls.threshold == -math.inf:  # overcast: cloud everywhere
            cloud, th = above, np.ones(len(p))
        else:
            e = p[:, 0] + s[0] * k - layer.offset_m[0]
            n = p[:, 1] + s[1] * k - layer.offset_m[1]
            field, _ = ls.tex.evaluate(e, n)
            field = field.astype(np.float64)
            cloud = above & (field > ls.threshold)
            th = np.clip((field - ls.thick_lo) / ls.thick_span, 0.0, 1.0)
        shade |= cloud
        thick = np.where(cloud, np.maximum(thick, th), thick)
    return shade.astype(np.float64), thick
