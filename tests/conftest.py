"""Shared fixtures: paths to the real data beside the repo and the preset station."""
from __future__ import annotations

from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"
OCAM_FILE = SHARED / "data" / "ocamcalib" / "skysol_calib_results.txt"
WAHRSIS_DIR = SHARED / "data" / "wahrsis-2015-10-29"


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
