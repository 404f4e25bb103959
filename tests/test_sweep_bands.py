"""The fine pass scores its planes band by band (:class:`cbh.pipeline.sweep._ZnccBand`, for
speed: a band's arrays stay in the core's cache). What a user relies on is that this changes no
number: every score of every plane is the whole region's, bit for bit, whatever the bands, the
window (odd or even half-window: the even one trims the region and grows the grid by a row and a
column), a clock-compensated camera 2 (two images, each with its motion weights), and whether the
plane tables are kept between pairs or cut from the region per band."""
from __future__ import annotations

import cv2
import numpy as np
import pytest

from cbh.geometry.station import load_station
from cbh.pipeline import Pipeline
from cbh.pipeline import sweep as S
from cbh.pipeline import threads
from cbh.presets import station_path


@pytest.fixture(scope="module")
def pair():
    """The simulated two-layers pair at 480 px (its working-size grey images) and its plane maps."""
    from cbh.sim import SkySimulator, load_scene

    sim = SkySimulator(load_station(station_path("unb-lea")), load_scene("two-layers"), size_px=480)
    shot = sim.render()
    pipe = Pipeline(sim.station)
    g1, g2 = (cv2.cvtColor(pipe.to_working(i, shot.views[c].image), cv2.COLOR_BGR2GRAY)
              for i, c in ((0, "cam1"), (1, "cam2")))
    return pipe.geometry.planes, g1, g2


def _views(g2, weighted: bool, shape):
    if not weighted:
        return g2
    rng = np.random.default_rng(3)
    wts = tuple(rng.uniform(0.2, 1.0, (shape[0] // 2, shape[1] // 2)).astype(np.float32) for _ in range(2))
    return S.PlaneViews.nearest([g2, np.roll(g2, 1, axis=1)], [1200.0, 3500.0], 0.0, wts)


@pytest.mark.parametrize("half_window", [3, 4])
@pytest.mark.parametrize("weighted", [False, True])
@pytest.mark.parametrize("n_threads", [1, 2])
def test_bands_score_every_plane_as_the_whole_region(pair, half_window, weighted, n_threads, monkeypatch):
    maps, g1, g2 = pair
    monkeypatch.setattr(threads, "workers", lambda: n_threads)
    monkeypatch.setattr(S, "_BAND_ROWS", 13)  # many bands, of unequal sizes, at this small size
    h, w = g1.shape
    sl = np.s_[6: h - 10, 4: w - 6]
    z = S._HalfZncc(np.ascontiguousarray(g1[sl].astype(np.float32)), _views(g2, weighted, (h, w)), maps, half_window, sl)
    bands = z.bands()
    assert len(bands) >= 4 and len(bands) % n_threads == 0
    covered = np.zeros(z.std1.shape[0], int)
    for b in bands:
        covered[b.rows] += 1
    assert (covered == 1).all()  # the bands tile the grown grid's rows exactly once
    for s in (0.0, 1.0 / 9000.0, 1.0 / 3500.0, 1.0 / 1500.0, 1.0 / 700.0):
        whole = z(s)
        banded = np.concatenate([b(s) for b in bands])
        assert banded.shape == whole.shape
        assert np.array_equal(banded, whole), f"plane 1/{1 / s if s else np.inf:.0f} m differs"


@pytest.mark.parametrize("half_window", [3, 4])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_band_scores_only_the_columns_it_needs_and_the_same_numbers(pair, half_window, seed, monkeypatch):
    """Bands asked for the scores of some pixels (``need``: a sky disc of random size and place,
    a clear stripe, random specks) cover each needed pixel, score it exactly as the whole region
    does (also in a row's last columns, which OpenCV's vector loops leave to scalar code), and a
    band that needs none is left out."""
    maps, g1, g2 = pair
    monkeypatch.setattr(S, "_BAND_ROWS", 13)
    rng = np.random.default_rng(seed)
    h, w = g1.shape
    sl = np.s_[6: h - 10, 4 + 2 * seed: w - 6]
    z = S._HalfZncc(np.ascontiguousarray(g1[sl].astype(np.float32)), g2, maps, half_window, sl)
    hh, wh = z.std1.shape
    yy, xx = np.mgrid[:hh, :wh]
    cy, cx, r = rng.uniform(0.3, 0.7) * hh, rng.uniform(0.2, 0.8) * wh, rng.uniform(0.3, 0.6) * hh
    need = (yy - cy) ** 2 + (xx - cx) ** 2 < r ** 2  # a disc, as the sky
    stripe = int(rng.integers(10, hh - 40))
    need |= rng.random((hh, wh)) < 0.002
    need[stripe: stripe + 30] = False  # clear across a few bands
    need[-1, -1] = True  # the grown grid's last row and column (odd windows replicate them)
    bands = z.bands(need)
    assert len(bands) < len(z.bands())
    covered = np.zeros((hh, wh), int)
    for b in bands:
        covered[b.rows, b.cols] += 1
    assert (covered[need] == 1).all() and covered.max() == 1
    for s in (0.0, 1.0 / 3500.0, 1.0 / 700.0):
        whole = z(s)
        for b in bands:
            assert np.array_equal(b(s), whole[b.rows, b.cols]), f"plane 1/{1 / s if s else np.inf:.0f} m differs"


def test_a_band_narrower_than_the_region_is_narrower_in_its_work():
    """A band whose needed columns lie inside the region reads only those, its halo and the
    alignment margin, not the region's whole width."""
    z = S._HalfZncc.__new__(S._HalfZncc)
    z.k, z.off = 4, 1
    z.mu1 = z.var1 = np.zeros((64, 400), np.float32)
    z.i1 = np.zeros((128, 800), np.float32)
    need = np.zeros((64, 401), bool)
    need[10:20, 200:230] = True
    b = S._ZnccBand(z, 0, 64, need)
    assert b.cols == slice(200, 230)
    assert b.region_cols.stop - b.region_cols.start <= 2 * (30 + 2 * (z.k // 2 + 1) + 2 * S._COL_HALO)
    assert S._ZnccBand(z, 0, 64, np.zeros((64, 401), bool)).cols is None


@pytest.mark.parametrize("shape", ["box", "disc with a clear stripe"])
def test_fine_pass_cost_is_the_plane_by_plane_cost(pair, shape, monkeypatch):
    """The fine pass's cost stack and accepted pixels equal those of scoring each whole plane in
    turn (the way it ran before the bands), with the plane tables kept between calls too; for a
    sky-shaped cloud too, whose bands score only their cloud's columns."""
    maps, g1, g2 = pair
    monkeypatch.setattr(S, "_BAND_ROWS", 11)
    cfg = Pipeline(load_station(station_path("unb-lea"))).config.matching.sweep
    h, w = g1.shape
    cloud = np.zeros((h, w), bool)
    cloud[20: h - 25, 15: w - 30] = True
    if shape != "box":
        yy, xx = np.mgrid[:h, :w]
        cloud &= (yy - h / 2) ** 2 + (xx - w / 2) ** 2 < (0.42 * h) ** 2
        cloud[h // 2 - 40: h // 2 + 40] = False
    s = np.linspace(0.0, 1.0 / 800.0, 15)  # the two layers: 1200 and 3500 m
    try:
        for keep in (False, True):
            _fine_pass_against_planes(maps, g1, g2, cloud, s, cfg, keep)
    finally:
        maps.keep_planes(0.0)  # the process-wide store off again, whatever happened


def _fine_pass_against_planes(maps, g1, g2, cloud, s, cfg, keep: bool) -> None:
    """One fine pass against the plane-by-plane scores (``keep``: with the plane tables kept)."""
    if keep:
        maps.keep_planes(200.0)
        maps.keep_planes(200.0)  # (kept from the second sweep on)
    f = S.fine_pass(g1.astype(np.float32), g2.astype(np.float32), cloud, maps, s, float(s[1]), cfg)
    sl = f.region
    z = S._HalfZncc(np.ascontiguousarray(g1.astype(np.float32)[sl]), g2.astype(np.float32), maps,
                    int(cfg.window_px) // 2, sl)
    ref = np.stack([cv2.multiply(z(float(x)), f.textured) for x in s])
    assert np.array_equal(f.cost, ref)
    best = np.max(np.stack([z(float(x)) for x in s]), axis=0)
    i1 = g1.astype(np.float32)[sl]
    k = int(cfg.window_px)
    mu = cv2.boxFilter(i1, -1, (k, k))
    var = cv2.sqrBoxFilter(i1, cv2.CV_32F, (k, k)) - mu * mu
    m0 = cloud[sl] & (var >= float(cfg.min_texture) ** 2)
    ok = m0 & (cv2.resize(best, (m0.shape[1], m0.shape[0]), interpolation=cv2.INTER_NEAREST) >= cfg.min_zncc)
    assert 0.3 < f.ok.mean() and np.array_equal(f.ok, ok)
