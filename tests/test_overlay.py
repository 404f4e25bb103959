"""A camera's on-screen text (its clock, its name) stamped on the sky (cbh.pipeline.overlay,
cbh.sim.overlay): found on real frames and on randomized skies in every style, never on the sky
itself, and kept out of the segmentation and the clip level."""
from __future__ import annotations

from datetime import datetime, timezone
from pathlib import Path

import cv2
import numpy as np
import pytest

from cbh.pipeline.overlay import overlay_text, strokes_per_height
from cbh.sim.overlay import OVERLAY_STYLES, Overlay, draw_overlay

FEHMARN = Path(__file__).resolve().parents[2] / "shared" / "data" / "fehmarn-2016-09-01"
T = datetime(2025, 6, 21, 11, 47, 5, tzinfo=timezone.utc)


def _sky(seed: int, size: int, **options):
    from cbh.geometry.station import load_station
    from cbh.presets import station_path
    from cbh.sim import SkySimulator
    from cbh.sim.randomize import RandomOptions, random_case

    case = random_case(seed, load_station(station_path("unb-lea")), RandomOptions(**options))
    sim = SkySimulator(case.station, case.scene, size_px=size)
    return case, sim, sim.render()


def test_strokes_are_counted_from_black_to_white_along_the_rows():
    """A comb of white strokes on black steps once per stroke; a roof's edge (black below white)
    and grey levels between the two classes step none."""
    comb = np.zeros((10, 40), np.uint8)
    comb[:, 2::4] = 255  # 10 strokes over 40 px: 10 per 40 px = 2.5 per height of 10 px
    assert strokes_per_height(comb) == pytest.approx(10 * 10 / 40)
    roof = np.full((10, 40), 255, np.uint8)
    roof[5:] = 0
    assert strokes_per_height(roof) == 0.0
    grey = comb.copy()
    grey[grey == 0] = 120  # a mid grey between the strokes is no outline
    assert strokes_per_height(grey) == 0.0


@pytest.mark.skipif(not FEHMARN.is_dir(), reason="needs ../shared/data/fehmarn-2016-09-01")
def test_the_real_fehmarn_stamps_are_found_and_nothing_on_its_sky():
    """Fehmarn's VIVOTEK cameras stamp the station's name, the date and time, the university and
    its web address in the four corners, outside the image circle: each corner's text is found
    (at the pipeline's 960 px working size), and nothing inside the circle (its mast, its
    lighthouse, its sunlit cirrus) is taken for text."""
    for name in ("fe3/FE3_Image_20160901_100500_UTCp1.jpg", "fe4/FE4_Image_20160901_103000_UTCp1.jpg"):
        im = cv2.resize(cv2.imread(str(FEHMARN / name)), (960, 960), interpolation=cv2.INTER_AREA)
        m = overlay_text(im)
        assert m is not None
        for corner in (m[:60, :480], m[:60, 480:], m[-60:, :480], m[-60:, 480:]):
            assert corner.sum() > 500  # one line of text, about 15 px by 150–300 px
        yy, xx = np.mgrid[:960, :960]
        assert not m[np.hypot(xx - 479.5, yy - 479.5) < 440].any()


@pytest.mark.parametrize("style", OVERLAY_STYLES)
@pytest.mark.parametrize("size", [480, 960])
def test_each_style_is_found_on_the_sky_and_the_plain_sky_gives_nothing(style, size):
    """White text with a one-pixel outline, a drop shadow or on a black banner, 2 % of the frame
    tall, stamped near the top of a randomized sky with tree and building skylines (its JPEG
    block re-encoded): every pixel it changed is masked; the same sky without it gives nothing."""
    case, sim, shot = _sky(19304, size, skylines=True, unmasked=True)
    plain = shot.views["cam1"].image
    assert overlay_text(plain) is None
    ov = Overlay("CAM1", "%Y-%m-%d %H:%M:%S", style, 0.02, 0.3, 0.12)
    stamped = draw_overlay(plain, ov, T, quality=75)
    changed = np.abs(stamped.astype(int) - plain.astype(int)).max(axis=2) > 30
    m = overlay_text(stamped)
    assert m is not None and changed.sum() > 200
    assert m[changed].mean() > 0.99
    ys, xs = np.nonzero(changed)
    cap = int(0.02 * size) + 1

    def near(k):  # the text's box grown by k cap heights
        out = np.zeros_like(m)
        out[ys.min() - k * cap: ys.max() + k * cap + 1, xs.min() - k * cap: xs.max() + k * cap + 1] = True
        return out

    # the line's box and its margin, and near-black pixels (a skyline's, beside it) a little beyond:
    # not the sky around it
    assert not (m & ~near(2)).any() and (m & ~near(1)).sum() <= 0.01 * m.sum()


def test_randomized_overlays_stamp_each_cameras_own_clock_and_leave_the_truth():
    """RandomOptions(overlays=True): the seed's sky, station and truth unchanged; both cameras in
    one style and place, each its own name, camera 2's clock drawn 0–40 s off."""
    from cbh.geometry.station import load_station
    from cbh.presets import station_path
    from cbh.sim.randomize import RandomOptions, finish_frames, random_case

    base = load_station(station_path("unb-lea"))
    styles, offsets = set(), []
    for seed in range(12):
        plain, ov = random_case(seed, base), random_case(seed, base, RandomOptions(overlays=True))
        assert ov.scene == plain.scene and ov.describe().startswith(plain.describe())
        (a, *_), (b, *_) = ov.overlays
        assert (a.style, a.x_frac, a.y_frac, a.height_frac) == (b.style, b.x_frac, b.y_frac, b.height_frac)
        styles.add(a.style)
        offsets.append(b.clock_offset_s - a.clock_offset_s)
    assert styles == set(OVERLAY_STYLES) and max(offsets) > 5.0 and 0.0 <= min(offsets) and max(offsets) <= 40.0
    case, sim, shot = _sky(2, 240, overlays=True)
    done = finish_frames(case, sim, shot)
    assert all(np.array_equal(done.views[n].height_m, shot.views[n].height_m, equal_nan=True) for n in ("cam1", "cam2"))
    assert not np.array_equal(done.views["cam1"].image, shot.views["cam1"].image)


def test_a_clear_sky_under_a_stamped_clock_stays_clear_and_keeps_its_sun_glare():
    """Randomized clear sky 15 (its cameras clip white at 237): each camera stamps its name and
    clock (white, outlined, 3 % of the frame tall, across the sky near the top; camera 2's clock
    7 s ahead). The pair reads as the unstamped one: clear, no cloud, the sun's glare found
    (the text's white at 255 is not taken for the clip, so the 237 clip still is). Without the
    overlay mask the text was unmatched cloud (``cloud_unmatched``, ``few_points``) and the
    glare was lost."""
    from cbh.pipeline import Pipeline

    case, sim, shot = _sky(15, 240, kind="clear")
    assert case.scene.image.white_level == 237
    plain = [shot.views[n].image for n in ("cam1", "cam2")]
    stamped = [draw_overlay(im, Overlay(f"CAM{k + 1}", "%Y-%m-%d %H:%M:%S", "outline", 0.03, 0.2, 0.16,
                                        clock_offset_s=7.0 * k), shot.time_utc, 80) for k, im in enumerate(plain)]
    want = Pipeline(sim.station).process(*plain, shot.time_utc, channels="bgr")
    got = Pipeline(sim.station).process(*stamped, shot.time_utc, channels="bgr")
    assert "clear_sky" in want.flags and "sun_glare" in want.flags
    assert sorted(got.flags) == sorted(want.flags)
    assert max(got.cloud_fraction.values()) <= 0.02 and not got.layers


def test_a_mask_made_from_frames_leaves_out_the_stamped_clock():
    """``cbh mask`` (:func:`obstacle_mask_from_frames`) on three frames of a randomized sky, each
    stamped with its own time (the seconds change, so the text is neither static nor dark):
    every pixel the stamp changed is masked; without the stamp, the mask has none of it."""
    from cbh.pipeline.obstacles import obstacle_mask_from_frames

    case, sim, shot = _sky(19303, 480)
    cam = sim.station.cameras["cam1"]
    frames, changed = [], np.zeros((480, 480), bool)
    for k in range(3):
        plain = shot.views["cam1"].image
        stamped = draw_overlay(plain, Overlay("CAM1", "%H:%M:%S", "outline", 0.03, 0.3, 0.2), T.replace(second=10 * k), 85)
        changed |= np.abs(stamped.astype(int) - plain.astype(int)).max(axis=2) > 30
        frames.append(stamped)
    mask = obstacle_mask_from_frames(frames, cam.model)
    assert changed.sum() > 300 and (mask[changed] == 0).all()
    plain_mask = obstacle_mask_from_frames([shot.views["cam1"].image] * 3, cam.model)
    assert (plain_mask[changed] == 255).mean() > 0.9


@pytest.mark.parametrize("seed", [19306, 19358])
def test_randomized_clear_skies_under_a_stamp_stay_clear(seed, tmp_path):
    """Two randomized clear skies whose cameras stamp their clock on the sky
    (``eval_random.py --overlays --seed 19300``, 480 px): 19306 (two shadowed lines) read
    ``cloud_unmatched`` and ``few_points`` before the overlay mask, 19358 (a banner) three
    spurious layers at 334, 418 and 1057 m with 9 % cloud. Both are clear: no layer, under
    2 % cloud, and the flags of the same sky unstamped (``clear_sky``; 19306 no ``sun_glare``:
    the text's white is no glare)."""
    from cbh.geometry.station import load_station
    from cbh.presets import station_path
    from cbh.sim.randomize import RandomOptions, run_random_case

    base = load_station(station_path("unb-lea"))
    case, r, score, _ = run_random_case(seed, base, 480, tmp_path, options=RandomOptions(overlays=True))
    _, plain, _, _ = run_random_case(seed, base, 480, tmp_path)
    assert case.kind == "clear" and case.overlays
    assert not r.layers and not score.spurious_m
    assert max(r.cloud_fraction.values()) < 0.02 and "clear_sky" in r.flags
    assert sorted(r.flags) == sorted(plain.flags)


@pytest.mark.slow
def test_a_deck_under_a_banner_at_960_px_is_kept(tmp_path):
    """Randomized 19612 (``eval_random.py --n 40 --seed 19600 --size 960 --overlays --skylines
    --unmasked --mounts``): decks at 403 m (cover 0.67), 1739 and 8984 m, B = 168 m, each camera
    stamping two lines on a banner. The unstamped pair finds 403/1744/8969 m; the stamped one lost
    the 403 m deck (a strict expected failure of stop 70: camera 2 read its sky as 25 % cloud,
    camera 1 91 %). It is kept since stop 72 (each channel saturated at its own clip level,
    ``cbh.pipeline.clip``)."""
    from cbh.geometry.station import load_station
    from cbh.presets import station_path
    from cbh.sim.randomize import RandomOptions, run_random_case

    opts = RandomOptions(overlays=True, skylines=True, unmasked=True, mounts=True)
    case, r, score, _ = run_random_case(19612, load_station(station_path("unb-lea")), 960, tmp_path, options=opts)
    assert 403 in [round(h) for h in score.expected_m]
    assert not score.missed_m


@pytest.mark.slow
@pytest.mark.xfail(strict=True, reason="found in stop 70, not fixed: text across the circle's rim, its glyphs cut by "
                                       "the rim, is not found; its 255 white beats the over-exposed sky's 233 DN clip")
def test_a_stamp_across_the_rim_leaves_the_clip_alone(tmp_path):
    """Randomized 19741 (``eval_random.py --n 100 --seed 19700 --size 480 --overlays --optics
    --mounts --skylines --unmasked --twice-encoded --contrails``): a clear sky over-exposed to
    camera 1's 233 DN clip, a shadowed clock across the top of the circle. Unstamped it flags
    ``sun_glare`` and ``overexposed``; stamped, the clip is read at 255 from 131 pixels of the
    text, and both flags are lost."""
    from cbh.geometry.station import load_station
    from cbh.presets import station_path
    from cbh.sim.randomize import RandomOptions, run_random_case

    base = load_station(station_path("unb-lea"))
    hard = dict(optics=True, mounts=True, skylines=True, unmasked=True, twice_encoded=True, contrails=True)
    _, r, _, _ = run_random_case(19741, base, 480, tmp_path, options=RandomOptions(overlays=True, **hard))
    _, plain, _, _ = run_random_case(19741, base, 480, tmp_path, options=RandomOptions(**hard))
    assert "overexposed" in plain.flags
    assert sorted(r.flags) == sorted(plain.flags)
