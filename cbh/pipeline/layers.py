"""Stage 5: cloud layers from the histogram of point heights.

Heights are binned in ln(height): the range error of a stereo height grows like h²/baseline,
so a layer's relative (not absolute) spread is what stays about constant from 500 m to 8 km.
The histogram is smoothed with a Gaussian (``smooth_log``); its local maxima are candidate
layers. Two neighbouring candidates are merged (the higher survives) when they are closer than
``min_separation_log`` (the expected height resolution) or when the histogram between them
does not dip below ``valley_ratio`` × the lower peak. Each surviving peak owns the heights
between the valleys on either side. A layer is reported only with enough support:
``min_points`` points, ``min_fraction`` of all points and ``min_cover`` of the usable sky. Where
the plane sweep resolved a layer of its own above its lowest one (a vote peak of the image or of
a region, each pixel refined on that layer's planes and pixels alone: :mod:`.sweep`), and a layer
is reported below it (only a layer can hide a deck),
``min_fraction_resolved``
(0.5 %, the share of the sky that ``min_cover`` asks for) of the points is enough: an upper deck
seen through the gaps of a lower one holds 0.8–4 % of them in dense skies, while a cluster of
noise (a pile of matches on one plane of the sweep, say) is no layer of the sweep and still
needs 4 %.

Each layer's statistics (:func:`layer_stats`):

- ``height_m``: the cloud-base height, a *noise-deconvolved low percentile*. A raw low
  percentile of the point heights is biased low by the matching noise even on a perfectly
  flat base (the 10th percentile of N(h, σ) is h − 1.28σ). So the observed robust spread
  σ_obs = 1.4826·MAD is split into measurement noise and true spread:
  σ_true = sqrt(max(σ_obs² − σ_noise², 0)), and
  ``height_m = median − z·σ_true`` with z the standard-normal quantile of
  ``base_percentile`` (z = 1.2816 for the 10th): the 10th percentile of the layer's true
  height distribution, assumed Gaussian around its median. σ_noise is the median of the
  points' predicted height noise (:func:`height_noise`): δh = h·R·δθ / B⊥ (R the range from
  camera 1, B⊥ the baseline component perpendicular to the ray, δθ the angular matching
  noise), with δθ estimated by :func:`angular_noise` from the ray-miss distances of the
  2-D correspondences (miss / range samples the same pixel noise across the epipolar
  direction that the height sees along it): the sparse ones, or, when no sparse match
  survives (e.g. LK under a large exposure difference), the dense 2-D ones (DIS; never the
  plane sweep, whose matches lie on the epipolar curve by construction). *Robust base*: the
  spread is tested against ``noise_margin`` × σ_noise (1.2: the noise model is a prediction
  from a different set of matches, good to about ±20 %), i.e.
  σ_true = sqrt(max(σ_obs² − (1.2·σ_noise)², 0)): when the measured noise explains the
  spread the base *is* the median, and it moves continuously away from it only as the spread
  grows beyond the noise (before this, an exposure change that lost every sparse match set
  σ_noise = 0 and dropped the WAHRSIS base from 827 m to 516–633 m on the same sky).
  Without any noise estimate (σ_noise = 0) it falls back to median − z·σ_obs, the
  Gaussian-robust raw percentile. *Better-measured half*: σ_obs and σ_noise are each a
  measured spread plus whatever error the noise model misses, so σ_true from any set of the
  points is an upper bound; with at least 120 points it is the smaller of that of all points
  and that of the half whose geometry measures best (σ_obs about the trend fitted on all):
  parallax × height above camera 1 ∝ B⊥ cos z at least its median (the geometry's factor, not
  the predicted noise itself: that grows with the height measured and would pick the low
  points; on the real 241 m station's tilted 8 km deck it did, 7912 → 6606 m). Near the horizon a low layer's
  planes are a fraction of a pixel apart and its matches there are spread over the swept
  planes far beyond their predicted noise (random dense seed 109: a 400 m layer at B = 52 m,
  its points 75–80° from the zenith at −28 … +54 %, σ_obs 23 m; based at 370 m from all
  points, 383 m now). The median is of all points, the worse-measured half weighed down by its
  relative inverse variance (:func:`geometry_median`; the plain median before stop 60). (The smaller of two sample
  estimates is biased low: on a homogeneous Gaussian layer, σ 50 m, it raises the base by
  3.6 / 2.0 / 1.4 m on average at 120 / 300 / 1000 points, against the 10–40 m it moves where the
  horizon's matches spread);
- ``median_height_m``; ``spread_m`` = σ_obs = 1.4826 · MAD (σ for Gaussian heights);
- ``cover``: fraction of camera 1's usable sky that is cloud of this layer
  (:func:`layer_covers`): every cloud pixel of camera 1's cloud mask belongs to the layer whose
  height interval holds its own height-map height, or, where it has none (untextured cloud,
  failed matches), the height of the nearest measured pixel. So the covers of the layers add up
  to the cloud fraction, less the cloud whose height lies in an interval without enough support
  for a layer (the pipeline flags ``cover_incomplete`` when that is over 10 % of the cloud);
- ``confidence`` = (1 − exp(−points / (4·min_points))) · exp(−spread / median / 0.15) ·
  min(1, cover / (4·min_cover)): support, precision and extent in one number in 0..1;
- ``height_lo_m`` … ``height_hi_m``, the layer's *band* (:func:`layer_band`): the heights it
  stands for. Its points' 10–90 % range, widened to what this pair cannot tell apart from the
  layer: ``min_separation_log`` either side of the median (the histogram joins closer peaks),
  and the heights whose parallax is within ``resolve_px`` (2 px at working size: the sweep's
  separate vote peaks, see below) of the layer's, taken as the 90th percentile of its points'
  parallax B⊥/R (:func:`parallax_px`; along a ray parallax ∝ 1 / height above camera 1, so the
  band is h·p / (p ± resolve_px), open to the top of the searched range where p ≤ resolve_px).
  Two layers closer than that are one layer to this pair; the band is how the result says so.
  The points cannot: in the dense randomized skies where that happens (a deck seen through the
  gaps of a lower one, 1.0–1.2 px of parallax from a third), the matches of both decks lie in
  one unimodal peak whose spread is that of a single layer (seed 113: the points of the 4695 m
  deck and of the 9738 m deck both have their median at 4.8 km, quartiles 4650–4909 m and
  4650–4906 m).

Resolvability: two layers are separate peaks when their log-heights differ by more than
``min_separation_log`` (18 %) *and* the matching kept them apart. For the dense plane sweep
that needs ≈ 2 px of parallax difference at the working size (see :mod:`.sweep`: 2800 m and
7000 m are 2.0 px apart at B = 30 m, 3.3 px at B = 50 m with the Table 1 lenses at 960 px);
the layer heights, statistics over thousands of points, are then within a few per cent even
where a single pixel's height is not (a 7 km pixel at B = 30 m has 1.3 px of parallax).

Contract of every method in :data:`LAYER_METHODS`::

    method(heights_m (N,), cfg) -> (Histogram, list of (lo_m, hi_m) intervals, ascending)
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from cbh.errors import ConfigError
from cbh.result import Histogram, Layer
from cbh.pipeline.config import FilteringConfig, LayersConfig
from cbh.pipeline.peaks import find_peaks, smooth_gaussian, valley_cuts

__all__ = ["LAYER_METHODS", "histogram_layers", "layer_stats", "layer_covers", "get_layer_method", "angular_noise", "height_noise",
           "parallax_px", "layer_band"]


def angular_noise(miss_m: np.ndarray, range_m: np.ndarray) -> float:
    """Angular matching noise δθ [rad] = 1.4826 · median(miss / range) (0 without points).

    The ray miss of a correspondence is its cross-epipolar error × range; for isotropic pixel
    noise the along-epipolar (height) error has the same angular size.
    """
    miss_m, range_m = np.asarray(miss_m, np.float64), np.asarray(range_m, np.float64)
    ok = np.isfinite(miss_m) & (range_m > 0)
    return float(1.4826 * np.median(miss_m[ok] / range_m[ok])) if ok.any() else 0.0


def height_noise(xyz_m: np.ndarray, o1: np.ndarray, o2: np.ndarray, dtheta_rad: float) -> np.ndarray:
    """Predicted height noise [m] of each point (N, 3): δh = h_rel · R · δθ / B⊥ (see module doc)."""
    xyz_m = np.asarray(xyz_m, np.float64).reshape(-1, 3)
    if dtheta_rad <= 0 or not len(xyz_m):
        return np.zeros(len(xyz_m))
    v = xyz_m - np.asarray(o1, np.float64)
    r = np.linalg.norm(v, axis=1)
    d = v / np.maximum(r, 1e-9)[:, None]
    b = np.asarray(o2, np.float64) - np.asarray(o1, np.float64)
    b_perp = np.linalg.norm(b[None, :] - (d @ b)[:, None] * d, axis=1)
    return np.abs(v[:, 2]) * r * dtheta_rad / np.maximum(b_perp, 1e-6)


def parallax_px(xyz_m: np.ndarray, o1: np.ndarray, o2: np.ndarray, px_per_rad: float) -> np.ndarray:
    """Each point's stereo parallax [px]: the angle B⊥ / R between its two rays (R the range from
    camera 1, B⊥ the baseline across the ray) at the lens scale ``px_per_rad`` (working size)."""
    v = np.asarray(xyz_m, np.float64).reshape(-1, 3) - np.asarray(o1, np.float64)
    b = np.asarray(o2, np.float64) - np.asarray(o1, np.float64)
    r2 = np.maximum(np.einsum("ij,ij->i", v, v), 1e-18)
    vb = v @ b
    # |B⊥|² / R² = (|B|² − (v·B)² / R²) / R²
    return px_per_rad * np.sqrt(np.maximum(float(b @ b) - vb * vb / r2, 0.0) / r2)


_BAND_SAMPLES = 4096  # a layer's parallax percentile from at most about this many of its points (a regular stride)


def layer_band(h_pct: tuple[float, float, float], parallax: np.ndarray | None, camera_z_m: float, cfg: LayersConfig,
               max_height_m: float = math.inf) -> tuple[float, float]:
    """The heights [m] a layer stands for (``height_lo_m``, ``height_hi_m``; see module doc): its
    points' 10–90 % range (``h_pct`` = their 10th, 50th and 90th percentile heights), widened to
    what this pair cannot tell apart from its median: ``min_separation_log`` either side, and
    the heights whose parallax is within ``resolve_px`` of the layer's (the 90th percentile of
    its points' ``parallax`` [px], None = unknown: its best-placed points, those nearest the
    zenith, are what could split it)."""
    p10, med, p90 = h_pct
    lo, hi = min(p10, med * math.exp(-cfg.min_separation_log)), max(p90, med * math.exp(cfg.min_separation_log))
    if parallax is not None and len(parallax) and cfg.resolve_px > 0:
        p = float(np.percentile(parallax[:: max(1, len(parallax) // _BAND_SAMPLES)], 90.0))
        rel = med - camera_z_m  # along a ray, parallax ∝ 1 / (height above camera 1)
        if p > 0 and rel > 0:
            lo = min(lo, camera_z_m + rel * p / (p + cfg.resolve_px))
            hi = max(hi, camera_z_m + rel * p / (p - cfg.resolve_px) if p > cfg.resolve_px else math.inf)
    return lo, min(hi, max(max_height_m, p90))


def histogram_layers(heights_m: np.ndarray, cfg: LayersConfig, limits: FilteringConfig = FilteringConfig()):
    """Candidate layer intervals from a smoothed log-height histogram (see module doc).

    Returns
    -------
    hist : Histogram
        Counts of ``heights_m`` in log-spaced bins between the filtering height limits.
    intervals : list of (lo_m, hi_m)
        Height interval owned by each candidate layer, ascending; not yet checked for support.
    """
    lo, hi = math.log(limits.min_height_m), math.log(limits.max_height_m)
    nb = max(1, int(math.ceil((hi - lo) / cfg.bin_log)))
    edges_log = lo + cfg.bin_log * np.arange(nb + 1)
    h = np.asarray(heights_m, np.float64)
    h = h[np.isfinite(h) & (h > 0)]
    counts, _ = np.histogram(np.log(h), bins=edges_log)
    hist = Histogram(edges_m=np.exp(edges_log), counts=counts.astype(np.float64))
    if counts.sum() == 0:
        return hist, []
    s = smooth_gaussian(counts, cfg.smooth_log / cfg.bin_log)
    peaks = find_peaks(s, 0.0, cfg.valley_ratio, cfg.min_separation_log / cfg.bin_log)
    cuts = [lo] + [edges_log[v] + 0.5 * cfg.bin_log for v in valley_cuts(s, peaks)]
    cuts.append(hi)
    intervals = [(math.exp(cuts[i]), math.exp(cuts[i + 1])) for i in range(len(peaks))]
    return hist, intervals


def layer_covers(cloud: np.ndarray, usable: np.ndarray, nearest_m: np.ndarray,
                 intervals: list[tuple[float, float]]) -> tuple[list[float], float]:
    """Sky cover of each height interval (see module doc, ``cover``).

    Parameters
    ----------
    cloud, usable : ndarray, shape (H, W), bool
        Camera 1's cloud mask and usable sky (working size).
    nearest_m : ndarray, shape (H, W), float32
        Height of each pixel's nearest measured height-map pixel [m] (the pixel's own height
        where it has one; NaN everywhere if nothing was measured).
    intervals : list of (lo_m, hi_m)
        Candidate layers' height intervals, ascending, half-open [lo, hi).

    Returns
    -------
    covers : list of float
        Fraction of the usable sky per interval, 0..1.
    unassigned : float
        Fraction of the usable sky that is cloud in no interval (no height at all, or outside
        every interval).
    """
    n_usable = int(np.count_nonzero(usable))
    if not n_usable:
        return [0.0] * len(intervals), 0.0
    cl = cloud & usable
    h = nearest_m[cl]
    h = h[np.isfinite(h)]
    covers = [float(np.count_nonzero((h >= lo) & (h < hi))) / n_usable for lo, hi in intervals]
    return covers, float(np.count_nonzero(cl)) / n_usable - sum(covers)


_TREND_MIN_POINTS = 60  # a layer's large-scale trend is fitted (6 terms) only on this many points
_TREND_MIN_EXTENT = 0.15  # ... spread over this much of the sky (plane offsets' standard deviation, ≈ 9°)


def local_spread(h: np.ndarray, offsets: np.ndarray | None, keep: np.ndarray | None = None,
                 trend: "tuple | None" = None) -> float:
    """A layer's height spread about its own large-scale trend [m] (1.4826 · MAD, relative to
    the median height): what a cloud base's vertical extent can be. ``keep`` (N,) bool: the
    spread of these points only (the trend is fitted on all: a subset near the zenith spans too
    little sky to tell a trend from extent); None = all. ``trend``: :func:`trend_residuals` of
    the same ``h`` and ``offsets``, when already fitted (a layer asks for two spreads of one fit).

    A trend across the sky, ln h quadratic in the points' plane offsets (6 terms, fitted
    robustly: least squares, then again without the residuals beyond 3 σ), is a tilted deck or a
    calibration error, which one pair cannot tell apart; neither is depth in the cloud base
    (the real 241 m station's authors' calibration puts a linear trend of ±15 % across its
    8 km deck: read as extent, the base came out 25 % below the median). Without enough
    points spread over enough sky: the plain spread."""
    hk = h if keep is None else h[keep]
    med = float(np.median(hk))
    plain = 1.4826 * float(np.median(np.abs(hk - med)))
    fit = trend_residuals(h, offsets) if trend is None else trend
    if fit is None:
        return plain
    ok, r, (kept, fitted) = fit
    if keep is not None:
        sel = np.asarray(keep, bool)[ok] & kept
        if sel.any():
            return min(plain, med * _trend_sigma(r, sel))
    return min(plain, med * _trend_sigma(r, fitted))


def _trend_sigma(r: np.ndarray, use: np.ndarray) -> float:
    """1.4826 · MAD of the trend's residuals ``r`` [ln m] over the points ``use`` of the last fit."""
    ru = r[use]
    return 1.4826 * float(np.median(np.abs(ru - np.median(ru))))


def trend_residuals(h: np.ndarray, offsets: np.ndarray | None) -> "tuple | None":
    """The robust 6-term trend of ln h over the points' plane offsets (:func:`local_spread`):
    (the points with an offset (N,) bool; their residuals [ln m]; (those within 3 σ of the last
    fit, those the last fit was made on)), or None with too few points or too little sky."""
    if offsets is None or len(h) < _TREND_MIN_POINTS:
        return None
    a = np.asarray(offsets, np.float64)
    ok = np.isfinite(a).all(1) & (h > 0)
    if ok.sum() < _TREND_MIN_POINTS or float(np.sqrt(np.linalg.eigvalsh(np.cov(a[ok].T)).max())) < _TREND_MIN_EXTENT:
        return None
    a, y = a[ok], np.log(h[ok])
    X = np.column_stack([np.ones(len(a)), a, a ** 2, a[:, 0] * a[:, 1]])
    use = np.ones(len(y), bool)
    for _ in range(2):
        # least squares by the normal equations (6 × 6; lstsq on the min-norm solution where the
        # points leave a term undetermined): LAPACK's lstsq on the (N, 6) matrix took 8–28 ms
        # for 19 000 points (its BLAS threads against the pipeline's), this 0.15 ms; the same
        # coefficients to 1e-11
        Xu = X[use]
        coef = np.linalg.lstsq(Xu.T @ Xu, Xu.T @ y[use], rcond=None)[0]
        r = y - X @ coef
        sig = _trend_sigma(r, use)
        use, fitted = np.abs(r - np.median(r[use])) <= 3.0 * max(sig, 1e-9), use
    return ok, r, (use, fitted)


def geometry_median(h: np.ndarray, parallax: np.ndarray | None, camera_z_m: float) -> float:
    """The median of the heights ``h`` [m], the half of them whose geometry measures worse
    weighted down by their inverse variance relative to the median geometry's: a point's height
    noise goes as 1 / (parallax × height above camera 1 ∝ B⊥ cos z) at a given height, so weight
    min((g / median g)², 1). Near the horizon a low deck's planes are a fraction of a pixel apart
    and its matches there can fall into a higher layer's interval (random seed 16981: the 538 m
    deck, seen only 55–80° from the zenith through a 334 m deck's gaps, gathered that deck's
    points at 540–860 m and read 569 m; 552 m now). The better half keeps equal weights: on the
    real 241 m station's deck, whose heights change across the sky, the inverse variance of every
    point moved the layer towards the zenith's part by 3–6 % (a pair 9228 m against the reference
    8009 m). The factor, not the predicted noise, which grows with the height measured and would
    favour the low points (see module doc). Without ``parallax``: the plain median."""
    if parallax is None or len(parallax) != len(h) or not len(h):
        return float(np.median(h))
    geo = np.asarray(parallax, np.float64) * (np.asarray(h, np.float64) - camera_z_m)
    g2 = np.where(np.isfinite(geo) & (geo > 0), geo, 0.0) ** 2
    ref = float(np.median(g2))
    if not ref > 0:
        return float(np.median(h))
    o = np.argsort(h)
    cw = np.cumsum(np.minimum(g2 / ref, 1.0)[o])
    return float(np.asarray(h)[o][np.searchsorted(cw, 0.5 * cw[-1])])


def layer_stats(h: np.ndarray, cover: float, cfg: LayersConfig, noise_m: np.ndarray | None = None,
                offsets: np.ndarray | None = None, parallax: np.ndarray | None = None, camera_z_m: float = 0.0,
                max_height_m: float = math.inf) -> Layer:
    """Statistics of one layer's point heights ``h`` (N,) [m] (see module doc).

    ``noise_m`` (N,): predicted height noise of each point [m] (:func:`height_noise`);
    None = unknown (0). ``offsets`` (N, 2): the points' plane offsets from camera 1 (horizontal
    offset / height); with them, the base is deconvolved from the spread about the layer's
    large-scale trend (:func:`local_spread`), not from its whole spread. ``parallax`` (N,) [px],
    ``camera_z_m`` (camera 1's height) and ``max_height_m``: the layer's band (:func:`layer_band`).
    """
    from statistics import NormalDist

    pct = tuple(float(v) for v in np.percentile(h, [10.0, 50.0, 90.0]))
    med = geometry_median(h, parallax, camera_z_m)
    spread = 1.4826 * float(np.median(np.abs(h - med)))
    n = int(h.size)
    trend = trend_residuals(h, offsets)
    local = local_spread(h, offsets, trend=trend)
    sig_n = float(np.median(noise_m)) if noise_m is not None and len(noise_m) else 0.0
    sig_e = cfg.noise_margin * sig_n  # the noise the spread is tested against (model uncertainty)
    sig_t = math.sqrt(max(local * local - sig_e * sig_e, 0.0))
    if noise_m is not None and parallax is not None and len(parallax) == n >= 2 * _TREND_MIN_POINTS:
        # and of the half whose geometry measures best, if that says less (see module doc): near
        # the horizon a low layer's planes are a fraction of a pixel apart, its cost flat over
        # many of them, and its matches there spread over the swept planes (seed 109: 400 m at
        # B = 52 m, 75–80° from the zenith, 10–90 % at −28 … +54 %) far beyond their predicted noise
        geo = np.asarray(parallax, np.float64) * (h - camera_z_m)  # ∝ B⊥ cos z: the geometry's, not the height's
        keep = geo >= np.median(geo)
        loc_k, sig_k = local_spread(h, offsets, keep, trend), cfg.noise_margin * float(np.median(noise_m[keep]))
        sig_t = min(sig_t, math.sqrt(max(loc_k * loc_k - sig_k * sig_k, 0.0)))
    z = -NormalDist().inv_cdf(min(max(cfg.base_percentile, 1e-6), 50.0) / 100.0)
    conf = (1 - math.exp(-n / (4.0 * max(cfg.min_points, 1)))) * math.exp(-(spread / med) / 0.15)
    conf *= min(1.0, cover / (4.0 * cfg.min_cover)) if cfg.min_cover > 0 else 1.0
    lo, hi = layer_band(pct, parallax, camera_z_m, cfg, max_height_m)
    return Layer(
        height_m=med - z * sig_t,
        median_height_m=med,
        spread_m=spread,
        height_lo_m=lo,
        height_hi_m=hi,
        cover=float(cover),
        points=n,
        confidence=float(min(max(conf, 0.0), 1.0)),
    )


_COVER_SLACK = 0.1  # flag cover_incomplete when more than this share of the cloud is in no layer
_GAPS_MAX_ZENITH_DEG = 65.0  # a deck seen through a lower one's gaps is seen mostly within this of the zenith …
_GAPS_NEAR_SHARE = 0.5  # … this share of its points at least


def seen_through_gaps(offsets: np.ndarray | None, sel: np.ndarray) -> bool:
    """Whether the points ``sel`` of a candidate layer can be a deck seen through the gaps of a
    lower one: at least ``_GAPS_NEAR_SHARE`` of them within ``_GAPS_MAX_ZENITH_DEG`` of the zenith
    (``offsets``: the points' plane offsets from camera 1, tan z; None = unknown: yes).

    Towards the horizon a lower deck's gaps close (foreshortened, and a line of sight runs far
    under it), while its fragments there are smaller than a ZNCC window, so windows hold both
    decks and match between their parallaxes. Decks found through gaps in randomized dense skies
    had 81–100 % of their points within 65° (16 decks in 130 skies at 960 px); the two layers the
    sweep resolved between two decks near the horizon had 0 and 5 % (17186, 17274: 1797 m over a
    1142 m overcast, 2369 m between 1359 and 7267 m decks). Such a layer still stands with the
    support any layer needs."""
    if offsets is None or not np.any(sel):
        return True
    t = np.hypot(offsets[sel, 0], offsets[sel, 1])
    near = t <= math.tan(math.radians(_GAPS_MAX_ZENITH_DEG))  # (NaN: not near)
    return bool(near.mean() >= _GAPS_NEAR_SHARE)


@dataclass(frozen=True)
class LayerSet:
    """Stage 7: the supported layers of a pair."""

    layers: list[Layer]  # ascending by height
    histogram: Histogram
    label: np.ndarray  # (N,) int16: each point's index into ``layers``, -1 = none
    cover_incomplete: bool  # over ``_COVER_SLACK`` of the cloud lies in no reported layer
    unassigned: float = 0.0  # share of the usable sky that is cloud in no reported layer


def supported_layers(heights_m: np.ndarray, noise_m: np.ndarray, hist: Histogram,
                     intervals: list[tuple[float, float]], cloud: np.ndarray, usable: np.ndarray,
                     nearest_m: np.ndarray, cloud_fraction: float, cfg: LayersConfig,
                     offsets: np.ndarray | None = None, resolved_m=(), parallax: np.ndarray | None = None,
                     camera_z_m: float = 0.0) -> LayerSet:
    """Keep the candidate intervals with enough support (points, share of points, cover).

    Parameters
    ----------
    heights_m, noise_m : ndarray, shape (N,)
        Point heights and their predicted noise [m].
    hist, intervals
        Output of the layer method (:data:`LAYER_METHODS`).
    cloud, usable : ndarray, shape (H, W), bool
        Camera 1's cloud mask and usable sky (working size).
    nearest_m : ndarray, shape (H, W), float32
        Nearest measured height of each pixel (:func:`cbh.pipeline.heightmap.nearest_fill`).
    cloud_fraction : float
        Camera 1's cloud fraction, 0..1.
    offsets : ndarray, shape (N, 2), optional
        The points' plane offsets from camera 1 (:func:`local_spread`).
    resolved_m : sequence of float
        Heights of the layers the plane sweep resolved on its own [m]: an interval holding one
        above the lowest, with a layer reported below it, needs only ``min_fraction_resolved`` of
        the points (a deck seen through the gaps of a lower one holds a few per cent of them; a
        cluster of noise is no layer of the sweep), where its points lie as such a deck's do
        (:func:`seen_through_gaps`). The lowest reported layer is hidden by nothing: it needs
        ``min_fraction`` as any other.
    parallax : ndarray, shape (N,), optional
        The points' parallax [px] (:func:`parallax_px`), for each layer's band (:func:`layer_band`).
    camera_z_m : float
        Camera 1's height above the ENU origin [m].
    """
    label = np.full(len(heights_m), -1, np.int16)
    cover_of, unassigned = layer_covers(cloud, usable, nearest_m, intervals)
    upper = sorted(resolved_m)[1:]  # the sweep's layers above its lowest: what a lower deck can hide
    layers = []
    for k, (lo, hi) in enumerate(intervals):
        sel = (heights_m >= lo) & (heights_m < hi)
        n = int(sel.sum())
        # only a reported layer below can hide a deck: the sweep's own lowest may be no layer (a
        # pile of matches at its floor over unmasked masts, randomized 17270: a 128 m "deck" over
        # 0.2 % of a clear sky, passed as hidden by a 100 m one that was none)
        hidden = bool(layers) and any(lo <= h < hi for h in upper) and seen_through_gaps(offsets, sel)
        frac = cfg.min_fraction_resolved if hidden else cfg.min_fraction
        # a deck seen through gaps is measured in their interiors only (a window on a gap's edge
        # takes the lower deck): its cover is short by as much as its share of the points
        cover = cfg.min_cover * frac / cfg.min_fraction if cfg.min_fraction > 0 else cfg.min_cover
        if n < cfg.min_points or n < frac * len(heights_m) or cover_of[k] < cover:
            unassigned += cover_of[k]  # cloud of an unsupported height interval: in no layer
            continue
        label[sel] = len(layers)
        layers.append(layer_stats(heights_m[sel], cover_of[k], cfg, noise_m[sel],
                                  None if offsets is None else offsets[sel], None if parallax is None else parallax[sel],
                                  camera_z_m, float(hist.edges_m[-1]) if len(hist.edges_m) else math.inf))
    if not isinstance(hist, Histogram):
        hist = Histogram(np.zeros(1), np.zeros(0))
    return LayerSet(layers=layers, histogram=hist, label=label,
                    cover_incomplete=cover_incomplete(bool(layers), unassigned, cloud_fraction), unassigned=unassigned)


def cover_incomplete(any_layer: bool, unassigned: float, cloud_fraction: float) -> bool:
    """Whether over ``_COVER_SLACK`` of the cloud (``cloud_fraction``) lies in no reported layer
    (``unassigned``, a share of the usable sky) while some layer is reported."""
    return any_layer and unassigned > max(_COVER_SLACK * cloud_fraction, 0.005)


LAYER_METHODS = {"histogram": histogram_layers}


def get_layer_method(name: str):
    try:
        return LAYER_METHODS[name.lower()]
    except KeyError:
        raise ConfigError(f"unknown layer method {name!r} (valid: {', '.join(LAYER_METHODS)})") from None
