"""A CL61-shaped ceilometer file of the simulator's truth above camera 1, at a recording's pair times.

    python scripts/make_truth_ceilometer.py REC.mcap SCENE.toml OUT.nc [--size 640]

For each pair time the scene is rendered (cbh.sim.SkySimulator) and the true cloud-base height
at camera 1's zenith pixel (its height map: the lowest cloud straight up) is the "first base";
clear sky is fill (−99). Check it with ``cbh validate --ceilometer OUT.nc REC.mcap``.
"""
from __future__ import annotations

import argparse

import numpy as np


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("recording"), ap.add_argument("scene"), ap.add_argument("out")
    ap.add_argument("--size", type=int, default=640)
    a = ap.parse_args(argv)
    import xarray as xr

    from cbh.outputs.record import open_session
    from cbh.sim import SkySimulator, load_scene

    s = open_session(a.recording)
    st = s.station.scaled(a.size)
    sim = SkySimulator(st, load_scene(a.scene), size_px=a.size)
    name = next(iter(st.cameras))  # camera 1
    camera = st.camera(name)
    zpx = camera.direction_to_pixel(np.array([[0.0, 0.0, 1.0]]))[0]
    col, row = int(round(zpx[0])), int(round(zpx[1]))
    times, bases = [], []
    for p in s.pairs(layers_only=True):
        v = sim.view(name, p.time_utc)
        h = float(v.height_m[row, col])
        times.append(np.datetime64(p.time_utc.replace(tzinfo=None), "ns"))
        bases.append([h if np.isfinite(h) and h > 0 else -99.0, -99.0, -99.0])
    ds = xr.Dataset({"cloud_base_heights": (("time", "layer"), np.array(bases), {"units": "m"})},
                    coords={"time": np.array(times), "layer": [1, 2, 3]})
    ds.to_netcdf(a.out, encoding={"cloud_base_heights": {"_FillValue": -99.0}})
    print(f"wrote {len(times)} truth profiles to {a.out}: bases {[b[0] for b in bases]}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
