"""cbh: cloud-base height mapping from two upward-looking fisheye cameras.

Use as a library (README, "Use as a library")::

    import cbh
    pipe = cbh.Pipeline(cbh.load_station("station.toml"))
    r = pipe.process("cam1.jpg", "cam2.jpg", "2015-10-29T04:58:01Z")   # paths, or arrays + channels="rgb"|"bgr"
    [(L.height_m, L.altitude_m, L.cover) for L in r.layers]
    df = cbh.layer_table([r])                                           # pandas, one row per layer

The package: camera models and stations (:mod:`cbh.geometry`), the pair pipeline
(:mod:`cbh.pipeline`), the live service (:mod:`cbh.live`), recording, Rerun and export
(:mod:`cbh.outputs`), the simulator (:mod:`cbh.sim`) and what each command does
(:mod:`cbh.actions`). Frames and units: docs/conventions.md. ``import cbh`` imports nothing
heavy: the names below are loaded on first use.
"""
from importlib import import_module
from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("cbh")
except PackageNotFoundError:  # pragma: no cover - running from a source tree without install
    __version__ = "0+unknown"

#: Public name → module that defines it (loaded lazily by :func:`__getattr__`).
_EXPORTS = {
    "Pipeline": "cbh.pipeline",
    "PipelineConfig": "cbh.pipeline",
    "load_station": "cbh.actions.station",
    "Station": "cbh.geometry.station",
    "PairResult": "cbh.result",
    "Layer": "cbh.result",
    "Frame": "cbh.result",
    "layer_table": "cbh.outputs.export",
    "sun_position": "cbh.geometry.sun",
    "parse_utc": "cbh.timeutil",
    "CbhError": "cbh.errors",
    "ConfigError": "cbh.errors",
    "ImageError": "cbh.errors",
    "InputError": "cbh.errors",
}

__all__ = ["__version__", *_EXPORTS]


def __getattr__(name: str):
    if name in _EXPORTS:
        value = getattr(import_module(_EXPORTS[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'cbh' has no attribute {name!r}")


def __dir__():
    return sorted(list(globals()) + list(_EXPORTS))
