"""Accuracy of per-layer motion, heights and camera 2's clock offset on a simulated sequence.

    python benchmarks/eval_motion.py DIR            # a folder written by `cbh simulate`
    python benchmarks/eval_motion.py --size 960 --frames 5 --cadence-s 10 --clock-offset 3

With DIR, reads the folder as ``cbh run --source cam1=DIR/cam1 --source cam2=DIR/cam2
--cadence-s 0`` does (JPEG files, times from the names, the run's MotionChain) and scores every
pair against ``DIR/truth/<time>.json``; without, renders the sequence first (``cbh simulate``
with the given options, into a temporary folder). Prints per pair and layer: height error [%],
speed error [%], direction error [deg], and the clock offset; then the worst values over the
pairs that have motion.
"""
from __future__ import annotations

import argparse
import json
import math
import tempfile
from pathlib import Path


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dir", nargs="?", type=Path)
    ap.add_argument("--scene", default="two-layers")
    ap.add_argument("--size", type=int, default=960)
    ap.add_argument("--frames", type=int, default=5)
    ap.add_argument("--cadence-s", type=float, default=10.0)
    ap.add_argument("--clock-offset", type=float, default=0.0, help="camera 2 captures this late [s]")
    args = ap.parse_args()

    tmp = None
    d = args.dir
    if d is None:
        from cbh.cli.main import main as cbh

        tmp = tempfile.TemporaryDirectory()
        d = Path(tmp.name)
        argv = ["simulate", "--scene", args.scene, "--out", str(d), "--frames", str(args.frames),
                "--cadence-s", str(args.cadence_s), "--size", str(args.size)]
        if args.clock_offset:
            argv += ["--clock-offset", f"cam2={args.clock_offset}"]
        assert cbh(argv) == 0
    from cbh.actions.run import MotionChain
    from cbh.timeutil import time_from_name
    from cbh.geometry.station import load_station
    from cbh.pipeline import Pipeline
    from cbh.sim.io import time_tag

    st = load_station(d / "station.toml")
    pipe = Pipeline(st)
    chain = MotionChain()
    names = [c.name for c in (pipe.cam1_full, pipe.cam2_full)]
    files = [sorted((d / n).glob(f"{n}_*")) for n in names]
    worst = {"height_pct": 0.0, "speed_pct": 0.0, "dir_deg": 0.0, "offset_s": 0.0}
    missing = 0
    for f1, f2 in zip(*files):
        t = time_from_name(f1.name)
        r = pipe.process(f1, f2, t, previous=chain.previous(t))
        chain.keep(r)
        truth = json.loads((d / "truth" / f"{time_tag(t)}.json").read_text())
        from datetime import datetime

        cap = {k: datetime.fromisoformat(v["capture_time_utc"].replace("Z", "+00:00"))
               for k, v in truth["cameras"].items()}
        true_off = (cap[names[1]] - cap[names[0]]).total_seconds()
        off = r.diagnostics["clock_offset_s"]
        line = [f"{time_tag(t)}  offset {off:+.2f} s (true {true_off:+.2f})"]
        moving = math.isfinite(r.diagnostics["motion_dt_s"])
        if moving:
            worst["offset_s"] = max(worst["offset_s"], abs(off - true_off) if math.isfinite(off) else math.inf)
        for tl in truth["layers"]:
            h, (we, wn) = tl["height_m"], tl["wind_ms"]
            ls = [l for l in r.layers if abs(math.log(l.height_m / h)) < 0.15]
            if not ls:
                line.append(f"| {h:.0f} m: not found")
                missing += moving
                continue
            L = ls[0]
            eh = 100 * (L.height_m / h - 1)
            line.append(f"| {h:.0f} m: {L.height_m:.0f} m ({eh:+.2f} %)")
            if moving:
                worst["height_pct"] = max(worst["height_pct"], abs(eh))
            if math.isfinite(L.motion_east_ms) and math.hypot(we, wn) < 0.1:  # a calm layer: no relative error
                line.append(f"(calm: {math.hypot(L.motion_east_ms, L.motion_north_ms):.2f} m/s measured)")
            elif math.isfinite(L.motion_east_ms):
                es = 100 * (math.hypot(L.motion_east_ms, L.motion_north_ms) / math.hypot(we, wn) - 1)
                ed = math.degrees(math.atan2(L.motion_east_ms, L.motion_north_ms) - math.atan2(we, wn))
                ed = (ed + 180) % 360 - 180
                worst["speed_pct"] = max(worst["speed_pct"], abs(es))
                worst["dir_deg"] = max(worst["dir_deg"], abs(ed))
                line.append(f"({L.motion_east_ms:+.2f}, {L.motion_north_ms:+.2f}) m/s, speed {es:+.2f} %, dir {ed:+.2f} deg")
        print(" ".join(line))
    print(f"worst over the pairs with motion: height {worst['height_pct']:.2f} %, speed {worst['speed_pct']:.2f} %, "
          f"direction {worst['dir_deg']:.2f} deg, offset error {worst['offset_s']:.2f} s; layers not found: {missing} "
          "(the first pair has no motion and no offset yet)")
    if tmp is not None:
        tmp.cleanup()


if __name__ == "__main__":
    main()
