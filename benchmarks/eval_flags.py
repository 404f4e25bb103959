"""Inputs that cannot support a result: are they flagged? (fog below the sweep's floor, a camera
turned from what the station says.)

    python benchmarks/eval_flags.py fog                      # 5 heights × 3 textures at 960 px
    python benchmarks/eval_flags.py fog --size 480
    python benchmarks/eval_flags.py turn --size 1920         # camera 2 yawed/pitched/rolled 0.05–1°

``fog``: one layer at 10–80 m (below the 100 m floor) and, for contrast, at 105–130 m; printed:
the share of camera 1's cloud measured, the share on the lowest plane, the lowest layer, flags.
``turn``: the two-layers scene with camera 2 rendered off its station orientation by
(yaw, pitch, roll); printed: layers (truth 1200 / 3500 m), the fitted rotation and its σ, the
median epipolar distance, flags.
"""
from __future__ import annotations

import argparse
import dataclasses
import math

FOG = [(h, cov, tex, seed) for h in (10.0, 20.0, 30.0, 45.0, 80.0, 105.0, 115.0, 130.0)
       for cov, tex, seed in ((0.6, 100.0, 5), (0.9, 50.0, 7), (0.4, 200.0, 3))]
TURNS = [(0, 0, 0), (0, 0.5, 0), (0.05, 0, 0), (0, 0.05, 0), (0, 0, 0.05), (0, 0, -0.05), (0.1, 0, 0), (0, 0.1, 0), (0, 0, 0.1),
         (0.25, 0, 0), (0, 0.25, 0), (0, 0, 0.25), (0.5, 0, 0), (1.0, 0, 0)]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("case", choices=("fog", "turn"))
    ap.add_argument("--size", type=int, default=960)
    a = ap.parse_args()

    from cbh.geometry.station import load_station
    from cbh.pipeline import Pipeline
    from cbh.presets import station_path
    from cbh.sim import SkySimulator, load_scene, parse_scene

    def run(scene):
        sim = SkySimulator(load_station(station_path("unb-lea")), scene, size_px=a.size)
        shot = sim.render()
        return Pipeline(sim.station).process(shot.views["cam1"].image, shot.views["cam2"].image, shot.time_utc,
                                             channels="bgr")

    def flags(r):
        return ",".join(f for f in r.flags if f != "sun_glare") or "-"

    if a.case == "fog":
        print(f"{'h_m':>5s} {'cover':>5s} {'tex_m':>5s} {'measured':>8s} {'floor':>6s} {'lowest_m':>8s}  flags")
        for h, cov, tex, seed in FOG:
            r = run(parse_scene({"name": "fog", "time_utc": "2024-06-21T14:00:00Z",
                                 "layers": [{"height_m": h, "coverage": cov, "texture_scale_m": tex, "seed": seed}]}))
            d = r.diagnostics
            low = min((L.height_m for L in r.layers), default=math.nan)
            print(f"{h:5.0f} {cov:5.1f} {tex:5.0f} {d.get('measured_fraction', math.nan):8.3f} "
                  f"{d.get('below_range_fraction', math.nan):6.3f} {low:8.0f}  {flags(r)}", flush=True)
    else:
        base = load_scene("two-layers")
        print(f"{'yaw,pitch,roll_deg':>20s} {'layers_m':>16s} {'rot_deg':>8s} {'sigma':>6s} {'resid_px':>8s}  flags")
        for err in TURNS:
            imp = parse_scene({"name": "t", "time_utc": "2024-06-21T14:00:00Z", "layers": [{"height_m": 1000.0, "coverage": 0.5}],
                               "imperfections": [{"camera": "cam2", "rotation_error_deg": list(err)}]}).imperfections
            r = run(dataclasses.replace(base, imperfections=imp))
            d = r.diagnostics
            print(f"{str(err):>20s} {'/'.join(f'{L.height_m:.0f}' for L in r.layers):>16s} "
                  f"{d['geometry_rotation_deg']:8.4f} {d['geometry_rotation_sigma_deg']:6.4f} "
                  f"{d['geometry_residual_px']:8.3f}  {flags(r)}", flush=True)


if __name__ == "__main__":
    main()
