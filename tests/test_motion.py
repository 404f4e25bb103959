"""Cloud motion per layer and camera 2's clock offset (cbh/pipeline/motion.py).

Simulated sequences at 640 px (working size = full size, 204 px per radian near the zenith,
50 m east-west baseline), two layers moving differently: 1200 m at (6, 2) m/s and 3500 m at
(−3, 8) m/s, frames 10 s apart.

Tolerances from the physics:
- Over 10 s the low layer moves 63 m = 0.053 rad = 11 px, the high one 85 m = 0.024 rad = 5 px.
  LK tracks are good to ≈ 0.1 px, i.e. 1–2 % per track; the layer's median over ≥ 100 tracks
  is good to ≈ 0.2 %. A track's ground speed is height × angular rate, so the speed carries
  the layer's height error: ≤ 1 % for 1200 m, ≤ 2 % for 3500 m (2.9 px of parallax, of which
  2 % is 0.06 px). Bands: speed within 5 % (the issue's target), direction within 3° (a 0.1 px
  bias across a 5 px displacement is 1.1°).
- Clock offset: one match measures δ through the parallax across the baseline, cross(B, c),
  divided by the motion across it, cross(B, w) ≈ 50 m × 0.0017–0.0023 /s ≈ 0.1 m/s. A
  systematic 0.02 px of cross-baseline stereo error (1e-4 rad: LK's sub-pixel bias) is
  0.005 m / 0.1 m/s = 0.05 s. Band for agreeing clocks: |offset| ≤ 0.15 s; for a 3 s offset,
  the issue's 0.2 s.
"""
from __future__ import annotations

import math
from datetime import timedelta

import numpy as np
import pytest

SIZE = 640
CADENCE_S = 10.0
WINDS = {1200.0: (6.0, 2.0), 3500.0: (-3.0, 8.0)}


def _sim(offset_s: float = 0.0, size: int = SIZE):
    from cbh.geometry.station import load_station
    from cbh.presets import scene_path, station_path
    from cbh.sim import SkySimulator, load_scene
    from cbh.sim.scene import with_clock_offsets

    sc = load_scene(scene_path("two-layers"))
    assert {l.height_m: tuple(l.wind_ms) for l in sc.layers} == WINDS
    if offset_s:
        sc = with_clock_offsets(sc, [f"cam2={offset_s}"])
    return SkySimulator(load_station(station_path()), sc, size_px=size), sc


def _run(sim, sc, n: int):
    from cbh.pipeline import Pipeline

    pipe = Pipeline(sim.station)
    state, out = None, []
    for i in range(n):
        shot = sim.render(sc.time_utc + timedelta(seconds=CADENCE_S * i))
        r = pipe.process(shot.views["cam1"].image, shot.views["cam2"].image, shot.time_utc, channels="bgr", previous=state)
        state = r.state
        out.append(r)
    return out


@pytest.fixture(scope="module")
def synced():
    sim, sc = _sim()
    return _run(sim, sc, 3)


def _layer_for(result, height_m):
    ls = [l for l in result.layers if abs(math.log(l.height_m / height_m)) < 0.1]
    assert len(ls) == 1, [l.height_m for l in result.layers]
    return ls[0]


def _check_motion(layer, wind, speed_tol=0.05, dir_tol_deg=3.0):
    e, n = layer.motion_east_ms, layer.motion_north_ms
    speed, true_speed = math.hypot(e, n), math.hypot(*wind)
    assert abs(speed / true_speed - 1) <= speed_tol, (e, n, wind)
    ang = math.degrees(math.atan2(e, n) - math.atan2(wind[0], wind[1]))
    assert abs((ang + 180) % 360 - 180) <= dir_tol_deg, (e, n, wind)
    # the spread is the scatter of single tracks: positive, and well below the speed itself
    assert 0 < layer.motion_spread_ms < 0.5 * true_speed
    assert layer.motion_tracks >= 50


def test_first_pair_has_no_motion_and_no_offset(synced):
    first = synced[0]
    assert len(first.layers) == 2
    for l in first.layers:
        assert math.isnan(l.motion_east_ms) and math.isnan(l.motion_north_ms) and l.motion_tracks == 0
    assert math.isnan(first.diagnostics["clock_offset_s"]) and math.isnan(first.diagnostics["motion_dt_s"])
    assert first.state is not None and first.state.gray is not None


def test_two_layers_moving_differently_speed_direction_height(synced):
    for r in synced[1:]:
        assert r.diagnostics["motion_dt_s"] == CADENCE_S
        for h, wind in WINDS.items():
            L = _layer_for(r, h)
            # heights: 1 % for the low layer; 2 % for 3500 m at 640 px (see the module docstring)
            assert abs(L.height_m / h - 1) <= (0.01 if h < 2000 else 0.02), L.height_m
            _check_motion(L, wind)
        d = r.layers[0].to_dict()
        assert d["motion_east_ms"] is not None and d["motion_tracks"] > 0


def test_agreeing_clocks_give_zero_offset_and_no_flag(synced):
    for r in synced[1:]:
        assert abs(r.diagnostics["clock_offset_s"]) <= 0.15, r.diagnostics
        assert "clock_offset" not in r.flags


def test_identical_consecutive_frames_give_exactly_zero_motion():
    """A frozen sky (the same frames again, 10 s later): every track has zero displacement, so
    each layer's motion is exactly 0 m/s (not NaN: it was measured); the offset needs motion
    across the baseline, so it stays unknown (NaN)."""
    from cbh.pipeline import Pipeline

    sim, sc = _sim(size=480)
    shot = sim.render(sc.time_utc)
    pipe = Pipeline(sim.station)
    a = pipe.process(shot.views["cam1"].image, shot.views["cam2"].image, shot.time_utc, channels="bgr")
    b = pipe.process(shot.views["cam1"].image, shot.views["cam2"].image, shot.time_utc + timedelta(seconds=10),
                     channels="bgr", previous=a.state)
    assert len(b.layers) == 2
    for L in b.layers:
        assert L.motion_tracks >= 50
        assert L.motion_east_ms == 0.0 and L.motion_north_ms == 0.0 and L.motion_spread_ms == 0.0
    assert math.isnan(b.diagnostics["clock_offset_pair_s"]) and math.isnan(b.diagnostics["clock_offset_s"])


@pytest.mark.slow
def test_no_motion_across_a_gap_or_without_time():
    from cbh.pipeline import Pipeline

    sim, sc = _sim(size=320)
    s0 = sim.render(sc.time_utc)
    s1 = sim.render(sc.time_utc + timedelta(seconds=300))
    pipe = Pipeline(sim.station)
    a = pipe.process(s0.views["cam1"].image, s0.views["cam2"].image, s0.time_utc, channels="bgr")
    b = pipe.process(s1.views["cam1"].image, s1.views["cam2"].image, s1.time_utc, channels="bgr", previous=a.state)
    assert all(math.isnan(l.motion_east_ms) for l in b.layers)  # 300 s > max_gap_s (200 s)
    c = pipe.process(s1.views["cam1"].image, s1.views["cam2"].image, None, channels="bgr", previous=a.state)
    assert all(math.isnan(l.motion_east_ms) for l in c.layers) and "time_unknown" in c.flags


def test_offset_per_match_recovers_the_offset_from_exact_geometry():
    """Noise-free rays: a layer at 1500 m moving (5, 4) m/s, camera 2 at (50, 10, 2) m capturing
    2.5 s late. Each match's 2 × 2 solve gives back δ and the height exactly."""
    from cbh.pipeline.motion import offset_per_match

    rng = np.random.default_rng(1)
    c1, c2 = np.zeros(3), np.array([50.0, 10.0, 2.0])
    z, v, delta = 1500.0, np.array([5.0, 4.0]), 2.5
    x = np.column_stack([rng.uniform(-2000, 2000, 200), rng.uniform(-2000, 2000, 200)])
    a1 = (x - c1[:2]) / (z - c1[2])
    a2 = (x + v * delta - c2[:2]) / (z - c2[2])
    w1 = np.broadcast_to(v / (z - c1[2]), a1.shape)
    d, q, wt = offset_per_match(c2[:2] - c1[:2], c2[2] - c1[2], a1, a2, w1)
    np.testing.assert_allclose(d, delta, rtol=1e-9)
    np.testing.assert_allclose(1.0 / q, z - c1[2], rtol=1e-9)
    assert (wt > 0).all()
    # a wind along the baseline leaves δ unobservable: no weight
    _, _, wt0 = offset_per_match(np.array([50.0, 0.0]), 0.0, a1, a1, np.broadcast_to([0.004, 0.0], a1.shape))
    assert np.all(wt0 == 0)


def test_motion_chain_drops_frames_after_a_gap_or_a_failure():
    from datetime import datetime, timezone

    from cbh.actions.run import MotionChain
    from cbh.pipeline.motion import PairState
    from cbh.result import PairResult

    t0 = datetime(2024, 6, 21, 14, tzinfo=timezone.utc)
    g = (np.zeros((4, 4), np.uint8),) * 2

    def res(t, offsets=(3.0,)):
        r = PairResult(t, ("cam1", "cam2"), [], None, None, None, {}, {})
        r.state = PairState(t, ("cam1", "cam2"), g, offsets)
        return r

    chain = MotionChain(cadence_s=0.0)
    first = chain.previous(t0)  # a run's first pair: a run is under way, nothing known yet
    assert first.gray is None and first.offsets_s == () and first.time_utc is None
    for k in range(4):
        chain.keep(res(t0 + timedelta(seconds=10 * k)))
    t = t0 + timedelta(seconds=30)
    assert chain.previous(t + timedelta(seconds=10)).gray is not None  # the next frame
    hole = chain.previous(t + timedelta(seconds=40))  # three frames missing
    assert hole.gray is None and hole.clock_offset_s == 3.0  # the offset history survives
    chain.lost()
    assert chain.state.gray is None and chain.state.offsets_s == (3.0,)


@pytest.fixture(scope="module")
def offset3():
    sim, sc = _sim(3.0)
    return _run(sim, sc, 4)


def _check_offset_run(results, high_layer_tol):
    assert math.isnan(results[0].diagnostics["clock_offset_s"])
    for r in results[1:]:
        assert abs(r.diagnostics["clock_offset_s"] - 3.0) <= 0.2, r.diagnostics
        assert "clock_offset" in r.flags
        for h, wind in WINDS.items():
            L = _layer_for(r, h)
            assert abs(L.height_m / h - 1) <= (0.02 if h < 2000 else high_layer_tol), [l.height_m for l in r.layers]
            _check_motion(L, wind)


def test_camera2_three_seconds_late_offset_found_and_compensated(offset3):
    """Camera 2 captures 3 s late: its view is shifted by wind × 3 s (19–26 m against a 50 m
    baseline), which without compensation merges both layers into one at ≈ 2000 m (checked on
    the first pair, which has no motion yet). From the second pair on the offset is found
    (within 0.2 s), flagged (> the 0.5 s pairing tolerance) and compensated.

    Bands at 640 px: the low layer within 2 % (the issue's target). The high layer: the
    compensation moves its camera-2 pixels by w·δ ≈ 0.0024/s × 3 s × 204 px = 1.5 px, against
    a parallax of only 2.9 px; a 10 % error of that move (bilinear resampling, the band the low
    layer uncovers in 3 s) is 0.15 px = 5 % of the parallax: band 5 % here, 2 % at 960 px
    (``test_offset_target_at_960_px``)."""
    first = offset3[0]
    assert not any(abs(l.height_m / 3500 - 1) <= 0.05 for l in first.layers)  # the fault is real
    _check_offset_run(offset3, 0.05)


@pytest.mark.slow
def test_offset_target_at_960_px():
    """The issue's target at the working size of the 1920 px cameras: offset within 0.2 s, both
    layers within 2 % from the second pair of the run on."""
    sim, sc = _sim(3.0, size=960)
    _check_offset_run(_run(sim, sc, 4), 0.02)


@pytest.fixture(scope="module")
def sequence_dir(tmp_path_factory):
    """`cbh simulate` folder: 3 frames 10 s apart at 480 px (what a directory source reads)."""
    from cbh.cli.main import main

    out = tmp_path_factory.mktemp("seq")
    rc = main(["simulate", "--scene", "two-layers", "--out", str(out), "--frames", "3", "--cadence-s", "10",
               "--size", "480"])
    assert rc == 0
    return out


def test_simulate_clock_offset_option_shifts_camera2_only(tmp_path):
    from cbh.cli.main import main
    from cbh.imageio import read_image

    a, b = tmp_path / "a", tmp_path / "b"
    for out, extra in ((a, []), (b, ["--clock-offset", "cam2=3"])):
        assert main(["simulate", "--out", str(out), "--size", "320", *extra]) == 0
    n1 = sorted((a / "cam1").iterdir())[0].name
    n2 = sorted((a / "cam2").iterdir())[0].name
    assert (b / "cam2" / n2).exists()  # stamped with the nominal time

    def im(p):
        return read_image(p)[0].astype(np.int16)

    assert np.abs(im(a / "cam1" / n1) - im(b / "cam1" / n1)).mean() < 2.0  # sensor noise only
    assert np.abs(im(a / "cam2" / n2) - im(b / "cam2" / n2)).mean() > 4.0  # clouds moved by 3 s of wind
    assert main(["simulate", "--out", str(tmp_path / "c"), "--clock-offset", "cam2"]) == 2


@pytest.mark.slow
def test_cbh_pair_with_previous_prints_motion(sequence_dir, capsys):
    from cbh.cli.main import main

    c1 = sorted((sequence_dir / "cam1").iterdir())
    c2 = sorted((sequence_dir / "cam2").iterdir())
    st = str(sequence_dir / "station.toml")
    rc = main(["pair", str(c1[1]), str(c2[1]), "--station", st, "--previous", str(c1[0]), str(c2[0]), "--json"])
    out = capsys.readouterr().out
    assert rc == 0
    import json

    s = json.loads(out)
    assert s["diagnostics"]["motion_dt_s"] == 10.0
    low = min(s["layers"], key=lambda l: l["height_m"])
    # 480 px: 153 px/rad, the low layer moves 8 px in 10 s; speed within 5 % (module docstring)
    assert abs(math.hypot(low["motion_east_ms"], low["motion_north_ms"]) / math.hypot(6, 2) - 1) <= 0.05
    rc = main(["pair", str(c1[1]), str(c2[1]), "--station", st, "--previous", str(c1[0]), str(c2[0])])
    out = capsys.readouterr().out
    assert rc == 0 and "east_ms" in out and "motion over 10 s" in out
    # without --previous the table has no motion columns (and no motion)
    rc = main(["pair", str(c1[1]), str(c2[1]), "--station", st, "--json"])
    assert rc == 0 and json.loads(capsys.readouterr().out)["layers"][0]["motion_east_ms"] is None
    rc = main(["pair", str(c1[1]), str(c2[1]), "--station", st, "--previous-time", "2024-06-21T14:00:00Z"])
    assert rc == 2 and "--previous-time needs --previous" in capsys.readouterr().err
    rc = main(["pair", str(c1[0]), str(c2[0]), "--station", st, "--previous", str(c1[1]), str(c2[1])])
    assert rc == 2 and "must be captured before" in capsys.readouterr().err


@pytest.mark.slow  # (the suite's time: 4.1 s; the same run through the CLI with the motion in its CSV runs by default below)
def test_run_on_directories_gives_motion_from_the_second_pair(sequence_dir):
    """`cbh run --source cam1=DIR --source cam2=DIR --cadence-s 0`: the service's results carry
    each layer's motion from the second pair on (the export writes what the results carry)."""
    from cbh.actions.run import build_run
    from cbh.live.service import MemorySink

    setup = build_run(station=str(sequence_dir / "station.toml"), cadence_s=0,
                      sources=[f"cam1={sequence_dir / 'cam1'}", f"cam2={sequence_dir / 'cam2'}"])
    sink = MemorySink()
    svc = setup.service()
    svc.sinks.append(sink)
    svc.run(handle_signals=False)
    results = [r for _, r in sink.items]
    assert len(results) == 3
    assert all(math.isnan(l.motion_east_ms) for l in results[0].layers)
    for r in results[1:]:
        low = min(r.layers, key=lambda l: l.height_m)
        assert abs(math.hypot(low.motion_east_ms, low.motion_north_ms) / math.hypot(6, 2) - 1) <= 0.05
        assert abs(r.diagnostics["clock_offset_s"]) <= 0.3  # 480 px: 0.15 s band × 640/480, rounded up
        assert "clock_offset" not in r.flags


def test_run_flags_offsets_above_its_pairing_tolerance(sequence_dir):
    from cbh.actions.run import build_run

    srcs = [f"cam1={sequence_dir / 'cam1'}", f"cam2={sequence_dir / 'cam2'}"]
    for tol in (0.5, 5.0):
        setup = build_run(station=str(sequence_dir / "station.toml"), sources=srcs, pair_tolerance_s=tol)
        try:
            assert setup.pipeline.config.motion.offset_tolerance_s == tol
        finally:
            for s in setup.sources:
                s.close()


@pytest.mark.slow
def test_wind_along_the_baseline_leaves_the_offset_unknown():
    """Both layers drifting east, along the 50 m east-west baseline: a clock offset would only
    scale the parallax along the baseline (indistinguishable from a height change), so the
    offset is reported unknown (NaN), never a confident number; the motion is still measured."""
    from dataclasses import replace as dc_replace

    from cbh.pipeline import Pipeline

    sim, sc = _sim(size=480)
    c1, c2 = sim.station.pair(None)
    assert abs(c2.position_m[1] - c1.position_m[1]) < 1e-6  # the baseline is east-west
    sc = dc_replace(sc, layers=tuple(dc_replace(l, wind_ms=(w, 0.0)) for l, w in zip(sc.layers, (6.0, -8.0))))
    from cbh.sim import SkySimulator

    sim = SkySimulator(sim.station, sc)
    pipe = Pipeline(sim.station)
    state = None
    for i in range(2):
        shot = sim.render(sc.time_utc + timedelta(seconds=CADENCE_S * i))
        r = pipe.process(shot.views["cam1"].image, shot.views["cam2"].image, shot.time_utc, channels="bgr",
                         previous=state)
        state = r.state
    assert math.isnan(r.diagnostics["clock_offset_s"]) and "clock_offset" not in r.flags
    low = min(r.layers, key=lambda l: l.height_m)
    assert abs(low.motion_east_ms / 6.0 - 1) <= 0.05 and abs(low.motion_north_ms) <= 0.05 * 6.0


@pytest.mark.parametrize("table, key", [({"window_px": 4}, "window_px"), ({"max_gap_s": -1}, "max_gap_s"),
                                        ({"nope": 1}, "nope"), ({"clock_offset": "yes"}, "clock_offset")])
def test_motion_config_errors_name_the_key(table, key):
    from cbh.errors import ConfigError
    from cbh.pipeline import PipelineConfig

    with pytest.raises(ConfigError, match=f"pipeline.motion.{key}"):
        PipelineConfig.from_dict({"motion": table})
    cfg = PipelineConfig.from_dict({"motion": {"max_gap_s": 60, "clock_offset": False}})
    assert PipelineConfig.from_dict(cfg.to_dict()) == cfg and cfg.motion.max_gap_s == 60.0


def test_run_export_csv_carries_height_and_motion(sequence_dir, tmp_path):
    """The issue's command: `cbh run --source cam1=DIR --source cam2=DIR --cadence-s 0 --export
    layers.csv`; the CSV has `cloud_base_height_m`, `motion_east_ms`, `motion_north_ms`, empty
    motion on the first pair and the layers' motion from the second pair on."""
    import pandas as pd

    from cbh.cli.main import main

    csv = tmp_path / "layers.csv"
    rc = main(["run", "--station", str(sequence_dir / "station.toml"), "--source", f"cam1={sequence_dir / 'cam1'}",
               "--source", f"cam2={sequence_dir / 'cam2'}", "--cadence-s", "0", "--export", str(csv)])
    assert rc == 0
    df = pd.read_csv(csv)
    for col in ("cloud_base_height_m", "motion_east_ms", "motion_north_ms"):
        assert col in df.columns, col
    times = sorted(df["time_utc"].unique())
    assert len(times) == 3
    first = df[df["time_utc"] == times[0]]
    assert first["motion_east_ms"].isna().all()
    for t in times[1:]:
        rows = df[(df["time_utc"] == t) & (df["layer"] >= 1)]
        low = rows.loc[rows["cloud_base_height_m"].idxmin()]
        high = rows.loc[rows["cloud_base_height_m"].idxmax()]
        # truth (two-layers scene): 1200 m at (6, 2) m/s, 3500 m at (-3, 8) m/s. 480 px: heights
        # within 2 % (parallax ≈ 306 px·B/h/2 at this size), speeds within 5 % (module docstring)
        assert abs(low["cloud_base_height_m"] / 1200 - 1) <= 0.02
        assert abs(high["cloud_base_height_m"] / 3500 - 1) <= 0.02
        assert abs(math.hypot(low["motion_east_ms"], low["motion_north_ms"]) / math.hypot(6, 2) - 1) <= 0.05
        bearing = math.degrees(math.atan2(low["motion_east_ms"], low["motion_north_ms"]))
        assert abs(bearing - math.degrees(math.atan2(6, 2))) <= 3.0


def _wrong_motion(results, tol=0.05, dir_tol_deg=3.0):
    """(time, layer height, motion) of every layer whose motion is reported but off the truth."""
    bad = []
    for r in results:
        for layer in r.layers:
            wind = WINDS[min(WINDS, key=lambda h: abs(math.log(layer.height_m / h)))]
            e, n = layer.motion_east_ms, layer.motion_north_ms
            if not math.isfinite(e):
                continue
            ang = math.degrees(math.atan2(e, n) - math.atan2(wind[0], wind[1]))
            if abs(math.hypot(e, n) / math.hypot(*wind) - 1) > tol or abs((ang + 180) % 360 - 180) > dir_tol_deg:
                bad.append((r.time_utc, round(layer.height_m), (round(e, 2), round(n, 2))))
    return bad


@pytest.mark.slow  # (5 s; motion at the default cadence is tested by default above)
@pytest.mark.parametrize("start_s", [0, 360])
def test_a_60_s_cadence_gives_no_wrong_motion(start_s):
    """At a 60 s cadence the 1200 m layer moves ≈ 95 px between frames at 960 px. Tracks of the
    3500 m deck that jumped onto it (the deck hidden by the moving low cloud), or whose window
    straddled its edge, gave the deck (+18, +5) m/s (the low layer's rate × 2.9) instead of
    (−3, 8), in 4 of 7 pairs. Now a track must still form a stereo pair of its height in the
    previous frames and see no lower cloud in its window: the deck's motion is right or NaN."""
    from cbh.pipeline import Pipeline

    sim, sc = _sim(size=960)
    pipe = Pipeline(sim.station)
    out = []
    for t in (start_s, start_s + 60):
        shot = sim.render(sc.time_utc + timedelta(seconds=t))
        out.append(pipe.process(shot.views["cam1"].image, shot.views["cam2"].image, shot.time_utc, channels="bgr",
                                previous=out[-1].state if out else None))
    assert not _wrong_motion(out), _wrong_motion(out)
    low = _layer_for(out[1], 1200.0)  # the low layer is measured (right, by the line above)
    assert math.isfinite(low.motion_east_ms) and low.motion_tracks >= 20


@pytest.mark.slow
def test_a_60_s_sequence_gives_no_wrong_motion():
    from cbh.pipeline import Pipeline

    sim, sc = _sim(size=960)
    pipe = Pipeline(sim.station)
    out, state = [], None
    for k in range(8):
        shot = sim.render(sc.time_utc + timedelta(seconds=60 * k))
        r = pipe.process(shot.views["cam1"].image, shot.views["cam2"].image, shot.time_utc, channels="bgr", previous=state)
        state = r.state
        out.append(r)
    assert not _wrong_motion(out), _wrong_motion(out)
    assert all(math.isfinite(_layer_for(r, 1200.0).motion_east_ms) for r in out[1:])


def test_tracks_at_a_lower_layers_rate_are_not_the_upper_layers_motion():
    """layer_motion, synthetic: the 3500 m layer's tracks are 40 % its own (−3, 8) m/s and 60 %
    dragged by the 1200 m layer (its angular rate: (6, 2) m/s at 1200 m). A median would give
    the dragged rate × 2.9; the dragged tracks are dropped, the true motion stays. Still layers
    (both rates 0, e.g. the same frame twice) drag nothing: every track counts."""
    from cbh.pipeline.motion import layer_motion
    from cbh.result import Layer

    rng = np.random.default_rng(0)
    layers = [Layer(3500.0, 3500.0, 30.0, 0.2, 500, 0.9), Layer(1200.0, 1200.0, 10.0, 0.3, 900, 0.9)]  # any order
    r_low, r_up = np.array([6.0, 2.0]) / 1200.0, np.array([-3.0, 8.0]) / 3500.0
    noise = lambda n: 1e-5 * rng.standard_normal((n, 2))  # noqa: E731 (≈ 1 % of the rates)
    w = np.concatenate([r_low + noise(80), r_up + noise(40), r_low + noise(60)])
    lab = np.array([1] * 80 + [0] * 100)  # the last 60 "3500 m" tracks move at the low rate
    out = layer_motion(layers, [(w, lab, 0.0)], min_tracks=10)
    assert [L.height_m for L in out] == [3500.0, 1200.0]  # order kept
    up, low = out
    assert (low.motion_east_ms, low.motion_north_ms) == pytest.approx((6.0, 2.0), abs=0.1)
    assert (up.motion_east_ms, up.motion_north_ms) == pytest.approx((-3.0, 8.0), abs=0.2)
    assert up.motion_tracks == 40
    still = layer_motion(layers, [(np.zeros((180, 2)), lab, 0.0)], min_tracks=10)
    assert [L.motion_tracks for L in still] == [100, 80] and still[0].motion_east_ms == 0.0


@pytest.mark.parametrize("noise", [0.02, 0.06])
def test_a_noisy_single_layer_keeps_its_tracks(noise):
    """stage_motion's window test drops a track only for a *lower layer* in its window: a single
    layer whose height map is noisy (the minimum of 225 noisy pixels lies well below the layer)
    keeps its tracks (at 6 % noise it kept none before: motion NaN)."""
    from cbh.geometry.station import load_station
    from cbh.pipeline import Pipeline
    from cbh.pipeline.heightmap import HeightMap
    from cbh.pipeline.layers import LayerSet
    from cbh.pipeline.run import MotionEstimate
    from cbh.presets import station_path
    from cbh.result import Histogram, Layer

    pipe = Pipeline(load_station(station_path()).scaled(320))
    h, w = pipe.cam1.model.height, pipe.cam1.model.width
    rng = np.random.default_rng(1)
    hm = (3000.0 * (1.0 + noise * rng.standard_normal((h, w)))).astype(np.float32)
    n = 400
    px1 = np.stack([rng.uniform(40, w - 40, n), rng.uniform(40, h - 40, n)], axis=1)
    rate = np.tile(np.array([[-3.0, 8.0]]) / 3000.0, (n, 1))
    est = MotionEstimate(dt_s=10.0, px1=px1, w1=rate.copy(), w2=rate.copy(),
                         height_m=3000.0 * (1.0 + noise * rng.standard_normal(n)))
    layer = Layer(3000.0, 3000.0, 3000.0 * noise, 0.5, 5000, 0.9)
    lay = LayerSet([layer], Histogram(np.zeros(2), np.zeros(1)), np.zeros(0, np.int16), False)
    out = pipe.stage_motion(lay, HeightMap(hm, hm, (w, h)), est, np.ones((h, w), bool))
    assert out.layers[0].motion_tracks >= 0.9 * 2 * n
    assert (out.layers[0].motion_east_ms, out.layers[0].motion_north_ms) == pytest.approx((-3.0, 8.0), rel=1e-6)


def test_parallax_heights_for_a_known_offset_from_exact_geometry():
    """The same noise-free geometry as above: with δ known, the least-squares q of
    ``q·B' = a1 − a2 + δ·w1`` is the height exactly and nothing is left across the baseline;
    with δ taken as 0 the cloud's move v·δ = (12.5, 10) m is left: its component across the
    50 m east baseline, 10 m at 1500 m (6.7e-3 in plane offsets, i.e. rays that miss by 0.67 %
    of the range), as the miss."""
    from cbh.pipeline.motion import parallax_heights

    rng = np.random.default_rng(1)
    c1, c2 = np.zeros(3), np.array([50.0, 0.0, 2.0])
    z, v, delta = 1500.0, np.array([5.0, 4.0]), 2.5
    x = np.column_stack([rng.uniform(-2000, 2000, 200), rng.uniform(-2000, 2000, 200)])
    a1 = (x - c1[:2]) / (z - c1[2])
    a2 = (x + v * delta - c2[:2]) / (z - c2[2])
    w1 = np.broadcast_to(v / (z - c1[2]), a1.shape)
    q, miss = parallax_heights(c2[:2] - c1[:2], c2[2] - c1[2], a1, a2, w1, delta)
    np.testing.assert_allclose(1.0 / q, z - c1[2], rtol=1e-9)
    np.testing.assert_allclose(miss, 0.0, atol=1e-12)
    _, miss0 = parallax_heights(np.array([50.0, 0.0]), 0.0, a1, (x + v * delta - c2[:2]) / z, w1, 0.0)
    np.testing.assert_allclose(np.abs(miss0), v[1] * delta / z, rtol=1e-9)


def test_track_profile_finds_each_layers_rate():
    """Tracks of two layers, 1000 m (4 % height noise) and 4000 m (10 %: 2 px of parallax), each
    with its own rate: two nodes at the layers' median heights with their median rates; a
    cluster smaller than min_tracks (a few stray tracks at 2000 m) gives none; too few tracks in
    all: an empty profile."""
    from cbh.pipeline.motion import track_profile

    rng = np.random.default_rng(3)
    r_low, r_high = np.array([2.0, 1.0]) / 1000.0, np.array([-6.0, 18.0]) / 4000.0
    h = np.concatenate([1000 * (1 + 0.04 * rng.standard_normal(150)), 4000 * (1 + 0.10 * rng.standard_normal(120)),
                        np.full(5, 2000.0)])
    rates = np.concatenate([np.tile(r_low, (150, 1)), np.tile(r_high, (120, 1)), np.tile([0.01, 0.0], (5, 1))])
    rates = rates + 2e-5 * rng.standard_normal(rates.shape)
    p = track_profile(h, rates, min_tracks=10, tolerance_log=0.1)
    assert len(p) == 2
    assert p.heights_m == pytest.approx([1000.0, 4000.0], rel=0.03)
    np.testing.assert_allclose(p.rates, [r_low, r_high], atol=1e-5)
    np.testing.assert_array_equal(p.nearest([900.0, 1900.0, 2100.0, 9000.0]), [0, 0, 1, 1])  # nearest in ln h
    assert len(track_profile(h[:5], rates[:5], min_tracks=10, tolerance_log=0.1)) == 0


def test_offset_error_weighs_each_match_as_the_estimate_does():
    """offset_estimate's standard error is the weighted MAD over the effective number of matches.
    70 matches of a slow layer (little motion across the baseline: each good to ±5 s) and 45 of
    a fast one (±0.05 s; weight 25 ×, capped at 2 × the median): the unweighted MAD over √n is
    0.12–0.16 s and refused δ (NaN), although the fast layer alone measures it to 0.01 s; now
    it is found within 0.05 s (the weighted median of the fast matches' ±0.05 s, pulled a little
    by the slow ones). 40 matches all at ±1.5 s (standard error 0.24 s) stay unknown."""
    from cbh.pipeline.motion import offset_estimate

    for seed in range(3):
        rng = np.random.default_rng(seed)
        d = np.concatenate([3.0 + 5.0 * rng.standard_normal(70), 3.0 + 0.05 * rng.standard_normal(45)])
        wt = np.concatenate([np.full(70, 1e-6), np.full(45, 25e-6)])
        est = offset_estimate(d, np.full(len(d), 1 / 2000.0), wt, 100.0, 15000.0, 30.0, 30.0)
        assert abs(est - 3.0) <= 0.05, (seed, est)
    d = 3.0 + 1.5 * np.random.default_rng(9).standard_normal(40)
    assert math.isnan(offset_estimate(d, np.full(40, 1 / 2000.0), np.full(40, 1e-6), 100.0, 15000.0, 30.0, 30.0))


def test_track_test_keeps_a_layer_that_moved_across_the_baseline():
    """Pipeline._jumped compares each track's parallax a1 − a2 between the frames: a layer 3 s
    late in camera 2 and moving 19 m/s across the baseline keeps its (offset-shifted) parallax
    and stays, though its rays miss by 1.4 % of the range and no longer triangulate; a track
    whose parallax changed by a fifth (it jumped to another cloud; the tolerance: 10 % of |c|, or
    3√2 × 0.1 px of LK noise, 0.0014 × 1/cos²θ at 960 px, against |c| = 0.022) goes."""
    from cbh.geometry.station import load_station
    from cbh.pipeline import Pipeline
    from cbh.presets import station_path

    pipe = Pipeline(load_station(station_path()).scaled(960))  # 306 px/rad: LK noise 3e-4, below a fifth of c
    rng = np.random.default_rng(2)
    z, v, delta, dt = 4000.0, np.array([-6.0, 18.0]), 3.0, 10.0
    x = np.column_stack([rng.uniform(-3000, 3000, 100), rng.uniform(-3000, 3000, 100)])
    b = np.array([50.0, 0.0])

    def offsets(xy):
        return xy / z, (xy + v * delta - b) / z

    a1, a2 = offsets(x)
    a1p, a2p = offsets(x - v * dt)
    assert not pipe._jumped(a1, a2, a1p, a2p).any()
    c = a1 - a2
    assert pipe._jumped(a1, a1 - 1.2 * c, a1p, a2p).all()


def test_a_resumed_clock_is_used_only_near_its_time():
    """`cbh run` resumes a recorded clock offset (PairState.resumed): on a first pair within a day of
    its last estimate, either way in time (an archive, a simulated run may start before it); a
    day beyond, a camera without NTP has drifted: not used, and the run starts afresh."""
    from datetime import datetime, timedelta, timezone

    from cbh.actions.run import MotionChain
    from cbh.pipeline.motion import PairState

    t0 = datetime(2016, 9, 1, 9, 30, tzinfo=timezone.utc)
    for dt_h, kept in ((-1.0, True), (3.0, True), (49.0, False)):
        chain = MotionChain(start=PairState.resumed(("fe3", "fe4"), (-31.0, -30.5), t0))
        s = chain.previous(t0 + timedelta(hours=dt_h))
        assert (s.offsets_s == (-31.0, -30.5)) is kept and (s.cameras == ("fe3", "fe4")) is kept
        assert s.time_utc is None and s.gray is None
