"""Triangulation throughput: pairs per second, numpy vs torch vs the paper's per-point SVD loop.

Run: python benchmarks/bench_triangulate.py [--sizes 1e6 1e7] [--dtype float32]
"""
from __future__ import annotations

import argparse
import time

import numpy as np
import torch

from cbh.geometry.triangulate import triangulate, triangulate_svd, triangulate_svd_loop


def rays(n, dtype, seed=0):
    rng = np.random.default_rng(seed)
    pts = np.column_stack([rng.uniform(-5e3, 5e3, n), rng.uniform(-5e3, 5e3, n), rng.uniform(300, 9e3, n)])
    o1, o2 = np.zeros(3), np.array([50.0, 0.0, 0.0])
    d1 = pts - o1
    d2 = pts - o2
    d1 /= np.linalg.norm(d1, axis=1, keepdims=True)
    d2 /= np.linalg.norm(d2, axis=1, keepdims=True)
    return o1.astype(dtype), d1.astype(dtype), o2.astype(dtype), d2.astype(dtype)


def best_of(fn, repeat):
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--sizes", nargs="+", type=float, default=[1e6, 1e7])
    ap.add_argument("--dtypes", nargs="+", default=["float32", "float64"])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--loop-n", type=int, default=20000, help="pairs for the per-point SVD loop")
    args = ap.parse_args()
    print(f"torch threads: {torch.get_num_threads()}")
    loop_rate = None
    for dtype in args.dtypes:
        for n in map(int, args.sizes):
            o1, d1, o2, d2 = rays(n, dtype)
            t_np = best_of(lambda: triangulate(o1, d1, o2, d2), args.repeat)
            tt = [torch.from_numpy(a) for a in (o1, d1, o2, d2)]
            t_th = best_of(lambda: triangulate(*tt), args.repeat)
            print(f"{dtype:8s} N={n:>9,d}  numpy {n / t_np / 1e6:7.1f} M pairs/s ({t_np * 1e3:7.1f} ms)"
                  f"   torch {n / t_th / 1e6:7.1f} M pairs/s ({t_th * 1e3:7.1f} ms)")
    o1, d1, o2, d2 = rays(args.loop_n, "float64")
    t_loop = best_of(lambda: triangulate_svd_loop(o1, d1, o2, d2), 1)
    loop_rate = args.loop_n / t_loop
    t_bsvd = best_of(lambda: triangulate_svd(o1, d1, o2, d2), args.repeat)
    t_vec = best_of(lambda: triangulate(o1, d1, o2, d2), args.repeat)
    print(f"per-point SVD loop (paper): {loop_rate / 1e3:.1f} k pairs/s;  batched SVD: {args.loop_n / t_bsvd / 1e6:.2f} M pairs/s;"
          f"  vectorized closest approach: {args.loop_n / t_vec / 1e6:.1f} M pairs/s"
          f"  → speed-up vs loop at N={args.loop_n}: {t_loop / t_vec:,.0f}x")


if __name__ == "__main__":
    main()
