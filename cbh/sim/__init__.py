"""Synthetic stereo skies with exact ground truth (issue 3).

- :mod:`cbh.sim.scene`: the scene TOML (layers, sun, sky, image, obstacles, imperfections).
- :mod:`cbh.sim.noise`: the world-space fractal cloud texture.
- :mod:`cbh.sim.render`: :class:`SkySimulator` renders a scene through a station's cameras.
- :mod:`cbh.sim.source`: :class:`SimSource`, the simulator as a frame source for the service.
- :mod:`cbh.sim.io`: writing shots (images + truth) to a folder, as ``cbh simulate`` does.
- :mod:`cbh.sim.photo`: stereo pairs built from a real sky photograph (real texture, known height).

Example::

    from cbh.sim import SkySimulator, load_scene
    from cbh.geometry.station import load_station
    sim = SkySimulator(load_station("configs/unb-lea.toml"), load_scene("two-layers"), size_px=480)
    shot = sim.render()                      # all cameras at the scene's start time
    shot.views["cam1"].image                 # (480, 480, 3) uint8 BGR
    shot.views["cam1"].height_m              # (480, 480) float32, NaN off-cloud
"""
from cbh.sim.render import SimShot, SimView, SkySimulator
from cbh.sim.source import SimSource
from cbh.sim.scene import CloudLayer, Imperfection, Obstacle, Scene, load_scene, parse_scene

__all__ = [
    "SkySimulator", "SimShot", "SimView", "Scene", "CloudLayer", "Obstacle", "Imperfection",
    "load_scene", "parse_scene", "SimSource",
]
