"""cbh: cloud-base height mapping from two upward-looking fisheye cameras.

The library: camera models (:mod:`cbh.geometry.camera`), stations (:mod:`cbh.geometry.station`), triangulation
(:mod:`cbh.geometry.triangulate`), the simulator (:mod:`cbh.sim`), the pair pipeline
(:mod:`cbh.pipeline`), sources and the live service (:mod:`cbh.live.sources`, :mod:`cbh.live.service`),
recording (:mod:`cbh.outputs.record`), Rerun (:mod:`cbh.outputs.rerun_view`) and export (:mod:`cbh.outputs.export`).
Frames and units: docs/conventions.md. Importing cbh imports nothing heavy.
"""
from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("cbh")
except PackageNotFoundError:  # pragma: no cover - running from a source tree without install
    __version__ = "0+unknown"
