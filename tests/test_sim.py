"""Synthetic stereo sky (cbh.sim): physical consistency, ground truth, determinism, imperfections.

Renders are 480 px (or smaller) so the whole file runs in well under a minute.
"""
from __future__ import annotations

import dataclasses
import math
from datetime import timedelta

import numpy as np
import pytest

from cbh.presets import list_scenes, station_path
from cbh.result import Frame
from cbh.sim import CloudLayer, Scene, SkySimulator, load_scene, parse_scene
from cbh.sim.sky import sun_direction
from cbh.geometry.station import load_station
from cbh.geometry.triangulate import triangulate_pixels

SIZE = 480
PRESETS = ("single-cumulus", "two-layers", "three-layers", "overcast", "clear-sky", "sun-behind-clouds")


@pytest.fixture(scope="module")
def station():
    return load_station(station_path())


def quiet(scene: Scene, **image) -> Scene:
    """The scene without sensor noise (and with other image settings changed)."""
    return dataclasses.replace(scene, image=dataclasses.replace(scene.image, noise_dn=0.0, **image))


@pytest.fixture(scope="module")
def two_layers(station):
    sim = SkySimulator(station, quiet(load_scene("two-layers")), size_px=SIZE)
    return sim, sim.render()


def gray(img):
    import cv2

    return cv2.cvtColor(img, cv2.COLOR_BGR2GRAY).astype(np.float32)


def sample(img, px):
    """Bilinear samples of a (H, W) float32 image at (N, 2) pixels."""
    import cv2

    n = len(px)
    cols = 500
    pad = (-n) % cols
    p = np.pad(px.astype(np.float32), ((0, pad), (0, 0)))
    out = cv2.remap(img, p[:, 0].reshape(-1, cols), p[:, 1].reshape(-1, cols), cv2.INTER_LINEAR)
    return out.ravel()[:n]


def cloud_points(sim, view, cam_name="cam1", max_zenith_deg=60.0):
    """cam1's cloud pixels (N, 2), their true heights (N,) and the world points (N, 3)."""
    cam = sim.station.cameras[cam_name]
    ys, xs = np.nonzero(view.cloud_mask & (cam.zenith_map() < max_zenith_deg))
    px = np.stack([xs, ys], axis=1).astype(np.float64)
    h = view.height_m[ys, xs].astype(np.float64)
    d = cam.pixel_to_world(px)
    pts = cam.position_m + d * ((h - cam.position_m[2]) / d[:, 2])[:, None]
    return px, h, pts


# --- the key bar: physically consistent stereo -----------------------------------------------

def test_truth_geometry_triangulates_to_true_height(two_layers):
    sim, shot = two_layers
    c1, c2 = sim.station.pair()
    px1, h, pts = cloud_points(sim, shot.views["cam1"])
    px2 = c2.world_to_pixel(pts)
    ok = c2.model.contains(px2)
    assert ok.sum() > 10_000
    tri = triangulate_pixels(c1, px1[ok], c2, px2[ok])
    assert tri.valid.all()
    # The bar of issue 3: < 0.1 % of the true height with the project's own triangulation.
    rel = np.abs(tri.height_m - h[ok]) / h[ok]
    assert rel.max() < 1e-3
    # Both layers are present among the points.
    assert set(np.unique(h)) == {1200.0, 3500.0}


def test_same_cloud_point_looks_the_same_from_both_cameras(two_layers):
    """The texture is a function of world (east, north) only: cam2's image at the true
    position of cam1's cloud point repeats cam1's pixel, and its truth agrees."""
    import cv2

    sim, shot = two_layers
    v1, v2 = shot.views["cam1"], shot.views["cam2"]
    c2 = sim.station.cameras["cam2"]
    px1, h, pts = cloud_points(sim, v1)
    px2 = c2.world_to_pixel(pts)
    ok = c2.model.contains(px2)
    px1, h, pts, px2 = px1[ok], h[ok], pts[ok], px2[ok]
    r = np.rint(px2).astype(int)
    h2 = v2.height_m[r[:, 1], r[:, 0]]
    low = h == 1200.0  # the lowest layer is never hidden from cam2 by another layer
    # Disagreement only at cloud edges (rounding to cam2's pixel grid).
    assert np.mean(h2[low] == 1200.0) > 0.95
    same = h2 == h
    # Compare the texture band (difference of Gaussians, sigma 1 and 4 px): the part the
    # matchers use. Blurring at 1 px removes the near-Nyquist part (the finest octave is
    # ~3 px per wavelength) that bilinear sampling between pixel centres cannot reproduce.
    def band(g):
        return cv2.GaussianBlur(g, (0, 0), 1.0) - cv2.GaussianBlur(g, (0, 0), 4.0)

    g1, g2 = band(gray(v1.image)), band(gray(v2.image))
    a = g1[px1[same, 1].astype(int), px1[same, 0].astype(int)]
    b = sample(g2, px2[same])
    assert a.std() > 8.0  # clouds have internal texture to compare
    assert np.corrcoef(a, b)[0, 1] > 0.93
    # Control: at the position that twice the height predicts (~2 px away) it does not match.
    c1 = sim.station.cameras["cam1"]
    wrong = c2.world_to_pixel(c1.position_m + (pts[same] - c1.position_m) * 2.0)
    inside = c2.model.contains(wrong)
    assert np.corrcoef(a[inside], sample(g2, wrong[inside]))[0, 1] < 0.8


def test_texture_is_matchable_lk_recovers_height(two_layers):
    """Pyramidal Lucas-Kanade from cam1 to cam2, started at a 5 % wrong height, converges to
    the true height: the texture has detail at the pixel scale."""
    import cv2

    sim, shot = two_layers
    v1, v2 = shot.views["cam1"], shot.views["cam2"]
    c1, c2 = sim.station.pair()
    # interior of the low clouds, so that the LK window does not straddle a depth edge
    inner = cv2.erode(v1.cloud_mask.astype(np.uint8), np.ones((15, 15), np.uint8)).astype(bool)
    inner &= (c1.zenith_map() < 50) & (v1.height_m == 1200.0)
    g1, g2 = gray(v1.image).astype(np.uint8), gray(v2.image).astype(np.uint8)
    pts = cv2.goodFeaturesToTrack(g1, 1000, 0.01, 4, mask=inner.astype(np.uint8))[:, 0, :].astype(np.float64)
    assert len(pts) > 60
    h = v1.height_m[np.rint(pts[:, 1]).astype(int), np.rint(pts[:, 0]).astype(int)].astype(np.float64)
    d = c1.pixel_to_world(pts)
    guess = c2.world_to_pixel(c1.position_m + d * (1.05 * h / d[:, 2])[:, None]).astype(np.float32)
    p2, status, _ = cv2.calcOpticalFlowPyrLK(
        g1, g2, pts.astype(np.float32), guess.copy(), winSize=(11, 11), maxLevel=2,
        flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
    )
    ok = status.ravel() == 1
    tri = triangulate_pixels(c1, pts[ok], c2, p2[ok].astype(np.float64))
    rel = (tri.height_m - h[ok]) / h[ok]
    # LK's sub-pixel error (~0.1 px) on a ~6 px disparity at 480 px is ~2 % per point;
    # the median of ~150 points is within 1 %, far from the 5 % start.
    assert abs(np.median(rel)) < 0.01
    assert np.median(np.abs(rel)) < 0.03


# --- ground truth ------------------------------------------------------------------------------

def test_truth_mask_and_height_agree(two_layers):
    sim, shot = two_layers
    for name, v in shot.views.items():
        cam = sim.station.cameras[name]
        assert v.image.shape == (SIZE, SIZE, 3) and v.image.dtype == np.uint8
        assert v.height_m.shape == (SIZE, SIZE) and v.height_m.dtype == np.float32
        np.testing.assert_array_equal(v.cloud_mask, np.isfinite(v.height_m))
        assert set(np.unique(v.height_m[v.cloud_mask])) <= {1200.0, 3500.0}
        assert not v.cloud_mask[~cam.model.image_circle_mask()].any()
        assert 0.1 < v.cloud_mask.mean() < 0.6
        # colours: cloud grey-white (blue/red ≈ 1), clear sky blue (blue/red well above 1)
        img = v.image.astype(np.float32) + 1.0
        br = img[..., 0] / img[..., 2]
        zen = cam.zenith_map()
        cos_sun = cam.model.ray_map() @ cam.R_world_from_cam.T @ sun_direction(shot.sun_zenith_deg, shot.sun_azimuth_deg)
        far_from_sun = cos_sun < math.cos(math.radians(20.0))
        import cv2

        core = cv2.erode(v.cloud_mask.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
        clear = cv2.erode((~v.cloud_mask).astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
        sel_sky = clear & (zen < 60) & far_from_sun & cam.model.image_circle_mask()
        assert np.median(br[core & (zen < 60)]) < 1.1
        assert np.median(br[sel_sky]) > 1.8


def test_coverage_is_the_cloudy_area_fraction():
    from cbh.sim.noise import LayerTexture

    tex = LayerTexture(1000.0, seed=5, finest_m=10.0, level_px_m=2.0, max_level=6)
    rng = np.random.default_rng(1)
    e, n = rng.uniform(-3e5, 3e5, size=(2, 200_000))
    shape, detail = tex.evaluate(e, n)
    assert abs(shape.std() - 1.0) < 0.1 and abs(detail.std() - 1.0) < 0.1
    for cov in (0.1, 0.35, 0.8):
        frac = np.mean(shape > tex.threshold(cov))
        assert abs(frac - cov) < 0.01  # 200k samples over many periods: sampling error ~0.001
    assert tex.threshold(0.0) == math.inf and tex.threshold(1.0) == -math.inf


def test_clear_sky_and_overcast_truth(station):
    clear = SkySimulator(station, load_scene("clear-sky"), size_px=160).render()
    for v in clear.views.values():
        assert not v.cloud_mask.any() and np.isnan(v.height_m).all()
    sim = SkySimulator(station, load_scene("overcast"), size_px=160)
    shot = sim.render()
    for name, v in shot.views.items():
        cam = sim.station.cameras[name]
        sky = cam.model.image_circle_mask() & (cam.zenith_map() < 90)
        np.testing.assert_array_equal(v.cloud_mask, sky)
        assert np.all(v.height_m[sky] == 700.0)


def test_sun_is_where_pvlib_puts_it(station):
    sim = SkySimulator(station, quiet(load_scene("clear-sky")), size_px=SIZE)
    shot = sim.render()
    zs, az = shot.sun_zenith_deg, shot.sun_azimuth_deg
    # Brasília, 2024-06-21 15:00 UTC (12:00 local), winter solstice: the sun culminates in
    # the north at zenith ≈ latitude + 23.44° ≈ 39.2°.
    assert abs(zs - 39.2) < 0.5 and (az < 10 or az > 350)
    for name, v in shot.views.items():
        cam = sim.station.cameras[name]
        x, y = cam.direction_to_pixel(sun_direction(zs, az))[0]
        assert v.image[int(round(y)), int(round(x))].min() >= 250  # disk saturates
        g = gray(v.image)
        iy, ix = np.unravel_index(np.argmax(g), g.shape)
        assert math.hypot(ix - x, iy - y) < 6  # the brightest pixel is at the sun
        x2, y2 = cam.direction_to_pixel(sun_direction(60.0, (az + 180) % 360))[0]
        assert v.image[int(round(y2)), int(round(x2))].max() < 240


def test_obstacles_have_no_height(station):
    sim = SkySimulator(station, quiet(load_scene("single-cumulus")), size_px=SIZE)
    cs = sim._cams["cam1"]
    assert cs.obstacle_idx.size > 100
    v = sim.view("cam1")
    h = v.height_m.reshape(-1)[cs.obstacle_idx]
    assert np.isnan(h).all() and not v.cloud_mask.reshape(-1)[cs.obstacle_idx].any()
    # dark silhouettes low on the horizon, in the configured azimuth ranges
    assert v.image.reshape(-1, 3)[cs.obstacle_idx].mean() < 90
    zen = sim.station.cameras["cam1"].zenith_map().reshape(-1)[cs.obstacle_idx]
    assert zen.min() > 90 - 12.0 - 0.5


# --- determinism, layers, time -----------------------------------------------------------------

def test_deterministic_for_a_seed(station):
    scene = load_scene("two-layers")
    a = SkySimulator(station, scene, size_px=200).render()
    b = SkySimulator(station, scene, size_px=200).render()
    for name in a.views:
        np.testing.assert_array_equal(a.views[name].image, b.views[name].image)
        np.testing.assert_array_equal(a.views[name].height_m, b.views[name].height_m)
    layers = (dataclasses.replace(scene.layers[0], seed=99),) + scene.layers[1:]
    c = SkySimulator(station, dataclasses.replace(scene, layers=layers), size_px=200).render()
    assert np.mean(c.views["cam1"].cloud_mask != a.views["cam1"].cloud_mask) > 0.05


def test_lower_layer_hides_higher(station):
    low = CloudLayer(height_m=1000.0, coverage=0.4, texture_scale_m=800.0, seed=3)
    high = CloudLayer(height_m=3000.0, coverage=1.0, texture_scale_m=1500.0, seed=4)
    base = quiet(Scene(layers=(low,)))
    only_low = SkySimulator(station, base, size_px=240).view("cam1")
    both = SkySimulator(station, dataclasses.replace(base, layers=(high, low)), size_px=240).view("cam1")
    cam = SkySimulator(station, base, size_px=240).station.cameras["cam1"]
    sky = cam.model.image_circle_mask() & (cam.zenith_map() < 90)
    np.testing.assert_array_equal(both.height_m[only_low.cloud_mask], 1000.0)
    np.testing.assert_array_equal(both.height_m[sky & ~only_low.cloud_mask], 3000.0)
    # where the low cloud is opaque the high deck does not show through at all
    import cv2

    core = cv2.erode(only_low.cloud_mask.astype(np.uint8), np.ones((7, 7), np.uint8)).astype(bool)
    core &= cam.zenith_map() < 45  # haze is negligible here
    assert core.sum() > 200
    np.testing.assert_array_equal(both.image[core], only_low.image[core])
    assert np.abs(both.image[sky & ~only_low.cloud_mask].astype(int)
                  - only_low.image[sky & ~only_low.cloud_mask]).mean() > 20


def test_clock_offset_moves_clouds_by_wind_times_dt(station):
    wind = (12.0, -5.0)
    layer = CloudLayer(height_m=1500.0, coverage=0.4, texture_scale_m=700.0, wind_ms=wind, seed=8)
    scene = quiet(Scene(layers=(layer,)))
    dt = 4.0
    late = parse_scene({"layers": [dataclasses.asdict(layer) | {"wind_ms": list(wind), "offset_m": [0.0, 0.0]}],
                        "imperfections": [{"camera": "cam2", "clock_offset_s": dt}],
                        "image": {"noise_dn": 0.0}})
    t = scene.time_utc + timedelta(seconds=30)
    v_late = SkySimulator(station, late, size_px=240).view("cam2", t)
    ref = SkySimulator(station, scene, size_px=240)
    v_then = ref.view("cam2", t + timedelta(seconds=dt))
    v_now = ref.view("cam2", t)
    assert v_late.time_utc == t + timedelta(seconds=dt) and v_late.stamp_utc == t
    np.testing.assert_array_equal(v_late.image, v_then.image)
    np.testing.assert_array_equal(v_late.height_m, v_then.height_m)
    assert np.mean(v_late.cloud_mask != v_now.cloud_mask) > 0.01
    # and "moved" means by wind · dt on the layer: cam2's truth at t+dt at the pixel of
    # world point P equals its truth at t at the pixel of P − wind · dt (away from cloud
    # edges, where rounding to whole pixels decides).
    import cv2

    cam = ref.station.cameras["cam2"]
    m = v_now.cloud_mask.astype(np.uint8)
    edge = cv2.dilate(m, np.ones((3, 3), np.uint8)) != cv2.erode(m, np.ones((3, 3), np.uint8))
    ys, xs = np.nonzero(cam.zenith_map() < 60)
    px = np.stack([xs, ys], 1).astype(float)
    d = cam.pixel_to_world(px)
    pts = cam.position_m + d * ((1500.0 - cam.position_m[2]) / d[:, 2])[:, None]

    def agreement(shift_m):
        r = np.rint(cam.world_to_pixel(pts - shift_m)).astype(int)
        ok = (r >= 0).all(1) & (r < 240).all(1)
        ok[ok] &= ~edge[r[ok, 1], r[ok, 0]]
        return np.mean(v_then.cloud_mask[ys[ok], xs[ok]] == v_now.cloud_mask[r[ok, 1], r[ok, 0]])

    moved = np.array([wind[0] * dt, wind[1] * dt, 0.0])
    assert agreement(moved) > 0.99
    assert agreement(0.0 * moved) < 0.97 and agreement(-moved) < 0.9  # controls


def test_orientation_error_renders_a_different_camera(station):
    scene = quiet(load_scene("single-cumulus"))
    bad = dataclasses.replace(scene, imperfections=parse_scene(
        {"imperfections": [{"camera": "cam2", "rotation_error_deg": [2.0, 0.5, 0.0]}]}).imperfections)
    good_sim = SkySimulator(station, scene, size_px=SIZE)
    bad_sim = SkySimulator(station, bad, size_px=SIZE)
    g, b = good_sim.view("cam2"), bad_sim.view("cam2")
    assert np.abs(g.image.astype(int) - b.image).mean() > 3
    assert np.mean(g.cloud_mask != b.cloud_mask) > 0.01
    assert not np.allclose(b.true_camera.R_world_from_cam, bad_sim.station.cameras["cam2"].R_world_from_cam)
    np.testing.assert_allclose(g.true_camera.R_world_from_cam, good_sim.station.cameras["cam2"].R_world_from_cam)
    # cam1 unaffected
    np.testing.assert_array_equal(good_sim.view("cam1").image, bad_sim.view("cam1").image)
    # The truth belongs to the true geometry: cam1 cloud points project through the true cam2
    # onto cam2's cloud truth at the right height, and the station's nominal cam2 mis-triangulates.
    px1, h, pts = cloud_points(bad_sim, bad_sim.view("cam1"), max_zenith_deg=45)
    true2, nom2 = b.true_camera, bad_sim.station.cameras["cam2"]
    p_true = true2.world_to_pixel(pts)
    r = np.rint(p_true).astype(int)
    assert np.mean(b.height_m[r[:, 1], r[:, 0]] == h) > 0.95
    c1 = bad_sim.station.cameras["cam1"]
    err_nominal = np.abs(triangulate_pixels(c1, px1, nom2, p_true).height_m - h) / h
    err_true = np.abs(triangulate_pixels(c1, px1, true2, p_true).height_m - h) / h
    assert err_true.max() < 1e-6 and np.median(err_nominal) > 0.05


# --- API: size, frames, sequences ----------------------------------------------------------------

def test_size_scales_the_station(station, two_layers):
    sim, shot = two_layers
    for name, cam in sim.station.cameras.items():
        assert (cam.model.width, cam.model.height) == (SIZE, SIZE)
        assert shot.views[name].image.shape[:2] == (SIZE, SIZE)
    full = station.cameras["cam1"].model
    assert sim.station.cameras["cam1"].model.center_xy[0] == pytest.approx((full.center_xy[0] + 0.5) * SIZE / 1920 - 0.5)


def test_frame_is_a_jpeg_camera_frame(station):
    from cbh.imageio import decode_image

    sim = SkySimulator(station, load_scene("two-layers"), size_px=128)
    f0 = sim.frame("cam1")
    f1 = sim.frame("cam1", sim.scene.time_utc + timedelta(seconds=10))
    assert isinstance(f0, Frame) and f0.format == "jpeg" and f0.encoded[:2] == b"\xff\xd8"
    np.testing.assert_array_equal(decode_image(f0.encoded), f0.image)
    assert f0.image.shape == (128, 128, 3)
    assert (f0.sequence, f1.sequence) == (0, 1)
    assert f1.time_utc - f0.time_utc == timedelta(seconds=10)
    assert f0.time_utc.tzinfo is not None


def test_jpeg_roundtrip_option(station):
    scene = quiet(load_scene("two-layers"))
    raw = SkySimulator(station, scene, size_px=128).view("cam1")

    def error(quality):
        v = SkySimulator(station, quiet(scene, jpeg_roundtrip=True, jpeg_quality=quality), size_px=128).view("cam1")
        np.testing.assert_array_equal(raw.height_m, v.height_m)  # truth is not compressed
        return np.abs(raw.image.astype(int) - v.image).mean()

    # compression artefacts are there and grow as the quality drops
    assert 0.5 < error(95) < error(60) < 20.0


def test_frames_advect_layers(station):
    sim = SkySimulator(station, load_scene("two-layers"), size_px=96)
    shots = list(sim.frames(None, 3, 20.0))
    assert [s.time_utc - shots[0].time_utc for s in shots] == [timedelta(seconds=20 * i) for i in range(3)]
    for i, s in enumerate(shots):
        for layer, base in zip(s.layers, sim.scene.layers):
            assert layer.offset_m == pytest.approx((base.wind_ms[0] * 20 * i, base.wind_ms[1] * 20 * i))
    assert not np.array_equal(shots[0].views["cam1"].cloud_mask, shots[2].views["cam1"].cloud_mask)


@pytest.mark.parametrize("name", PRESETS)
def test_presets_exist_and_render(station, name):
    assert name in list_scenes()
    scene = load_scene(name)
    shot = SkySimulator(station, scene, size_px=64).render()
    assert set(shot.views) == {"cam1", "cam2"}
    truth = shot.truth()
    assert len(truth["layers"]) == len(scene.layers)


def test_sun_behind_clouds_preset_hides_the_sun(station):
    sim = SkySimulator(station, load_scene("sun-behind-clouds"), size_px=SIZE)
    shot = sim.render()
    for name, v in shot.views.items():
        cam = sim.station.cameras[name]
        x, y = cam.direction_to_pixel(sun_direction(shot.sun_zenith_deg, shot.sun_azimuth_deg))[0]
        assert v.cloud_mask[int(round(y)), int(round(x))]


# --- skylines, hazy horizons, twice-encoded frames (issue 33) -----------------------------------

def _skyline_view(station, kind, **sky):
    """Camera 1 of a clear sky with one ``kind`` of skyline over azimuths 0-120° (40° high), quiet."""
    sc = parse_scene({"name": kind, "time_utc": "2024-06-21T14:00:00Z", "sky": sky,
                      "obstacles": [{"kind": kind, "azimuth_deg": [0.0, 120.0], "max_elevation_deg": 40.0, "seed": 5}]})
    sim = SkySimulator(station, quiet(sc), size_px=SIZE)
    return sim, sim.view("cam1")


def test_skyline_kinds_are_what_they_say(station):
    """Skylines: rows of blocks with notches (sky between roof-top cells of one block), thin masts
    (less than 1° of azimuth each), tree lines with sky between the branches (holes inside a crown's
    outline), sunlit walls brighter than the sky at the same elevation. Their pixels have no height."""
    from cbh.sim.sky import RASTER_BINS_PER_DEG as n, skyline_raster
    from cbh.sim.scene import Obstacle

    def raster(kind):
        ids, pal = skyline_raster((Obstacle(kind=kind, azimuth_deg=(0.0, 120.0), max_elevation_deg=30.0, seed=5),))
        return ids[:, :120 * n] > 0, pal

    occ, pal = raster("masts")
    cols = occ.any(axis=0)
    runs = np.diff(np.flatnonzero(np.diff(np.r_[0, cols.astype(int), 0])))[::2]  # widths of the occupied runs
    assert 1 <= len(runs) and np.median(runs) < 1.0 * n  # thin
    occ, _ = raster("treeline")
    top = np.array([np.flatnonzero(c).max() if c.any() else -1 for c in occ.T])
    below = np.arange(occ.shape[0])[:, None] <= top[None, :]
    assert (below & ~occ).sum() > 0.05 * occ.sum()  # sky seen through the crowns and between trunks
    occ, pal = raster("skyline")
    assert occ.sum() > 0 and pal.shape[1] == 4 and (pal[1:, 3] > 0).any()  # a hazier back row
    sim, v = _skyline_view(station, "walls")
    m = sim.obstacle_mask("cam1")
    assert m.sum() > 500 and np.isnan(v.height_m[m]).all()
    zen = sim.station.cameras["cam1"].zenith_map()
    ring = (zen > 75) & (zen < 80)
    wall, sky = v.image[ring & m].max(axis=1), v.image[ring & ~m].max(axis=1)
    assert np.median(wall) > np.median(sky)  # sunlit: brighter than the sky


def test_a_hazy_horizon_is_a_pale_band_above_it(station):
    """haze_band whitens the clear sky towards the horizon: at 84-86° zenith its red rises by the
    band's 0.8 · exp(−(4..6)/4) = 0.18-0.29 of the way from the sky's ~186 to the haze's 240 DN
    (10-16 DN before vignetting and exposure: 5-15), at 30° zenith (exp(−60/4)) not at all."""
    sim, plain = _skyline_view(station, "masts")
    _, hazy = _skyline_view(station, "masts", haze_band=0.8, haze_band_deg=4.0)
    zen = sim.station.cameras["cam1"].zenith_map()
    free = ~sim.obstacle_mask("cam1")
    for lo, hi, change in ((84, 86, True), (29, 31, False)):
        sel = (zen > lo) & (zen < hi) & free
        d = np.median(hazy.image[sel][:, 2].astype(float)) - np.median(plain.image[sel][:, 2].astype(float))
        assert (5 <= d <= 15) if change else (d == 0), (lo, d)


def test_reencode_adds_a_second_jpeg(station):
    """reencode_quality: the delivered frame is the first JPEG's decoded pixels encoded again."""
    sc = parse_scene({"name": "re", "time_utc": "2024-06-21T14:00:00Z", "layers": [{"height_m": 1500.0, "coverage": 0.5}],
                      "image": {"jpeg_roundtrip": True, "jpeg_quality": 90}})
    once = SkySimulator(station, sc, size_px=240).view("cam1").image
    sc2 = dataclasses.replace(sc, image=dataclasses.replace(sc.image, reencode_quality=70))
    twice = SkySimulator(station, sc2, size_px=240).view("cam1").image
    from cbh.sim.render import reencode

    assert np.array_equal(twice, reencode(once, 70)) and not np.array_equal(twice, once)


def test_random_options_widen_without_changing_the_historical_seeds(station):
    """RandomOptions off: the historical case of each seed; skylines: skyline kinds; unmasked:
    obstacles in every sky and never a mask; kind: that kind; twice_encoded: a second JPEG and a
    clip level 230-255 DN."""
    from cbh.sim.randomize import RandomOptions, random_case
    from cbh.sim.sky import SKYLINE_KINDS

    base = station
    for seed in range(6):
        old = random_case(seed, base)
        assert old.describe() == random_case(seed, base, RandomOptions()).describe()
        wide = random_case(seed, base, RandomOptions(skylines=True, unmasked=True, kind="clear", twice_encoded=True))
        assert wide.kind == "clear" and wide.scene.layers == () and not wide.mask_given
        assert wide.scene.obstacles and all(o.kind in SKYLINE_KINDS for o in wide.scene.obstacles)
        im = wide.scene.image
        clip = 16 + im.white_level * 219 / 255 if im.limited_range else im.white_level
        assert im.reencode_quality > 0 and im.jpeg_roundtrip and 229.5 <= clip <= 255
    with pytest.raises(ValueError, match="kind"):
        RandomOptions(kind="foggy")



def test_mounted_cameras_are_tilted_stacked_and_each_its_own_lens(station):
    """RandomOptions(mounts=True): each camera tilted 0–3° (its yaw kept), camera 2 up to 15 m
    above or below camera 1 (the horizontal baseline kept), each camera's lens the base's own, an
    equidistant or an equisolid one, centred within 2 % of the width; the rest of the seed's sky
    unchanged. The rendered frames agree with the stated geometry: camera 1's cloud points at
    their true heights show camera 1's texture in camera 2 (a renderer that left a camera level,
    at camera 1's height or with the base's lens would put camera 2's view pixels off: a 3° tilt
    is 4 px at 160 px)."""
    from cbh.geometry.station import angles_from_rotation
    from cbh.sim.randomize import RandomOptions, random_case

    kinds = set()
    for seed in range(8):
        plain, mounted = random_case(seed, station), random_case(seed, station, RandomOptions(mounts=True))
        assert mounted.describe().startswith(plain.describe()) and "; mounts " in mounted.describe()
        for name in list(plain.station.cameras)[:2]:
            a, b = plain.station.cameras[name], mounted.station.cameras[name]
            tilt = math.degrees(math.acos(min(1.0, float(b.R_world_from_cam[2, 2]))))
            assert 0.0 <= tilt <= 3.0 + 1e-9
            assert angles_from_rotation(b.R_world_from_cam)[0] == pytest.approx(angles_from_rotation(a.R_world_from_cam)[0])
            assert np.allclose(a.position_m[:2], b.position_m[:2])
            off = np.asarray(b.model.center_xy) - (np.array([b.model.width, b.model.height]) - 1) / 2
            assert np.abs(off).max() <= 0.02 * b.model.width + 1e-9
            kinds.add(b.model.kind)
        dz = mounted.station.cameras["cam2"].position_m[2] - mounted.station.cameras["cam1"].position_m[2]
        assert abs(dz) <= 15.0
    assert kinds == {"ocam", "equidistant", "equisolid"}, kinds
    import cv2

    case = random_case(5, station, RandomOptions(mounts=True, kind="overcast"))  # tilts 2.1° and 0.4°, dz +10.6 m
    sim = SkySimulator(case.station, case.scene, size_px=160)
    shot = sim.render()
    px1, h, pts = cloud_points(sim, shot.views["cam1"])
    px2 = sim.station.cameras["cam2"].world_to_pixel(pts)
    ok = sim.station.cameras["cam2"].model.contains(px2)
    band = lambda g: cv2.GaussianBlur(g, (0, 0), 1.0) - cv2.GaussianBlur(g, (0, 0), 4.0)  # noqa: E731 (as above)
    a = band(gray(shot.views["cam1"].image))[px1[ok, 1].astype(int), px1[ok, 0].astype(int)]
    b = sample(band(gray(shot.views["cam2"].image)), px2[ok])
    assert ok.sum() > 5000 and a.std() > 3.0
    # the same texture where the stated geometry says (0.97 measured; camera 2 taken level at camera
    # 1's height with the base's lens: 0.09)
    assert np.corrcoef(a, b)[0, 1] > 0.85


def test_optics_put_ghosts_across_the_centre_from_the_sun_and_spots_dim_one_camera(station):
    """RandomOptions(optics=True): each camera its own lens-flare ghosts and dome spots, drawn
    onto its finished frame only; the rest of the seed's sky and its truth unchanged. A ghost's
    centre lies on the line from the sun's image through the optical centre, ``ratio`` times the
    sun's distance beyond it (where the frame brightens by its tint); a dome spot dims the sky
    behind it by its transmission (a smooth sky: the blur changes nothing there)."""
    import dataclasses as dc

    from cbh.sim.optics import DomeSpot, Ghost, draw_dome_spot, draw_ghost
    from cbh.sim.randomize import RandomOptions, finish_frames, random_case

    drawn = 0
    for seed in range(6):
        plain, optic = random_case(seed, station), random_case(seed, station, RandomOptions(optics=True))
        assert optic.describe().startswith(plain.describe()) and len(optic.optics) == 2
        assert optic.scene == plain.scene and optic.baseline_m == plain.baseline_m
        drawn += sum(len(g) + len(d) for g, d in optic.optics)
    assert drawn > 6
    case = random_case(3, station, RandomOptions(optics=True, kind="clear"))
    sim = SkySimulator(case.station, case.scene, size_px=240)
    shot = sim.render()
    done = finish_frames(case, sim, shot)
    assert all(np.array_equal(done.views[n].height_m, shot.views[n].height_m, equal_nan=True) for n in ("cam1", "cam2"))
    cam = sim.station.cameras["cam1"]
    sun = sun_direction(*sim.sun(shot.time_utc))
    p_sun = cam.direction_to_pixel(sun[None, :])[0]
    c = np.asarray(cam.model.center_xy)
    im = shot.views["cam1"].image
    g = draw_ghost(im, cam, sun, Ghost(ratio=0.6, radius_frac=0.05, brightness_dn=40.0, tint="green"))
    diff = g.astype(float) - im.astype(float)
    ys, xs = np.nonzero(diff[..., 1] > 20)
    centre = np.array([xs.mean(), ys.mean()])
    assert np.linalg.norm(centre - (c - 0.6 * (p_sun - c))) < 1.5
    assert diff[ys, xs, 1].mean() > diff[ys, xs, 2].mean() + 10  # green: more in G than in R
    hot = im.copy()
    hot[:3, :3] = 255  # above the white the ghost clips at (JPEG's ringing round a clipped sun): kept
    g = draw_ghost(hot, cam, sun, Ghost(ratio=0.6, radius_frac=0.05, brightness_dn=40.0, tint="green"), white_dn=200.0)
    assert np.array_equal(g[:40, :40], hot[:40, :40]) and g.max() == 255
    assert np.all(g.astype(int) <= np.maximum(hot.astype(int), 200))  # no pixel brighter than white or than it was
    spot = DomeSpot(centre_frac=(0.3, -0.2), radius_frac=0.05, blur_frac=0.005, transmission=0.8)
    d = draw_dome_spot(im, cam, spot)
    r_px = float(cam.model.r_from_theta(np.array([math.pi / 2]))[0])
    x, y = (c + np.array(spot.centre_frac) * r_px).round().astype(int)
    assert d[y, x].astype(float).mean() == pytest.approx(0.8 * im[y, x].astype(float).mean(), abs=3.0)
    assert np.array_equal(d[:20, :20], im[:20, :20])  # nothing outside the spot

# --- bad input ---------------------------------------------------------------------------------

@pytest.mark.parametrize("text, key", [
    ('[[layers]]\nheight_m = 1000.0\ncoverage = 0.5\ncolour = "grey"\n', "layers[0].colour"),
    ('[[layers]]\nheight_m = -5.0\ncoverage = 0.5\n', "layers[0].height_m"),
    ('[[layers]]\nheight_m = 1000.0\ncoverage = 0.5\n[[layers]]\nheight_m = 2000.0\ncoverage = 1.5\n',
     "layers[1].coverage"),
    ('[[layers]]\nheight_m = 1000.0\ncoverage = -0.1\n', "layers[0].coverage"),
    ('cloudz = 3\n', "cloudz"),
    ('[sun]\nposition = "moon"\n', "sun.position"),
    ('[sun]\nzenith = 30\n', "sun.zenith"),
    ('time_utc = 2024-06-21T14:00:00\n', "time_utc"),
    ('[[imperfections]]\ncamera = "cam2"\nclock_offset = 2\n', "imperfections[0].clock_offset"),
    ('[[layers]]\nheight_m = "high"\ncoverage = 0.5\n', "layers[0].height_m"),
    ('[[layers]]\ncoverage = 0.5\n', "layers[0].height_m"),
    ('[sky]\nhaze_band = 1.5\n', "sky.haze_band"),
    ('[image]\nreencode_quality = 101\n', "image.reencode_quality"),
    ('[[obstacles]]\nkind = "castle"\nazimuth_deg = [0, 30]\nmax_elevation_deg = 10\n', "obstacles[0].kind"),
])
def test_bad_scene_files_name_the_key(tmp_path, text, key):
    from cbh.errors import ConfigError

    p = tmp_path / "bad.toml"
    p.write_text(text)
    with pytest.raises(ConfigError) as exc:
        load_scene(p)
    assert key in str(exc.value) and "bad.toml" in str(exc.value)
    assert "\n" not in str(exc.value)


def test_bad_scene_other_errors(tmp_path, station):
    from cbh.errors import ConfigError

    p = tmp_path / "broken.toml"
    p.write_text("[[layers]\nheight_m = 1\n")
    with pytest.raises(ConfigError, match="malformed TOML"):
        load_scene(p)
    with pytest.raises(ConfigError, match="not-a-scene"):
        load_scene("not-a-scene")
    scene = parse_scene({"imperfections": [{"camera": "cam9", "clock_offset_s": 1.0}]})
    with pytest.raises(ConfigError, match="cam9"):
        SkySimulator(station, scene)


# --- CLI ---------------------------------------------------------------------------------------

def test_cli_writes_images_truth_and_station(tmp_path, capsys):
    from cbh.cli.main import main

    from cbh.imageio import read_image

    out = tmp_path / "sim"
    rc = main(["simulate", "--scene", "single-cumulus", "--out", str(out), "--frames", "2",
               "--cadence-s", "5", "--size", "96", "--start", "2024-06-21T15:00:00Z"])
    assert rc == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert len(lines) == 2 and lines[0].startswith("20240621T150000.000Z")
    for tag in ("20240621T150000.000Z", "20240621T150005.000Z"):
        for cam in ("cam1", "cam2"):
            img, data = read_image(out / cam / f"{cam}_{tag}.jpg")
            assert img.shape == (96, 96, 3)
        z = np.load(out / "truth" / f"{tag}.npz")
        assert set(z.files) == {"cam1_height_m", "cam1_cloud_mask", "cam2_height_m", "cam2_cloud_mask",
                                   "ground_shade", "ground_thickness", "ground_x_m", "ground_y_m"}
        assert z["cam1_height_m"].shape == (96, 96)
        np.testing.assert_array_equal(z["cam1_cloud_mask"], np.isfinite(z["cam1_height_m"]))
        import json

        truth = json.loads((out / "truth" / f"{tag}.json").read_text())
        assert truth["layers"][0]["height_m"] == 1500.0 and "zenith_deg" in truth["sun"]
    st = load_station(out / "station.toml")
    assert all((c.model.width, c.model.height) == (96, 96) for c in st.cameras.values())
    assert load_scene(out / "scene.toml").name == "single-cumulus"


def test_cli_bad_scene_exits_2(tmp_path, capsys):
    from cbh.cli.main import main

    bad = tmp_path / "bad.toml"
    bad.write_text("[[layers]]\nheight_m = 1000.0\ncoverage = 2.0\n")
    rc = main(["simulate", "--scene", str(bad), "--out", str(tmp_path / "o"), "--size", "64"])
    err = capsys.readouterr().err
    assert rc == 2 and err.startswith("cbh: error:") and "layers[0].coverage" in err
    rc = main(["simulate", "--out", str(tmp_path / "o"), "--start", "yesterday"])
    assert rc == 2 and "--start" in capsys.readouterr().err


def test_camera_servers_print_a_url_a_client_can_open(tmp_path):
    """--bind to one address: the URLs name that address (RTSP said 127.0.0.1 whatever it was
    bound to); --bind 0.0.0.0 (every interface): the URLs name the loopback, which a client on
    this machine can open (0.0.0.0 is not an address to connect to)."""
    import socket
    import urllib.request

    import cv2

    from cbh.sim.camera_server import CameraServer, RtspCameraServer

    jpeg = cv2.imencode(".jpg", np.full((16, 16, 3), (200, 120, 60), np.uint8))[1].tobytes()
    with RtspCameraServer(lambda cam, t: jpeg, ["cam1"], fps=5, host="127.0.0.2") as srv:
        url = srv.url("cam1")
        assert url.startswith("rtsp://127.0.0.2:")
        socket.create_connection(("127.0.0.2", srv.port), timeout=2).close()
    with CameraServer(lambda cam, t: jpeg, ["cam1"], fps=5, host="0.0.0.0") as srv:
        url = srv.url("cam1", "snapshot")
        assert url.startswith("http://127.0.0.1:")
        with urllib.request.urlopen(url, timeout=5) as resp:
            assert resp.read()[:2] == b"\xff\xd8"
