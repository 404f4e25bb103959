"""Clear-sky radiance, the sun, and horizon obstacles for the simulator (per-pixel maps).

Colours are BGR in digital numbers (DN, 0–255 before clipping); angles in degrees.
"""
from __future__ import annotations

from datetime import datetime

import cv2
import numpy as np

from cbh.geometry.sun import direction_enu, sun_position as _sun
from cbh.sim.scene import Obstacle, Scene

__all__ = ["sun_position", "sun_direction", "obstacle_profile", "skyline_raster", "OBSTACLE_BGR", "SUN_RADIUS_DEG",
           "SKYLINE_KINDS", "RASTER_BINS_PER_DEG", "RASTER_MAX_ELEVATION_DEG", "HAZE_BGR"]

SUN_RADIUS_DEG = 0.267  # apparent solar radius [deg]
SUN_BGR = np.array([250.0, 253.0, 255.0], np.float32)  # colour of the sun's glow [DN]
OBSTACLE_BGR = {"buildings": (72.0, 74.0, 80.0), "trees": (38.0, 62.0, 42.0)}
GROUND_BGR = (60.0, 68.0, 72.0)  # below the horizon (tilted cameras)
HAZE_BGR = np.array([236.0, 238.0, 240.0], np.float32)  # the pale band of a hazy horizon [DN]
SKYLINE_KINDS = ("skyline", "masts", "treeline", "walls")  # drawn on the (azimuth, elevation) raster
RASTER_BINS_PER_DEG = 20  # raster cells per degree of azimuth and of elevation
RASTER_MAX_ELEVATION_DEG = 60.0  # top of the raster [deg]


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


def _paint(ids, pal, a0, a1, e0, e1, colour, rel_lo=0.0, haze=0.0) -> None:
    """Fill the raster cells of azimuths [a0, a1) (relative to the column ``rel_lo``, degrees
    from the obstacle's start, wrapped) and elevations [e0, e1) with a new palette colour
    (``colour`` None: with sky, index 0) seen through ``haze`` (the fraction of its light replaced
    by the sky's: distant rows)."""
    n = RASTER_BINS_PER_DEG
    k = 0
    if colour is not None:
        pal.append(np.append(np.asarray(colour, np.float64).clip(0.0, 255.0), haze))
        k = len(pal) - 1
    c0, c1 = int(round((rel_lo + a0) * n)), int(round((rel_lo + a1) * n))
    r0, r1 = max(int(round(e0 * n)), 0), min(int(round(e1 * n)), ids.shape[0])
    if c1 <= c0:
        c1 = c0 + 1  # at least one cell: thin masts stay visible
    if r1 <= r0:
        return
    cols = np.arange(c0, c1) % ids.shape[1]
    ids[r0:r1, cols] = k


def _skyline(rng, ids, pal, start, span, top, walls: bool) -> None:
    """Rows of blocks of different heights (a hazier back row), with notches and rooftop
    antennas; ``walls``: sunlit façades brighter than the sky, with rows of dark windows."""
    for row, (lo, hi) in enumerate(((0.6, 1.0), (0.2, 0.75))) if not walls else enumerate(((0.2, 1.0),)):
        x = 0.0
        while x < span:
            w = min(rng.uniform(1.5, 8.0), span - x)
            h = rng.uniform(lo, hi) * top
            if walls:
                col = np.array([205.0, 226.0, 242.0]) * rng.uniform(0.97, 1.12)
            else:
                col = np.array([72.0, 76.0, 84.0]) * rng.uniform(0.6, 1.5)
            haze = rng.uniform(0.2, 0.6) if row == 0 and not walls else 0.0  # the back row: farther, hazier
            _paint(ids, pal, x, x + w, 0.0, h, col, start, haze)
            for _ in range(int(rng.integers(0, 4))):  # notches cut into the roof line
                nw, nd = rng.uniform(0.2, 1.0), rng.uniform(0.3, 2.0)
                nx = x + rng.uniform(0.0, max(w - nw, 0.0))
                _paint(ids, pal, nx, nx + nw, max(h - nd, 0.0), h, None, start)  # a notch is sky
            if walls and rng.random() < 0.7:  # windows
                wc = np.array([60.0, 62.0, 66.0]) * rng.uniform(0.7, 1.3)
                for wy in np.arange(0.4, h - 0.6, rng.uniform(1.0, 2.0)):
                    for wx in np.arange(x + 0.3, x + w - 0.5, rng.uniform(0.7, 1.5)):
                        _paint(ids, pal, wx, wx + 0.3, wy, wy + 0.4, wc, start)
            if rng.random() < 0.3:  # a rooftop antenna
                ax = x + rng.uniform(0.0, w)
                _paint(ids, pal, ax, ax + rng.uniform(0.05, 0.15), h, h + rng.uniform(1.0, 5.0), (50.0, 52.0, 55.0), start)
            x += w + (rng.uniform(0.5, 3.0) if rng.random() < 0.15 else 0.0)


def _masts(rng, ids, pal, start, span, top) -> None:
    """Thin poles and lattice masts (0.05–0.4° wide), some with a cross-arm or a lamp head."""
    for _ in range(int(rng.integers(1, 5))):
        x, w, h = rng.uniform(0.0, span), rng.uniform(0.05, 0.4), rng.uniform(0.4, 1.0) * top
        col = np.array([55.0, 58.0, 62.0]) * rng.uniform(0.6, 1.6)
        _paint(ids, pal, x, x + w, 0.0, h, col, start)
        if rng.random() < 0.5:  # cross-arm or lamp head
            aw = rng.uniform(0.6, 2.5)
            _paint(ids, pal, x - aw / 2, x + aw / 2, h - rng.uniform(0.15, 0.4), h, col, start)
        if rng.random() < 0.3:  # lattice: rungs between two legs
            _paint(ids, pal, x + 3 * w, x + 4 * w, 0.0, 0.9 * h, col, start)
            for y in np.arange(0.5, 0.9 * h, rng.uniform(0.8, 2.0)):
                _paint(ids, pal, x, x + 4 * w, y, y + 0.1, col, start)


def _treeline(rng, ids, pal, start, span, top) -> None:
    """Tree crowns with sky between their branches (holes 0.1–0.5° across) on thin trunks."""
    n = RASTER_BINS_PER_DEG
    x = 0.0
    while x < span:
        r = rng.uniform(1.0, 4.0)
        c = x + r * rng.uniform(0.3, 1.0)
        h = rng.uniform(0.45, 1.0) * top
        col = np.array([38.0, 62.0, 42.0]) * rng.uniform(0.7, 1.4)
        cb = min(h * rng.uniform(0.1, 0.35), h - 0.5)  # crown base (a trunk 2-5 m of a 10-20 m tree)
        tw = rng.uniform(0.15, 0.5)  # trunk width (0.3-0.9 m at 100 m) [deg]
        _paint(ids, pal, c - tw / 2, c + tw / 2, 0.0, max(cb, 0.0) + 0.3, 0.7 * col, start)
        cr = int(round((start + c - r) * n)), int(round((start + c + r) * n))
        rr = max(int(cb * n), 0), min(int(round(h * n)), ids.shape[0])
        if rr[1] > rr[0] and cr[1] > cr[0]:
            yy, xx = np.mgrid[rr[0]:rr[1], cr[0]:cr[1]].astype(np.float64) / n
            u, v = (xx - start - c) / r, (yy - (cb + h) / 2) / max((h - cb) / 2, 0.25)
            inside = u * u + v * v <= 1.0
            holes = rng.random(inside.shape) < rng.uniform(0.1, 0.35)  # sky between the branches …
            holes = cv2.dilate(holes.view(np.uint8), np.ones((int(rng.integers(2, 8)),) * 2, np.uint8)) > 0
            inside &= ~(holes & (u * u + v * v > rng.uniform(0.0, 0.3)))  # … the crown's core is denser
            pal.append(np.append(col, 0.0))
            block = ids[rr[0]:rr[1], np.arange(cr[0], cr[1]) % ids.shape[1]]
            block[inside] = len(pal) - 1
            ids[rr[0]:rr[1], np.arange(cr[0], cr[1]) % ids.shape[1]] = block
        x = c + r * rng.uniform(0.5, 1.2)


def skyline_raster(obstacles: tuple[Obstacle, ...]) -> tuple[np.ndarray, np.ndarray]:
    """The skyline kinds (:data:`SKYLINE_KINDS`) on a raster of azimuth × elevation.

    Returns
    -------
    ids : ndarray, shape (RASTER_MAX_ELEVATION_DEG · n, 360 · n), int32
        Palette index of each cell (row = elevation from the horizon up, column = azimuth
        clockwise from north, ``n`` = :data:`RASTER_BINS_PER_DEG`); 0 = sky.
    palette : ndarray, shape (K, 4), float32
        BGR colour [DN] of each index (index 0 unused) and the fraction of its light replaced
        by the sky's colour behind it (aerial perspective of a distant row), 0..1.
    """
    n = RASTER_BINS_PER_DEG
    ids = np.zeros((int(RASTER_MAX_ELEVATION_DEG * n), 360 * n), np.int32)
    pal: list[np.ndarray] = [np.zeros(4)]
    for ob in obstacles:
        if ob.kind not in SKYLINE_KINDS:
            continue
        rng = np.random.default_rng(np.random.SeedSequence([ob.seed, 0x5B1]))
        a0, a1 = ob.azimuth_deg
        span = (a1 - a0) % 360.0 or 360.0
        top = min(ob.max_elevation_deg, RASTER_MAX_ELEVATION_DEG - 6.0)
        if ob.kind in ("skyline", "walls"):
            _skyline(rng, ids, pal, a0 % 360.0, span, top, ob.kind == "walls")
        elif ob.kind == "masts":
            _masts(rng, ids, pal, a0 % 360.0, span, top)
        else:
            _treeline(rng, ids, pal, a0 % 360.0, span, top)
    return ids, np.array(pal, np.float32)
