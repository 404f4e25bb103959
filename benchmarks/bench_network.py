"""Benchmark: a three-camera station against its two-camera pair, on one frame set.

    python benchmarks/bench_network.py [--size 1920] [--repeat 5] [--scene low-and-high]

Renders the ``unb-lea-network`` station (cam1 + cam2 50 m apart, cam3 630 m north) under the
scene (not timed), warms both pipelines (tables, caches), then times ``--repeat`` runs each of

- ``Pipeline(station, "cam1,cam2").process`` (today's pair),
- ``StationPipeline(station, "cam1,cam2").process`` (the two-camera station: the same pipeline),
- ``StationPipeline(station).process`` (three cameras: the star pairs cam1+cam2, cam1+cam3,
  fused),

and prints the median wall times and the ratios (the variants interleaved), then ``cbh pair``
end to end on two and on three of the images (process start-up, decoding, cached tables). Bars
(issue 24): three cameras ≤ 2.2 × the pair; the two-camera station as fast as the pair.
"""
from __future__ import annotations

import argparse
import statistics
import time


def _median_ms(fn, repeat: int) -> float:
    out = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        out.append((time.perf_counter() - t) * 1000.0)
    return statistics.median(out)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=1920)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--scene", default="low-and-high")
    args = ap.parse_args()

    from cbh.geometry.station import load_station
    from cbh.pipeline import Pipeline
    from cbh.pipeline.network import StationPipeline
    from cbh.presets import station_path
    from cbh.sim import SkySimulator, load_scene

    sim = SkySimulator(load_station(station_path("unb-lea-network")), load_scene(args.scene), size_px=args.size)
    shot = sim.render()
    ims = [shot.views[c].image for c in ("cam1", "cam2", "cam3")]
    t = shot.time_utc
    pair = Pipeline(sim.station, "cam1,cam2")
    two = StationPipeline(sim.station, "cam1,cam2")
    three = StationPipeline(sim.station)
    runs = {
        "pair (Pipeline cam1,cam2)": lambda: pair.process(ims[0], ims[1], t, channels="bgr"),
        "station of two cameras": lambda: two.process(ims[:2], t, channels="bgr"),
        "station of three cameras": lambda: three.process(ims, t, channels="bgr"),
    }
    for fn in runs.values():  # warm-up: tables, caches
        fn()
    times: dict[str, list[float]] = {name: [] for name in runs}
    for _ in range(args.repeat):  # interleaved: the machine's drift hits every variant alike
        for name, fn in runs.items():
            times[name].append(_median_ms(fn, 1))
    ms = {name: statistics.median(v) for name, v in times.items()}
    base = ms["pair (Pipeline cam1,cam2)"]
    for name, v in ms.items():
        print(f"{name:28s} {v:7.0f} ms  ({v / base:.2f} x the pair)")
    r = three.process(ims, t, channels="bgr")
    print("three-camera layers: " + ", ".join(f"{L.height_m:.0f} m" for L in r.layers)
          + f"  (truth: {', '.join(f'{L.height_m:g} m' for L in shot.layers)})")
    print("bar: three cameras <= 2.2 x the pair: " + ("met" if ms["station of three cameras"] <= 2.2 * base else "NOT met"))
    _cli(sim, shot, args.repeat)


def _cli(sim, shot, repeat: int) -> None:
    """`cbh pair` end to end (start-up, decoding, cached tables): two images against three."""
    import subprocess
    import sys
    import tempfile
    from pathlib import Path

    import cv2

    with tempfile.TemporaryDirectory() as d:
        (Path(d) / "station.toml").write_text(sim.station.to_toml())
        files = []
        for c in ("cam1", "cam2", "cam3"):
            files.append(str(Path(d) / f"{c}_20240621T140000Z.jpg"))
            cv2.imwrite(files[-1], shot.views[c].image, [cv2.IMWRITE_JPEG_QUALITY, 92])
        cmd = [sys.executable, "-m", "cbh.cli.main", "pair", "--station", str(Path(d) / "station.toml")]
        wall = {2: [], 3: []}
        for n in (2, 3):  # warm-up: the table cache
            subprocess.run(cmd + files[:n], capture_output=True, check=True)
        for _ in range(repeat):
            for n in (2, 3):
                t = time.perf_counter()
                subprocess.run(cmd + files[:n], capture_output=True, check=True)
                wall[n].append(time.perf_counter() - t)
        two, three = statistics.median(wall[2]), statistics.median(wall[3])
        print(f"cbh pair end to end: two images {two * 1000:.0f} ms, three {three * 1000:.0f} ms ({three / two:.2f} x)")


if __name__ == "__main__":
    main()
