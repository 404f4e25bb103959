"""Regenerate recordings/sample-two-layers.mcap: a small simulated session (simulator → pipeline → recorder).

    python scripts/make_sample_recording.py [--pairs 8] [--size 640] [--out recordings/sample-two-layers.mcap]

The scene is configs/scenes/two-layers.toml seen by the configs/unb-lea.toml station at
``--size`` px; pairs are ``--cadence`` s apart (the clouds drift between pairs). The file also
carries one /service/status message, as `cbh run` writes.
"""
from __future__ import annotations

import argparse
import time
from datetime import timedelta
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pairs", type=int, default=8)
    ap.add_argument("--size", type=int, default=640)
    ap.add_argument("--cadence", type=float, default=10.0)
    ap.add_argument("--scene", default=str(REPO / "configs" / "scenes" / "two-layers.toml"))
    ap.add_argument("--station", default=str(REPO / "configs" / "unb-lea.toml"))
    ap.add_argument("--out", default=str(REPO / "recordings" / "sample-two-layers.mcap"))
    a = ap.parse_args(argv)

    from cbh.pipeline import Pipeline
    from cbh.outputs.record import McapRecorder
    from cbh.sim import SkySimulator, load_scene
    from cbh.geometry.station import load_station

    station = load_station(a.station).scaled(a.size)
    sim = SkySimulator(station, load_scene(a.scene), size_px=a.size)
    pipe = Pipeline(station)
    out = Path(a.out)
    if out.exists():
        out.unlink()
    t0 = time.perf_counter()
    with McapRecorder(out, station, pipe.config.to_dict()) as rec:
        first = sim.scene.time_utc
        for k in range(a.pairs):
            t = first + timedelta(seconds=a.cadence * k)
            f1, f2 = sim.frame(pipe.cameras[0], t), sim.frame(pipe.cameras[1], t)
            result = pipe.process(f1.image, f2.image, t, channels="bgr")
            rec.write((f1, f2), result)
            print(f"pair {k}: {t.isoformat()} layers "
                  + ", ".join(f"{l.height_m:.0f} m" for l in result.layers), flush=True)
        rec.write_status(first + timedelta(seconds=a.cadence * (a.pairs - 1)),
                         {"pairs_processed": a.pairs, "pairs_dropped": 0, "unpaired": 0,
                          "sources": {c: {"state": "ok"} for c in pipe.cameras}})
    print(f"wrote {out} ({out.stat().st_size / 1e6:.2f} MB, {a.pairs} pairs) in {time.perf_counter() - t0:.1f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
