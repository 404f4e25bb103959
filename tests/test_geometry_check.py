"""No confident wrong answer: each pair checks itself against the station geometry (issue 10.5),
and the sun check reports the detected vs predicted sun (issue 12.4).

Simulated pairs at 480 px (working size = full size; LK's median epipolar distance on a correct
geometry is ~0.1 px, the check's floor is 1 px); the real WAHRSIS pair for a real calibration
whose rays miss by 2–3 % of the range.
"""
from __future__ import annotations

import logging
import math
from datetime import datetime, timedelta, timezone

import numpy as np
import pytest

from cbh.flags import INVALIDATING
from cbh.geometry.station import load_station
from cbh.pipeline import Pipeline
from cbh.sim import SkySimulator, load_scene
from cbh.sim.randomize import RandomOptions, run_random_case
from cbh.sim.scene import Imperfection

T0 = datetime(2024, 6, 21, 14, 0, tzinfo=timezone.utc)


@pytest.fixture(scope="module")
def unb(repo):
    return load_station(repo / "configs" / "unb-lea.toml")


@pytest.fixture(scope="module")
def sim(unb, repo):
    return SkySimulator(unb, load_scene(repo / "configs" / "scenes" / "two-layers.toml"), size_px=480)


@pytest.fixture(scope="module")
def shot(sim):
    return sim.render(T0)


@pytest.fixture(scope="module")
def pipe(sim):
    return Pipeline(sim.station)


def test_correct_station_is_not_flagged(pipe, shot):
    r = pipe.process(shot.views["cam1"].image, shot.views["cam2"].image, T0, channels="bgr")
    assert "geometry_mismatch" not in r.flags and "identical_images" not in r.flags
    assert r.diagnostics["geometry_residual_px"] < 0.5  # matching noise, far below the 1 px floor
    assert r.diagnostics["geometry_inlier_fraction"] > 0.9
    assert r.diagnostics["geometry_rotation_deg"] < 0.05  # noise; 0.25 px is 0.095° at this size
    assert not (set(r.flags) & INVALIDATING)


def test_same_image_twice_is_always_flagged(pipe, shot):
    img = shot.views["cam1"].image
    r = pipe.process(img, img.copy(), T0, channels="bgr")
    assert "identical_images" in r.flags
    assert "geometry_mismatch" in r.flags  # no parallax: the rays meet at infinity


def test_same_camera_twice_is_flagged(pipe, sim):
    """Both sources on camera 1, frames 10 s apart (the clouds moved 60 m): not identical, but
    its rays have camera 1's parallax, not the baseline's."""
    a = sim.render(T0, cameras=["cam1"]).views["cam1"].image
    b = sim.render(T0 + timedelta(seconds=10), cameras=["cam1"]).views["cam1"].image
    r = pipe.process(a, b, T0, channels="bgr")
    assert "identical_images" not in r.flags
    assert "geometry_mismatch" in r.flags


def test_swapped_cameras_are_flagged(pipe, shot):
    r = pipe.process(shot.views["cam2"].image, shot.views["cam1"].image, T0, channels="bgr")
    assert "geometry_mismatch" in r.flags


# one misorientation in the default tier (8 s each at this size); the others in the slow tier
@pytest.mark.parametrize("error_deg", [(0.0, 0.0, 0.25),
                                       pytest.param((0.1, 0.0, 0.0), marks=pytest.mark.slow),
                                       # 0.05° is the check's resolution: a −0.05° roll (3500 m layer −8 %)
                                       # is caught; subtracting 3 σ from the size let it through
                                       pytest.param((0.0, 0.0, -0.05), marks=pytest.mark.slow),
                                       pytest.param((0.0, 0.5, 0.0), marks=pytest.mark.slow),
                                       pytest.param((0.6, 0.0, 0.0), marks=pytest.mark.slow),
                                       pytest.param((-5.6, -0.4, 0.25), marks=pytest.mark.slow)])
@pytest.mark.slow
def test_misoriented_camera_is_flagged(unb, repo, error_deg):
    """A tenth of a degree off is enough at the default working size (960 px images: 306 px/rad
    at 45° off axis, so 0.1° ≈ 0.53 px, against the rotation's 0.25 px). A 0.25° roll leaves a
    median epipolar distance of only 0.25 px (the 1 px floor let it through, and the 3500 m
    layer came out at 5341 m); the fitted rotation finds the error itself (to 0.03°)."""
    from dataclasses import replace

    scene = load_scene(repo / "configs" / "scenes" / "two-layers.toml")
    scene = replace(scene, imperfections={"cam2": Imperfection("cam2", rotation_error_deg=error_deg)})
    s = SkySimulator(unb, scene, size_px=960)
    shot = s.render(T0)
    r = Pipeline(s.station).process(shot.views["cam1"].image, shot.views["cam2"].image, T0, channels="bgr")
    assert "geometry_mismatch" in r.flags, r.diagnostics
    # the fit uses the matches within 2 px of their curves: it sizes turns up to 0.25°; a larger
    # one (flagged by the median distance already) pushes most matches out and comes out low
    if max(map(abs, error_deg)) <= 0.25:
        assert r.diagnostics["geometry_rotation_deg"] == pytest.approx(float(np.linalg.norm(error_deg)), abs=0.03)


def test_relative_rotation_recovers_a_small_turn_despite_outliers():
    """Rays of points on a 2 km plane seen from two cameras 50 m apart; camera 2's rays turned by
    a known 0.1° rotation, 0.1 px-like noise (3e-4 rad), and 10 % of the matches replaced by
    random rays (mismatches): the robust fit returns the turn that undoes it, to 1e-4 rad
    (0.006°, a thirtieth of the 0.05° it must resolve)."""
    from cbh.geometry.calibrate import rotvec_to_matrix
    from cbh.pipeline.geocheck import relative_rotation

    rng = np.random.default_rng(3)
    n = 600
    p = np.stack([rng.uniform(-4000, 4000, n), rng.uniform(-4000, 4000, n), np.full(n, 2000.0)], 1)
    o2 = np.array([50.0, 0.0, 0.0])
    d1 = p / np.linalg.norm(p, axis=1, keepdims=True)
    d2 = (p - o2) / np.linalg.norm(p - o2, axis=1, keepdims=True)
    w_true = np.radians([0.06, -0.05, 0.06])
    d2 = d2 @ rotvec_to_matrix(w_true).T + rng.normal(0, 3e-4, (n, 3))
    bad = rng.random(n) < 0.1
    d2[bad] = rng.normal(size=(bad.sum(), 3)) * [1, 1, 0.2] + [0, 0, 1]
    d2 /= np.linalg.norm(d2, axis=1, keepdims=True)
    omega, sigma = relative_rotation(d1, d2, o2)
    np.testing.assert_allclose(omega, -w_true, atol=1e-4)
    assert 0 < sigma < 1e-4


def test_rotation_fit_trusts_the_matches_of_unsheared_views_more():
    """A correct station (no turn): matches on a far deck (2 km, B = 50 m: views 1.4° apart)
    unbiased, and as many on a near deck (300 m at B = 241 m: 39° apart, its texture sheared by
    ~0.7 between the views) all pushed across their curves one way (LK on a sheared patch is
    biased, not only noisy). Fitted on all alike the bias reads as a turn of ~0.1°; weighted by
    the views' shear (as :func:`check_geometry` does) the fit stays within 0.01° of none."""
    from cbh.geometry.calibrate import rotvec_to_matrix
    from cbh.pipeline.geocheck import _SHEAR_SCALE, relative_rotation

    rng = np.random.default_rng(5)
    n = 300
    o2 = np.array([241.0, 0.0, 0.0])
    far = np.stack([rng.uniform(-3000, 3000, n), rng.uniform(-3000, 3000, n), np.full(n, 2000.0)], 1)
    near = np.stack([rng.uniform(-400, 400, n), rng.uniform(-400, 400, n), np.full(n, 300.0)], 1)
    p = np.concatenate([far, near])
    d1 = p / np.linalg.norm(p, axis=1, keepdims=True)
    d2 = (p - o2) / np.linalg.norm(p - o2, axis=1, keepdims=True)
    bias = rotvec_to_matrix(np.radians([0.0, 0.12, 0.0]))  # the near deck's matches, pushed one way
    d2[n:] = d2[n:] @ bias.T
    d2 += rng.normal(0, 3e-4, d2.shape)
    d2 /= np.linalg.norm(d2, axis=1, keepdims=True)
    shear = np.arccos(np.clip(np.einsum("ij,ij->i", d1, d2), -1, 1))  # the views' angle [rad]
    plain, _ = relative_rotation(d1, d2, o2)
    weighted, _ = relative_rotation(d1, d2, o2, prior=1.0 / (1.0 + (shear / _SHEAR_SCALE) ** 2))
    assert math.degrees(np.linalg.norm(plain)) > 0.05
    assert math.degrees(np.linalg.norm(weighted)) < 0.01


def test_patches_that_disagree_make_no_significant_turn():
    """A correct station whose matches are biased across their curves patch by patch (each patch
    of sky by an offset of its own, 0.03° rms, as LK's matches on one deck share a bias: randomized
    seeds 4028 and 11). The normal equations' σ shrinks with the 600 matches and calls the turn
    they ask for significant (8 σ); the turn explains almost none of their scatter, and the
    patches' jackknife σ says it is no turn (under 4 σ). The same matches turned alike by a real
    0.05° (every patch agrees) are at > 10 σ."""
    from cbh.geometry.calibrate import rotvec_to_matrix
    from cbh.pipeline.geocheck import _EXPLAINS, _GROUP_RAD, _SIGNIFICANCE, _explained, _patches, relative_rotation

    rng = np.random.default_rng(5)
    n = 600
    o2 = np.array([66.0, 0.0, 0.0])
    h = np.where(rng.random(n) < 0.5, 1000.0, 3000.0)
    p = np.stack([rng.uniform(-1.2, 1.2, n) * h, rng.uniform(-1.2, 1.2, n) * h, h], 1)
    d1 = p / np.linalg.norm(p, axis=1, keepdims=True)
    d2 = (p - o2) / np.linalg.norm(p - o2, axis=1, keepdims=True)
    # camera 1's pixels (an equidistant 480 px lens): the patches are squares of the image
    theta = np.arccos(d1[:, 2])
    px1 = 480.0 + 480.0 * theta[:, None] / (np.pi / 2) * d1[:, :2] / np.linalg.norm(d1[:, :2], axis=1, keepdims=True)
    groups = _patches(px1, 480.0 / (np.pi / 2), _GROUP_RAD)
    ids, inv = np.unique(groups, return_inverse=True)
    normal = np.cross(o2[None, :], d1)
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    offset = rng.normal(0.0, 6e-4, len(ids))[inv]  # each patch's own push across its curves [rad]
    biased = d2 + offset[:, None] * normal + rng.normal(0, 3e-4, (n, 3))
    biased /= np.linalg.norm(biased, axis=1, keepdims=True)
    omega, formal = relative_rotation(d1, biased, o2)
    _, sigma = relative_rotation(d1, biased, o2, groups=groups)
    e0 = np.einsum("ij,ij->i", biased, normal)
    assert _explained(e0, e0 + np.cross(biased, normal) @ omega) < _EXPLAINS
    assert np.linalg.norm(omega) > _SIGNIFICANCE * formal  # what flagged the correct stations
    assert np.linalg.norm(omega) < _SIGNIFICANCE * sigma
    # on two grids (the second shifted by half a side) the larger σ stands
    shifted = _patches(px1, 480.0 / (np.pi / 2), _GROUP_RAD, 0.5)
    _, s_shifted = relative_rotation(d1, biased, o2, groups=shifted)
    _, s_both = relative_rotation(d1, biased, o2, groups=[groups, shifted])
    assert s_shifted != sigma and s_both == max(sigma, s_shifted)
    turned = d2 @ rotvec_to_matrix(np.radians([0.05, 0.0, 0.0])).T + rng.normal(0, 3e-4, (n, 3))
    turned /= np.linalg.norm(turned, axis=1, keepdims=True)
    om_t, sig_t = relative_rotation(d1, turned, o2, groups=groups)
    assert math.degrees(np.linalg.norm(om_t)) == pytest.approx(0.05, abs=0.005)
    assert np.linalg.norm(om_t) > 10 * sig_t


def test_patches_are_the_same_sky_at_any_working_size():
    """The jackknife's patches are squares of sky (30° at camera 2's scale 45° off axis), not of
    pixels: the same matches at half the working size fall in the same patches, as many as at
    960 px. With 160 px squares, an overcast's matches within 40° of the zenith at 480 px fell in
    3 patches, too few for the jackknife, and the formal σ made their shared 0.01 px bias a
    significant turn on a correct station (randomized 17716, 17138, 17389)."""
    from cbh.pipeline.geocheck import _GROUP_RAD, _MIN_GROUPS, _patches

    rng = np.random.default_rng(3)
    theta = np.radians(rng.uniform(0.0, 40.0, 300))
    az = rng.uniform(0.0, 2 * np.pi, 300)
    unit = np.stack([np.cos(az), np.sin(az)], 1) * theta[:, None]  # equidistant lens [rad from the centre]
    counts = []
    for radius_px in (480.0, 240.0):
        ppr = radius_px / (np.pi / 2)
        g = _patches(radius_px + ppr * unit, ppr, _GROUP_RAD)
        counts.append(len(np.unique(g)))
        if radius_px == 480.0:
            first = np.unique(g, return_inverse=True)[1]
        else:
            assert np.array_equal(np.unique(g, return_inverse=True)[1], first)
    assert counts[1] == counts[0] >= _MIN_GROUPS


def test_a_turn_the_matches_barely_constrain_is_one_small_biases_make():
    """Matches within 40° of the zenith (an overcast's, randomized 17716) barely constrain the turn
    about the horizontal axis across the baseline: it moves them along their curves. Biases of 1
    on their epipolar angles can make a turn 6 or more times as large along it, while matches
    over the whole sky bound every direction's gain under 3: only there is a turn that needs
    biases beyond ``_SHARED_BIAS_PX`` judged on its formal σ alone."""
    from cbh.pipeline.geocheck import _bias_gain

    rng = np.random.default_rng(2)
    o2 = np.array([50.0, 0.0, 0.0])
    gains = {}
    for name, max_z in (("zenith", 40.0), ("sky", 80.0)):
        z, az = np.radians(rng.uniform(0.0, max_z, 400)), rng.uniform(0.0, 2 * np.pi, 400)
        d1 = np.stack([np.sin(z) * np.cos(az), np.sin(z) * np.sin(az), np.cos(z)], 1)
        p = d1 * (3000.0 / d1[:, 2:])
        d2 = (p - o2) / np.linalg.norm(p - o2, axis=1, keepdims=True)
        n = np.cross(o2[None, :], d1)
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        J = np.cross(d2, n)
        gains[name] = [_bias_gain(J, np.ones(len(J)), u) for u in np.eye(3)]
    across = 1  # the y axis: horizontal, across the x baseline
    assert gains["zenith"][across] > 6.0  # 8.7 here; 17716's matches, nearer the zenith: 13
    assert max(gains["sky"]) < 3.0 and gains["sky"][across] < gains["zenith"][across] / 3


_DENSE_HARD = RandomOptions(skylines=True, unmasked=True, twice_encoded=True, contrails=True, dense=True)


def _quiet_correct_station(seed: int, size: int, tmp_path, options: RandomOptions = RandomOptions()):
    """Randomized sky ``seed`` at ``size`` px on its correct station: no invalidating flag.
    Returns (result, score) (:func:`cbh.sim.randomize.run_random_case`)."""
    from cbh.presets import station_path

    _, r, score, _ = run_random_case(seed, load_station(station_path()), size, tmp_path, options=options)
    assert not set(r.flags) & INVALIDATING, (r.flags, r.diagnostics.get("geometry_rotation_deg"))
    return r, score


@pytest.mark.slow
@pytest.mark.xfail(strict=True, raises=AssertionError, reason="a known limit (docs/accuracy.md, Limits): one sheared deck's shared LK bias")
def test_randomized_low_deck_far_apart_is_no_turn(tmp_path):
    """Randomized overcast seed 15821 at 480 px (skylines): one 556 m deck seen by cameras 189 m
    apart, the true orientation given, is flagged geometry_mismatch (a fitted turn of 1.03° ±
    0.087° along the direction its 117 LK matches barely constrain); the deck is at 556 m. Kept as
    a strict expected failure: a fix makes it pass, and then this mark must go. (Widening σ by
    the matches' shared shear bias fixed it, and also hid a camera 2° off level seen 630 m away.)"""
    r, _ = _quiet_correct_station(15821, 480, tmp_path, RandomOptions(kind="overcast", skylines=True))
    assert [round(L.height_m, -1) for L in r.layers] == [560.0]


@pytest.mark.slow
def test_randomized_clear_sky_with_horizon_only_matches_is_no_turn(tmp_path):
    """Randomized clear seed 15523 at 960 px (skylines, unmasked obstacles, twice encoded; B =
    196 m): its only LK matches, 67–80° from the zenith and at infinity, are on bright unmasked
    skyline blocks read as cloud; they fit a turn of 0.075° ± 0.014° and flagged the correct
    station geometry_mismatch. Passing since stop 56, whose geometry check leaves out matches
    within half a window of a camera's clipped pixels where the two cameras' responses differ
    (:func:`cbh.pipeline.masks.near_clip`)."""
    _quiet_correct_station(15523, 960, tmp_path, RandomOptions(skylines=True, unmasked=True, twice_encoded=True))


@pytest.mark.slow
def test_randomized_deck_whose_matches_lean_by_azimuth_is_no_turn(tmp_path):
    """Fresh dense sky 16727 of stop 54 at 480 px (skylines, unmasked obstacles, twice encoded;
    1176 m over 69 % of the sky, 7146 m through its gaps, B = 49 m, the sun 16° from the zenith):
    the correct station is flagged geometry_mismatch. Its 508 LK matches, all on the 1176 m deck,
    miss their curves by ±0.06–0.08 px in a pattern of period 180° in azimuth and fit a turn of
    0.099° ± 0.014°, just over the 0.094° that 0.25 px is at this size. Taking Lucas–Kanade's
    peak locking out of them (the sky clock's bicubic steps) gives 0.079°, no flag, but leaves
    the pattern: not the cause. Passing since stop 63, whose rotation fit leaves out matches within
    2 tolerances of infinity (as for 17165): 0.106° ± 0.041°, not significant."""
    _quiet_correct_station(16727, 480, tmp_path,
                           RandomOptions(skylines=True, unmasked=True, twice_encoded=True, dense=True))


@pytest.mark.slow
def test_randomized_high_deck_through_a_low_decks_gaps_is_no_turn(tmp_path):
    """Fresh dense sky 17138 of stop 62 at 480 px (``eval_random.py --n 30 --seed 17124 --size 480
    --skylines --unmasked --twice-encoded --contrails --dense``; 1594 m over 62 % of the sky, 9271 m
    through its gaps, B = 99 m, masts and a tree line): the correct station is flagged
    geometry_mismatch. 361 of its 369 LK matches fit a turn of 0.160° ± 0.029° (tolerance 0.090°),
    their median parallax 1.8 px: the far deck's, seen through the near one's gaps. Not the
    contrails (drawn out, the same turn), not the masts (5 of the fit beside them). At 960 px the
    same sky fits 0.045° against a tolerance of 0.045°: a bias of ≈ 0.2–0.4 working pixels in
    either, like the two known limits above. Passing since stop 67, whose patches of sky for the
    turn's jackknife σ are a fixed angle (30°), not 160 px: at 480 px the matches now fall in
    enough patches for their disagreement to count."""
    _quiet_correct_station(17138, 480, tmp_path, _DENSE_HARD)


@pytest.mark.slow
def test_randomized_dense_deck_with_few_lk_matches_is_no_turn(tmp_path):
    """Fresh dense sky 17389 of stop 64 at 480 px (``eval_random.py --n 30 --seed 17382 --size 480
    --dense --skylines --unmasked --twice-encoded --contrails``; 3578 m over 79 % of the sky, 5146 m
    over 42 %, B = 184 m, skylines and tree lines unmasked): the correct station is flagged
    geometry_mismatch. Its 37 LK matches, all within 42° of the zenith (median parallax 7.5 px:
    the 3578 m deck's), lie 0.05 px off their curves (median) yet fit a turn of 0.176° ± 0.030°
    against a tolerance of 0.090°; at 960 px LK keeps 15 and the check does not run. 17138's kind
    (above), with ten times fewer matches. Passing since stop 67 (patches of 30° of sky, as for
    17138)."""
    _quiet_correct_station(17389, 480, tmp_path, _DENSE_HARD)


@pytest.mark.slow
@pytest.mark.xfail(strict=True, raises=AssertionError, reason="found in stop 64, not fixed (docs/accuracy.md, Stop 64)")
def test_randomized_low_deck_and_a_higher_one_with_default_options_is_no_turn(tmp_path):
    """Fresh sky 17498 of stop 64 at 960 px with the default options (``eval_random.py --n 30
    --seed 17482 --size 960``: 34 / 34 layers, this the one false alarm): 314 m over 35 % of the
    sky and 1173 m over 16 %, B = 145 m, white at 255, JPEG 60. The correct station is flagged
    geometry_mismatch: a turn of 0.143° ± 0.021° (median distance 0.29 px, 94 % inliers). The
    314 m deck's views are sheared by 0.46 rad, so the fit weighs its matches little. Established
    in stop 67: 48 of the 50 matches fitted lie on the 1173 m deck, 50–71° from the zenith, and
    alone ask for 0.144° ± 0.022° against a tolerance of 0.059°; the turn takes 31 % off their
    scatter, so the patches' σ is not asked. At 480 px no turn is fitted and both decks are found."""
    _quiet_correct_station(17498, 960, tmp_path)


@pytest.mark.slow
def test_randomized_low_overcast_with_horizon_matches_is_no_turn(tmp_path):
    """Fresh sky 17165 of stop 63 at 960 px (``eval_random.py --n 30 --seed 17154 --size 960
    --skylines --unmasked --twice-encoded --contrails``; a 352 m overcast, B = 71 m, the sun 11°
    from the zenith, a tree line and skylines): the correct station was flagged geometry_mismatch,
    a fitted turn of 0.235° ± 0.057° against 0.206°. 185 of its LK matches lie on the deck, in one
    patch, and ask for 0.12°; 4 more near the horizon, 0.7–1.6 px from infinity and 1–1.4 px off
    their curves, carried the fit along the axis the patch barely constrains. Matches within 2
    tolerances of infinity are no longer counted as the cloud's in the fit."""
    _, score = _quiet_correct_station(17165, 960, tmp_path,
                                      RandomOptions(skylines=True, unmasked=True, twice_encoded=True, contrails=True))
    assert score.missed_m == [] and score.spurious_m == [], (score.found_m, score.expected_m)


@pytest.mark.slow
@pytest.mark.parametrize("seed", [16781, 16855])
def test_matches_whose_windows_hold_clipped_pixels_are_no_evidence_of_a_turn(seed, tmp_path):
    """Fresh dense skies whose correct station was flagged geometry_mismatch by LK matches whose
    windows held pixels at a camera's clip level (their texture cut where that camera's exposure
    clips, :func:`cbh.pipeline.masks.near_clip`), both with ``exposure_mismatch``:

    - 16781 (stop 55, ``eval_random.py --n 30 --seed 16770 --dense``, 960 px: 998 m over 82 %,
      1372 and 4200 m through its gaps, B = 55 m, white at 254): a turn of 0.047° ± 0.009°
      against the 0.047° that 0.25 px is at this size; 0.032° ± 0.020° without those matches.
    - 16855 (``--seed 16830 --dense``: 499 m and 7717 m, B = 114 m, an over-exposed sky with 24 %
      and 39 % of the two working images at white): all 76 matches the check had were such, their
      median 1.9 px off their epipolar curves; none is left, and the check gives no verdict."""
    r, _ = _quiet_correct_station(seed, 960, tmp_path, RandomOptions(dense=True))
    assert len(r.layers) >= 2


def test_a_match_near_either_cameras_clipped_pixels_is_left_out_of_the_check():
    """:func:`near_clip` marks the pixels within ``reach_px`` (a square) of a pixel at the image's
    clip level, nothing for an image that does not clip; the geometry check's matches whose
    camera-1 pixel is near camera 1's clipping, or camera-2 pixel near camera 2's, are left out
    where the cameras' responses differ (``exposure_mismatch``), and only there."""
    from cbh.pipeline.clip import clip_level
    from cbh.pipeline.config import MasksConfig
    from cbh.pipeline.masks import near_clip
    from cbh.pipeline.match import Matches
    from cbh.pipeline.run import _off_clip

    rng = np.random.default_rng(3)
    img = rng.integers(60, 200, (200, 200, 3)).astype(np.uint8)
    assert near_clip(img, MasksConfig(), clip_level(img), 10) is None
    img[90:110, 50:70] = 255  # a clipped blob, 20 × 20 px
    m = near_clip(img, MasksConfig(), clip_level(img), 10)
    assert m[100, 40] and m[80, 60] and m[119, 79]  # 10 px out, on each side and at the corner
    assert not m[100, 39] and not m[79, 60] and not m[120, 80]  # 11 px out
    far = np.zeros((200, 200), bool)
    far[:, 150:] = True  # camera 2's clipping, elsewhere
    px = np.array([[60.0, 100.0], [100.0, 100.0], [100.0, 20.0]])
    mt = Matches("lk", px, px[::-1] + [80.0, 0.0])  # camera 2: x 180, 180, 140
    kept = _off_clip(mt, (m, far))
    assert kept.px1.tolist() == [[100.0, 20.0]]  # the first near camera 1's clip, the second near camera 2's
    assert _off_clip(mt, (None, None)) is mt
    # only cameras of unlike responses clip one cloud along different contours
    from types import SimpleNamespace

    from cbh.pipeline import PipelineConfig
    from cbh.pipeline.run import Masks

    plain = rng.integers(60, 200, (200, 200, 3)).astype(np.uint8)
    masks = Masks(usable=(far, far), sun_angle=(None, None), sun_dir_enu=None, clips=(clip_level(img), None))
    pipe = SimpleNamespace(config=PipelineConfig())  # (LK window 21 px: a reach of 10)
    unlike = Pipeline._clip_contours(pipe, (img, plain), masks, SimpleNamespace(flags=["sun_glare", "exposure_mismatch"]))
    assert np.array_equal(unlike.near_clip[0], m) and unlike.near_clip[1] is None
    assert Pipeline._clip_contours(pipe, (img, plain), masks, SimpleNamespace(flags=["sun_glare"])).near_clip == (None, None)


def test_the_jackknifes_widening_is_students_t():
    """The patch jackknife's σ from G patches is widened by t(0.9995, G − 1) / z(0.9995): the
    table to 29 degrees of freedom and the Cornish–Fisher expansion beyond meet (within 0.1 %),
    and the widening falls towards 1 with more patches (exact values: scipy.stats.t.ppf)."""
    from cbh.pipeline.geocheck import _t_widening

    assert _t_widening(5) == pytest.approx(6.8688 / 3.2905, rel=1e-4)
    assert _t_widening(9) == pytest.approx(4.7809 / 3.2905, rel=1e-4)
    assert _t_widening(30) == pytest.approx(3.6460 / 3.2905, rel=2e-3)
    w = [_t_widening(d) for d in range(5, 200)]
    assert all(a > b for a, b in zip(w, w[1:])) and 1.0 < w[-1] < 1.02


@pytest.mark.slow
@pytest.mark.parametrize("scene, heights_m", [("single-cumulus", (350.0,)), ("three-layers", (300.0, 900.0, 4000.0))])
def test_low_cloud_at_a_long_baseline_is_no_mismatch(unb, scene, heights_m):
    """Low cloud seen by a 241 m pair (the real Fehmarn station's baseline): the views are
    20–40° apart, LK's matches scatter 1–2 px across their curves (median 1.3 px at 75–200 px of
    parallax) and lean one way on the near deck. Judged against a fixed 1 px, and a turn fitted on
    them alike, the correct station was flagged ``geometry_mismatch`` (both); every layer within
    5 % and no invalidating flag now."""
    import dataclasses

    from cbh.sim.evaluate import station_variant

    sc = load_scene(scene)
    sc = dataclasses.replace(sc, layers=tuple(dataclasses.replace(L, height_m=h) for L, h in zip(sc.layers, heights_m)))
    sim = SkySimulator(station_variant(unb, 241.0, 20.0), sc, size_px=960)
    shot = sim.render()
    r = Pipeline(sim.station).process(shot.views["cam1"].image, shot.views["cam2"].image, shot.time_utc, channels="bgr")
    assert not set(r.flags) & INVALIDATING, r.flags
    found = sorted(L.height_m for L in r.layers)
    assert len(found) == len(heights_m), found
    for f, h in zip(found, heights_m):
        assert abs(f - h) <= 0.05 * h, (found, heights_m)


@pytest.mark.slow
def test_sun_check_reports_the_residual_and_flags_a_misaligned_camera(unb, repo):
    from dataclasses import replace

    scene = load_scene(repo / "configs" / "scenes" / "misoriented-day.toml")
    level = load_station(repo / "configs" / "unb-lea-level.toml")
    t = datetime(2024, 6, 21, 12, 30, tzinfo=timezone.utc)  # sun in the clear at zenith 56°
    s = SkySimulator(level, scene, size_px=480)
    shot = s.render(t)
    r = Pipeline(s.station).process(shot.views["cam1"].image, shot.views["cam2"].image, t, channels="bgr")
    d = r.diagnostics
    # camera 1 is (2.0, 0.3, −0.2)° off: at zenith 56° that moves the sun by ≈ 2.0·sin 56° ≈ 1.7°
    assert 1.0 < d["sun_residual_cam1_deg"] < 2.2
    assert d["sun_residual_cam2_deg"] > 3.0  # −5.6° of yaw
    assert d["sun_residual_deg"] == max(d["sun_residual_cam1_deg"], d["sun_residual_cam2_deg"])
    assert "sun_misaligned" in r.flags
    ok = SkySimulator(level, replace(scene, imperfections={}), size_px=480)
    shot = ok.render(t)
    r = Pipeline(ok.station).process(shot.views["cam1"].image, shot.views["cam2"].image, t, channels="bgr")
    # the detector's bias towards the brighter sky is ≤ 0.3° at 480 px (in each camera that
    # found the sun; the pair's residual needs both)
    per_cam = [r.diagnostics[f"sun_residual_{c}_deg"] for c in ("cam1", "cam2")]
    assert any(math.isfinite(v) for v in per_cam)
    assert all(v < 0.3 for v in per_cam if math.isfinite(v)) and "sun_misaligned" not in r.flags
    assert not r.diagnostics["sun_residual_deg"] >= 0.3


def test_unknown_time_or_hidden_sun_leaves_the_sun_residual_out(pipe, shot):
    r = pipe.process(shot.views["cam1"].image, shot.views["cam2"].image, None, channels="bgr")
    assert "sun_residual_deg" not in r.diagnostics and "sun_misaligned" not in r.flags


def test_service_leaves_flagged_layers_out_and_warns_once():
    from cbh.live.service import Service
    from cbh.live.sources import MemorySource
    from cbh.result import Frame, Histogram, Layer, PairResult, PointSet

    n = 6
    frames = lambda cam: [Frame(cam, T0 + timedelta(seconds=10 * i), np.zeros((4, 4, 3), np.uint8)) for i in range(n)]

    def process(f1, f2):
        i = int((f1.time_utc - T0).total_seconds() // 10)
        flags = ["geometry_mismatch"] if 1 <= i <= 3 else []
        if i >= 2:
            flags.append("sun_misaligned")
        return PairResult(f1.time_utc, ("cam1", "cam2"), [Layer(2000.0 + i, 2000.0, 10.0, 0.3, 100, 0.9)],
                          Histogram(np.zeros(2), np.zeros(1)), PointSet.empty(), np.zeros((4, 4), np.float32),
                          {}, {}, flags=flags, diagnostics={"geometry_residual_px": 12.0 if i <= 3 else 0.1,
                                                            "sun_residual_deg": 3.0 if i >= 2 else 0.1})

    class Collect(logging.Handler):
        records: list = []

        def emit(self, record):
            self.records.append(record)

    handler = Collect(logging.WARNING)
    svc_log = logging.getLogger("cbh.live.service")  # a handler of its own: other tests reconfigure logging
    svc_log.addHandler(handler)
    seen = []
    try:
        st = Service([MemorySource("cam1", frames("cam1")), MemorySource("cam2", frames("cam2"))], process, [],
                     on_pair=lambda s, r: r is not None and seen.append((r.time_utc, list(s.last_layers_m), s.line()))).run()
    finally:
        svc_log.removeHandler(handler)
    assert st.pairs_failed == 0, st.last_error
    seen = [x[1:] for x in sorted(seen)]
    assert st.pairs_processed == n and st.pairs_invalid == 3
    assert seen[0][0] == [2000.0]
    for layers, line in seen[1:4]:
        assert layers == [] and "not valid: geometry_mismatch" in line
    assert seen[4][0] == [2004.0]
    warnings = [r for r in handler.records if "disagree with the station geometry" in r.getMessage()]
    assert len(warnings) == 1  # once, not per pair
    assert len([r for r in handler.records if "sun_misaligned" in r.getMessage()]) == 1
    assert st.to_dict()["pairs_invalid"] == 3


@pytest.mark.slow
def test_real_wahrsis_pair_is_not_flagged_but_its_sun_is(shared, repo):
    """The authors' calibration: rays miss by 2–3 % of the range (the station states 3 %), and
    WAHRSIS4's rotation puts the sun 3.4° off (6° of azimuth at zenith 15°)."""
    from cbh.imageio import read_image

    d = shared / "data" / "wahrsis-2015-10-29"
    st = load_station(repo / "configs" / "wahrsis-2015-10-29.toml")
    i1, _ = read_image(d / "2015-10-29-12-58-01-wahrsis3-low.jpg")
    i2, _ = read_image(d / "2015-10-29-12-58-01-wahrsis4-low.jpg")
    r = Pipeline(st).process(i1, i2, datetime(2015, 10, 29, 4, 58, 1, tzinfo=timezone.utc), channels="bgr")
    assert "geometry_mismatch" not in r.flags and "identical_images" not in r.flags
    assert "sun_misaligned" in r.flags
    assert 2.5 < r.diagnostics["sun_residual_cam2_deg"] < 4.5


@pytest.mark.slow
def test_sun_in_one_camera_only_raises_no_alarm():
    """Broken cumulus around the sun (the default two-layers scene at 14:00-14:00:30 UTC): the
    sun detector once took a saturated cloud beside the hidden sun for the sun in one camera,
    3-5 deg off (it now rejects a round piece carved out of saturated cloud: its ring is
    saturated all round). A correct station must not be flagged, and a sun found in either
    camera is the sun (within 1 deg of the prediction); a pair's residual needs the sun in both
    cameras (the per-camera residuals stay in the diagnostics)."""
    from datetime import timedelta

    from cbh.geometry.station import load_station
    from cbh.pipeline import Pipeline
    from cbh.presets import scene_path, station_path
    from cbh.sim import SkySimulator, load_scene

    sc = load_scene(scene_path("two-layers"))
    sim = SkySimulator(load_station(station_path("unb-lea")), sc)
    pipe = Pipeline(sim.station)
    for k in (0, 3):  # cam1 takes the cloud for the sun at 14:00:00, cam2 at 14:00:30
        t = sc.time_utc + timedelta(seconds=10 * k)
        shot = sim.render(t)
        r = pipe.process(shot.views["cam1"].image, shot.views["cam2"].image, t, channels="bgr")
        assert "sun_misaligned" not in r.flags
        per_cam = [r.diagnostics[f"sun_residual_{c}_deg"] for c in ("cam1", "cam2")]
        assert all(v < 1.0 for v in per_cam if math.isfinite(v))  # no cloud taken for the sun
        if sum(map(math.isfinite, per_cam)) == 1:
            assert math.isnan(r.diagnostics["sun_residual_deg"])


def test_same_image_twice_is_flagged_when_working_sizes_differ(sim, shot):
    """The cameras' lenses differ slightly, so at a working radius below the full size their
    working images differ in size (at 155 px: 310 vs 303 px). The same image
    delivered twice must still be flagged: the check compares what the cameras delivered."""
    from cbh.pipeline.config import PipelineConfig

    pipe = Pipeline(sim.station, config=PipelineConfig(working_radius_px=155.0))
    assert pipe.cam1.model.width != pipe.cam2.model.width  # the case this test is about
    img = shot.views["cam1"].image
    r = pipe.process(img, img.copy(), T0, channels="bgr")
    assert "identical_images" in r.flags


def test_matches_from_one_patch_of_sky_do_not_flag_a_correct_station(unb):
    """A lone cloud gives matches in one patch only, where the fitted rotation is poorly
    constrained: on a correct geometry its scatter reached 0.06–0.1° (above the 0.047° that
    0.25 px is at this size) and flagged 6–11 of 40 such pairs. The rotation is judged beyond
    3 σ of the fit, so noise-only patches pass, while a 0.5° turn over the whole sky is caught.
    Synthetic matches: points of a 2 km plane projected into both working-size cameras, 0.1 px
    Gaussian noise (LK's level on simulated pairs)."""
    from cbh.geometry.calibrate import rotvec_to_matrix
    from cbh.pipeline.config import FilteringConfig, GeometryCheckConfig
    from cbh.pipeline.geocheck import check_geometry
    from cbh.pipeline.match import Matches, PairGeometry

    st = unb.scaled(960)
    cam1, cam2 = st.pair()
    geom = PairGeometry(cam1, cam2)
    rng = np.random.default_rng(7)

    def matches(centre_m, radius_m, n, turn_deg=0.0):
        e = centre_m[0] + rng.uniform(-radius_m, radius_m, n)
        nn = centre_m[1] + rng.uniform(-radius_m, radius_m, n)
        p = np.stack([e, nn, np.full(n, 2000.0)], 1)
        px1 = cam1.world_to_pixel(p)
        d2 = (p - cam2.position_m) @ rotvec_to_matrix(np.radians([0.0, 0.0, turn_deg])).T
        px2 = cam2.direction_to_pixel(d2)
        ok = np.isfinite(px1).all(1) & np.isfinite(px2).all(1)
        noise = lambda k: rng.normal(0.0, 0.1, (k, 2))  # noqa: E731
        return Matches("lk", px1[ok] + noise(ok.sum()), px2[ok] + noise(ok.sum()))

    flagged = 0
    for _ in range(20):
        c = rng.uniform(-2500, 2500, 2)
        chk = check_geometry(geom, [matches(c, 300.0, 60)], FilteringConfig(), GeometryCheckConfig())
        flagged += chk.mismatch
    assert flagged == 0
    whole = check_geometry(geom, [matches((0.0, 0.0), 4000.0, 600, turn_deg=0.5)], FilteringConfig(),
                           GeometryCheckConfig())
    assert whole.mismatch and whole.rotation_deg == pytest.approx(0.5, abs=0.03)



def test_matches_whose_windows_do_not_correlate_or_are_lines_are_not_judged(unb):
    """Two ways LK's forward-backward check lets a wrong match through, both no evidence about
    the station: a lock onto a neighbouring blob of fine texture (its windows do not correlate:
    randomized 17849, 0.18–0.37 against 0.67–0.80 for the true matches), and a slide along a line
    (a contrail: the window matches itself anywhere along it; randomized 17945's matches slid
    0.5–3° off their curves, corner ratios 0.02–0.09). 80 true matches of a 2 km deck with 140
    such: judged all together the correct station is flagged, judged on ``min_zncc`` and
    ``min_corner_ratio`` it is not; the same true matches of a camera turned 0.5° still are."""
    from dataclasses import replace

    from cbh.geometry.calibrate import rotvec_to_matrix
    from cbh.pipeline.config import FilteringConfig, GeometryCheckConfig
    from cbh.pipeline.geocheck import check_geometry
    from cbh.pipeline.match import Matches, PairGeometry

    cam1, cam2 = unb.scaled(480).pair()
    geom = PairGeometry(cam1, cam2)
    rng = np.random.default_rng(11)
    p = np.stack([rng.uniform(-3000, 3000, 400), rng.uniform(-3000, 3000, 400), np.full(400, 2000.0)], 1)

    def lk(turn_deg, kind):
        px1 = cam1.world_to_pixel(p)
        px2 = cam2.direction_to_pixel((p - cam2.position_m) @ rotvec_to_matrix(np.radians([0.0, 0.0, turn_deg])).T)
        ok = np.flatnonzero(np.isfinite(px1).all(1) & np.isfinite(px2).all(1))[:220]
        px1, px2 = px1[ok] + rng.normal(0, 0.1, (220, 2)), px2[ok] + rng.normal(0, 0.1, (220, 2))
        a = rng.uniform(0, 2 * np.pi, 140)  # the wrong ones: a blob's width or a slide off, any direction
        px2[80:] += rng.uniform(10, 20, (140, 1)) * np.stack([np.cos(a), np.sin(a)], 1)
        zncc, corner = rng.uniform(0.67, 0.8, 220), rng.uniform(0.3, 1.0, 220)
        if kind == "blobs":
            zncc[80:] = rng.uniform(0.18, 0.37, 140)
        else:  # lines: they correlate well
            zncc[80:], corner[80:] = rng.uniform(0.95, 0.99, 140), rng.uniform(0.02, 0.09, 140)
        return Matches("lk", px1, px2, zncc=zncc, corner=corner)

    cfg = GeometryCheckConfig()
    for kind in ("blobs", "lines"):
        every = replace(cfg, min_zncc=0.0, min_corner_ratio=0.0)
        assert check_geometry(geom, [lk(0.0, kind)], FilteringConfig(), every).mismatch, kind
        judged = check_geometry(geom, [lk(0.0, kind)], FilteringConfig(), cfg)
        assert not judged.mismatch and judged.matches == 80 and judged.residual_px < 0.3, (kind, judged)
        assert check_geometry(geom, [lk(0.5, kind)], FilteringConfig(), cfg).mismatch, kind


def test_a_line_is_no_corner():
    """:func:`cbh.pipeline.match.corner_ratio`: a contrail-like line (Gaussian, σ 2 px) in any
    direction reads under 0.1, blurred noise (cloud texture) over 0.3, a flat window 0."""
    import cv2

    from cbh.pipeline.match import corner_ratio

    yy, xx = np.mgrid[0:120, 0:120].astype(np.float32)
    p = np.array([[60.0, 60.0], [50.5, 70.2]])
    for ang in (0.0, 0.4, 1.2, 2.0):
        d = (xx - 60) * np.sin(ang) - (yy - 60) * np.cos(ang)
        line = 100 + 80 * np.exp(-0.5 * (d / 2.0) ** 2)
        assert corner_ratio(line, p, 21).max() < 0.1, ang
    rng = np.random.default_rng(2)
    tex = cv2.GaussianBlur(rng.normal(0, 40, (120, 120)).astype(np.float32), (0, 0), 1.5)
    assert corner_ratio(tex, rng.uniform(20, 100, (40, 2)), 21).min() > 0.3
    assert np.all(corner_ratio(np.full((120, 120), 7.0, np.float32), p, 21) == 0)


@pytest.mark.parametrize("size", [480, pytest.param(960, marks=pytest.mark.slow)])
def test_randomized_overcast_whose_lk_locked_onto_other_blobs_is_no_mismatch(size, tmp_path):
    """Randomized 17849 (default options): a 5745 m overcast of fine texture at B = 40 m, camera 1
    near its white. 140 of LK's 218 matches (480 px) locked 12–26 px off onto other blobs and
    passed the forward-backward check (ZNCC of their windows 0.18–0.37; the true ones 0.67–0.80):
    a median of 12 px (32 px at 960 px) flagged the correct station ``geometry_mismatch``. Judged
    on the matches whose windows correlate: 0.04 px at 480 px, no verdict at 960 px (too few)."""
    r, score = _quiet_correct_station(17849, size, tmp_path)
    assert score.missed_m == [] and score.spurious_m == [], score.found_m


def test_randomized_decks_whose_lk_windows_held_two_of_them_are_no_turn(tmp_path):
    """Randomized 18601 (default options, 480 px, found in stop 69): decks at 430, 1211 and 2201 m
    over 28, 60 and 39 % of the sky, cameras 172 m apart. LK's corners were where one deck's edge
    crosses another's (T-junctions): 71 of its 72 judged windows held two decks, whose parallaxes
    differ by ~10 px there; the translation that LK fits to such a window misses the epipolar
    curve, and together they fitted a turn of 0.39° ± 0.07° (tolerance 0.18°) on a correct
    station: ``geometry_mismatch``. The check now judges only windows of one deck (the sweep's
    heights in them within ``layers.min_separation_log``): no flag, and every deck found."""
    r, score = _quiet_correct_station(18601, 480, tmp_path)
    assert score.missed_m == [] and score.spurious_m == [], score.found_m


def test_a_window_across_two_decks_spreads_its_heights():
    """:func:`cbh.pipeline.geocheck.window_height_spread`: ln(90th / 10th percentile) of the dense
    heights in each window: 0 on one deck, ln 2 across a 1000 m / 2000 m edge, NaN where the
    sweep measured under 3 heights (no judgement), and a window at the border is cut, not wrapped."""
    from cbh.pipeline.geocheck import window_height_spread

    grid = np.full((100, 100), 1000.0, np.float32)
    grid[:, 50:] = 2000.0
    grid[:, 80:] = np.nan
    px = np.array([[20.0, 50.0], [50.0, 50.0], [96.0, 50.0], [0.0, 0.0]])
    spread = window_height_spread(grid, px, 21)
    assert spread[0] == pytest.approx(0.0, abs=1e-6)
    assert spread[1] == pytest.approx(math.log(2.0), abs=1e-5)
    assert math.isnan(spread[2])
    assert spread[3] == pytest.approx(0.0, abs=1e-6)
    noisy = grid[:, :50] * np.random.default_rng(0).normal(1.0, 0.01, (100, 50)).astype(np.float32)
    assert window_height_spread(noisy, px[:1], 21)[0] < 0.05  # 1 % noise: one deck (ln 1.18 = 0.166 is two)


@pytest.mark.slow
def test_randomized_clear_sky_whose_lk_slid_along_contrails_is_no_mismatch(tmp_path):
    """Randomized 17945 (960 px, skylines unmasked, twice encoded, contrails): a clear sky with
    three contrails at 7.1–11.4 km, B = 30 m. 16 of LK's 33 matches slid 0.5–3° along the
    contrails (ZNCC 0.95–0.99: a line matches itself anywhere along it): flagged
    ``geometry_mismatch`` at 1.28 px. Their windows' corner ratios are 0.02–0.09; judged on
    corners only, too few matches are left for a verdict."""
    _quiet_correct_station(17945, 960, tmp_path, RandomOptions(skylines=True, unmasked=True, twice_encoded=True,
                                                               contrails=True))

def test_a_window_correlates_with_itself_and_not_with_its_neighbour():
    """:func:`cbh.pipeline.match.window_zncc`: the same texture at a sub-pixel place correlates
    (≥ 0.99, bilinear), with a gain and an offset too; a window beside it does not (fine texture
    of 3 px blobs: median |ZNCC| < 0.2); a flat window scores 0."""
    import cv2

    from cbh.pipeline.match import window_zncc

    rng = np.random.default_rng(3)
    tex = cv2.GaussianBlur(rng.normal(0, 40, (200, 200)).astype(np.float32), (0, 0), 1.5) + 128
    p = rng.uniform(40, 160, (50, 2))
    shifted = cv2.warpAffine(tex, np.float32([[1, 0, 3.3], [0, 1, -2.6]]), (200, 200), flags=cv2.INTER_CUBIC)
    z = window_zncc(tex, p, 0.5 * shifted + 20, p + [3.3, -2.6], 21)
    assert z.min() > 0.99
    assert np.median(np.abs(window_zncc(tex, p, tex, p + [25.0, 0.0], 21))) < 0.2  # (chance: σ ≈ 0.17)
    assert np.all(window_zncc(np.full((200, 200), 90, np.float32), p, tex, p, 21) == 0)

def test_carried_matches_are_judged_on_their_pattern_not_their_scatter(unb):
    """Matches carried in time by each pixel's own motion (the sky maps', ``skyflow``) scatter by
    the carry's noise (cloud evolving over a half-minute clock offset: 0.2–0.8° on the real
    Fehmarn pairs), which says nothing of the geometry. Judged one by one, 4 px of isotropic
    scatter on a correct station leaves 38 % of the matches within 2 tolerances: flagged (2.5 px
    leaves 58 %, whose median is within the tolerance: a 1.7 px median over all of them was
    flagged until stop 74). Judged on tile medians (a geometry error moves neighbours alike), 2.5
    px passes; and a 0.5° turn of camera 2 under the same scatter is still caught."""
    from cbh.geometry.calibrate import rotvec_to_matrix
    from cbh.pipeline.config import FilteringConfig, GeometryCheckConfig
    from cbh.pipeline.geocheck import check_geometry
    from cbh.pipeline.match import Matches, PairGeometry

    st = unb.scaled(960)
    cam1, cam2 = st.pair()
    geom = PairGeometry(cam1, cam2)
    rng = np.random.default_rng(11)

    def matches(method, turn_deg=0.0, n=6000, scatter_px=2.5):
        p = np.stack([rng.uniform(-5000, 5000, n), rng.uniform(-5000, 5000, n), np.full(n, 3000.0)], 1)
        px1 = cam1.world_to_pixel(p)
        d2 = (p - cam2.position_m) @ rotvec_to_matrix(np.radians([0.0, 0.0, turn_deg])).T
        px2 = cam2.direction_to_pixel(d2)
        ok = np.isfinite(px1).all(1) & np.isfinite(px2).all(1)
        return Matches(method, px1[ok], px2[ok] + rng.normal(0.0, scatter_px, (ok.sum(), 2)))

    cfg = GeometryCheckConfig()
    carried = check_geometry(geom, [matches("skyflow")], FilteringConfig(), cfg)
    assert not carried.mismatch and carried.residual_px < 0.5
    assert check_geometry(geom, [matches("skyflow", turn_deg=0.5)], FilteringConfig(), cfg).mismatch
    stated = GeometryCheckConfig(expected_miss_ratio=0.0026)  # the rotation fit not judged: the tiles catch it
    assert not check_geometry(geom, [matches("skyflow")], FilteringConfig(), stated).mismatch
    assert check_geometry(geom, [matches("skyflow", turn_deg=0.5)], FilteringConfig(), stated).mismatch
    assert check_geometry(geom, [matches("lk", scatter_px=4.0)], FilteringConfig(), cfg).mismatch  # read as geometry
    assert not check_geometry(geom, [matches("lk")], FilteringConfig(), cfg).mismatch



@pytest.mark.parametrize("seed, dense, size", [pytest.param(4028, False, 960, marks=pytest.mark.slow),
                                               pytest.param(11, True, 960, marks=pytest.mark.slow), (9919, True, 480)])
def test_randomized_correct_stations_whose_decks_ask_for_different_turns(seed, dense, size, tmp_path):
    """Randomized skies of three decks, the true orientation given, once flagged geometry_mismatch
    (seed 4028: 0.048° ± 0.011° from 216 LK matches; dense seed 11: 0.17° ± 0.024° from 68): each
    deck's matches asked for another turn, and σ now says so (:func:`_jackknife_sigma`). Dense
    seed 9919 at 480 px (twice encoded): 0.20° ± 0.023°, a turn that took 11 % off the residuals'
    scale, just over the 10 % below which the patches' σ (± 0.066°) was asked; now 15 %.

    9919 since the check leaves out matches whose windows hold clipped pixels (stop 56,
    :func:`cbh.pipeline.masks.near_clip`: 7 of its 240): 0.243° ± 0.055°, 4.4 σ, over the 0.178°
    that 2 % of the matches' parallax is. 212 of the 229 matches it fits lie on the 788 m deck,
    11° of parallax apart (B = 151 m), and alone ask for 0.270° ± 0.026°: LK's bias on one sheared
    deck, shared by every patch of it. The turn is judged beyond that bias (``_LK_SHEAR_BIAS``:
    0.292° here)."""
    _quiet_correct_station(seed, size, tmp_path, RandomOptions(dense=dense, twice_encoded=seed == 9919))


def test_a_turn_is_judged_beyond_lks_bias_on_sheared_views(unb):
    """On a low deck whose views are sheared (300 m at B = 50 m: 0.08–0.17 rad) LK's 21 px window
    is biased by up to ``_LK_SHEAR_BIAS`` × shear × window, a share of the parallax twice as large
    at 480 px as at 960 px: a fitted turn within it is not judged, one beyond it is; a matcher with
    a 5 px window is judged down to 2 % of the parallax."""
    from cbh.pipeline.config import FilteringConfig, GeometryCheckConfig
    from cbh.pipeline.geocheck import check_geometry
    from cbh.pipeline.match import PairGeometry

    cam1, cam2 = unb.scaled(480).pair()
    geom = PairGeometry(cam1, cam2)
    rng = np.random.default_rng(5)

    def matches(turn_deg, n=600):
        return _deck_matches(cam1, cam2, rng, turn_deg, n, 600.0, 300.0, 0.1)

    def check(turn_deg, window_px):
        return check_geometry(geom, [matches(turn_deg)], FilteringConfig(), GeometryCheckConfig(), window_px=window_px)

    assert not check(0.0, 21).mismatch
    within = check(0.12, 21)  # 0.12° of turn: 0.32 px, inside the 21 px window's bias (0.155°)
    assert within.rotation_deg == pytest.approx(0.12, abs=0.01) and not within.mismatch
    assert check(0.12, 5).mismatch  # beyond 2 % of the parallax (0.095°)
    assert check(0.3, 21).mismatch


def test_a_turn_from_matches_beside_obstacles_is_not_judged_but_a_gross_one_is(unb):
    """Matches beside a horizon obstacle found in the frame (``beside``) carry a near object's
    parallax and a mast's drag along its length: the rotation is judged only when ``min_matches``
    of its fit lie elsewhere (randomized 17076). A small turn asked for by such matches alone is no
    verdict; the same matches with enough others are; a turn that moves every match off its curve
    is flagged by the median whatever the matches lie on."""
    from cbh.pipeline.config import FilteringConfig, GeometryCheckConfig
    from cbh.pipeline.geocheck import check_geometry
    from cbh.pipeline.match import PairGeometry

    cam1, cam2 = unb.scaled(480).pair()
    geom = PairGeometry(cam1, cam2)
    rng = np.random.default_rng(17076)
    cfg = GeometryCheckConfig()

    def matches(turn_deg, n=200):
        return _deck_matches(cam1, cam2, rng, turn_deg, n, 900.0, 2000.0, 0.05)

    def check(m, n_beside):
        beside = np.zeros(len(m), bool)
        beside[:n_beside] = True
        return check_geometry(geom, [m], FilteringConfig(), cfg, window_px=5, beside=[beside])

    small, gross = matches(0.15), matches(2.0)
    alone = check(small, len(small))
    assert alone.rotation_deg == pytest.approx(0.15, abs=0.02) and not alone.mismatch
    assert check(small, 0).mismatch
    assert check(small, len(small) - cfg.min_matches).mismatch  # min_matches elsewhere: judged
    assert not check(small, len(small) - cfg.min_matches + 1).mismatch
    g = check(gross, len(gross))
    assert g.mismatch and g.residual_px > g.tolerance_px


def test_matches_within_noise_of_infinity_do_not_steer_a_low_decks_turn(unb):
    """A low deck's matches from one patch of sky barely constrain one axis of the turn, and the
    fit weighs each by its views' shear (a 350 m deck's: little). A few matches at the horizon whose
    parallax is within 2 tolerances of infinity (no height the pair resolves), 1.2 px off their
    curves as LK's are in the haze there, counted with the deck and at full weight, steered the fit
    along that axis and flagged a correct station (randomized 17165: 0.24° against 0.21°). They
    are left out of the deck's fit: no verdict from them, and a real turn is still flagged."""
    from cbh.pipeline.config import FilteringConfig, GeometryCheckConfig
    from cbh.pipeline.geocheck import check_geometry
    from cbh.pipeline.match import Matches, PairGeometry

    cam1, cam2 = unb.scaled(480).pair()
    geom = PairGeometry(cam1, cam2)
    rng = np.random.default_rng(17165)
    deck = _deck_matches(cam1, cam2, rng, 0.0, 200, 120.0, 350.0, 0.05)
    # far cloud 10–20 km out at 75–80° from the zenith: under 2 px of parallax, pushed 1.2 px across its curve
    az = np.radians(rng.uniform(200.0, 230.0, 6))
    far = np.stack([np.sin(az), np.cos(az), np.full(6, 0.0)], 1) * rng.uniform(10e3, 20e3, (6, 1))
    far[:, 2] = np.linalg.norm(far[:, :2], axis=1) / np.tan(np.radians(rng.uniform(75.0, 80.0, 6)))
    px1, px2 = cam1.world_to_pixel(far), cam2.world_to_pixel(far)
    along = cam2.world_to_pixel(far + [0.0, 0.0, 200.0]) - px2  # a change of height moves it along its curve
    across = np.stack([-along[:, 1], along[:, 0]], 1) / np.linalg.norm(along, axis=1, keepdims=True)
    horizon = Matches("lk", px1, px2 + 1.2 * across)
    assert (np.linalg.norm(px2 - geom.infinity(px1), axis=1) < 2.0).all()

    def check(*ms):
        return check_geometry(geom, list(ms), FilteringConfig(), GeometryCheckConfig())

    alone, both = check(deck), check(deck, horizon)
    assert not alone.mismatch and not both.mismatch, (both.rotation_deg, both.rotation_tolerance_deg)
    assert both.rotation_deg == pytest.approx(alone.rotation_deg, abs=0.02)
    turned = _deck_matches(cam1, cam2, rng, 0.5, 200, 120.0, 350.0, 0.05)
    assert check(turned, horizon).mismatch


def _deck_matches(cam1, cam2, rng, turn_deg: float, n: int, half_m: float, height_m: float, noise_px: float):
    """LK-like matches of ``n`` points of a flat deck at ``height_m`` over ±``half_m``, seen by
    camera 2 turned by ``turn_deg`` about east, each pixel with ``noise_px`` of Gaussian noise."""
    from cbh.geometry.calibrate import rotvec_to_matrix
    from cbh.pipeline.match import Matches

    p = np.stack([rng.uniform(-half_m, half_m, n), rng.uniform(-half_m, half_m, n), np.full(n, height_m)], 1)
    px1 = cam1.world_to_pixel(p)
    px2 = cam2.direction_to_pixel((p - cam2.position_m) @ rotvec_to_matrix(np.radians([turn_deg, 0.0, 0.0])).T)
    ok = np.isfinite(px1).all(1) & np.isfinite(px2).all(1)
    return Matches("lk", px1[ok] + rng.normal(0, noise_px, (ok.sum(), 2)),
                   px2[ok] + rng.normal(0, noise_px, (ok.sum(), 2)))


def test_a_turn_is_fitted_on_the_matches_that_do_not_look_obliquely(unb):
    """A flat deck seen far from the zenith is foreshortened differently by the two cameras (their
    views scaled against each other along the zenith by 2·parallax·tan z), and LK's translation
    matches it with a bias (randomized dense 20138: 49 LK matches 70–80° from the zenith 0.40 px
    off their curves against 0.06 px within 40°, and a correct station fitted 0.063° ± 0.009°,
    over its 0.045°). Here the far matches of a correct station ask for a 0.3° yaw and the 200
    within 47° for none: the turn is fitted on the near ones and reads ≈ 0, while a real 0.1° yaw,
    which moves the near matches too, is still read and flagged."""
    from cbh.geometry.calibrate import rotvec_to_matrix
    from cbh.pipeline.config import FilteringConfig, GeometryCheckConfig
    from cbh.pipeline.geocheck import check_geometry
    from cbh.pipeline.match import Matches, PairGeometry

    cam1, cam2 = unb.scaled(960).pair()
    geom = PairGeometry(cam1, cam2)
    rng = np.random.default_rng(20138)

    def matches(turn_deg, far_turn_deg, h=1400.0):
        near = np.stack([rng.uniform(-1500, 1500, 200), rng.uniform(-1500, 1500, 200)], 1)
        r, az = h * np.tan(np.radians(rng.uniform(71.0, 79.0, 60))), rng.uniform(-np.pi, np.pi, 60)
        p = np.concatenate([near, np.stack([r * np.cos(az), r * np.sin(az)], 1)])
        p = np.concatenate([p, np.full((len(p), 1), h)], 1)
        far = np.arange(len(p)) >= len(near)
        d = np.where(far[:, None], (p - cam2.position_m) @ rotvec_to_matrix(np.radians([0, 0, far_turn_deg])).T,
                     p - cam2.position_m)
        px1 = cam1.world_to_pixel(p)
        px2 = cam2.direction_to_pixel(d @ rotvec_to_matrix(np.radians([0.0, 0.0, turn_deg])).T)
        ok = np.isfinite(px1).all(1) & np.isfinite(px2).all(1)
        return Matches("lk", px1[ok] + rng.normal(0, 0.1, (ok.sum(), 2)), px2[ok] + rng.normal(0, 0.1, (ok.sum(), 2)))

    def check(turn_deg, far_turn_deg):
        return check_geometry(geom, [matches(turn_deg, far_turn_deg)], FilteringConfig(), GeometryCheckConfig())

    correct = check(0.0, 0.3)
    assert not correct.mismatch and correct.rotation_deg < 0.025  # 0.025°: 3 σ of 200 matches' 0.1 px noise
    turned = check(0.1, 0.3)
    assert turned.mismatch and turned.rotation_deg == pytest.approx(0.1, abs=0.02)


def test_lock_ons_are_counted_by_the_inlier_fraction_not_the_median(unb):
    """LK on the sheared views of a low deck locks onto other texture: randomized dense 20198 at
    640 px (a 499 m deck at B = 125 m) had a third of its 41 judged matches 3–15 px off their
    curves and the 64 % within 2 px at a median of 0.61 px, and their median over all of them,
    1.00 px, sat on the 1 px tolerance. The lock-ons are counted by the inlier fraction; the median measures the
    matches within 2 tolerances. A correct station with a third of its matches locked on passes;
    camera 2 turned 0.3° (1.6 px, within 2 tolerances: the median's case, the turn not judged as
    the station states an expected miss) under the same lock-ons is flagged."""
    from cbh.pipeline.config import FilteringConfig, GeometryCheckConfig
    from cbh.pipeline.geocheck import check_geometry
    from cbh.pipeline.match import Matches, PairGeometry

    cam1, cam2 = unb.scaled(960).pair()
    geom = PairGeometry(cam1, cam2)
    rng = np.random.default_rng(20198)
    cfg = GeometryCheckConfig(expected_miss_ratio=0.0026)  # tolerance 1.0 px, the turn not judged

    def check(turn_deg):
        m = _deck_matches(cam1, cam2, rng, turn_deg, 90, 1500.0, 2000.0, 0.6)
        px2 = m.px2.copy()
        k = len(px2) // 3
        ang = rng.uniform(0, 2 * np.pi, k)
        px2[:k] += rng.uniform(3.0, 15.0, k)[:, None] * np.stack([np.cos(ang), np.sin(ang)], 1)
        return check_geometry(geom, [Matches("lk", m.px1, px2)], FilteringConfig(), cfg)

    correct = check(0.0)
    assert not correct.mismatch and correct.inlier_fraction < 0.8, correct
    assert check(0.3).mismatch
