"""The simulator as a :class:`~cbh.interfaces.FrameSource`: the live service runs on it like on cameras."""
from __future__ import annotations

import threading
import time
from datetime import datetime, timedelta, timezone

from cbh.errors import ConfigError
from cbh.interfaces import EndOfStream, FrameSource
from cbh.result import Frame
from cbh.timeutil import wait_until

__all__ = ["SimSource"]

_SIM_LOCKS: dict[int, threading.Lock] = {}
_SIM_LOCKS_GUARD = threading.Lock()


def _sim_lock(sim) -> threading.Lock:
    with _SIM_LOCKS_GUARD:
        return _SIM_LOCKS.setdefault(id(sim), threading.Lock())


class SimSource(FrameSource):
    """Frames from :class:`cbh.sim.SkySimulator` at simulated times ``start_utc + k · step_s``.

    Parameters
    ----------
    camera : str
    sim : SkySimulator
        Shared by both cameras' sources (calls are serialised by a lock).
    step_s : float
        Simulated time between frames [s].
    start_utc : datetime or None
        First frame's time (default: now, rounded down to the second).
    realtime : bool
        Deliver frame k at wall time open + k · ``pace_s`` (a live camera; the service may drop
        old pairs); False: as fast as they are consumed (lossless).
    pace_s : float or None
        Wall time between frames in realtime mode (default ``step_s``).
    frames : int or None
        Stop after this many frames (None: endless).
    """

    kind = "sim"
    live = False
    clock = False  # simulated time: exempt from the service's wall-clock checks

    def __init__(self, camera: str, sim, step_s: float = 10.0, start_utc: datetime | None = None,
                 realtime: bool = False, pace_s: float | None = None, frames: int | None = None):
        if step_s <= 0:
            raise ConfigError(f"simulator step must be > 0 s, got {step_s}")
        self.camera, self.sim, self.step_s = camera, sim, float(step_s)
        self.start_utc = start_utc or datetime.now(timezone.utc).replace(microsecond=0)
        self.live = bool(realtime)  # realtime: a camera-like live source
        self.pace_s = self.step_s if pace_s is None else float(pace_s)
        self.frames = frames
        self._k = 0
        self._t0 = None

    def __repr__(self) -> str:
        return f"SimSource({self.camera!r}, step_s={self.step_s})"

    def open(self) -> None:
        if self._t0 is None:
            self._t0 = time.monotonic()

    def read(self, timeout_s: float) -> Frame | None:
        if self.frames is not None and self._k >= self.frames:
            raise EndOfStream(self.camera)
        if self.live:
            if not wait_until(self._t0 + self._k * self.pace_s, timeout_s):
                return None
        t = self.start_utc + timedelta(seconds=self._k * self.step_s)
        with _sim_lock(self.sim):
            f = self.sim.frame(self.camera, t)
        self._k += 1
        f.sequence = self._k
        return f

    def close(self) -> None:
        pass
