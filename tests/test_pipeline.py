"""Pipeline stages on synthetic inputs, and the whole pipeline on simulated skies.

Simulated-scene tolerances: a flat cloud base at height h seen with baseline B and angular
pixel size δ has a per-pixel height error of about h·δ·h/(B·cos²z) — at 960 px (δ ≈ 0.19°)
with B = 100 m and h = 1 km that is ≈ 3 %, so medians over thousands of pixels are good to well
under 1 % while a *low percentile* (the cloud-base statistic) sits ≈ 1.3 σ_noise below.
"""
from datetime import datetime, timezone

import numpy as np
import pytest

from cbh.errors import ImageError
from cbh.pipeline import FilteringConfig, HeightMapConfig, LayersConfig, Pipeline, PipelineConfig, working_factor
from cbh.pipeline.heightmap import nearest_fill, rasterize_heights
from cbh.pipeline.layers import histogram_layers, layer_stats
from cbh.pipeline.segment import normalized_blue_red, segment
from cbh.pipeline.config import SegmentationConfig
from cbh.presets import station_path
from cbh.station import load_station, rotation_from_angles

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


# --- segmentation -------------------------------------------------------------------------
@pytest.mark.parametrize("method", ["nbr", "nbr_adaptive", "otsu"])
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
        pipe.process(np.zeros((200, 240, 3), np.uint8), ok, T)


# --- simulated skies ----------------------------------------------------------------------
def _sim(layers, size, baseline_m=50.0, yaw2=-5.6, time="2024-06-21T14:00:00Z"):
    from dataclasses import replace

    from cbh.sim import SkySimulator, parse_scene

    st = load_station(station_path("unb-lea"))
    cams = dict(st.cameras)
    cams["cam2"] = replace(cams["cam2"], position_m=np.array([baseline_m, 0.0, 0.0]), R_world_from_cam=rotation_from_angles(yaw2))
    st = replace(st, cameras=cams)
    sim = SkySimulator(st, parse_scene({"name": "t", "time_utc": time, "layers": layers}), size_px=size)
    shot = sim.render()
    return sim, shot


def test_clear_sky_gives_no_layer():
    sim, shot = _sim([], 480)
    r = Pipeline(sim.station).process(shot.views["cam1"].image, shot.views["cam2"].image, shot.time_utc)
    assert r.layers == []
    assert r.cloud_fraction["cam1"] < 0.01 and "clear_sky" in r.flags
    assert np.isnan(r.height_map).all()


def test_single_low_layer_found_and_dense_map_accurate():
    # 1 km cumulus, 100 m baseline, camera 2 yawed 20° against camera 1, sun in view.
    sim, shot = _sim([{"height_m": 1000.0, "coverage": 0.4, "texture_scale_m": 800.0, "seed": 5}], 960, 100.0, 20.0)
    v1 = shot.views["cam1"]
    r = Pipeline(sim.station).process(v1.image, shot.views["cam2"].image, shot.time_utc)
    assert len(r.layers) == 1, [l.to_dict() for l in r.layers]
    layer = r.layers[0]
    assert abs(layer.median_height_m - 1000.0) <= 20.0  # 2 %
    assert 950.0 <= layer.height_m <= 1000.0  # base statistic (10th percentile): within 5 %, low side
    truth = v1.height_m
    cloud = np.isfinite(truth)
    have = cloud & np.isfinite(r.height_map)
    ape = np.abs(r.height_map[have] - truth[have]) / truth[have]
    assert np.median(ape) <= 0.02
    assert have.sum() >= 0.70 * cloud.sum()


@pytest.mark.slow
@pytest.mark.xfail(strict=True, reason="multi-layer bar not met yet: DIS blends heights across layer edges "
                   "(1200 m layer median 1330 m, dense median APE 12 %; see issue 4 report)")
def test_two_layers_full_size_meet_the_bar():
    sim, shot = _sim([{"height_m": 1200.0, "coverage": 0.35, "texture_scale_m": 900.0, "seed": 21},
                      {"height_m": 3500.0, "coverage": 0.3, "texture_scale_m": 1500.0, "seed": 22}], 1920, 100.0, 20.0)
    v1 = shot.views["cam1"]
    r = Pipeline(sim.station).process(v1.image, shot.views["cam2"].image, shot.time_utc)
    assert [round(l.median_height_m / h, 2) for l, h in zip(r.layers, (1200.0, 3500.0))] == [1.0, 1.0]
    assert len(r.layers) == 2
    for layer, h in zip(r.layers, (1200.0, 3500.0)):
        assert abs(layer.height_m - h) <= 0.05 * h
    cloud = np.isfinite(v1.height_m)
    have = cloud & np.isfinite(r.height_map)
    assert np.median(np.abs(r.height_map[have] - v1.height_m[have]) / v1.height_m[have]) <= 0.02
    assert have.sum() >= 0.7 * cloud.sum()
