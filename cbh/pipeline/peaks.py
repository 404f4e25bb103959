"""The one peak finder of 1-D histograms (layer heights in :mod:`.layers`, plane votes in :mod:`.sweep`).

A peak is a local maximum (a plateau counts once, at its first index) with a positive value of
at least ``min_height``. Two neighbouring peaks are one when they are closer than
``min_separation`` bins or when the histogram between them does not dip below
``valley_ratio`` × the lower of the two; such pairs are merged weakest first (the pair whose
lower peak is smallest; the higher peak survives), so the result does not depend on the
direction of the scan. Each surviving peak either owns the bins between the valleys on either
side (:func:`valley_cuts`) or the run of bins around it that stay above a fraction of it and
fall monotonically away from it (:func:`peak_extent`). And the weighted median of a 1-D sample
(:func:`weighted_median`), the middle of its weighted histogram.
"""
from __future__ import annotations

import numpy as np

__all__ = ["find_peaks", "valley_cuts", "peak_extent", "smooth_gaussian", "weighted_median"]


def find_peaks(values: np.ndarray, min_height: float = 0.0, valley_ratio: float = 0.5,
               min_separation: float = 0.0) -> list[int]:
    """Indices of the peaks of a histogram, ascending.

    Parameters
    ----------
    values : ndarray, shape (N,), float
        The (smoothed) histogram.
    min_height : float
        A peak has at least this value (and more than 0).
    valley_ratio : float
        Neighbouring peaks stay apart only where the minimum between them is at most this ×
        the lower peak.
    min_separation : float
        Neighbouring peaks closer than this [bins] are merged.

    Returns
    -------
    list of int
    """
    v = np.asarray(values, np.float64)
    if v.size == 0:
        return []
    left = np.concatenate([[-np.inf], v[:-1]])
    right = np.concatenate([v[1:], [-np.inf]])
    peaks = [int(i) for i in np.flatnonzero((v > left) & (v >= right) & (v > 0) & (v >= min_height))]
    while len(peaks) > 1:
        weakest = None
        for i in range(len(peaks) - 1):
            a, b = peaks[i], peaks[i + 1]
            low = min(v[a], v[b])
            if (b - a) < min_separation or v[a: b + 1].min() > valley_ratio * low:
                if weakest is None or low < weakest[0]:
                    weakest = (low, i)
        if weakest is None:
            break
        i = weakest[1]
        a, b = peaks[i], peaks[i + 1]
        peaks.pop(i + 1 if v[a] >= v[b] else i)
    return peaks


def valley_cuts(values: np.ndarray, peaks: list[int]) -> list[int]:
    """Index of the lowest bin between each pair of neighbouring peaks (first of equal lows).

    The bins ``[0, c0]``, ``[c0 + 1, c1]`` … ``[c_last + 1, N − 1]`` then tile the histogram,
    one range per peak.
    """
    v = np.asarray(values, np.float64)
    return [a + int(np.argmin(v[a: b + 1])) for a, b in zip(peaks[:-1], peaks[1:])]


def peak_extent(values: np.ndarray, peak: int, ratio: float) -> tuple[int, int]:
    """Bins ``[lo, hi]`` around ``peak`` that stay ≥ ``ratio`` × the peak and fall away from it."""
    v = np.asarray(values, np.float64)
    lo = hi = int(peak)
    while lo > 0 and ratio * v[peak] <= v[lo - 1] <= v[lo]:
        lo -= 1
    while hi < len(v) - 1 and ratio * v[peak] <= v[hi + 1] <= v[hi]:
        hi += 1
    return lo, hi


def smooth_gaussian(values: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian smoothing of a 1-D histogram with zeros outside, float64 (scipy's
    ``gaussian_filter1d(values, sigma, mode="constant")`` with its 4 σ truncation; no scipy import).
    ``sigma`` ≤ 0: the values unchanged."""
    v = np.asarray(values, np.float64)
    if sigma <= 0:
        return v
    r = int(4.0 * sigma + 0.5)
    x = np.arange(-r, r + 1, dtype=np.float64)
    k = np.exp(-0.5 * (x / sigma) ** 2)
    out = np.convolve(v, k / k.sum(), mode="full")  # "same" centres wrongly when the kernel is longer
    return out[r: r + len(v)]


def weighted_median(v: np.ndarray, w: np.ndarray) -> float:
    """The value of ``v`` (N,) at which the cumulative weight ``w`` (N,), in ascending ``v``,
    first reaches half the total (the lower weighted median)."""
    o = np.argsort(v, kind="stable")
    cw = np.cumsum(w[o])
    return float(v[o][np.searchsorted(cw, 0.5 * cw[-1])])
