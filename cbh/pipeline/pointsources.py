"""Point sources in sky frames: a drone's light at night, a dark speck by day (``cbh validate --drone``).

Two steps, both on one camera's frames:

1. :func:`detect_points` finds compact sources in one frame: the frame's top-hat (black-hat
   for a dark speck) over an 11 px disk, which keeps anything a few pixels wide and removes
   clouds, the sky's gradient and airglow, local maxima above ``k_sigma`` times the residual's robust noise, and their
   intensity-weighted centroids over 7 x 7 px (sub-pixel, unbiased for a symmetric spot).
2. :func:`persistent_sources` marks what stays put: stars (which turn with the sky about the
   celestial pole at the sidereal rate, :func:`sky_turn`) and hot pixels (which never move) are
   found where they should be in most frames minutes apart; a drone hovering for a minute, an
   aircraft or a blinking light is not.
"""
from __future__ import annotations

import cv2
import numpy as np

__all__ = ["detect_points", "persistent_sources", "sky_turn", "SIDEREAL_RAD_S"]

SIDEREAL_RAD_S = 7.2921e-5  # the sky's rotation rate [rad/s]
BACKGROUND_PX = 11  # the background's structuring element [px]: a source is at most a few px wide (sigma <= 2 px)
WINDOW = 7  # centroid window [px] (+-3 px: +-3 sigma of a 1 px spot, +-1.5 sigma of a 2 px one)


def detect_points(gray: np.ndarray, valid: np.ndarray | None = None, polarity: str = "bright",
                  k_sigma: float = 6.0, min_amplitude: float = 6.0, max_points: int = 400) -> np.ndarray:
    """Compact sources in one frame.

    Parameters
    ----------
    gray : ndarray, shape (H, W), uint8
        The frame in grey.
    valid : ndarray, shape (H, W), bool, optional
        Where to look (the image circle, less any obstacle mask).
    polarity : {"bright", "dark"}
        A light at night, or a dark speck against a day sky.
    k_sigma, min_amplitude : float
        A source stands ``k_sigma`` robust standard deviations and ``min_amplitude`` grey
        levels above its background.
    max_points : int
        Keep the strongest this many.

    Returns
    -------
    ndarray, shape (N, 5), float64
        ``x, y`` centroid [px], ``flux`` (sum over the window above the background), ``peak``
        (the residual at the maximum), ``snr`` (peak over the residual's robust noise),
        strongest first.
    """
    if polarity not in ("bright", "dark"):
        raise ValueError(f"polarity: 'bright' or 'dark', got {polarity!r}")
    g = np.ascontiguousarray(gray, dtype=np.uint8)
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (BACKGROUND_PX, BACKGROUND_PX))
    res = cv2.morphologyEx(g, cv2.MORPH_TOPHAT if polarity == "bright" else cv2.MORPH_BLACKHAT, kernel).astype(np.float32)
    inside = np.ones(g.shape, bool) if valid is None else np.asarray(valid, bool)
    sample = res[inside][:: max(1, int(inside.sum()) // 40_000)]
    if sample.size == 0:
        return np.zeros((0, 5))
    sigma = 1.4826 * float(np.median(np.abs(sample - np.median(sample)))) + 0.5  # +0.5: a quantisation floor
    thr = max(k_sigma * sigma, min_amplitude)
    peaks = (res >= cv2.dilate(res, np.ones((5, 5), np.uint8))) & (res > thr) & inside
    ys, xs = np.nonzero(peaks)
    if ys.size > max_points * 4:  # a flood of maxima (a cloud's edge): the strongest only
        keep = np.argsort(res[ys, xs])[::-1][: max_points * 4]
        ys, xs = ys[keep], xs[keep]
    out = _centroids(res, xs, ys, max_points)
    return np.concatenate([out, out[:, 3:4] / sigma], axis=1)


def _centroids(res: np.ndarray, xs: np.ndarray, ys: np.ndarray, max_points: int) -> np.ndarray:
    """Centroids, the window moved onto the last centroid twice: a clipped light is a plateau
    whose first maximum may sit 2 px off its centre, and a window cut unevenly pulls toward it."""
    h, w = res.shape
    half = WINDOW // 2
    xs, ys = np.asarray(xs, int), np.asarray(ys, int)
    peak = res[ys, xs]
    for _ in range(3):
        ok = (xs >= half) & (ys >= half) & (xs < w - half) & (ys < h - half)
        xs, ys, peak = xs[ok], ys[ok], peak[ok]
        if xs.size == 0:
            return np.zeros((0, 4))
        cx, cy, flux = _window_centroid(res, xs, ys, half)
        nx, ny = np.round(cx).astype(int), np.round(cy).astype(int)
        if np.array_equal(nx, xs) and np.array_equal(ny, ys):
            break
        xs, ys = nx, ny
    out = np.stack([cx, cy, flux, peak], axis=1).astype(np.float64)
    return _strongest_apart(out, max_points)


def _window_centroid(res: np.ndarray, xs: np.ndarray, ys: np.ndarray, half: int):
    d = np.arange(-half, half + 1)
    yy = ys[:, None, None] + d[None, :, None]
    xx = xs[:, None, None] + d[None, None, :]
    patch = res[yy, xx]
    ring = np.concatenate([patch[:, 0, :], patch[:, -1, :], patch[:, 1:-1, 0], patch[:, 1:-1, -1]], axis=1)
    patch = np.clip(patch - np.median(ring, axis=1)[:, None, None], 0.0, None)  # the window's pedestal off
    flux = patch.sum(axis=(1, 2))
    cx = xs + (patch * d[None, None, :]).sum(axis=(1, 2)) / np.maximum(flux, 1e-9)
    cy = ys + (patch * d[None, :, None]).sum(axis=(1, 2)) / np.maximum(flux, 1e-9)
    return cx, cy, flux


def _strongest_apart(out: np.ndarray, max_points: int) -> np.ndarray:
    """Two maxima of one flat (clipped) spot: the stronger kept."""
    out = out[np.argsort(-out[:, 2])]
    if len(out) > 1:
        from scipy.spatial import cKDTree

        drop = np.zeros(len(out), bool)
        for i, j in sorted(cKDTree(out[:, :2]).query_pairs(float(WINDOW))):
            if not drop[i]:
                drop[j] = True
        out = out[~drop]
    return out[:max_points]


def sky_turn(camera, latitude_deg: float):
    """``move(xy (N, 2), dt_s) -> xy (N, 2)``: where a star seen at pixel ``xy`` is ``dt_s``
    seconds later in this camera (its ray turned about the celestial pole at the sidereal rate;
    NaN where it leaves the view)."""
    lat = np.radians(latitude_deg)
    k = np.array([0.0, np.cos(lat), np.sin(lat)])  # the celestial pole, ENU

    def move(xy: np.ndarray, dt_s: float) -> np.ndarray:
        v = camera.pixel_to_world(xy)
        a = -SIDEREAL_RAD_S * dt_s  # the sky turns westward about the pole
        w = v * np.cos(a) + np.cross(k, v) * np.sin(a) + np.outer(v @ k, k) * (1 - np.cos(a))
        return camera.direction_to_pixel(w)

    return move


def persistent_sources(times_s: np.ndarray, points: list[np.ndarray], move=None, window_s: float = 180.0,
                       compare: int = 8, radius_px: float = 1.5, share: float = 0.75) -> list[np.ndarray]:
    """Which sources stay put: stars and hot pixels (one bool array per frame).

    A source of frame ``i`` is persistent when, in up to ``compare`` frames between 10 % and 100 %
    of ``window_s`` away in time, a source lies within ``radius_px`` of where it would be had it
    stayed put: at the same pixel (a hot pixel) or where the sky's turn carries it (a star,
    ``move``: :func:`sky_turn`), in at least ``share`` of them. Frames with fewer than three
    such frames to compare with keep all their sources (nothing can be told). A drone hovering
    beside a star is not the star: the star's own place is predicted to the pixel, not allowed
    for with a radius that grows with time.

    Parameters
    ----------
    times_s : ndarray, shape (F,)
        Frame times [s].
    points : list of F ndarrays, shape (N_i, >=2)
        Each frame's sources (``x, y`` first).
    """
    from scipy.spatial import cKDTree

    t = np.asarray(times_s, np.float64)
    trees = [cKDTree(p[:, :2]) if len(p) else None for p in points]
    out = []
    for i, p in enumerate(points):
        if not len(p):
            out.append(np.zeros(0, bool))
            continue
        dt = t - t[i]
        cand = np.flatnonzero((np.abs(dt) >= 0.1 * window_s) & (np.abs(dt) <= window_s))
        if cand.size < 3:
            out.append(np.zeros(len(p), bool))
            continue
        pick = cand[np.unique(np.linspace(0, cand.size - 1, min(compare, cand.size)).round().astype(int))]
        hits = np.zeros(len(p), int)
        for j in pick:
            if trees[j] is None:
                continue
            d, _ = trees[j].query(p[:, :2], k=1, distance_upper_bound=radius_px)
            hit = np.isfinite(d)
            if move is not None:
                q = move(p[:, :2], float(dt[j]))
                ok = np.all(np.isfinite(q), axis=1)
                dq = np.full(len(p), np.inf)
                if ok.any():
                    dq[ok], _ = trees[j].query(q[ok], k=1, distance_upper_bound=radius_px)
                hit |= np.isfinite(dq)
            hits += hit
        out.append(hits >= share * pick.size)
    return out
