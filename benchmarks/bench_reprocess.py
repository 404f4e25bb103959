"""`cbh reprocess` throughput on Ray: pairs/s for 1 and 2 workers (and 16 / GPU where available),
and the overhead against a plain loop over `Pipeline.process` on the same files.

    python benchmarks/bench_reprocess.py [--pairs 96] [--size 480] [--chunk-pairs 16]

A simulated two-day archive (one folder per camera per day) is rendered into a temporary
folder. Each Ray run is end to end as a user sees it, minus Ray's own start (printed apart,
paid once per command): actors start and build their pipelines, every pair is processed,
the daily NetCDF + Parquet files and the index are written. "steady" is the rate once every
actor has processed its first chunk (process start-up and the first pair's warm-up
excluded). The plain loop runs in this process with OpenCV limited to one thread, as in an
actor (one CPU each), and hands the motion state from pair to pair as reprocess does (which
also re-processes one lead-in pair per chunk), so the comparison isolates the engine's overhead.
"""
from __future__ import annotations

import argparse
import os

# one BLAS/OpenMP thread in the plain loop too, as Ray gives each one-CPU actor
for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")
import shutil
import tempfile
import time
from datetime import datetime, timedelta, timezone
from pathlib import Path


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


def plain_loop(root: Path) -> tuple[float, float, int]:
    import cv2

    from cbh.actions.archive import load_images
    from cbh.actions.reprocess import ReprocessOptions, load_jobs, plan_reprocess
    from cbh.pipeline import Pipeline

    cv2.setNumThreads(1)
    jobs = load_jobs([root / "station.toml"], [f"cam1={root / 'cam1'}", f"cam2={root / 'cam2'}"])
    plan = plan_reprocess(jobs, ReprocessOptions(out=root / "unused"))
    pairs = [p for d in plan.days for p in d.pairs]
    t0 = time.perf_counter()
    from cbh.actions.run import MotionChain

    pipe, chain = Pipeline(jobs[0].station), MotionChain()  # the same work as reprocess: motion state too
    t1 = None
    for p in pairs:
        imgs = load_images([p.frame1, p.frame2])
        r = pipe.process(imgs[p.frame1], imgs[p.frame2], p.time_utc, channels="bgr", previous=chain.previous(p.time_utc))
        chain.keep(r)
        t1 = t1 or time.perf_counter()  # after the first pair (warm-up)
    t_end = time.perf_counter()
    return t_end - t0, (len(pairs) - 1) / (t_end - t1), len(pairs)


def ray_run(root: Path, workers: int, chunk_pairs: int, device: str = "cpu") -> tuple[float, float, int]:
    from cbh.actions.reprocess import reprocess

    out = root / f"out-{workers}-{device}"
    shutil.rmtree(out, ignore_errors=True)
    first_done: dict[int, float] = {}
    n_after = [0]
    t0 = time.perf_counter()

    def ev(e):
        if e["event"] == "chunk":
            if e["pid"] not in first_done:
                first_done[e["pid"]] = time.perf_counter()
            elif len(first_done) >= workers:
                n_after[0] += e["pairs"]

    _, s = reprocess([root / "station.toml"], [f"cam1={root / 'cam1'}", f"cam2={root / 'cam2'}"], out=out,
                     workers=workers, chunk_pairs=chunk_pairs, device=device, on_event=ev)
    t_end = time.perf_counter()
    steady = n_after[0] / (t_end - max(first_done.values())) if len(first_done) >= workers and n_after[0] else float("nan")
    assert s.failures == 0 and s.pairs_processed > 0
    return t_end - t0, steady, s.pairs_processed


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pairs", type=int, default=96)
    ap.add_argument("--size", type=int, default=480)
    ap.add_argument("--chunk-pairs", type=int, default=16)
    a = ap.parse_args()
    from cbh.actions.reprocess import start_ray

    ncpu = os.cpu_count() or 1
    try:
        import torch

        gpu = torch.cuda.is_available()
    except ImportError:
        gpu = False
    counts = [1, 2] + ([16] if ncpu >= 16 else [])
    with tempfile.TemporaryDirectory(prefix="cbh-bench-reprocess-") as tmp:
        root = make_archive(Path(tmp), a.pairs, a.size)
        t_loop, loop_steady, n = plain_loop(root)
        print(f"archive: {n} pairs at {a.size} px over 2 days; {ncpu} CPUs; GPU: {'yes' if gpu else 'no'}")
        print(f"plain loop over Pipeline.process (1 thread): {n / t_loop:.2f} pairs/s ({t_loop:.1f} s), "
              f"steady {loop_steady:.2f} pairs/s")
        t0 = time.perf_counter()
        start_ray(workers=max(counts), device="cuda" if gpu else "cpu")
        print(f"Ray start (once per command): {time.perf_counter() - t0:.1f} s")
        rates, steadies = {}, {}
        for w in counts:
            t, steady, m = ray_run(root, w, a.chunk_pairs)
            rates[w], steadies[w] = m / t, steady
            print(f"ray {w:>2} worker(s): {m / t:.2f} pairs/s end to end ({t:.1f} s), steady {steady:.2f} pairs/s")
        print(f"speed-up 2 vs 1 workers: {rates[2] / rates[1]:.2f}x end to end, {steadies[2] / steadies[1]:.2f}x steady "
              "(goal >= 1.7x)")
        if 16 in rates:
            print(f"speed-up 16 vs 1 workers: {rates[16] / rates[1]:.2f}x end to end, {steadies[16] / steadies[1]:.2f}x "
                  "steady (goal >= 12x)")
        else:
            print(f"16 workers: not run ({ncpu} CPUs here)")
        print(f"overhead of 1 Ray worker vs the plain loop: {100 * (n / rates[1] - t_loop) / t_loop:+.0f} % end to end "
              f"(actor start, pipeline build, output files), {100 * (loop_steady / steadies[1] - 1):+.0f} % steady")
        if gpu:
            t, steady, m = ray_run(root, min(ncpu, 16), a.chunk_pairs, device="cuda")
            print(f"ray GPU actors ({min(ncpu, 16)} sharing the GPU): {m / t:.2f} pairs/s end to end, steady {steady:.2f}")
        else:
            print("GPU actors: not run (no CUDA device here)")
        import ray

        ray.shutdown()


if __name__ == "__main__":
    main()
