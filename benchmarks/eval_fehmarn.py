"""The real Fehmarn station (issue 32): every pair of the shared half hour, in time order, as a
station runs it, scored against the reference layers of ../shared/data/fehmarn-2016-09-01.

    python benchmarks/eval_fehmarn.py [--data DIR] [--shift N] [--extra-offset S] [--first K] [--step N] [--json OUT]

``--shift N`` re-pairs the real images: FE3's frame i with FE4's frame i+N (stamped as FE4's frame
i), which adds N × 60 s to camera FE4's clock offset (about +30 s as recorded: N = 1 gives
≈ +90 s, N = −2 ≈ −90 s). The reference layers are those of FE3's frame.

Per pair: the clock offset (running and the pair's own), flags, layers; then the issue's scores
from the third pair on: valid pairs with a layer within 10 % of a reference layer (15 % above
5 km), pairs led (largest cover) by a layer the reference does not have, offsets within 2 s of
the median estimate (the truth is not recorded: its stability is what is scored).
"""
from __future__ import annotations

import argparse
import csv
import json
import math
import statistics
import time
from collections import defaultdict
from datetime import datetime, timedelta
from pathlib import Path

DEFAULT = Path(__file__).resolve().parents[2] / "shared" / "data" / "fehmarn-2016-09-01"


def reference_layers(data: Path) -> dict[datetime, list[tuple[float, float]]]:
    from cbh.timeutil import parse_utc

    ref = defaultdict(list)
    with open(data / "reference-layers.csv") as f:
        for row in csv.DictReader(f):
            ref[parse_utc(row["time_utc"])].append((float(row["layer_height_m"]), float(row["share_of_matched_cloud"])))
    return dict(ref)


def frames(data: Path, shift: int = 0, step: int = 1) -> list[tuple[Path, Path, datetime]]:
    """FE3's frame i with FE4's frame i + ``shift``, every ``step``-th frame (a cadence of
    ``step`` minutes)."""
    from cbh.timeutil import time_from_name

    f3 = sorted((data / "fe3").glob("*.jpg"))
    f4 = sorted((data / "fe4").glob("*.jpg"))
    out = []
    for i, a in enumerate(f3):
        j = i + shift
        if 0 <= j < len(f4):
            out.append((a, f4[j], time_from_name(a.name)))
    return out[::step]


def agrees(h: float, refs: list[tuple[float, float]]) -> bool:
    return any(abs(h - r) <= (0.15 if r > 5000 else 0.10) * r for r, _ in refs)


def _ratio(x) -> str:
    """The pair's parallax over its carry noise (``carry_parallax_ratio``), where it was measured."""
    return "" if x is None else f" carry ratio {x:.2f}"


def evaluate(data: Path, shift: int = 0, first: int | None = None, verbose: bool = True, config=None,
             step: int = 1) -> dict:
    from cbh.flags import INVALIDATING
    from cbh.geometry.station import load_station
    from cbh.pipeline import Pipeline
    from cbh.pipeline.motion import PairState

    station = load_station(data / "station.toml")
    pipe = Pipeline(station, config=config) if config is not None else Pipeline(station)
    ref = reference_layers(data)
    rows, state = [], PairState.start()  # as `cbh run` starts
    for k, (a, b, t) in enumerate(frames(data, shift, step)[:first]):
        t0 = time.perf_counter()
        r = pipe.process(a, b, t, previous=state)
        state = r.state
        refs = ref.get(t, [])
        lead = max(r.layers, key=lambda L: L.cover) if r.layers else None
        valid = not (INVALIDATING & set(r.flags))
        row = {"time": t.isoformat(), "offset_s": r.diagnostics.get("clock_offset_s"),
               "offset_pair_s": r.diagnostics.get("clock_offset_pair_s"), "flags": r.flags,
               "layers": [(round(L.height_m), round(L.cover, 3)) for L in r.layers], "ref": refs,
               "valid": valid, "hit": valid and any(agrees(L.height_m, refs) for L in r.layers),
               "phantom_lead": valid and lead is not None and not agrees(lead.height_m, refs),
               "carry_ratio": r.diagnostics.get("carry_parallax_ratio"),
               "ms": round((time.perf_counter() - t0) * 1000)}
        rows.append(row)
        if verbose:
            print(f"{k:2d} {t:%H:%M} off {row['offset_s']:7.1f} (pair {row['offset_pair_s']:7.1f}) "
                  f"{'HIT ' if row['hit'] else 'miss'}{' PHANTOM' if row['phantom_lead'] else ''} "
                  f"layers {row['layers']} ref {[round(h) for h, _ in refs]} flags {r.flags}"
                  f"{_ratio(row['carry_ratio'])} {row['ms']} ms", flush=True)
    tail = rows[2:]
    offs = [r["offset_s"] for r in tail if r["offset_s"] is not None and math.isfinite(r["offset_s"])]
    med = statistics.median(offs) if offs else math.nan
    score = {"pairs": len(tail), "valid_with_reference_layer": sum(r["hit"] for r in tail) / max(len(tail), 1),
             "phantom_led": sum(r["phantom_lead"] for r in tail) / max(len(tail), 1),
             "geometry_mismatch": sum("geometry_mismatch" in r["flags"] for r in tail),
             "offset_median_s": med,
             "offset_within_2s_of_median": sum(abs(o - med) <= 2 for o in offs) / max(len(tail), 1),
             "ms_median": statistics.median(r["ms"] for r in rows) if rows else math.nan}
    if verbose:
        print(json.dumps(score, indent=1))
    return {"rows": rows, "score": score}


def _positive(text: str) -> int:
    n = int(text)
    if n < 1:
        raise argparse.ArgumentTypeError(f"must be 1 or more, not {n}")
    return n


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=DEFAULT)
    ap.add_argument("--shift", type=int, default=0)
    ap.add_argument("--first", type=int, default=None)
    ap.add_argument("--step", type=_positive, default=1, help="every N-th frame: a cadence of N minutes")
    ap.add_argument("--json", type=Path)
    a = ap.parse_args()
    res = evaluate(a.data, a.shift, a.first, step=a.step)
    if a.json:
        a.json.write_text(json.dumps(res, indent=1, default=str))


if __name__ == "__main__":
    main()
