"""Find the sun in a fisheye image: the direction of its saturated disk and glow, or a reason why not.

Used by the pipeline's sun check (detected vs predicted sun, ``sun_residual_deg``) and by
``cbh calibrate`` (absolute orientation from the sun track).

Method (:func:`detect_sun`):

1. Saturated pixels inside the usable image circle, within ``search_deg`` of the predicted
   sun when a prediction is given (else anywhere): every channel within
   ``saturation_margin_dn`` of the image's own clip level (:func:`cbh.pipeline.clip.clip_level`,
   estimated on the whole image: 255 at full range, 235 for limited-range video, lower for a
   sensor that clips early). A clip found only on the smoothed plateau (a frame encoded twice,
   ``ClipLevel.smeared``) is tested on the luma, which JPEG keeps at full resolution: chroma
   subsampled twice bleeds the sky's colour unevenly into the disk's edge, and the disk's
   blocky edge is closed after the opening of step 2 (a twice-encoded limited-range day at
   960 px: the sun in 13 and 11 of 25 frames instead of 5 and 3; full range: 15 and 12).
2. Blooming streaks and diffraction spikes (lines a few pixels wide) are removed by a
   morphological opening with a disk a third of the blob's equivalent diameter.
3. The largest remaining blob is the sun; a second blob of at least ``ambiguous_ratio`` of its
   area means *ambiguous* (bright cloud edges, reflections); a blob smaller than
   ``min_area_px`` means *absent* (sun behind cloud or below the horizon).
4. The direction is the solid-angle-weighted mean of the blob's pixel rays (a sub-pixel
   centroid on the sphere, free of the fisheye's stretching). The blob must be round on the
   sphere: the ratio of the small to the large axis of its angular second moments at least
   ``min_roundness`` and its fill of the disk of its mean radius at least ``min_fill``;
   and its farthest pixel at most ``max_extent_ratio`` × the disk's edge; otherwise a cloud
   edge cuts it or saturated cloud joins it (*occluded*): its centroid would be biased.
5. The ring just outside the disk (1.15 to 1.6 times its radius) must be the sun's glow, even
   all around: ``(p90 − p10) / median`` of its brightness at most ``max_ring_spread``. A
   saturated cloud near a hidden sun has blue sky on one side and cloud on the other.
   And at most ``max_ring_saturated`` of the ring may be saturated: the blob holds every
   saturated pixel next to it, so a ring saturated nearly all around means the opening of
   step 2 carved a round piece out of a larger saturated region (a sunlit cloud hiding the
   sun: 2.6-5.4° off in the default simulated scene, its ring 59-70 % saturated), whose even
   white passes the spread test. A saturated cloud beside a visible sun covers about one side
   of the ring at most (28-40 % seen, the detection still within 0.4°).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from cbh.geometry.station import Camera
from cbh.pipeline.ccl import components_with_stats
from cbh.pipeline.clip import ClipConfig, ClipLevel, clip_level, saturated_pixels

__all__ = ["SunDetection", "SunDetectConfig", "detect_sun"]


@dataclass(frozen=True)
class SunDetectConfig:
    """Sun detection thresholds (pixels at the size of the image given)."""

    saturation_margin_dn: int = 5  # a pixel is saturated when every channel is within this of the image's clip level [DN]
    clip: ClipConfig = ClipConfig()  # how the clip level is estimated
    min_area_px: int = 12  # smallest sun blob [px]
    max_radius_deg: float = 12.0  # a saturated region wider than this is glare, not the sun [deg]
    ambiguous_ratio: float = 0.3  # a second blob this large (relative) makes the detection ambiguous [1]
    min_roundness: float = 0.85  # minor/major axis ratio of the blob's angular moments, at least [1]
    min_fill: float = 0.93  # blob area / area of the disk of its RMS radius · √2, at least [1]
    max_extent_ratio: float = 1.2  # farthest blob pixel / (√2 · RMS radius), at most (a disk: 1) [1]
    max_ring_spread: float = 0.2  # (p90 − p10) / p50 of the brightness just outside the disk, at most [1]
    max_ring_saturated: float = 0.5  # fraction of saturated pixels just outside the disk, at most [1]


@dataclass(frozen=True)
class SunDetection:
    """Result of :func:`detect_sun`.

    Attributes
    ----------
    ok : bool
        True when a sun was found; otherwise ``reason`` says why not.
    reason : str
        "ok", "absent", "ambiguous", "occluded", "glare" or "edge".
    ray_cam : ndarray, shape (3,), or None
        Unit ray to the sun in the camera frame.
    px : ndarray, shape (2,), or None
        Its pixel (x, y) at the size of the image given.
    area_px : int
        Pixels of the sun blob.
    radius_deg : float
        RMS angular radius of the blob [deg].
    """

    ok: bool
    reason: str
    ray_cam: np.ndarray | None = None
    px: np.ndarray | None = None
    area_px: int = 0
    radius_deg: float = math.nan


def detect_sun(image_bgr: np.ndarray, cam: Camera, expected_ray_cam: np.ndarray | None = None,
               search_deg: float = 20.0, usable: np.ndarray | None = None,
               cfg: SunDetectConfig = SunDetectConfig(), clip: ClipLevel | None = None) -> SunDetection:
    """The sun's direction in one image (see the module docstring).

    Parameters
    ----------
    image_bgr : ndarray, shape (H, W, 3), uint8
        The camera's image at the size of ``cam.model``.
    cam : Camera
    expected_ray_cam : ndarray, shape (3,), optional
        Predicted camera-frame sun ray; the search is limited to ``search_deg`` around it.
    search_deg : float
        Search radius around the prediction [deg].
    usable : ndarray, shape (H, W), bool, optional
        Pixels that may hold the sun (default: the image circle).
    cfg : SunDetectConfig
    clip : ClipLevel, optional
        The image's clip level, when the caller has it (default: :func:`~cbh.pipeline.clip.clip_level`
        of ``image_bgr`` with ``cfg.clip``).

    Returns
    -------
    SunDetection
    """
    m = cam.model
    h, w = image_bgr.shape[:2]
    window = _search_window(m, expected_ray_cam, search_deg, w, h)
    if window is None:
        return SunDetection(False, "absent")
    x0, y0, x1, y1 = window
    if clip is None:
        clip = clip_level(image_bgr, cfg.clip)
    if clip.smeared:  # twice encoded: chroma subsampled twice bleeds the sky's colour into the
        # disk's edge unevenly, the luma keeps full resolution
        luma = cv2.cvtColor(np.ascontiguousarray(image_bgr[y0:y1, x0:x1]), cv2.COLOR_BGR2GRAY)
        sat = cv2.inRange(luma, max(int(clip.level_dn) - cfg.saturation_margin_dn, 0), 255)
    else:
        sat = saturated_pixels(image_bgr[y0:y1, x0:x1], cfg.saturation_margin_dn, clip)
    if cv2.countNonZero(sat) < cfg.min_area_px:
        return SunDetection(False, "absent")
    if usable is None:
        usable = m.image_circle_mask()
    sat[~usable[y0:y1, x0:x1]] = 0
    n, lab, stats, _ = components_with_stats(sat)
    if n <= 1:
        return SunDetection(False, "absent")
    big = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    # open away streaks and spikes: a disk a third of the blob's equivalent diameter
    d_eq = 2.0 * math.sqrt(stats[big, cv2.CC_STAT_AREA] / math.pi)
    k = int(round(d_eq / 3.0)) | 1
    if k >= 3:
        disk = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k))
        sat = cv2.morphologyEx(sat, cv2.MORPH_OPEN, disk)
        if clip.smeared:  # a twice-encoded clip: its blocky, ragged edge closed (a cloud's cut is wider)
            sat = cv2.morphologyEx(sat, cv2.MORPH_CLOSE, disk)
        n, lab, stats, _ = components_with_stats(sat)
        if n <= 1:
            return SunDetection(False, "absent")
    areas = stats[1:, cv2.CC_STAT_AREA]
    order = np.argsort(areas)[::-1]
    best = 1 + int(order[0])
    area = int(areas[order[0]])
    if area < cfg.min_area_px:
        return SunDetection(False, "absent", area_px=area)
    if len(order) > 1 and areas[order[1]] >= cfg.ambiguous_ratio * area:
        return SunDetection(False, "ambiguous", area_px=area)
    bx, by, bw, bh = (int(stats[best, c]) for c in (cv2.CC_STAT_LEFT, cv2.CC_STAT_TOP, cv2.CC_STAT_WIDTH, cv2.CC_STAT_HEIGHT))
    # a blob touching the edge of the usable circle is cut by it
    ring = cv2.dilate((lab[by:by + bh, bx:bx + bw] == best).astype(np.uint8), np.ones((3, 3), np.uint8))
    ub = usable[y0 + by: y0 + by + bh, x0 + bx: x0 + bx + bw]
    cut_by_roi = (bx == 0 and x0 > 0) or (by == 0 and y0 > 0) or (bx + bw >= x1 - x0 and x1 < w) \
        or (by + bh >= y1 - y0 and y1 < h)
    if cut_by_roi or np.any(ring.astype(bool) & ~ub):
        return SunDetection(False, "edge", area_px=area)
    ys, xs = np.nonzero(lab[by:by + bh, bx:bx + bw] == best)
    px = np.stack([xs + bx + x0, ys + by + y0], axis=-1).astype(np.float64)
    c, u, v, q, wgt, ev = _spherical_moments(m, px)
    rms = math.sqrt(max(ev.sum(), 0.0))
    radius_deg = math.degrees(rms)
    if radius_deg * math.sqrt(2.0) > cfg.max_radius_deg:
        return SunDetection(False, "glare", area_px=area, radius_deg=radius_deg)
    roundness = math.sqrt(max(ev[0], 0.0) / ev[1]) if ev[1] > 0 else 1.0
    # a uniform disk of radius R has RMS radius R/√2
    disk_sr = math.pi * 2.0 * ev.sum()
    fill = float(wgt.sum() / disk_sr) if disk_sr > 0 else 1.0
    # a disk's farthest pixel is √2 × its RMS radius out; saturated cloud has lobes farther out
    rho_max = float(np.sqrt(np.max(np.sum(q ** 2, axis=1))))
    if roundness < cfg.min_roundness or fill < cfg.min_fill or rho_max > cfg.max_extent_ratio * math.sqrt(2.0) * rms:
        return SunDetection(False, "occluded", area_px=area, radius_deg=radius_deg)
    spread, saturated = _ring_stats(image_bgr, m, c, u, v, rho_max, usable, clip, cfg.saturation_margin_dn)
    if not (spread <= cfg.max_ring_spread and saturated <= cfg.max_ring_saturated):
        return SunDetection(False, "occluded", area_px=area, radius_deg=radius_deg)
    pc = m.ray_to_pixel(c[None, :])[0]
    return SunDetection(True, "ok", ray_cam=c, px=pc, area_px=area, radius_deg=radius_deg)


def _search_window(m, expected_ray_cam, search_deg: float, w: int, h: int) -> tuple[int, int, int, int] | None:
    """Pixel box (x0, y0, x1, y1) within ``search_deg`` of the predicted sun (the whole image
    without a prediction); None when the prediction falls off the image."""
    if expected_ray_cam is None:
        return 0, 0, w, h
    e = np.asarray(expected_ray_cam, np.float64)
    e = e / np.linalg.norm(e)
    pe = m.ray_to_pixel(e[None, :])[0]
    if not np.all(np.isfinite(pe)):
        return None
    # pixels per degree near the prediction, from a ray one degree away
    ortho = np.cross(e, [0.0, 0.0, 1.0] if abs(e[2]) < 0.9 else [1.0, 0.0, 0.0])
    ortho /= np.linalg.norm(ortho)
    p1 = m.ray_to_pixel((e * math.cos(math.radians(1)) + ortho * math.sin(math.radians(1)))[None, :])[0]
    ppd = float(np.linalg.norm(p1 - pe)) if np.all(np.isfinite(p1)) else 0.5 * max(h, w) / 90.0
    half = int(math.ceil(ppd * search_deg)) + 2
    x0, y0 = max(int(pe[0]) - half, 0), max(int(pe[1]) - half, 0)
    x1, y1 = min(int(pe[0]) + half + 1, w), min(int(pe[1]) + half + 1, h)
    if x1 <= x0 or y1 <= y0:
        return None
    return x0, y0, x1, y1


def _spherical_moments(m, px: np.ndarray):
    """A blob's solid-angle-weighted centroid ray ``c`` and second moments on the sphere.

    Returns ``c`` (3,), the tangent-plane axes ``u``, ``v`` (3,), each pixel's tangent-plane
    coordinates ``q`` (N, 2) [rad] and solid angle ``wgt`` (N,) [sr], and the eigenvalues
    ``ev`` (2,) of the weighted covariance of ``q`` [rad²], ascending.
    """
    rays = m.pixel_to_ray(px)
    # solid angle of each pixel: |∂ray/∂x × ∂ray/∂y| (central differences of the lens model)
    dx = m.pixel_to_ray(px + [0.5, 0.0]) - m.pixel_to_ray(px - [0.5, 0.0])
    dy = m.pixel_to_ray(px + [0.0, 0.5]) - m.pixel_to_ray(px - [0.0, 0.5])
    wgt = np.linalg.norm(np.cross(dx, dy), axis=1)
    c = (rays * wgt[:, None]).sum(axis=0)
    c /= np.linalg.norm(c)
    # angular moments in the tangent plane at the centroid
    u = np.cross(c, [0.0, 0.0, 1.0] if abs(c[2]) < 0.9 else [1.0, 0.0, 0.0])
    u /= np.linalg.norm(u)
    v = np.cross(c, u)
    q = np.stack([rays @ u, rays @ v], axis=-1)
    cov = (q * wgt[:, None]).T @ q / wgt.sum()
    return c, u, v, q, wgt, np.linalg.eigvalsh(cov)


def _ring_stats(image_bgr, m, c, u, v, rho_edge, usable, clip: ClipLevel, margin_dn: int) -> tuple[float, float]:
    """(p90 − p10) / p50 of the grey level in the ring 1.15–1.6 × ``rho_edge`` around ``c``, and
    the fraction of the ring's pixels that are saturated (inf, inf when the ring is not seen)."""
    h, w = image_bgr.shape[:2]
    pc = m.ray_to_pixel(c[None, :])[0]
    out = 1.6 * rho_edge
    pe = m.ray_to_pixel((c * math.cos(out) + u * math.sin(out))[None, :])[0]
    if not (np.all(np.isfinite(pc)) and np.all(np.isfinite(pe))):
        return math.inf
    rad = int(math.ceil(1.3 * float(np.linalg.norm(pe - pc)))) + 2
    x0, y0 = max(int(pc[0]) - rad, 0), max(int(pc[1]) - rad, 0)
    x1, y1 = min(int(pc[0]) + rad + 1, w), min(int(pc[1]) + rad + 1, h)
    ys, xs = np.nonzero(usable[y0:y1, x0:x1])
    if len(xs) < 30:
        return math.inf, math.inf
    rays = m.pixel_to_ray(np.stack([xs + x0, ys + y0], axis=-1).astype(np.float64))
    rho = np.hypot(rays @ u, rays @ v)
    sel = (rho >= 1.15 * rho_edge) & (rho <= out) & (rays @ c > 0)
    if sel.sum() < 30:
        return math.inf, math.inf
    px = image_bgr[y0:y1, x0:x1][ys[sel], xs[sel]]
    g = px.astype(np.float64).mean(axis=1)
    p10, p50, p90 = np.percentile(g, [10, 50, 90])
    sat = float(np.mean(saturated_pixels(px[:, None, :], margin_dn, clip) > 0))
    return float((p90 - p10) / max(p50, 1.0)), sat
