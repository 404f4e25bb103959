"""The components helper (cbh.pipeline.ccl) is OpenCV's own call with another algorithm: the same
labels, areas, boxes and centroids, so every mask built on it is unchanged."""
import cv2
import numpy as np
import pytest

from cbh.pipeline.ccl import components_with_stats


@pytest.mark.parametrize("seed", range(40))
def test_same_components_as_opencvs_default(seed):
    rng = np.random.default_rng(seed)
    h, w = rng.integers(3, 260, 2)
    m = (rng.random((h, w)) < rng.uniform(0.03, 0.7)).astype(np.uint8)
    if seed % 2:  # blobs as well as speckle
        m = cv2.dilate(m, np.ones((3, 3), np.uint8))
    if seed % 5 == 0:  # a strided view, as the saturation mask passes
        m = m[1:, 2:]
    want = cv2.connectedComponentsWithStats(m, connectivity=8)
    got = components_with_stats(m)
    assert got[0] == want[0]
    for a, b in zip(got[1:], want[1:]):
        assert a.dtype == b.dtype and np.array_equal(a, b, equal_nan=a.dtype.kind == "f")  # (an empty background: NaN)


def test_empty_and_full():
    for m in (np.zeros((7, 9), np.uint8), np.ones((7, 9), np.uint8)):
        n, lab, stats, _ = components_with_stats(m)
        assert n == 1 + int(m.any()) and stats[:, cv2.CC_STAT_AREA].sum() == m.size
