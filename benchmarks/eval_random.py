"""Randomized-sky benchmark: layers found, spurious layers, clear skies with cloud, false alarms.

Run: python benchmarks/eval_random.py --n 200 --seed 0 [--size 960] [--jobs 2] [--verbose]
     [--skylines] [--unmasked] [--kind clear] [--twice-encoded] [--dense] [--contrails]
     [--mounts] [--optics] [--overlays]
     [--station NAME_OR_TOML]

Each sky is :func:`cbh.sim.randomize.random_case` (seed S, S+1, …): clear, broken or overcast;
1–3 layers 300 m – 10 km; baselines 20–200 m in any direction; winds 0–30 m/s; the sun 10–85°
from the zenith; aureole strength; horizon obstacles with and without a mask; colour
responses; white levels 235–255 and limited-range video; JPEG; noise. One pair per sky, the
true orientation given. The options widen the distribution
(:class:`cbh.sim.randomize.RandomOptions`): skyline obstacles and hazy horizons, obstacles in
every sky without a mask, one kind of sky, twice-encoded frames, dense skies of two or three
layers (upper decks seen through the gaps of the lowest), aircraft contrails, cameras mounted as
real stations are (tilted 0–3°, 0–15 m apart in height, each its own lens, off-centre), each
camera's optics (lens-flare ghosts of the sun, dust on the dome), each camera's on-screen clock and
name stamped on its frames (``--overlays``); ``--station``: another
station's lenses (a preset or a TOML, e.g. the real Fehmarn station's OCamCalib fits; its first two
cameras' intrinsics and its ``[pipeline]`` table are kept, positions and yaws drawn). A layer is found when a reported one is within max(5 %, H·δθ/B) of it,
δθ = half a rendered pixel at the zenith (:func:`cbh.sim.evaluate.layer_tolerance`).

Two true layers closer than the pair resolves are found *reported as one* (counted found, listed
as ``as one``, left out of the height errors) when both lie in one reported layer's band
(``Layer.height_lo_m`` … ``height_hi_m``, each within its max(5 %, H·δθ/B) of the band): the
heights whose parallax is within ``layers.resolve_px`` (2 px at working size, what the plane
sweep tells apart) of the layer's, or within ``layers.min_separation_log`` (18 %) of its median,
or in its points' 10–90 % range. That reported layer is then not spurious. A band holding one
true layer changes nothing: it is scored by the rule above alone, and no other rule is looser
(:class:`cbh.sim.evaluate.LayerScore`).

The cloud fraction of the cloudy skies is scored too: the larger camera's against the share of
the analysed field that is cloud in truth (median and mean |error|, skies more than 0.1 off).
"""
from __future__ import annotations

import argparse
import sys
import tempfile
from collections import defaultdict

import numpy as np

from cbh.flags import INVALIDATING
from cbh.geometry.station import load_station
from cbh.presets import station_path
from cbh.sim.randomize import RandomOptions, run_random_case

BANDS = ((0, 1000), (1000, 3000), (3000, 6000), (6000, 10_001))


def one_sky(job):
    """One sky's summary (run in a worker): (seed, kind, expected, matched, spurious, missed,
    found, cloud fraction, layer count, flags, seconds)."""
    seed, size, options, station = job
    base = load_station(station_path(station))
    with tempfile.TemporaryDirectory() as folder:
        case, r, sc, dt = run_random_case(seed, base, size, folder, options=options)
    return dict(seed=seed, kind=case.kind, describe=case.describe(), expected=sc.expected_m, matched=sc.matched,
                merged=sc.merged,
                spurious=sc.spurious_m, missed=sc.missed_m, found=sc.found_m,
                cf=max(r.cloud_fraction.values(), default=0.0), n_layers=len(r.layers), flags=list(r.flags), dt=dt,
                measured=r.diagnostics.get("measured_fraction", float("nan")), true_cf=sc.cloud_fraction)


def report(rows, args) -> None:
    """Print each failing sky (every sky with ``--verbose``) and the totals."""
    found = expected = spurious = clear_bad = clear_n = alarms = 0
    errs = defaultdict(list)
    bad_seeds = []
    fmt = lambda hs: "/".join(f"{h:.0f}" for h in hs) or "-"  # noqa: E731
    for row in rows:
        expected += len(row["expected"])
        found += len(row["matched"]) + len(row.get("merged", ()))
        spurious += len(row["spurious"])
        inval = sorted(set(row["flags"]) & INVALIDATING)
        alarms += bool(inval)
        for h, f in row["matched"].items():
            errs[next(b for b in BANDS if b[0] <= h < b[1])].append(abs(f - h) / h)
        bad = bool(row["missed"] or row["spurious"] or inval)
        if row["kind"] == "clear":
            clear_n += 1
            # (a "clear" sky's contrails are cloud: its layers must then be theirs, scored above)
            true_cf = row.get("true_cf", 0.0)
            cbad = row["cf"] > true_cf + 0.02 or (row["n_layers"] > 0 and not true_cf)
            clear_bad += cbad
            bad |= cbad
        if bad:
            bad_seeds.append(row["seed"])
        if args.verbose or bad:
            print(f"{'BAD ' if bad else 'ok  '}{row['describe']}\n     expected {fmt(row['expected'])} found "
                  f"{fmt(row['found'])} missed {fmt(row['missed'])} spurious {fmt(row['spurious'])}"
                  + (f" as one {fmt(row['merged'])}" if row.get("merged") else "") + f" cf {row['cf']:.3f} "
                  f"measured {row.get('measured', float('nan')):.3f} "
                  f"flags {','.join(row['flags']) or '-'} {row['dt']:.2f} s", flush=True)
    print(f"\nskies {args.n} (seeds {args.seed}..{args.seed + args.n - 1}, {args.size} px, lenses of {args.station})")
    as_one = sum(len(row.get("merged", ())) for row in rows)
    print(f"layers found {found}/{expected} ({100 * found / max(expected, 1):.1f} %; {as_one} of them reported as one "
          f"with another, closer than the pair resolves)")
    print(f"spurious layers {spurious}")
    print(f"clear skies with cloud > 0.02 (beyond their contrails) or a layer (but a contrail's): {clear_bad}/{clear_n}")
    print(f"skies with an invalidating flag (false alarms on a correct station): {alarms}")
    for b in BANDS:
        e = errs.get(b, [])
        med = f"{100 * float(np.median(e)):.2f} %" if e else "-"
        print(f"  {b[0]:>5d}-{b[1]:<5d} m: {len(e):3d} layers, median error {med}")
    cf_err = [abs(row["cf"] - row["true_cf"]) for row in rows if row["kind"] != "clear" and "true_cf" in row]
    if cf_err:
        print(f"cloud fraction of cloudy skies (the larger camera's against the scene's): |error| median "
              f"{float(np.median(cf_err)):.3f}, mean {float(np.mean(cf_err)):.3f}, over 0.1 in "
              f"{sum(e > 0.1 for e in cf_err)}/{len(cf_err)}")
    print(f"failing seeds: {' '.join(map(str, bad_seeds)) or 'none'}")


def parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=30)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--size", type=int, default=960)
    ap.add_argument("--jobs", type=int, default=1, help="skies run side by side (processes)")
    ap.add_argument("--verbose", action="store_true", help="one line per sky")
    ap.add_argument("--skylines", action="store_true", help="skyline obstacles (blocks, masts, tree lines, walls), hazy horizons")
    ap.add_argument("--unmasked", action="store_true", help="obstacles in every sky, never a mask")
    ap.add_argument("--kind", choices=["clear", "broken", "overcast"], help="only skies of this kind")
    ap.add_argument("--twice-encoded", action="store_true", help="camera JPEG then recorder JPEG, clip 230-255 DN")
    ap.add_argument("--dense", action="store_true", help="broken skies of 2-3 layers, the lowest covering 0.55-0.85")
    ap.add_argument("--contrails", action="store_true", help="1-3 aircraft contrails at 7-11.5 km in 70 %% of skies")
    ap.add_argument("--mounts", action="store_true",
                    help="cameras tilted 0-3 deg, 0-15 m apart in height, each its own lens (ocam/equidistant/equisolid, off-centre)")
    ap.add_argument("--optics", action="store_true",
                    help="each camera its own lens-flare ghosts of the sun (80 %% of frames) and dome spots (half)")
    ap.add_argument("--overlays", action="store_true",
                    help="each camera stamps its clock (and name) on its frames: outline, shadow or banner, mostly on the sky")
    ap.add_argument("--station", default="unb-lea", help="preset name or station TOML whose lenses are kept")
    return ap


def main(argv=None) -> int:
    args = parser().parse_args(argv)
    options = RandomOptions(skylines=args.skylines, unmasked=args.unmasked, kind=args.kind,
                            twice_encoded=args.twice_encoded, dense=args.dense, contrails=args.contrails,
                            mounts=args.mounts, optics=args.optics, overlays=args.overlays)
    jobs = [(s, args.size, options, args.station) for s in range(args.seed, args.seed + args.n)]
    if args.jobs > 1:
        import multiprocessing as mp

        with mp.get_context("spawn").Pool(args.jobs) as pool:
            rows = pool.map(one_sky, jobs, chunksize=1)
    else:
        rows = [one_sky(j) for j in jobs]
    report(rows, args)
    return 0


if __name__ == "__main__":
    sys.exit(main())
