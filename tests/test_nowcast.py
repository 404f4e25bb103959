"""The irradiance nowcast (issue 35): the shade geometry on an analytic sky, the export, and the real
Fehmarn pyranometer (slow)."""
from __future__ import annotations

import math
from datetime import datetime, timedelta, timezone
from functools import lru_cache
from types import SimpleNamespace

import numpy as np
import pytest

from .conftest import REPO, SHARED

SAMPLE = REPO / "recordings" / "sample-two-layers.mcap"
FEHMARN = SHARED / "data" / "fehmarn-2016-09-01"


@lru_cache(maxsize=4)
def _sky_rays(height_m: float, size: int):
    """Camera 1 of the default station at ``size`` px; its pixels' rays, which of them look up, and
    the east coordinate where each meets a layer at ``height_m``."""
    from cbh.geometry.station import load_station
    from cbh.presets import station_path

    cam = load_station(station_path()).pair()[0]
    cam = cam.scaled(size / cam.model.width)
    H, W = cam.model.height, cam.model.width
    yy, xx = np.mgrid[0:H, 0:W]
    rays = cam.pixel_to_world(np.column_stack([xx.ravel(), yy.ravel()]).astype(np.float64))
    up = rays[:, 2] > 0.05
    t = np.where(up, (height_m - cam.position_m[2]) / np.where(up, rays[:, 2], 1.0), np.nan)
    return cam, rays, up, cam.position_m[0] + rays[:, 0] * t


def _half_sky(edge_east_m: float, height_m: float = 3000.0, size: int = 320, sun=None, glare_deg: float = 0.0):
    """Camera 1 of the default station at ``size`` px, looking at one layer at ``height_m`` that is
    cloud west of ``edge_east_m`` and clear east of it: its labels, as pair_ground makes them; with
    ``glare_deg`` every pixel within that angle of ``sun`` reads clear (a mask fooled by the aureole)."""
    from cbh.geometry import ground

    cam, rays, up, x = _sky_rays(float(height_m), int(size))
    H, W = cam.model.height, cam.model.width
    lab = np.full(H * W, ground.UNKNOWN, np.int16)
    lab[up & (x < edge_east_m)] = 0
    lab[up & (x >= edge_east_m)] = ground.CLEAR
    if glare_deg:
        lab[up & (rays @ np.asarray(sun) > math.cos(math.radians(glare_deg)))] = ground.CLEAR
    return SimpleNamespace(camera=cam, labels=lab.reshape(H, W), heights=[height_m + float(cam.position_m[2])],
                           motions=[(10.0, 0.0)], cloud_fraction=0.5, sun_dir=sun, valid=True)


def test_the_shadow_edge_arrives_within_a_minute_of_the_truth():
    """A straight cloud edge on a 3000 m layer moving east at 10 m/s, the sun 40° from the zenith
    in the south: the site is shaded while the sun ray meets the cloud. Its shade probability
    crosses 1/2 within a minute of the true arrival of the shadow edge, at every lead up to 5 min
    and for edges 0.2–2.8 km away (the issue's bar: ≥ 90 % of edges within one minute)."""
    from cbh.outputs.nowcast import shade_probability

    zen = math.radians(40.0)
    sun = np.array([0.0, -math.sin(zen), math.cos(zen)])  # towards the south
    errors = []
    for edge in (-200.0, -600.0, -1200.0, -2000.0, -2800.0):  # the edge is west of the site; cloud moves east
        pg = _half_sky(edge)
        site = np.array([0.0, 0.0, float(pg.camera.position_m[2])])
        # the shadow edge reaches the site when the edge has moved |edge| east: t = |edge| / 10 m/s
        truth = -edge / 10.0
        leads = np.arange(0.0, 301.0, 10.0)
        p = np.array([shade_probability(pg, site, sun, lead)[0] for lead in leads])
        # the ray point is x = −v·lead (the sun is due south: no east offset); cloud there while x < edge
        assert np.nanmax(p) <= 1.0 and np.nanmin(p) >= 0.0
        if truth <= 300.0:
            cross = leads[np.flatnonzero(p >= 0.5)[0]] if (p >= 0.5).any() else math.inf
            errors.append(abs(cross - truth))
        else:
            assert np.nanmax(p) < 0.5, (edge, p)  # not yet: sunny throughout
    assert errors and all(e <= 60.0 for e in errors), errors


def test_a_height_error_moves_the_shadow_by_its_share_of_the_sites_distance_from_the_camera():
    """A deck measured 10 % too high (3300 m for 3000 m) is also measured 10 % too fast (11 m/s for
    10 m/s): both come from camera 1's pixels scaled by the height. The errors cancel at the camera:
    the straight cloud edge's shadow still arrives at the camera's site when it does (within 5 s: the
    2 s lead step and a pixel of the 320 px map, 30–40 m there). At a site 2 km east (downwind) the read lands 10 % × 2 km = 200 m upwind of the truth:
    the shadow is forecast 200 m / 11 m/s ≈ 18 s early, whatever the lead (here 120 s and 240 s). This
    is why the read disk's height term is ``HEIGHT_ERROR`` × the site's distance from camera 1
    (:func:`cbh.outputs.nowcast.read_sigma_m`), not a share of the lead or the slant range."""
    from cbh.outputs.nowcast import shade_probability

    zen = math.radians(40.0)
    sun = np.array([0.0, -math.sin(zen), math.cos(zen)])  # due south: the ray point's east = the site's
    for east_m, arrive_s in ((0.0, 120.0), (0.0, 240.0), (2000.0, 120.0), (2000.0, 240.0)):
        pg = _half_sky(east_m - 10.0 * arrive_s, height_m=3000.0, sun=sun)  # the true deck at 3000 m
        pg.heights, pg.motions = [3300.0], [(11.0, 0.0)]  # as measured: 10 % high, 10 % fast
        site = np.array([east_m, 0.0, 0.0])
        leads = np.arange(arrive_s - 30.0, arrive_s + 31.0, 2.0)
        p = np.array([shade_probability(pg, site, sun, lead)[0] for lead in leads])
        forecast = leads[np.flatnonzero(p >= 0.5)[0]]
        early = 0.1 * east_m / 11.0
        assert abs(arrive_s - forecast - early) <= 5.0, (east_m, arrive_s, forecast)


def test_the_lagged_ensemble_reads_the_cloud_away_from_the_glare():
    """A cloud deck moving east at 10 m/s will cover the sun ray of the site (the sun 40° from the
    zenith in the south) 5 min from now, and does at the issue time, but the issue pair's mask
    calls everything within 15° of the sun clear (the aureole, as on the real Fehmarn deck). Its own
    lead-0 forecast says sun; the time-lagged ensemble uses the pair of 5 min before, which read
    that cloud 37° from the sun, and says shade, seen earlier. Without the older pair it can only
    repeat the issue pair's answer."""
    from datetime import timedelta

    from cbh.outputs.nowcast import Site, glare_angle_deg, lagged_shade, shade_probability

    zen = math.radians(40.0)
    sun = np.array([0.0, -math.sin(zen), math.cos(zen)])
    t0 = datetime(2016, 9, 1, 9, 0, tzinfo=timezone.utc)
    old = _half_sky(-1000.0, sun=sun)
    now = _half_sky(2000.0, sun=sun, glare_deg=15.0)  # the same edge 300 s later, the glare called clear
    old.time_utc, now.time_utc = t0, t0 + timedelta(seconds=300)
    site_m = np.array([0.0, 0.0, float(now.camera.position_m[2])])
    site = Site("s", math.nan, math.nan, float(site_m[2]), site_m)
    assert shade_probability(now, site_m, sun, 0.0)[0] < 0.1  # fooled by the glare
    assert glare_angle_deg(now, site_m, sun, 0.0) < 1.0 and 30.0 < glare_angle_deg(old, site_m, sun, 300.0) < 45.0
    p, why = lagged_shade([old, now], site, sun, now.time_utc)
    assert p > 0.9 and why == "seen_earlier", (p, why)
    p, why = lagged_shade([now], site, sun, now.time_utc)
    assert p < 0.1 and why == "", (p, why)
    # 3 min on, both pairs read the deck outside the aureole (25° and 47°) and agree: shade, the
    # issue pair's own forecast among those averaged
    p, why = lagged_shade([old, now], site, sun, now.time_utc + timedelta(seconds=180))
    assert p > 0.9 and why == "", (p, why)


def test_the_disk_grows_with_the_motions_measured_error():
    """A 200 m cloud 3.1 km upwind of the sun ray of the site (the sun 40° from the zenith in the
    south) on a 3000 m layer moving east at 10 m/s shades the site from 300 to 320 s ahead. Three
    pairs a minute apart measured the motion within 0.1 m/s: the disk at 310 s then has σ ≈ 34 m
    (10 m, 8.5 m of the sun's disk over the 3.9 km ray, 0.1 m/s × 310 s, in quadrature; the site
    at the camera: no height term) and the strip's shade probability 1/2 < p (erf(100/(34·√2)) ≈ 1
    for one read). The prior alone (5 % + 0.2 m/s: 0.7 m/s, σ ≈ 220 m) blurs it below 1/2
    (erf(100/(220·√2)) ≈ 0.35): the shadow would be missed. The measured error is the members' scatter
    (sample standard deviation, the RMS of both axes), at least 1 % of the speed, unknown from one motion."""
    from datetime import timedelta

    from cbh.actions.nowcast import _ensemble
    from cbh.geometry import ground
    from cbh.outputs.nowcast import Site, lagged_shade, motion_errors

    zen = math.radians(40.0)
    sun = np.array([0.0, -math.sin(zen), math.cos(zen)])
    t0 = datetime(2016, 9, 1, 9, 0, tzinfo=timezone.utc)
    history, recent, winds = [], [], [(9.9, -0.1), (10.1, 0.1), (10.0, 0.0)]
    for i, wind in enumerate(winds):  # the strip 600 m further west a minute earlier
        back = 600.0 * (len(winds) - 1 - i)
        pg, west = _half_sky(-3000.0 - back, sun=sun), _half_sky(-3200.0 - back, sun=sun)
        pg.labels[west.labels == 0] = ground.CLEAR
        pg.motions, pg.time_utc = [wind], t0 + timedelta(seconds=60.0 * i)
        history = _ensemble(history, pg, recent)
    err = history[-1].motion_errors[0]
    assert err == pytest.approx(math.sqrt(np.mean(np.var(np.array(winds), axis=0, ddof=1))))  # 0.1 m/s
    assert motion_errors(history[-1:]) == [pytest.approx(math.nan, nan_ok=True)]
    steady = [SimpleNamespace(heights=[3000.0], motions=[(10.0, 0.0)])] * 3
    assert motion_errors(steady) == [pytest.approx(0.1)]  # the floor: 1 % of 10 m/s
    # pairs 10 s apart, the first without a motion (a station's first pair): the ensemble keeps one
    # member a minute (the first and the newest), but the error is measured from the second motion on
    quick, recent = [], []
    for i, wind in enumerate([(math.nan, math.nan), *winds[:2]]):
        q = SimpleNamespace(heights=[3000.0], motions=[wind], time_utc=t0 + timedelta(seconds=10.0 * i))
        quick = _ensemble(quick, q, recent)
    assert [m.time_utc.second for m in quick] == [0, 20]
    assert quick[-1].motion_errors == [pytest.approx(0.1 * math.sqrt(2.0))]  # the two motions' scatter
    site_m = np.array([0.0, 0.0, float(pg.camera.position_m[2])])
    site = Site("s", math.nan, math.nan, float(site_m[2]), site_m)
    tv = pg.time_utc + timedelta(seconds=310.0)
    p, _ = lagged_shade(history, site, sun, tv)
    assert p > 0.8, p
    pg.motion_errors = None  # the prior
    p, _ = lagged_shade([pg], site, sun, tv)
    assert 0.2 < p < 0.5, p


def test_the_sunny_level_is_the_pyranometers_upper_quantile():
    """With a pyranometer the prior's sunny level is the upper quantile of its last hour's
    clear-sky index: a cloudless hour at 1.10 (the clear-sky model 10 % low for the day's clean
    air) says 1.10, a broken hour half in shade still says its sunny 1.10, not the mean 0.78; too
    short or nonsense records say nothing, and the level stays within 0.8–1.4."""
    from cbh.outputs.nowcast import Levels, sunny_level

    rng = np.random.default_rng(3)
    clear = 1.10 + rng.normal(0.0, 0.01, 60)
    broken = np.where(np.arange(60) % 2 == 0, clear, 0.45)
    assert abs(sunny_level(clear) - 1.11) < 0.02 and abs(sunny_level(broken) - 1.11) < 0.02
    assert math.isnan(sunny_level(clear[:10])) and math.isnan(sunny_level(np.full(60, np.nan)))
    assert sunny_level(np.full(60, 1.9)) == 1.4
    lv = Levels()
    lv.set_prior(1.1, 0.5)
    assert lv.levels() == pytest.approx((1.1, 0.5))


def test_the_levels_follow_the_cloud_that_is_there_now():
    """The shade level is the cloud's optical depth, and the cloud changes: 30 min of a thin deck
    (0.85 of the clear sky in shade) then a thick one (0.5). Observations age (their weight halves
    every 5 min), so 30 min into the thick deck the shade level is within 0.06 of 0.5 (equal
    weights for all would still say 0.68), while the sunny level stays; and a station that runs
    for months keeps only the last 8 half-lives of them."""
    from cbh.outputs.nowcast import LEVELS_HALF_LIFE_S, Levels

    t0 = datetime(2016, 9, 1, 9, 0, tzinfo=timezone.utc)
    aged, equal = Levels(), Levels(half_life_s=math.inf)
    for minute in range(60):
        k_shade = 0.85 if minute < 30 else 0.5
        for i in range(11):  # one verified forecast per lead 0 … 10 min, alternately shade and sun
            p, k = (1.0, k_shade) if i % 2 else (0.0, 1.2)
            for lv in (aged, equal):
                lv.add(p, k, t0 + timedelta(minutes=minute, seconds=i))
    ks, kd = aged.levels()
    assert abs(kd - 0.5) < 0.06 and abs(ks - 1.2) < 0.02, (ks, kd)
    assert equal.levels()[1] > 0.65
    for minute in range(60, 300):  # four more hours
        aged.add(0.0, 1.2, t0 + timedelta(minutes=minute))
    assert abs(aged.n - 8 * LEVELS_HALF_LIFE_S / 60.0) <= 1  # one a minute, for 8 half-lives
    overnight = t0 + timedelta(hours=20)  # the next morning's first issue time: yesterday is gone
    assert aged.levels(overnight) == pytest.approx(aged.prior, abs=1e-6) and aged.n == 0


def test_the_map_ends_where_the_camera_stops_seeing():
    """A sun ray that leaves the camera's view (a low sun and a long lead) has no forecast, and says so."""
    from cbh.outputs.nowcast import shade_probability

    pg = _half_sky(-500.0, height_m=1000.0)
    zen = math.radians(75.0)
    p, why = shade_probability(pg, np.zeros(3), np.array([0.0, -math.sin(zen), math.cos(zen)]), 600.0)
    assert math.isnan(p) and why == "beyond_view"
    p, why = shade_probability(pg, np.zeros(3), np.array([0.0, 0.0, -1.0]), 0.0)
    assert math.isnan(p) and why == "night"


def _checker_sky(height_m: float = 1000.0, size: int = 320, cell_m: float = 800.0, far_deg: float = 90.0,
                 far_label: int | None = None):
    """Camera 1 looking at one layer at ``height_m`` that is a checkerboard of ``cell_m`` cloud and
    clear squares (cloud where the east and north cell indices add up to an even number: half the
    layer, and half of every ring about the camera); beyond ``far_deg`` from the zenith every
    pixel reads ``far_label`` when one is given (the real deck read overcast there: 0; haze read
    clear: ground.CLEAR)."""
    from cbh.geometry import ground

    cam, rays, up, x = _sky_rays(float(height_m), int(size))
    t = np.where(up, (height_m - cam.position_m[2]) / np.where(up, rays[:, 2], 1.0), np.nan)
    y = cam.position_m[1] + rays[:, 1] * t
    with np.errstate(invalid="ignore"):
        cloud = (np.floor(x / cell_m) + np.floor(y / cell_m)) % 2 == 0
    lab = np.full(rays.shape[0], ground.UNKNOWN, np.int16)
    lab[up & cloud] = 0
    lab[up & ~cloud] = ground.CLEAR
    if far_label is not None:
        lab[up & (rays[:, 2] < math.cos(math.radians(far_deg)))] = far_label
    H, W = cam.model.height, cam.model.width
    return SimpleNamespace(camera=cam, labels=lab.reshape(H, W), heights=[float(height_m)], motions=[(0.0, 0.0)],
                           cloud_fraction=0.5, sun_dir=None, valid=True)


def test_the_map_reaches_past_65_degrees_where_it_agrees_with_itself_overhead():
    """A 1000 m layer read 70–72° from camera 1's zenith (the sun 68° from the zenith in the east,
    two sites whose sun rays meet a clear and a cloud square of a checkerboard, 2.8 km out): the
    map reads the same half cloud there as overhead, so it reaches on (``map_reach_deg``: to
    ``MAX_REACH_DEG``) and both sites get the right shade. Where the far map reads the sky
    overcast beyond 65° (the real Fehmarn deck's failure) or clear beyond 67.5° (distant cloud
    lost in the haze, as in the simulator), its cloud share there leaves the overhead share's
    tolerance and the map ends: ``beyond_view``, as with the fixed 65° before."""
    from cbh.geometry import ground
    from cbh.outputs.nowcast import MAX_REACH_DEG, MAX_ZENITH_DEG, map_reach_deg, shade_probability

    zen = math.radians(68.0)
    sun = np.array([math.sin(zen), 0.0, math.cos(zen)])  # towards the east
    pg = _checker_sky()
    z = float(pg.camera.position_m[2])
    # the sun ray meets the layer 2475 m east of the site: square (3, 0) is clear, (3, 1) cloud
    clear_site, cloud_site = np.array([325.0, 400.0, z]), np.array([325.0, 1200.0, z])
    assert map_reach_deg(pg) == [MAX_REACH_DEG]
    p, why = shade_probability(pg, clear_site, sun, 0.0)
    assert p < 0.1 and why == "", (p, why)
    p, why = shade_probability(pg, cloud_site, sun, 0.0)
    assert p > 0.9 and why == "", (p, why)
    overcast = _checker_sky(far_deg=MAX_ZENITH_DEG, far_label=0)
    assert map_reach_deg(overcast) == [MAX_ZENITH_DEG]
    p, why = shade_probability(overcast, clear_site, sun, 0.0)
    assert math.isnan(p) and why == "beyond_view"
    hazy = _checker_sky(far_deg=67.5, far_label=ground.CLEAR)
    assert map_reach_deg(hazy) == [67.5]
    p, why = shade_probability(hazy, cloud_site, sun, 0.0)
    assert math.isnan(p) and why == "beyond_view"


def test_only_the_issue_pairs_own_read_reaches_past_65_degrees():
    """The lagged ensemble: a pair issued a minute earlier whose map of the same deck reads the
    opposite there (its far read 70–72° from the zenith) is left out, as its map stops at
    ``MAX_ZENITH_DEG``; only the issue pair's own map reaches on (simulated: older members' far
    reads of the low deck, 3–6 min old, read cloud where the shadow did not come). The clear site
    then reads clear (with the older read averaged in it would read half) and the cloud one cloud."""
    from cbh.geometry import ground
    from cbh.outputs.nowcast import Site, lagged_shade

    zen = math.radians(68.0)
    sun = np.array([math.sin(zen), 0.0, math.cos(zen)])
    t0 = datetime(2016, 9, 1, 9, 0, tzinfo=timezone.utc)
    issue = _checker_sky()
    older = _checker_sky()
    older.labels = np.where(older.labels == 0, ground.CLEAR, np.where(older.labels == ground.CLEAR, 0, older.labels))
    older.time_utc, issue.time_utc = t0, t0 + timedelta(minutes=1)
    z = float(issue.camera.position_m[2])
    for (e, n), want in (((325.0, 400.0), 0.0), ((325.0, 1200.0), 1.0)):
        site = Site("s", math.nan, math.nan, z, np.array([e, n, z]))
        p, why = lagged_shade([older, issue], site, sun, issue.time_utc)
        assert abs(p - want) < 0.1 and why == "", (e, n, p, why)


def test_a_plant_is_the_share_of_its_points_in_shade(tmp_path):
    """A plant (a polygon, a list of points, or a CSV's rows sharing a name) straddling a cloud's
    shadow edge: its shade probability is the share of its area under the cloud (0.5 for a
    rectangle half under it, within the grid's step), where a point inside the clear half says 0."""
    import pymap3d

    from cbh.errors import ConfigError
    from cbh.geometry.station import load_station
    from cbh.outputs.nowcast import parse_site, parse_sites, shade_at_site
    from cbh.presets import station_path

    st = load_station(station_path())
    pg = _half_sky(-200.0)
    zen = math.radians(40.0)
    sun = np.array([0.0, -math.sin(zen), math.cos(zen)])

    def ll(e, n):
        lat, lon, _ = pymap3d.enu2geodetic(e, n, 0.0, st.latitude_deg, st.longitude_deg, st.altitude_m)
        return f"{float(lat):.7f},{float(lon):.7f}"

    rect = ";".join(ll(e, n) for e, n in ((-600, -100), (200, -100), (200, 100), (-600, 100)))
    plant = parse_site(f"farm=polygon:{rect}", st)
    assert plant.name == "farm" and 40 <= len(plant.points_m) <= 80
    p, why, _ = shade_at_site(pg, plant, sun, 0.0)
    assert why == "" and abs(p - 0.5) < 0.1, p
    row = parse_site("row=" + ";".join(ll(e, 0) for e in (-500, -400, -300, 0, 100, 200)), st)
    assert abs(shade_at_site(pg, row, sun, 0.0)[0] - 0.5) < 0.05
    assert shade_at_site(pg, parse_site(ll(100, 0), st), sun, 0.0)[0] < 0.05
    (tmp_path / "sites.csv").write_text("name,latitude,longitude\n" + "".join(
        f"{n},{ll(e, 0)}\n" for n, e in (("a", -500), ("a", 100), ("b", 150))))
    sites = parse_sites([f"@{tmp_path / 'sites.csv'}", "c=" + ll(0, 0)], st)
    assert [x.name for x in sites] == ["a", "b", "c"] and len(sites[0].points_m) == 2 and sites[1].points_m is None
    with pytest.raises(ConfigError, match="given twice"):
        parse_sites(["a=" + ll(0, 0), "a=" + ll(10, 0)], st)
    with pytest.raises(ConfigError, match="at least 3 corners"):
        parse_site("p=polygon:" + ";".join(ll(e, 0) for e in (0, 10)), st)


def test_irradiance_export_rows_and_dataset(tmp_path, capsys):
    """`cbh export --product irradiance`: one row per issue time, site and lead with the clear-sky
    GHI of pvlib; a NetCDF dataset on (time, lead_time, site); refused without a site."""
    import csv

    import xarray as xr

    from cbh.cli.main import main
    from cbh.outputs.record import open_session

    st = open_session(SAMPLE).station
    site = f"plant={st.latitude_deg + 0.001},{st.longitude_deg}"
    out = tmp_path / "n.csv"
    assert main(["export", str(SAMPLE), "--product", "irradiance", "--site", site, "--leads", "0,1,5",
                 "-o", str(out)]) == 0
    assert "8 issue times x 1 site(s) x 3 leads" in capsys.readouterr().out
    with out.open() as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == 24 and rows[0]["site"] == "plant"
    for r in rows:
        cs = float(r["clear_sky_ghi_wm2"])
        assert 500.0 < cs < 1100.0  # a June afternoon at the sample station
        if r["ghi_wm2"]:
            assert 0.0 <= float(r["shade_probability"]) <= 1.0
            assert float(r["ghi_wm2"]) == pytest.approx(float(r["clear_sky_index"]) * cs, rel=2e-3)
    nc = tmp_path / "n.nc"
    assert main(["export", str(SAMPLE), "--product", "irradiance", "--site", site, "-o", str(nc)]) == 0
    ds = xr.open_dataset(nc)
    assert ds["ghi_wm2"].dims == ("time", "lead_time", "site") and ds.sizes["lead_time"] == 21
    ds.close()
    assert main(["export", str(SAMPLE), "--product", "irradiance", "-o", str(out)]) == 2
    assert "needs at least one --site" in capsys.readouterr().err


def test_pyranometer_records_read_in_their_zone(tmp_path):
    """The LEX 2016 logger's file (date; time_utcp1; …; G_wm2) is read as UTC: 10:00 UTC+1 is 09:00."""
    from cbh.outputs.nowcast import read_pyranometer

    f = tmp_path / "r.csv"
    f.write_text("date;time_utcp1;G_wm2\n01.09.2016;10:00;531.8\n01.09.2016;10:01;-1\n")
    t, g = read_pyranometer(f)
    assert t[0] == datetime(2016, 9, 1, 9, 0, tzinfo=timezone.utc) and g[0] == 531.8 and math.isnan(g[1])


@pytest.mark.slow
@pytest.mark.skipif(not FEHMARN.is_dir(), reason="needs ../shared/data/fehmarn-2016-09-01")
def test_the_real_pyranometer_half_hour(tmp_path):
    """The real hour's first half against its pyranometer (benchmarks/eval_irradiance.py): skill
    against smart persistence above 0 at 5 and 10 min, and at lead 0 an RMSE at most 0.8× the
    clear-sky guess's (the issue's targets; measured +0.20, +0.28 and 0.76 with the layer-wise
    time-lagged ensemble and the read disk's σ in quadrature), with a forecast at every issue time for those leads. The levels learn from the same
    forecasts whichever leads are asked for: "0,5,10" gives what the benchmark's eight leads give."""
    import sys

    sys.path.insert(0, str(REPO / "benchmarks"))
    from eval_irradiance import evaluate, record

    res = evaluate(record(FEHMARN, tmp_path / "f.mcap"), FEHMARN, "0,5,10")
    for lead in (5, 10):
        v = res["leads"][lead]
        assert v["skill_vs_persistence"] > 0.0 and v["n"] >= 28, v
    assert res["leads"][0]["rmse_over_clear_sky"] <= 0.8 and res["leads"][0]["n"] >= 28, res["leads"][0]


@pytest.mark.slow  # (4 real pairs through `cbh run`: 6 s)
@pytest.mark.skipif(not FEHMARN.is_dir(), reason="needs ../shared/data/fehmarn-2016-09-01")
def test_a_station_states_its_pyranometer(tmp_path, capsys):
    """``[station] pyranometer = FILE`` (relative to the station file) travels with the recording:
    the export learns its levels from it without --pyranometer."""
    from cbh.cli.main import main

    text = (FEHMARN / "station.toml").read_text().replace("altitude_m = 9.0\n", 'altitude_m = 9.0\npyranometer = "r.csv"\n', 1)
    (tmp_path / "st.toml").write_text(text)
    (tmp_path / "r.csv").symlink_to(FEHMARN / "radiation-20160901.csv")
    d = {}
    for cam in ("fe3", "fe4"):
        d[cam] = tmp_path / cam
        d[cam].mkdir()
        for f in sorted((FEHMARN / cam).glob("*.jpg"))[:4]:
            (d[cam] / f.name).symlink_to(f)
    rec = tmp_path / "r.mcap"
    assert main(["run", "--station", str(tmp_path / "st.toml"), "--source", f"fe3={d['fe3']}", "--source",
                 f"fe4={d['fe4']}", "--record", str(rec), "-q"]) == 0
    capsys.readouterr()
    assert main(["export", str(rec), "--product", "irradiance", "--site", "54.4947,11.240817", "--leads", "0:3",
                 "-o", str(tmp_path / "n.csv")]) == 0
    out = capsys.readouterr().out
    assert "levels site1: k_sun" in out and "measurements" in out, out


@pytest.mark.slow  # (two 10 min runs of the scene: about 50 s)
def test_shadow_edges_in_simulation_meet_the_target():
    """benchmarks/eval_nowcast_sim.py as run by default (the two-layer scene at 480 px, 10 min):
    the issue's target, the forecast shade within 60 s of ≥ 90 % of the true shadow edges, met at
    every lead up to 5 min over all edges, abstentions counted as misses (measured 94 %, 93 %, 94 %,
    94 %, 94 %: 46 of 49 at 5 min; 88 % while the map ended at 65° from the zenith whatever it
    showed, the site whose lower deck's upwind cloud lay at 65–70° saying ``beyond_view``).
    The ensemble no worse than the issue pair alone at 0 and 1 min (where the masked sun hides the
    issue pair's own read)."""
    import sys

    sys.path.insert(0, str(REPO / "benchmarks"))
    from eval_nowcast_sim import evaluate

    res = evaluate("two-layers", 480, 10.0)["leads"]
    one = evaluate("two-layers", 480, 10.0, single=True)["leads"]
    assert res[0]["edges"] >= 90, res
    for lead in (0, 60, 120, 180):
        assert res[lead]["share"] >= 0.9, (lead, res[lead])
    assert res[300]["share"] >= 0.9 and res[300]["share_with_forecast"] >= 0.9, res[300]
    assert res[0]["share"] >= one[0]["share"] and res[60]["share"] >= one[60]["share"], (res, one)


def test_the_simulators_ground_shadow_agrees_with_what_camera_1_sees(tmp_path):
    """The scene's own shadow on the ground (the nowcast's truth in simulation, written by `cbh
    simulate` into each truth NPZ) agrees with camera 1's rendered truth where the camera sees
    the sun ray's cloud: at least 90 % of 169 sites (measured 94 % at 480 px; the camera fades
    texture finer than its pixels, the ground truth does not)."""
    import sys
    from datetime import timedelta

    sys.path.insert(0, str(REPO / "benchmarks"))
    from eval_nowcast_sim import truth_shade

    from cbh.actions.simulate import simulate_to_folder
    from cbh.geometry.station import load_station
    from cbh.geometry.sun import sun_position
    from cbh.presets import scene_path, station_path
    from cbh.sim import SkySimulator, load_scene
    from cbh.sim.ground import ground_shade

    sc = load_scene(scene_path("two-layers"))
    sim = SkySimulator(load_station(station_path()), sc, size_px=480)
    st, cam1 = sim.station, sim.station.pair()[0].name
    z = float(st.cameras[cam1].position_m[2])
    sites = np.array([[x, y, z] for x in np.linspace(-1500, 1500, 13) for y in np.linspace(-1500, 1500, 13)])
    agree = known = 0
    for i in range(2):
        t = sc.time_utc + timedelta(seconds=120 * i)
        shot = sim.render(t, cameras=[cam1])
        sp = sun_position(st.latitude_deg, st.longitude_deg, st.altitude_m, t)
        cam = np.array([truth_shade(shot.views[cam1], shot.layers, sp.direction_enu, s) for s in sites])
        ground, thick = ground_shade(sim, t, sites)
        ok = np.isfinite(cam)
        agree, known = agree + int((cam[ok] == ground[ok]).sum()), known + int(ok.sum())
        assert np.all(thick[ground == 0] == 0) and np.all((thick >= 0) & (thick <= 1))
    assert known > 200 and agree / known >= 0.9, (agree, known)
    list(simulate_to_folder(tmp_path / "s", frames=1, size_px=160))
    npz = np.load(next((tmp_path / "s" / "truth").glob("*.npz")))
    assert npz["ground_shade"].shape == (len(npz["ground_y_m"]), len(npz["ground_x_m"]))
    assert 0.05 < float(np.mean(npz["ground_shade"])) < 0.95


def test_quicklook_gains_the_ghi_panel_with_a_pyranometer(tmp_path, capsys):
    """`cbh quicklook --pyranometer FILE`: the measured GHI, the clear sky and the nowcast 5 and 10
    min ahead in a fifth panel (the figure grows by it); without one, the four panels as before."""
    import cv2

    from cbh.cli.main import main

    pyr = tmp_path / "g.csv"
    pyr.write_text("time_utc,ghi_wm2\n" + "".join(f"2024-06-21T14:{m:02d}:00Z,{700 + 10 * m}\n" for m in range(12)))
    assert main(["quicklook", str(SAMPLE), "-o", str(tmp_path / "a.png"), "--pyranometer", str(pyr)]) == 0
    assert "with the GHI panel" in capsys.readouterr().out
    assert main(["quicklook", str(SAMPLE), "-o", str(tmp_path / "b.png")]) == 0
    assert "GHI" not in capsys.readouterr().out
    a, b = cv2.imread(str(tmp_path / "a.png")), cv2.imread(str(tmp_path / "b.png"))
    assert a.shape[1] == b.shape[1] and a.shape[0] > b.shape[0] * 1.15


def test_a_pyranometer_file_that_is_not_one_is_one_line(tmp_path, capsys):
    """A recording (binary) or a CSV without a GHI column given as the pyranometer: one line, exit 2."""
    from cbh.cli.main import main

    for bad, says in ((SAMPLE, "not text"), (tmp_path / "x.csv", "no GHI column")):
        if bad.suffix == ".csv":
            bad.write_text("time_utc,temperature\n2024-06-21T14:00:00Z,20\n")
        assert main(["export", str(SAMPLE), "--product", "irradiance", "--site", "-15.76,-47.87", "--pyranometer",
                     str(bad), "-o", str(tmp_path / "n.csv")]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and says in err[0] and err[0].isprintable(), err
