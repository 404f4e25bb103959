"""Sustained pairs per second of the live service with recording and export on.

Frames are simulated once (a few distinct pairs, 1920 x 1920 by default) and then fed
endlessly with advancing time stamps, so the simulator's own cost is not counted: what is
measured is the service as on the roof: JPEG bytes in → decode → pipeline → MCAP (images as
received, masks, points, height map …) + layer export (+ status records).

    python benchmarks/bench_service.py                      # 1920 px, 20 pairs, in-memory frames
    python benchmarks/bench_service.py --via mjpeg          # through the loopback HTTP camera (MJPEG)
    python benchmarks/bench_service.py --size 960 --pairs 30
    python benchmarks/bench_service.py --no-ahead           # without preparing the next pair ahead

Prints pairs/s, mean time per pair, the pipeline's share, and the bytes recorded per pair.
"""
from __future__ import annotations

import argparse
import tempfile
import time
from datetime import timedelta
from pathlib import Path


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--size", type=int, default=1920, help="image width [px]")
    ap.add_argument("--pairs", type=int, default=20, help="pairs to process (after 2 warm-up pairs)")
    ap.add_argument("--distinct", type=int, default=3, help="distinct simulated pairs to cycle through")
    ap.add_argument("--via", choices=("memory", "mjpeg"), default="memory", help="frame source")
    ap.add_argument("--export", default="parquet", choices=("csv", "parquet"))
    ap.add_argument("--no-ahead", action="store_true", help="no look-ahead (each pair prepared when its turn comes)")
    a = ap.parse_args()

    from cbh.sim.camera_server import CameraServer
    from cbh.pipeline import Pipeline, PipelineConfig
    from cbh.presets import scene_path, station_path
    from cbh.outputs.record import McapRecorder
    from cbh.outputs.export import LayerExporter
    from cbh.result import Frame
    from cbh.live.service import Service, ServiceConfig
    from cbh.sim import SkySimulator, load_scene
    from cbh.live.sources import MemorySource, open_source
    from cbh.geometry.station import load_station

    t = time.perf_counter()
    scene = load_scene(scene_path())
    sim = SkySimulator(load_station(station_path()), scene, size_px=a.size)
    st = sim.station
    shots = []
    for k in range(a.distinct):
        tk = scene.time_utc + timedelta(seconds=10 * k)
        shots.append({c: sim.frame(c, tk).encoded for c in ("cam1", "cam2")})
    print(f"simulated {a.distinct} distinct pairs at {a.size} px in {time.perf_counter() - t:.1f} s "
          f"(JPEG {sum(len(b) for b in shots[0].values()) / 2e6:.2f} MB per image)")

    n = a.pairs + 2
    pcfg = PipelineConfig.from_dict(st.sections.get("pipeline", {}))
    pipe = Pipeline(st, "cam1,cam2", pcfg)
    pipe_s: list[float] = []

    prep_s: list[float] = []

    def prepare(f1, f2):  # the first half, run ahead on the next pair (non-live sources)
        t0 = time.perf_counter()
        p = pipe.prepare(f1.image, f2.image, f1.time_utc, channels="bgr")
        prep_s.append(time.perf_counter() - t0)
        return p

    def process(f1, f2, prepared=None):
        t0 = time.perf_counter()
        p = prepared.result() if prepared is not None else prepare(f1, f2)
        r = pipe.finish(p)
        pipe_s.append(time.perf_counter() - t0)
        return r

    done_t: list[float] = []

    def on_pair(stats, result):
        if result is not None:
            done_t.append(time.perf_counter())

    with tempfile.TemporaryDirectory() as tmp:
        rec = McapRecorder(Path(tmp) / "bench.mcap", st, pcfg.to_dict())
        exp = LayerExporter(Path(tmp) / f"bench.{a.export}", st)
        server = None
        if a.via == "memory":
            srcs = [MemorySource(c, [Frame(c, scene.time_utc + timedelta(seconds=10 * k), None,
                                           shots[k % a.distinct][c], "jpeg", k) for k in range(n)])
                    for c in ("cam1", "cam2")]
            cfg = ServiceConfig(frames=n)
        else:
            server = CameraServer(lambda c, tt: shots[int((tt - scene.time_utc).total_seconds()) % a.distinct][c],
                                  ["cam1", "cam2"], fps=4.0, step_s=1.0, start_utc=scene.time_utc).start()
            srcs = [open_source(c, server.url(c), decode=False) for c in ("cam1", "cam2")]
            cfg = ServiceConfig(frames=n)
        t_start = time.perf_counter()
        stats = Service(srcs, process, [rec, exp], cfg, on_pair=on_pair,
                        prepare=None if a.no_ahead else prepare).run(handle_signals=False)
        if server is not None:
            server.close()
        size = sum(p.stat().st_size for p in rec.paths)
    steady = done_t[2:]
    rate = (len(steady) - 1) / (steady[-1] - steady[0]) if len(steady) > 1 else float("nan")
    pipe_mean = sum(pipe_s[2:]) / max(1, len(pipe_s) - 2)  # from the call (incl. waiting for a look-ahead) to the result
    prep_mean = sum(prep_s[2:]) / max(1, len(prep_s) - 2)
    print(f"size {a.size} px, via {a.via}: {stats.pairs_processed} pairs "
          f"({stats.pairs_dropped} dropped), first pair after {done_t[0] - t_start:.2f} s")
    print(f"sustained: {rate:.2f} pairs/s ({1 / rate:.2f} s per pair; pipeline {pipe_mean:.2f} s = "
          f"{100 * pipe_mean * rate:.0f} % of which the prepared first half {prep_mean:.2f} s ran ahead"
          f"{' (look-ahead off)' if a.no_ahead else ''}), recording {size / stats.pairs_processed / 1e6:.2f} MB per pair")
    print(f"a 10 s cadence would use {100 / (10 * rate):.0f} % of this machine")


if __name__ == "__main__":
    main()
