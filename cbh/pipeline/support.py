"""Is a candidate layer real, or an alias of another? (photo-consistency of competing heights)

A plane sweep, or any matcher, can put part of one cloud layer at a second height: the
matcher's second peak in a repetitive or smooth texture, or box costs that straddle a layer
boundary, give a small, tight pile of heights that exists in no sky (e.g. 909 m beside a true
1282 m layer). The histogram cannot tell such a pile from a small real layer. The images can:
a real layer's pixels correlate clearly better at their own height than at any other layer's,
an alias's pixels correlate about as well at the layer they belong to.

:func:`alias_layers` tests every candidate layer against every layer with more points. For a
sample of the candidate's points (camera 1 working pixels), camera 2's image is resampled
through the horizontal plane of each height hypothesis (:class:`~.sweep.PlaneMaps`: the
exact plane mapping of the sweep) onto a ``window_px`` patch around the pixel, and scored by
zero-mean normalised cross-correlation against camera 1's patch. The candidate is an alias of
the bigger layer when at least ``alias_share`` of its pixels score there within ``margin`` of
their score at its own height, and at least ``min_zncc``: a clear match (pixels that match
nowhere, e.g. fog far below the sweep's floor, are chance matches at every height; those
layers are left to the flags that say so, ``below_range`` and ``cloud_unmatched``). Measured on randomized skies (``benchmarks/eval_random.py``,
640 px): the pixels of real, distinct layers do so at 2–20 %, those of an alias at 55 %.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

__all__ = ["AliasConfig", "hypothesis_zncc", "alias_layers", "unseen_layers", "flare_layers", "on_sun_lines",
           "without_layers"]


@dataclass(frozen=True)
class AliasConfig:
    window_px: int = 9  # ZNCC patch side at working size [px]
    margin: float = 0.02  # "as good": the other height's ZNCC at least own − this [1]
    alias_share: float = 0.4  # a layer is an alias when this share of its pixels is as good elsewhere [1]
    min_zncc: float = 0.6  # … and clearly matched there: chance matches (fog below the sweep's floor) match nowhere [1]
    max_samples: int = 300  # points sampled per layer (the share is then good to ±3 %) [1]


def hypothesis_zncc(gray1: np.ndarray, gray2: np.ndarray, planes, s_values, px1: np.ndarray,
                    window_px: int = 9) -> np.ndarray:
    """ZNCC of camera 1's patches at ``px1`` with camera 2 resampled through each plane.

    Parameters
    ----------
    gray1, gray2 : ndarray, shape (H1, W1) and (H2, W2)
        Working-size grey images.
    planes : PlaneMaps
        Camera-2 pixel of each camera-1 pixel as a cubic in s (:class:`~.sweep.PlaneMaps`).
    s_values : sequence of float
        The planes' s = 1/(h − o1z) [1/m].
    px1 : ndarray, shape (N, 2), int
        Camera-1 working pixels (x, y).

    Returns
    -------
    zncc : ndarray, shape (len(s_values), N), float32
        −1 … 1; NaN where a patch has no texture or leaves camera 2's image.
    """
    H1, W1 = gray1.shape
    k = window_px // 2
    off = np.arange(-k, k + 1)
    dy, dx = np.meshgrid(off, off, indexing="ij")
    xx = np.clip(px1[:, 0:1] + dx.ravel()[None], 0, W1 - 1)
    yy = np.clip(px1[:, 1:2] + dy.ravel()[None], 0, H1 - 1)
    a = gray1[yy, xx].astype(np.float32)
    a -= a.mean(axis=1, keepdims=True)
    na = np.sqrt((a * a).sum(axis=1))
    yi, xi = yy.ravel(), xx.ravel()
    H2, W2 = gray2.shape
    out = np.full((len(s_values), len(px1)), np.nan, np.float32)
    g2 = gray2.astype(np.float32)
    for i, s in enumerate(s_values):
        p2 = planes.points(np.full(len(yi), s, np.float32), yi, xi).astype(np.float32).reshape(yy.shape + (2,))
        inside = ((p2[..., 0] >= 0) & (p2[..., 0] <= W2 - 1) & (p2[..., 1] >= 0) & (p2[..., 1] <= H2 - 1)).all(axis=1)
        b = cv2.remap(g2, np.ascontiguousarray(p2[..., 0]), np.ascontiguousarray(p2[..., 1]), cv2.INTER_LINEAR)
        b -= b.mean(axis=1, keepdims=True)
        nb = np.sqrt((b * b).sum(axis=1))
        z = (a * b).sum(axis=1) / np.maximum(na * nb, 1e-6)
        ok = inside & (na > 1e-3) & (nb > 1e-3)
        out[i, ok] = z[ok]
    return out


def alias_layers(gray1, gray2, planes, o1z_m: float, heights_m, points_px1: np.ndarray, labels: np.ndarray,
                 cfg: AliasConfig = AliasConfig()) -> dict[int, int]:
    """Candidate layers that are aliases of a bigger one: {alias index: the layer it belongs to}.

    Parameters
    ----------
    gray1, gray2 : ndarray
        Working-size grey images (camera 2 as matched: compensated for its clock, if it was).
    planes : PlaneMaps
    o1z_m : float
        Camera 1's height in the ENU frame [m].
    heights_m : sequence of float
        Each candidate layer's height [m].
    points_px1 : ndarray, shape (N, 2)
        Camera-1 working pixels of the points.
    labels : ndarray, shape (N,), int
        Each point's candidate layer (−1 = none).
    """
    n = len(heights_m)
    if n < 2:
        return {}
    counts = np.array([np.count_nonzero(labels == k) for k in range(n)])
    s_values = [1.0 / max(h - o1z_m, 1.0) for h in heights_m]
    rng = np.random.default_rng(0)
    out: dict[int, int] = {}
    for k in np.argsort(counts):  # smallest first
        idx = np.flatnonzero(labels == k)
        bigger = [j for j in range(n) if counts[j] > counts[k] and j not in out]
        if idx.size == 0 or not bigger:
            continue
        if idx.size > cfg.max_samples:
            idx = rng.choice(idx, cfg.max_samples, replace=False)
        px = np.rint(points_px1[idx]).astype(np.int64)
        z = hypothesis_zncc(gray1, gray2, planes, [s_values[k]] + [s_values[j] for j in bigger], px, cfg.window_px)
        own, ok = z[0], np.isfinite(z[0])
        if not ok.any():
            continue
        for row, j in zip(z[1:], bigger):
            other = np.nan_to_num(row[ok], nan=-2.0)
            share = float(np.mean((other >= own[ok] - cfg.margin) & (other >= cfg.min_zncc)))
            if share >= cfg.alias_share:
                out[int(k)] = int(j)
                break
    return out


#: A layer is seen by camera 2 when at least this share of its points' camera-2 pixels lie on
#: camera 2's cloud (within ``UNSEEN_TOLERANCE_PX``). Below, it is camera 1's alone: the ring of
#: aureole round a sun that camera 1's exposure saturates far wider than camera 2's, read as
#: cloud and matched (randomized clear sky 9733: 12 % of a 1629 m layer's points at 480 px,
#: 0.3 and 2 % of two layers at 960 px; camera 2 saw 2 % of its sky as cloud, none of it there).
#: The layers of randomized broken and overcast skies sit at 99.7–100 %.
UNSEEN_SHARE = 0.25
UNSEEN_TOLERANCE_PX = 3  # camera 2's cloud grown by this [px, working size]: its mask's edges, the match's error


def unseen_layers(cloud2: np.ndarray, px2: np.ndarray, label: np.ndarray, n_layers: int) -> list[int]:
    """Indices of the layers camera 2 does not see as cloud (:data:`UNSEEN_SHARE`).

    ``cloud2``: camera 2's cloud mask (working size, the frame the matches were made in);
    ``px2``: the points' camera-2 pixels (N, 2), working size; ``label``: each point's layer."""
    if not n_layers or not len(px2):
        return []
    k = 2 * UNSEEN_TOLERANCE_PX + 1
    near = cv2.dilate(cloud2.view(np.uint8), cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k)))
    h, w = near.shape
    ok = np.isfinite(px2).all(axis=1)
    p = np.where(ok[:, None], px2, 0.0)
    xi = np.clip(np.rint(p[:, 0]), 0, w - 1).astype(np.int64)
    yi = np.clip(np.rint(p[:, 1]), 0, h - 1).astype(np.int64)
    on = near[yi, xi] > 0
    out = []
    for j in range(n_layers):
        mine = (label == j) & ok  # (a point without a camera-2 position is not judged)
        if mine.any() and float(on[mine].mean()) < UNSEEN_SHARE:
            out.append(j)
    return out


#: A layer of small cover whose points lie, in both cameras, within this angle of the line through
#: the sun's image and the optical centre is a lens-flare ghost (:func:`flare_layers`).
FLARE_BAND_DEG = 12.0
FLARE_SHARE = 0.8  # … this share of its points or more
FLARE_MAX_COVER = 0.05  # … and it covers less than this of the sky


def on_sun_lines(px: tuple[np.ndarray, np.ndarray], lines: tuple, band_px: float) -> np.ndarray | None:
    """Which matches lie within ``band_px`` of the line through the sun's image and the optical
    centre in both cameras (``px``: each camera's pixels (N, 2); ``lines``: per camera (sun pixel,
    optical centre); working size), where a lens's ghosts of the sun lie (:func:`flare_layers`);
    None when the sun is within ``band_px`` of a camera's centre (no line to speak of)."""
    inside = np.ones(len(px[0]), bool)
    for p, (sun, centre) in zip(px, lines):
        d = np.asarray(sun, np.float64) - np.asarray(centre, np.float64)
        norm = float(np.hypot(*d))
        if not np.isfinite(norm) or norm < band_px:
            return None
        n = np.array([-d[1], d[0]]) / norm
        with np.errstate(invalid="ignore"):
            inside &= np.abs((np.asarray(p, np.float64) - np.asarray(centre, np.float64)) @ n) <= band_px
    return inside


def flare_layers(px: tuple[np.ndarray, np.ndarray], lines: tuple, label: np.ndarray, covers: list[float],
                 band_px: float) -> list[int]:
    """Indices of the layers that are lens-flare ghosts, not cloud.

    A lens is rotationally symmetric about its axis, so the ghosts of the sun (reflections between
    its elements) lie on the line through the sun's image and the optical centre, and a pair of
    cameras of one design puts them at nearly one direction in each: zero parallax but for the two
    lenses' differences, which the sweep turns into any height. A probe of 30 randomized clear
    skies with 2–5 ghosts (8–70 px discs at 960 px, 15–70 DN, the same in both cameras) gave layers
    at 1896 and 12 405 m whose points all lay within 12° of those lines in both cameras, against at
    most 28 % for the 45 layers of 40 randomized skies without ghosts. A real cloud on the sun's
    vertical in camera 1 is on it in camera 2 only as far as the baseline allows, and a layer of
    ``FLARE_MAX_COVER`` or more does not fit the band.

    ``px``: the points' pixels in each camera (N, 2), working size; ``lines``: per camera (sun
    pixel, optical centre), working size; ``label``: each point's layer; ``covers``: each layer's
    cover; ``band_px``: ``FLARE_BAND_DEG`` in pixels."""
    inside = on_sun_lines(px, lines, band_px)
    if inside is None:
        return []
    out = []
    for j, cover in enumerate(covers):
        mine = label == j
        if cover < FLARE_MAX_COVER and mine.any() and float(inside[mine].mean()) >= FLARE_SHARE:
            out.append(j)
    return out


def without_layers(lay, dropped: dict[int, int | None]):
    """``lay`` (a :class:`~.layers.LayerSet`) less the layers ``dropped`` (index → the layer its
    cover goes to): an alias's cover goes to the layer it belongs to (its cloud is that layer's
    cloud), an unseen layer's (``None``) to no layer; their points to no layer."""
    from dataclasses import replace

    if not dropped:
        return lay
    extra = {}
    for k, j in dropped.items():
        if j is not None:
            extra[j] = extra.get(j, 0.0) + lay.layers[k].cover
    keep = [k for k in range(len(lay.layers)) if k not in dropped]
    new_index = {k: i for i, k in enumerate(keep)}
    label = np.full_like(lay.label, -1)
    for k, i in new_index.items():
        label[lay.label == k] = i
    layers = [replace(lay.layers[k], cover=lay.layers[k].cover + extra.get(k, 0.0)) for k in keep]
    return replace(lay, layers=layers, label=label)
