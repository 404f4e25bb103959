"""Shared fixtures and helpers (test modules import helpers from here, never from each other):
paths to the real data beside the repo, the preset station, synthetic recorded pairs, and the
rerun CLI."""
from __future__ import annotations

import shutil
import subprocess
from datetime import datetime, timedelta, timezone
from pathlib import Path

import os

import numpy as np
import pytest
from hypothesis import settings

# Property tests run in the default tier, so they are reproducible there: the same examples on
# every run (derandomize). HYPOTHESIS_PROFILE=explore searches fresh random examples.
settings.register_profile("default-tier", derandomize=True, database=None)
settings.register_profile("explore", derandomize=False)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "default-tier"))

from cbh.result import Frame, Histogram, Layer, PairResult, PointSet

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"
OCAM_FILE = SHARED / "data" / "ocamcalib" / "skysol_calib_results.txt"
WAHRSIS_DIR = SHARED / "data" / "wahrsis-2015-10-29"
SAMPLE = REPO / "recordings" / "sample-two-layers.mcap"
T0 = datetime(2024, 3, 1, 12, 0, 0, tzinfo=timezone.utc)
SIZE = 240  # px: small images keep the tests fast


@pytest.fixture(scope="session")
def repo() -> Path:
    return REPO


@pytest.fixture(scope="session")
def shared() -> Path:
    if not SHARED.is_dir():
        pytest.skip("../shared data not present beside the repository")
    return SHARED


@pytest.fixture(scope="session")
def unb_station():
    from cbh.geometry.station import load_station

    return load_station(REPO / "configs" / "unb-lea.toml")


# --- synthetic recorded pairs --------------------------------------------------------------

def small_station(size: int = SIZE):
    from cbh.geometry.station import load_station

    return load_station(REPO / "configs" / "unb-lea.toml").scaled(size)


def synthetic_pair(station, k: int, heights=(1800.0, 4200.0), n_points: int = 60, seed: int = 0,
                   dt_s: float = 10.0, encode: bool = True):
    """A pair whose points are real projections of two cloud layers into both cameras."""
    from cbh.imageio import encode_jpeg

    rng = np.random.default_rng(seed + k)
    cam1, cam2 = station.pair()
    t = T0 + timedelta(seconds=dt_s * k)
    n_layers = 1 + (k % len(heights))  # varies from pair to pair: 1, 2, 1, 2 …
    xyz, lay = [], []
    for i in range(n_layers):
        n = n_points // n_layers
        e = rng.uniform(-2500, 2500, n)
        nn = rng.uniform(-2500, 2500, n)
        z = heights[i] + rng.normal(0, 15.0, n)
        xyz.append(np.stack([e, nn, z], 1))
        lay.append(np.full(n, i, np.int16))
    xyz = np.concatenate(xyz).astype(np.float32)
    lay = np.concatenate(lay)
    px1 = cam1.world_to_pixel(xyz.astype(np.float64) - cam1.position_m).astype(np.float32)
    px2 = cam2.world_to_pixel(xyz.astype(np.float64) - cam2.position_m).astype(np.float32)
    pts = PointSet(xyz, rng.uniform(0, 3, len(xyz)).astype(np.float32), px1, px2, lay)
    layers = [Layer(float(np.percentile(xyz[lay == i, 2], 5)), float(np.median(xyz[lay == i, 2])),
                    float(1.4826 * np.median(np.abs(xyz[lay == i, 2] - np.median(xyz[lay == i, 2])))),
                    0.3 / (i + 1), int((lay == i).sum()), 0.9 - 0.1 * i) for i in range(n_layers)]
    edges = np.arange(0.0, 6001.0, 250.0)
    counts, _ = np.histogram(xyz[:, 2], edges)
    hm = np.full((cam1.model.height, cam1.model.width), np.nan, np.float32)
    hm[40:120, 50:150] = rng.normal(heights[0], 20, (80, 100)).astype(np.float32)
    masks = {}
    imgs = {}
    for c in (cam1, cam2):
        m = np.zeros((c.model.height, c.model.width), bool)
        m[30 + k: 130, 40:160] = True
        masks[c.name] = m
        img = np.full((c.model.height, c.model.width, 3), (200, 150, 100), np.uint8)
        img[m] = (230, 230, 230)
        img[:, :, 1] = (img[:, :, 1].astype(int) + rng.integers(0, 20, img.shape[:2])).clip(0, 255)
        imgs[c.name] = img
    matches = {"lk": np.concatenate([px1, px2], 1).astype(np.float64)}
    res = PairResult(t, (cam1.name, cam2.name), layers, Histogram(edges, counts.astype(np.float64)), pts, hm,
                     masks, {cam1.name: 0.41 + 0.01 * k, cam2.name: 0.40}, {"segment": 3.5, "match": 12.25},
                     ["few_points"] if k % 3 == 2 else [], matches)
    frames = tuple(Frame(c.name, t + timedelta(milliseconds=20 * j), imgs[c.name],
                         encoded=encode_jpeg(imgs[c.name], 85) if encode else None, sequence=k)
                   for j, c in enumerate((cam1, cam2)))
    return frames, res


def write_session(path, station, n: int = 4, **kw):
    from cbh.outputs.record import McapRecorder

    rec = McapRecorder(path, station, {"segment": {"method": "rbr", "threshold": 0.6}}, **kw)
    made = []
    for k in range(n):
        frames, res = synthetic_pair(station, k)
        rec.write(frames, res)
        made.append((frames, res))
    rec.write_status(T0 + timedelta(seconds=10 * n), {"pairs_processed": n, "pairs_dropped": 1, "unpaired": 2,
                                                      "sources": {"cam1": {"state": "ok"}, "cam2": "reconnecting"}})
    rec.close()
    return rec, made


# --- the rerun CLI ------------------------------------------------------------------------------

RERUN = shutil.which("rerun")
needs_cli = pytest.mark.skipif(RERUN is None, reason="the rerun CLI (from rerun-sdk) is not on PATH")


def rrd_verify(path) -> subprocess.CompletedProcess:
    return subprocess.run([RERUN, "rrd", "verify", str(path)], capture_output=True, text=True, timeout=120)


def rrd_print(path, verbose: str = "") -> str:
    args = [RERUN, "rrd", "print"] + ([verbose] if verbose else []) + [str(path)]
    return subprocess.run(args, capture_output=True, text=True, timeout=120).stdout


# --- one small simulated sky, shared -------------------------------------------------------------

SKY_LAYER_M = 1500.0  # the layer of :func:`small_sky`


@pytest.fixture(scope="session")
def small_sky():
    """(simulator, shot): the unb-lea station at 320 px under one cumulus layer at 1500 m
    (coverage 0.4), 2024-06-21 14:00 UTC; rendered once per test session."""
    from cbh.geometry.station import load_station
    from cbh.presets import station_path
    from cbh.sim import SkySimulator, parse_scene

    sc = parse_scene({"name": "small-sky", "time_utc": "2024-06-21T14:00:00Z",
                      "layers": [{"height_m": SKY_LAYER_M, "coverage": 0.4, "texture_scale_m": 800.0, "seed": 3}]})
    sim = SkySimulator(load_station(station_path("unb-lea")), sc, size_px=320)
    return sim, sim.render()
@pytest.fixture(scope="session", autouse=True)
def _table_cache(tmp_path_factory):
    """The pipeline's on-disk table cache (cbh/pipeline/tables.py) in a per-session directory, so
    the suite neither reads stale entries from nor fills the user's ~/.cache/cbh."""
    import os

    old = os.environ.get("CBH_CACHE_DIR")
    os.environ["CBH_CACHE_DIR"] = str(tmp_path_factory.mktemp("cbh-cache"))
    yield
    if old is None:
        os.environ.pop("CBH_CACHE_DIR", None)
    else:
        os.environ["CBH_CACHE_DIR"] = old
