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


def test_fine_pass_cost_is_the_plane_by_plane_cost(pair, monkeypatch):
    """The fine pass's cost stack and accepted pixels equal those of scoring each whole plane in
    turn (the way it ran before the bands), with the plane tables kept between calls too."""
    maps, g1, g2 = pair
    monkeypatch.setattr(S, "_BAND_ROWS", 11)
    cfg = Pipeline(load_station(station_path("unb-lea"))).config.matching.sweep
    h, w = g1.shape
    cloud = np.zeros((h, w), bool)
    cloud[20: h - 25, 15: w - 30] = True
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
