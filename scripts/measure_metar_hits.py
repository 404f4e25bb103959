"""Compare the METAR hit samplers (cbh/outputs/aviation.py) on a recording: the last pair's groups.

    python scripts/measure_metar_hits.py REC.mcap [REC2.mcap ...]

Prints, per sampler (virtual, map) and hit height (layer base, pixel height), the METAR string,
its groups (okta, base [ft], code), the hits and measurements behind it, and the run time.
"""
from __future__ import annotations

import sys
import time


def main(argv=None) -> int:
    from cbh.actions.aviation import metar_reports

    paths = list(sys.argv[1:] if argv is None else argv)
    for method in ("virtual", "map"):
        for heights in ("layer", "pixel"):
            t0 = time.perf_counter()
            r = metar_reports(paths, method=method, heights=heights, every_s=1e12)[-1]
            groups = ", ".join(f"{g.okta} okta {g.height_ft:.0f} ft {g.code}" for g in r.groups)
            print(f"{method:8s} {heights:6s} {r.metar:24s} [{groups}] hits {r.hits} measurements {r.measurements} "
                  f"({time.perf_counter() - t0:.1f} s)", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
