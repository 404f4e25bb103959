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


def test_capped_slope_keeps_the_table_under_it_monotone_and_within_the_slope():
    """The cap's contract on random non-decreasing tables: never above the table, non-decreasing,
    a rise over any n levels within slope · max(n, span), and the table itself where it already
    keeps that."""
    from cbh.pipeline.photometric import capped_slope

    rng = np.random.default_rng(71)
    for _ in range(50):
        t = np.cumsum(rng.exponential(1.0, 256) ** 3)
        slope, span = float(rng.uniform(1.0, 4.0)), int(rng.integers(1, 6))
        c = capped_slope(t, slope, span)
        assert (c <= t + 1e-9).all() and (np.diff(c) >= -1e-9).all()
        for n in range(1, 24):
            assert (c[n:] - c[:-n] <= slope * max(n, span) + 1e-6).all()
    gentle = np.linspace(0.0, 255.0, 256) * 0.9
    assert np.array_equal(capped_slope(gentle, 3.0, 4), gentle)


def test_a_camera_compressed_at_its_clip_is_not_stretched_onto_the_other():
    """Camera 2 brighter (mapped down at mid-grey) but its blue compressed near its clip into
    237–250 DN where camera 1 spans 182–236 (randomized 19871's clear sky): the matching table
    follows the percentiles below and rises at most 2 levels per level over any 4 levels at the
    top (uncapped: 10 levels per level, each JPEG step of camera 2 stretched into a cloud edge)."""
    from cbh.pipeline.photometric import LUT_SLOPE_SPAN, MAX_LUT_SLOPE

    q = np.linspace(0.5, 99.5, 100)
    low2 = np.linspace(10.0, 236.0, 80)  # camera 2 up to 236 DN, mapped down by 0.78
    q2 = np.concatenate([low2, np.linspace(237.0, 250.0, 20)])
    q1 = np.concatenate([0.78 * low2, np.linspace(184.0, 236.0, 20)])
    qs2, qs1 = (np.repeat(np.round(v)[:, None], 3, axis=1) for v in (q2, q1))
    lut21, _ = ColourResponse(pixels=len(q), q1=qs1, q2=qs2).matching_luts(capped=True)
    b = lut21[:, 0, 0].astype(int)
    assert (b[4:] - b[:-4]).max() <= MAX_LUT_SLOPE * LUT_SLOPE_SPAN
    assert abs(int(b[200]) - round(0.78 * 200)) <= 1  # below the shoulder: the percentiles, followed
    assert int(b[250]) <= int(b[237]) + 3 * 13 + 1  # the top left compressed


@pytest.mark.parametrize("seed", [19871, pytest.param(19844, marks=pytest.mark.slow)])
def test_a_clear_sky_with_contrails_is_not_cloud_in_a_camera_compressed_at_its_clip(seed):
    """Randomized clear skies with contrails (``eval_random.py --n 60 --seed 19840 --size 480
    --optics --mounts --skylines --unmasked --twice-encoded --contrails --overlays``), camera 2's
    blue squeezed near its clip. 19871: a pale sky (true cloud 0.020) at 246–250 DN; its matching
    table stretched that 10×, and camera 2 read 0.528 of its sky as cloud in JPEG-block shapes.
    19844 (true cloud 0.032): its aureole at 245–251 DN stretched 22× read as a ring of cloud
    round the sun (0.084). Now each camera reads the contrails (within 0.02 of the truth: the
    trails' soft edges, and 19844's unmasked facades)."""
    import tempfile

    from cbh.sim.randomize import RandomOptions, run_random_case

    hard = dict(optics=True, mounts=True, skylines=True, unmasked=True, twice_encoded=True, contrails=True,
                overlays=True)
    with tempfile.TemporaryDirectory() as t:
        _, r, score, _ = run_random_case(seed, load_station(station_path("unb-lea")), 480, t,
                                         options=RandomOptions(**hard))
    assert 0.0 < score.cloud_fraction < 0.04  # contrails only
    assert max(r.cloud_fraction.values()) <= score.cloud_fraction + 0.02


@pytest.mark.slow
@pytest.mark.xfail(strict=True, reason="found in stop 71: a 421 m deck at 480 px that a 3 DN change of camera 1's "
                                       "matching table loses")
def test_an_overexposed_cameras_low_deck_survives_its_capped_table(tmp_path):
    """Randomized 17916 (``eval_random.py --n 100 --seed 17830 --size 480``): decks at 421, 1349
    and 3460 m, camera 1 over-exposed (its blue at 255 over half the sky, red 244) and mapped
    down onto camera 2. Before the slope cap it found 436 / 1388 / 4077 m; capped (camera 1's
    tables changed by up to 23 DN at its top; a cap of 5 levels per level, which changes them by
    3 DN, loses it too) the 421 m deck is lost: camera 1 reads 0.403 of its sky as cloud (truth
    0.449, 0.457 before)."""
    from cbh.sim.randomize import run_random_case

    _, r, score, _ = run_random_case(17916, load_station(station_path("unb-lea")), 480, tmp_path)
    assert not score.missed_m
