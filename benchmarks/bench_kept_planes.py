"""The sweep's kept plane tables (``matching.sweep.map_cache_mb``), on and off, in one process.

    python benchmarks/bench_kept_planes.py                       # two-layers, 1920 px, 15 rounds
    python benchmarks/bench_kept_planes.py --scene three-layers --rounds 9

Two pipelines on the same station and pair, one keeping its planes' remap tables between pairs
and one not, are run alternately (so load on a shared machine hits both alike); printed: the
median pair and sweep time of each, whether the results are bit-identical, and what the process
keeps.
"""
from __future__ import annotations

import argparse
import statistics
import time
from dataclasses import replace


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="two-layers")
    ap.add_argument("--size", type=int, default=1920)
    ap.add_argument("--rounds", type=int, default=15)
    ap.add_argument("--mb", type=float, default=256.0, help="the budget of the pipeline that keeps planes [MB]")
    a = ap.parse_args()

    import numpy as np

    from cbh.geometry.station import load_station
    from cbh.pipeline import Pipeline
    from cbh.pipeline import sweep as S
    from cbh.presets import station_path
    from cbh.sim import SkySimulator, load_scene

    sim = SkySimulator(load_station(station_path("unb-lea")), load_scene(a.scene), size_px=a.size)
    shot = sim.render()
    pair = (shot.views["cam1"].image, shot.views["cam2"].image, shot.time_utc)
    base = Pipeline(sim.station).config

    def with_budget(mb):
        sw = replace(base.matching.sweep, map_cache_mb=mb)
        return Pipeline(sim.station, config=replace(base, matching=replace(base.matching, sweep=sw)))

    pipes = {"off": with_budget(0.0), "on": with_budget(a.mb)}
    first = {k: p.process(*pair, channels="bgr") for k, p in pipes.items()}  # tables built; "on" keeps from now
    total, sweep, last = {k: [] for k in pipes}, {k: [] for k in pipes}, {}
    for _ in range(a.rounds):
        for k, p in pipes.items():
            t0 = time.perf_counter()
            last[k] = p.process(*pair, channels="bgr")
            total[k].append(1e3 * (time.perf_counter() - t0))
            sweep[k].append(last[k].timing_ms["match_sweep"])
    same = all(np.array_equal(first["off"].height_map, r.height_map, equal_nan=True)
               and [L.height_m for L in first["off"].layers] == [L.height_m for L in r.layers] for r in last.values())
    med = statistics.median
    print(f"{a.scene}, {a.size} px, {a.rounds} rounds alternating (median):")
    for k in pipes:
        print(f"  planes kept {k:3s}: pair {med(total[k]):6.1f} ms, sweep {med(sweep[k]):6.1f} ms")
    print(f"  results bit-identical: {same}; the process keeps {len(S._KEPT.items)} planes, {S._KEPT.bytes / 1e6:.0f} MB")


if __name__ == "__main__":
    main()
