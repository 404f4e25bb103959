"""Clock offsets with fast layers: each layer compensated with its own motion (issue 22).

Camera 2 captures δ late, so it sees a cloud at height H moved by ``v(H)·δ``. A 19 m/s layer at
4000 m moves 57 m in 3 s, more than the 50 m baseline: one global shift, or a per-pixel label
of which layer camera 2 shows, cannot synchronise the pair, and the two layers came out as one
at 2860 m on the first pair of a run that had the offset right. The plane sweep now matches
each plane at height H against camera 2 moved with the motion of the profile node nearest to H
(:class:`cbh.pipeline.sweep.PlaneViews`, :func:`cbh.pipeline.motion.shifted_images`).

The default tier checks that compensation on its own (exact geometry, the node chosen per plane,
the camera-1 motion factor); the slow tier runs the issue's sequence through the pipeline.
"""
from __future__ import annotations

import math
from dataclasses import replace
from datetime import timedelta

import numpy as np
import pytest

#: The issue's scene: a slow layer at 1000 m and a fast one at 4000 m, camera 2 3 s late.
SLOW, FAST = (1000.0, (2.0, 1.0)), (4000.0, (-6.0, 18.0))
OFFSET_S, CADENCE_S = 3.0, 10.0


@pytest.fixture(scope="module")
def pipe320():
    from cbh.geometry.station import load_station
    from cbh.pipeline import Pipeline
    from cbh.presets import station_path

    return Pipeline(load_station(station_path()).scaled(320))


def test_plane_views_take_the_image_of_the_nearest_height():
    """Each plane takes the node nearest in ln(h − o1z): the cut between 1000 m and 4000 m lies at
    their geometric mean, 2000 m, whatever the order the nodes come in."""
    from cbh.pipeline.sweep import PlaneViews

    low, high = np.zeros((2, 2), np.uint8), np.ones((2, 2), np.uint8)
    for images, heights in (((low, high), (1000.0, 4000.0)), ((high, low), (4000.0, 1000.0))):
        v = PlaneViews.nearest(images, heights, o1z=0.0)
        assert v.cuts_s == pytest.approx([1.0 / 2000.0])
        assert v.for_plane(1.0 / 1990.0) is low and v.for_plane(1.0 / 2010.0) is high
        assert v.for_plane(1.0 / 150.0) is low and v.for_plane(0.0) is high  # beyond the nodes: the nearest
    one = PlaneViews.single(low)
    assert one.for_plane(1e-3) is low and one.weights_on(np.s_[0:2, 0:2], (1, 1)) is None


def test_per_height_compensation_is_the_moved_point(pipe320):
    """Exact geometry: on plane H the sweep reads camera 2's node image at the plane mapping's
    pixel; that pixel of the node image (``shift_map`` of ``v/(H − z2)·δ``) must be where camera 2
    sees the cloud point δ later, moved by ``v·δ``: 57 m here, 0.9 px at 320 px, against a
    parallax of 1.3 px. Bound: the plane mapping's quadratic in s and the bilinear 8 px grid of
    the shift are each good to ≈ 0.01 px (measured 0.006 px at the 99th percentile): 0.02 px,
    2 % of the shift."""
    from cbh.pipeline.match import sample_map
    from cbh.pipeline.motion import shift_map

    g, c1, c2 = pipe320.geometry, pipe320.cam1, pipe320.cam2
    o1, o2 = c1.position_m, c2.position_m
    (h, v), delta = FAST, OFFSET_S
    v = np.asarray(v)
    m = shift_map(c2, (c2.model.height, c2.model.width), v / (h - o2[2]) * delta)
    ys, xs = np.nonzero(pipe320.static_mask(0))
    pick = np.random.default_rng(0).choice(len(ys), 1500, replace=False)
    yi, xi = ys[pick], xs[pick]
    d = g.rays1_world[yi, xi].astype(np.float64)
    up = d[:, 2] > 0.3  # within 73° of the zenith: camera 2 sees the moved point too
    yi, xi, d = yi[up], xi[up], d[up]
    p2 = g.planes.points(np.full(len(yi), 1.0 / (h - o1[2])), yi, xi)
    got = sample_map(m[..., 0], m[..., 1], p2)
    x = o1[None, :] + d * ((h - o1[2]) / d[:, 2])[:, None]
    x[:, :2] += v * delta
    ray = (x - o2) / np.linalg.norm(x - o2, axis=1, keepdims=True)
    want = c2.direction_to_pixel(ray)
    assert np.median(np.linalg.norm(want - p2, axis=1)) > 0.5  # the shift is real
    assert np.abs(got - want).max() <= 0.02


def test_motion_weights_prefer_the_node_that_moves_camera_1_right(pipe320):
    """The planes of node k are weighted by T_k / max_j T_j (T: ZNCC of camera 1 now against its
    previous frame moved on with node k's motion; motion_factors); where no node explains the
    pixel (max T below the sweep's min_zncc: a cloud that changed), every weight is 1, so the
    test can only demote a plane, never reject a pixel. motion_weights, on a texture moved by a
    node's exact motion: that node's weight is 1 where the texture is, the other's falls by
    the ZNCC of the texture against itself shifted by the motion difference."""
    from cbh.pipeline.motion import motion_factors, motion_weights, shift_map

    t = [np.array([[0.95, 0.3, 0.9]], np.float32), np.array([[0.5, 0.4, -0.2]], np.float32)]
    f0, f1 = motion_factors(t, min_zncc=0.6)
    np.testing.assert_allclose(f0, [[1.0, 1.0, 1.0]])
    np.testing.assert_allclose(f1, [[0.5 / 0.95, 1.0, 0.0]], rtol=1e-6)

    cam = pipe320.cam1
    h, w = cam.model.height, cam.model.width
    rng = np.random.default_rng(4)
    import cv2

    prev = cv2.GaussianBlur(rng.uniform(0, 255, (h, w)).astype(np.float32), (0, 0), 2.0).astype(np.uint8)
    r_low, r_high, dt = np.array([2.0, 1.0]) / 1000.0, np.array([-6.0, 18.0]) / 4000.0, 10.0
    now = cv2.remap(prev, shift_map(cam, (h, w), -r_low * dt), None, cv2.INTER_LINEAR)  # all moving with r_low
    wl, wh = motion_weights(now, prev, cam, [r_low, r_high], dt, window_px=9, min_zncc=0.6)
    near = np.s_[h // 4 - 20: h // 4 + 20, w // 4 - 20: w // 4 + 20]  # (half resolution) near the zenith
    # the nodes' motions differ by 3.6 px in 10 s here, against texture of σ = 2 px: ZNCC ≈ 0
    assert np.median(wl[near]) == 1.0 and np.median(wh[near]) < 0.2


def _scene(offset_s=OFFSET_S, slow=SLOW, fast=FAST):
    from cbh.presets import scene_path
    from cbh.sim import load_scene
    from cbh.sim.scene import with_clock_offsets

    sc = load_scene(scene_path("two-layers"))
    lo, hi = sc.layers
    sc = replace(sc, layers=(replace(lo, height_m=slow[0], wind_ms=slow[1]), replace(hi, height_m=fast[0],
                                                                                     wind_ms=fast[1])))
    return with_clock_offsets(sc, [f"cam2={offset_s}"])


def _sequence(size, n=4, cadence_s=CADENCE_S, **kw):
    from cbh.geometry.station import load_station
    from cbh.pipeline import Pipeline
    from cbh.presets import station_path
    from cbh.sim import SkySimulator

    sc = _scene(**kw)
    sim = SkySimulator(load_station(station_path()), sc, size_px=size)
    pipe, state, out = Pipeline(sim.station), None, []
    for shot in sim.frames(sc.time_utc, n, cadence_s):
        r = pipe.process(shot.views["cam1"].image, shot.views["cam2"].image, shot.time_utc, channels="bgr",
                         previous=state)
        state = r.state
        out.append(r)
    return out


@pytest.mark.slow
def test_a_fast_layer_moving_farther_than_the_baseline_is_found():
    """The issue's case at 560 px (178 px/rad; the smallest size at which the fix reaches the 2 %
    target, 480 px: 2.5 %): 1000 m at 2.2 m/s under 4000 m at 19 m/s, camera 2 3 s late, 10 s
    cadence. Before (one per-pixel compensated image for every plane, the offset measured on it
    as a residual): the 4000 m layer 3.5, 2.9, 1.9 % low on pairs 2–4, the offset +2.79 …
    +2.83 s (at 960 px the second pair had no offset and no 4000 m layer: 1004, 1885 and 2630 m
    instead). From the second pair on: the offset within 0.1 s (the
    4000 m layer's 4.5 px of motion across the baseline per 10 s measure δ to ≈ 0.02 s per
    track), both layers within 2 % (the 4000 m layer has 2.2 px of parallax: 2 % is 0.045 px,
    about what 3 s × 19 m/s compensated to 1 % leaves), and each layer's speed within 5 %."""
    out = _sequence(560)
    # uncompensated, the fault is real: the first pair (no motion yet) is flagged and a layer is off
    # (1146 m for 1000 m; its 4000 m deck happens to read 4051 m, within 2 %, since 2026-12-04)
    assert set(out[0].flags) & {"geometry_mismatch", "clock_unknown"}, out[0].flags
    assert not all(any(abs(L.height_m / h - 1) <= 0.02 for L in out[0].layers) for h, _ in (SLOW, FAST))
    for r in out[1:]:
        assert abs(r.diagnostics["clock_offset_s"] - OFFSET_S) <= 0.1, r.diagnostics
        for h, wind in (SLOW, FAST):
            near = [L for L in r.layers if abs(math.log(L.height_m / h)) < 0.1]
            assert len(near) == 1, [L.height_m for L in r.layers]
            L = near[0]
            assert abs(L.height_m / h - 1) <= 0.02, (h, [L.height_m for L in r.layers])
            assert abs(math.hypot(L.motion_east_ms, L.motion_north_ms) / math.hypot(*wind) - 1) <= 0.05
