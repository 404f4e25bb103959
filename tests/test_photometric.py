"""Photometric invariance between the two cameras (issue 11): the simulator's per-camera colour
response, its estimate and removal, results that do not depend on it, and the robust layer base.
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from cbh.geometry.station import load_station
from cbh.pipeline import Pipeline
from cbh.pipeline.config import LayersConfig
from cbh.pipeline.layers import layer_stats
from cbh.pipeline.photometric import ColourResponse, estimate_response
from cbh.presets import station_path
from cbh.sim import Imperfection, SkySimulator, load_scene, parse_scene
from cbh.sim.evaluate import station_variant

# camera 2's response: 0.55× gain, gamma 0.8, red ×1.12, blue ×0.88 (a different make, exposed
# about a stop darker): far beyond the exposure_mismatch bars
GAIN, GAMMA, WB = 0.55, 0.8, (1.12, 0.88)


def _render(scene: str, imperfections: dict, size: int = 480):
    st = station_variant(load_station(station_path()), 50.0, -5.6)
    sim = SkySimulator(st, dataclasses.replace(load_scene(scene), imperfections=imperfections), size_px=size)
    return sim, sim.render()


def test_scene_colour_response_keys_parse_and_validate():
    sc = parse_scene({"layers": [{"height_m": 1000.0, "coverage": 0.3}], "imperfections": [
        {"camera": "cam2", "gain": 0.5, "gamma": 0.8, "white_balance": [1.1, 0.9]}]})
    imp = sc.imperfection("cam2")
    assert (imp.gain, imp.gamma, imp.white_balance) == (0.5, 0.8, (1.1, 0.9)) and imp.has_colour_response
    assert not sc.imperfection("cam1").has_colour_response
    from cbh.errors import ConfigError

    with pytest.raises(ConfigError, match="gamma"):
        parse_scene({"layers": [], "imperfections": [{"camera": "cam2", "gamma": 0.0}]})


def test_simulated_colour_response_changes_only_the_colours():
    imp = {"cam2": Imperfection(camera="cam2", gain=GAIN, gamma=GAMMA, white_balance=WB)}
    sim0, shot0 = _render("single-cumulus", {}, 240)
    sim1, shot1 = _render("single-cumulus", imp, 240)
    a, b = shot0.views["cam2"], shot1.views["cam2"]
    assert np.array_equal(a.cloud_mask, b.cloud_mask)  # same sky, same truth
    assert np.array_equal(shot0.views["cam1"].image, shot1.views["cam1"].image)
    # green channel: 255·(0.55·x)^0.8 (± 1 DN of rounding and noise of the reference render)
    x = a.image[..., 1].astype(float) / 255.0
    want = 255.0 * np.clip(GAIN * x, 0, 1) ** GAMMA
    assert np.abs(b.image[..., 1] - want)[a.image[..., 1] > 20].max() <= 1.5


def test_estimate_recovers_the_response_and_its_inverse():
    imp = {"cam2": Imperfection(camera="cam2", gain=GAIN, gamma=GAMMA, white_balance=WB)}
    sim, shot = _render("two-layers", imp)
    pipe = Pipeline(sim.station)
    u1, u2 = pipe.static_mask(0), pipe.static_mask(1)
    resp = estimate_response(shot.views["cam1"].image, shot.views["cam2"].image, pipe.geometry, u1, u2)
    # simulated: I2 = 255·(g·wb_c·I1/255)^γ. Its inverse, I1 = 255·(k_c·I2/255)^(1/γ) with
    # k_c = (g·wb_c)^−γ, is what the estimate reports (camera 2 → camera 1). Tolerance 3 %: the
    # cameras see the same sky 50 m apart (parallax shifts the clouds a little), in 8 bits.
    assert resp.gamma == pytest.approx(1 / GAMMA, rel=0.03)
    assert resp.gain == pytest.approx(GAIN ** -GAMMA, rel=0.03)
    assert resp.wb_red == pytest.approx(WB[0] ** -GAMMA, rel=0.03)
    assert resp.wb_blue == pytest.approx(WB[1] ** -GAMMA, rel=0.03)
    assert resp.is_large() and resp.brightens()
    inv = resp.inverse()
    assert inv.gamma == pytest.approx(GAMMA, rel=0.03) and inv.gain == pytest.approx(GAIN, rel=0.03)
    # identical cameras: the identity, no flag
    sim0, shot0 = _render("two-layers", {})
    r0 = estimate_response(shot0.views["cam1"].image, shot0.views["cam2"].image, pipe.geometry, u1, u2)
    assert abs(math.log(r0.gain)) < 0.02 and abs(r0.gamma - 1) < 0.02 and not r0.is_large()
    assert ColourResponse().is_identity


@pytest.mark.parametrize("scene", ["single-cumulus", "two-layers"])
def test_independent_exposure_gives_the_same_layers_and_cloud_fractions(scene):
    """Real-appearance stereo under independent exposure: the issue's bars (layers within 2 %,
    no spurious layer, the cameras' cloud fractions within 0.05)."""
    sim, shot = _render(scene, {"cam2": Imperfection(camera="cam2", gain=GAIN, gamma=GAMMA, white_balance=WB)})
    r = Pipeline(sim.station).process(shot.views["cam1"].image, shot.views["cam2"].image, shot.time_utc, channels="bgr")
    truth = [l.height_m for l in shot.layers]
    assert len(r.layers) == len(truth)
    for L, h in zip(r.layers, truth):
        assert abs(L.height_m - h) <= 0.02 * h
    f = list(r.cloud_fraction.values())
    assert abs(f[0] - f[1]) <= 0.05
    assert "exposure_mismatch" in r.flags
    d = r.diagnostics
    assert d["exposure_gain"] == pytest.approx(GAIN ** -GAMMA, rel=0.05)
    assert d["exposure_gamma"] == pytest.approx(1 / GAMMA, rel=0.05)
    assert {"wb_red", "wb_blue"} <= set(d)


def test_over_exposed_camera_keeps_its_saturated_cloud():
    """Camera 2 over-exposed (×1.5): its cloud saturates; far from the sun that is cloud, not glare."""
    sim, shot = _render("two-layers", {"cam2": Imperfection(camera="cam2", gain=1.5, gamma=1.15, white_balance=(1.1, 0.85))})
    r = Pipeline(sim.station).process(shot.views["cam1"].image, shot.views["cam2"].image, shot.time_utc, channels="bgr")
    f = list(r.cloud_fraction.values())
    assert abs(f[0] - f[1]) <= 0.05
    assert [abs(L.height_m - h) <= 0.02 * h for L, h in zip(r.layers, [1200.0, 3500.0])] == [True, True]


# --- the robust layer base ---------------------------------------------------------------------
def test_base_is_the_median_when_noise_explains_the_spread():
    rng = np.random.default_rng(1)
    h = 830.0 + 200.0 * rng.standard_normal(10000)
    # predicted noise 190 m against an observed spread of ≈ 200 m: within the 1.2 margin of the
    # noise model, so the base is the median (not median − 1.28·σ ≈ 570 m)
    L = layer_stats(h, 0.5, LayersConfig(), np.full(h.size, 190.0))
    assert L.height_m == pytest.approx(L.median_height_m)
    # continuous: the base moves away from the median only as the spread outgrows the noise
    # (σ_true = sqrt(200.7² − (1.2·165)²) ≈ 33 m → base ≈ median − 42 m; no jump to − 256 m)
    bases = [layer_stats(h, 0.5, LayersConfig(), np.full(h.size, s)).height_m for s in (165.0, 160.0, 150.0)]
    assert L.height_m > bases[0] > bases[1] > bases[2]
    assert bases[0] > L.median_height_m - 50.0


@pytest.mark.parametrize("n", [1, 2, 7, 30_000])
def test_channel_percentiles_of_uint8_pixels_equal_numpys_to_the_bit(n):
    """The response's quantiles come from 256-bin histograms, not a sort: they must be NumPy's
    linear percentiles exactly (any drift would move the fitted gain and gamma)."""
    from cbh.pipeline.photometric import _QUANTILES, channel_percentiles

    rng = np.random.default_rng(n)
    for v in (rng.integers(0, 256, (n, 3)), np.clip(rng.normal(200, 60, (n, 3)), 0, 255), np.full((n, 3), 255)):
        v8 = v.astype(np.uint8)
        want = np.percentile(v8.astype(np.float64), _QUANTILES, axis=0)
        np.testing.assert_array_equal(channel_percentiles(v8, _QUANTILES), want)
    f = rng.random((n, 3)) * 255.0  # not uint8: numpy's own path
    np.testing.assert_array_equal(channel_percentiles(f, _QUANTILES), np.percentile(f, _QUANTILES, axis=0))
