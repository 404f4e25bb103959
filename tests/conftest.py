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
