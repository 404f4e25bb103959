"""Horizon skylines without a mask, found on one pair (issue 33).

Randomized skies with :class:`cbh.sim.randomize.RandomOptions` ``skylines`` (rows of blocks of
different heights with notches and antennas, a hazier back row, thin masts, tree lines with sky
between the branches, sunlit walls; hazy horizons) and ``unmasked`` (every sky has obstacles, no
station mask). Every seed here once failed; the comment says what it gave before.
``benchmarks/eval_random.py --skylines --unmasked`` runs many of them.
"""
from __future__ import annotations

import cv2
import numpy as np
import pytest

from cbh.flags import INVALIDATING
from cbh.geometry.station import load_station
from cbh.presets import station_path
from cbh.sim.randomize import RandomOptions, random_case, run_random_case

SIZE = 480  # render size [px] (the pipeline's working size for these lenses is about this)
SKYLINES = RandomOptions(skylines=True, unmasked=True)
CLEAR = RandomOptions(skylines=True, unmasked=True, kind="clear")


@pytest.fixture(scope="module")
def base():
    return load_station(station_path())


def _assert_clear(r):
    assert max(r.cloud_fraction.values()) <= 0.02, r.cloud_fraction
    assert r.layers == []
    assert not set(r.flags) & INVALIDATING, r.flags


@pytest.mark.parametrize("seed", [
    1,  # three block rows and sunlit walls: cf 0.065 (the hazy back row called cloud)
    pytest.param(3, marks=pytest.mark.slow),  # block rows and a tree line: cf 0.063, geometry_mismatch
    4,  # one block skyline under a hazy horizon (band 0.7): cf 0.043, geometry_mismatch
    pytest.param(9, marks=pytest.mark.slow),  # tree lines and masts: cf 0.037
])
def test_clear_skies_over_a_skyline_are_clear(base, seed, tmp_path):
    case, r, score, _ = run_random_case(seed, base, SIZE, tmp_path, options=CLEAR)
    assert case.kind == "clear" and case.scene.obstacles and not case.mask_given
    _assert_clear(r)


def _found(base, seed, options, cam="cam1"):
    """(found obstacles at the truth's size, truth, the analysed sky) of camera 1 of ``seed``."""
    from cbh.pipeline import Pipeline
    from cbh.sim import SkySimulator

    case = random_case(seed, base, options)
    sim = SkySimulator(case.station, case.scene, size_px=SIZE)
    pipe = Pipeline(sim.station)
    found = pipe.auto_obstacles(0, pipe.to_working(0, sim.view(cam).image))
    truth = sim.obstacle_mask(cam)
    if found.shape != truth.shape:
        found = cv2.resize(found.view(np.uint8), truth.shape[::-1], interpolation=cv2.INTER_NEAREST) > 0
    usable = pipe.cam1_full.zenith_map() <= pipe.config.masks.max_zenith_deg
    return found, truth, usable


def test_a_skyline_with_a_hazy_back_row_is_found_in_one_frame(base):
    """Seed 3: block rows (the back row hazed 20-60 % towards the sky's colour: as bright as 0.8 of
    the sky above it) and a tree line. Before, the back row and the crowns above thin trunks were
    left in the sky (45 % of the obstacle in the analysed sky found); now ≥ 98 % (99.1 % measured),
    and beyond 3 px of the silhouettes ≤ 0.5 % of the sky is taken (0.10 % measured)."""
    found, truth, usable = _found(base, 3, CLEAR)
    near = cv2.dilate(truth.view(np.uint8), np.ones((7, 7), np.uint8)) > 0
    sky = usable & ~truth
    assert found[truth & usable].mean() >= 0.98
    assert (found & ~near & sky).sum() <= 0.005 * sky.sum()


def test_a_cloudy_sky_beside_a_skyline_keeps_its_clouds(base):
    """What stands on the ground is judged against its own column's sky, and only beside dark
    obstacles that stand on the horizon themselves. Seed 113 (three layers, dark bases, walls
    below the analysed sky): nothing taken (without that rule its dark clouds walked down to the
    grey horizon: 7 % of camera 1's sky at 960 px). Seed 108 (broken cumulus at 378 and 632 m
    right above block rows): cloud standing on the buildings is taken with them, ≤ 3 % of the
    sky beyond 3 px of the silhouettes (2.6 % measured; 1.1 % before masts one pixel wide were
    searched in the darkest of each 2 × 2 and crowns joined within 8 half-size pixels, not 5;
    2.6 % before the paler parts' rise was capped): the price of the pale rows and thin trunks."""
    found, truth, usable = _found(base, 113, SKYLINES)
    assert (found & usable & ~truth).sum() == 0
    found, truth, usable = _found(base, 108, SKYLINES)
    near = cv2.dilate(truth.view(np.uint8), np.ones((7, 7), np.uint8)) > 0
    sky = usable & ~truth
    assert (found & ~near & sky).sum() <= 0.03 * sky.sum()


@pytest.mark.slow
@pytest.mark.parametrize("seed,options", [
    (4, CLEAR),  # one block skyline under a hazy band 0.7: cf 0.042, geometry_mismatch
    (14, CLEAR),  # three block rows under a band 0.8: a layer at 290 m, geometry_mismatch
    (22, CLEAR),  # tree line, block rows, masts: cf 0.034, geometry_mismatch
    (104, SKYLINES),  # clear, one skyline: cf 0.051, geometry_mismatch
    (128, SKYLINES),  # clear, rows, tree line, masts, band 0.7: cf 0.034, geometry_mismatch
    (7008, CLEAR),  # masts, block rows, tree line, band 0.7: geometry_mismatch (matches at infinity as outliers)
    (7017, CLEAR),  # a tree line under a band 0.8: geometry_mismatch (76 LK matches 73-79° out, all at infinity)
    (5, CLEAR),  # tree lines under a sun 51° out: the skyline walk 30° wide took its aureole, cf 0.064, a layer at 335 m
])
def test_skyline_skies_at_960px(base, seed, options, tmp_path):
    """Randomized skyline skies at 960 px that failed before issue 33's detection (the seeds of
    ``eval_random.py --n 30 --size 960 --skylines --unmasked [--kind clear]``): no spurious
    layer, no invalidating flag on the true station, a clear sky clear."""
    case, r, score, _ = run_random_case(seed, base, 960, tmp_path, options=options)
    if case.kind == "clear":
        _assert_clear(r)
    assert score.spurious_m == []
    assert not set(r.flags) & INVALIDATING, r.flags


@pytest.mark.slow
@pytest.mark.parametrize("seed", [
    7000,  # block rows and a tree line, band 0.5: cf 0.064, geometry_mismatch
    7020,  # block rows, tree line, white 248: cf 0.016/0.027, geometry_mismatch
    7025,  # rows, tree lines, masts, white 245: cf 0.011/0.028, geometry_mismatch
])
def test_matches_at_infinity_over_a_skyline_are_no_mismatch(base, seed, tmp_path):
    """Clear skies over a skyline at 960 px (``eval_random.py --n 30 --seed 7000 --size 960
    --skylines --unmasked --kind clear``) whose only matches lie 64–79° from the zenith, 81–100 %
    of them within 2 px of infinity (haze and far skylines: on their epipolar curves, no height):
    counted as outliers they flagged the correct station ``geometry_mismatch``. No layer and no
    invalidating flag (all three are clear since: :func:`test_crowns_above_thin_trunks_are_no_cloud`,
    :func:`test_pale_sunlit_blocks_over_a_clear_sky_are_no_cloud`)."""
    case, r, score, _ = run_random_case(seed, base, 960, tmp_path, options=CLEAR)
    assert case.kind == "clear" and r.layers == [], r.layers
    assert not set(r.flags) & INVALIDATING, r.flags


def test_a_mast_one_pixel_wide_stays_dark_at_half_size():
    """The half-size obstacle search sees a mast or trunk one full-size pixel wide
    (:func:`cbh.pipeline.obstacles.darkest_of_four`): the area average halves its contrast, the
    darkest of each 2 × 2 keeps it; odd sizes round up, as the half-size frame does."""
    from cbh.pipeline.obstacles import darkest_of_four

    im = np.full((9, 11, 3), 200, np.uint8)
    im[:, 5] = (40, 50, 60)  # a mast one pixel wide (brightest channel 60)
    half = darkest_of_four(im)
    assert half.shape == (5, 6)
    assert (half[:, 2] == 60).all() and (half[:, [0, 1, 3, 4, 5]] == 200).all()
    assert cv2.resize(im, (6, 5), interpolation=cv2.INTER_AREA).max(axis=2).min() > 100


@pytest.mark.slow
@pytest.mark.parametrize("seed", [
    7020,  # block rows, tree line, white 248: cf 0.016/0.027 (crowns on sub-pixel trunks called cloud)
    7025,  # rows, tree lines, masts, white 245: cf 0.011/0.028 (crowns 2-5° above their visible trunks)
])
def test_crowns_above_thin_trunks_are_no_cloud(base, seed, tmp_path):
    """Clear skies over tree lines at 960 px (``eval_random.py --n 30 --seed 7000 --size 960
    --skylines --unmasked --kind clear``): trunks one full-size pixel wide vanish at the obstacle
    search's half size, and crowns hang up to 4° above what is left of them; both read as cloud
    (2-3 %). Masts and trunks are now searched in the darkest of each 2 × 2, and crowns join what
    stands within 8 half-size pixels (10 at first): cf 0.014/0.016 and 0.0 measured with 10."""
    case, r, score, _ = run_random_case(seed, base, 960, tmp_path, options=CLEAR)
    assert case.kind == "clear"
    _assert_clear(r)


def test_cloud_only_on_the_skylines_of_a_pair_without_a_layer_is_no_cloud():
    """:func:`cbh.pipeline.run._only_on_skylines`: a pair without a layer whose cloud (under 15 %
    in each camera) lies in components touching the obstacles found in its frames is a clear sky
    over a skyline; one free-standing cloud, an obstacle-free camera or a station mask (no
    obstacles found) says otherwise."""
    from cbh.pipeline.run import Masks, Segmentation, _only_on_skylines

    obst = np.zeros((60, 60), bool)
    obst[45:, :30] = True  # a block row
    on = np.zeros((60, 60), bool)
    on[38:45, 5:20] = True  # a pale block on it, 3 % of the frame
    free = np.zeros((60, 60), bool)
    free[5:12, 35:50] = True  # a cloud standing free
    usable = np.ones((60, 60), bool)

    def pair(c1, c2, o=(obst, obst)):
        f = {"a": float(c1.mean()), "b": float(c2.mean())}
        return Segmentation(clouds=(c1, c2), fractions=f), Masks(usable=(usable, usable), sun_angle=(None, None),
                                                                  sun_dir_enu=None, obstacles=o)

    assert _only_on_skylines(*pair(on, on))
    assert _only_on_skylines(*pair(on, np.zeros_like(on)))
    assert not _only_on_skylines(*pair(on, on | free))
    assert not _only_on_skylines(*pair(on, on, (obst, None)))
    assert not _only_on_skylines(*pair(np.zeros_like(on), np.zeros_like(on)))  # nothing to clear


@pytest.mark.slow
def test_pale_sunlit_blocks_over_a_clear_sky_are_no_cloud(base, tmp_path):
    """Seed 7000 (``eval_random.py --n 30 --seed 7000 --size 960 --skylines --unmasked --kind
    clear``): pale grey sunlit blocks as bright as the sky above them (brightest channel 140-151
    against 148-159, (B - R)/(B + R) 0.05-0.10 against 0.20), more than 10° of azimuth from any
    block dark enough to seed the skyline walk, read as cloud: cf 0.064/0.048, unmatched. No layer,
    and all that cloud stands on the skylines found: a clear sky (cf 0.0 measured)."""
    case, r, score, _ = run_random_case(7000, base, 960, tmp_path, options=CLEAR)
    assert case.kind == "clear"
    _assert_clear(r)


@pytest.mark.slow
def test_matches_beside_masts_and_blocks_give_no_verdict(base, tmp_path):
    """Seed 17076 (``eval_random.py --n 40 --seed 17044 --size 960 --skylines --unmasked
    --twice-encoded --contrails``): a clear sky over block rows, a tree line and masts, the sun
    58° from the zenith with a strong aureole, camera 2 pale. Every one of the geometry check's
    52 LK matches lies on or beside the obstacles (34 on them, the rest along the masts and the
    found blocks' edges, 66–80° from the zenith); their fitted turn of 0.10° ± 0.02° flags the
    correct station ``geometry_mismatch``. Leaving out matches within half an LK window of a found
    obstacle fixed it (19 left, no verdict) but flagged seed 9564
    (:func:`tests.test_phantom.test_a_textured_warm_cast_overcast_is_all_cloud`): its three such
    matches had kept the fit's σ wide over a sheared 319 m deck (0.31° ± 0.19° → 0.21° ± 0.05°).
    Since stop 62 such matches stay in the check, but a rotation verdict needs ``min_matches`` of
    the fit elsewhere (``check_geometry``'s ``beside``): 17076 has no verdict, 9564 is as it was."""
    opts = RandomOptions(skylines=True, unmasked=True, twice_encoded=True, contrails=True)
    case, r, score, _ = run_random_case(17076, base, 960, tmp_path, options=opts)
    assert case.kind == "clear" and r.layers == [], r.layers
    assert not set(r.flags) & INVALIDATING, r.flags


@pytest.mark.slow
def test_a_speckled_high_deck_on_a_blue_sky_is_not_one_cloud(base, tmp_path):
    """Seed 17087 (``eval_random.py --n 40 --seed 17084 --size 480 --skylines --unmasked
    --twice-encoded --contrails``): a speckled 7653 m deck of cover 0.23 over a 157 m baseline, a
    strong aureole, tree lines and walls. At 480 px its blue deficit stands 0.053 above the clear
    sky's, under ``min_gap``: one class, textured, so the whole sky was one cloud (cf 1.0) with a
    phantom 583 m layer in the horizon's haze. Blue sky with faint cloud on it is judged as a clear
    sky is: 7679 m alone, cf 0.17 and 0.14 (truth 0.14 in the analysed field). Its LK matches fit
    a turn of 0.109° against a tolerance of 0.090° and the correct station must stay unflagged: at
    the geometry check's resolution (± 0.025° from 160 px patches until stop 66, 4.4 σ; ± 0.022°
    from stop 67's 30° patches on two grids, 4.9 σ; ± 0.021° on one grid alone, flagged)."""
    opts = RandomOptions(skylines=True, unmasked=True, twice_encoded=True, contrails=True)
    case, r, score, _ = run_random_case(17087, base, 480, tmp_path, options=opts)
    assert score.spurious_m == [] and score.missed_m == [], (score.found_m, score.expected_m)
    assert max(r.cloud_fraction.values()) < 0.3, r.cloud_fraction
    assert not set(r.flags) & INVALIDATING, r.flags


@pytest.mark.slow
def test_a_clear_sky_over_block_rows_has_no_verdict_on_its_skyline(base, tmp_path):
    """Seed 112 (``eval_random.py --n 30 --seed 100 --size 960 --skylines --unmasked``): a clear
    sky over three block rows, the back row hazed to within 10 % of the sky: cf 0.081 and the
    correct station flagged ``geometry_mismatch`` by the skyline's matches. All that cloud stands
    on the skylines found and gives no layer: a clear sky, and, as for any clear pair, no
    geometry verdict (cf 0.0, ``sun_glare,clear_sky`` measured)."""
    case, r, score, _ = run_random_case(112, base, 960, tmp_path, options=SKYLINES)
    assert case.kind == "clear"
    _assert_clear(r)


@pytest.mark.slow
def test_a_pale_clear_sky_is_clear_in_both_cameras(base, tmp_path):
    """Seed 8025 (``eval_random.py --n 1 --seed 8025 --size 960 --skylines --unmasked``): a clear
    sky that camera 1's colour response makes pale (raw median NBR 0.096, chroma 0.17), camera 2
    blue (NBR 0.21); the photometric step maps camera 2 onto camera 1, both then read one grey
    class, overcast: cf 1.0, layers at 104–151, 1092, 3673 m and ``below_range``. Camera 2's
    sky as taken is blue and both are smooth: clear."""
    case, r, score, _ = run_random_case(8025, base, 960, tmp_path, options=SKYLINES)
    assert case.kind == "clear"
    _assert_clear(r)
    assert score.spurious_m == []


def test_learned_obstacles_are_forgotten_on_request(base):
    """A pipeline keeps masking what it found in most of a camera's frames after ten of them (a
    building under a dark cloud is still a building); :meth:`Pipeline.forget_learned` drops that,
    so that ``cbh reprocess`` chunks learn from their own frames on whichever actor takes them."""
    from cbh.pipeline import Pipeline
    from cbh.sim import SkySimulator

    case = random_case(1, base, CLEAR)
    sim = SkySimulator(case.station, case.scene, size_px=SIZE)
    pipe = Pipeline(sim.station)
    frame = pipe.to_working(0, sim.view("cam1").image)
    for _ in range(10):
        seen = pipe.auto_obstacles(0, frame)
    assert seen.sum() > 100
    empty = np.zeros_like(frame)
    empty[...] = (200, 150, 110)  # a plain blue sky: nothing dark at the horizon
    assert pipe.auto_obstacles(0, empty).sum() >= 0.9 * seen.sum()  # the learned ones stay masked
    pipe.forget_learned()
    assert pipe.auto_obstacles(0, empty).sum() == 0


_FRESH_52 = RandomOptions(skylines=True, unmasked=True, twice_encoded=True)


@pytest.mark.slow
@pytest.mark.parametrize("seed", [16503, 16510])
def test_fresh_skyline_skies_of_stop_52_report_no_phantom(base, seed, tmp_path):
    """``eval_random.py --n 30 --seed 16500 --size 480 --skylines --unmasked --twice-encoded``
    (the same before and after stop 52's changes): 16503, a clear sky with a haze band and a
    skyline, reports a 3948 m layer (3 % cloud), valid; 16510 (362 / 519 / 2309 m, B 39 m, walls)
    a 178 m layer of 512 points 69–78° from the zenith, valid, beside the two low decks (the
    2309 m one missed): an alias of the 360 m deck that the alias check misses under the second
    JPEG (38 % of its points as good at 360 m, 40 % needed; encoded once, 44 %). 16510 passes since
    the plane maps became a cubic in s (stop 59), 16503 since a layer's windows across its edge
    weigh less and its median weighs its worse-measured points down (stop 60)."""
    case, r, score, _ = run_random_case(seed, base, 480, tmp_path, options=_FRESH_52)
    valid = not set(r.flags) & INVALIDATING
    assert not (valid and score.spurious_m), (score.spurious_m, r.flags)


@pytest.mark.slow
@pytest.mark.xfail(strict=True, raises=AssertionError, reason="found in stop 52, not fixed (docs/accuracy.md, Limits)")
def test_a_dark_high_overcast_is_not_called_clear(base, tmp_path):
    """``eval_random.py --n 30 --seed 16560 --kind overcast --skylines``: 16562, one overcast deck at
    7914 m (brightness 0.65, B 195 m) seen through enough air to look bluish: both cameras split
    off 3 % as cloud and call the rest clear (the clear class's bluest tenth above NBR 0), and the
    pair reports ``clear_sky``, cloud fraction 0. A strict expected failure."""
    case, r, score, _ = run_random_case(16562, base, 960, tmp_path,
                                        options=RandomOptions(kind="overcast", skylines=True))
    assert case.kind == "overcast"
    assert "clear_sky" not in r.flags and max(r.cloud_fraction.values()) >= 0.5, (r.cloud_fraction, r.flags)


@pytest.mark.slow
@pytest.mark.parametrize("seed", [
    17270,  # clear, B = 135 m, masts and a tree line unmasked, a haze band, the sun 78° out: a 128 m layer, cf 0.08
    17274,  # 1359 m (57 %) and 7267 m (51 %), B = 119 m, skylines: a spurious 2183 m layer between them
])
def test_fresh_skies_of_stop_63_with_skylines_are_right(base, seed, tmp_path):
    """``eval_random.py --n 30 --seed 17268 --size 960 --skylines --unmasked --twice-encoded``: 32 / 32
    layers, 2 spurious, no false alarm in stop 63; both layers stood on the smaller share of the
    points that a deck seen through a lower one's gaps needs. Since stop 64 (strict expected
    failures before): only a reported layer can hide a deck (17270's 128 m "deck" over 0.2 % of a
    clear sky was hidden by a 100 m pile of matches that was none), and such a deck is seen mostly
    within 65° of the zenith (17274's 2183 m layer lay 70–80° out, between the decks:
    :func:`cbh.pipeline.layers.seen_through_gaps`)."""
    opts = RandomOptions(skylines=True, unmasked=True, twice_encoded=True)
    case, r, score, _ = run_random_case(seed, base, 960, tmp_path, options=opts)
    assert score.missed_m == [] and score.spurious_m == [], (case.describe(), score.found_m)


_STOP_64 = pytest.mark.xfail(strict=True, raises=AssertionError, reason="found in stop 64, not fixed (docs/accuracy.md, Stop 64)")


@pytest.mark.slow
@pytest.mark.parametrize("seed", [
    pytest.param(17472, marks=_STOP_64),  # B = 23 m, tree lines and masts unmasked, two contrails: camera 2's cloud 0.040 for 0.015
    17477,  # B = 46 m, the sun 47° out, aureole 3.5 clipped at 230, tree line, masts, a skyline (fixed in stop 65)
])
def test_fresh_clear_skies_of_stop_64_with_obstacles_are_clear(base, seed, tmp_path):
    """``eval_random.py --n 20 --seed 17462 --size 960 --skylines --unmasked --twice-encoded
    --contrails --kind clear``: 18 of 20 clear skies right, no false alarm. 17477 reported two
    layers, 384 m (728 of 3010 points, cover 0.047) and 1392 m (536 points, 0.048): its contrail
    was drawn through the sun at 255 above the camera's 230 clip (a simulator fault, fixed in
    stop 65: ``test_contrails.py::test_a_contrail_is_no_brighter_than_its_camera_can_output``),
    so the clip finder took 255 for the white level and the clipped aureole was segmented as
    cloud; now no layer. 17472 reports no layer, but camera 2's cloud is 0.040 against the
    truth's 0.015 (0.173 for camera 1 before stop 65). A strict expected failure: a fix makes it
    pass, and then its mark must go. The benchmark's test: no layer but a contrail's, cloud at
    most 0.02 beyond the contrails'."""
    opts = RandomOptions(skylines=True, unmasked=True, twice_encoded=True, contrails=True, kind="clear")
    case, r, score, _ = run_random_case(seed, base, 960, tmp_path, options=opts)
    assert case.kind == "clear"
    assert score.spurious_m == [], (case.describe(), score.found_m)
    assert max(r.cloud_fraction.values()) <= score.cloud_fraction + 0.02, (r.cloud_fraction, score.cloud_fraction)


_STOP_65 = pytest.mark.xfail(strict=True, raises=AssertionError, reason="found in stop 65, not fixed (docs/accuracy.md, Stop 65)")
_HARD = RandomOptions(skylines=True, unmasked=True, twice_encoded=True, contrails=True)


@pytest.mark.slow
@_STOP_65
@pytest.mark.parametrize("seed, size", [
    (17522, 960),  # camera 2 over-exposed, camera 1 pale: a 106 m layer, flagged below_range (the cause: the exposure, not fog)
    (17537, 960),  # 9107 m over 42 % missed above 303 m over 53 % (B = 169 m): the class of stop 59
    (17540, 960),  # a clear sky, tree lines unmasked, a contrail: cloud 0.119 against 0.081
    (17563, 480),  # 613 m over 30 % missed above 400 m over 54 % (B = 34 m: 1.5 % apart in parallax)
    (17571, 480),  # 9229 m missed above 1298 m and 4219 m (B = 29 m); 4219 m read 4806 m
])
def test_fresh_skies_of_stop_65_are_right(base, seed, size, tmp_path):
    """``eval_random.py --n 30 --seed 17512 --size 960 --skylines --unmasked --twice-encoded
    --contrails`` (26 of 27 decks, 1 spurious, 1 of 12 clear skies wrong, 1 pair invalidated) and
    ``--n 30 --seed 17542 --size 480`` with the same options (50 of 52, none spurious, no false
    alarm), fresh after stop 65's contrail fix: each sky's decks found and none invented, no
    invalidating flag, and a clear sky's cloud at most 0.02 beyond its contrails'. Strict expected
    failures: a fix makes them pass, and then its mark must go."""
    case, r, score, _ = run_random_case(seed, base, size, tmp_path, options=_HARD)
    assert score.missed_m == [] and score.spurious_m == [], (case.describe(), score.found_m)
    assert not set(r.flags) & INVALIDATING, r.flags
    if case.kind == "clear":
        assert max(r.cloud_fraction.values()) <= score.cloud_fraction + 0.02, (r.cloud_fraction, score.cloud_fraction)


def test_a_pale_clear_sky_camera_1_alone_calls_cloud_is_no_fog(base, tmp_path):
    """Randomized 18125 (480 px, skylines unmasked, twice encoded, contrails, found in stop 68): a
    pale clear sky that camera 1's segmentation calls 30 % cloud and camera 2's 1.6 %; 16 % of its
    chance matches sat on the sweep's floor and flagged ``below_range`` (fog under the floor), an
    invalidating flag on a correct station. Fog is cloud in both cameras: floor matches whose
    camera-2 pixel is clear sky are not counted where camera 2 calls under a fifth of camera 1's
    share cloud (``match._camera1_alone_calls_cloud``). No layer, before and after; its cloud
    fraction stays
    camera 1's (the class of the pale clear skies, 20032 and others)."""
    case, r, score, _ = run_random_case(18125, base, 480, tmp_path, options=_HARD)
    assert case.kind == "clear" and score.spurious_m == [] and r.layers == []
    assert not set(r.flags) & INVALIDATING, r.flags


@pytest.mark.parametrize("kind, whitening", [("clear", True), ("clear", False), ("overcast", True)])
def test_a_pale_smooth_sky_is_clear_if_it_whitens_to_the_horizon(base, tmp_path, monkeypatch, kind, whitening):
    """Randomized 18361 (480 px, mounted cameras, skylines unmasked, twice encoded, contrails;
    found in stop 69): a clear sky under a high sun (zenith 14°) that both cameras render pale
    (median NBR 0.09, chroma 0.17, smooth): as pale as grey cloud under a bluish cast, so both
    called it one overcast cloud (cloud fraction 1.0), and the chance matches of its smooth sky
    (69 LK matches 0.3–17 px from infinity) flagged ``geometry_mismatch`` on a correct station.
    Its NBR falls by 0.06 from mid-sky to the horizon, away from the sun, as clear sky's does and
    an overcast's does not (:func:`cbh.pipeline.segment.horizon_whitening`): now clear. With that
    test off (a sky as pale everywhere), it is one smooth cloud, and a smooth one-cloud pair gets
    no geometry verdict: its matches witness nothing (``overcast_no_texture`` says why). The
    overcast of the same seed (a pale deck, NBR 0.09, bluer at the horizon by 0.07) stays one cloud."""
    from dataclasses import replace

    from cbh.pipeline import segment

    if not whitening:
        monkeypatch.setattr(segment, "HORIZON_WHITENING", float("inf"))
    opts = replace(_HARD, mounts=True, kind=kind)
    case, r, score, _ = run_random_case(18361, base, 480, tmp_path, options=opts)
    assert case.kind == kind and not set(r.flags) & INVALIDATING, r.flags
    if kind == "overcast":
        assert min(r.cloud_fraction.values()) > 0.95 and score.missed_m == [], (r.cloud_fraction, score)
    elif whitening:
        assert "clear_sky" in r.flags and r.layers == [] and max(r.cloud_fraction.values()) < 0.02
    else:
        assert "overcast_no_texture" in r.flags and r.layers == [], r.flags


_STOP_73 = pytest.mark.xfail(strict=True, raises=AssertionError, reason="found in stop 73, not fixed (docs/accuracy.md, Stop 73)")
_EVERY = RandomOptions(mounts=True, optics=True, overlays=True, twice_encoded=True, contrails=True, skylines=True,
                       unmasked=True)


@pytest.mark.slow
@_STOP_73
@pytest.mark.parametrize("seed", [
    20099,  # a clear pale sky (aureole 2.0), facades and tree crowns unmasked: camera 2's cloud 0.069
    20119,  # an 8558 m deck over 51 % missed above a 541 m one (B = 23 m: 0.4 px of parallax at 480 px)
])
def test_fresh_skies_of_stop_73_are_right(base, seed, tmp_path):
    """``eval_random.py --n 40 --seed 20094 --size 480`` with every hard option (``--mounts --optics
    --overlays --twice-encoded --contrails --skylines --unmasked``), fresh at stop 73: 56 of 57
    decks, none spurious, no false alarm, 1 of 7 clear skies with cloud. Each sky's decks found and
    none invented, and a clear sky's cloud at most 0.02 beyond its contrails'. Strict expected
    failures: a fix makes them pass, and then its mark must go."""
    case, r, score, _ = run_random_case(seed, base, 480, tmp_path, options=_EVERY)
    assert score.missed_m == [] and score.spurious_m == [], (case.describe(), score.found_m)
    if case.kind == "clear":
        assert max(r.cloud_fraction.values()) <= score.cloud_fraction + 0.02, (r.cloud_fraction, score.cloud_fraction)


@pytest.mark.slow
@_STOP_73
def test_an_overexposed_high_overcast_is_found(base, tmp_path):
    """``eval_random.py --n 30 --seed 20160 --size 480 --kind overcast --mounts --optics
    --twice-encoded --skylines`` (stop 73): 29 of 30 decks, 5 spurious (all 20166's), 1 sky flagged.
    20166: a 9482 m overcast (B = 100 m, aureole 2.9, white clipped at 235, the sun 22° above the
    horizon), both cameras over-exposed: 0.134 of the sky measured, matches at 104–13710 m, flagged
    ``below_range``; the deck is missed. A strict expected failure."""
    opts = RandomOptions(kind="overcast", mounts=True, optics=True, twice_encoded=True, skylines=True)
    case, r, score, _ = run_random_case(20166, base, 480, tmp_path, options=opts)
    assert score.missed_m == [], (case.describe(), score.found_m)
