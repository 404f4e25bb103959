"""Stage 3 (dense): plane-sweep stereo on the raw fisheye images (matching method ``sweep``).

Why: a dense optical flow (DIS) regularises across the occlusion boundary between two cloud
layers and returns heights that exist in neither. A plane sweep instead tests *hypotheses of
the scene*: horizontal planes at height h. For each plane, image 2 is resampled onto camera
1's pixel grid through the plane (p1 → ray of camera 1 → the point at height h → camera 2's
pixel), and photo-consistency is scored per pixel. Every pixel takes the plane that explains
it best, so a pixel of the 1200 m layer beside a pixel of the 3500 m layer gets 1200 m or
3500 m, never a blend.

Plane mapping (exact geometry, no rectification). For a camera-1 ray d (ENU, unit) and a
plane at height h, the point is o1 + d·(h − o1z)/d_z, and its direction from camera 2 is
proportional to ``d − s·d_z·B`` with ``s = 1/(h − o1z)`` [1/m] and ``B = o2 − o1``. The
camera-2 pixel is therefore a smooth function of the single number s. It is evaluated
exactly (``Camera.direction_to_pixel``) for s = 0 (infinity), s_a and 2·s_a once per camera
pair, and in between by the quadratic through those three maps
(:class:`PlaneMaps`): ``p2(s) = m0 + a·s + b·s²`` — 2 FMAs per pixel per plane instead of a
fisheye projection. ``s_a·|B| = 0.1 rad``: interpolation covers parallaxes up to 0.2 rad
(h ≥ 5·|B|), with a cubic remainder below 0.05 px; beyond, it extrapolates.

Planes are spaced uniformly in s, so neighbouring planes shift image 2 by at most
``step_px`` pixels anywhere in the image (``|a|`` is the parallax in pixels per unit s).

Score: zero-mean normalised cross-correlation (ZNCC) over a ``window_px`` box, computed with
box filters (O(1) per pixel per plane). ZNCC is invariant to gain and offset, so the
view-dependent brightness of a cloud seen from two places does not bias it.

Two passes:

1. *Coarse*: at 1/``coarse_factor`` resolution, all planes from ``max_height_m`` down to
   ``min_height_m`` at one coarse pixel per step. Each cloud pixel votes for its best plane
   (if ZNCC ≥ ``min_zncc``); peaks of the vote histogram over s are the layer hypotheses,
   each with the extent of s around it where its votes stay above ``extent_ratio`` × peak.
   High layers (a few pixels of parallax) are not resolved at coarse size, so:
2. *Fine*: at working resolution, at ``step_px`` per plane, every plane of the *far range*
   (parallax ≤ ``far_px``, from infinity on) and the union of the coarse extents (± 1.5 coarse
   steps). Each cloud pixel takes its best plane; the height is refined
   between planes by a parabola through the three scores around the best (in s), and the
   match is kept if its ZNCC ≥ ``min_zncc`` and the window has texture (grey-level standard
   deviation ≥ ``min_texture``).

Output: one correspondence per accepted cloud pixel of camera 1 (``dense=True``), px2 = the
plane mapping at the refined s. Such a correspondence lies on the epipolar geometry by
construction, so its ray miss is ≈ 0 (not a measurement of matching quality; the sparse
``lk`` matches carry that).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["PlaneMaps", "plane_maps", "sweep_matches", "zncc_planes"]

_OUTSIDE = -1.0e5


@dataclass
class PlaneMaps:
    """Camera-2 pixel of each camera-1 pixel as a quadratic in s = 1/(h − o1z).

    Attributes
    ----------
    m0, a, b : ndarray, shape (H1, W1, 2), float32
        ``p2(s) = m0 + a·s + b·s²`` [px, px·m, px·m²]; m0 = _OUTSIDE, a = b = 0 where
        camera 2 cannot see the pixel's ray at s = 0, s_a or 2·s_a.
    s_a : float
        Anchor [1/m].
    scale_px : float
        Largest ``|a|`` over valid pixels: parallax in pixels per unit s [px·m].
    """

    m0: np.ndarray
    a: np.ndarray
    b: np.ndarray
    s_a: float
    scale_px: float

    def at(self, s: float, sl=np.s_[:, :]) -> tuple[np.ndarray, np.ndarray]:
        """Remap tables (map_x, map_y) (h, w) float32 for one plane, on the region ``sl``."""
        import cv2

        if getattr(self, "_planes_key", None) != sl:  # contiguous (h, w) planes of the region, cached
            self._planes = [[np.ascontiguousarray(m[sl + (k,)]) for m in (self.m0, self.a, self.b)] for k in (0, 1)]
            self._planes_key = sl
        out = []
        for m0, a, b in self._planes:
            out.append(cv2.scaleAdd(b, float(s * s), cv2.scaleAdd(a, float(s), m0)))
        return out[0], out[1]

    def points(self, s: np.ndarray, yi: np.ndarray, xi: np.ndarray) -> np.ndarray:
        """Camera-2 pixels (N, 2) float64 at per-pixel s (N,) for camera-1 pixels (yi, xi)."""
        s = s[:, None].astype(np.float64)
        return self.m0[yi, xi].astype(np.float64) + self.a[yi, xi] * s + self.b[yi, xi] * s * s

    def downsampled(self, factor: int) -> "PlaneMaps":
        """The same mapping between images downsampled by an integer ``factor`` (INTER_AREA)."""
        import cv2

        def rs(m):
            h, w = m.shape[:2]
            return cv2.resize(m, (w // factor, h // factor), interpolation=cv2.INTER_AREA)

        m0 = rs(self.m0)
        bad = m0[..., 0] < -1.0e3
        m0 = (m0 + 0.5) / factor - 0.5
        a, b = rs(self.a) / factor, rs(self.b) / factor
        m0[bad], a[bad], b[bad] = _OUTSIDE, 0.0, 0.0
        return PlaneMaps(m0.astype(np.float32), a.astype(np.float32), b.astype(np.float32), self.s_a, self.scale_px / factor)


def plane_maps(cam1, cam2, rays1_world: np.ndarray) -> PlaneMaps:
    """Build :class:`PlaneMaps` for two cameras (working size) and camera 1's ENU rays (H, W, 3)."""
    h, w = rays1_world.shape[:2]
    d = rays1_world.reshape(-1, 3).astype(np.float64)
    base = np.asarray(cam2.position_m, np.float64) - np.asarray(cam1.position_m, np.float64)
    blen = float(np.linalg.norm(base))
    s_a = 0.1 / max(blen, 1e-6)
    maps, ok = [], d[:, 2] > 1e-3
    for s in (0.0, s_a, 2.0 * s_a):
        p = cam2.direction_to_pixel(d - s * d[:, 2:3] * base[None, :])
        good = np.isfinite(p).all(axis=1)
        good[good] = cam2.model.contains(p[good])
        ok &= good
        maps.append(np.nan_to_num(p, nan=0.0))
    p0, p1, p2 = maps
    a = (4.0 * p1 - p2 - 3.0 * p0) / (2.0 * s_a)
    b = (p2 - 2.0 * p1 + p0) / (2.0 * s_a * s_a)
    p0[~ok], a[~ok], b[~ok] = _OUTSIDE, 0.0, 0.0
    scale = float(np.linalg.norm(a[ok], axis=1).max()) if ok.any() else 1.0
    f32 = lambda m: m.reshape(h, w, 2).astype(np.float32)  # noqa: E731
    return PlaneMaps(f32(p0), f32(a), f32(b), s_a, scale)


def _box(img, k):
    import cv2

    return cv2.boxFilter(img, -1, (k, k), normalize=True, borderType=cv2.BORDER_REFLECT)


def zncc_planes(gray1: np.ndarray, gray2: np.ndarray, maps: PlaneMaps, s_values: np.ndarray, window_px: int,
                sl=np.s_[:, :]) -> tuple[np.ndarray, np.ndarray]:
    """ZNCC of image 1 against image 2 mapped through each plane, on the region ``sl``.

    Parameters
    ----------
    gray1 : ndarray, shape (H1, W1), float32
    gray2 : ndarray, shape (H2, W2), float32
    maps : PlaneMaps (at the same size as the images)
    s_values : ndarray, shape (P,), float [1/m]
    window_px : int, odd

    Returns
    -------
    scores : ndarray, shape (P, h, w), float32
        ZNCC in [-1, 1] (0 where either window is flat).
    std1 : ndarray, shape (h, w), float32
        Grey-level standard deviation of image 1 in each window.
    """
    import cv2

    i1 = np.ascontiguousarray(gray1[sl])
    k = int(window_px)
    mu1 = _box(i1, k)
    var1 = np.maximum(_box(cv2.multiply(i1, i1), k) - mu1 * mu1, 0.0)
    out = np.empty((len(s_values),) + i1.shape, np.float32)
    for j, s in enumerate(s_values):
        mx, my = maps.at(float(s), sl)
        w = cv2.remap(gray2, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        mu2 = _box(w, k)
        var2 = np.maximum(_box(cv2.multiply(w, w), k) - mu2 * mu2, 0.0)
        cov = _box(cv2.multiply(i1, w), k) - mu1 * mu2
        den = cv2.sqrt(var1 * var2 + 1e-3)
        out[j] = cov / den
    return out, cv2.sqrt(var1)


def _bbox(mask: np.ndarray, pad: int):
    ys, xs = np.nonzero(mask.any(axis=1))[0], np.nonzero(mask.any(axis=0))[0]
    h, w = mask.shape
    return np.s_[max(ys[0] - pad, 0): min(ys[-1] + pad + 1, h), max(xs[0] - pad, 0): min(xs[-1] + pad + 1, w)]


def _best(scores) -> tuple[np.ndarray, np.ndarray]:
    """Index of the best plane (h, w) and its score (h, w) of a score stack (P, h, w)."""
    j, c0, _, _ = _best3(scores)
    return j, c0


def _best3(scores):
    """Best plane index j, its score and the scores of planes j−1 and j+1 (streaming, one pass)."""
    n = len(scores)
    best = scores[0].copy()
    j = np.zeros(best.shape, np.int32)
    left = best.copy()
    right = scores[min(1, n - 1)].copy()
    for q in range(1, n):
        cur = scores[q]
        np.copyto(right, cur, where=(j == q - 1))
        gt = cur > best
        np.copyto(left, scores[q - 1], where=gt)
        np.copyto(best, cur, where=gt)
        j[gt] = q
    return j, best, left, right


def _refine(scores, j: np.ndarray, c0: np.ndarray, s_values: np.ndarray, ds: float, cm1=None, cp1=None) -> np.ndarray:
    """s of the peak of the parabola through the scores of planes j−1, j, j+1 (where adjacent)."""
    n = len(s_values)
    if cm1 is None:
        _, _, cm1, cp1 = _best3(scores)
    gap = np.diff(s_values, prepend=-np.inf, append=np.inf)
    adj = (j > 0) & (j < n - 1) & (gap[j] < 1.01 * ds) & (gap[np.minimum(j + 1, n)] < 1.01 * ds)
    den = cm1 - 2.0 * c0 + cp1
    with np.errstate(invalid="ignore", divide="ignore"):
        delta = np.where(adj & (den < 0), 0.5 * (cm1 - cp1) / den, 0.0)
    return s_values[j] + np.clip(delta, -0.5, 0.5) * ds


def _peaks(votes: np.ndarray, min_votes: float, extent_ratio: float, valley_ratio: float,
           valleys: bool = False) -> list[tuple[int, int]]:
    """Index ranges [lo, hi] of the peaks of a vote histogram (merging peaks without a deep valley).

    ``valleys``: the ranges tile the histogram, split at the lowest point between peaks.
    """
    v = votes.astype(np.float64)
    left = np.concatenate([[-np.inf], v[:-1]])
    right = np.concatenate([v[1:], [-np.inf]])
    peaks = [int(i) for i in np.flatnonzero((v > left) & (v >= right) & (v >= min_votes))]
    merged = True
    while merged and len(peaks) > 1:  # neighbours without a valley below valley_ratio × lower peak
        merged = False
        for i in range(len(peaks) - 1):
            a, b = peaks[i], peaks[i + 1]
            if v[a: b + 1].min() > valley_ratio * min(v[a], v[b]):
                peaks.pop(i + 1 if v[a] >= v[b] else i)
                merged = True
                break
    out = []
    if valleys:
        cuts = [a + int(np.argmin(v[a: b + 1])) for a, b in zip(peaks[:-1], peaks[1:])]
        return [(lo, hi) for lo, hi in zip([0] + [c + 1 for c in cuts], cuts + [len(v) - 1])] if peaks else []
    for p in peaks:
        lo = p
        while lo > 0 and v[lo - 1] >= extent_ratio * v[p] and v[lo - 1] <= v[lo]:
            lo -= 1
        hi = p
        while hi < len(v) - 1 and v[hi + 1] >= extent_ratio * v[p] and v[hi + 1] <= v[hi]:
            hi += 1
        out.append((lo, hi))
    return out


def sweep_matches(gray1: np.ndarray, gray2: np.ndarray, cloud1: np.ndarray, maps: PlaneMaps, o1z: float, cfg):
    """Dense plane-sweep correspondences (see module doc).

    Parameters
    ----------
    gray1, gray2 : ndarray, (H1, W1) and (H2, W2), uint8
        Working-size grey images.
    cloud1 : ndarray, (H1, W1), bool
        Camera 1's cloud mask: the pixels to match.
    maps : PlaneMaps
        Working-size plane mapping camera 1 → camera 2.
    o1z : float
        Height of camera 1 above the ENU origin [m].
    cfg : SweepConfig

    Returns
    -------
    px1 : ndarray, shape (N, 2), float64 — camera-1 pixels (integer coordinates)
    px2 : ndarray, shape (N, 2), float64 — camera-2 pixels
    info : dict — ``planes`` (fine s values), ``layers_m`` (coarse layer hypotheses [m])
    """
    import cv2

    empty = np.zeros((0, 2)), np.zeros((0, 2)), {"planes": np.zeros(0), "layers_m": []}
    if not cloud1.any() or maps.scale_px <= 0:
        return empty
    g1 = gray1.astype(np.float32)
    g2 = gray2.astype(np.float32)
    s_min = 1.0 / max(cfg.max_height_m - o1z, 1.0)
    s_max = 1.0 / max(cfg.min_height_m - o1z, 1.0)

    # 1. coarse pass: layer hypotheses from the votes of all cloud pixels
    f = int(cfg.coarse_factor)
    if f > 1:
        cm = maps.downsampled(f)
        h, w = g1.shape
        c1 = cv2.resize(g1, (w // f, h // f), interpolation=cv2.INTER_AREA)
        h2, w2 = g2.shape
        c2 = cv2.resize(g2, (w2 // f, h2 // f), interpolation=cv2.INTER_AREA)
        ccloud = cv2.resize(cloud1.astype(np.float32), (w // f, h // f), interpolation=cv2.INTER_AREA) >= 0.5
    else:
        cm, c1, c2, ccloud = maps, g1, g2, cloud1
    if not ccloud.any():
        return empty
    ds_c = cfg.coarse_step_px / cm.scale_px
    s_coarse = np.arange(s_min, s_max + ds_c, ds_c)
    slc = _bbox(ccloud, cfg.coarse_window_px)
    sc, _ = zncc_planes(c1, c2, cm, s_coarse, cfg.coarse_window_px, slc)
    best, cbest = _best(sc)
    good = ccloud[slc] & (cbest >= cfg.min_zncc)
    votes = np.bincount(best[good], minlength=len(s_coarse)).astype(np.float64)
    n_cloud = float(ccloud.sum())
    ranges = _peaks(votes, cfg.min_vote_fraction * n_cloud, cfg.extent_ratio, cfg.valley_ratio)
    layers_m = [float(o1z + 1.0 / s_coarse[(lo + hi) // 2]) for lo, hi in ranges]

    # 2. fine pass at working resolution over the far range and the union of the peaks' extents
    ds = cfg.step_px / maps.scale_px
    s_fine = [np.arange(0.0, min(cfg.far_px / maps.scale_px, s_max) + 0.5 * ds, ds)]  # from infinity
    for lo, hi in ranges:
        a = max(s_coarse[lo] - 1.5 * ds_c, s_min)
        b = min(s_coarse[hi] + 1.5 * ds_c, s_max)
        s_fine.append(np.arange(a, b + 0.5 * ds, ds))
    s_fine = np.unique(np.round(np.concatenate(s_fine) / ds) * ds)
    if len(s_fine) > cfg.max_planes:  # too many: thin uniformly (coarser steps)
        s_fine = s_fine[np.linspace(0, len(s_fine) - 1, cfg.max_planes).round().astype(int)]
    sl = _bbox(cloud1, cfg.window_px)
    sf, std1 = zncc_planes(g1, g2, maps, s_fine, cfg.window_px, sl)
    j, c0, cm1, cp1 = _best3(sf)
    ok = cloud1[sl] & (c0 >= cfg.min_zncc) & (std1 >= cfg.min_texture)
    s_px = _refine(sf, j, c0, s_fine, ds, cm1, cp1)

    # 3. layers: peaks of the winners of the cost summed over a wide box (sharp, layer-mixing only
    #    at boundaries); each pixel labelled with the layer whose planes its own (label_px box)
    #    cost prefers; then refined on its layer's cost summed over the same layer's pixels only.
    if cfg.aggregate_px > 1 and ok.any():
        from scipy.ndimage import gaussian_filter1d

        k = int(cfg.aggregate_px)
        wide = np.stack([_box(sf[q], k) for q in range(len(s_fine))])
        jw, cw, lw, rw = _best3(wide)
        s_w = _refine(wide, jw, cw, s_fine, ds, lw, rw)
        del wide
        bw = 0.5 * ds
        nb = int(np.ceil(s_fine[-1] / bw)) + 2
        votes = np.bincount(np.clip((s_w[ok] / bw).round().astype(int), 0, nb - 1), minlength=nb)
        fr = _peaks(gaussian_filter1d(votes.astype(np.float64), 1.0, mode="constant"),
                    cfg.min_vote_fraction * ok.sum(), 0.0, cfg.valley_ratio, valleys=True)
        cuts = np.array([bw * (b + 0.5) for (_, b) in fr[:-1]])
        edges = np.concatenate([[-np.inf], cuts, [np.inf]])
        plane_layer = np.searchsorted(cuts, s_fine)
        lab = np.zeros(s_px.shape, np.int64)
        if len(fr) > 1:
            best = np.full((len(fr),) + s_px.shape, -np.inf, np.float32)
            for q in range(len(s_fine)):
                np.maximum(best[plane_layer[q]], _box(sf[q], cfg.label_px), out=best[plane_layer[q]])
            lab = best.argmax(axis=0)
            del best
        for L in range(len(fr)):
            here = ok & (lab == L)
            sel = np.flatnonzero((s_fine >= edges[L] - 1.01 * ds) & (s_fine <= edges[L + 1] + 1.01 * ds))
            if not here.any() or len(sel) < 3:
                continue
            m = here.astype(np.float32)
            wsum = np.maximum(_box(m, k), 1e-6)
            agg = np.stack([_box(sf[q] * m, k) / wsum for q in sel])
            ja, ca, la, ra = _best3(agg)
            s_px[here] = _refine(agg, ja, ca, s_fine[sel], ds, la, ra)[here]
    ys, xs = np.nonzero(ok)
    yi, xi = ys + sl[0].start, xs + sl[1].start
    px1 = np.stack([xi, yi], axis=-1).astype(np.float64)
    px2 = maps.points(s_px[ys, xs], yi, xi)
    return px1, px2, {"planes": s_fine, "layers_m": layers_m}
