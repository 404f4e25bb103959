"""Stage 3: classical cloud segmentation of colour images (no learned weights).

Contract of every method in :data:`SEGMENTERS`::

    method(nbr, usable, zenith_deg, sun_angle_deg, cfg, chroma=None, image_bgr=None) -> cloud (H, W) bool

``nbr`` = (B − R)/(B + R) (float32, (H, W)); clear sky is blue (NBR ≈ 0.2 … 0.6 on most
cameras, 0.08–0.15 on a hazy tropical sky), clouds are white or grey (NBR ≈ 0, shifted by a
camera's colour cast). ``usable`` is the sky mask, ``zenith_deg`` the zenith angle of each
pixel and ``sun_angle_deg`` its angle from the sun (either None when unknown: no geometry).
``chroma`` = (max − min)/max of the three channels (float32, (H, W); 0 = grey; None =
unknown); ``image_bgr`` the image itself (texture, saturated sun; None = unknown). Pixels
outside ``usable`` are never cloud. Greyscale images (2-D, or three identical channels) are
refused by :func:`segment` (:class:`~cbh.errors.ImageError`): there is no blue-red ratio.

- ``hybrid`` (default): adapts per image and per region, from the physics (clear sky is the
  bluest, most saturated thing in the sky by Rayleigh scattering, and its colour varies
  smoothly with the zenith angle and the angle to the sun; cloud is grey or white):

  1. *clear-sky reference* (:func:`clear_sky_references`): per region (zenith × sun-angle
     bins with geometry; without, the rings of an all-sky disk around its saturated sun, or
     6 × 6 image blocks) the ``clear_percentile`` (85th) percentile of NBR and of chroma;
     regions far below a smooth surface through the others (all cloud) are raised to it.
     A colour cast or exposure of the camera is in the reference as much as in the pixel.
  2. *blue deficit* r = reference − NBR. Its minimum-cross-entropy (Li) threshold splits the
     sky in two classes; the sky is *bimodal* when the upper class's deficit exceeds the lower
     one's (taken ≥ 0) by ``min_gap`` (0.06), or by half of it when the upper class is also
     ``chroma_gap`` greyer and half as saturated (pale hazy or over-exposed skies; a textured
     overcast has both classes equally grey).
  3. bimodal: cloud where (1 − w)·r / (median deficit of the cloud class) + w·(relative
     desaturation vs the reference) > ``score_threshold`` (w = ``chroma_weight`` = 0.3: the
     desaturation cue catches thin cloud and bluish edges, which keep some blue). One class
     only (the hybrid-thresholding idea: no threshold from a unimodal histogram): overcast when
     the median NBR is below ``fixed_threshold`` (0.15), unless the sky's chroma or its
     whitening towards the horizon (:func:`horizon_whitening`: clear sky pales there, an
     overcast does not) shows it clear, or when the sky is textured (median local contrast ≥
     ``texture_cv``); else a clear sky, where only what stands out by ≈ 0.05 from the reference
     is cloud. A textured sky that is blue (median NBR ≥ 0.15) and whose classes
     are at least half of ``min_gap`` apart is faint cloud on a blue sky, judged as a clear sky
     (:func:`faint_cloud_on_blue`).

  Measured (``benchmarks/segmentation.py --simulate``, 24 simulated skies × camera colour
  responses, with the station): 97.5 % accuracy, F1 97.2, against 84.2 % / 80.7 for
  ``nbr_adaptive`` and 73.9 % / 72.8 for the fixed NBR < 0.15.
- ``nbr``: fixed threshold.
- ``nbr_adaptive``: the threshold falls towards the sun and the horizon, where clear sky is
  whiter (forward scattering, longer air path): t = t0 + (t_sun − t0)·exp(−ψ/ψ0) +
  (t_hor − t0)·ramp(zenith), so that bright clear sky there is not taken for cloud.
  The sun term is *not* applied to grey pixels (``chroma < grey_chroma``): sunlit cloud near
  the sun is bright and colourless (chroma ≈ 0.02–0.05), while clear sky, even in the bright
  aureole just outside the masked sun disk, keeps a blue tint (chroma ≥ 0.1; ≥ 0.2 in the
  simulator). Lowering the threshold there called most sunlit cloud within 25° of the sun clear
  (cloud NBR ≈ 0 ± 0.015 against a threshold of ≈ 0 at ψ = 10°). Without geometry: no ramp.
- ``otsu``: Otsu's threshold on the usable NBR histogram, clamped to [otsu_min, otsu_max]
  (copes with a global colour shift of the camera).

Per pixel everything runs through OpenCV (or torch on a device: :mod:`.torch_segment`); the hybrid's references are sampled (≈ 25 000
pixels) and interpolated on a 4× coarser grid, so it costs a few times ``nbr_adaptive``'s ≈ 5 ms
per 960² image. Images with a long side above ``max_side_px`` (1600) are classified
area-averaged and the mask is brought back to full size.
"""
from __future__ import annotations

import math

import cv2
import numpy as np

from cbh.errors import ConfigError, ImageError
from cbh.imageio import is_greyscale
from cbh.pipeline.ccl import components_with_stats
from cbh.pipeline.config import SegmentationConfig

__all__ = ["SEGMENTERS", "normalized_blue_red", "chroma", "segment", "get_segmenter", "check_colour",
           "local_contrast", "clear_sky_reference", "clear_sky_references", "li_threshold"]


def normalized_blue_red(image_bgr: np.ndarray) -> np.ndarray:
    """NBR = (B − R)/(B + R) of a BGR uint8 image, shape (H, W), float32 (0 where B + R = 0)."""
    b, _, r = cv2.split(image_bgr)
    s = cv2.add(b, r, dtype=cv2.CV_32F)
    d = cv2.subtract(b, r, dtype=cv2.CV_32F)
    return cv2.divide(d, cv2.max(s, 1.0))  # s = 0 only where d = 0


def chroma(image_bgr: np.ndarray) -> np.ndarray:
    """(max − min)/max of the channels of a BGR uint8 image, (H, W) float32 (0 where black)."""
    b, g, r = cv2.split(image_bgr)
    mx = cv2.max(cv2.max(b, g), r)
    mn = cv2.min(cv2.min(b, g), r)
    return cv2.divide(cv2.subtract(mx, mn, dtype=cv2.CV_32F), cv2.max(mx, 1).astype(np.float32))


def _nbr(nbr, usable, zenith_deg, sun_angle_deg, cfg: SegmentationConfig, chroma=None, image_bgr=None):
    return (nbr < cfg.threshold) & usable


def _nbr_adaptive(nbr, usable, zenith_deg, sun_angle_deg, cfg: SegmentationConfig, chroma=None, image_bgr=None):
    span = max(90.0 - cfg.horizon_start_deg, 1e-6)
    if zenith_deg is None:  # no geometry: no horizon ramp
        zenith_deg = np.zeros(nbr.shape, np.float32)
    ramp = cv2.min(cv2.max(cv2.subtract(np.asarray(zenith_deg, np.float32), cfg.horizon_start_deg), 0.0), span)
    t = cv2.add(cv2.multiply(ramp, (cfg.horizon_threshold - cfg.threshold) / span), cfg.threshold)
    cloud = cv2.compare(nbr, t, cv2.CMP_LT)
    if sun_angle_deg is not None:
        sun = cv2.exp(cv2.multiply(np.asarray(sun_angle_deg, np.float32), -1.0 / cfg.sun_scale_deg))
        ts = cv2.add(t, cv2.multiply(sun, cfg.sun_threshold - cfg.threshold))
        sun_cloud = cv2.compare(nbr, ts, cv2.CMP_LT)
        if chroma is not None:  # grey pixels keep the threshold without the sun term
            grey = cv2.compare(chroma, cfg.grey_chroma, cv2.CMP_LT)
            sun_cloud = cv2.bitwise_or(sun_cloud, cv2.bitwise_and(cloud, grey))
        cloud = sun_cloud
    return (cloud > 0) & usable


def _otsu(nbr, usable, zenith_deg, sun_angle_deg, cfg: SegmentationConfig, chroma=None, image_bgr=None):
    v = nbr[usable]
    if v.size < 16:
        return np.zeros_like(usable)
    # map [-1, 1] to 0..255 for cv2's Otsu
    q = np.clip((v + 1.0) * 127.5, 0, 255).astype(np.uint8).reshape(-1, 1)
    t8, _ = cv2.threshold(q, 0, 255, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
    # Otsu puts values <= t8 in the low (cloud) class: the boundary is half a level above t8
    t = float(np.clip((t8 + 1.0) / 127.5 - 1.0, cfg.otsu_min, cfg.otsu_max))
    return (nbr < t) & usable


# --- hybrid: per-image, per-region adaptive (the default) ---------------------------------------

_Z_EDGES_DEG = (0.0, 20.0, 35.0, 48.0, 58.0, 66.0, 73.0, 90.0)  # zenith bins of the clear-sky reference
_PSI_EDGES_DEG = (0.0, 12.0, 22.0, 35.0, 55.0, 80.0, 180.0)  # sun-angle bins
_BLOCKS = 6  # without geometry: the image is cut into _BLOCKS × _BLOCKS regions
_MIN_BIN = 100  # a bin needs this many sampled usable pixels for its own reference
_SAMPLES = 25000  # pixels sampled for the reference (subsampled on a regular grid)
_REF_STRIDE = 4  # the references are interpolated on a grid this much coarser, then resized
BRIGHTNESS_MIN_CLEAR = 0.05  # the brightness cue needs this share of the usable sky found clear by the first pass


def li_threshold(values: np.ndarray, tol: float = 1e-4, bins: int = 512) -> float:
    """Minimum-cross-entropy threshold (Li & Lee 1993; Li & Tam 1998 iteration) of 1-D values.

    Values at or below the threshold are the low class. Iterates on a ``bins``-bin histogram
    (the threshold is good to a bin width, range / 512). Works on any real range (shifted to
    positive internally); returns the value itself for a constant input.
    """
    v = np.asarray(values, np.float64).ravel()
    if v.size == 0:
        return 0.0
    lo, hi = float(v.min()), float(v.max())
    if hi - lo < 1e-9:
        return lo
    counts, edges = np.histogram(v, bins=bins, range=(lo, hi))
    x = 0.5 * (edges[:-1] + edges[1:]) - lo + 1e-3  # positive: the cross entropy takes logs of the class means
    cw, cm = np.cumsum(counts), np.cumsum(counts * x)
    t = float(cm[-1] / cw[-1])
    for _ in range(100):
        k = min(max(int(np.searchsorted(x, t, side="right")) - 1, 0), bins - 2)  # bins 0..k: low class
        n0, n1 = cw[k], cw[-1] - cw[k]
        if n0 == 0 or n1 == 0:
            break
        m0, m1 = cm[k] / n0, (cm[-1] - cm[k]) / n1
        t_new = (m1 - m0) / (math.log(m1) - math.log(m0)) if m1 > m0 else t
        if abs(t_new - t) < tol:
            t = t_new
            break
        t = t_new
    return float(t + lo - 1e-3)


def _fisheye_circle(usable: np.ndarray, box) -> tuple[float, float, float] | None:
    """(cy, cx, radius) when the usable pixels form a disk inside a dark frame (an all-sky image), else None.

    The usable pixels fill π/4 of their bounding box within 0.65–0.88 and the box's corner
    squares (a tenth of its side) are nearly empty (< 10 % usable).
    """
    y0, y1, x0, x1 = box
    h, w = y1 - y0, x1 - x0
    if min(h, w) < 32 or not 0.8 < h / w < 1.25:
        return None
    sub = usable[y0:y1, x0:x1]
    fill = float(np.count_nonzero(sub)) / (h * w)
    k = max(2, min(h, w) // 10)
    corners = [sub[:k, :k], sub[:k, -k:], sub[-k:, :k], sub[-k:, -k:]]
    if not 0.65 <= fill <= 0.88 or max(float(c.mean()) for c in corners) > 0.1:
        return None
    return 0.5 * (y0 + y1 - 1), 0.5 * (x0 + x1 - 1), 0.5 * max(h, w)


def _saturated_sun(image_bgr: np.ndarray, usable: np.ndarray) -> tuple[float, float] | None:
    """(row, col) of the largest saturated blob (the sun; saturated at the image's own clip
    level, :mod:`.clip`) of at least 0.02 % of the image, else None."""
    from cbh.pipeline.clip import saturated_pixels

    sat = saturated_pixels(image_bgr)
    n, _, stats, cent = components_with_stats(sat)
    if n < 2:
        return None
    k = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    if stats[k, cv2.CC_STAT_AREA] < 2e-4 * sat.size:
        return None
    return float(cent[k, 1]), float(cent[k, 0])


def _region_coords(shape, usable, zenith_deg, sun_angle_deg, image_bgr=None):
    """Per-pixel region coordinates (u, v) and their bin edges for the clear-sky reference.

    With geometry: zenith angle × angle to the sun (or zenith only). Without: the radius of an
    all-sky image's disk (:func:`_fisheye_circle`) as a stand-in for the zenith angle, else a
    grid of image blocks (a crop or an ordinary photograph).
    """
    H, W = shape
    if zenith_deg is not None:
        u, ue = np.asarray(zenith_deg, np.float32), np.asarray(_Z_EDGES_DEG, np.float32)
        if sun_angle_deg is not None:
            return u, ue, np.asarray(sun_angle_deg, np.float32), np.asarray(_PSI_EDGES_DEG, np.float32)
        return u, ue, None, None
    ys, xs = np.nonzero(usable) if usable.any() else (np.array([0, H - 1]), np.array([0, W - 1]))
    y0, y1, x0, x1 = ys.min(), ys.max() + 1, xs.min(), xs.max() + 1
    circle = _fisheye_circle(usable, (y0, y1, x0, x1))
    if circle is not None:  # an all-sky image without its calibration: radius as a stand-in for zenith
        cy, cx, r = circle
        yy, xx = np.mgrid[0:H, 0:W].astype(np.float32)
        rr = cv2.magnitude(xx - np.float32(cx), yy - np.float32(cy)) * np.float32(90.0 / r)
        sun = _saturated_sun(image_bgr, usable) if image_bgr is not None else None
        if sun is None:
            return rr, np.asarray(_Z_EDGES_DEG, np.float32), None, None
        psi = cv2.magnitude(xx - np.float32(sun[1]), yy - np.float32(sun[0])) * np.float32(90.0 / r)
        return rr, np.asarray(_Z_EDGES_DEG, np.float32), psi, np.asarray(_PSI_EDGES_DEG, np.float32)
    yy = np.broadcast_to(np.arange(H, dtype=np.float32)[:, None], (H, W))
    xx = np.broadcast_to(np.arange(W, dtype=np.float32)[None, :], (H, W))
    return (yy, np.linspace(y0, y1, _BLOCKS + 1, dtype=np.float32),
            xx, np.linspace(x0, x1, _BLOCKS + 1, dtype=np.float32))


def _bin_reference(values, bu, bv, nu, nv, q):
    """q-th percentile of ``values`` in each (u, v) bin: (nu, nv) float64, NaN where too few.

    One sort by (bin, value); each bin's percentile is then read at its rank (nearest rank).
    ``values`` must lie within [−1, 1] (NBR and chroma do).
    """
    ref = np.full((nu, nv), np.nan)
    key = (bu * nv + bv).astype(np.float64)
    # one float sort of bin·8 + value (values are NBR or chroma, within [−1, 1]: no overlap)
    c = np.sort(key * 8.0 + np.clip(values, -1.0, 1.0))
    ks = np.round(c / 8.0)
    vs = c - 8.0 * ks
    bounds = np.searchsorted(ks, np.arange(nu * nv + 1) - 0.5)
    a, b = bounds[:-1], bounds[1:]
    ok = (b - a) >= _MIN_BIN
    rank = a[ok] + np.round((b[ok] - a[ok] - 1) * (q / 100.0)).astype(np.int64)
    ref.flat[np.flatnonzero(ok)] = vs[rank]
    return ref


def _raise_cloudy_bins(ref: np.ndarray, tolerance: float = 0.02) -> np.ndarray:
    """Regions too cloudy for their own envelope take a smooth surface through the clear ones.

    A region that is (almost) all cloud has an envelope at the *cloud's* value, far below its
    neighbours'. A quadratic surface in the bin indices is fitted to the envelopes, starting
    from the upper half of the bins and then keeping those within ``tolerance`` below it or
    above (an upper fit: clear sky is the top of the distribution, and most regions may be
    cloudy); bins below the final surface by more than ``tolerance`` take the surface's value.
    """
    ok = ~np.isnan(ref)
    if ok.sum() < 8:
        return ref
    iu, iv = np.meshgrid(np.arange(ref.shape[0], dtype=np.float64), np.arange(ref.shape[1], dtype=np.float64), indexing="ij")
    su, sv = max(ref.shape[0] - 1, 1), max(ref.shape[1] - 1, 1)
    iu, iv = iu / su, iv / sv
    cols = [np.ones_like(iu), iu, iu * iu] + ([iv, iv * iv, iu * iv] if ref.shape[1] > 1 else [])
    A = np.stack([c[ok] for c in cols], axis=1)
    y = ref[ok]
    keep = y >= np.median(y)  # start from the upper half: with most regions cloudy, the clear ones
    if keep.sum() < A.shape[1] + 2:
        keep = np.ones(len(y), bool)
    for _ in range(6):
        if keep.sum() < A.shape[1] + 2:
            return ref
        coef = np.linalg.lstsq(A[keep], y[keep], rcond=None)[0]
        e = y - A @ coef
        new = e > -tolerance
        if (new == keep).all():
            break
        keep = new
    fit = np.full(ref.shape, np.nan)
    fit[ok] = A @ coef
    low = ok & (ref < fit - tolerance)
    out = ref.copy()
    out[low] = fit[low]
    return out


def _fill_bins(ref: np.ndarray, fallback) -> np.ndarray:
    """Empty bins take the mean of filled neighbours (repeated), then ``fallback()`` (called only
    when some bin is still empty: every bin was)."""
    ref = ref.copy()
    for _ in range(sum(ref.shape)):
        nan = np.isnan(ref)
        if not nan.any() or nan.all():
            break
        p = np.pad(ref, 1, constant_values=np.nan)
        nb = np.stack([p[:-2, 1:-1], p[2:, 1:-1], p[1:-1, :-2], p[1:-1, 2:]])
        cnt = np.sum(~np.isnan(nb), axis=0)
        s = np.nansum(nb, axis=0)
        fill = nan & (cnt > 0)
        ref[fill] = s[fill] / cnt[fill]
    empty = np.isnan(ref)
    if empty.any():
        ref[empty] = fallback()
    return ref


def _interp_bins(ref, u, ue, v, ve):
    """Bilinear interpolation of a bin table between bin centres at every pixel, (H, W) float32."""
    def frac_index(x, e):
        c = 0.5 * (e[:-1] + e[1:])
        return np.interp(x.ravel(), c, np.arange(len(c), dtype=np.float32)).reshape(x.shape).astype(np.float32)

    fu = frac_index(u, ue)
    fv = frac_index(v, ve) if v is not None else np.zeros_like(fu)
    table = np.ascontiguousarray(ref.T if v is not None else ref[:, :1].T, np.float32)  # rows = v, cols = u
    return cv2.remap(table, fu, fv, interpolation=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


def clear_sky_reference(feature, usable, zenith_deg, sun_angle_deg, q: float, image_bgr=None):
    """Upper envelope of a per-pixel feature over regions of the sky, interpolated per pixel.

    Clear sky is the bluest and most saturated thing in the sky (Rayleigh scattering), and its
    colour varies smoothly with the zenith angle and the angle to the sun. So, per region (bins
    of zenith × sun angle when the geometry is known; else zenith-like rings of an all-sky
    image, around a saturated sun if there is one, or a 6 × 6 grid of image blocks), the
    ``q``-th percentile of the feature is the clear-sky value as long as at least 100 − q % of
    the region is clear. Regions far below a smooth surface through the others (all cloud) are
    raised to it; empty ones are filled from their neighbours.

    Returns
    -------
    ref : ndarray, shape (H, W), float32
        Reference value at every pixel (bilinear between region centres).
    """
    return clear_sky_references([feature], usable, zenith_deg, sun_angle_deg, q, image_bgr)[0]


def sample_lattice(n_usable: int) -> tuple[slice, slice]:
    """The regular subsample of an image on which the hybrid's statistics are taken: every
    ``step``-th row and column, so that ``n_usable`` usable pixels give ≈ ``_SAMPLES``."""
    step = max(1, int(math.sqrt(max(int(n_usable), 1) / _SAMPLES)))
    return slice(step // 2, None, step), slice(step // 2, None, step)


def reference_tables(samples, u_s, ue, v_s, ve, q: float) -> list[np.ndarray]:
    """The clear-sky reference of each feature per region, from samples: one (nu, nv) table each
    (nv = 2 repeated columns without a second coordinate), ready for :func:`_interp_bins`.

    ``samples``: the features' values at the sampled usable pixels, ``u_s``/``v_s`` those pixels'
    region coordinates (``v_s`` None: zenith only), ``ue``/``ve`` the bin edges; the host-side half
    of :func:`clear_sky_references`, shared by the torch backend (:mod:`.torch_segment`).
    """
    nu, nv = len(ue) - 1, (len(ve) - 1 if ve is not None else 1)
    bu = np.clip(np.searchsorted(ue, u_s, side="right") - 1, 0, nu - 1)
    bv = np.clip(np.searchsorted(ve, v_s, side="right") - 1, 0, nv - 1) if ve is not None else np.zeros_like(bu)
    out = []
    for fs in samples:
        if fs.size == 0:
            out.append(None)
            continue
        ref = _fill_bins(_raise_cloudy_bins(_bin_reference(fs, bu, bv, nu, nv, q)),
                         lambda fs=fs: float(np.percentile(fs, q)))
        out.append(np.repeat(ref, 2, axis=1) if ve is None else ref)
    return out


def clear_sky_references(features, usable, zenith_deg, sun_angle_deg, q: float, image_bgr=None) -> list[np.ndarray]:
    """:func:`clear_sky_reference` of several (H, W) features sharing one set of regions."""
    H, W = usable.shape
    u, ue, v, ve = _region_coords((H, W), usable, zenith_deg, sun_angle_deg, image_bgr)
    sl = sample_lattice(np.count_nonzero(usable))
    m = usable[sl]
    tables = reference_tables([f[sl][m] for f in features], u[sl][m], ue, v[sl][m] if v is not None else None, ve, q)
    # the references are smooth: interpolate them on a 4× coarser grid, then resize
    c = (slice(0, None, _REF_STRIDE), slice(0, None, _REF_STRIDE))
    us, vs = np.ascontiguousarray(u[c]), (np.ascontiguousarray(v[c]) if v is not None else None)
    out = []
    for ref in tables:
        if ref is None:
            out.append(np.zeros((H, W), np.float32))
            continue
        small = _interp_bins(ref, us, ue, vs, ve)
        out.append(cv2.resize(small, (W, H), interpolation=cv2.INTER_LINEAR))
    return out


def hybrid_classes(rs: np.ndarray, cs: np.ndarray | None, cfg: SegmentationConfig) -> float | None:
    """The hybrid's class decision from samples: the cloud class's typical blue deficit (the
    divisor of the score) when the sky is bimodal, None when it is one class only.

    ``rs``: blue deficits (reference − NBR) of the sampled usable pixels; ``cs``: their chroma
    (None = unknown). Shared by both backends (:mod:`.torch_segment`).
    """
    split = _li_split(rs)
    bimodal = False
    if split is not None:
        t, gap_n, hi_median = split
        bimodal = gap_n >= cfg.min_gap
        if not bimodal and gap_n >= cfg.min_gap / 2 and cs is not None:
            # a pale (hazy, over-exposed) sky: a small blue deficit, but the high class is grey and
            # the low class is not (textured overcast: both classes equally grey)
            c_lo, c_hi = float(np.median(cs[rs <= t])), float(np.median(cs[rs > t]))
            bimodal = c_lo - c_hi >= cfg.chroma_gap and c_hi <= 0.5 * c_lo
    return max(hi_median, cfg.min_gap) if bimodal else None  # blue deficit of typical cloud


def _li_split(rs: np.ndarray) -> tuple[float, float, float] | None:
    """Li's threshold of the sampled blue deficits ``rs``, the gap between its classes (the upper
    class's median deficit less the lower's, floored at 0: the clear sky's own deficit is ≈ 0,
    and a lower class far below 0 is a tail of one broad class, not clear sky) and the upper
    class's median. None when either class holds under 2 % of the samples."""
    t = li_threshold(rs)
    lo, hi = rs[rs <= t], rs[rs > t]
    if lo.size < 0.02 * rs.size or hi.size < 0.02 * rs.size:
        return None
    hi_median = float(np.median(hi))
    return t, hi_median - max(float(np.median(lo)), 0.0), hi_median


def faint_cloud_on_blue(rs: np.ndarray, nbr_s: np.ndarray, cfg: SegmentationConfig) -> bool:
    """A one-class sky (:func:`hybrid_classes` None) that is blue sky with faint cloud on it: its
    sampled median NBR reaches ``fixed_threshold`` (more than half of it bluer than grey cloud
    under the usual casts) and its blue deficits ``rs`` split into classes at least half of
    ``min_gap`` apart (a cloud class that stands out, if less than a full ``min_gap``). The hybrid
    then takes as cloud only what stands out from the clear sky, textured or not: fine high
    cloud, downsampled, keeps under ``min_gap`` (randomized 17087 at 480 px: a speckled 7653 m
    deck of cover 0.23, classes 0.053 apart, median NBR 0.23, local contrast 0.13, was read as one
    cloud, cf 1.0, with a phantom 583 m layer in the horizon's haze; now cf 0.17, 7679 m alone).
    An overcast under a strong blue cast is as blue (NBR ≈ 0.19 at white balance 0.85 / 1.25) but
    one class: its deficits split 0.012 apart, and it stays cloud."""
    if nbr_s.size == 0 or float(np.median(nbr_s)) < cfg.fixed_threshold:
        return False
    split = _li_split(rs)
    return split is not None and split[1] >= cfg.min_gap / 2


def one_class_is_clear(nbr_s: np.ndarray, contrast_s, cfg: SegmentationConfig, chroma_s=None,
                       whitening: float | None = None) -> bool:
    """One class only (the hybrid-thresholding idea: no threshold from a unimodal histogram): a
    clear sky when the sky is blue — the sampled median NBR at least ``fixed_threshold``, or
    (pale, hazy or warm-cast cameras, whose clear sky can sit at NBR 0.13) its median chroma
    ``chroma_s`` at least ``clear_chroma``: grey cloud keeps ≈ 0.03–0.1 under the same casts —,
    or it whitens towards the horizon as only clear sky does (``whitening``,
    :func:`horizon_whitening`, at least :data:`HORIZON_WHITENING`) — and smooth
    (``contrast_s()``: the sampled local contrast, called only then; None = no image); else
    overcast. Chroma and whitening count only for a sky bluer than red (median NBR at least
    :data:`CLEAR_MIN_NBR`): a warm cast's chroma is red's, and grey cloud under a +10 % warm cast
    with gamma 1.25 reaches 1 − (0.9/1.1)^1.25 ≈ 0.22 (randomized 16947, 960 px: an overcast
    303 m deck at NBR −0.12, chroma 0.21, read clear sky by both cameras)."""
    nbr_median = float(np.median(nbr_s))
    blue = nbr_median >= cfg.fixed_threshold
    if not blue and chroma_s is not None and chroma_s.size and nbr_median >= CLEAR_MIN_NBR:
        blue = float(np.median(chroma_s)) >= cfg.clear_chroma
    if not blue and whitening is not None and nbr_median >= CLEAR_MIN_NBR:
        blue = whitening >= HORIZON_WHITENING
    if not blue:
        return False
    return contrast_s is None or float(np.median(contrast_s())) < cfg.texture_cv


#: A one-class sky whose NBR falls by this much from mid-sky to the horizon, away from the sun, is
#: clear sky (:func:`horizon_whitening`) [1]. Clear sky whitens towards the horizon: its light
#: there has crossed several air masses and been scattered many times, which greys Rayleigh's blue
#: (and haze, which lies low, greys it more). An overcast deck does not: its light is grey wherever
#: it comes from, and the air between the camera and the far deck adds blue (aerial perspective),
#: so the horizon is as blue or bluer. Randomized skies at 480 px, mounted cameras, skylines
#: unmasked, twice-encoded (`--seed 18310`, 60 clear and 60 overcast, both cameras): every
#: overcast −0.070 … +0.001; clear skies +0.026 … +0.141 save two pale cameras (−0.012, +0.009)
#: whose pairs the other camera decided; the pale clear skies called overcast before (18358,
#: 18360, 18361: NBR 0.09–0.11, chroma 0.17–0.19, smooth) +0.046 … +0.078.
HORIZON_WHITENING = 0.03
_WHITENING_MID_DEG = (30.0, 55.0)  # mid-sky band of zenith angles [deg]
_WHITENING_LOW_DEG = (65.0, 80.0)  # horizon band [deg]
_WHITENING_SUN_DEG = 45.0  # both bands only this far from the sun (its aureole whitens any sky) [deg]
_WHITENING_MIN_SAMPLES = 200  # samples each band needs


def horizon_whitening(nbr_s: np.ndarray, zenith_s: np.ndarray | None, sun_s: np.ndarray | None) -> float | None:
    """How much a sky's NBR falls from mid-sky to the horizon: the median NBR of the sampled pixels
    at zenith 30–55° less that at 65–80°, both at least 45° from the sun (:data:`HORIZON_WHITENING`).

    ``nbr_s``, ``zenith_s``, ``sun_s``: the same sampled usable pixels' NBR, zenith angle and angle
    to the sun [deg]. None without geometry, or where either band has under 200 samples (a
    horizon hidden by obstacles, a sun that fills the sky)."""
    if zenith_s is None or sun_s is None or nbr_s.size == 0:
        return None
    far = sun_s >= _WHITENING_SUN_DEG
    mid = far & (zenith_s >= _WHITENING_MID_DEG[0]) & (zenith_s < _WHITENING_MID_DEG[1])
    low = far & (zenith_s >= _WHITENING_LOW_DEG[0]) & (zenith_s < _WHITENING_LOW_DEG[1])
    if np.count_nonzero(mid) < _WHITENING_MIN_SAMPLES or np.count_nonzero(low) < _WHITENING_MIN_SAMPLES:
        return None
    return float(np.median(nbr_s[mid]) - np.median(nbr_s[low]))


def one_class_pair_is_clear(taken, usables, cfg: SegmentationConfig) -> bool:
    """Both cameras of a pair call their sky one cloud: whether it is a clear sky all the same.

    ``taken``: the two images as the cameras took them, before the photometric step maps one
    onto the other's response; ``usables``: their usable sky. A camera's colour response can
    make a clear sky pale (red up, blue down, gamma: raw median NBR ≈ 0.1, like grey cloud
    under a bluish cast), and mapping the bluer camera onto the paler one makes both pale. The
    response does not make grey cloud blue: white-balance casts of ±10 % and gammas 0.8–1.25
    lift it to NBR ≈ (1.1/0.9)^1.25 → 0.125 (randomized overcasts: at most 0.118), so a sky
    whose median NBR reaches ``fixed_threshold`` (0.15) *as taken* in either camera is blue
    sky; chroma is no cue here (grey cloud under a bluish cast reaches 0.21). And both cameras
    must see it smooth (median local contrast < ``texture_cv``; a textured sky is cloud,
    whatever its colour): a thin uniform overcast is smooth too, so colour decides.
    """
    samples = []
    for image, usable in zip(taken, usables):
        sl = sample_lattice(np.count_nonzero(usable))
        u = usable[sl]
        if not u.any():
            return False
        samples.append((image, sl, u))
    if max(float(np.median(normalized_blue_red(im[sl])[u])) for im, sl, u in samples) < cfg.fixed_threshold:
        return False
    return all(float(np.median(local_contrast(im)[sl][u])) < cfg.texture_cv for im, sl, u in samples)


_AUREOLE_MAX_DEG = 40.0  # the circumsolar aureole's profile is followed out to this angle from the sun [deg]
_AUREOLE_STEP_DEG = 1.5  # ring width of the aureole profile [deg]
_AUREOLE_MIN_RING = 30  # a ring needs this many sampled pixels for its own value


_TEXTURE_SIGMA_PX = 1.5  # fine texture: the grey image less its Gaussian blur of this sigma [px]
_TEXTURE_BOX_PX = 9  # … its RMS over boxes of this side [px]
_TEXTURED = 4.0  # a ring whose clearest pixels have this × the image's noise floor of fine texture is cloud (simulated: aureole ≤ 3.7, fog around the sun ≥ 4.3)


#: Clear sky is bluer than it is red (Rayleigh scattering: NBR 0.2–0.3 on a neutral camera) in
#: any camera whose white balance is off by less than ±10 %: the warmest clear sky of the
#: labelled simulated set (a warm over-exposed camera) reads 0.07; grey cloud under such a warm
#: cast reads down to −0.125, the mirror of a bluish cast's +0.125 (:func:`one_class_pair_is_clear`).
CLEAR_MIN_NBR = 0.0
#: A two-class split's clear class that is textured is clear sky only where its bluest tenth reaches
#: this NBR (:func:`clear_class_is_sky`; bluer than red, 0, until stop 66). Cloud far off takes the
#: airlight's blue, and a near-overcast sky whose regions hold no clear sky of their own has its
#: regions' reference at the cloud's colour, so the split calls a shade of the cloud clear.
#: Randomized dense skies at 480 px (80 skies): every textured clear class whose bluest tenth lay
#: under 0.1 (−0.02 … 0.094, 8 cameras) was cloud, the pair's true cloud 0.92–0.98 read as 0.38–0.88
#: (17716's overcast split from its unmasked facades: 0.068). Clear sky is bluer: the textured clear
#: classes of the labelled simulated set (four colour responses, a warm over-exposed one among
#: them) reach 0.24 and more, those of 40 randomized broken skies (480 px, skylines unmasked) 0.14
#: and more, the real Fehmarn hour's 0.18 and more (smooth).
TEXTURED_CLEAR_MIN_NBR = 0.1


def fine_texture(image_bgr: np.ndarray) -> np.ndarray:
    """RMS of the grey image's fine detail (less its σ = 1.5 px blur) in 9 px boxes, (H, W) float32 [DN].

    Clear sky, the aureole and haze are smooth: their fine detail is sensor and JPEG noise
    (its floor over the image). Cloud has detail at every scale.
    """
    g = cv2.cvtColor(image_bgr, cv2.COLOR_BGR2GRAY).astype(np.float32)
    hp = cv2.subtract(g, cv2.GaussianBlur(g, (0, 0), _TEXTURE_SIGMA_PX))
    # (where the detail is flat, the box filter's running sums can leave −1e-6 under the root: NaN there, and a
    # NaN among a ring's samples or the floor's leaves aureole_profile's texture test unmet. Flooring it at 0
    # turns the test on for such images, and then the steep aureole within 6° of the sun reads 5–13 × the
    # floor (randomized 9119, JPEG 66: camera 2's cloud 0.14 → 0.24 for 0.145 true); left as it was measured)
    return cv2.sqrt(cv2.blur(cv2.multiply(hp, hp), (_TEXTURE_BOX_PX, _TEXTURE_BOX_PX)))


class _LazyTexture:
    """:func:`fine_texture` of an image, computed on the first call and kept."""

    def __init__(self, image_bgr):
        self.image, self.value = image_bgr, None

    def __call__(self) -> np.ndarray:
        if self.value is None:
            self.value = fine_texture(self.image)
        return self.value


def ring_value_order(ring: np.ndarray, values: np.ndarray) -> np.ndarray:
    """``np.lexsort((values, ring))`` (by ring, then value; ties in their order) for rings 0 … 2³¹
    and float32 values, in one sort of 64-bit keys (ring above, the value's bits below, mapped so
    that their unsigned order is the float order: −0 as +0, NaN last): 2–3× faster. Other value
    types (float64 would lose its order in 32 bits) go to ``np.lexsort`` itself."""
    if np.asarray(values).dtype != np.float32 or np.asarray(ring).dtype.kind not in "iu":
        return np.lexsort((values, ring))
    v = np.ascontiguousarray(values, np.float32) + np.float32(0.0)  # −0 → +0 (lexsort: equal)
    bits = v.view(np.uint32).astype(np.uint64)
    neg = (bits >> np.uint64(31)).astype(bool)
    bits = np.where(neg, ~bits & np.uint64(0xFFFFFFFF), bits | np.uint64(0x80000000))
    bits[np.isnan(v)] = np.uint64(0xFFFFFFFF)
    return np.argsort((np.asarray(ring).astype(np.uint64) << np.uint64(32)) | bits, kind="stable")


def aureole_profile(values_s: np.ndarray, sun_angle_s: np.ndarray, q: float,
                    texture_s: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray] | None:
    """The clear sky's excess of a cloud-like feature in rings around the sun (the aureole).

    The circumsolar aureole is whiter and brighter than any region's reference: its blue
    deficit (and brightness) rises steeply and smoothly towards the sun, faster than the
    zenith × sun-angle regions can follow. Per ring of ``_AUREOLE_STEP_DEG`` out to
    ``_AUREOLE_MAX_DEG``, the ``q``-th percentile of the feature over the sampled pixels (the
    clear part of the ring as long as ``q`` % of it is clear), floored at 0 and made
    non-increasing outwards (the aureole fades monotonically from the sun; a cloudy ring
    farther out cannot raise it), is the aureole's own value. With ``texture_s`` (the samples'
    :func:`fine_texture`, or a callable giving them when first needed), a ring whose pixels
    at or below that percentile are textured (median over ``_TEXTURED`` × the noise floor, the 10th percentile of all samples) is
    cloud, not aureole: its excess, and so that of every ring outside it, is 0 (sunlit cloud
    around the sun is never taken for the aureole).

    Returns
    -------
    (centres_deg, excess) : two ndarrays (n,), float32, or None when no ring has an excess
        Ring centres [deg] and the excess to subtract there (0 beyond the last ring).
    """
    edges = np.arange(0.0, _AUREOLE_MAX_DEG + _AUREOLE_STEP_DEG, _AUREOLE_STEP_DEG)
    n_rings = len(edges) - 1
    k = np.searchsorted(edges, sun_angle_s, side="right") - 1
    inside = (k >= 0) & (k < n_rings)
    order = np.flatnonzero(inside)[ring_value_order(k[inside], values_s[inside])]  # by ring, then value
    ks, vs = k[order], values_s[order]
    bounds = np.searchsorted(ks, np.arange(n_rings + 1))
    prof = np.zeros(n_rings)
    floor, tex_sorted, started = 0.0, None, False
    for i in range(n_rings):
        a, b = int(bounds[i]), int(bounds[i + 1])
        if b - a < _AUREOLE_MIN_RING:
            prof[i] = prof[i - 1] if (started and i) else 0.0  # inside the masked sun disk, or a gap
            continue
        rank = a + int(round((b - a - 1) * q / 100.0))  # nearest-rank percentile of the sorted ring
        prof[i] = max(float(vs[rank]), 0.0)
        if texture_s is not None and prof[i] > 0.0:
            if tex_sorted is None:  # computed on first need (most rings of most skies have no excess)
                tex = texture_s() if callable(texture_s) else texture_s
                floor = max(float(np.percentile(tex, 10.0)), 0.5) if tex.size else 0.0
                tex_sorted = tex[order]
            if float(np.median(tex_sorted[a:rank + 1])) > _TEXTURED * floor:
                prof[i] = 0.0
        if started:
            prof[i] = min(prof[i], prof[i - 1])
        started = True
    if not prof.any():
        return None
    prof = np.append(prof, 0.0)
    centres = np.append(0.5 * (edges[:-1] + edges[1:]), edges[-1] + _AUREOLE_STEP_DEG)
    return centres.astype(np.float32), prof.astype(np.float32)


PROFILE_STEPS_PER_DEG = 4  # the aureole excess is looked up per quarter degree of sun angle (0 … 63.75°)


def profile_table(profile) -> np.ndarray:
    """The aureole excess (:func:`aureole_profile`) per quarter degree of sun angle, (256,) float32:
    linear between ring centres, the innermost value inside, 0 beyond the last ring."""
    c, p = profile
    return np.interp(np.arange(256) / PROFILE_STEPS_PER_DEG, c, p, left=p[0], right=0.0).astype(np.float32)


def apply_profile(sun_angle_deg: np.ndarray, profile) -> np.ndarray:
    """The aureole excess (:func:`aureole_profile`) at every pixel, (H, W) float32 (0 beyond): a
    lookup of :func:`profile_table` at the sun angle rounded to a quarter degree (the rings
    are 1.5° wide; one lookup instead of an interpolation per pixel)."""
    a = np.asarray(sun_angle_deg, np.float32)
    idx = cv2.convertScaleAbs(a, alpha=float(PROFILE_STEPS_PER_DEG))  # rounded, saturated at 255
    return cv2.LUT(idx, profile_table(profile))


def _minus_aureole(feature, feature_s, sun_angle_s, sun_angle_deg, q: float, texture_s=None):
    """``feature`` less the aureole's excess (:func:`aureole_profile` of its samples)."""
    prof = aureole_profile(feature_s, sun_angle_s, q, texture_s)
    if prof is None:
        return feature
    return cv2.subtract(feature, apply_profile(sun_angle_deg, prof))


def _hybrid(nbr, usable, zenith_deg, sun_angle_deg, cfg: SegmentationConfig, chroma=None, image_bgr=None,
            sky_clear: bool = False):
    """Per-image, per-region adaptive segmentation (see the module docstring, ``hybrid``).

    ``sky_clear``: the other camera of the pair sees this sky clear (:meth:`Pipeline.stage_segment`):
    one class, or a clear class no clear sky could be, is then this camera's pale or colour-cast
    rendering of clear sky, and only what stands out from it is cloud (never the whole sky)."""
    if not usable.any():
        return np.zeros_like(usable)
    refs = clear_sky_references([nbr] if chroma is None else [nbr, chroma], usable, zenith_deg, sun_angle_deg,
                                cfg.clear_percentile, image_bgr)
    ref_n = refs[0]
    r_n = cv2.subtract(ref_n, nbr)  # blue deficit against the clear sky of the same region
    if chroma is not None:
        ref_s = refs[1]
        r_s = cv2.divide(cv2.subtract(ref_s, chroma), cv2.max(ref_s, 0.02))  # relative desaturation
    else:
        r_s = None
    # class statistics on a regular subsample of the usable sky (≈ _SAMPLES pixels)
    sub = sample_lattice(np.count_nonzero(usable))
    us = usable[sub]
    if sun_angle_deg is not None and us.any():  # the aureole is clear sky: its own excess removed
        psi_s = np.asarray(sun_angle_deg, np.float32)[sub][us]
        tex = _LazyTexture(image_bgr)
        tex_s = (lambda: tex()[sub][us]) if image_bgr is not None else None
        r_n = _minus_aureole(r_n, r_n[sub][us], psi_s, sun_angle_deg, 100.0 - cfg.clear_percentile, tex_s)
        if r_s is not None:
            r_s = _minus_aureole(r_s, r_s[sub][us], psi_s, sun_angle_deg, 100.0 - cfg.clear_percentile, tex_s)
    rs = r_n[sub][us]
    if rs.size == 0:
        return np.zeros_like(usable)
    gap = hybrid_classes(rs, chroma[sub][us] if chroma is not None else None, cfg)
    if gap is None:  # one class only: the whole usable sky is clear or cloud
        contrast = None if image_bgr is None else (lambda: local_contrast(image_bgr)[sub][us])
        nbr_s = nbr[sub][us]
        white = None if zenith_deg is None or sun_angle_deg is None else horizon_whitening(
            nbr_s, np.asarray(zenith_deg)[sub][us], np.asarray(sun_angle_deg)[sub][us])
        if not sky_clear and not faint_cloud_on_blue(rs, nbr_s, cfg) and not one_class_is_clear(
                nbr_s, contrast, cfg, chroma[sub][us] if chroma is not None else None, white):
            return usable.copy()
        score = cv2.divide(r_n, cfg.min_gap * 2.0)  # clear: only what stands out from the clear sky
    else:
        score = cv2.divide(r_n, gap)
    if r_s is not None:
        score = cv2.addWeighted(score, 1.0 - cfg.chroma_weight, r_s, cfg.chroma_weight, 0.0)
    cloud = cv2.compare(score, cfg.score_threshold, cv2.CMP_GT) > 0
    if gap is not None and image_bgr is not None and cfg.brightness_weight > 0:
        # brightness cue: cloud is brighter (sunlit, thin) or darker (thick base) than the clear
        # sky of the same region, which the first pass found; exposure cancels in the ratio
        b, g, r = cv2.split(image_bgr)
        value = cv2.max(cv2.max(b, g), r).astype(np.float32)
        clear = usable & ~cloud
        if np.count_nonzero(clear) >= BRIGHTNESS_MIN_CLEAR * np.count_nonzero(usable):
            v_ref = clear_sky_references([value / 255.0], clear, zenith_deg, sun_angle_deg, 50.0, image_bgr)[0]
            dv = cv2.subtract(cv2.log(cv2.max(value, 1.0)), cv2.log(cv2.max(v_ref * 255.0, 1.0)))
            if sun_angle_deg is not None:  # the aureole's brightening, from the clear pixels around the sun
                cs_ = clear[sub]
                dv = _minus_aureole(dv, dv[sub][cs_], np.asarray(sun_angle_deg, np.float32)[sub][cs_],
                                    sun_angle_deg, 50.0, lambda: tex()[sub][cs_])
            dv = cv2.absdiff(dv, 0.0)
            score = cv2.addWeighted(score, 1.0, dv, cfg.brightness_weight / math.log(1.5), 0.0)
            cloud = cv2.compare(score, cfg.score_threshold, cv2.CMP_GT) > 0
    cloud &= usable
    if gap is not None and not sky_clear:
        clear = (usable & ~cloud)[sub]
        contrast = None if image_bgr is None else (lambda: local_contrast(image_bgr)[sub][clear])
        if not clear_class_is_sky(nbr[sub][clear], contrast, cfg):
            return usable.copy()
    return cloud


def clear_class_is_sky(nbr_clear: np.ndarray, contrast_clear, cfg: SegmentationConfig) -> bool:
    """Whether what a two-class split left clear can be clear sky: some of it bluer than grey cloud
    can be (the bluest tenth at NBR ≥ :data:`TEXTURED_CLEAR_MIN_NBR`), or smooth (median local
    contrast under ``texture_cv``).

    The split is relative (each region's bluest pixels are its clear-sky reference), so on an
    overcast whose cloud comes in two shades it calls the bluer shade clear. A clear class with
    no blue part that is also textured is cloud, and so is the whole sky (randomized sky 9570 at
    480 px: a textured warm-cast overcast whose "clear" class had its bluest tenth at NBR −0.02
    and a local contrast of 0.06, read 5 % cloud). The bluest tenth, not the median: a clear
    class that mixes blue gaps with a shade of cloud taken for clear has its median near 0
    (randomized 9564, median −0.003, bluest tenth 0.37). Texture alone does not tell (the
    clear gaps of a broken sky lie near cloud edges: median contrast 0.03–0.06 in the labelled
    simulated set), nor does chroma (0.13 for that overcast and for a warm over-exposed
    camera's clear sky).

    A textured clear class needs more than bluer than red: distant cloud takes the airlight's
    blue (aerial perspective), and the regions of a near-overcast sky whose only clear-sky
    reference is their own cloud split a shade of it off as clear (:data:`TEXTURED_CLEAR_MIN_NBR`).

    ``nbr_clear``: the sampled NBR of the clear class; ``contrast_clear``: a callable giving the
    same pixels' local contrast (called only when the colour does not decide; None: no image,
    no judgement). Both backends call this on the same sampling lattice.
    """
    if nbr_clear.size == 0 or contrast_clear is None:
        return True
    bluest = float(np.percentile(nbr_clear, 90))
    return bluest >= TEXTURED_CLEAR_MIN_NBR or float(np.median(contrast_clear())) < cfg.texture_cv


SEGMENTERS = {"hybrid": _hybrid, "nbr": _nbr, "nbr_adaptive": _nbr_adaptive, "otsu": _otsu}


def get_segmenter(name: str):
    """The segmentation function registered as ``name`` (case-insensitive)."""
    try:
        return SEGMENTERS[name.lower()]
    except KeyError:
        raise ConfigError(f"unknown segmentation method {name!r} (valid: {', '.join(SEGMENTERS)})") from None


def check_colour(image, what: str = "image") -> None:
    """Raise :class:`~cbh.errors.ImageError` unless ``image`` is a colour (H, W, 3) uint8 image."""
    a = image
    if not isinstance(a, np.ndarray) or a.dtype != np.uint8 or a.ndim not in (2, 3):
        raise ImageError(f"{what}: expected a BGR uint8 (H, W, 3) image, got {getattr(a, 'shape', type(a).__name__)}")
    if is_greyscale(a):
        raise ImageError(f"{what}: greyscale image; segmentation needs colour (clear sky and cloud differ by "
                         "their blue-red ratio)")
    if a.ndim != 3 or a.shape[2] != 3:
        raise ImageError(f"{what}: expected 3 colour channels, got shape {a.shape}")


def local_contrast(image_bgr: np.ndarray, window_px: int = 7) -> np.ndarray:
    """Local standard deviation / local mean of the grey image in a box, (H, W) float32."""
    g = cv2.cvtColor(image_bgr, cv2.COLOR_BGR2GRAY).astype(np.float32)
    k = (window_px, window_px)
    m = cv2.blur(g, k)
    var = cv2.subtract(cv2.blur(cv2.multiply(g, g), k), cv2.multiply(m, m))
    return cv2.divide(cv2.sqrt(cv2.max(var, 0.0)), cv2.max(m, 1.0))


def segment(image_bgr, usable, zenith_deg, sun_angle_deg, cfg: SegmentationConfig,
            what: str = "image", sky_clear: bool = False) -> tuple[np.ndarray, float]:
    """Cloud mask (H, W) bool and cloud fraction of the usable sky (0..1, 0 if none usable).

    Parameters
    ----------
    image_bgr : ndarray, shape (H, W, 3), uint8
        Colour image (a greyscale one raises :class:`~cbh.errors.ImageError`).
    usable : ndarray, shape (H, W), bool
        Sky that may be classified.
    zenith_deg, sun_angle_deg : ndarray, shape (H, W), float32, or None
        Zenith angle and angle to the sun of each pixel [deg]; None = unknown (no geometry:
        ``hybrid`` then uses image regions, ``nbr_adaptive`` no horizon ramp).
    cfg : SegmentationConfig
    what : str
        Name of the image in error messages.
    sky_clear : bool
        The other camera of the pair sees this sky clear: ``hybrid`` then never calls the whole
        sky one cloud (see :func:`_hybrid`); the other methods have no such decision.

    Images larger than ``cfg.max_side_px`` on their long side are classified area-averaged
    to that size (less sensor and JPEG noise per pixel, and fast on 24-megapixel frames) and
    the mask is brought back to full size.
    """
    check_colour(image_bgr, what)
    H, W = image_bgr.shape[:2]
    if cfg.max_side_px and max(H, W) > cfg.max_side_px:  # classify area-averaged, bring the mask back
        f = cfg.max_side_px / max(H, W)
        size = (max(1, round(W * f)), max(1, round(H * f)))
        small = cv2.resize(image_bgr, size, interpolation=cv2.INTER_AREA)
        u = cv2.resize(usable.view(np.uint8), size, interpolation=cv2.INTER_NEAREST) > 0
        rs = lambda a: None if a is None else cv2.resize(np.asarray(a, np.float32), size, interpolation=cv2.INTER_LINEAR)  # noqa: E731
        c, _ = segment(small, u, rs(zenith_deg), rs(sun_angle_deg), cfg, what, sky_clear)
        cloud = cv2.resize(c.view(np.uint8), (W, H), interpolation=cv2.INTER_NEAREST) > 0
        b, g, r = cv2.split(image_bgr)
        usable = usable & (cv2.max(cv2.max(b, g), r) >= cfg.min_brightness)
        cloud &= usable
        n = int(np.count_nonzero(usable))
        return cloud, (float(np.count_nonzero(cloud)) / n if n else 0.0)
    b, g, r = cv2.split(image_bgr)  # once: NBR, chroma and brightness share the channels
    s = cv2.add(b, r, dtype=cv2.CV_32F)
    nbr = cv2.divide(cv2.subtract(b, r, dtype=cv2.CV_32F), cv2.max(s, 1.0))
    mx = cv2.max(cv2.max(b, g), r)
    mn = cv2.min(cv2.min(b, g), r)
    chr_ = cv2.divide(cv2.subtract(mx, mn, dtype=cv2.CV_32F), cv2.max(mx, 1).astype(np.float32))
    usable = usable & (mx >= cfg.min_brightness)
    more = {"sky_clear": True} if sky_clear and get_segmenter(cfg.method) is _hybrid else {}
    cloud = get_segmenter(cfg.method)(nbr, usable, zenith_deg, sun_angle_deg, cfg, chroma=chr_, image_bgr=image_bgr,
                                      **more)
    n = int(np.count_nonzero(usable))
    return cloud, (float(np.count_nonzero(cloud)) / n if n else 0.0)
