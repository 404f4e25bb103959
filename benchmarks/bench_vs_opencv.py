"""cbh against the route a computer-vision engineer writes first, in one process on the same pair.

    python benchmarks/bench_vs_opencv.py                         # simulated two-layers, 1920 px
    python benchmarks/bench_vs_opencv.py --scene three-layers --repeat 7
    python benchmarks/bench_vs_opencv.py --real                  # the WAHRSIS pair (no truth)
    python benchmarks/bench_vs_opencv.py --cpu-time              # CPU time, one thread each: robust on a busy machine
    python benchmarks/bench_vs_opencv.py --working-radius 320    # cbh at 640 px working size: faster, less precise
    python benchmarks/bench_vs_opencv.py --deck-m 7000           # one deck of the scene's texture at 7000 m
    python benchmarks/bench_vs_opencv.py --oblique-levels 2      # cbh's boxes grown near the horizon: more precise there

The OpenCV route: rectify both raw fisheye images to a common ``--rect-px`` (1024) px,
``--rect-fov`` (120°) perspective pair looking up, x along the baseline (``cv2.remap``, maps
built once, not timed), grey, ``cv2.StereoSGBM`` (5 px blocks, 1/16 px disparities), then
depth = f·B/disparity along the common optical axis → ENU point → height. cbh: the warm
``Pipeline.process`` on the raw pair (the first call, which builds the per-camera tables, is
not timed either). Both are timed warm, median of ``--repeat`` runs, interleaved (so load on a
shared machine hits both alike); the ratio cbh / OpenCV is what to read under contention.

Accuracy (simulated scenes): dense MdAPE = median |h − h_true| / h_true over the pixels each
method measures that are cloud in truth (OpenCV: each valid disparity's camera-1 raw pixel;
cbh: its height map inside the analysed field); coverage = measured / true-cloud pixels of
camera 1's analysed field (zenith ≤ 80°); layer error: the same log-height histogram layer
method (:func:`cbh.pipeline.layers.histogram_layers`, median height per supported interval
for OpenCV; cbh's own reported layers) against the true layer heights.
"""
from __future__ import annotations

import argparse
import math
import statistics
import time
from pathlib import Path

import cv2
import numpy as np


class OpenCVStereo:
    """Rectify-and-SGBM for two cameras of a station (maps built once in ``__init__``)."""

    def __init__(self, cam1, cam2, size_px: int = 1024, fov_deg: float = 120.0, num_disp: int = 64, block: int = 5):
        o1, o2 = np.asarray(cam1.position_m, float), np.asarray(cam2.position_m, float)
        base = o2 - o1
        self.baseline_m = float(np.linalg.norm(base))
        x = base / self.baseline_m  # rectified frame: x along the baseline, z as close to up as x allows
        up = np.array([0.0, 0.0, 1.0])
        z = up - x * (x @ up)
        z /= np.linalg.norm(z)
        y = np.cross(z, x)
        self.R_world_from_rect = np.stack([x, y, z], axis=1)  # columns: rect axes in ENU
        self.f_px = 0.5 * size_px / math.tan(math.radians(fov_deg) / 2)
        self.c = (size_px - 1) / 2.0
        self.o1 = o1
        u, v = np.meshgrid(np.arange(size_px, dtype=np.float64), np.arange(size_px, dtype=np.float64))
        rays_rect = np.stack([(u - self.c) / self.f_px, (v - self.c) / self.f_px, np.ones_like(u)], axis=-1)
        rays_world = rays_rect.reshape(-1, 3) @ self.R_world_from_rect.T
        rays_world /= np.linalg.norm(rays_world, axis=1, keepdims=True)
        self.maps = []
        for cam in (cam1, cam2):
            p = cam.direction_to_pixel(rays_world)
            p = np.nan_to_num(p, nan=-1e5).reshape(size_px, size_px, 2).astype(np.float32)
            self.maps.append((np.ascontiguousarray(p[..., 0]), np.ascontiguousarray(p[..., 1])))
        self.size = size_px
        self.sgbm = cv2.StereoSGBM_create(minDisparity=0, numDisparities=num_disp, blockSize=block,
                                          P1=8 * block * block, P2=32 * block * block, disp12MaxDiff=1,
                                          uniquenessRatio=10, speckleWindowSize=100, speckleRange=2,
                                          mode=cv2.STEREO_SGBM_MODE_SGBM)

    def heights(self, image1: np.ndarray, image2: np.ndarray) -> np.ndarray:
        """Height above the ENU origin [m] on the rectified camera-1 grid (NaN = no disparity)."""
        g = [cv2.remap(cv2.cvtColor(im, cv2.COLOR_BGR2GRAY), mx, my, cv2.INTER_LINEAR) for im, (mx, my) in
             zip((image1, image2), self.maps)]
        # rectified camera 2 sits at +B along x: a point at depth Z appears shifted by −f·B/Z in it
        disp = self.sgbm.compute(g[0], g[1]).astype(np.float32) / 16.0
        with np.errstate(divide="ignore", invalid="ignore"):
            depth = np.where(disp > 0, self.f_px * self.baseline_m / disp, np.nan)
        # ENU z of the point: o1z + depth · (z-component of the rectified ray (x/f, y/f, 1))
        r = self.R_world_from_rect
        u = (np.arange(self.size, dtype=np.float32) - self.c) / self.f_px
        rz = r[2, 0] * u[None, :] + r[2, 1] * u[:, None] + r[2, 2]
        return (self.o1[2] + depth * rz).astype(np.float32)


def _layers_of(heights: np.ndarray, pipe) -> list[float]:
    """Median height of each supported histogram interval (cbh's layer method on these heights)."""
    from cbh.pipeline.layers import histogram_layers

    h = heights[np.isfinite(heights) & (heights > 0)]
    cfg = pipe.config
    _, intervals = histogram_layers(h, cfg.layers, cfg.filtering)
    out = []
    for lo, hi in intervals:
        sel = h[(h >= lo) & (h < hi)]
        if len(sel) >= max(cfg.layers.min_points, cfg.layers.min_fraction * len(h)):
            out.append(float(np.median(sel)))
    return out


def _score(found: list[float], truth: list[float]) -> str:
    if len(found) != len(truth):
        return f"count {len(found)} vs {len(truth)}"
    return f"max {100 * max(abs(f - t) / t for f, t in zip(found, truth)):.2f} %"


def _positive_m(text: str) -> float:
    h = float(text)
    if not h > 0:
        raise argparse.ArgumentTypeError(f"a deck's height must be above 0 m, not {text}")
    return h


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="two-layers")
    ap.add_argument("--deck-m", type=_positive_m, default=None, metavar="H",
                    help="one deck only: the scene's last layer moved to H m (the sub-plane peak against height)")
    ap.add_argument("--size", type=int, default=1920)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--real", action="store_true", help="the WAHRSIS pair in ../shared/data (no truth)")
    ap.add_argument("--rect-px", type=int, default=1024)
    ap.add_argument("--rect-fov", type=float, default=120.0)
    ap.add_argument("--device", default="cpu", help="cbh's device (cpu or cuda)")
    ap.add_argument("--working-radius", type=float, default=None, metavar="PX",
                    help="cbh's pipeline.working_radius_px (default: the station's, 480): the speed/accuracy trade-off")
    ap.add_argument("--oblique-levels", type=int, default=None, metavar="N",
                    help="cbh's matching.sweep.oblique_levels (default: the station's, 2): boxes grown 2× per level "
                         "where a plane step moves a pixel less (near the horizon)")
    ap.add_argument("--breakdown", action="store_true",
                    help="cbh's dense error split by true deck and by zenith band (median and signed median): "
                         "where the error comes from")
    ap.add_argument("--cpu-time", action="store_true",
                    help="time with process_time, OpenCV and torch on one thread (robust under load; minimum of the runs)")
    a = ap.parse_args()
    clock, pick = time.perf_counter, statistics.median
    if a.cpu_time:
        import torch

        cv2.setNumThreads(1)
        torch.set_num_threads(1)
        clock, pick = time.process_time, min

    from cbh.geometry.station import load_station
    from cbh.pipeline import Pipeline
    from cbh.presets import station_path

    truth = None
    if a.real:
        from cbh.imageio import read_image

        root = Path(__file__).resolve().parents[1]
        d = root.parent / "shared" / "data" / "wahrsis-2015-10-29"
        st = load_station(root / "configs" / "wahrsis-2015-10-29.toml")
        im1, _ = read_image(d / "2015-10-29-12-58-01-wahrsis3-med.jpg")
        im2, _ = read_image(d / "2015-10-29-12-58-01-wahrsis4-med.jpg")
        from datetime import datetime, timezone

        t_utc = datetime(2015, 10, 29, 4, 58, 1, tzinfo=timezone.utc)
    else:
        from cbh.sim import SkySimulator, load_scene

        scene = load_scene(a.scene)
        if a.deck_m is not None:
            from dataclasses import replace

            scene = replace(scene, layers=(replace(scene.layers[-1], height_m=a.deck_m),))
        sim = SkySimulator(load_station(station_path("unb-lea")), scene, size_px=a.size)
        shot = sim.render()
        st, t_utc = sim.station, shot.time_utc
        im1, im2 = shot.views["cam1"].image, shot.views["cam2"].image
        truth = shot.views["cam1"].height_m, [l.height_m for l in shot.layers]

    from cbh.errors import ConfigError

    try:
        from cbh.pipeline import PipelineConfig

        cfg = PipelineConfig.from_dict(st.sections.get("pipeline", {}))
        if a.working_radius is not None:
            cfg = cfg.replace(working_radius_px=a.working_radius)
        if a.oblique_levels is not None:
            from dataclasses import replace

            sweep = replace(cfg.matching.sweep, oblique_levels=a.oblique_levels)
            cfg = cfg.replace(matching=replace(cfg.matching, sweep=sweep))
        pipe = Pipeline(st, config=cfg, device=a.device)
    except ConfigError as e:  # e.g. --device cuda without CUDA: a benchmark skips, it does not fail
        print(f"skipped: {e}")
        return
    cam1, cam2 = pipe.cam1_full, pipe.cam2_full
    ocv = OpenCVStereo(cam1, cam2, a.rect_px, a.rect_fov)
    r = pipe.process(im1, im2, t_utc, channels="bgr")  # warm-up: per-camera tables
    h_ocv = ocv.heights(im1, im2)
    t_cbh, t_ocv = [], []
    for _ in range(a.repeat):
        t0 = clock()
        h_ocv = ocv.heights(im1, im2)
        t_ocv.append(clock() - t0)
        t0 = clock()
        r = pipe.process(im1, im2, t_utc, channels="bgr")
        t_cbh.append(clock() - t0)
    mc, mo = 1000 * pick(t_cbh), 1000 * pick(t_ocv)
    what = "CPU time (1 thread), minimum" if a.cpu_time else "wall time, median"
    print(f"pair {im1.shape[1]}x{im1.shape[0]} ({'real WAHRSIS' if a.real else a.scene}), {what} of {a.repeat} warm runs")
    print(f"  OpenCV rectify {a.rect_px} px/{a.rect_fov:.0f}° + SGBM: {mo:7.1f} ms")
    print(f"  cbh Pipeline.process ({a.device}):        {mc:7.1f} ms   "
          + ", ".join(f"{k} {v:.0f}" for k, v in r.timing_ms.items() if k != "total"))
    print(f"  ratio cbh / OpenCV: {mc / mo:.2f}")
    lay_ocv = _layers_of(h_ocv, pipe)
    lay_cbh = [L.height_m for L in r.layers]
    fmt = lambda hs: "/".join(f"{h:.0f}" for h in hs) or "none"  # noqa: E731
    if truth is None:
        print(f"  layers: OpenCV {fmt(lay_ocv)} m, cbh {fmt(lay_cbh)} m (no truth for the real pair)")
        return
    _accuracy(truth, cam1, pipe, ocv, h_ocv, r, lay_ocv, lay_cbh, fmt)
    if a.breakdown:
        _breakdown(truth, cam1, pipe, r)


def _accuracy(truth, cam1, pipe, ocv, h_ocv, r, lay_ocv, lay_cbh, fmt) -> None:
    """Both routes' dense median error and coverage against the simulator's truth, and their layers."""
    th, tl = truth
    fov = cam1.zenith_map() <= pipe.config.masks.max_zenith_deg
    cloud = np.isfinite(th) & fov
    # OpenCV: each valid rectified pixel → camera 1's raw pixel (its rectification map) → truth
    mx, my = ocv.maps[0]
    ok = np.isfinite(h_ocv)
    xi, yi = np.rint(mx[ok]).astype(int), np.rint(my[ok]).astype(int)
    inside = (xi >= 0) & (xi < th.shape[1]) & (yi >= 0) & (yi < th.shape[0])
    xi, yi, ho = xi[inside], yi[inside], h_ocv[ok][inside]
    tv = th[yi, xi]
    sel = np.isfinite(tv) & fov[yi, xi]
    ape_o = np.abs(ho[sel] - tv[sel]) / tv[sel]
    cov_o = np.zeros(th.shape, bool)
    cov_o[yi[sel], xi[sel]] = True
    have = cloud & np.isfinite(r.height_map)
    ape_c = np.abs(r.height_map[have] - th[have]) / th[have]
    print(f"  truth layers {fmt(tl)} m")
    print(f"  OpenCV: dense MdAPE {100 * np.median(ape_o):.2f} %, coverage {100 * (cov_o & cloud).sum() / cloud.sum():.0f} %"
          f" of true cloud (zenith ≤ 80°), layers {fmt(lay_ocv)} m ({_score(lay_ocv, tl)})")
    print(f"  cbh:    dense MdAPE {100 * np.median(ape_c):.2f} %, coverage {100 * have.sum() / cloud.sum():.0f} %"
          f" of true cloud (zenith ≤ 80°), layers {fmt(lay_cbh)} m ({_score(lay_cbh, sorted(tl))})")


def _breakdown(truth, cam1, pipe, r) -> None:
    """cbh's dense error against the truth, per true deck (pixels within 2 % of its height) and
    per 10° of zenith: share of the measured pixels, MdAPE, signed median (+ = read too high). A
    median error that equals its signed median is a bias (the sub-plane peak, a neighbour's
    height), one well above it is noise (the parallax a plane step gives there)."""
    th, tl = truth
    zen = cam1.zenith_map()
    have = np.isfinite(th) & (zen <= pipe.config.masks.max_zenith_deg) & np.isfinite(r.height_map)
    if not have.any():
        print("  breakdown: no measured cloud pixel")
        return
    e = (r.height_map[have] - th[have]) / th[have]
    tv, z = th[have], zen[have]
    rows = [(f"deck {h:.0f} m", np.abs(tv - h) <= 0.02 * h) for h in sorted(tl)]
    rows += [(f"zenith {lo}-{lo + 10}°", (z >= lo) & (z < lo + 10)) for lo in range(0, 90, 10)]
    print("  cbh's error by part of the sky (share of measured pixels, MdAPE, signed median):")
    for name, m in rows:
        if m.any():
            print(f"    {name:<16} {100 * m.mean():5.1f} %   {100 * np.median(np.abs(e[m])):6.2f} %   "
                  f"{100 * np.median(e[m]):+6.2f} %")


if __name__ == "__main__":
    main()
