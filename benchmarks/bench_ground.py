"""Ground maps per pair: labels, per-layer cloud maps, shadow map and the sun-blocking answers.

Run from the repository root: python benchmarks/bench_ground.py
(the sample recording's 8 pairs at their recorded working size, the station's default grid).
"""
from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from cbh.actions.export import _shadow, _sun_blocked, pair_ground
from cbh.geometry import ground
from cbh.outputs.record import open_session
from cbh.pipeline.config import PipelineConfig

REPO = Path(__file__).resolve().parents[1]


def main() -> None:
    s = open_session(REPO / "recordings" / "sample-two-layers.mcap")
    st = s.station
    cfg = PipelineConfig.from_dict(s.config, where="recorded pipeline config")
    grid = st.ground
    pairs = [p.result for p in s.pairs()]
    t_lab, t_cloud, t_shadow, t_sun = [], [], [], []
    history = []  # earlier pairs, newest first (what the export keeps)
    for res in pairs:
        t0 = time.perf_counter()
        pg = pair_ground(st, cfg.masks, res)
        t1 = time.perf_counter()
        ground.cloud_maps(pg.camera, pg.labels, pg.heights, grid)
        t2 = time.perf_counter()
        _shadow(pg, grid)
        t3 = time.perf_counter()
        _sun_blocked(st, pg, history)
        t4 = time.perf_counter()
        history.insert(0, pg)
        t_lab.append(t1 - t0), t_cloud.append(t2 - t1), t_shadow.append(t3 - t2), t_sun.append(t4 - t3)
    ms = lambda v: 1000 * float(np.median(v))  # noqa: E731
    H, W = pairs[0].cloud_masks[pairs[0].cameras[0]].shape
    print(f"{len(pairs)} pairs, mask {W}x{H}, grid {grid.n}x{grid.n} ({grid.resolution_m:g} m), "
          f"{len(pairs[0].layers)} layers; medians per pair:")
    print(f"  labels (usable sky, sun disk, layer of each pixel) {ms(t_lab):.1f} ms")
    print(f"  cloud maps (all layers)                            {ms(t_cloud):.1f} ms")
    print(f"  shadow map                                         {ms(t_shadow):.1f} ms")
    print(f"  sun blocked now, +1, +5, +10 min                   {ms(t_sun):.1f} ms")


if __name__ == "__main__":
    main()
