"""The real Fehmarn station (issue 32): two VIVOTEK IP cameras 241 m apart whose clocks disagree by
about half a minute (../shared/data/fehmarn-2016-09-01). No ground truth for the offset: what a user
checks on such a station is tested: the offset found from the second pair and stable, the same
images re-paired one frame apart giving the offset 60 s further (the re-pairing adds exactly the
cadence of the stamps), the first pair's disagreement not blamed on the geometry, and the high deck
of the reference found once the offset is out.
"""
from __future__ import annotations

import math
import statistics
import sys
from pathlib import Path

import numpy as np
import pytest

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "fehmarn-2016-09-01"
pytestmark = pytest.mark.skipif(not DATA.is_dir(), reason="needs ../shared/data/fehmarn-2016-09-01")
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))


@pytest.fixture(scope="module")
def station():
    from cbh.geometry.station import load_station

    return load_station(DATA / "station.toml")


def _run(station, shift: int, n: int, start: int = 0):
    from eval_fehmarn import frames

    from cbh.pipeline import Pipeline
    from cbh.pipeline.motion import PairState

    pipe, state, out = Pipeline(station), PairState.start(), []
    for a, b, t in frames(DATA, shift)[start:start + n]:
        r = pipe.process(a, b, t, previous=state)
        state = r.state
        out.append(r)
    return out


@pytest.fixture(scope="module")
def as_recorded(station):
    return _run(station, 0, 5)


def test_file_names_stamped_in_utc_plus_one():
    from cbh.timeutil import time_from_name

    t = time_from_name("FE3_Image_20160901_100000_UTCp1.jpg")
    assert t.isoformat() == "2016-09-01T09:00:00+00:00"  # the README: 09:00:00 UTC


def test_offset_found_from_the_second_pair_and_stable(as_recorded):
    """About −30 s (camera FE4 captures half a minute before FE3's stamp): known from the second
    pair (the first motion), each pair's own estimate within 2 s of the run's (the target)."""
    r0, rest = as_recorded[0], as_recorded[1:]
    assert math.isnan(r0.diagnostics["clock_offset_s"])
    offs = [r.diagnostics["clock_offset_pair_s"] for r in rest]
    med = statistics.median(offs)
    assert -40.0 <= med <= -20.0, offs
    assert all(abs(o - med) <= 2.0 for o in offs), offs
    for r in rest:
        assert "clock_offset" in r.flags and "clock_unknown" not in r.flags


def test_first_pair_is_not_blamed_on_the_geometry(as_recorded):
    """Before any motion, a clock offset and a wrong geometry look alike: the first pair of a run
    says the clock is unknown (layers not valid), never geometry_mismatch."""
    assert "geometry_mismatch" not in as_recorded[0].flags
    assert "clock_unknown" in as_recorded[0].flags


def test_a_first_pair_without_a_verdict_is_not_trusted(station):
    """Re-paired two frames earlier (camera 2 ≈ 151 s behind), the run's first pair left LK nothing
    to judge the geometry on (0 plain, 1 seeded of several hundred), and the sweep's best planes
    along the epipolar curves put a 1.6–1.8 km deck under the real 8.4 km one, with no flag but
    ``sun_glare``. With no verdict and the clock unknown, its layers are not valid: ``clock_unknown``
    (the offset is measured from the next pair on). One-shot (no run, no clock to check) it is
    left as it was."""
    from eval_fehmarn import frames

    from cbh.pipeline import Pipeline
    from cbh.pipeline.motion import PairState

    a, b, t = frames(DATA, -2)[0]
    pipe = Pipeline(station)
    r = pipe.process(a, b, t, previous=PairState.start())
    assert any(L.height_m < 3000 for L in r.layers)  # what would otherwise be reported
    assert math.isnan(r.diagnostics["geometry_residual_px"])
    assert "clock_unknown" in r.flags and "geometry_mismatch" not in r.flags
    assert "clock_unknown" not in pipe.process(a, b, t).flags


def test_sky_maps_two_minutes_apart_find_the_offset(station):
    """The first two frames at a 2-minute cadence (09:00, 09:02): the 8 km deck moved ≈ 45 map px on
    each camera's map between them, and the maps' estimate had been NaN (the phase correlation of
    a camera's two frames took the static flare and masts for the motion, and the flow lost the
    clouds). Now the offset is measured on this very first interval, within 2 s of the half hour's
    median at the 1-minute cadence (−31.1 s; its pair-to-pair scatter there is about 1 s)."""
    from eval_fehmarn import frames

    from cbh.pipeline import Pipeline

    pipe = Pipeline(station)
    prep = [pipe.prepare(a, b, t) for a, b, t in frames(DATA, 0, 2)[:2]]
    sky = pipe.sky_offset(prep[1].gray, prep[1].masks.usable, prep[0].gray, 120.0)
    assert abs(sky.offset_s + 31.1) <= 2.0, (sky.offset_s, sky.tiles)


@pytest.mark.slow  # (the suite's time; the first interval's estimate runs by default above)
@pytest.mark.parametrize("shift, offset_s", [(0, -31.1), (1, 29.0)])
def test_at_a_two_minute_cadence_the_offset_is_found_at_once_and_the_deck_is_valid(shift, offset_s):
    """Every other frame (pairs 120 s apart, the longest gap motion is taken over), as recorded and
    re-paired one frame later. Before: the sky maps of the first pairs did not match across 120 s
    (the camera's own motion was taken for none), the offset was unknown until the fourth pair,
    and a pair's own estimate, which scatters by about 3 s at this cadence (1 s at 1 minute), was
    called a possible jump (``clock_unknown``) on a 3 s threshold: 29 % / 23 % of the pairs valid
    with a reference layer, 14 % / 15 % led by a phantom deck, one ``geometry_mismatch``. Now the
    offset is known from the second pair, within 2 s of its 1-minute median, and ≥ 75 % of the
    pairs from the third on are valid with a reference layer (measured 79 % / 77 %), none led by
    a phantom, no ``geometry_mismatch``. Since stop 72 (the sky clock's tiles read δ from their
    median flows) one pair of 14 as recorded is led by the 8 km deck read 15.1 % high (9222 m
    against 8009 m; 9187 m, 14.7 %, before): at most one, within 20 %."""
    from eval_fehmarn import evaluate

    res = evaluate(DATA, shift, verbose=False, step=2)
    sc, rows = res["score"], res["rows"]
    assert abs(rows[1]["offset_s"] - offset_s) <= 2.0, rows[1]
    assert sc["valid_with_reference_layer"] >= 0.75, sc
    phantoms = [r for r in rows[2:] if r["phantom_lead"]]
    assert len(phantoms) <= 1, phantoms
    for r in phantoms:  # the deck read a little beyond the bar, not a phantom of another height
        lead = max(r["layers"], key=lambda L: L[1])[0]
        assert min(abs(lead - h) / h for h, _ in r["ref"]) <= 0.2, r
    assert not any("geometry_mismatch" in r["flags"] for r in rows), [r["flags"] for r in rows]


def test_high_deck_found_once_the_offset_is_out(as_recorded):
    """The reference's cirrocumulus deck (8.4–9.3 km in these minutes) leads every pair after the
    first, valid, within the issue's bar of a reference layer (15 % above 5 km: the calibration's
    ±0.2° alone moves an 8 km layer by ±12 %). Before the clock was found the leading layers were
    phantoms at 1.5–2.5 km; before the sky-map matches were triangulated on their epipolar lines
    and the base was taken about the deck's trend, its base read 5.5–6.0 km."""
    from eval_fehmarn import agrees, reference_layers

    from cbh.flags import INVALIDATING

    ref = reference_layers(DATA)
    for r in as_recorded[1:]:
        lead = max(r.layers, key=lambda L: L.cover)
        assert not INVALIDATING & set(r.flags), r.flags
        assert agrees(lead.height_m, ref[r.time_utc]), ([L.height_m for L in r.layers], ref[r.time_utc])


@pytest.mark.slow
@pytest.mark.parametrize("shift", [0, 1])
def test_the_half_hour_meets_the_bar(shift):
    """The issue's targets on the whole shared half hour, as recorded and re-paired one frame
    later (≈ +29 s): from the third pair on, ≥ 90 % of the pairs valid with a layer within 10 %
    (15 % above 5 km) of the reference, ≤ 5 % led by a layer the reference does not have, the
    offset within 2 s of its median on ≥ 90 %."""
    from eval_fehmarn import evaluate

    sc = evaluate(DATA, shift, verbose=False)["score"]
    assert sc["valid_with_reference_layer"] >= 0.9, sc
    assert sc["phantom_led"] <= 0.05, sc
    assert sc["offset_within_2s_of_median"] >= 0.9, sc
    # a clock is not a geometry: re-paired one frame later, pair 22's own offset (32.3 s) left the
    # running one (29.0 s) by enough to move its carried matches 2.2 px off their curves; it was
    # flagged geometry_mismatch, now clock_unknown (Pipeline._carry_explains)
    assert sc["geometry_mismatch"] == 0, sc


@pytest.mark.slow  # (the default suite's time; the offset as recorded runs by default above)
def test_re_paired_one_frame_later_the_offset_moves_by_the_cadence(station, as_recorded):
    """FE4's next frame paired with FE3's: the same cameras, 60 s more offset. Beyond the ±30 s
    that the previous estimator allowed, and found from the second pair all the same."""
    base = statistics.median(r.diagnostics["clock_offset_pair_s"] for r in as_recorded[1:])
    shifted = _run(station, 1, 3)
    for r in shifted[1:]:
        assert abs(r.diagnostics["clock_offset_s"] - (base + 60.0)) <= 2.0, r.diagnostics["clock_offset_s"]


@pytest.mark.slow
def test_re_paired_at_minus_ninety_seconds(station, as_recorded):
    base = statistics.median(r.diagnostics["clock_offset_pair_s"] for r in as_recorded[1:])
    shifted = _run(station, -1, 4, start=1)
    for r in shifted[1:]:
        assert abs(r.diagnostics["clock_offset_s"] - (base - 60.0)) <= 2.0, r.diagnostics["clock_offset_s"]


@pytest.mark.slow
@pytest.mark.parametrize("shift, low, phantom", [(3, 0.8, 0.16), (-2, 0.7, 0.15), (4, 0.38, 0.22)])
def test_re_paired_minutes_apart_no_unflagged_phantom_decks(shift, low, phantom):
    """Re-paired 3, −2 and 4 frames (+149, −151, +210 s). Before: the estimate beyond 150 s was not
    believed (−2: never found), and a pair whose own sky-map estimate failed was matched on the raw
    images with the carry left to the compensation, which at these carries gave layers at 1.5–2.3 km
    under the 8 km deck with no flag (+3: 69 % valid, 54 % led by a phantom; −2: 30 %, 56 %, 3
    mismatches; +4: 32 %, 68 %). Now such a pair is carried on its maps by the running offset, or,
    when they do not match either, flagged ``clock_too_far`` (not valid). From the third pair no
    valid pair is led by such a low phantom deck; what the shares still count as phantoms is the
    8 km deck read 15–30 % off (+3: 81 % valid, 15 % phantom-led; −2: 67 %, 7 %; +4: 24 %, 28 %:
    at 210 s the sky itself has changed too much between the captures for most pairs). Since the
    maps take each camera's own motion out first and the jump floor is 5 % of the offset (stop 51),
    fewer pairs lose their own estimate: +3: 88 %, 12 %; −2: 81 %, 11 % (one more phantom, a pair
    carried by the running offset whose deck read 17 % high); +4: 60 %, 24 %. Stop 72 (the sky
    clock's tiles read δ from their median flows; its offsets here moved 0.1–0.4 s): +3: 85 %, 15 %
    (pair 25's deck 8099 → 8265 m against 7117 m, 13.8 → 16.1 % high); −2 as before; +4: 48 %.
    Stop 75 (the frames' timing in the carry's noise: the two cameras' intervals' ratio, 0.99–1.01
    here, times 210 s of carry): +4: 40 %, 20 %; two phantom-led pairs (9931 m for 8445, 9086 m
    for 7074) and two within 7 % of the reference (8209 m for 8761, 7590 m for 7108) are now
    ``clock_too_far``; +3 and −2 as before."""
    from eval_fehmarn import evaluate

    res = evaluate(DATA, shift, verbose=False)
    sc = res["score"]
    assert sc["valid_with_reference_layer"] >= low, sc
    assert sc["phantom_led"] <= phantom, sc
    assert sc["geometry_mismatch"] == 0, sc
    # (also the first two pairs, before the offset is known: `clock_unknown` where nothing judged them)
    low_decks = [r for r in res["rows"] if r["phantom_lead"] and max(r["layers"], key=lambda L: L[1])[0] < 3000]
    assert not low_decks, low_decks


def test_a_stated_offset_is_used_from_the_first_pair(station, tmp_path):
    """A station file that states the clocks (``clock_offset_s`` per camera): the first pair already
    reports the offset, and the estimate goes on from there. Without motion it cannot carry a
    camera yet, so its mismatch is the clock's (``clock_unknown``), never ``geometry_mismatch``;
    the second pair is valid."""
    from dataclasses import replace

    cams = dict(station.cameras)
    cams["fe4"] = replace(cams["fe4"], clock_offset_s=-30.5)
    st = replace(station, cameras=cams)
    from cbh.geometry.station import load_station

    (tmp_path / "station.toml").write_text(st.to_toml())
    again = load_station(tmp_path / "station.toml")
    assert again.cameras["fe4"].clock_offset_s == -30.5
    r, r2 = _run(again, 0, 2)
    assert r.diagnostics["clock_offset_s"] == pytest.approx(-30.5)
    assert "geometry_mismatch" not in r.flags and "clock_offset" in r.flags
    assert not {"clock_unknown", "geometry_mismatch"} & set(r2.flags), r2.flags


def test_offset_history_restarts_on_a_clock_jump():
    """A camera rebooted: two pairs agree on a new offset far from the running one; the history
    restarts from them instead of waiting for half of it to turn over."""
    from cbh.pipeline.motion import running_offset, update_offsets

    h = (-30.0, -30.4, -29.8, -30.1)
    h = update_offsets(h, 12.0, 15, 3.0)  # one wild pair: kept, the median does not move
    assert running_offset(h) == pytest.approx(-30.0, abs=0.3)
    h = update_offsets(h, 12.3, 15, 3.0)  # a second that agrees with it: the clock jumped
    assert h == (12.0, 12.3)
    assert update_offsets(h, math.nan, 15, 3.0) == h


def test_a_run_of_outliers_is_not_a_jump():
    """The real hour re-paired one frame later (+29 s): 09:22 and 09:23 read 32.5 and 35.1 s, both
    beyond the 3 s threshold and 2.6 s apart; they had restarted the history at 33.8 s (and
    09:23's deck, carried by it, read 18 % high), while the next pairs read 28.4, 26.8, 30.0 s.
    Two estimates confirm a jump when they agree to half the threshold; and at a 2-minute cadence
    the threshold's floor doubles (the estimates scatter about three times as much there), and it
    is at least 5 % of the offset."""
    from cbh.pipeline.motion import jump_floor_s, running_offset, update_offsets

    h = (28.8, 29.0, 29.0, 29.5, 28.6, 28.7, 26.9, 27.4, 27.0, 26.3, 25.7, 29.0, 29.5, 30.2, 31.1, 29.9, 29.8,
         29.5, 29.8, 29.1, 28.7)
    for new in (32.5, 35.1):
        h = update_offsets(h, new, 60, 3.0)
    assert running_offset(h) == pytest.approx(29.0, abs=0.3)
    assert (jump_floor_s(3.0, 60.0), jump_floor_s(3.0, 120.0), jump_floor_s(3.0, 10.0)) == (3.0, 6.0, 3.0)
    # and at 5 % of the offset: re-paired to −151 s the estimates drifted to −146 s with the offset fixed
    assert jump_floor_s(3.0, 60.0, -31.0) == 3.0 and jump_floor_s(3.0, 60.0, -151.0) == pytest.approx(7.55)
    h = (-152.0, -151.3, -151.1, -151.1, -150.8, -152.1, -152.1, -153.2, -154.4, -154.0, -148.4)
    for new in (-145.4, -145.4):
        h = update_offsets(h, new, 60, jump_floor_s(3.0, 60.0, running_offset(h)))
    assert running_offset(h) == pytest.approx(-151.3, abs=0.5)


def test_run_summary_names_each_cause(station):
    """The end of a run says what made pairs invalid, cause by cause: a clock not yet measured is
    not a geometry (the summary said "disagreed with the station geometry" for both)."""
    from types import SimpleNamespace

    from cbh.actions.run import summary_lines
    from cbh.live.service import ServiceStats

    st = ServiceStats(pairs_processed=31, pairs_invalid=10, invalid_counts={"clock_unknown": 1, "geometry_mismatch": 9},
                      stop_reason="sources ended")
    setup = SimpleNamespace(station=station, outputs=lambda: [])
    text = "\n".join(summary_lines(setup, st))
    assert "1 disagreed with the geometry, or had too few matches to judge it, while the cameras' clock offset was not known yet, or had layers that an offset too small for the check to see would move (clock_unknown)" in text
    assert "9 disagreed with the station geometry (geometry_mismatch)" in text


@pytest.mark.slow
def test_a_restarted_run_resumes_the_recorded_clock(tmp_path, capsys):
    """`cbh run --record DIR` on the real station, stopped after three pairs and started again on
    the next frames: the second run resumes the first one's offset from its recording (said in the
    notes), so its first pair already states it, within 2 s of the first run's. (That pair has no
    motion yet to carry a camera with: its mismatch is the clock's, ``clock_unknown``, not the
    geometry's.)"""
    from cbh.cli.main import main
    from cbh.outputs.record import open_session

    dirs = {}
    for part, idx in (("a", range(0, 3)), ("b", range(3, 5))):
        for cam in ("fe3", "fe4"):
            d = tmp_path / part / cam
            d.mkdir(parents=True)
            for f in sorted((DATA / cam).glob("*.jpg"))[idx.start:idx.stop]:
                (d / f.name).symlink_to(f)  # the shared frames themselves, never copied
            dirs[part, cam] = d
    rec = tmp_path / "rec"
    rec.mkdir()

    def run(part):
        assert main(["run", "--station", str(DATA / "station.toml"), "--source", f"fe3={dirs[part, 'fe3']}",
                     "--source", f"fe4={dirs[part, 'fe4']}", "--record", str(rec), "-q"]) == 0
        cap = capsys.readouterr()
        return cap.out + cap.err

    run("a")
    first = [p.result.diagnostics["clock_offset_s"] for p in open_session(rec).pairs(layers_only=True)]
    out = run("b")
    assert "clock offset fe4 - fe3 resumed from" in out, out
    files = sorted(rec.glob("*.mcap"), key=lambda f: f.stat().st_mtime)
    again = [p.result for p in open_session(files[-1]).pairs(layers_only=True)]
    assert math.isnan(first[0]) and math.isfinite(first[-1])
    assert abs(again[0].diagnostics["clock_offset_s"] - first[-1]) <= 2.0, (first, again[0].diagnostics)
    assert "clock_offset" in again[0].flags and "geometry_mismatch" not in again[0].flags
    assert "clock_unknown" not in again[1].flags


@pytest.mark.slow
def test_calibrate_reports_the_clock_beside_the_orientation(tmp_path):
    """`cbh calibrate --relative-only` on the half hour (the sun's track is too short for an
    absolute fit): it measures FE4's clock from the sky maps (within 2 s of the run's −31 s),
    writes it into the station (``clock_offset_s``, which a run then starts from), matches the
    clouds carried to one capture time (ORB at one stamp met behind both cameras, and the fit was
    refused as swapped cameras), and warns that the clouds alone turn FE4 by more than the
    station's calibration claims: its tilt along the baseline trades against the heights."""
    from cbh.actions.calibrate import CalibrateOptions, calibrate
    from cbh.geometry.station import load_station

    out = tmp_path / "cal.toml"
    rep = calibrate(DATA / "station.toml", {"fe3": str(DATA / "fe3"), "fe4": str(DATA / "fe4")}, out,
                    CalibrateOptions(relative_only=True))
    c = rep["cameras"]["fe4"]
    assert abs(c["clock_offset_s"] + 31.0) <= 2.0 and c["clock_offset_pairs"] >= 25, c
    assert rep["pairs"][0]["method"] == "skyflow"
    assert load_station(out).cameras["fe4"].clock_offset_s == pytest.approx(c["clock_offset_s"])
    assert any("trades against the layers' heights" in w for w in rep["warnings"]), rep["warnings"]
    assert any("clock offset" in line for line in rep["summary"])
