"""Property tests (hypothesis) of the geometry invariants; cheap (about 3 s together), so they run
in the default tier."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cbh.geometry.camera import EquisolidModel, OCamModel
from cbh.geometry.station import rotation_from_angles
from cbh.geometry.triangulate import triangulate

angles = st.floats(-180, 180, allow_nan=False)
small = st.floats(-10, 10, allow_nan=False)


@settings(max_examples=200, deadline=None)
@given(theta=st.floats(0, 89), phi=st.floats(0, 360), a2=st.floats(-9e-4, -3e-4), cx=st.floats(900, 1020), cy=st.floats(900, 1020))
@pytest.mark.slow
def test_ocam_round_trip_any_table1_like_lens(theta, phi, a2, cx, cy):
    # lenses of the Table 1 family: f(r) = a0 + a2 r² with f(r90) ≈ 0 near the image edge
    a0 = -a2 * 950.0**2
    m = OCamModel(width=1920, height=1920, center_xy=(cx, cy), poly=(a0, 0.0, a2))
    t, p = np.radians(theta), np.radians(phi)
    ray = np.array([[np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)]])
    px = m.ray_to_pixel(ray)
    assert np.isfinite(px).all()
    np.testing.assert_allclose(m.pixel_to_ray(px), ray, atol=1e-9)


@settings(max_examples=200, deadline=None)
@given(yaw=angles, pitch=small, roll=small)
def test_rotation_from_angles_is_a_rotation(yaw, pitch, roll):
    R = rotation_from_angles(yaw, pitch, roll)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)
    # the optical axis is tilted from the zenith by the combined pitch and roll only
    # (atan2 of the horizontal and vertical parts: arccos of a cosine near 1 loses half the
    # digits, e.g. 6.1037e-5° for a 6.1035e-5° roll)
    axis = R @ [0, 0, 1]
    tilt = np.degrees(np.arctan2(np.hypot(axis[0], axis[1]), axis[2]))
    assert tilt <= abs(pitch) + abs(roll) + 1e-9


@settings(max_examples=100, deadline=None)
@given(
    e=st.floats(-3000, 3000), n=st.floats(-3000, 3000), h=st.floats(300, 9000),
    bx=st.floats(20, 120), by=st.floats(-50, 50), shift=st.tuples(*[st.floats(-1e3, 1e3)] * 3),
)
def test_triangulation_is_translation_equivariant_and_symmetric(e, n, h, bx, by, shift):
    p = np.array([e, n, h])
    o1, o2 = np.zeros(3), np.array([bx, by, 0.0])
    d1, d2 = (p - o1)[None], (p - o2)[None]
    t = triangulate(o1, d1, o2, d2)
    np.testing.assert_allclose(t.point_m[0], p, rtol=1e-7, atol=1e-6)
    s = np.array(shift)
    ts = triangulate(o1 + s, d1, o2 + s, d2)
    np.testing.assert_allclose(ts.point_m[0], p + s, rtol=1e-7, atol=1e-5)
    sw = triangulate(o2, d2, o1, d1)
    np.testing.assert_allclose(sw.point_m[0], t.point_m[0], rtol=1e-9, atol=1e-6)


@settings(max_examples=100, deadline=None)
@given(r90=st.floats(300, 2000), x=st.floats(-0.99, 0.99), y=st.floats(-0.99, 0.99))
def test_scaled_equisolid_equals_resized_pixels(r90, x, y):
    m = EquisolidModel(width=4000, height=3000, center_xy=(2000.3, 1499.7), radius_px=r90)
    if x * x + y * y > 0.98:
        return
    px = np.array([[m.center_xy[0] + x * r90, m.center_xy[1] + y * r90]])
    s = m.scaled(0.25)
    np.testing.assert_allclose(s.pixel_to_ray((px + 0.5) * 0.25 - 0.5), m.pixel_to_ray(px), atol=1e-9)
