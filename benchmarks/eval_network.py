"""Randomized skies seen by a three-camera network: fused layers against the short pair alone.

Run: python benchmarks/eval_network.py --n 30 --seed 0 [--size 960] [--tilt] [--verbose]

Each sky is the scene of :func:`cbh.sim.randomize.random_case` (seed S, S+1, …: clear, broken or
overcast skies, 1–3 layers 300 m – 10 km, the sun 10–85° from the zenith, aureole, obstacles,
colour responses, white levels, JPEG, noise) over a random place, seen by three cameras: cam1 at
the origin, cam2 20–200 m away and cam3 300–1000 m away, in random directions, each yawed
anywhere (cam3 with cam1's lens). Printed per sky: the true layers, the station's fused layers,
the 50 m-class pair's (cam1 + cam2) own layers, flags. Summary: the median and 90th percentile
|error| of the matched layers (fused, and the short pair alone) per height band, spurious layers
(a reported layer farther than max(5 %, H·δθ/B_long) from every true one), missed layers.
``--tilt``: one camera (drawn per sky) 2° off level about a random horizontal axis while the
station says level: how often it is named in ``mismatched_cameras``, and named wrongly.
"""
from __future__ import annotations

import argparse
import math
import sys
import time

import numpy as np

BANDS = ((0, 1000), (1000, 3000), (3000, 6000), (6000, 10_001))


def one(seed: int, size: int, tilt: bool, verbose: bool):
    from cbh.pipeline.network import StationPipeline

    from cbh.sim.randomize import random_network_case

    case, sim, bad, b3 = random_network_case(seed, size, tilt)
    shot = sim.render()
    t0 = time.perf_counter()
    r = StationPipeline(sim.station).process([shot.views[c].image for c in ("cam1", "cam2", "cam3")],
                                             shot.time_utc, channels="bgr")
    dt = time.perf_counter() - t0
    truth = sorted({float(L.height_m) for L in shot.layers})
    short = r.pairs.get("cam1+cam2")
    row = dict(seed=seed, kind=case.kind, truth=truth, fused=[L.height_m for L in r.layers],
               short=[L.height_m for L in short.layers] if short is not None else None,
               b2=case.baseline_m, b3=b3, bad=bad, named=list(r.diagnostics.get("mismatched_cameras", [])),
               flags=list(r.flags), dt=dt)
    if verbose:
        print(f"seed {seed} {case.kind}: B {case.baseline_m:.0f} / {b3:.0f} m; truth "
              f"{', '.join(f'{h:.0f}' for h in truth) or '-'}; fused {', '.join(f'{h:.0f}' for h in row['fused']) or '-'}; "
              f"cam1+cam2 {', '.join(f'{h:.0f}' for h in row['short'] or []) or '-'}"
              + (f"; tilted {bad}, named {row['named']}" if tilt else "") + f"; {' '.join(r.flags)} ({dt:.1f} s)",
              flush=True)
    return row


def _match(found, truth, tol_rel):
    """(errors of matched true layers {truth: rel error}, spurious reports)."""
    errs, spurious = {}, []
    for f in found:
        near = [h for h in truth if abs(f - h) / h <= tol_rel(h)]
        if not near:
            spurious.append(f)
            continue
        h = min(near, key=lambda h: abs(f - h))
        if h in errs:
            spurious.append(f)
        else:
            errs[h] = (f - h) / h
    return errs, spurious


def summarize(rows, tilt: bool) -> None:
    px = math.radians(90.0) / 480.0  # a working pixel at the zenith of the 960 px lens [rad]
    stats = {k: {b: [] for b in BANDS} for k in ("fused", "short")}
    from cbh.flags import INVALIDATING

    spur = {"fused": 0, "short": 0}
    spur_valid = 0  # in station answers not flagged invalid (what a user is told to rely on)
    missed = 0
    for row in rows:
        tol = lambda h: max(0.05, h * 0.5 * px / row["b3"])  # noqa: E731
        for k in ("fused", "short"):
            if row[k] is None:
                continue
            errs, sp = _match(row[k], row["truth"], tol)
            spur[k] += len(sp)
            if k == "fused" and not INVALIDATING & set(row["flags"]):
                spur_valid += len(sp)
            for h, e in errs.items():
                band = next(b for b in BANDS if b[0] <= h < b[1])
                stats[k][band].append(abs(e))
            if k == "fused":
                missed += len(row["truth"]) - len(errs)
    print(f"\n{len(rows)} skies; layers: {sum(len(r['truth']) for r in rows)} true, {missed} missed by the station")
    print(f"{'band [m]':>14} {'fused n':>7} {'median':>7} {'p90':>7} {'50 m-class n':>12} {'median':>7} {'p90':>7}")
    for b in BANDS:
        f, s = np.array(stats["fused"][b]), np.array(stats["short"][b])
        q = lambda a, p: f"{100 * np.percentile(a, p):6.2f}%" if a.size else "     -"  # noqa: E731
        print(f"{b[0]:>6}-{b[1]:<7} {f.size:7d} {q(f, 50):>7} {q(f, 90):>7} {s.size:12d} {q(s, 50):>7} {q(s, 90):>7}")
    print(f"spurious layers: station {spur['fused']} ({spur_valid} in answers not flagged invalid), "
          f"cam1+cam2 alone {spur['short']}")
    if tilt:
        right = sum(r["named"] == [r["bad"]] for r in rows)
        wrong = sum(bool(set(r["named"]) - {r["bad"]}) for r in rows)
        print(f"tilted camera named: {right} of {len(rows)}; a wrong camera named: {wrong}")
    print(f"seconds per sky (processing): median {np.median([r['dt'] for r in rows]):.1f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=30)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--size", type=int, default=960)
    ap.add_argument("--tilt", action="store_true")
    ap.add_argument("--verbose", action="store_true")
    args = ap.parse_args()
    rows = [one(s, args.size, args.tilt, args.verbose) for s in range(args.seed, args.seed + args.n)]
    summarize(rows, args.tilt)
    sys.stdout.flush()


if __name__ == "__main__":
    main()
