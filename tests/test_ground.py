"""Cloud and shadow maps on the ground against the simulator's physics, and their files."""
from __future__ import annotations

import math
from dataclasses import replace
from datetime import timedelta

import numpy as np
import pytest

from cbh.errors import ConfigError

SIZE = 256  # camera 1's render width [px]
PROBES = np.linspace(-2000.0, 2000.0, 7)  # probe cameras on a 7 x 7 grid of ground points [m]


def _probe_sim(unb_station, cameras: tuple[str, ...], size: int):
    """(simulator, scene, probes): the two-layer scene seen by the station's ``cameras`` and by
    49 probe cameras (camera 1's model) standing on the ground at PROBES × PROBES."""
    from cbh.presets import scene_path
    from cbh.sim import SkySimulator
    from cbh.sim.scene import load_scene

    c1 = unb_station.cameras["cam1"]
    cams = {k: unb_station.cameras[k] for k in cameras}
    probes = []
    for i, x in enumerate(PROBES):
        for j, y in enumerate(PROBES):
            name = f"p{i}_{j}"
            cams[name] = replace(c1, name=name, position_m=np.array([x, y, 0.0]))
            probes.append((name, float(x), float(y)))
    scene = load_scene(scene_path("two-layers"))
    return SkySimulator(replace(unb_station, cameras=cams).scaled(size), scene), scene, probes


@pytest.fixture(scope="module")
def probe_world(unb_station):
    """The two-layer scene seen by camera 1 and by 49 probe cameras standing on the ground.

    A probe at ground point g tells the truth about g: its pixel towards the sun is cloud
    exactly when g lies in a cloud's shadow (the renderer traces that ray through the layers),
    with nothing of cbh's ground-projection code involved.
    """
    return _probe_sim(unb_station, ("cam1",), SIZE)


def _labels(sim, scene, t, *, sun_disk: bool):
    """Camera 1's truth labels at time t (perfect segmentation and heights: tests the geometry)."""
    from cbh.geometry import ground
    from cbh.pipeline.config import MasksConfig
    from cbh.geometry.sun import sun_position
    from cbh.pipeline.masks import angle_map_deg, static_sky_mask

    st = sim.station
    cam = st.cameras["cam1"]
    v = sim.view("cam1", t)
    usable = static_sky_mask(cam, MasksConfig())
    sun = sun_position(st.latitude_deg, st.longitude_deg, st.altitude_m, t).direction_enu
    if sun_disk:
        usable &= angle_map_deg(cam, sun) > MasksConfig().sun_radius_deg
    heights = [l.height_m for l in scene.layers]
    covers = [float(np.mean(v.height_m[usable] == np.float32(h))) for h in heights]
    return cam, ground.layer_labels(v.cloud_mask, usable, v.height_m, heights, covers), heights, sun


def _truth_shaded(sim, probes, sun, t) -> np.ndarray:
    out = []
    for name, _x, _y in probes:
        cam = sim.station.cameras[name]
        c, r = np.floor(cam.direction_to_pixel(sun)[0] + 0.5).astype(int)
        out.append(bool(sim.view(name, t).cloud_mask[r, c]))
    return np.array(out)


@pytest.mark.slow
def test_shadow_map_agrees_with_simulated_shadows_and_is_not_displaced(probe_world, unb_station):
    from cbh.geometry import ground

    sim, scene, probes = probe_world
    grid = ground.GroundGrid(25.0, 2500.0, unb_station.latitude_deg, unb_station.longitude_deg)
    agree, known, shifted, flat_agree = [], [], [], []
    for dt in (0.0, 90.0):  # two skies: the clouds moved 0.6-0.8 km in between
        t = scene.time_utc + timedelta(seconds=dt)
        cam, labels, heights, sun = _labels(sim, scene, t, sun_disk=True)
        shadow = ground.shadow_map(cam, labels, heights, sun, grid)
        truth = _truth_shaded(sim, probes, sun, t)
        assert 0.2 < truth.mean() < 0.8  # both shaded and sunlit probes: the comparison can fail

        def agreement(m, dx=0.0, dy=0.0):
            v = np.array([m[grid.index(x + dx, y + dy)] for _, x, y in probes])
            ok = np.isfinite(v)
            return float(np.mean(v[ok] == truth[ok])), float(ok.mean())

        a, k = agreement(shadow)
        agree.append(a)
        known.append(k)
        shifted.append(max(agreement(shadow, dx, dy)[0] for dx, dy in ((250, 0), (-250, 0), (0, 250), (0, -250))))
        flat = ground.combine_layers(list(ground.cloud_maps(cam, labels, heights, grid)), (grid.n, grid.n))
        flat_agree.append(agreement(flat)[0])  # vertical projection: the sun displacement left out
    agree, shifted, flat_agree = np.mean(agree), np.mean(shifted), np.mean(flat_agree)
    # Mismatches come from probes within about one camera-1 pixel footprint of a cloud edge
    # (at 256 px, 0.7 deg/px: 100-150 m at the 3500 m layer seen 50-60 deg off the zenith),
    # against cloud features of ~1 km; and from the simulator drawing less detail where camera
    # 1 sees the layer at a grazing angle. Measured 0.97 and 0.78 (mean 0.87) of the 65-75 %
    # of probes the map knows (the rest: behind the lower layer); over five skies 0.78-0.97
    # with no consistent best shift (within ±100 m, in varying directions).
    print(f"shadow agreement {agree:.3f} known {known} shifted 250 m {shifted:.3f} vertical {flat_agree:.3f}")
    assert min(known) >= 0.6 and agree >= 0.8, (agree, known)
    # Position: shifted by 250 m (the best of four directions) the map agrees far worse, and so
    # does the vertical projection: the shadows sit where the physics puts them.
    assert shifted <= agree - 0.15 and flat_agree <= agree - 0.15, (agree, shifted, flat_agree)


@pytest.mark.parametrize("lead, min_agree", [(60.0, 0.9), pytest.param(300.0, 0.75, marks=pytest.mark.slow)])
def test_sun_blocked_forecast_follows_the_layer_motion(probe_world, lead, min_agree):
    """Frozen advection with the scene's wind: the forecast at every probe point against the
    simulator rendered ``lead`` seconds later (whose clouds move with exactly that wind)."""
    from cbh.geometry import ground
    from cbh.geometry.sun import sun_position

    sim, scene, probes = probe_world
    t = scene.time_utc
    cam, labels, heights, _ = _labels(sim, scene, t, sun_disk=False)
    st = sim.station
    sun_later = sun_position(st.latitude_deg, st.longitude_deg, st.altitude_m, t + timedelta(seconds=lead)).direction_enu
    truth = _truth_shaded(sim, probes, sun_later, t + timedelta(seconds=lead))
    winds = [l.wind_ms for l in scene.layers]
    pred = np.array([ground.sun_blocked(cam, labels, heights, winds, sun_later, lead, at_m=(x, y)) for _, x, y in probes])
    still = np.array([ground.sun_blocked(cam, labels, heights, [(0.0, 0.0)] * 2, sun_later, lead, at_m=(x, y))
                      for _, x, y in probes])
    known = np.isfinite(pred)
    agree = float(np.mean(pred[known] == truth[known]))
    # Same edge argument as the shadow map, but the cloud that will cover the sun is looked up
    # upwind, farther out and lower in camera 1's view (larger footprint): measured 0.94 at
    # +1 min (clouds moved 0.4-0.5 km) and 0.80 at +5 min (1.9-2.6 km). Ignoring the motion
    # ("still") must do much worse: measured 0.61 and 0.36.
    assert known.mean() >= 0.5 and agree >= min_agree, (agree, known.mean())
    ks = np.isfinite(still)
    assert float(np.mean(still[ks] == truth[ks])) <= agree - 0.2
    # unknown motion: no forecast (NaN), never a guess
    assert math.isnan(ground.sun_blocked(cam, labels, heights, [(math.nan, math.nan)] * 2, sun_later, lead))


def test_ground_table_is_strict_and_has_defaults(tmp_path, unb_station, repo):
    from cbh.geometry.station import load_station

    g = unb_station.ground
    assert (g.resolution_m, g.extent_m, g.n) == (50.0, 5000.0, 201)
    lat, lon = g.lat_lon()
    i, j = g.index(0.0, 0.0)
    assert (lat[i, j], lon[i, j]) == (unb_station.latitude_deg, unb_station.longitude_deg)
    # 1 km north at -15.76 deg: WGS84 meridional radius a(1-e²)/(1-e² sin²φ)^1.5 = 6.34015e6 m
    assert abs((lat[i + 20, j] - lat[i, j]) - 1000.0 / 6.34015e6 * 180 / math.pi) < 1e-7  # 1 cm
    text = (repo / "configs" / "unb-lea.toml").read_text()  # inline intrinsics: loads from anywhere

    def load(extra: str):
        p = tmp_path / "station.toml"
        p.write_text(text + extra)
        return load_station(p)

    st = load('\n[ground]\nresolution_m = 100.0\nextent_m = 3000.0\n')
    assert st.ground.n == 61 and st.ground.x_m[-1] == 3000.0
    with pytest.raises(ConfigError, match="ground.resolution: unknown key"):
        load('\n[ground]\nresolution = 100.0\n')
    with pytest.raises(ConfigError, match="ground.extent_m"):
        load('\n[ground]\nextent_m = -1\n')


def test_station_metadata_is_strict_and_survives_a_recording(tmp_path, repo):
    import tomllib

    from cbh.geometry.station import load_station, parse_station

    text = (repo / "configs" / "unb-lea.toml").read_text()
    p = tmp_path / "station.toml"
    p.write_text(text + '\n[station.metadata]\ninstitution = "UnB"\nsite = "LEA roof"\n')
    st = load_station(p)
    assert st.metadata == {"institution": "UnB", "site": "LEA roof"}
    assert parse_station(tomllib.loads(st.to_toml())).metadata == st.metadata  # what a recording stores
    p.write_text(text + '\n[station.metadata]\ninstitute = "UnB"\n')
    with pytest.raises(ConfigError, match="station.metadata.institute: unknown key"):
        load_station(p)
    p.write_text(text + '\n[station.metadata]\nsite = 3\n')
    with pytest.raises(ConfigError, match="station.metadata.site: expected a string"):
        load_station(p)


@pytest.mark.slow
def test_shadow_map_through_the_whole_pipeline(unb_station):
    """End to end: simulated frames → Pipeline (segmentation, matching, heights, layers) →
    the export's ground labels → shadow map, against probe cameras on the ground."""
    from cbh.actions.export import pair_ground
    from cbh.geometry import ground
    from cbh.pipeline import Pipeline
    from cbh.pipeline.config import PipelineConfig

    sim, scene, probes = _probe_sim(unb_station, tuple(unb_station.cameras), 640)
    t = scene.time_utc
    st = replace(sim.station, cameras={k: sim.station.cameras[k] for k in ("cam1", "cam2")})
    f1, f2 = sim.frame("cam1", t), sim.frame("cam2", t)
    cfg = PipelineConfig()
    res = Pipeline(st, config=cfg).process(f1.image, f2.image, t, channels="bgr")
    assert len(res.layers) == 2
    pg = pair_ground(st, cfg.masks, res)
    grid = ground.GroundGrid(25.0, 2500.0, unb_station.latitude_deg, unb_station.longitude_deg)
    shadow = ground.shadow_map(pg.camera, pg.labels, pg.heights, pg.sun_dir, grid)
    truth = _truth_shaded(sim, probes, pg.sun_dir, t)
    v = np.array([shadow[grid.index(x, y)] for _, x, y in probes])
    known = np.isfinite(v)
    agree = float(np.mean(v[known] == truth[known]))
    # Segmentation errors at cloud edges and the working size add to the geometric edge
    # mismatch of the test above (0.97 in this sky); measured 0.89 of the 73 % of probes known (640 px).
    print(f"end-to-end shadow agreement {agree:.3f} over {known.mean():.2f} of the probes")
    assert known.mean() >= 0.5 and agree >= 0.85, (agree, known.mean())


@pytest.mark.slow
def test_sun_blocked_now_comes_from_the_previous_pair_when_the_sun_disk_is_masked(probe_world):
    """The sun disk is masked (8°), so the pair itself cannot tell whether the sun is behind
    cloud right at the station; earlier pairs advected by the layers' motion can, once the
    cloud has moved a disk radius (~230 m at 1200 m, ~670 m at 3500 m: 40-80 s with this
    wind). Pairs every 30 s; checked at every probe point against the simulator's truth."""
    from cbh.actions.export import PairGround, _sun_blocked
    from cbh.geometry import ground
    from cbh.geometry.sun import sun_position

    sim, scene, probes = probe_world
    st = sim.station
    t = scene.time_utc + timedelta(seconds=90)
    winds = [tuple(l.wind_ms) for l in scene.layers]

    def pair(tt):
        cam, labels, heights, sun = _labels(sim, scene, tt, sun_disk=True)
        zen = sun_position(st.latitude_deg, st.longitude_deg, st.altitude_m, tt).zenith_deg
        return PairGround(cam, labels, heights, [0.3, 0.1], winds, sun, zen, 0.4, tt, True)

    now = pair(t)
    history = [pair(t - timedelta(seconds=s)) for s in (30, 60, 90)]  # most recent first
    truth = _truth_shaded(sim, probes, now.sun_dir, t)
    alone = np.array([ground.sun_blocked(now.camera, now.labels, now.heights, now.motions, now.sun_dir, 0.0,
                                         at_m=(x, y)) for _, x, y in probes])
    both = np.array([_sun_blocked(st, now, history, at_m=(x, y))[0] for _, x, y in probes])
    station = [k for k, (_, x, y) in enumerate(probes) if x == 0 and y == 0][0]
    assert np.isnan(alone[station]) and np.isfinite(both[station])  # the sun disk hides it; the past tells
    filled = np.isnan(alone) & np.isfinite(both)
    known = np.isfinite(both)
    agree = float(np.mean(both[known] == truth[known]))
    # Measured: 12 probes filled from the past, 0.92 of them right; all known probes 0.81 (the
    # pair's own answers agree 0.78 in this sky, see the shadow-map test).
    assert filled.sum() >= 3 and agree >= 0.75, (filled.sum(), agree)
    assert np.mean(both[filled] == truth[filled]) >= 0.75
