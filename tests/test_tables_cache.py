"""The on-disk cache of a camera pair's tables (cbh/pipeline/tables.py): what is read back is what
would have been built, and a changed camera gets its own entry."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from cbh.pipeline import Pipeline
from cbh.pipeline.tables import tables_key


def _small(station):
    from cbh.sim import SkySimulator, load_scene

    sim = SkySimulator(station, load_scene("single-cumulus"), size_px=240)
    return sim, sim.render()


def test_cached_tables_equal_built_tables(unb_station, tmp_path, monkeypatch):
    monkeypatch.setenv("CBH_CACHE_DIR", str(tmp_path))
    sim, shot = _small(unb_station)
    im1, im2 = shot.views["cam1"].image, shot.views["cam2"].image
    built = Pipeline(sim.station)
    r1 = built.process(im1, im2, shot.time_utc, channels="bgr")
    files = list(tmp_path.glob("tables-*.bin"))
    assert len(files) == 1
    cached = Pipeline(sim.station)
    cached._load_tables()
    assert 0 in cached._rays and 1 in cached._zenith  # before any pair: the cache filled them
    r2 = cached.process(im1, im2, shot.time_utc, channels="bgr")
    assert cached._tables_loaded and not built._tables_loaded
    g1, g2 = built.geometry, cached.geometry
    assert np.array_equal(g1.map_x, g2.map_x) and np.array_equal(g1.rays1_world, g2.rays1_world)
    assert np.array_equal(g1.planes.m0, g2.planes.m0) and g1.planes.scale_px == g2.planes.scale_px
    for i in (0, 1):
        assert np.array_equal(built.static_mask(i), cached.static_mask(i))
        assert i in cached._rays and i in cached._zenith  # read from the cache, not rebuilt
        assert np.array_equal(built.rays_cam(i), cached.rays_cam(i)) and np.array_equal(built.zenith(i), cached.zenith(i))
    assert [L.height_m for L in r1.layers] == [L.height_m for L in r2.layers]
    assert np.array_equal(r1.height_map, r2.height_map, equal_nan=True)


def test_key_changes_with_the_camera_and_the_cache_can_be_off(unb_station, tmp_path, monkeypatch):
    p = Pipeline(unb_station)
    cam2 = p.cam2
    moved = replace(cam2, position_m=cam2.position_m + np.array([0.0, 0.001, 0.0]))
    assert tables_key(p.cam1, cam2, p.config.masks) != tables_key(p.cam1, moved, p.config.masks)
    monkeypatch.setenv("CBH_CACHE_DIR", "off")
    sim, shot = _small(unb_station)
    Pipeline(sim.station).process(shot.views["cam1"].image, shot.views["cam2"].image, shot.time_utc, channels="bgr")
    assert not list(tmp_path.iterdir())


@pytest.mark.parametrize("damage", ["garbage", "truncated"])
def test_a_damaged_cache_entry_is_rebuilt(unb_station, tmp_path, monkeypatch, damage):
    """A cache file cut short (a full disk, a crash mid-copy) or overwritten is ignored with a
    warning and written again; the pair's result is the one without a cache."""
    monkeypatch.setenv("CBH_CACHE_DIR", str(tmp_path))
    sim, shot = _small(unb_station)
    im1, im2 = shot.views["cam1"].image, shot.views["cam2"].image
    r1 = Pipeline(sim.station).process(im1, im2, shot.time_utc, channels="bgr")
    (f,) = tmp_path.glob("tables-*.bin")
    data = f.read_bytes()
    f.write_bytes(b"not a table file" * 100 if damage == "garbage" else data[: len(data) // 2])
    p = Pipeline(sim.station)
    r2 = p.process(im1, im2, shot.time_utc, channels="bgr")
    assert not p._tables_loaded
    assert np.array_equal(r1.height_map, r2.height_map, equal_nan=True)
    assert f.read_bytes() == data  # written again, whole
