"""Cold start: one `cbh pair` from the shell, against the same pair processed warm in-process.

    python benchmarks/bench_cold_start.py [--repeat 3]

The WAHRSIS pair (../shared/data/wahrsis-2015-10-29, medium exposure) and the simulated unb-lea
pair (1920 px, written to a temporary folder). For each: the warm pair time (median of
``--repeat`` ``Pipeline.process`` calls after one warm-up, in this process), then `cbh pair` as
a user runs it, in a fresh process: once with an empty table cache (``$CBH_CACHE_DIR`` in a
temporary folder: the first call ever for that station) and ``--repeat`` times with the cache
filled. Overhead = wall time of the command − warm pair time: imports, reading the images,
the tables, the first call's allocations and printing. Goal (issue 14): ≤ 1 s.
"""
from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
WAHRSIS = REPO.parent / "shared" / "data" / "wahrsis-2015-10-29"


def warm_ms(station_path: Path, im1: Path, im2: Path, t: str, repeat: int) -> float:
    from cbh import Pipeline, load_station

    pipe = Pipeline(load_station(station_path))
    pipe.process(im1, im2, t)
    runs = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        pipe.process(im1, im2, t)
        runs.append((time.perf_counter() - t0) * 1000.0)
    return statistics.median(runs)


def cli_ms(args: list[str], cache: Path) -> float:
    env = dict(os.environ, CBH_CACHE_DIR=str(cache))
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-m", "cbh.cli.main", "pair", *args], env=env, check=True,
                   stdout=subprocess.DEVNULL)
    return (time.perf_counter() - t0) * 1000.0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        cases = []
        if WAHRSIS.is_dir():
            cases.append(("WAHRSIS (real, LK + DIS)", REPO / "configs" / "wahrsis-2015-10-29.toml",
                          WAHRSIS / "2015-10-29-12-58-01-wahrsis3-med.jpg", WAHRSIS / "2015-10-29-12-58-01-wahrsis4-med.jpg",
                          "2015-10-29T04:58:01Z"))
        from cbh.geometry.station import load_station
        from cbh.presets import station_path
        from cbh.sim import SkySimulator, load_scene
        from cbh.sim.io import write_shot

        sim = SkySimulator(load_station(station_path("unb-lea")), load_scene("two-layers"), size_px=1920)
        shot = sim.render()
        write_shot(shot, tmp / "sim")
        st = tmp / "station.toml"
        st.write_text(sim.station.to_toml())
        f1, f2 = (next((tmp / "sim" / c).glob("*.jpg")) for c in ("cam1", "cam2"))
        cases.append(("simulated 1920 px (LK + sweep)", st, f1, f2, shot.time_utc.isoformat()))
        for name, station, im1, im2, t in cases:
            warm = warm_ms(station, im1, im2, t, args.repeat)
            cli = ["--station", str(station), str(im1), str(im2), "--time", t]
            cache = tmp / f"cache-{len(name)}"
            first = cli_ms(cli, cache)
            again = statistics.median(cli_ms(cli, cache) for _ in range(args.repeat))
            print(f"{name}: warm pair {warm:.0f} ms; `cbh pair` first ever {first:.0f} ms "
                  f"(overhead {first - warm:.0f} ms), cache filled {again:.0f} ms (overhead {again - warm:.0f} ms)")


if __name__ == "__main__":
    main()
