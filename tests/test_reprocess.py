"""`cbh reprocess` on Ray, started locally with 2 workers, on small simulated archives (480 px).

One Ray session serves the whole module (Ray takes seconds to start); each run makes and
kills its own actors, as the command does.
"""
from __future__ import annotations

import json
import os
import shutil
import signal
from datetime import datetime, timedelta, timezone
from pathlib import Path

import numpy as np
import pytest

T0 = datetime(2024, 6, 21, 14, 0, tzinfo=timezone.utc)
DAY2 = datetime(2024, 6, 22, 14, 0, tzinfo=timezone.utc)


@pytest.fixture(scope="module")
def archive(tmp_path_factory) -> Path:
    """Two UTC days of a simulated station in the folder-per-camera-per-day layout.

    Day 1: three pairs with identical stamps and, in the middle (14:00:45), a pair whose
    camera-1 JPEG is corrupt. Day 2: camera 2's stamps 0.2 s late (paired within the 0.5 s
    tolerance) and one extra camera-2 frame with no partner.
    """
    from cbh.presets import scene_path, station_path
    from cbh.sim import SkySimulator, load_scene
    from cbh.sim.io import time_tag, write_shot
    from cbh.geometry.station import load_station

    root = tmp_path_factory.mktemp("archive")
    sim = SkySimulator(load_station(station_path()), load_scene(scene_path("two-layers")), size_px=480)
    (root / "station.toml").write_text(sim.station.to_toml())
    flat = root / "flat"
    for start in (T0, DAY2):
        for k in range(3):
            write_shot(sim.render(start + timedelta(seconds=30 * k)), flat)
    for cam in ("cam1", "cam2"):
        for f in sorted((flat / cam).glob("*.jpg")):
            t = datetime.strptime(f.name.split("_")[1][:15], "%Y%m%dT%H%M%S").replace(tzinfo=timezone.utc)
            if cam == "cam2" and t.date() == DAY2.date():
                t += timedelta(seconds=0.2)
            dest = root / cam / f"{t:%Y-%m-%d}" / f"{cam}_{time_tag(t)}.jpg"
            dest.parent.mkdir(parents=True, exist_ok=True)
            shutil.copy(f, dest)
    extra = DAY2 + timedelta(seconds=75)  # 15 s from any camera-1 frame: never paired
    shutil.copy(next((root / "cam2" / "2024-06-22").glob("*.jpg")), root / "cam2" / "2024-06-22" / f"cam2_{time_tag(extra)}.jpg")
    shutil.rmtree(flat)
    mid = T0 + timedelta(seconds=45)
    for cam in ("cam1", "cam2"):
        good = sorted((root / cam / "2024-06-21").glob("*.jpg"))[1].read_bytes()
        (root / cam / "2024-06-21" / f"{cam}_{time_tag(mid)}.jpg").write_bytes(
            good if cam == "cam2" else good[:200] + b"\x00" * 100)  # a JPEG cut short and overwritten
    return root


@pytest.fixture(scope="module")
def ray_session():
    from cbh.actions.reprocess import start_ray

    before = os.environ.get("PYTHONPATH")
    owned, cpus = start_ray(workers=2)
    assert cpus >= 2
    yield before
    if owned:
        import ray

        ray.shutdown()


def _run(archive: Path, out: Path, **kw):
    from cbh.actions.reprocess import reprocess

    return reprocess([archive / "station.toml"], [f"cam1={archive / 'cam1'}", f"cam2={archive / 'cam2'}"],
                     out=out, workers=2, chunk_pairs=2, **kw)


@pytest.fixture(scope="module")
def baseline(archive, ray_session, tmp_path_factory):
    out = tmp_path_factory.mktemp("out")
    events: list[dict] = []
    plan, summary = _run(archive, out, on_event=events.append)
    return plan, summary, out, events


def test_days_are_cut_into_even_chunks():
    """At most chunk_pairs per chunk, as few chunks as that allows, sizes within one of each other."""
    from cbh.actions.reprocess import _chunk_bounds

    assert _chunk_bounds(50, 16) == [0, 12, 25, 37, 50]  # not 16, 16, 16, 2
    assert _chunk_bounds(32, 16) == [0, 16, 32] and _chunk_bounds(1, 32) == [0, 1]
    for n in range(1, 70):
        for c in (1, 2, 3, 7, 16, 32):
            b = _chunk_bounds(n, c)
            sizes = [j - i for i, j in zip(b, b[1:])]
            assert b[0] == 0 and b[-1] == n and len(sizes) == -(-n // c)
            assert max(sizes) <= c and max(sizes) - min(sizes) <= 1 and min(sizes) >= 1


def _heights_by_time(parquet: Path) -> dict:
    import pyarrow.parquet as pq

    rows = pq.read_table(parquet).to_pylist()
    out: dict = {}
    for r in rows:
        out.setdefault(r["time_utc"], [])
        if r["layer"] >= 0:
            out[r["time_utc"]].append(r["cloud_base_height_m"])
    return out


def test_chunks_are_handed_out_in_contiguous_stretches():
    """Each actor works through a contiguous stretch (no lead-in pair to re-process inside it);
    an actor without work takes the later half of the largest stretch; a second station gets its
    own actor while both have work."""
    from datetime import date

    from cbh.actions.reprocess import Chunk, _ChunkQueue

    def chunks(st, n):
        return [Chunk(st, date(2024, 6, 21), k, ()) for k in range(n)]

    q = _ChunkQueue({"a": chunks("a", 6)})
    order = [(slot, q.next(slot).index) for slot in (0, 1, 0, 1, 0, 1)]
    assert order == [(0, 0), (1, 3), (0, 1), (1, 4), (0, 2), (1, 5)] and len(q) == 0 and q.next(0) is None

    q = _ChunkQueue({"a": chunks("a", 5)})
    assert [q.next(0).index for _ in range(5)] == [0, 1, 2, 3, 4]  # one actor: one stretch

    q = _ChunkQueue({"a": chunks("a", 8)})
    assert [q.next(0).index, q.next(1).index, q.next(2).index] == [0, 4, 2]  # left: 0 [1,2), 1 [5,8), 2 [3,4)
    assert [q.next(1).index for _ in range(4)] == [5, 6, 7, 1]  # slot 1 done with its own: it takes slot 0's last
    assert len(q) == 1 and q.next(1).index == 3 and q.next(0) is None  # slot 2's, once slot 2 is gone (Ray gave up on it)

    q = _ChunkQueue({"a": chunks("a", 4), "b": chunks("b", 4)})
    got = [q.next(slot) for slot in (0, 1)]
    assert [(c.station, c.index) for c in got] == [("a", 0), ("b", 0)]


def test_a_lead_pair_beyond_the_motion_gap_is_not_reprocessed():
    """A chunk's lead pair is re-processed only for the state it hands on; more than
    ``motion.max_gap_s`` before the chunk's first pair (a day's first chunk after the night) it
    hands on nothing the pipeline uses, so it is skipped, and the actor that processed it last
    does not hand its state on either: which actor takes the chunk changes nothing."""
    from datetime import date, datetime, timezone

    from cbh.actions.archive import PairRef
    from cbh.actions.reprocess import Chunk, _lead_in_reach

    t = datetime(2024, 6, 21, 14, tzinfo=timezone.utc)
    pairs = tuple(PairRef(t + timedelta(seconds=30 * k), None, None) for k in range(3))
    for gap_s, reach in ((30.0, True), (120.0, True), (120.5, False), (86400.0, False)):
        lead = PairRef(t - timedelta(seconds=gap_s), None, None)
        assert _lead_in_reach(Chunk("a", date(2024, 6, 21), 1, pairs, lead), 120.0) is reach, gap_s
    assert not _lead_in_reach(Chunk("a", date(2024, 6, 21), 0, pairs, None), 120.0)  # a station's first chunk
    untimed = PairRef(None, None, None)  # no capture time: kept (the pipeline decides)
    assert _lead_in_reach(Chunk("a", date(2024, 6, 21), 1, pairs, untimed), 120.0)


def test_a_days_first_chunk_is_the_same_on_any_actor(archive):
    """Day 2's first chunk, whose lead pair is day 1's last (a day earlier: beyond
    ``motion.max_gap_s``), gives the same records on an actor that has just processed day 1's
    last chunk (its state is not handed on) as on a fresh one, and neither re-processes the lead."""
    from cbh.actions.reprocess import PairWorker, ReprocessOptions, _plan_chunks, load_jobs, plan_reprocess

    jobs = load_jobs([archive / "station.toml"], [f"cam1={archive / 'cam1'}", f"cam2={archive / 'cam2'}"])
    plan = plan_reprocess(jobs, ReprocessOptions(out=archive / "unused", chunk_pairs=2))
    (chunks,) = _plan_chunks(plan)[0].values()
    first2 = next(c for c in chunks if c.day == DAY2.date() and c.index == 0)
    last1 = max((c for c in chunks if c.day == T0.date()), key=lambda c: c.index)
    assert first2.lead == last1.pairs[-1] and (first2.pairs[0].time_utc - first2.lead.time_utc).total_seconds() > 86000
    stations = {j.name: (j.station.to_toml(), j.cameras) for j in plan.jobs}
    on = PairWorker(stations)
    forgot = []
    pipe = on.pipeline(first2.station)
    pipe.forget_learned = lambda: forgot.append(1)  # counted: when the learned obstacles are dropped
    assert on.process(last1).lead_in == 1 and len(forgot) == 2  # at its lead, and at its first pair
    forgot.clear()
    continued, fresh = on.process(first2), PairWorker(stations).process(first2)
    assert len(forgot) == 1  # at its first pair: the chunk's pairs learn from themselves alone
    assert continued.lead_in == fresh.lead_in == 0 and continued.error is None and fresh.error is None
    assert continued.records and repr(continued.records) == repr(fresh.records)


def test_an_error_outside_the_pairs_comes_back_with_its_chunk():
    """A bug or a pipeline that cannot be built is not a Ray task error (which Ray's pool could
    not tie to its chunk) but a result naming the chunk and the error: its day is left unwritten."""
    from datetime import date

    from cbh.actions.reprocess import Chunk, PairWorker

    res = PairWorker({}).process(Chunk("nowhere", date(2024, 6, 21), 3, ()))
    assert (res.station, res.index, res.records, res.restarted) == ("nowhere", 3, [], False)
    assert res.error == "KeyError: 'nowhere'" and res.elapsed_s >= 0


@pytest.mark.slow
def test_agrees_with_cbh_pair_then_resumes(archive, baseline, capsys):
    """Every day's heights equal `cbh pair` on the same two files (the pipeline keeps no state
    between pairs and uses no temporal information here: identical, not just close); a second
    run finds every day finished and processes no pair."""
    import xarray as xr

    from cbh.actions.reprocess import daily_paths
    from cbh.cli.main import main

    plan, s, out, events = baseline
    assert (s.pairs_total, s.pairs_processed, s.failures, s.days_written, s.workers) == (7, 7, 1, 2, 2)
    # chunks of at most 2 (chunk_pairs), even within a day: day 1's 4 pairs as 2 + 2, day 2's 3 as 1 + 2;
    # an actor works through a contiguous stretch (usually one actor day 1, the other day 2; an
    # actor done early takes over the other's next chunk): a chunk re-processes its lead-in pair
    # exactly where its actor did not process the chunk before it just before and that chunk is
    # the same day's (day 2's first pair lies a day after day 1's last: beyond motion.max_gap_s,
    # nothing to hand on); the motion check below holds either way; each chunk reports the
    # actor's CPU time
    done = [e for e in events if e["event"] == "chunk"]
    chunks = sorted((e["day"], e["chunk"], e["pairs"]) for e in done)
    assert [(d, n) for d, _, n in chunks] == [("2024-06-21", 2), ("2024-06-21", 2), ("2024-06-22", 1), ("2024-06-22", 2)]
    before = {c[:2]: p[:2] for p, c in zip(chunks, chunks[1:])}  # chunk → the chunk before it in time
    last: dict = {}  # pid → the chunk it processed last
    for e in done:  # per actor in the order it processed them
        me = (e["day"], e["chunk"])
        same_day = me in before and before[me][0] == me[0]
        assert e["lead_in"] == (same_day and last.get(e["pid"]) != before[me]), (e, last)
        last[e["pid"]] = me
    assert sum(e["lead_in"] for e in done) <= 1 and len(last) == 2
    assert all(e["cpu_s"] > 0 and e["elapsed_s"] > 0 for e in done)
    inv = plan.inventories["unb-lea"]
    assert inv.frames == {"cam1": 7, "cam2": 8} and inv.unpaired == {"cam1": 0, "cam2": 1}
    capsys.readouterr()
    for w in plan.days:
        paths = daily_paths(out, "unb-lea", w.day)
        got = _heights_by_time(paths["parquet"])
        ds = xr.open_dataset(paths["netcdf"])
        good = [p for p in w.pairs if p.time_utc != T0 + timedelta(seconds=45)]
        assert ds.sizes["time"] == len(good) == 3
        for i, p in enumerate(good):
            assert abs((p.frame2.time_utc - p.frame1.time_utc).total_seconds()) <= 0.2 + 1e-6
            assert main(["pair", p.frame1.path, p.frame2.path, "--station", str(archive / "station.toml"), "--json"]) == 0
            ref = [l["height_m"] for l in json.loads(capsys.readouterr().out)["layers"]]
            assert len(ref) >= 1
            assert got[p.time_utc] == ref  # exact equality of float64 heights
            nc = ds.cloud_base_height.values[i]
            assert np.array_equal(nc[: len(ref)], np.array(ref)) and np.isnan(nc[len(ref):]).all()
        ds.close()
        side = json.loads(paths["sidecar"].read_text())
        assert side["records"] == 3 and side["pairs"] == len(w.pairs)
        if w.day == T0.date():  # the corrupt file in the middle: counted with its reason, not fatal
            (f,) = side["failures"]
            assert f["time_utc"] == "2024-06-21T14:00:45Z" and "corrupt" in f["reason"] and "cam1_" in f["frames"][0]
        else:
            assert side["failures"] == []
    # motion: chunks start with a lead-in pair, so every pair's motion equals one sequential run's
    import pyarrow.parquet as pq

    from cbh.actions.run import MotionChain
    from cbh.errors import ImageError
    from cbh.geometry.station import load_station
    from cbh.pipeline import Pipeline

    pipe, chain, n_moving = Pipeline(load_station(archive / "station.toml")), MotionChain(), 0
    rows = [r for w in plan.days for r in pq.read_table(daily_paths(out, "unb-lea", w.day)["parquet"]).to_pylist()]
    for p in [p for w in plan.days for p in w.pairs]:
        try:
            r = pipe.process(p.frame1.path, p.frame2.path, p.time_utc, previous=chain.previous(p.time_utc))
        except ImageError:
            chain.lost()
            continue
        chain.keep(r)
        got_m = [(x["motion_east_ms"], x["motion_north_ms"]) for x in rows if x["time_utc"] == p.time_utc]
        want_m = [(l.motion_east_ms, l.motion_north_ms) for l in r.layers]
        assert [tuple(np.isnan(v) for v in m) for m in want_m] == [tuple(v is None for v in m) for m in got_m]
        # equal up to summation order (the actors run OpenCV on one thread, this process on all):
        # 1e-9 relative is far below anything physical (a 10 m/s cloud known to 1e-8 m/s)
        assert np.allclose(np.array(want_m, float), np.array([[np.nan if v is None else v for v in m] for m in got_m]),
                           rtol=1e-9, atol=0, equal_nan=True)
        n_moving += all(v is not None for m in got_m for v in m)
    assert n_moving >= 3  # pairs 2 and 3 of each day (after the corrupt one, too) move

    index = json.loads((out / "index.json").read_text())
    assert [d["status"] for d in index["stations"]["unb-lea"]["days"]] == ["written", "written"]
    assert index["time_span_utc"] == ["2024-06-21T14:00:00Z", "2024-06-22T14:01:00Z"]

    mtimes = {p: p.stat().st_mtime_ns for p in (out / "unb-lea").iterdir()}
    _, s2 = _run(archive, out)
    assert (s2.pairs_processed, s2.days_written, s2.days_resumed, s2.pairs_resumed) == (0, 0, 2, 7)
    assert {p: p.stat().st_mtime_ns for p in (out / "unb-lea").iterdir()} == mtimes
    index = json.loads((out / "index.json").read_text())
    assert [d["status"] for d in index["stations"]["unb-lea"]["days"]] == ["resumed", "resumed"]


def _kill_mid_run(archive: Path, out: Path, **kw):
    """Reprocess (2 workers, chunks of 2) and SIGKILL an actor's process right after its second
    chunk is handed to it (mid-run: it holds the motion state of its first chunk, and the second
    is in flight). Returns (pid killed, summary, events)."""
    pids: list[int] = []
    seen: dict[int, int] = {}
    killed: list[int] = []
    events: list[dict] = []

    def on_event(e):
        events.append(e)
        if e["event"] == "workers":
            pids.extend(e["pids"])
        elif e["event"] == "dispatch":
            seen[e["slot"]] = seen.get(e["slot"], 0) + 1
            if seen[e["slot"]] == 2 and not killed:
                os.kill(pids[e["slot"]], signal.SIGKILL)
                killed.append(pids[e["slot"]])

    _, s = _run(archive, out, on_event=on_event, **kw)
    assert killed
    return killed[0], s, events


def _day_tables(out: Path) -> dict:
    """Every day file's rows (heights, motion, clock offset…): what a fault must not change
    (as their repr: NaN diagnostics compare equal)."""
    import pyarrow.parquet as pq

    return {f.name: repr(pq.read_table(f).to_pydict()) for f in sorted((out / "unb-lea").glob("*.parquet"))}


@pytest.mark.slow  # real Ray, an actor killed: ~10 s
def test_killed_worker_is_restarted_and_its_task_retried(archive, baseline, tmp_path):
    """SIGKILL of an actor process mid-run: Ray restarts the actor (max_restarts) and retries the
    chunk it was on (max_task_retries); the restarted actor has lost its motion state, so the
    retried chunk re-processes its lead-in pair, and every row equals the undisturbed run's."""
    _, _, base_out, _ = baseline
    killed, s, events = _kill_mid_run(archive, tmp_path / "out")
    assert s.worker_restarts == 1 and s.lost_chunks == 0
    (retried,) = [e for e in events if e["event"] == "chunk" and e["restarted"]]
    assert retried["pid"] != killed and retried["lead_in"] == 1
    assert (s.pairs_processed, s.failures, s.days_written, s.days_failed) == (7, 1, 2, 0)
    assert _day_tables(tmp_path / "out") == _day_tables(base_out)


@pytest.mark.slow  # real Ray, an actor killed, and a rerun: ~15 s
def test_a_worker_ray_gives_up_on_leaves_its_day_for_a_rerun(archive, baseline, tmp_path):
    """With Ray's restarts off, the killed actor leaves the pool and its chunk is lost: the other
    actor does the rest, that chunk's day is left unwritten (the index says why), and the same
    command again processes exactly that day; the day files then equal the undisturbed run's."""
    _, _, base_out, _ = baseline
    out = tmp_path / "out"
    _, s, _ = _kill_mid_run(archive, out, actor_restarts=0)
    assert (s.lost_chunks, s.worker_restarts, s.days_written, s.days_failed) == (1, 0, 1, 1)
    index = json.loads((out / "index.json").read_text())
    (lost,) = [d for d in index["stations"]["unb-lea"]["days"] if d["status"] == "not finished"]
    assert "max_restarts" in lost["reason"] and index["totals"]["lost_chunks"] == 1
    _, s2 = _run(archive, out)
    assert (s2.days_resumed, s2.days_written, s2.pairs_processed) == (1, 1, lost["pairs"])
    assert _day_tables(out) == _day_tables(base_out)


def test_network_file_and_source_binding_errors(archive, tmp_path):
    """A network TOML lists stations; --source must name a camera of the pair; live URLs are refused."""
    from cbh.actions.reprocess import load_jobs
    from cbh.errors import ConfigError

    net = tmp_path / "network.toml"
    st = archive / "station.toml"
    net.write_text(f'[[stations]]\nstation = "{st}"\n[stations.sources]\ncam1 = "{archive / "cam1"}"\n'
                   f'cam2 = "{archive / "cam2"}"\n')
    (job,) = load_jobs([net])
    assert job.cameras == ("cam1", "cam2") and job.specs["cam2"] == str(archive / "cam2")
    # two stations in one network: the work is partitioned by station and UTC day
    st_b = tmp_path / "b.toml"
    st_b.write_text(st.read_text().replace('name = "unb-lea"', 'name = "site-b"', 1))
    net.write_text(net.read_text() + f'[[stations]]\nstation = "{st_b}"\n')
    from cbh.actions.reprocess import ReprocessOptions, plan_reprocess

    jobs = load_jobs([net], [f"site-b/cam1={archive / 'cam1'}", f"site-b/cam2={archive / 'cam2'}"])
    plan = plan_reprocess(jobs, ReprocessOptions(out=tmp_path / "out", t_to=DAY2))
    assert [(d.station, str(d.day), len(d.pairs)) for d in plan.days] == [
        ("unb-lea", "2024-06-21", 4), ("site-b", "2024-06-21", 4)]  # --to: day 2 left out
    with pytest.raises(ConfigError, match="STATION/cam1"):
        load_jobs([net], [f"cam1={archive / 'cam1'}"])
    with pytest.raises(ConfigError, match="no station"):
        load_jobs([st], ["cam9=/tmp"])
    with pytest.raises(ConfigError, match="given twice"):
        load_jobs([st, net])
    from cbh.actions.archive import source_kind

    with pytest.raises(ConfigError, match="archives"):
        source_kind("rtsp://127.0.0.1/x")
    (job,) = load_jobs([st], ["cam1=rtsp://127.0.0.1/x"])
    assert job.specs["cam1"] == "rtsp://127.0.0.1/x"  # kept as given, so the scan says what is wrong


def test_cli_bad_input_is_one_line(tmp_path, capsys):
    from cbh.cli.main import main

    assert main(["reprocess", "--station", "unb-lea", "--out", str(tmp_path / "o"), "--format", "csv"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("cbh: error: --format") and err.count("\n") == 1


def test_the_private_ray_keeps_token_auth_without_its_notice(ray_session):
    """Ray prints "Token authentication is enabled …" unless RAY_AUTH_MODE is set: cbh sets it
    (token, Ray's own default for a local instance) for the private instance it starts. The
    repository's folder goes on the path of the processes Ray starts (its workers import this
    cbh: every chunk test here), not on this process's: it had stayed on PYTHONPATH, and a later
    subprocess found the repository's top-level ``cli`` (tests/test_api.py, run after this file)."""
    import ray

    import cbh

    assert ray.is_initialized() and os.environ.get("RAY_AUTH_MODE") == "token"
    assert os.environ.get("PYTHONPATH") == ray_session
    root = str(Path(cbh.__file__).resolve().parent.parent)
    workers_path = ray.get(ray.remote(lambda: os.environ.get("PYTHONPATH", "")).remote())
    assert workers_path.split(os.pathsep)[0] == root, workers_path


@pytest.mark.slow  # a fresh process starting Ray: ~6 s
def test_ray_imported_before_the_private_ray_starts(tmp_path):
    """A program that imported ray before cbh starts its private Ray (a notebook, the benchmark)
    got "Authentication token is missing": the token setting came after Ray had read its own.
    cbh now leaves Ray's settings alone once ray is imported."""
    import subprocess
    import sys

    code = ("import ray; from cbh.actions.reprocess import start_ray; "
            "owned, cpus = start_ray(workers=1); print(owned, cpus, ray.get(ray.put(7))); ray.shutdown()")
    env = {k: v for k, v in os.environ.items() if k != "RAY_AUTH_MODE"}
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, env=env,
                       cwd=Path(__file__).resolve().parents[1])
    assert p.returncode == 0 and p.stdout.split() == ["True", "1", "7"], p.stderr[-2000:]


def test_empty_camera_folders_are_an_error_as_in_cbh_run(tmp_path, capsys):
    """`cbh run` over empty folders says no pair was found and exits 2; so does reprocess, and
    writes nothing (no Ray is started)."""
    from cbh.cli.main import main

    (tmp_path / "c1").mkdir()
    (tmp_path / "c2").mkdir()
    out = tmp_path / "o"
    srcs = ["--source", f"cam1={tmp_path / 'c1'}", "--source", f"cam2={tmp_path / 'c2'}"]
    assert main(["run", *srcs]) == 2
    assert "no pair processed" in capsys.readouterr().err
    assert main(["reprocess", "--station", "unb-lea", *srcs, "--out", str(out)]) == 2
    captured = capsys.readouterr()
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1 and lines[0] == "cbh: error: no pair to process: found unb-lea: cam1 0 frames, cam2 0 frames"
    assert captured.out == "" and not out.exists()


@pytest.mark.slow
def test_truncated_recording_and_video_inputs(archive, ray_session, repo, tmp_path):
    """A recording cut mid-write is repaired and its complete pairs processed; video files
    are read frame by frame. Heights equal `Pipeline.process` on the same decoded images."""
    import cv2

    from cbh.actions.reprocess import reprocess
    from cbh.outputs.record import open_session
    from cbh.pipeline import Pipeline

    # recording: the sample session cut at 60 % of its bytes (a killed writer)
    rec = tmp_path / "session.mcap"
    data = (repo / "recordings" / "sample-two-layers.mcap").read_bytes()
    rec.write_bytes(data[: int(0.6 * len(data))])
    full = open_session(repo / "recordings" / "sample-two-layers.mcap")
    st_file = tmp_path / "rec-station.toml"
    st_file.write_text(full.station.to_toml())
    plan, s = reprocess([st_file], [f"cam1={rec}"], out=tmp_path / "out-rec", workers=2, chunk_pairs=2,
                        formats=("parquet",))
    inv = plan.inventories["unb-lea"]
    assert len(inv.repaired) == 1 and 0 < inv.repaired[0]["pairs"] < 8
    assert s.pairs_processed == inv.repaired[0]["pairs"] and s.failures == 0
    from cbh.actions.run import MotionChain

    def same(got_h, result):  # equal up to summation order (actors run OpenCV on one thread)
        want_h = [l.height_m for l in result.layers]
        return len(got_h) == len(want_h) and np.allclose(got_h, want_h, rtol=1e-9, atol=0)

    pipe, chain = Pipeline(full.station), MotionChain()  # reference: one sequential run, as `cbh run`
    got = _heights_by_time(next((tmp_path / "out-rec" / "unb-lea").glob("*.parquet")))
    for rp in list(full.pairs())[: s.pairs_processed]:
        f1, f2 = rp.frames()
        r = pipe.process(f1.image, f2.image, rp.time_utc, channels="bgr", previous=chain.previous(rp.time_utc))
        chain.keep(r)
        assert same(got[rp.time_utc], r)

    # video: day 1 of the archive as two MJPEG videos, 1 frame per second
    vids = {}
    for cam in ("cam1", "cam2"):
        vids[cam] = tmp_path / f"{cam}_20240621T140000Z.avi"
        w = cv2.VideoWriter(str(vids[cam]), cv2.VideoWriter_fourcc(*"MJPG"), 1.0, (480, 480))
        for f in sorted((archive / cam / "2024-06-21").glob("*.jpg")):
            if "T140045" not in f.name:  # not the corrupt pair
                w.write(cv2.imread(str(f)))
        w.release()
    plan, s = reprocess([archive / "station.toml"], [f"cam1={vids['cam1']}", f"cam2={vids['cam2']}"],
                        out=tmp_path / "out-vid", workers=2, chunk_pairs=2, formats=("parquet",))
    assert (s.pairs_processed, s.failures) == (3, 0)
    (w,) = plan.days
    assert [p.frame1.index for p in w.pairs] == [0, 1, 2]
    steps = [(b.time_utc - a.time_utc).total_seconds() for a, b in zip(w.pairs, w.pairs[1:])]
    assert np.allclose(steps, 1.0)
    from cbh.geometry.station import load_station

    pipe, chain = Pipeline(load_station(archive / "station.toml")), MotionChain()
    caps = {c: cv2.VideoCapture(str(v)) for c, v in vids.items()}
    got = _heights_by_time(next((tmp_path / "out-vid" / "unb-lea").glob("*.parquet")))
    for p in w.pairs:
        im1, im2 = caps["cam1"].read()[1], caps["cam2"].read()[1]
        r = pipe.process(im1, im2, p.time_utc, channels="bgr", previous=chain.previous(p.time_utc))
        chain.keep(r)
        assert same(got[p.time_utc], r)


@pytest.mark.slow
def test_ctrl_c_keeps_finished_days_and_rerun_finishes(archive, baseline, tmp_path):
    """A real Ctrl-C (SIGINT to the command's process group) once the first day is written:
    exit code 130, that day kept, the index says interrupted; the same command run again
    resumes (the finished day is not processed again) and finishes the rest."""
    import subprocess
    import sys

    out = tmp_path / "out"
    cmd = [sys.executable, "-c", "import sys; from cbh.cli.main import main; sys.exit(main())", "reprocess", "--station", str(archive / "station.toml"),
           "--source", f"cam1={archive / 'cam1'}", "--source", f"cam2={archive / 'cam2'}", "--out", str(out),
           "--workers", "2", "--chunk-pairs", "1"]
    p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)
    first = json.loads(p.stdout.readline())  # the JSON line of the first finished day
    os.killpg(p.pid, signal.SIGINT)
    rest, err = p.communicate(timeout=120)
    # each actor works through one day (contiguous stretches): either may finish first
    pairs = {"2024-06-21": 4, "2024-06-22": 3}
    assert first["day"] in pairs and first["records"] == 3
    (other,) = set(pairs) - {first["day"]}
    index = json.loads((out / "index.json").read_text())
    statuses = {d["day"]: d["status"] for d in index["stations"]["unb-lea"]["days"]}
    assert "Token authentication" not in err  # Ray's notice on every run (issue 26)
    if p.returncode == 130:  # interrupted while the other day was in flight (the usual case)
        assert index["interrupted"] and statuses == {first["day"]: "written", other: "not finished"}
        assert "interrupted" in err
    else:  # the other day finished before the signal arrived
        assert p.returncode == 0 and set(statuses.values()) == {"written"}
    _, s2 = _run(archive, out)
    assert s2.days_resumed + s2.days_written == 2 and s2.days_resumed >= 1
    assert s2.pairs_processed == (pairs[other] if s2.days_written else 0)


def test_a_replaced_image_redoes_its_day_a_repaired_copy_does_not(tmp_path):
    """A corrupt image replaced under the same name kept its day "already done" (with the failure)
    forever: the day's work hash named only times and paths. Now the files' size (images and
    videos: and modification time) is in it; a recording's repaired copy, rewritten by every run
    with the same bytes, keeps the hash."""
    from cbh.actions.archive import FrameRef, PairRef
    from cbh.actions.reprocess import _work_hash

    t = datetime(2024, 6, 21, 14, tzinfo=timezone.utc)
    a, b, rec = tmp_path / "a.jpg", tmp_path / "b.jpg", tmp_path / "r.mcap"
    a.write_bytes(b"\xff\xd8 good image")
    b.write_bytes(b"junk")  # the corrupt one
    rec.write_bytes(b"recorded bytes")
    img = [PairRef(t, FrameRef("cam1", t, "image", str(a)), FrameRef("cam2", t, "image", str(b)))]
    recd = [PairRef(t, FrameRef("cam1", t, "recording", str(rec), 0), FrameRef("cam2", t, "recording", str(rec), 0))]
    h_img, h_rec = _work_hash(img), _work_hash(recd)
    assert _work_hash(img) == h_img  # nothing changed: the day stays done
    b.write_bytes(b"\xff\xd8 the real image, copied again")
    assert _work_hash(img) != h_img
    os.utime(rec, ns=(1, 1))  # rewritten with the same bytes (a repaired copy): same hash
    assert _work_hash(recd) == h_rec


@pytest.mark.slow
def test_every_pair_failing_is_an_error(archive, ray_session, tmp_path, capsys):
    """An archive none of whose pairs can be processed (every camera-1 image unreadable) is a
    run that could not do its job: one line, exit 2, not 'days: 1 written'."""
    from cbh.cli.main import main

    bad = tmp_path / "bad"
    for cam in ("cam1", "cam2"):
        shutil.copytree(archive / cam / "2024-06-21", bad / cam / "2024-06-21")
    for f in (bad / "cam1" / "2024-06-21").glob("*.jpg"):
        f.write_bytes(b"\xff\xd8 not a jpeg")
    rc = main(["reprocess", "--station", str(archive / "station.toml"), "--source", f"cam1={bad / 'cam1'}",
               "--source", f"cam2={bad / 'cam2'}", "--out", str(tmp_path / "out"), "--workers", "2"])
    err = capsys.readouterr().err
    assert rc == 2
    assert "cbh: error: every pair failed (4 of 4" in err


@pytest.mark.slow  # slow: a three-camera network on Ray (4.9 s with its teardown); one station's reprocess stays in the default suite
def test_a_camera_network_is_reprocessed_from_its_folders(ray_session, tmp_path):
    """Three cameras' folders (unb-lea-network, 480 px, 1500 m and 8000 m): frame sets grouped
    within the tolerance, the station pipeline on Ray, one row per layer. 480 px: a working
    pixel of 0.38°, so the bar is the issue's 0.4 % at 1500 m and 1 % at 8000 m (the 630 m pair:
    δH = H² δθ / B ≈ 1.2 % per pixel at 8 km, averaged over thousands)."""
    import pyarrow.parquet as pq

    from cbh.actions.reprocess import reprocess
    from cbh.cli.main import main

    src = tmp_path / "in"
    assert main(["simulate", "--out", str(src), "--station", "unb-lea-network", "--scene", "low-and-high",
                 "--frames", "2", "--size", "480"]) == 0
    plan, s = reprocess([src / "station.toml"], [f"{c}={src / c}" for c in ("cam1", "cam2", "cam3")],
                        out=tmp_path / "out", workers=2, chunk_pairs=1)
    assert s.pairs_processed == 2 and s.failures == 0 and s.days_written == 1
    t = pq.read_table(next((tmp_path / "out" / "unb-lea-network").glob("*.parquet"))).to_pandas()
    assert sorted(set(t["layer"])) == [1, 2] and len(t) == 4
    low, high = t[t["layer"] == 1]["cloud_base_height_m"], t[t["layer"] == 2]["cloud_base_height_m"]
    assert (abs(low / 1500.0 - 1) < 0.004).all() and (abs(high / 8000.0 - 1) < 0.01).all()
    assert "cam1+cam3.baseline_m" in t.columns
