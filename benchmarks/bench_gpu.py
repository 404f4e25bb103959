"""Benchmark for a lent CUDA machine (issue 36): a 1920 px pair end to end on the device at batch
sizes 1, 8 and 32, its parity with the CPU, and `cbh reprocess` on a few hundred pairs.

    python benchmarks/bench_gpu.py [--pairs 240] [--distinct 48] [--size 1920] [--json OUT.json]

Prints each number as it is measured (a run cut short still says what it got) and, with
``--json``, writes them all. Without CUDA it says so and exits 0 (a benchmark, not a test).

- **single pairs**: ``Pipeline(device="cuda").process`` on one pair, median of 7 after a warm-up,
  with ``timing_ms`` per stage; the same on the CPU backend for the ratio.
- **batches**: ``Pipeline.process_batch`` on 8 and 32 copies of the pair (pairs/s).
- **parity**: layers and the height map of the CUDA run against the CPU run (median relative
  difference where both measured).
- **reprocess**: an archive of ``--pairs`` pairs (``--distinct`` rendered skies, each written at
  several times: rendering is not what is measured), processed by ``cbh reprocess`` on a private
  Ray with GPU actors sharing the device, then with CPU actors on every core; pairs/s end to end
  and steady (after every actor's first chunk).
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from datetime import datetime, timedelta, timezone
from pathlib import Path

RESULTS: dict = {}
_JSON: list[Path] = []


def note(key: str, value, text: str) -> None:
    RESULTS[key] = value
    print(text, flush=True)
    if _JSON:
        _JSON[0].write_text(json.dumps(RESULTS, indent=1, default=str))


def _render_one(args):
    k, size, flat = args
    from cbh.geometry.station import load_station
    from cbh.presets import scene_path, station_path
    from cbh.sim import SkySimulator, load_scene
    from cbh.sim.io import write_shot

    sim = SkySimulator(load_station(station_path()), load_scene(scene_path("two-layers")), size_px=size)
    t = datetime(2024, 6, 21, 11, tzinfo=timezone.utc) + timedelta(seconds=30 * k)
    write_shot(sim.render(t), Path(flat) / f"s{k}")
    return k


def make_archive(root: Path, pairs: int, distinct: int, size: int) -> Path:
    """``distinct`` skies rendered in parallel, copied to ``pairs`` pairs 30 s apart (one day)."""
    from cbh.geometry.station import load_station
    from cbh.presets import scene_path, station_path
    from cbh.sim import SkySimulator, load_scene
    from cbh.sim.io import image_path

    sim = SkySimulator(load_station(station_path()), load_scene(scene_path("two-layers")), size_px=size)
    (root / "station.toml").write_text(sim.station.to_toml())  # the lens scaled to the images' size
    flat = root / "flat"
    with ProcessPoolExecutor(min(os.cpu_count() or 1, 16)) as ex:
        list(ex.map(_render_one, [(k, size, str(flat)) for k in range(distinct)]))
    srcs = {(k, cam): sorted((flat / f"s{k}" / cam).glob("*.jpg"))[0] for k in range(distinct) for cam in ("cam1", "cam2")}
    t0 = datetime(2024, 6, 21, 11, tzinfo=timezone.utc)
    for i in range(pairs):
        t = t0 + timedelta(seconds=30 * i)
        for cam in ("cam1", "cam2"):
            src = srcs[(i % distinct, cam)]
            dst = image_path(root / cam, t.strftime("%Y-%m-%d"), t)  # <root>/<cam>/<day>/<day>_<tag>.jpg
            dst = dst.with_name(f"{cam}_{dst.name.split('_', 1)[1]}")
            dst.parent.mkdir(parents=True, exist_ok=True)
            shutil.copy(src, dst)
    shutil.rmtree(flat)
    return root


def single_pairs(size: int, devices=("cuda", "cpu")) -> None:
    import numpy as np

    from cbh.geometry.station import load_station
    from cbh.pipeline import Pipeline
    from cbh.presets import scene_path, station_path
    from cbh.sim import SkySimulator, load_scene

    sim = SkySimulator(load_station(station_path()), load_scene(scene_path("two-layers")), size_px=size)
    shot = sim.render()
    im1, im2 = shot.views["cam1"].image, shot.views["cam2"].image
    truth = shot.truth().get("layers")
    out = {}
    for dev in devices:
        t = time.perf_counter()
        pipe = Pipeline(sim.station, device=dev)
        r = pipe.process(im1, im2, shot.time_utc, channels="bgr")
        first = (time.perf_counter() - t) * 1000
        walls, stages = [], []
        for _ in range(7):
            t = time.perf_counter()
            r = pipe.process(im1, im2, shot.time_utc, channels="bgr")
            walls.append((time.perf_counter() - t) * 1000)
            stages.append(r.timing_ms)
        med = {s: round(statistics.median(x[s] for x in stages), 1) for s in stages[0]}
        out[dev] = r
        note(f"single_{dev}", {"first_ms": round(first), "median_ms": round(statistics.median(walls), 1), "stages": med,
                               "layers_m": [round(L.height_m, 1) for L in r.layers]},
             f"{dev}: first pair {first:.0f} ms, then median {statistics.median(walls):.1f} ms/pair; "
             f"layers {[round(L.height_m) for L in r.layers]}; stages {med}")
        if dev == devices[0]:
            for b in (1, 8, 32):
                t = time.perf_counter()
                pipe.process_batch([(im1, im2, shot.time_utc)] * b, channels="bgr")
                dt = time.perf_counter() - t
                note(f"batch_{b}_{dev}", b / dt, f"{dev} process_batch of {b}: {b / dt:.2f} pairs/s ({dt * 1000:.0f} ms)")
    rc, rn = out[devices[0]], out[devices[-1]]
    hc, hn = rc.height_map, rn.height_map
    both = np.isfinite(hc) & np.isfinite(hn)
    rel = float(np.median(np.abs(hc[both] - hn[both]) / hn[both])) if both.any() else float("nan")
    note("parity", {"layers_cuda": [L.height_m for L in rc.layers],
                    "layers_cpu": [L.height_m for L in rn.layers], "heightmap_median_rel": rel,
                    "both_measured_share": float(both.mean()), "truth": truth},
         f"parity: layers cuda {[round(L.height_m, 1) for L in rc.layers]} cpu "
         f"{[round(L.height_m, 1) for L in rn.layers]}; height map median rel diff {rel:.2e} "
         f"over {100 * both.mean():.1f} % of the grid")


def reprocess_runs(root: Path, workers: int, device: str, chunk_pairs: int) -> None:
    from cbh.actions.reprocess import reprocess, start_ray

    out = root / f"out-{device}-{workers}"
    first: dict[int, float] = {}
    n_after = [0]

    def ev(e):
        if e["event"] == "chunk":
            if e["pid"] not in first:
                first[e["pid"]] = time.perf_counter()
            elif len(first) >= workers:
                n_after[0] += e["pairs"]

    t0 = time.perf_counter()
    start_ray(workers=workers, device=device)
    t_ray = time.perf_counter() - t0
    import ray  # after start_ray: it sets Ray's environment (RAY_AUTH_MODE …) before Ray is imported

    try:
        t0 = time.perf_counter()
        _, s = reprocess([root / "station.toml"], [f"cam1={root / 'cam1'}", f"cam2={root / 'cam2'}"], out=out,
                         workers=workers, chunk_pairs=chunk_pairs, device=device, on_event=ev)
        wall = time.perf_counter() - t0
    finally:
        ray.shutdown()
    steady = n_after[0] / (t0 + wall - max(first.values())) if len(first) >= workers and n_after[0] else float("nan")
    note(f"reprocess_{device}_{workers}", {"pairs": s.pairs_processed, "failures": s.failures, "wall_s": wall,
                                           "pairs_per_s": s.pairs_processed / wall, "steady_pairs_per_s": steady,
                                           "ray_start_s": t_ray},
         f"cbh reprocess, {workers} {device} actors: {s.pairs_processed} pairs ({s.failures} failed) in {wall:.1f} s = "
         f"{s.pairs_processed / wall:.2f} pairs/s end to end, steady {steady:.2f} pairs/s; Ray start {t_ray:.1f} s apart")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pairs", type=int, default=240)
    ap.add_argument("--distinct", type=int, default=48)
    ap.add_argument("--size", type=int, default=1920)
    ap.add_argument("--chunk-pairs", type=int, default=8)
    ap.add_argument("--workers", type=int, default=16)
    ap.add_argument("--json", type=Path)
    ap.add_argument("--skip-single", action="store_true")
    a = ap.parse_args()
    if a.json:
        _JSON.append(a.json)
    import torch

    if not torch.cuda.is_available():
        print("no CUDA device here: nothing measured")
        return
    note("hardware", {"gpu": torch.cuda.get_device_name(0), "torch": torch.__version__, "cpus": os.cpu_count(),
                      "python": sys.version.split()[0]},
         f"{torch.cuda.get_device_name(0)}, torch {torch.__version__}, {os.cpu_count()} CPUs, Python {sys.version.split()[0]}")
    with tempfile.TemporaryDirectory(prefix="cbh-bench-gpu-") as tmp:
        t = time.perf_counter()
        root = make_archive(Path(tmp), a.pairs, a.distinct, a.size)
        note("archive_s", time.perf_counter() - t, f"archive: {a.pairs} pairs ({a.distinct} distinct skies) at {a.size} px "
             f"in {time.perf_counter() - t:.0f} s")
        if not a.skip_single:
            single_pairs(a.size)
        reprocess_runs(root, a.workers, "cuda", a.chunk_pairs)
        reprocess_runs(root, a.workers, "cpu", a.chunk_pairs)


if __name__ == "__main__":
    main()
