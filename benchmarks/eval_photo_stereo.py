"""Accuracy on stereo pairs built from real sky photographs: real texture, known truth.

    python benchmarks/eval_photo_stereo.py                          # 3 heights × 3 baselines, med exposure
    python benchmarks/eval_photo_stereo.py --heights 800 3000 --baselines 50 --exposure low
    python benchmarks/eval_photo_stereo.py --opencv                 # also the rectify-and-SGBM route

Camera 1 is a real WAHRSIS photograph (../shared/data/wahrsis-2015-10-29, wahrsis3) with its
calibration, resized to ``--width``. Camera 2 is a virtual camera with the same lens at
``--baselines`` m east, yawed ``--yaw`` degrees, that sees the photograph's sky as a horizontal
plane at height h (:mod:`cbh.sim.photo`). The truth is therefore h at every pixel of camera 1
that is cloud; what is scored is what cbh reports:

- layers: the reported layer(s) against h (one expected);
- dense MdAPE: median |h_map − h| / h over the pixels cbh measured;
- measured: the share of camera 1's cloud mask with a measured height (``measured_fraction``);
- flags.

Camera 2's sun is the photograph's sun moved onto the plane, so ``sun_misaligned`` is expected.
"""
from __future__ import annotations

import argparse
import math
import time
from dataclasses import replace
from datetime import datetime, timezone
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data" / "wahrsis-2015-10-29"
T_UTC = datetime(2015, 10, 29, 4, 58, 1, tzinfo=timezone.utc)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--heights", nargs="+", type=float, default=[500.0, 1500.0, 4000.0])
    ap.add_argument("--baselines", nargs="+", type=float, default=[30.0, 50.0, 100.0])
    ap.add_argument("--yaw", type=float, default=20.0, help="camera 2's yaw against camera 1 [deg]")
    ap.add_argument("--exposure", default="med", choices=("low", "med", "high"))
    ap.add_argument("--width", type=int, default=2592, help="photograph resized to this width [px]")
    ap.add_argument("--opencv", action="store_true", help="also score the rectify-and-SGBM route (bench_vs_opencv)")
    a = ap.parse_args()

    from cbh.geometry.station import Station, load_station
    from cbh.imageio import read_image
    from cbh.pipeline import Pipeline
    from cbh.sim.photo import plane_view, virtual_camera

    wahrsis = load_station(ROOT / "configs" / "wahrsis-2015-10-29.toml")
    cam1 = wahrsis.camera("wahrsis3")
    full, _ = read_image(DATA / f"2015-10-29-12-58-01-wahrsis3-{a.exposure}.jpg")
    cam1 = cam1.scaled(a.width / cam1.model.width)
    photo = cv2.resize(full, (cam1.model.width, cam1.model.height), interpolation=cv2.INTER_AREA)
    ocv_cls = None
    if a.opencv:
        import sys

        sys.path.insert(0, str(Path(__file__).resolve().parent))
        from bench_vs_opencv import OpenCVStereo as ocv_cls
    print(f"WAHRSIS3 {a.exposure} photograph at {photo.shape[1]} x {photo.shape[0]} px; camera 2 yawed {a.yaw:g} deg")
    print(f"{'h_m':>6s} {'B_m':>5s} {'layers_m':>16s} {'err_%':>6s} {'MdAPE_%':>8s} {'measured':>8s} {'s':>5s}  flags"
          + ("   | OpenCV MdAPE_% cover_%" if a.opencv else ""))
    for hgt in a.heights:
        for b in a.baselines:
            cam2 = virtual_camera(cam1, (b, 0.0, 0.0), a.yaw)
            img2 = plane_view(photo, cam1, cam2, hgt)
            st = Station(name="photo-stereo", latitude_deg=wahrsis.latitude_deg, longitude_deg=wahrsis.longitude_deg,
                         altitude_m=wahrsis.altitude_m, cameras={"cam1": replace(cam1, name="cam1"), "cam2": replace(cam2, name="cam2")})
            pipe = Pipeline(st)
            t0 = time.perf_counter()
            r = pipe.process(photo, img2, T_UTC, channels="bgr")
            dt = time.perf_counter() - t0
            hm = r.height_map
            have = np.isfinite(hm)
            mdape = float(np.median(np.abs(hm[have] - hgt) / hgt)) if have.any() else math.nan
            lay = [L.height_m for L in r.layers]
            err = max((abs(x - hgt) / hgt for x in lay), default=math.nan)
            flags = ",".join(f for f in r.flags if f != "sun_glare")
            line = (f"{hgt:6.0f} {b:5.0f} {'/'.join(f'{x:.0f}' for x in lay) or 'none':>16s} {100 * err:6.2f} "
                    f"{100 * mdape:8.2f} {r.diagnostics.get('measured_fraction', math.nan):8.2f} {dt:5.2f}  {flags or '-'}")
            if ocv_cls is not None:
                ocv = ocv_cls(pipe.cam1_full, pipe.cam2_full)
                ho = ocv.heights(photo, img2)
                ok = np.isfinite(ho) & (ho > 0)
                m_o = float(np.median(np.abs(ho[ok] - hgt) / hgt)) if ok.any() else math.nan
                line += f"   | {100 * m_o:8.2f} {100 * ok.mean():6.1f}"
            print(line, flush=True)


if __name__ == "__main__":
    main()
