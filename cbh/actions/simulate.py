"""``cbh simulate`` in library terms: a synthetic stereo sky sequence with exact truth, to a folder."""
from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass
from datetime import datetime, timedelta
from pathlib import Path
from typing import Iterator

from cbh.errors import ConfigError

__all__ = ["SimulatedFrame", "simulate_to_folder"]


@dataclass
class SimulatedFrame:
    """One written time step (for the progress line)."""

    shot: object  # cbh.sim.SimShot
    seconds: float  # render + write time [s]

    def line(self) -> str:
        from cbh.sim.io import time_tag

        s = self.shot
        clouds = "  ".join(f"{n}: cloud {100.0 * v.cloud_mask.mean():.1f} %" for n, v in s.views.items())
        layers = ", ".join(f"{l.height_m:g} m" for l in s.layers) or "none"
        return (f"{time_tag(s.time_utc)}  {clouds}  layers {layers}  sun z={s.sun_zenith_deg:.1f} "
                f"az={s.sun_azimuth_deg:.1f} deg  ({self.seconds:.2f} s)")


def simulate_to_folder(out, *, station=None, scene="two-layers", frames: int = 1, cadence_s: float = 10.0,
                       start_utc: datetime | None = None, size_px: int | None = None,
                       clock_offsets=()) -> Iterator[SimulatedFrame]:
    """Render ``frames`` time steps of every camera of a station looking at a scene into ``out``.

    Writes ``out/<camera>/<camera>_<YYYYmmddTHHMMSS.fffZ>.jpg``, ``out/truth/<time>.npz`` (per
    camera ``height_m``, ``cloud_mask``) and ``.json`` (layers, sun), ``out/station.toml`` (the
    scaled station: ``out`` can be processed as it is) and ``out/scene.toml``. A generator:
    one :class:`SimulatedFrame` per written step.

    Parameters
    ----------
    station, scene : str or path-like, optional
        Station / scene TOML or preset name (default: ``unb-lea``, ``two-layers``).
    frames : int
        Number of time steps (≥ 1).
    cadence_s : float
        Simulated time between steps [s] (> 0).
    start_utc : datetime, optional
        First step's time (default: the scene's ``time_utc``).
    size_px : int, optional
        Image width [px] (calibration scaled); at most :data:`cbh.sim.render.MAX_SIZE_PX`.
    clock_offsets : sequence of str
        ``CAMERA=SECONDS``: that camera captures this late, its files stamped on time
        (overrides the scene's ``[[imperfections]]``; the truth JSON has every camera's real
        capture time).
    """
    from cbh.actions.station import load_station
    from cbh.presets import scene_path, station_path
    from cbh.sim import SkySimulator, load_scene
    from cbh.sim.io import write_shot

    if frames < 1:
        raise ConfigError(f"frames must be >= 1, got {frames}")
    if not (math.isfinite(cadence_s) and cadence_s > 0):
        raise ConfigError(f"cadence must be > 0 s, got {cadence_s}")
    from cbh.fileio import refuse_inputs

    out = Path(out)
    if out.exists() and not out.is_dir():
        raise ConfigError(f"output folder is a file, not a directory: {out}")
    st_file = station_path(station) if station else station_path()
    scene_file = scene_path(scene)
    refuse_inputs([out / "station.toml", out / "scene.toml"], [st_file, scene_file], "--out")
    st = load_station(st_file)
    sc = load_scene(scene_file)
    if clock_offsets:
        from cbh.sim.scene import with_clock_offsets

        sc = with_clock_offsets(sc, clock_offsets)
    sim = SkySimulator(st, sc, size_px=size_px)
    out.mkdir(parents=True, exist_ok=True)
    (out / "station.toml").write_text(sim.station.to_toml())
    (out / "scene.toml").write_bytes(Path(scene_file).read_bytes())
    t0 = sc.time_utc if start_utc is None else start_utc
    for i in range(frames):
        tic = time.perf_counter()
        shot = sim.render(t0 + timedelta(seconds=i * cadence_s))
        write_shot(shot, out, sc.image.jpeg_quality, _ground_truth(sim, shot.time_utc))
        yield SimulatedFrame(shot, time.perf_counter() - tic)


def _ground_truth(sim, time_utc) -> dict:
    """The scene's own cloud shadow on the station's ground grid (:func:`cbh.sim.ground.ground_shade`)."""
    import numpy as np

    from cbh.sim.ground import ground_shade

    grid = sim.station.ground
    X, Y = np.meshgrid(grid.x_m, grid.y_m)
    pts = np.column_stack([X.ravel(), Y.ravel(), np.zeros(X.size)])
    shade, thick = ground_shade(sim, time_utc, pts)
    return {"ground_shade": shade.reshape(X.shape).astype(np.float32),
            "ground_thickness": thick.reshape(X.shape).astype(np.float32),
            "ground_x_m": grid.x_m, "ground_y_m": grid.y_m}


def simulate_drone_to_folder(out, *, station=None, positions: int = 20, cadence_s: float = 1.0,
                             start_utc: datetime | None = None, size_px: int | None = None, log_offset_s: float = 3.0,
                             seed: int = 0) -> Iterator[str]:
    """Render a night drone flight (:mod:`cbh.sim.drone`) into ``out``: every camera's frames,
    the log as CSV and DJI SRT, ``station.toml`` and ``truth.json``. A generator of progress lines."""
    from cbh.actions.station import load_station
    from cbh.fileio import refuse_inputs
    from cbh.presets import station_path
    from cbh.sim.drone import DEFAULT_START, paper_plan, render_flight

    out = Path(out)
    if out.exists() and not out.is_dir():
        raise ConfigError(f"output folder is a file, not a directory: {out}")
    st_file = station_path(station) if station else station_path()
    refuse_inputs([out / "station.toml"], [st_file], "--out")
    st = load_station(st_file)
    if size_px is not None:
        st = st.scaled(size_px)
    tic = time.perf_counter()
    gen = render_flight(st, out, paper_plan(positions), start_utc=start_utc or DEFAULT_START, cadence_s=cadence_s,
                        log_offset_s=log_offset_s, seed=seed)
    while True:
        try:
            i, n = next(gen)
        except StopIteration as stop:
            flight = stop.value
            break
        if i % 100 == 0 or i == n - 1:
            yield f"frame {i + 1} of {n}  ({time.perf_counter() - tic:.1f} s)"
    yield (f"wrote {flight.times_s.size} frames of {len(st.cameras)} cameras, {len(flight.plan.positions_m)} hover "
           f"positions, the log {log_offset_s:+g} s off the cameras' clock: {out}/flight.csv, {out}/flight.SRT, "
           f"{out}/truth.json; take-off: --takeoff={json.loads((out / 'truth.json').read_text())['takeoff_arg']}")
