"""Speed of the synthetic sky (issue 3 bar: a 1920 x 1920 pair in <= 2 s on 2 cores).

Run: python benchmarks/bench_sim.py [--scenes two-layers,three-layers] [--sizes 1920,480] [--repeat 5]

Prints, per scene and size, the one-off set-up time (ray maps, pyramid grids, textures) and
the median / best wall time to render one frame pair (both cameras, with ground truth), plus
the JPEG encoding time of the pair (what SkySimulator.frame adds).
"""
from __future__ import annotations

import argparse
import statistics
import time


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", default="two-layers,three-layers,overcast")
    ap.add_argument("--sizes", default="1920,480")
    ap.add_argument("--repeat", type=int, default=5)
    args = ap.parse_args()

    import cv2

    from cbh.imageio import encode_jpeg
    from cbh.presets import station_path
    from cbh.sim import SkySimulator, load_scene
    from cbh.geometry.station import load_station

    station = load_station(station_path())
    print(f"cv2 threads: {cv2.getNumThreads()}")
    print(f"{'scene':<16} {'size':>5} {'setup_s':>8} {'pair_median_s':>14} {'pair_best_s':>12} {'jpeg_pair_s':>12}")
    for scene_name in args.scenes.split(","):
        scene = load_scene(scene_name)
        for size in (int(s) for s in args.sizes.split(",")):
            t0 = time.perf_counter()
            sim = SkySimulator(station, scene, size_px=size)
            setup = time.perf_counter() - t0
            sim.render()  # warm-up: imports, sun maps, caches
            times = []
            for i in range(args.repeat):
                t = scene.time_utc.replace(second=(i * 10) % 60)
                tic = time.perf_counter()
                shot = sim.render(t)
                times.append(time.perf_counter() - tic)
            tic = time.perf_counter()
            for v in shot.views.values():
                encode_jpeg(v.image, scene.image.jpeg_quality)
            jpeg = time.perf_counter() - tic
            print(f"{scene_name:<16} {size:>5} {setup:>8.2f} {statistics.median(times):>14.3f} "
                  f"{min(times):>12.3f} {jpeg:>12.3f}", flush=True)


if __name__ == "__main__":
    main()
