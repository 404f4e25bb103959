"""`cbh reprocess` throughput on Ray: pairs/s for 1 and 2 workers (and 16 / GPU where available),
against a plain loop over `Pipeline.process` on the same files, with where the CPU went.

    python benchmarks/bench_reprocess.py [--pairs 64] [--size 960] [--chunk-pairs 8] [--repeat 1] [--archive DIR]
    python benchmarks/bench_reprocess.py --against OTHER_CHECKOUT [--repeat 3] [--archive DIR]

A simulated two-day archive (one folder per camera per day) is rendered into a temporary
folder (960 px by default: nearer the real 1920 px cost per pair than 480 px, so the fixed
costs weigh as they would on real archives). Then, in turn:

- **plain loop**: this process, OpenCV and BLAS on one thread (as in a one-CPU actor),
  `Pipeline.process` over every pair in time order with the motion state handed on, as
  reprocess does (reprocess also re-processes one lead-in pair per stretch of chunks; the loop does not).
- **2 plain loops at once**: two processes, each the loop over half of the pairs (no Ray): the
  most two workers can give on this machine (two cores that are really two, the memory
  bandwidth and caches they share, other load).
- **Ray, 1 and 2 workers**: each run as the command does it: a private Ray instance with
  ``num_cpus`` = workers is started (its start printed apart), ``reprocess`` runs end to end
  (actors start and build their pipelines, every pair is processed, the daily NetCDF +
  Parquet files and the index are written), Ray is stopped. The 1-worker baseline is one
  single-threaded actor (one CPU, OpenCV on one thread), like each of the 2 workers.
  "steady" is the rate once every actor has finished its first chunk (process start-up and
  pipeline build excluded). Chunks of 8 pairs by default (the command's default is 32): four per
  actor with 2 workers, so the steady window holds three; smaller chunks cost no lead-in pairs,
  since an actor re-processes one only where it starts a new stretch of a station's chunks.

Then **exactness and resumption** (:func:`resume_check`, on the 2-worker output): the 1- and
2-worker day files hold identical rows; the same command again processes no pair (every day
resumed: its wall time); a run stopped like a Ctrl-C once its first day is written, then the
same command again, processes every pair exactly once between them apart from the days in
flight when it stopped, and writes day files identical to the undisturbed run's. Each Ray run
prints the load average (``uptime``) before it: this benchmark shares the machine.

``--against DIR`` measures only the Ray runs, of this checkout's cbh and of DIR's (another
checkout: the commit before a change), alternately, each in a fresh process, so that both meet
the same load on a shared machine (:func:`ab_runs`). Run the benchmark with ``PYTHONPATH`` set to
the checkout to measure, where another cbh is installed.

Where the CPU went during each measured window (Linux ``/proc``): the actors, this driver
process, Ray's own processes (raylet, GCS, dashboard/agents, log monitor, idle workers), and
the rest of the machine (other processes; and the hypervisor's steal time). When other load
took more than 5 % of the machine, the rates are marked as not representative: measure again
on a quiet machine.
"""
from __future__ import annotations

import argparse
import os

# one BLAS/OpenMP thread in the plain loops too, as Ray gives each one-CPU actor
for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")
import shutil
import tempfile
import threading
import time
from datetime import datetime, timedelta, timezone
from pathlib import Path

OTHER_LOAD_LIMIT = 0.05  # share of the machine other processes may take before a warning


# --- where the CPU went (Linux /proc) -------------------------------------------------------------

_HZ = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100


def _procs() -> dict[int, tuple[int, float, str]]:
    """pid → (ppid, CPU seconds so far, command name) of every process."""
    out = {}
    for p in os.listdir("/proc"):
        if not p.isdigit():
            continue
        try:
            with open(f"/proc/{p}/stat") as f:
                st = f.read()
        except OSError:
            continue
        name = st[st.find("(") + 1:st.rfind(")")]
        rest = st[st.rfind(")") + 2:].split()
        out[int(p)] = (int(rest[1]), (int(rest[11]) + int(rest[12])) / _HZ, name)
    return out


def _machine() -> tuple[float, float]:
    """(busy, steal) CPU seconds of the whole machine so far (/proc/stat)."""
    with open("/proc/stat") as f:
        v = [int(x) for x in f.readline().split()[1:]]
    user, nice, system, idle, iowait, irq, softirq, steal = (v + [0] * 8)[:8]
    return (user + nice + system + irq + softirq) / _HZ, steal / _HZ


class CpuMeter:
    """CPU seconds per process over a window, sampled every ``period_s`` (processes that end
    inside the window keep their last sample). Not available off Linux (``ok`` False)."""

    def __init__(self, period_s: float = 0.2):
        self.ok = os.path.exists("/proc/stat")
        self.period_s = period_s
        self.first: dict = {}
        self.last: dict = {}
        self._stop = threading.Event()

    def _sample(self):
        for pid, v in _procs().items():
            self.last[pid] = v

    def _loop(self):
        while not self._stop.wait(self.period_s):
            self._sample()

    def __enter__(self):
        if self.ok:
            self.t0 = time.perf_counter()
            self.m0 = _machine()
            self.first = _procs()
            self.last = dict(self.first)
            self._thread = threading.Thread(target=self._loop, daemon=True)
            self._thread.start()
        return self

    def __exit__(self, *exc):
        if self.ok:
            self._stop.set()
            self._thread.join()
            self._sample()
            self.m1 = _machine()
            self.wall_s = time.perf_counter() - self.t0

    def split(self, worker_pids=()) -> dict | None:
        """CPU seconds of: workers (``worker_pids``: the actors, or the loop processes), driver
        (this process), ray (the other processes started from here: Ray's raylet, GCS,
        dashboard/agents, log monitor, idle workers), other (the rest of the machine); steal
        (the hypervisor's); capacity (wall × CPUs)."""
        if not self.ok:
            return None
        me = os.getpid()

        def ours(pid: int) -> bool:
            seen = set()
            while pid > 1 and pid not in seen:
                if pid == me:
                    return True
                seen.add(pid)
                pid = self.last.get(pid, (0,))[0]
            return False

        acc = {"workers": 0.0, "driver": 0.0, "ray": 0.0}
        for pid, (_, cpu, _name) in self.last.items():
            used = cpu - (self.first[pid][1] if pid in self.first else 0.0)
            if pid == me:
                acc["driver"] += used
            elif pid in worker_pids:
                acc["workers"] += used
            elif ours(pid):
                acc["ray"] += used
        busy = self.m1[0] - self.m0[0]
        acc["other"] = max(0.0, busy - sum(acc.values()))
        acc["steal"] = self.m1[1] - self.m0[1]
        acc["capacity"] = self.wall_s * (os.cpu_count() or 1)
        return acc


def _cpu_line(acc: dict | None) -> str:
    if acc is None:
        return "CPU split: not measured (no /proc)"
    cap = acc["capacity"]
    return (f"CPU s: workers {acc['workers']:.1f}, driver {acc['driver']:.1f}, Ray's processes {acc['ray']:.1f}, "
            f"other load {acc['other']:.1f} ({100 * acc['other'] / cap:.0f} % of the machine), steal {acc['steal']:.1f}; "
            f"capacity {cap:.1f}")


# --- the archive and the plain loops ----------------------------------------------------------------

def make_archive(root: Path, pairs: int, size: int) -> Path:
    from cbh.geometry.station import load_station
    from cbh.presets import scene_path, station_path
    from cbh.sim import SkySimulator, load_scene
    from cbh.sim.io import write_shot

    sim = SkySimulator(load_station(station_path()), load_scene(scene_path("two-layers")), size_px=size)
    (root / "station.toml").write_text(sim.station.to_toml())
    flat = root / "flat"
    days = (datetime(2024, 6, 21, 13, tzinfo=timezone.utc), datetime(2024, 6, 22, 13, tzinfo=timezone.utc))
    for k in range(pairs):
        write_shot(sim.render(days[k % 2] + timedelta(seconds=30 * (k // 2))), flat)
    for cam in ("cam1", "cam2"):
        for f in (flat / cam).glob("*.jpg"):
            day = f"{f.name.split('_')[1][:4]}-{f.name.split('_')[1][4:6]}-{f.name.split('_')[1][6:8]}"
            (root / cam / day).mkdir(parents=True, exist_ok=True)
            shutil.move(str(f), root / cam / day / f.name)
    shutil.rmtree(flat)
    return root


def _pairs(root: Path) -> tuple:
    from cbh.actions.reprocess import ReprocessOptions, load_jobs, plan_reprocess

    jobs = load_jobs([root / "station.toml"], [f"cam1={root / 'cam1'}", f"cam2={root / 'cam2'}"])
    plan = plan_reprocess(jobs, ReprocessOptions(out=root / "unused"))
    return jobs[0].station, [p for d in plan.days for p in d.pairs]


def plain_loop(root: Path, part: tuple[int, int] = (0, 1), start=None, ready=None) -> tuple[float, float, int, float]:
    """(wall s, steady pairs/s, pairs, CPU s) of the loop over part k of n of the pairs.

    With ``start`` (an Event), the pipeline is built and warmed on the part's first pair, then
    the loop says so on ``ready`` (a Queue), waits for ``start`` and runs from a fresh motion state.
    """
    import cv2

    from cbh.actions.archive import load_images
    from cbh.actions.run import MotionChain
    from cbh.pipeline import Pipeline

    cv2.setNumThreads(1)
    station, pairs = _pairs(root)
    k, n = part
    pairs = pairs[k * len(pairs) // n:(k + 1) * len(pairs) // n]
    pipe = Pipeline(station)
    if start is not None:
        imgs = load_images([pairs[0].frame1, pairs[0].frame2])
        pipe.process(imgs[pairs[0].frame1], imgs[pairs[0].frame2], pairs[0].time_utc, channels="bgr")
        ready.put(k)
        start.wait()
    t0, c0 = time.perf_counter(), time.process_time()
    chain = MotionChain()  # the same work as reprocess: motion state too
    t1 = None
    for p in pairs:
        imgs = load_images([p.frame1, p.frame2])
        r = pipe.process(imgs[p.frame1], imgs[p.frame2], p.time_utc, channels="bgr", previous=chain.previous(p.time_utc))
        chain.keep(r)
        t1 = t1 or time.perf_counter()  # after the first pair (warm-up)
    t_end = time.perf_counter()
    return t_end - t0, (len(pairs) - 1) / (t_end - t1), len(pairs), time.process_time() - c0


def _loop_part(root, k, n, start, ready, q):
    q.put(plain_loop(root, (k, n), start, ready))


def parallel_loops(root: Path, n: int) -> tuple[float, int, dict | None]:
    """n plain loops at once in n processes, each over 1/n of the pairs: (wall s, pairs, CPU split)."""
    import multiprocessing as mp

    ctx = mp.get_context("spawn")
    start, ready, q = ctx.Event(), ctx.Queue(), ctx.Queue()
    procs = [ctx.Process(target=_loop_part, args=(root, k, n, start, ready, q)) for k in range(n)]
    for p in procs:
        p.start()
    for _ in procs:  # each has built its pipeline and processed a first pair: start together
        ready.get()
    with CpuMeter() as m:
        t0 = time.perf_counter()
        start.set()
        res = [q.get() for _ in procs]
        wall = time.perf_counter() - t0
    for p in procs:
        p.join()
    return wall, sum(r[2] for r in res), m.split({p.pid for p in procs})


# --- Ray runs --------------------------------------------------------------------------------------

def ray_run(root: Path, workers: int, chunk_pairs: int, device: str = "cpu") -> dict:
    """One run as ``cbh reprocess`` does it: a private Ray with num_cpus=workers, run, stop."""
    from cbh.actions.reprocess import reprocess, start_ray

    out = root / f"out-{workers}-{device}"
    shutil.rmtree(out, ignore_errors=True)
    print(f"    (ray {workers}: load average before {_loadavg()})", flush=True)
    t0 = time.perf_counter()
    start_ray(workers=workers, device=device)  # before Ray is imported here: it sets Ray's environment first
    t_ray = time.perf_counter() - t0
    import ray
    first_done: dict[int, float] = {}
    actor_pids: set[int] = set()
    n_after = [0]
    cpu = {"s": 0.0, "pairs": 0, "lead": 0}  # after each actor's first chunk (imports, pipeline build)

    spans: dict[int, list] = {}  # pid → [(start, end)] of its chunks (the actor's clock)

    def ev(e):
        if e["event"] == "workers":
            actor_pids.update(p for p in e["pids"] if p)
        elif e["event"] == "chunk":
            actor_pids.add(e["pid"])
            end = e.get("finished_unix", float("nan"))  # not reported before issue 36
            spans.setdefault(e["pid"], []).append((end - e["elapsed_s"], end))
            if e["pid"] in first_done:
                cpu["s"] += e["cpu_s"]
                cpu["pairs"] += e["pairs"] + e["lead_in"]
            cpu["lead"] += e["lead_in"]
            if e["pid"] not in first_done:
                first_done[e["pid"]] = time.perf_counter()
            elif len(first_done) >= workers:
                n_after[0] += e["pairs"]

    try:
        with CpuMeter() as m:
            t0 = time.perf_counter()
            _, s = reprocess([root / "station.toml"], [f"cam1={root / 'cam1'}", f"cam2={root / 'cam2'}"], out=out,
                             workers=workers, chunk_pairs=chunk_pairs, device=device, on_event=ev)
            t_end = time.perf_counter()
    finally:
        ray.shutdown()
    steady = (n_after[0] / (t_end - max(first_done.values())) if len(first_done) >= workers and n_after[0]
              else float("nan"))
    assert s.failures == 0 and s.pairs_processed > 0
    return {"wall": t_end - t0, "steady": steady, "pairs": s.pairs_processed, "ray_start": t_ray,
            "cpu_per_pair": cpu["s"] / cpu["pairs"] if cpu["pairs"] else float("nan"), "lead": cpu["lead"],
            "split": m.split(actor_pids), "out": out, "gap_ms": _gap_ms(spans)}


def _gap_ms(spans: dict[int, list]) -> float:
    """Mean time an actor waited between the end of one chunk and the start of its next [ms]
    (what handing out chunks costs the actors; NaN where the cbh measured does not report it)."""
    gaps = []
    for s in spans.values():
        s = sorted(s)
        gaps.extend(b[0] - a[1] for a, b in zip(s, s[1:]))
    return 1000 * sum(gaps) / len(gaps) if gaps else float("nan")


def _loadavg() -> str:
    try:
        return " ".join(Path("/proc/loadavg").read_text().split()[:3])
    except OSError:
        return "n/a"


def _day_tables(out: Path) -> dict:
    """Day file name → its rows (the Parquet table's repr, so NaN equals NaN): what must not change."""
    import pyarrow.parquet as pq

    return {f.name: repr(pq.read_table(f).to_pydict()) for f in sorted(out.glob("*/*.parquet"))}


def _timed_reprocess(root: Path, out: Path, workers: int, chunk_pairs: int, stop_after_day: bool = False):
    """(wall s, Summary) of one reprocess run on a fresh private Ray; ``stop_after_day``: a
    KeyboardInterrupt (as Ctrl-C) once the first day is written."""
    from cbh.actions.reprocess import reprocess

    def ev(e):
        if stop_after_day and e["event"] == "day":
            raise KeyboardInterrupt

    t0 = time.perf_counter()
    try:
        _, s = reprocess([root / "station.toml"], [f"cam1={root / 'cam1'}", f"cam2={root / 'cam2'}"], out=out,
                         workers=workers, chunk_pairs=chunk_pairs, on_event=ev)
    finally:
        import ray

        ray.shutdown()
    return time.perf_counter() - t0, s


def resume_check(root: Path, runs: dict, chunk_pairs: int) -> None:
    """Exactness (1 vs 2 workers) and resumption (a rerun; a stop after the first day + a rerun)."""
    ref = _day_tables(runs[2]["out"])
    same = ref == _day_tables(runs[1]["out"])
    print(f"exact: day files of 1 and 2 workers identical: {'yes' if same else 'NO'} ({len(ref)} days)")
    t, s = _timed_reprocess(root, runs[2]["out"], 2, chunk_pairs)
    print(f"resume, nothing left: {s.pairs_processed} pairs processed, {s.days_resumed} days resumed, "
          f"{t:.1f} s (plan + index; no Ray started)")
    out = root / "out-stopped"
    shutil.rmtree(out, ignore_errors=True)
    t1, s1 = _timed_reprocess(root, out, 2, chunk_pairs, stop_after_day=True)
    t2, s2 = _timed_reprocess(root, out, 2, chunk_pairs)
    total = s1.pairs_total
    kept = s1.days_written
    redone = s1.pairs_processed + s2.pairs_processed - total
    same = _day_tables(out) == ref
    print(f"resume after a stop once the first day was written: run 1 {s1.pairs_processed} pairs in {t1:.1f} s "
          f"({kept} day kept, interrupted={s1.interrupted}); run 2 {s2.pairs_processed} pairs in {t2:.1f} s "
          f"({s2.days_resumed} resumed, {s2.days_written} written); {redone} pairs done twice (in flight at the "
          f"stop); day files identical to the undisturbed run: {'yes' if same else 'NO'}")


def one_ray(root: Path, workers: int, chunk_pairs: int) -> None:
    """``--one-ray W``: one Ray run of the cbh this process imports; its numbers as a JSON line."""
    import json

    import cbh

    load = _loadavg()
    r = ray_run(root, workers, chunk_pairs)
    acc = r["split"]
    print(json.dumps({"wall": r["wall"], "steady": r["steady"], "pairs": r["pairs"], "lead": r["lead"], "gap_ms": r["gap_ms"],
                      "load": load, "cbh": str(Path(cbh.__file__).parent),
                      "other": acc["other"] / acc["capacity"] if acc else None}))


def ab_runs(root: Path, against: Path, repeat: int, chunk_pairs: int) -> None:
    """``--against DIR``: the 1- and 2-worker Ray runs of this checkout and of DIR's cbh (another
    checkout, e.g. the commit before a change), alternately in fresh processes, so that both
    meet the same load on a shared machine; 2 vs 1 is taken per round (consecutive runs)."""
    import json
    import subprocess
    import sys

    trees = {"this": Path(__file__).resolve().parents[1], "against": against.resolve()}
    got: dict = {(t, w): [] for t in trees for w in (1, 2)}
    for _ in range(repeat):
        for t, d in trees.items():
            for w in (1, 2):
                p = subprocess.run([sys.executable, __file__, "--one-ray", str(w), "--archive", str(root),
                                    "--chunk-pairs", str(chunk_pairs)], env=dict(os.environ, PYTHONPATH=str(d)),
                                   capture_output=True, text=True)
                if p.returncode:
                    raise SystemExit(f"{t} ray {w} failed:\n{p.stderr[-3000:]}")
                r = json.loads(p.stdout.strip().splitlines()[-1])
                got[(t, w)].append(r)
                print(f"  {t} ({r['cbh']}) ray {w}: {r['pairs'] / r['wall']:.2f} pairs/s end to end ({r['wall']:.1f} s), "
                      f"steady {r['steady']:.2f}; {r['lead']} lead-in pairs; actors wait {r['gap_ms']:.0f} ms between "
                      f"chunks; load average before {r['load']}, "
                      f"other load {100 * (r['other'] or 0):.0f} % of the machine", flush=True)
    for t, d in trees.items():
        e2e = {w: [r["pairs"] / r["wall"] for r in got[(t, w)]] for w in (1, 2)}
        steady = {w: [r["steady"] for r in got[(t, w)]] for w in (1, 2)}
        rounds = ", ".join(f"{b / a:.2f}" for a, b in zip(e2e[1], e2e[2]))
        print(f"{t} ({d}): best 1 worker {max(e2e[1]):.2f}, 2 workers {max(e2e[2]):.2f} pairs/s end to end "
              f"({max(e2e[2]) / max(e2e[1]):.2f}x; steady {max(steady[2]) / max(steady[1]):.2f}x); "
              f"2 vs 1 per round: {rounds}")


def _archive(a, tmp: str) -> tuple[Path, float]:
    """The archive to measure on: ``--archive`` if it holds one, else rendered (there, or in ``tmp``)."""
    root = Path(a.archive) if a.archive else Path(tmp)
    t0 = time.perf_counter()
    if not (root / "station.toml").is_file():
        root.mkdir(parents=True, exist_ok=True)
        make_archive(root, a.pairs, a.size)
    return root, time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pairs", type=int, default=64)
    ap.add_argument("--size", type=int, default=960)
    ap.add_argument("--chunk-pairs", type=int, default=8)
    ap.add_argument("--repeat", type=int, default=1,
                    help="run each measurement this often (Ray runs interleaved 1, 2, 1, 2 …) and keep the fastest, "
                         "the least disturbed by other load")
    ap.add_argument("--archive", help="render the archive into this folder and keep it, or reuse the one there")
    ap.add_argument("--against", help="another checkout (its root folder): only the Ray runs, of both, alternately")
    ap.add_argument("--one-ray", type=int, help=argparse.SUPPRESS)  # one Ray run with this many workers (--against)
    a = ap.parse_args()
    if a.one_ray:
        return one_ray(Path(a.archive), a.one_ray, a.chunk_pairs)
    if a.against:
        with tempfile.TemporaryDirectory(prefix="cbh-bench-reprocess-") as tmp:
            root, t_render = _archive(a, tmp)
            print(f"load average at the start: {_loadavg()}; archive: {a.pairs} pairs at {a.size} px "
                  f"(rendered in {t_render:.0f} s); chunks of <= {a.chunk_pairs} pairs")
            return ab_runs(root, Path(a.against), a.repeat, a.chunk_pairs)

    ncpu = os.cpu_count() or 1
    try:
        import torch

        gpu = torch.cuda.is_available()
    except ImportError:
        gpu = False
    counts = [1, 2] + ([16] if ncpu >= 16 else [])
    loaded: list[str] = []

    def note_load(what: str, acc: dict | None) -> None:
        if acc is not None and acc["other"] > OTHER_LOAD_LIMIT * acc["capacity"]:
            loaded.append(f"{what} ({100 * acc['other'] / acc['capacity']:.0f} %)")

    t_all = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="cbh-bench-reprocess-") as tmp:
        root, t_render = _archive(a, tmp)
        print(f"load average at the start: {_loadavg()}")
        print(f"archive: {a.pairs} pairs at {a.size} px over 2 days (rendered in {t_render:.0f} s); "
              f"{ncpu} CPUs; GPU: {'yes' if gpu else 'no'}; chunks of <= {a.chunk_pairs} pairs")

        best = f" (fastest of {a.repeat})" if a.repeat > 1 else ""
        loops = []
        for _ in range(a.repeat):
            with CpuMeter() as m:
                res = plain_loop(root)
            loops.append((res, m.split()))
        (t_loop, loop_steady, n, loop_cpu), split = min(loops, key=lambda x: x[0][0])
        note_load("plain loop", split)
        print(f"plain loop over Pipeline.process (1 process, 1 thread){best}: {n / t_loop:.2f} pairs/s ({t_loop:.1f} s), "
              f"steady {loop_steady:.2f} pairs/s, {1000 * loop_cpu / n:.0f} ms CPU/pair\n    {_cpu_line(split)}")

        t_par, n_par, split = min((parallel_loops(root, 2) for _ in range(a.repeat)), key=lambda x: x[0])
        note_load("2 plain loops", split)
        print(f"2 plain loops at once (2 processes, half the pairs each, no Ray){best}: {n_par / t_par:.2f} pairs/s = "
              f"{n_par / t_par / loop_steady:.2f}x the loop's steady rate (the most 2 workers can give here)"
              f"\n    {_cpu_line(split)}")

        runs: dict[int, dict] = {}
        for _ in range(a.repeat):
            for w in counts:
                r = ray_run(root, w, a.chunk_pairs)
                if w not in runs or r["wall"] < runs[w]["wall"]:
                    runs[w] = r
        for w in counts:
            r = runs[w]
            note_load(f"ray {w}", r["split"])
            what = "worker: one single-threaded actor (1 CPU, OpenCV 1 thread)" if w == 1 else \
                "workers (single-threaded actors)"
            print(f"ray {w:>2} {what}{best}: {r['pairs'] / r['wall']:.2f} pairs/s end to end ({r['wall']:.1f} s), "
                  f"steady {r['steady']:.2f} pairs/s; actors {1000 * r['cpu_per_pair']:.0f} ms CPU/pair steady "
                  f"({r['lead']} lead-in pairs in all); actors wait {r['gap_ms']:.0f} ms between chunks; "
                  f"Ray start {r['ray_start']:.1f} s (apart)\n    {_cpu_line(r['split'])}"
                  + (f"; actors running {100 * r['split']['workers'] / (w * r['wall']):.0f} % of the run (low with little "
                     "other load: actors waiting on the engine)" if r["split"] else ""))
        e2e = {w: runs[w]["pairs"] / runs[w]["wall"] for w in runs}
        print(f"speed-up 2 vs 1 workers: {e2e[2] / e2e[1]:.2f}x end to end, "
              f"{runs[2]['steady'] / runs[1]['steady']:.2f}x steady (goal >= 1.8x, issue 36); the actors' CPU per pair "
              f"{runs[2]['cpu_per_pair'] / runs[1]['cpu_per_pair']:.2f}x that of 1 worker (above 1: the two slow each "
              "other down through shared caches, memory or cores)")
        if 16 in runs:
            print(f"speed-up 16 vs 1 workers: {e2e[16] / e2e[1]:.2f}x end to end, "
                  f"{runs[16]['steady'] / runs[1]['steady']:.2f}x steady (goal >= 12x)")
        else:
            print(f"16 workers: not run ({ncpu} CPUs here)")
        print(f"overhead of 1 Ray worker vs the plain loop: {100 * (t_loop and (n / e2e[1] - t_loop) / t_loop):+.0f} % "
              f"end to end (actor start, pipeline build, lead-in pairs, output files), "
              f"{100 * (loop_steady / runs[1]['steady'] - 1):+.0f} % steady")
        resume_check(root, runs, a.chunk_pairs)
        if gpu:
            r = ray_run(root, min(ncpu, 16), a.chunk_pairs, device="cuda")
            print(f"ray GPU actors ({min(ncpu, 16)} sharing the GPU): {r['pairs'] / r['wall']:.2f} pairs/s end to end, "
                  f"steady {r['steady']:.2f}")
        else:
            print("GPU actors: not run (no CUDA device here)")
    print(f"total {time.perf_counter() - t_all:.0f} s")
    if loaded:
        print(f"WARNING: other processes took more than {100 * OTHER_LOAD_LIMIT:.0f} % of the machine during: "
              f"{', '.join(loaded)}; these rates are not representative: measure again on a quiet machine")


if __name__ == "__main__":
    main()
