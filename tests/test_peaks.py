"""The one peak finder (cbh/pipeline/peaks.py) used by the layer histogram and the plane sweep."""
from __future__ import annotations

import numpy as np
import pytest

from cbh.pipeline.peaks import find_peaks, peak_extent, smooth_gaussian, valley_cuts


def test_two_separated_peaks_and_their_valley():
    v = np.array([0, 1, 5, 9, 5, 1, 0, 2, 6, 3, 0], float)
    p = find_peaks(v, 0.0, 0.5)
    assert p == [3, 8]
    assert valley_cuts(v, p) == [6]
    assert peak_extent(v, 3, 0.5) == (2, 4)  # bins ≥ 4.5 falling away from the peak


def test_shallow_valley_merges_weakest_first_and_separation():
    v = np.array([0, 10, 7, 8, 7, 9, 0], float)  # three maxima, valleys 7 > 0.5 × 8
    assert find_peaks(v, 0.0, 0.5) == [1]
    w = np.array([0, 10, 0, 0, 8, 0], float)
    assert find_peaks(w, 0.0, 0.5) == [1, 4]
    assert find_peaks(w, 0.0, 0.5, min_separation=4) == [1]  # closer than 4 bins: one peak
    assert find_peaks(w, 9.0, 0.5) == [1]  # below min_height
    assert find_peaks(np.zeros(5), 0.0, 0.5) == []


@pytest.mark.parametrize("sigma", [0.5, 1.0, 4.0, 20.0])
def test_smoothing_equals_scipy(sigma):
    ndimage = pytest.importorskip("scipy.ndimage")
    v = np.random.default_rng(0).random(50)
    assert np.allclose(smooth_gaussian(v, sigma), ndimage.gaussian_filter1d(v, sigma, mode="constant"), atol=1e-12)
