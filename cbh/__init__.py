"""cbh: cloud-base height mapping from two upward-looking fisheye cameras.

The library: camera models (:mod:`cbh.camera`), stations (:mod:`cbh.station`), triangulation
(:mod:`cbh.triangulate`), the simulator (:mod:`cbh.sim`), the pair pipeline
(:mod:`cbh.pipeline`), sources and the live service (:mod:`cbh.sources`, :mod:`cbh.service`),
recording (:mod:`cbh.record`), Rerun (:mod:`cbh.viz`) and export (:mod:`cbh.export`).
Frames and units: docs/conventions.md. Importing cbh imports nothing heavy.
"""
from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("cbh")
except PackageNotFoundError:  # pragma: no cover - running from a source tree without install
    __version__ = "0+unknown"
