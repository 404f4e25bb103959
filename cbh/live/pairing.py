"""Pairing two cameras' frames by nearest time stamp within a tolerance.

Two cameras of a station are not triggered together: each frame carries its own UTC time.
A pair taken seconds apart is wrong by the clouds' motion (a 10 m/s cloud moves 10 m per
second, which shifts the triangulated point), so frames farther apart than the tolerance
are never paired; they are counted as unpaired and dropped.

The rule (frames of each camera arrive in time order):

1. Look at the oldest waiting frame of each camera, ``a`` and ``b``. If they are more than
   ``tolerance_s`` apart, the older one can never be paired (every later frame of the other
   camera is later still): drop it, counted as unpaired.
2. Otherwise the later of the two, say ``b``, is the best partner for ``a`` (later frames of
   b's camera are farther). But a later frame of a's camera may be closer to ``b``: if one has
   already arrived and is closer, ``a`` is dropped; else ``(a, b)`` is a pair.
3. If no later frame of a's camera has arrived yet and ``a`` and ``b`` are not simultaneous
   (|dt| > ``sync_s``), wait for one, at most until ``b`` has waited ``patience`` further frames
   of its own camera (then pair anyway): the choice is the nearest among frames received.

Memory is bounded: each camera keeps at most ``max_waiting`` frames; the oldest overflow is
dropped and counted.

Clock jumps (``jump_s``): a frame slightly older than its camera's newest waiting frame is
dropped (out of order), but one older by more than ``jump_s`` means the camera's clock stepped
back: the waiting frames stamped after it are dropped and pairing resynchronizes on the new
time (a single frame stamped years ahead cannot block its camera). Frames dropped because the other
camera's waiting frame is more than ``jump_s`` away are reported by :meth:`Pairer.pop_disagreements`.
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field

from cbh.errors import ConfigError
from cbh.result import Frame

__all__ = ["Pairer", "Grouper", "PairingStats", "make_pairer"]


@dataclass
class PairingStats:
    """Counters of one pairer (mutable state, not config)."""

    pairs: int = 0  # pairs formed
    unpaired: dict[str, int] = field(default_factory=dict)  # camera → frames dropped without a partner
    max_dt_s: float = 0.0  # largest |dt| of a formed pair [s]

    def to_dict(self) -> dict:
        return {"pairs": self.pairs, "unpaired": dict(self.unpaired), "max_dt_s": self.max_dt_s}


class Pairer:
    """Pairs frames of two cameras by nearest time stamp within ``tolerance_s``.

    Parameters
    ----------
    cameras : tuple of str
        (camera 1, camera 2); pairs come out in this order.
    tolerance_s : float
        Largest |t1 − t2| of a pair [s].
    sync_s : float
        Frames this close are taken as simultaneous and paired at once, without waiting to
        see whether a closer frame follows [s].
    max_waiting : int
        Frames kept per camera while waiting for a partner.
    jump_s : float or None
        Backward step of one camera's time taken as a clock jump (resynchronize) [s];
        None: never (out-of-order frames are always dropped).

    Examples
    --------
    >>> from datetime import datetime, timezone, timedelta
    >>> t0 = datetime(2015, 10, 29, 4, 58, tzinfo=timezone.utc)
    >>> p = Pairer(("cam1", "cam2"), tolerance_s=0.5)
    >>> p.push(Frame("cam1", t0, None)); p.push(Frame("cam2", t0 + timedelta(seconds=0.01), None))
    >>> [(a.camera, b.camera) for a, b in p.pop_pairs()]
    [('cam1', 'cam2')]
    """

    def __init__(self, cameras: tuple[str, str], tolerance_s: float = 0.5, sync_s: float = 0.02,
                 max_waiting: int = 16, patience: int = 1, jump_s: float | None = None):
        if not tolerance_s > 0:
            raise ConfigError(f"pair tolerance must be > 0 s, got {tolerance_s}")
        if cameras[0] == cameras[1]:
            raise ConfigError(f"pairing needs two different cameras, got {cameras}")
        if max_waiting < 2:
            raise ConfigError(f"max_waiting must be >= 2, got {max_waiting}")
        self.cameras = (cameras[0], cameras[1])
        self.tolerance_s, self.sync_s = float(tolerance_s), float(sync_s)
        self.max_waiting, self.patience = int(max_waiting), int(patience)
        if jump_s is not None and not jump_s > tolerance_s:
            raise ConfigError(f"jump_s ({jump_s}) must exceed the pair tolerance ({tolerance_s})")
        self.jump_s = None if jump_s is None else float(jump_s)
        self._disagree: deque[tuple[str, str, float]] = deque(maxlen=64)
        self._q: dict[str, deque[Frame]] = {c: deque() for c in self.cameras}
        self._ready: list[tuple[Frame, Frame]] = []
        self.stats = PairingStats(unpaired={c: 0 for c in self.cameras})

    def waiting(self) -> dict[str, int]:
        return {c: len(q) for c, q in self._q.items()}

    def push(self, frame: Frame) -> None:
        """Add one frame (of either camera). Out-of-order frames (older than the newest) are dropped."""
        q = self._q.get(frame.camera)
        if q is None:
            raise ConfigError(f"frame of camera {frame.camera!r}, but pairing {self.cameras[0]},{self.cameras[1]}")
        if q and frame.time_utc < q[-1].time_utc:
            back_s = (q[-1].time_utc - frame.time_utc).total_seconds()
            if self.jump_s is None or back_s <= self.jump_s:
                self._drop(frame)
                return
            while q and q[-1].time_utc > frame.time_utc:  # the clock stepped back: drop the
                self._drop(q.pop())  # frames stamped after the new one (the bad time line)
        q.append(frame)
        while len(q) > self.max_waiting:
            self._drop(q.popleft())
        self._match()

    def _drop(self, f: Frame) -> None:
        self.stats.unpaired[f.camera] += 1

    def _disagreement(self, dropped: Frame, other: Frame, dt: float) -> None:
        self._drop(dropped)
        if self.jump_s is not None and dt > self.jump_s:
            self._disagree.append((dropped.camera, other.camera, dt))

    def pop_disagreements(self) -> list[tuple[str, str, float]]:
        """(dropped camera, other camera, other's time − dropped's [s]) for frames dropped because
        the other camera's waiting frame was more than ``jump_s`` away; cleared on return."""
        out = list(self._disagree)
        self._disagree.clear()
        return out

    def _match(self, final: bool = False) -> None:
        qa, qb = self._q[self.cameras[0]], self._q[self.cameras[1]]
        while qa and qb:
            a, b = qa[0], qb[0]
            dt = (b.time_utc - a.time_utc).total_seconds()
            if dt > self.tolerance_s:
                self._disagreement(qa.popleft(), b, dt)
                continue
            if dt < -self.tolerance_s:
                self._disagreement(qb.popleft(), a, -dt)
                continue
            # e = the earlier frame's queue, l = the later one's
            qe, ql = (qa, qb) if dt >= 0 else (qb, qa)
            if len(qe) > 1:
                nxt = abs((qe[1].time_utc - ql[0].time_utc).total_seconds())
                if nxt < abs(dt):
                    self._drop(qe.popleft())
                    continue
            elif abs(dt) > self.sync_s and not final and len(ql) <= self.patience:
                return  # a closer frame of the earlier camera may still come
            fa, fb = qa.popleft(), qb.popleft()
            self.stats.pairs += 1
            self.stats.max_dt_s = max(self.stats.max_dt_s, abs(dt))
            self._ready.append((fa, fb))

    def pop_pairs(self) -> list[tuple[Frame, Frame]]:
        """All pairs formed since the last call, oldest first (camera 1's frame first)."""
        out, self._ready = self._ready, []
        return out

    def flush(self) -> list[tuple[Frame, Frame]]:
        """At the end of a run: pair what can be paired, count the rest as unpaired."""
        self._match(final=True)
        for q in self._q.values():
            while q:
                self._drop(q.popleft())
        return self.pop_pairs()


class Grouper:
    """Groups frames of N ≥ 3 cameras (a camera network) into frame sets by time stamp.

    The anchor is the oldest waiting frame of any camera. Every other camera contributes its
    waiting frame nearest to the anchor within ``tolerance_s``, once its choice is final: it
    has a frame later than anchor + tolerance (later frames are only farther), or its source
    ended (:meth:`end`) or the run ends, or — live cameras — it has fallen behind by
    ``patience`` frames of the cameras that did answer (it went away: the set goes on without
    it, ``None`` in its place; ``patience=None``, for files read as fast as they can be, never
    presumes a camera gone that is only read more slowly). A set needs two frames at least;
    an anchor no other camera matches is dropped as unpaired, and so are frames older than the
    ones chosen. ``pop_pairs`` returns tuples in ``cameras`` order. Out-of-order frames (older
    than their camera's newest) are dropped, also after a clock jump: ``jump_s`` is taken for
    :class:`Pairer`'s interface and not used (no resynchronisation; docs/networks.md, Limits).
    """

    def __init__(self, cameras: tuple[str, ...], tolerance_s: float = 0.5, max_waiting: int = 16,
                 patience: int | None = 2, jump_s: float | None = None):
        if not tolerance_s > 0:
            raise ConfigError(f"pair tolerance must be > 0 s, got {tolerance_s}")
        if len(set(cameras)) != len(cameras) or len(cameras) < 2:
            raise ConfigError(f"grouping needs two or more different cameras, got {cameras}")
        if max_waiting < 2:
            raise ConfigError(f"max_waiting must be >= 2, got {max_waiting}")
        self.cameras = tuple(cameras)
        self.tolerance_s, self.max_waiting = float(tolerance_s), int(max_waiting)
        self.patience = None if patience is None else int(patience)
        self.jump_s = jump_s
        self._ended: set[str] = set()
        self._q: dict[str, deque[Frame]] = {c: deque() for c in self.cameras}
        self._ready: list[tuple] = []
        self.stats = PairingStats(unpaired={c: 0 for c in self.cameras})

    def waiting(self) -> dict[str, int]:
        return {c: len(q) for c, q in self._q.items()}

    def pop_disagreements(self) -> list[tuple[str, str, float]]:
        return []

    def end(self, camera: str) -> None:
        """Camera ``camera``'s source delivers no more frames: the sets go on without it."""
        self._ended.add(camera)
        self._match()

    def push(self, frame: Frame) -> None:
        """Add one frame (of any camera)."""
        q = self._q.get(frame.camera)
        if q is None:
            raise ConfigError(f"frame of camera {frame.camera!r}, but grouping {','.join(self.cameras)}")
        if q and frame.time_utc < q[-1].time_utc:
            self.stats.unpaired[frame.camera] += 1
            return
        q.append(frame)
        while len(q) > self.max_waiting:
            self.stats.unpaired[frame.camera] += 1
            q.popleft()
        self._match()

    def _choice(self, cam: str, t, final: bool, answered: int):
        """(decided, index of the nearest frame within tolerance or None) of one camera."""
        q = self._q[cam]
        dts = [(f.time_utc - t).total_seconds() for f in q]
        near = [i for i, d in enumerate(dts) if abs(d) <= self.tolerance_s]
        best = min(near, key=lambda i: abs(dts[i])) if near else None
        gone = cam in self._ended or (self.patience is not None and answered > self.patience)
        decided = final or (dts and dts[-1] > self.tolerance_s) or gone
        return bool(decided), best

    def _match(self, final: bool = False) -> None:
        while True:
            heads = [(q[0].time_utc, c) for c, q in self._q.items() if q]
            if not heads:
                return
            t, anchor = min(heads)
            behind = max(len(q) for q in self._q.values())  # frames the busiest camera has waiting
            choices = {c: self._choice(c, t, final, behind) for c in self.cameras if c != anchor}
            if not all(d for d, _ in choices.values()):
                return  # a camera may still deliver a nearer frame
            picked = {anchor: self._q[anchor].popleft()}
            for c, (_, i) in choices.items():
                if i is not None:
                    for _ in range(i):  # older than the chosen one: never in a set
                        self.stats.unpaired[c] += 1
                        self._q[c].popleft()
                    picked[c] = self._q[c].popleft()
            if len(picked) < 2:
                self.stats.unpaired[anchor] += 1
                continue
            dt = max(abs((f.time_utc - t).total_seconds()) for f in picked.values())
            self.stats.pairs += 1
            self.stats.max_dt_s = max(self.stats.max_dt_s, dt)
            self._ready.append(tuple(picked.get(c) for c in self.cameras))

    def pop_pairs(self) -> list[tuple]:
        """The frame sets formed since the last call, oldest first (``None`` for a missing camera)."""
        out, self._ready = self._ready, []
        return out

    def flush(self) -> list[tuple]:
        """At the end of a run: group what can be grouped, count the rest as unpaired."""
        self._match(final=True)
        for c, q in self._q.items():
            self.stats.unpaired[c] += len(q)
            q.clear()
        return self.pop_pairs()


def make_pairer(cameras: tuple[str, ...], tolerance_s: float, max_waiting: int, jump_s: float | None,
                live: bool = True):
    """A :class:`Pairer` for two cameras, a :class:`Grouper` for a network (``live``: a camera
    that falls behind the others is presumed gone)."""
    if len(cameras) == 2:
        return Pairer(tuple(cameras), tolerance_s, max_waiting=max_waiting, jump_s=jump_s)
    return Grouper(tuple(cameras), tolerance_s, max_waiting=max_waiting, patience=2 if live else None, jump_s=jump_s)
