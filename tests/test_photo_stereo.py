"""Stereo pairs built from a real sky photograph (cbh.sim.photo): the real WAHRSIS3 photograph is
camera 1, a virtual camera of the same lens sees its sky as a plane at a known height. Real cloud
texture, JPEG noise and vignetting, with exact truth.

Tolerances: the parallax at zenith is p ≈ f·B/h, with f = R90·cos 45° ≈ 260 px/rad for the
equisolid lens of the 1296 px photograph (R90 = 367.5 px; it is below the working size, so it
is matched as it is): B = 50 m, h = 1500 m gives p ≈ 8.7 px. The sweep's aggregated parallax is
good to ≈ 0.1 px, so a pixel's height is good to ≈ 1.2 % (dense MdAPE bar 2 %) and a layer, a
median over 10⁴ pixels, far better (bar 1 %)."""
from __future__ import annotations

import cv2
import numpy as np
import pytest
from datetime import datetime, timezone
from dataclasses import replace

from cbh.flags import INVALIDATING

T = datetime(2015, 10, 29, 4, 58, 1, tzinfo=timezone.utc)


@pytest.fixture(scope="module")
def photo(shared):
    from cbh.geometry.station import load_station
    from cbh.imageio import read_image

    from .conftest import REPO

    st = load_station(REPO / "configs" / "wahrsis-2015-10-29.toml")
    cam1 = st.camera("wahrsis3")
    cam1 = replace(cam1.scaled(1296 / cam1.model.width), name="cam1")
    full, _ = read_image(shared / "data" / "wahrsis-2015-10-29" / "2015-10-29-12-58-01-wahrsis3-med.jpg")
    img = cv2.resize(full, (cam1.model.width, cam1.model.height), interpolation=cv2.INTER_AREA)
    return st, cam1, img


def _run(photo, height_m: float, baseline_m: float, yaw_deg: float = 20.0, misyaw_deg: float = 0.0):
    """The pair through the pipeline; ``misyaw_deg``: camera 2 really turned this much more about
    the vertical than the station says."""
    from cbh.geometry.station import Station
    from cbh.pipeline import Pipeline
    from cbh.sim.photo import plane_view, virtual_camera

    st, cam1, img = photo
    cam2 = virtual_camera(cam1, (baseline_m, 0.0, 0.0), yaw_deg, name="cam2")
    img2 = plane_view(img, cam1, virtual_camera(cam2, cam2.position_m, misyaw_deg, name="cam2"), height_m)
    station = Station("photo-stereo", st.latitude_deg, st.longitude_deg, st.altitude_m, {"cam1": cam1, "cam2": cam2})
    return Pipeline(station).process(img, img2, T, channels="bgr")


def _check(r, height_m: float, layer_tol: float, dense_tol: float):
    assert len(r.layers) == 1, [L.height_m for L in r.layers]
    assert r.layers[0].height_m == pytest.approx(height_m, rel=layer_tol)
    hm = r.height_map[np.isfinite(r.height_map)]
    assert np.median(np.abs(hm - height_m) / height_m) < dense_tol
    assert r.diagnostics["measured_fraction"] > 0.5
    assert r.diagnostics["geometry_rotation_deg"] < 0.02  # exact geometry: real-texture LK fits ≈ 0.003°
    assert not set(r.flags) & INVALIDATING, r.flags


def test_plane_view_puts_the_photograph_on_the_plane(photo):
    """A camera-1 pixel's point on the plane, seen by camera 2, has camera 1's colour there."""
    from cbh.sim.photo import plane_view, virtual_camera

    _, cam1, img = photo
    cam2 = virtual_camera(cam1, (50.0, 0.0, 0.0), 20.0, name="cam2")
    img2 = plane_view(img, cam1, cam2, 1000.0)
    rng = np.random.default_rng(0)
    px1 = np.stack([rng.uniform(500, 800, 50), rng.uniform(300, 600, 50)], 1)
    d = cam1.pixel_to_world(px1)
    p = cam1.position_m + d * ((1000.0 - cam1.position_m[2]) / d[:, 2:3])
    px2 = cam2.world_to_pixel(p)
    i2 = np.rint(px2).astype(int)
    i1 = np.rint(px1).astype(int)
    # nearest pixels on both sides: within the texture's change over ≈ 1 px (JPEG sky: a few levels)
    diff = np.abs(img2[i2[:, 1], i2[:, 0]].astype(int) - img[i1[:, 1], i1[:, 0]].astype(int))
    assert np.median(diff) <= 6


@pytest.mark.slow
def test_real_texture_at_1500_m_50_m_baseline(photo):
    _check(_run(photo, 1500.0, 50.0), 1500.0, 0.01, 0.02)


@pytest.mark.slow
@pytest.mark.parametrize("height_m, baseline_m", [(500.0, 30.0), (4000.0, 50.0), (4000.0, 100.0), (800.0, 100.0)])
def test_real_texture_heights_and_baselines(photo, height_m, baseline_m):
    """4000 m at 50 m: p ≈ 3.3 px, a pixel good to ≈ 3 %: dense bar 3 % (median), layer 2 %."""
    _check(_run(photo, height_m, baseline_m), height_m, 0.02, 0.03)


def test_a_half_degree_yaw_on_real_texture_is_flagged_not_reported(photo):
    """Camera 2 turned 0.5° about the vertical from what the station says: its matches sit only
    0.6 px off their epipolar curves (under the 1 px floor), but the heights move by tens of per
    cent (a 1500 m layer came out at 1091 and 2153 m, confidence 1.0, unflagged). The fitted
    rotation finds the 0.5° (a shift of 2.3 px at 45° off axis here, against 0.25 px) and the pair
    is flagged ``geometry_mismatch`` (invalidating); the correct pair fits ≈ 0.003°."""
    r = _run(photo, 1500.0, 50.0, misyaw_deg=0.5)
    assert "geometry_mismatch" in r.flags and "geometry_mismatch" in INVALIDATING
    assert r.diagnostics["geometry_rotation_deg"] == pytest.approx(0.5, abs=0.03)
    assert r.diagnostics["geometry_residual_px"] < 1.0  # what the median alone would have let through


def _network(photo, height_m: float, b3_m: float):
    """The photograph's sky at ``height_m`` seen by cam1 (the photograph), cam2 50 m east (yawed
    20°) and cam3 ``b3_m`` north (yawed −35°): a three-camera station on real texture."""
    from cbh.geometry.station import Station
    from cbh.pipeline.network import StationPipeline
    from cbh.sim.photo import plane_view, virtual_camera

    st, cam1, img = photo
    cam2 = virtual_camera(cam1, (50.0, 0.0, 0.0), 20.0, name="cam2")
    cam3 = virtual_camera(cam1, (0.0, b3_m, 0.0), -35.0, name="cam3")
    station = Station("photo-network", st.latitude_deg, st.longitude_deg, st.altitude_m,
                      {"cam1": cam1, "cam2": cam2, "cam3": cam3})
    imgs = [img, plane_view(img, cam1, cam2, height_m), plane_view(img, cam1, cam3, height_m)]
    return StationPipeline(station).process(imgs, T, channels="bgr")


@pytest.mark.slow  # (2.4 s each; networks run by default in tests/test_network.py)
@pytest.mark.parametrize("height_m,b3_m", [(8000.0, 630.0), (1500.0, 630.0), (4000.0, 630.0), (1500.0, 300.0)])
def test_a_camera_network_on_real_texture(photo, height_m, b3_m):
    """Real WAHRSIS texture on a plane, three cameras (issue 24). At 8000 m the 50 m pair has
    2.1 px of parallax at the zenith (p ≈ 260 px/rad · B/h) and misses by −0.45 % (measured); the
    630 m pair has 20 px, so the station's layer must be within the issue's 0.4 % and its dense
    map within 1 % per pixel. No camera named (the geometry is exact; `sun_misaligned` is the
    plane view's moved sun)."""
    r = _network(photo, height_m, b3_m)
    assert len(r.layers) == 1 and r.layers[0].height_m == pytest.approx(height_m, rel=0.004)
    hm = r.height_map[np.isfinite(r.height_map)]
    assert np.median(np.abs(hm - height_m) / height_m) < 0.01
    assert r.diagnostics["mismatched_cameras"] == [] and not set(r.flags) & INVALIDATING
    assert {p for p, *_ in r.layers[0].support} == {"cam1+cam2", "cam1+cam3"}
