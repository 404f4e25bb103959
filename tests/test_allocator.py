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
    e = {k: v for k, v in os.environ.items() if not k.startswith("MALLOC_") and k not in ("CBH_MALLOC_TUNE", "GLIBC_TUNABLES")}
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


@pytest.mark.parametrize("env", [{"CBH_MALLOC_TUNE": "0"}, {"CBH_MALLOC_TUNE": "off"}, {"MALLOC_ARENA_MAX": "2"},
                                 {"MALLOC_TRIM_THRESHOLD_": "0"},
                                 {"GLIBC_TUNABLES": "glibc.malloc.mmap_threshold=131072"}])
def test_the_users_choice_wins(env):
    a, b, _ = _probe(**env)
    assert a == {} and b == {}


def test_the_pipeline_applies_them(unb_station):
    from cbh.pipeline import Pipeline
    from cbh.pipeline.allocator import _state

    Pipeline(unb_station)
    assert _state["done"]


def test_a_refused_mmap_threshold_sets_nothing(monkeypatch):
    """A glibc that refuses the 64 MB threshold gets 32 MB; one that refuses both gets nothing at
    all (trim threshold and top pad alone would freeze the adaptive mmap threshold at 128 kB)."""
    from cbh.pipeline import allocator

    for accept, want in ((lambda p, v: p != -3 or v <= 32 << 20, {"M_MMAP_THRESHOLD": 32 << 20,
                                                                   "M_TRIM_THRESHOLD": 512 << 20, "M_TOP_PAD": 64 << 20}),
                         (lambda p, v: p != -3, {})):
        calls = []

        def fake(p, v, accept=accept):
            calls.append(p)
            return int(accept(p, v))

        monkeypatch.setattr(allocator, "_glibc_mallopt", lambda: fake)
        monkeypatch.setattr(allocator, "_state", {"done": False, "applied": {}})
        for k in [k for k in os.environ if k.startswith("MALLOC_") or k in ("CBH_MALLOC_TUNE", "GLIBC_TUNABLES")]:
            monkeypatch.delenv(k)
        assert allocator.tune_malloc() == want
        if not want:
            assert set(calls) == {-3}  # only the threshold was tried
