"""The C allocator's settings (cbh/pipeline/allocator.py): applied once per process by the first
Pipeline on glibc, never against the user's own MALLOC_* choice or CBH_MALLOC_TUNE=0."""
from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from .conftest import REPO

_PROBE = ("import json; from cbh.pipeline.allocator import tune_malloc, _glibc_mallopt; "
          "a = tune_malloc(); b = tune_malloc(); print(json.dumps([a, b, _glibc_mallopt() is not None]))")


def _probe(**env) -> tuple[dict, dict, bool]:
    e = {k: v for k, v in os.environ.items() if not k.startswith("MALLOC_") and k != "CBH_MALLOC_TUNE"}
    e.update(env, PYTHONPATH=str(REPO))
    out = subprocess.run([sys.executable, "-c", _PROBE], env=e, capture_output=True, text=True, check=True).stdout
    a, b, glibc = json.loads(out)
    return a, b, glibc


def test_settings_applied_once_on_glibc():
    from cbh.pipeline.allocator import MALLOC_SETTINGS

    a, b, glibc = _probe()
    if not glibc:
        pytest.skip("not glibc: nothing to tune")
    assert a == MALLOC_SETTINGS and b == a  # the second call reports the first's, applies nothing again


@pytest.mark.parametrize("env", [{"CBH_MALLOC_TUNE": "0"}, {"MALLOC_ARENA_MAX": "2"}, {"MALLOC_TRIM_THRESHOLD_": "0"}])
def test_the_users_choice_wins(env):
    a, b, _ = _probe(**env)
    assert a == {} and b == {}


def test_the_pipeline_applies_them(unb_station):
    from cbh.pipeline import Pipeline
    from cbh.pipeline.allocator import _state

    Pipeline(unb_station)
    assert _state["done"]
