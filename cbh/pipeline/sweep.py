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
   steps). A cloud pixel is matched if its best plane's ZNCC ≥ ``min_zncc`` and its window
   has texture (grey-level standard deviation ≥ ``min_texture``). The planes are streamed
   (no (planes, H, W) stack at working size): per plane, the running best score and the ZNCC
   of the textured cloud pixels pooled 2 × 2.
3. *Layers and heights* (``aggregate_px`` > 1, the default), at half resolution on the pooled
   scores (a box of ``aggregate_px // 2`` there is the ``aggregate_px`` box at working size):
   the winners of the wide-box cost vote, in bins of half a plane step, for the layers of the
   image (votes only from the boxes whose mean ZNCC is above the ``vote_percentile``: a box
   that straddles two layers correlates worse and would fill the valley between their peaks);
   each pixel is labelled with the layer whose planes its ``label_px`` box cost prefers; its
   height is refined (parabola through the three best planes) on its layer's cost summed over
   that layer's pixels only — and of those, only the ones whose own (2 × 2 pooled) best plane
   lies in the layer's range: a pixel labelled into the layer by mistake (occluded in camera 2,
   or at a boundary) has its cost peak outside the range, and its sloped cost would pull the
   parabola towards the range's edge (−3 … −5 % bias on the far layer at B = 30 m before) — so
   it is sharp at layer boundaries; the half-resolution s is
   brought back to working size bilinearly (a box average varies smoothly inside a layer).
   With ``aggregate_px`` = 1 each pixel keeps its own best plane, refined by the parabola.

Far layers (``far_aggregate_px``): the parallax noise of a box average falls like 1/box
side, while 2 % of a far layer's height is a small parallax (2 % of p). A layer whose vote
peak has less than ``far_aggregate_px`` of parallax is refined on a box grown by
``far_aggregate_px`` / p (at most 4×): coarser detail where the parallax is small.

Resolvability (numbers for the Table 1 lenses at the default working size, lens radius 480 px
for 90°, 305.6 px/rad): parallax at zenith p = 305.6 px · B / h. The aggregated per-pixel
parallax (31 px box) is good to ≈ 0.1 px, so a pixel's height is within 2 % where
0.02·p ≥ 0.1 px, i.e. p ≥ 5 px (B = 50 m: h ≤ 3.0 km; B = 30 m: h ≤ 1.8 km; B = 100 m:
h ≤ 6.1 km); the grown box for far layers extends this to p ≈ 2 px (7000 m at B = 50 m:
2.2 px, dense-map median error 1.4 % with three layers). Two layers are told apart (separate
vote peaks) down to ≈ 2 px of parallax difference: 2800 m and 7000 m are 3.3 px apart at
B = 50 m and 2.0 px at B = 30 m (both separated; layer heights, aggregated over thousands of
pixels, within 2 %). At B = 30 m the pixels of the upper two layers are not resolved to 2 %:
p = 3.3 and 1.3 px, 2 % of which is 0.066 and 0.026 px, and the 7000 m pixels within ≈ 3 px
of a lower cloud (a third of them; many occluded in camera 2) take a lower layer's label:
dense-map median error 2.2 % over all three layers, coverage 69 %. Use a larger
working size (``working_radius_px``: parallax scales with it) or a longer baseline there.

Speed (1920 px pair, working size 960 px, 2-core machine): ≈ 0.35–0.4 s for the sweep, of
which the fine pass (≈ 12 ms per plane: remap, three box filters, a dozen OpenCV arithmetic
calls) is about half. Everything per pixel goes through OpenCV (multi-threaded, no numpy
temporaries); numpy's masked ``copyto`` and ``argmax`` over a stack axis are avoided (20× and
10× slower).

Output: one correspondence per accepted cloud pixel of camera 1 (``dense=True``), px2 = the
plane mapping at the refined s. Such a correspondence lies on the epipolar geometry by
construction, so its ray miss is ≈ 0 (not a measurement of matching quality; the sparse
``lk`` matches carry that).
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

__all__ = ["PlaneMaps", "plane_maps", "sweep_matches", "zncc_planes"]

_OUTSIDE = -1.0e5
_MAX_GROW = 4.0  # far layers: aggregation box at most this × aggregate_px
_VOTE_SMOOTH_BINS = 0.5  # Gaussian smoothing of the fine vote histogram [bins of half a plane step]


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
        if getattr(self, "_planes_key", None) != sl:  # contiguous (h, w) planes of the region, cached
            self._planes = [[np.ascontiguousarray(m[sl + (k,)]) for m in (self.m0, self.a, self.b)] for k in (0, 1)]
            self._planes_key = sl
        out = []
        for m0, a, b in self._planes:
            out.append(cv2.scaleAdd(b, float(s * s), cv2.scaleAdd(a, float(s), m0)))
        return out[0], out[1]

    def points(self, s: np.ndarray, yi: np.ndarray, xi: np.ndarray) -> np.ndarray:
        """Camera-2 pixels (N, 2) float64 at per-pixel s (N,) for camera-1 pixels (yi, xi)."""
        w = self.m0.shape[1]
        idx = np.asarray(yi, np.int64) * w + np.asarray(xi, np.int64)  # flat gathers: ~3× faster
        s = np.asarray(s, np.float64)[:, None]
        m0, a, b = (m.reshape(-1, 2)[idx].astype(np.float64) for m in (self.m0, self.a, self.b))
        return m0 + (a + b * s) * s

    def downsampled(self, factor: int) -> "PlaneMaps":
        """The same mapping between images downsampled by an integer ``factor`` (INTER_AREA; cached)."""
        cache = self.__dict__.setdefault("_down", {})
        if factor not in cache:
            cache[factor] = self._downsampled(factor)
        return cache[factor]

    def _downsampled(self, factor: int) -> "PlaneMaps":
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
    return cv2.boxFilter(img, -1, (k, k), normalize=True, borderType=cv2.BORDER_REFLECT)


def _zncc_iter(i1: np.ndarray, gray2: np.ndarray, maps: PlaneMaps, s_values: np.ndarray, window_px: int, sl):
    """Yield (std1, None) once, then (j, score (h, w) float32) for every plane ``s_values[j]``.

    All per-pixel arithmetic goes through OpenCV (multi-threaded, no numpy temporaries):
    ZNCC = (E[i1·w] − μ1·μ2) / sqrt(var1·var2 + 1e-3) over a ``window_px`` box.
    """
    k = int(window_px)
    mu1 = _box(i1, k)
    var1 = cv2.max(cv2.subtract(cv2.sqrBoxFilter(i1, cv2.CV_32F, (k, k), borderType=cv2.BORDER_REFLECT), cv2.multiply(mu1, mu1)), 0.0)
    yield cv2.sqrt(var1), None
    for j, s in enumerate(s_values):
        mx, my = maps.at(float(s), sl)
        w = cv2.remap(gray2, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        mu2 = _box(w, k)
        var2 = cv2.max(cv2.subtract(cv2.sqrBoxFilter(w, cv2.CV_32F, (k, k), borderType=cv2.BORDER_REFLECT), cv2.multiply(mu2, mu2)), 0.0)
        cov = cv2.subtract(_box(cv2.multiply(i1, w), k), cv2.multiply(mu1, mu2))
        den = cv2.sqrt(cv2.add(cv2.multiply(var1, var2), 1e-3))
        yield j, cv2.divide(cov, den)


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
    i1 = np.ascontiguousarray(gray1[sl], np.float32)
    it = _zncc_iter(i1, np.asarray(gray2, np.float32), maps, s_values, window_px, sl)
    std1, _ = next(it)
    out = np.empty((len(s_values),) + i1.shape, np.float32)
    for j, score in it:
        out[j] = score
    return out, std1


def _bbox(mask: np.ndarray, pad: int, even: bool = False):
    """Bounding box of ``mask`` grown by ``pad``; ``even``: start and size even (for 2× pooling)."""
    ys, xs = np.nonzero(mask.any(axis=1))[0], np.nonzero(mask.any(axis=0))[0]
    h, w = mask.shape
    y0, y1 = max(ys[0] - pad, 0), min(ys[-1] + pad + 1, h)
    x0, x1 = max(xs[0] - pad, 0), min(xs[-1] + pad + 1, w)
    if even:
        y0, x0 = y0 - y0 % 2, x0 - x0 % 2
        y1 = min(y1 + (y1 - y0) % 2, h - (h - y0) % 2)
        x1 = min(x1 + (x1 - x0) % 2, w - (w - x0) % 2)
    return np.s_[int(y0): int(y1), int(x0): int(x1)]


class _Best3:
    """Streaming best plane: after ``add(j, score)`` for j = 0, 1, … (consecutive planes),
    ``result()`` = (index j (h, w) int32, its score, score of plane j−1, score of plane j+1).

    OpenCV masked copies; no (P, h, w) stack is needed. Ties keep the first plane.
    """

    def __init__(self):
        self.best = None

    def add(self, j: int, cur: np.ndarray) -> None:
        if self.best is None:
            self.best, self.left, self.right = cur.copy(), cur.copy(), cur.copy()
            self.j = np.zeros(cur.shape, np.int32)
            self._q = np.empty(cur.shape, np.int32)
        else:
            cv2.copyTo(cur, cv2.compare(self.j, j - 1, cv2.CMP_EQ), self.right)
            gt = cv2.compare(cur, self.best, cv2.CMP_GT)
            cv2.copyTo(self.prev, gt, self.left)
            cv2.copyTo(cur, gt, self.best)
            self._q.fill(j)  # (np.copyto with where= is ~20x slower than OpenCV's masked copy)
            cv2.copyTo(self._q, gt, self.j)
        self.prev = cur

    def result(self):
        return self.j, self.best, self.left, self.right


def _best3(scores):
    """Best plane index j, its score and the scores of planes j−1 and j+1 of a stack (P, h, w)."""
    b = _Best3()
    for q in range(len(scores)):
        b.add(q, scores[q])
    return b.result()


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
    info : dict — ``planes`` (fine s values), ``layers_m`` (coarse layer hypotheses [m]),
        ``timing_ms`` (per step)
    """
    import time


    timing: dict[str, float] = {}
    t0 = time.perf_counter()

    def lap(name):
        nonlocal t0
        t1 = time.perf_counter()
        timing[name] = (t1 - t0) * 1000.0
        t0 = t1

    empty = np.zeros((0, 2)), np.zeros((0, 2)), {"planes": np.zeros(0), "layers_m": [], "timing_ms": timing}
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
    it = _zncc_iter(np.ascontiguousarray(c1[slc]), c2, cm, s_coarse, cfg.coarse_window_px, slc)
    next(it)
    run = _Best3()
    for q, sc in it:
        run.add(q, sc)
    best, cbest, _, _ = run.result()
    good = ccloud[slc] & (cbest >= cfg.min_zncc)
    votes = np.bincount(best[good], minlength=len(s_coarse)).astype(np.float64)
    n_cloud = float(ccloud.sum())
    ranges = _peaks(votes, cfg.min_vote_fraction * n_cloud, cfg.extent_ratio, cfg.valley_ratio)
    layers_m = [float(o1z + 1.0 / s_coarse[(lo + hi) // 2]) for lo, hi in ranges]
    lap("coarse")

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
    info = {"planes": s_fine, "layers_m": layers_m, "timing_ms": timing}
    aggregate = cfg.aggregate_px > 1
    sl = _bbox(cloud1, cfg.window_px, even=aggregate)
    i1 = np.ascontiguousarray(g1[sl])
    h, w = i1.shape
    it = _zncc_iter(i1, g2, maps, s_fine, cfg.window_px, sl)
    std1, _ = next(it)
    m0 = cloud1[sl] & (std1 >= cfg.min_texture)  # textured cloud pixels: the candidates
    if not aggregate:  # per-pixel best plane, refined by a parabola
        sf, _ = zncc_planes(g1, g2, maps, s_fine, cfg.window_px, sl)
        j, c0, cm1, cp1 = _best3(sf)
        ok = m0 & (c0 >= cfg.min_zncc)
        s_px = _refine(sf, j, c0, s_fine, ds, cm1, cp1)
        lap("fine")
    else:
        # 3. aggregation at half resolution. Each plane's ZNCC (textured cloud pixels only) is
        #    pooled 2 × 2; a box of aggregate_px // 2 there is the aggregate_px box at working size.
        #    The layers are the peaks of the votes of the wide-box winners; each pixel is labelled
        #    with the layer whose planes its own (label_px box) cost prefers, then its height is
        #    refined on its layer's cost summed over the same layer's pixels only (sharp at layer
        #    boundaries), and brought back to working size by bilinear interpolation (it varies
        #    smoothly inside a layer: it is a box average itself).
        hh, wh = h // 2, w // 2
        m0f = m0.astype(np.float32)
        pooled = np.empty((len(s_fine), hh, wh), np.float32)
        c0 = None
        for q, score in it:
            c0 = score.copy() if c0 is None else cv2.max(c0, score, dst=c0)
            pooled[q] = cv2.resize(cv2.multiply(score, m0f), (wh, hh), interpolation=cv2.INTER_AREA)
        ok = m0 & (c0 >= cfg.min_zncc)
        lap("fine")
        if not ok.any():
            return empty[0], empty[1], info
        k2 = max(3, (int(cfg.aggregate_px) // 2) | 1)
        kl = max(1, (int(cfg.label_px) // 2) | 1)
        okh = cv2.resize(ok.astype(np.float32), (wh, hh), interpolation=cv2.INTER_AREA)
        run = _Best3()
        for q in range(len(s_fine)):
            run.add(q, _box(pooled[q], k2))
        jw, cw, lw, rw = run.result()
        s_w = _refine(None, jw, cw, s_fine, ds, lw, rw).astype(np.float32)
        from scipy.ndimage import gaussian_filter1d

        bw = 0.5 * ds
        nb = int(np.ceil(s_fine[-1] / bw)) + 2
        vote = okh > 0
        if cfg.vote_percentile > 0 and vote.any():  # boxes that straddle two layers correlate worse:
            # leave them out of the votes, or they fill the valley between the layers' peaks
            mean_w = cw / np.maximum(_box(cv2.resize(m0f, (wh, hh), interpolation=cv2.INTER_AREA), k2), 1e-6)
            vote &= mean_w >= np.percentile(mean_w[vote], cfg.vote_percentile)
        votes = np.bincount(np.clip((s_w[vote] / bw).round().astype(int), 0, nb - 1), weights=okh[vote], minlength=nb)
        fr = _peaks(gaussian_filter1d(votes, _VOTE_SMOOTH_BINS, mode="constant"),
                    cfg.min_vote_fraction * float(okh.sum()), 0.0, cfg.valley_ratio, valleys=True)
        cuts = np.array([bw * (b + 0.5) for (_, b) in fr[:-1]])
        edges = np.concatenate([[-np.inf], cuts, [np.inf]])
        info["votes"], info["vote_bin_s"], info["cuts_s"] = votes, bw, cuts
        plane_layer = np.searchsorted(cuts, s_fine)
        lab_h = np.zeros((hh, wh), np.uint8)
        if len(fr) > 1:
            best_l = [None] * len(fr)
            for q in range(len(s_fine)):
                L = int(plane_layer[q])
                b = _box(pooled[q], kl) if kl > 1 else pooled[q]
                best_l[L] = b.copy() if best_l[L] is None else cv2.max(best_l[L], b, dst=best_l[L])
            stack = np.stack([b if b is not None else np.full((hh, wh), -np.inf, np.float32) for b in best_l])
            lab_h = stack.argmax(axis=0).astype(np.uint8)
        lab = cv2.resize(lab_h, (w, h), interpolation=cv2.INTER_NEAREST)
        if len(fr) > 1:
            run = _Best3()
            for q in range(len(s_fine)):
                run.add(q, pooled[q])
            j_loc = run.result()[0]
        else:
            j_loc = np.zeros((hh, wh), np.int32)
        lap("layers")
        s_px = np.empty((h, w), np.float32)
        for L in range(max(len(fr), 1)):
            here = ok & (lab == L)
            if not here.any():
                continue
            lo_e, hi_e = (edges[L], edges[L + 1]) if fr else (-np.inf, np.inf)
            sel = np.flatnonzero((s_fine >= lo_e - 1.01 * ds) & (s_fine <= hi_e + 1.01 * ds))
            if len(sel) < 3:
                s_half = s_w
            else:
                kL = k2
                if cfg.far_aggregate_px > 0 and fr:  # far layers: the box grows like 1/parallax
                    lo_b, hi_b = fr[L]
                    p_l = bw * (lo_b + int(np.argmax(votes[lo_b: hi_b + 1]))) * maps.scale_px
                    grow = min(max(cfg.far_aggregate_px / max(p_l, 1e-6), 1.0), _MAX_GROW)
                    kL = max(3, int(round(k2 * grow)) | 1)
                mL = (lab_h == L)
                if len(fr) > 1:  # only pixels whose own (2 × 2 pooled) best plane is in this layer:
                    mL &= plane_layer[j_loc] == L  # mislabelled ones would bias the parabola
                mL = mL.astype(np.float32)
                run = _Best3()
                for i, q in enumerate(sel):
                    run.add(i, _box(cv2.multiply(pooled[q], mL), kL))
                ja, ca, la, ra = run.result()
                s_half = _refine(None, ja, ca, s_fine[sel], ds, la, ra).astype(np.float32)
            up = cv2.resize(s_half, (w, h), interpolation=cv2.INTER_LINEAR)
            np.copyto(s_px, up, where=here)
        lap("refine")
    ys, xs = np.nonzero(ok)
    yi, xi = ys + sl[0].start, xs + sl[1].start
    px1 = np.stack([xi, yi], axis=-1).astype(np.float64)
    px2 = maps.points(s_px[ys, xs], yi, xi)
    lap("points")
    return px1, px2, info
