"""Recorder, reader, Rerun and export throughput (run on demand; prints numbers).

    python benchmarks/bench_record.py [--size 1920] [--pairs 10] [--full-size-maps]

Writes synthetic pairs of the given size (JPEG images as received, a dense float32 height map,
~8000 points) with McapRecorder, then reads them back, replays into an .rrd and exports NetCDF;
then times one pair appended to a live Parquet export that already holds ``--parquet-rows``.
"""
from __future__ import annotations

import os
import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--size", type=int, default=1920)
    ap.add_argument("--pairs", type=int, default=10)
    ap.add_argument("--parquet-rows", type=int, nargs="*", default=[26_000, 50_000],
                    help="rows a live Parquet export already holds (a day at a 10 s cadence ≈ 26 000)")
    ap.add_argument("--full-size-maps", action="store_true",
                    help="hand the recorder full-size maps (the pipeline hands working-size ones, enlarged on read)")
    a = ap.parse_args(argv)

    from dataclasses import replace

    from cbh.outputs.export import export_sessions
    from cbh.outputs.record import McapRecorder, open_session
    from cbh.outputs.rerun_view import RerunSink
    from tests.test_record import small_station, synthetic_pair

    from cbh.result import Enlarged

    st = small_station(a.size)
    pairs = []
    for k in range(a.pairs):
        frames, res = synthetic_pair(st, k, n_points=8000)
        rng = np.random.default_rng(k)
        h, w = res.height_map.shape
        hm = np.where(rng.random((h // 2, w // 2)) < 0.5, np.nan,
                      1200 + 30 * rng.standard_normal((h // 2, w // 2))).astype(np.float32)
        # as the pipeline hands them over: made at half size, enlarged when read (Enlarged)
        maps = dict(height_map=Enlarged(hm, w, h),
                    cloud_masks={c: Enlarged(np.ascontiguousarray(m[::2, ::2]), w, h) for c, m in res.cloud_masks.items()})
        if a.full_size_maps:  # as before 2026-12-02: full-size arrays
            maps = dict(height_map=maps["height_map"].full(), cloud_masks={c: m.full() for c, m in maps["cloud_masks"].items()})
        pairs.append((frames, replace(res, **maps)))
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "bench.mcap"
        t0 = time.perf_counter()
        with McapRecorder(path, st, {}) as rec:
            for frames, res in pairs:
                rec.write(frames, res)
        t_write = (time.perf_counter() - t0) / a.pairs
        size = path.stat().st_size / a.pairs / 1e6
        t0 = time.perf_counter()
        n = sum(1 for _ in open_session(path).pairs())
        t_read = (time.perf_counter() - t0) / n
        t0 = time.perf_counter()
        with RerunSink(st, "save", str(Path(d) / "b.rrd")) as sink:
            for frames, res in pairs:
                sink.write(frames, res)
        t_rr = (time.perf_counter() - t0) / a.pairs
        t0 = time.perf_counter()
        export_sessions([path], "netcdf", Path(d) / "b.nc")
        t_nc = time.perf_counter() - t0
    print(f"size {a.size}px, {a.pairs} pairs ({os.cpu_count()} CPUs; load average {os.getloadavg()[0]:.1f}):")
    print(f"  McapRecorder.write   {t_write * 1e3:8.1f} ms/pair   {size:6.2f} MB/pair on disk")
    print(f"  Session.pairs()      {t_read * 1e3:8.1f} ms/pair (decode all topics)")
    print(f"  RerunSink.write      {t_rr * 1e3:8.1f} ms/pair (save mode)")
    print(f"  export netcdf        {t_nc * 1e3:8.1f} ms total")
    for held in a.parquet_rows:
        print(f"  live Parquet export  {_parquet_pair_ms(st, pairs[0][1], held):8.1f} ms/pair with {held} rows held")
    return 0


def _parquet_pair_ms(station, result, held: int) -> float:
    """One pair's rows appended to a live Parquet export already holding ``held`` rows (the file
    is rewritten whole after every pair: what a long run pays per pair); median of 5."""
    from cbh.outputs.export import LayerExporter, _arrow_table, pair_record, record_rows

    rec = pair_record(result, float(station.altitude_m))
    with tempfile.TemporaryDirectory() as d:
        exp = LayerExporter(Path(d) / "live.parquet", station)
        exp.write_record(rec)
        rows = record_rows(rec, exp.diagnostics)
        exp._table = _arrow_table(rows * max(held // max(len(rows), 1), 1), exp.diagnostics)
        ts = []
        for _ in range(5):
            t0 = time.perf_counter()
            exp.write_record(rec)
            ts.append(time.perf_counter() - t0)
        exp.close()
    return 1e3 * sorted(ts)[2]


if __name__ == "__main__":
    raise SystemExit(main())
