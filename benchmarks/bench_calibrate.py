"""Speed and accuracy of `cbh calibrate` on a simulated day (issue 12: ~100 pairs at 960 px in
<= 60 s on the 2-core machine; each camera within 0.1 deg, the relative rotation within 0.05 deg).

Run: python benchmarks/bench_calibrate.py [--frames 100] [--size 960] [--data DIR]

Renders (once; kept in --data, default /tmp/cbh-bench-calibrate-<size>-<frames>) the scene
`misoriented-day` seen through configs/unb-lea-level.toml: camera 1 truly at (2.0, 0.3, -0.2) deg,
camera 2 at (-5.6, -0.4, 0.25) deg, one frame pair every 6 minutes from 10:00 UTC. Then times the
calibration (wall and CPU seconds; rendering is not timed) and prints each camera's error
against the truth, the relative rotation's error and the 2000 m layer before and after.
"""
from __future__ import annotations

import argparse
import math
import time
from datetime import datetime, timedelta, timezone
from pathlib import Path

import numpy as np

TRUE = {"cam1": (2.0, 0.3, -0.2), "cam2": (-5.6, -0.4, 0.25)}


def _angle_deg(A, B) -> float:
    return math.degrees(math.acos(min(1.0, (np.trace(A.T @ B) - 1.0) / 2.0)))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=100)
    ap.add_argument("--size", type=int, default=960)
    ap.add_argument("--data", type=Path, default=None)
    args = ap.parse_args()

    from cbh.actions.calibrate import calibrate
    from cbh.geometry.station import angles_from_rotation, load_station, rotation_from_angles
    from cbh.imageio import read_image
    from cbh.pipeline import Pipeline
    from cbh.presets import configs_dir
    from cbh.sim import SkySimulator, load_scene
    from cbh.sim.io import write_shot

    data = args.data or Path(f"/tmp/cbh-bench-calibrate-{args.size}-{args.frames}")
    t0 = datetime(2024, 6, 21, 10, 0, tzinfo=timezone.utc)
    cadence = timedelta(seconds=max(1, round(36000 / args.frames)))
    if not (data / "station.toml").is_file() or len(list((data / "cam2").glob("*.jpg"))) < args.frames:
        tic = time.perf_counter()
        st = load_station(configs_dir() / "unb-lea-level.toml")
        sim = SkySimulator(st, load_scene(configs_dir() / "scenes" / "misoriented-day.toml"), size_px=args.size)
        data.mkdir(parents=True, exist_ok=True)
        for i in range(args.frames):
            write_shot(sim.render(t0 + i * cadence), data, 92)
        (data / "station.toml").write_text(sim.station.to_toml())
        print(f"rendered {args.frames} pairs at {args.size} px into {data} ({time.perf_counter() - tic:.1f} s, not timed)")

    out = data / "calibrated.toml"
    wall, cpu = time.perf_counter(), time.process_time()
    rep = calibrate(data / "station.toml", {"cam1": str(data / "cam1"), "cam2": str(data / "cam2")}, out)
    wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
    print(f"calibrate: {args.frames} pairs at {args.size} px in {wall:.1f} s wall, {cpu:.1f} s CPU")

    cal = load_station(out)
    R = {n: rotation_from_angles(*a) for n, a in TRUE.items()}
    C = {n: cal.cameras[n].R_world_from_cam for n in TRUE}
    for n in TRUE:
        c = rep["cameras"][n]
        print(f"{n}: fitted {np.round(angles_from_rotation(C[n]), 3)} deg, true {TRUE[n]}; error {_angle_deg(C[n], R[n]):.3f} deg; "
              f"sun in {c['sun_detections']}/{c['frames']} frames, RMS {c['sun_rms_deg']:.3f} deg, {c['sun_outliers']} outliers")
    print(f"relative rotation error: {_angle_deg(C['cam1'].T @ C['cam2'], R['cam1'].T @ R['cam2']):.4f} deg")

    before, after = Pipeline(load_station(data / "station.toml")), Pipeline(cal)
    for i in (args.frames // 10, args.frames // 2, 9 * args.frames // 10):
        t = t0 + i * cadence
        tag = t.strftime("%Y%m%dT%H%M%S.000Z")
        i1, _ = read_image(data / "cam1" / f"cam1_{tag}.jpg")
        i2, _ = read_image(data / "cam2" / f"cam2_{tag}.jpg")
        rb, ra = before.process(i1, i2, t, channels="bgr"), after.process(i1, i2, t, channels="bgr")
        fmt = lambda r: ", ".join(f"{l.height_m:.0f} m ({l.confidence:.2f})" for l in r.layers) + (f" [{', '.join(r.flags)}]")
        print(f"{tag}: 2000 m layer before: {fmt(rb)}; after: {fmt(ra)}")


if __name__ == "__main__":
    main()
