"""Benchmark: what cloud motion and the clock-offset estimate add to the per-pair time.

    python benchmarks/bench_motion.py [--size 1920] [--repeat 5] [--scene two-layers] [--clock-offset 3]

Renders a short sequence (10 s apart; not timed) and warms a Pipeline up on it, so the last
pair's ``previous`` state carries frames, layer motion and the offset history. Then times, on
the same last pair, ``--repeat`` times each:

- *without*: ``process(img1, img2, t)`` (no previous pair: no motion, no offset);
- *with*: ``process(img1, img2, t, previous=state)`` (tracks in both cameras, per-layer motion,
  this pair's offset estimate; with ``--clock-offset``, camera 2 captures that late and the
  compensation of camera 2 runs too, reported on its own line).

Prints the median stage times of both, the wall times, and the ``motion`` (and
``compensation``) stage against the pair without [ms, %]. Bar (issue 13): motion and offset
estimation add ≤ 15 % to the per-pair time. On a loaded machine compare the stage times: the
wall-time difference then carries the load's noise.
"""
from __future__ import annotations

import argparse
import statistics
import time
from datetime import timedelta


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=1920)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--scene", default="two-layers")
    ap.add_argument("--clock-offset", type=float, default=0.0, help="camera 2 captures this late [s]")
    ap.add_argument("--warmup-pairs", type=int, default=3)
    args = ap.parse_args()

    from cbh.geometry.station import load_station
    from cbh.pipeline import Pipeline
    from cbh.presets import station_path
    from cbh.sim import SkySimulator, load_scene
    from cbh.sim.scene import with_clock_offsets

    sc = load_scene(args.scene)
    if args.clock_offset:
        sc = with_clock_offsets(sc, [f"cam2={args.clock_offset}"])
    sim = SkySimulator(load_station(station_path("unb-lea")), sc, size_px=args.size)
    shots = [sim.render(sc.time_utc + timedelta(seconds=10.0 * i)) for i in range(args.warmup_pairs + 1)]
    pipe = Pipeline(sim.station)
    state = None
    for s in shots[:-1]:  # warm-up: caches, and the state of the pair before the timed one
        state = pipe.process(s.views["cam1"].image, s.views["cam2"].image, s.time_utc, channels="bgr", previous=state).state
    last = shots[-1]
    im1, im2, t = last.views["cam1"].image, last.views["cam2"].image, last.time_utc
    print(f"pair {im1.shape[1]}x{im1.shape[0]}, scene {sc.name}, camera 2 clock offset {args.clock_offset:+g} s, "
          f"{args.repeat} runs each (medians)")
    without, with_ = [], []
    for _ in range(args.repeat):  # interleaved, so that machine load hits both alike
        t0 = time.perf_counter()
        r0 = pipe.process(im1, im2, t, channels="bgr")
        without.append(((time.perf_counter() - t0) * 1000, r0.timing_ms))
        t0 = time.perf_counter()
        r = pipe.process(im1, im2, t, channels="bgr", previous=state)
        with_.append(((time.perf_counter() - t0) * 1000, r.timing_ms))
    med = lambda runs, k: statistics.median(x[1].get(k, 0.0) for x in runs)  # noqa: E731
    w0 = statistics.median(x[0] for x in without)
    w1 = statistics.median(x[0] for x in with_)
    stages = list(dict.fromkeys([*without[0][1], *with_[0][1]]))
    print(f"  {'stage [ms]':<16} {'without':>9} {'with':>9}")
    for k in stages:
        print(f"  {k:<16} {med(without, k):9.1f} {med(with_, k):9.1f}")
    print(f"  {'wall':<16} {w0:9.1f} {w1:9.1f}   (+{100 * (w1 - w0) / w0:.1f} %)")
    mot, comp = med(with_, "motion"), med(with_, "compensation")
    print(f"motion + offset estimation (stage 'motion': tracks in both cameras, per-layer motion, offset): "
          f"{mot:.1f} ms = {100 * mot / w0:.1f} % of the pair without")
    if args.clock_offset:
        print(f"compensation of camera 2 (stage 'compensation'): {comp:.1f} ms = {100 * comp / w0:.1f} %")
    print("layers: " + ", ".join(
        f"{l.height_m:.0f} m ({l.motion_east_ms:+.2f}, {l.motion_north_ms:+.2f}) m/s" for l in r.layers)
        + f"   clock offset {r.diagnostics['clock_offset_s']:+.2f} s")
    print("truth:  " + ", ".join(f"{l.height_m:.0f} m ({l.wind_ms[0]:+.2f}, {l.wind_ms[1]:+.2f}) m/s" for l in sc.layers))


if __name__ == "__main__":
    main()
