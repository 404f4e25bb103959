"""Triangulation: closest approach vs. the paper's SVD, backends and dtypes, validity, the drone experiment."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from cbh.geometry.triangulate import TriangulationLimits, triangulate, triangulate_svd, triangulate_svd_loop


def random_scene(n, seed=0, baseline=50.0):
    rng = np.random.default_rng(seed)
    o1 = np.zeros(3)
    o2 = np.array([baseline, 10.0, 1.0])
    pts = np.column_stack([rng.uniform(-5000, 5000, n), rng.uniform(-5000, 5000, n), rng.uniform(300, 9000, n)])
    return o1, pts - o1, o2, pts - o2, pts


def test_exact_rays_meet_at_the_point():
    o1, d1, o2, d2, pts = random_scene(1000)
    t = triangulate(o1, d1, o2, d2)
    np.testing.assert_allclose(t.point_m, pts, rtol=1e-9, atol=1e-6)
    np.testing.assert_allclose(t.height_m, pts[:, 2], rtol=1e-9)
    assert t.miss_m.max() < 1e-6 and t.valid.all()
    np.testing.assert_allclose(t.range1_m, np.linalg.norm(d1, axis=1), rtol=1e-9)


def test_miss_distance_is_the_common_perpendicular():
    # ray 1 along +x at z=0; ray 2 along +y offset by 3 m in z: they miss by exactly 3 m
    t = triangulate(np.array([0.0, 0, 0]), np.array([[1.0, 0, 0]]), np.array([5.0, -5, 3]), np.array([[0.0, 1, 0]]))
    assert t.miss_m[0] == pytest.approx(3.0)
    np.testing.assert_allclose(t.point_m[0], [5, 0, 1.5])
    assert t.angle_deg[0] == pytest.approx(90.0)


def test_svd_reference_agrees_on_well_conditioned_pairs():
    o1, d1, o2, d2, pts = random_scene(500, seed=1)
    a = triangulate(o1, d1, o2, d2)
    b = triangulate_svd(o1, d1, o2, d2)
    c = triangulate_svd_loop(o1, d1[:50], o2, d2[:50])
    np.testing.assert_allclose(b.height_m, a.height_m, rtol=1e-9)  # exact rays: identical
    np.testing.assert_allclose(c.height_m, b.height_m[:50], rtol=1e-9)


def test_svd_and_closest_approach_differ_far_less_than_the_noise():
    o1, d1, o2, d2, pts = random_scene(2000, seed=1)
    rng = np.random.default_rng(2)
    d1 = d1 / np.linalg.norm(d1, axis=1, keepdims=True) + rng.normal(0, 2e-4, d1.shape)  # ~0.01° ray noise
    d2 = d2 / np.linalg.norm(d2, axis=1, keepdims=True) + rng.normal(0, 2e-4, d2.shape)
    a = triangulate(o1, d1, o2, d2)
    b = triangulate_svd(o1, d1, o2, d2)
    ok = a.angle_deg > 1.0  # well conditioned
    err = np.median(np.abs(a.height_m[ok] - pts[ok, 2]))
    diff = np.median(np.abs(a.height_m[ok] - b.height_m[ok]))
    # the SVD minimises an algebraic error, closest approach a geometric one: both are
    # estimators of the same point, their disagreement is a small part of the noise error
    assert diff < 0.2 * err, (diff, err)
    assert np.median(np.abs(b.height_m[ok] - pts[ok, 2])) < 1.3 * err


@pytest.mark.parametrize("backend", ["numpy", "torch"])
@pytest.mark.parametrize("dtype", ["float64", "float32"])
def test_backends_and_dtypes(backend, dtype):
    # Rounding the unit directions to the dtype turns each ray by about eps (one ulp of a unit
    # component); a point's relative height error is then about that angle over the
    # triangulation angle between its rays. Bound: 2·eps/angle per point (measured: 0.69·eps/angle
    # at most in float32, i.e. 1.5e-5 relative over this scene, whose smallest angle is 0.11°).
    o1, d1, o2, d2, pts = random_scene(2000, seed=3)
    d1 = d1 / np.linalg.norm(d1, axis=1, keepdims=True)
    d2 = d2 / np.linalg.norm(d2, axis=1, keepdims=True)
    args = [a.astype(dtype) for a in (o1, d1, o2, d2)]
    if backend == "torch":
        args = [torch.from_numpy(a) for a in args]
    t = triangulate(*args)
    h = t.height_m.numpy() if backend == "torch" else t.height_m
    assert str(h.dtype).endswith(dtype)
    angle_rad = np.radians(triangulate(o1, d1, o2, d2).angle_deg)
    rel = np.abs(h.astype(np.float64) - pts[:, 2]) / pts[:, 2]
    assert np.all(rel <= 2 * np.finfo(dtype).eps / angle_rad + 1e-12)
    assert bool(np.asarray(t.valid).all())


def _degenerate_rays():
    """Rows: a good pair; parallel; anti-parallel; a zero-length direction; a NaN direction;
    parallel rays of different lengths (|d2| = 3 |d1|)."""
    d1 = np.array([[0, 0, 1.0], [0, 0.6, 0.8], [0, 0, 1.0], [0, 0, 0.0], [np.nan, 0, 1.0], [1.0, 2.0, 3.0]])
    d2 = np.array([[-0.05, 0, 1.0], [0, 0.6, 0.8], [0, 0, -1.0], [0, 0, 1.0], [0, 0, 1.0], [3.0, 6.0, 9.0]])
    return np.zeros(3), d1, np.array([50.0, 0, 0]), d2


@pytest.mark.parametrize("dtype", ["float64", "float32"])
def test_numpy_and_torch_agree_including_degenerate_rays(dtype):
    o1, d1, o2, d2 = (a.astype(dtype) for a in _degenerate_rays())
    a = triangulate(o1, d1, o2, d2)
    b = triangulate(*(torch.from_numpy(x) for x in (o1, d1, o2, d2)))
    assert a.valid.tolist() == b.valid.numpy().tolist() == [True, False, False, False, False, False]
    tol = 1e-12 if dtype == "float64" else 1e-5
    for f in ("point_m", "miss_m", "range1_m", "range2_m", "angle_deg"):
        np.testing.assert_allclose(getattr(b, f).numpy(), getattr(a, f), rtol=tol, atol=0, equal_nan=True, err_msg=f)
    # no common perpendicular: no point, no miss distance, no range (never a made-up point)
    for k in range(1, 6):
        assert np.isnan(a.point_m[k]).all() and np.isnan(a.miss_m[k]) and np.isnan(a.range1_m[k]), k
    # angles: parallel 0°, anti-parallel 180°, undefined for a zero-length or NaN direction
    assert a.angle_deg[1] == 0 and a.angle_deg[5] == 0 and a.angle_deg[2] == pytest.approx(180.0)
    assert np.isnan(a.angle_deg[3]) and np.isnan(a.angle_deg[4])
    assert a.height_m[0] == pytest.approx(1000.0, rel=1e-6)


def test_numpy_and_torch_agree_on_a_random_scene():
    o1, d1, o2, d2, _ = random_scene(5000, seed=8)
    d1 = d1 + np.random.default_rng(9).normal(0, 1.0, d1.shape)  # rays that miss: miss_m > 0
    a = triangulate(o1, d1, o2, d2)
    b = triangulate(*(torch.from_numpy(np.asarray(x, np.float64)) for x in (o1, d1, o2, d2)))
    for f in ("point_m", "miss_m", "range1_m", "range2_m", "angle_deg"):
        np.testing.assert_allclose(getattr(b, f).numpy(), getattr(a, f), rtol=1e-12, atol=1e-9, err_msg=f)
    assert (a.valid == b.valid.numpy()).all()


def test_chunked_numpy_equals_unchunked():
    o1, d1, o2, d2, _ = random_scene(10_000, seed=4)
    a = triangulate(o1, d1, o2, d2, chunk=1 << 20)
    b = triangulate(o1, d1, o2, d2, chunk=777)
    np.testing.assert_array_equal(a.point_m, b.point_m)
    np.testing.assert_array_equal(a.valid, b.valid)


def test_validity_flags():
    o1, o2 = np.zeros(3), np.array([50.0, 0, 0])
    d1 = np.array([[0, 0, 1.0], [0, 0, 1.0], [0, 0, -1.0], [0, 0, 1.0]])
    d2 = np.array([[-0.05, 0, 1.0], [0, 0, 1.0], [0.05, 0, -1.0], [-50 / 200_000, 0, 1.0]])
    t = triangulate(o1, d1, o2, d2, TriangulationLimits(min_angle_deg=0.01, max_range_m=100_000))
    # ok; parallel; behind both cameras; 200 km away (out of range)
    assert t.valid.tolist() == [True, False, False, False]


def test_swapping_cameras_leaves_heights_unchanged():
    o1, d1, o2, d2, _ = random_scene(300, seed=5)
    a = triangulate(o1, d1 + 1e-4, o2, d2)
    b = triangulate(o2, d2, o1, d1 + 1e-4)
    np.testing.assert_allclose(a.height_m, b.height_m, rtol=1e-12)
    np.testing.assert_allclose(a.miss_m, b.miss_m, rtol=1e-9)


def test_shape_errors_are_clear():
    from cbh.errors import ShapeError

    with pytest.raises(ShapeError, match=r"d1: expected shape \(N, 3\)"):
        triangulate(np.zeros(3), np.zeros((4, 2)), np.zeros(3), np.zeros((4, 3)))


# float32: asin loses precision where its slope diverges (90°): an error of eps32 in the sine
# gives sqrt(2·eps32) ≈ 3.5e-4 rad ≈ 0.02° there, and ~1e-5° at the small angles that matter
@pytest.mark.parametrize("dtype, atol", [("float64", 1e-9), ("float32", 0.02)])
def test_triangulation_angle_matches_arctan2_from_acute_to_obtuse(dtype, atol):
    rng = np.random.default_rng(7)
    d1 = rng.normal(size=(5000, 3)).astype(dtype)
    d2 = rng.normal(size=(5000, 3)).astype(dtype)
    t = triangulate(np.zeros(3), d1, np.array([50.0, 0, 0]), d2)
    a, b = d1.astype(np.float64), d2.astype(np.float64)
    ref = np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b), axis=1), np.einsum("ij,ij->i", a, b)))
    assert ref.min() < 5 and ref.max() > 175  # the whole range is exercised
    np.testing.assert_allclose(t.angle_deg, ref, atol=atol)


def test_points_on_epipolar_are_unbiased_where_skew_rays_read_low():
    """Carried sky-map matches miss across the baseline as much as along it. The closest approach
    of two skew rays reads their height short (range b⊥·Δd / |Δd|², the miss adds to |Δd|²); the
    along-baseline parallax alone does not. A 8 km deck over a 241 m baseline (the real Fehmarn
    station's, with its 9 m height step), 0.3° of isotropic angular noise on camera 2's rays (the
    carry's scatter there was 0.2–0.8°): the closest approach's median is 5 % low; the epipolar
    points' median is within 1 % (the sampling noise of a median of 4000 is about 0.5 % here)."""
    from cbh.geometry.triangulate import points_on_epipolar, triangulate

    rng = np.random.default_rng(3)
    o1, o2 = np.zeros(3), np.array([-203.0, 130.0, -9.0])
    p = np.column_stack([rng.uniform(-6000, 6000, 4000), rng.uniform(-6000, 6000, 4000), np.full(4000, 8000.0)])
    d1 = p - o1
    d2 = p - o2
    d2 /= np.linalg.norm(d2, axis=1, keepdims=True)
    d2 = d2 + rng.normal(0.0, math.radians(0.3), d2.shape)
    skew = np.median(triangulate(o1, d1, o2, d2).height_m)
    along = points_on_epipolar(o1, d1, o2, d2)
    assert skew < 0.96 * 8000.0
    assert np.nanmedian(along[:, 2]) == pytest.approx(8000.0, rel=0.01)
    exact = points_on_epipolar(o1, d1[:5], o2, p[:5] - o2)
    assert np.allclose(exact, p[:5], atol=1e-6 * 8000)
    assert np.isnan(points_on_epipolar(o1, d1[:1], o2, (p[:1] - o2) * [1, 1, -1])).all()  # a downward ray
