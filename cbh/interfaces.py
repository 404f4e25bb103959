"""The small I/O contracts between the wings (OpenSfM's DataSet idea, pysteps' interfaces).

- :class:`FrameSource`: where one camera's frames come from (RTSP, HTTP MJPEG/snapshot,
  video file, directory, recording, simulator, in-memory list).
- :class:`ResultSink`: where frame pairs and their results go (MCAP recorder, Rerun,
  CSV/Parquet export, in-memory list).

Every source and sink subclasses one of these; the service reads only what is declared here
(no probing with ``getattr``, no tests on class names).
"""
from __future__ import annotations

from abc import ABC, abstractmethod
from datetime import datetime
from pathlib import Path

from cbh.result import Frame, PairResult

__all__ = ["FrameSource", "ResultSink", "EndOfStream"]


class EndOfStream(Exception):
    """A finite source has no more frames (not an error)."""


class FrameSource(ABC):
    """One camera's frames.

    ``read`` blocks up to ``timeout_s`` and returns a :class:`Frame` or None (no frame yet);
    it raises :class:`cbh.errors.SourceError` when the camera failed (the caller reconnects
    with backoff by calling ``open`` again) and :class:`EndOfStream` when a
    finite source is exhausted.

    Attributes
    ----------
    camera : str
        Station camera name of the frames.
    live : bool
        True: frames arrive in real time whether or not they are consumed (a camera; the
        service may drop frames to keep up). False: a finite source read as fast as it is
        consumed (files, recordings, the simulator at full speed): nothing is dropped.
    clock : bool
        True: frame times come from a clock (a camera's, a file's), which the service checks
        against the wall clock for jumps. False: simulated time (no wall-clock checks).
    """

    camera: str
    live: bool = True
    clock: bool = True

    def open(self) -> None:
        """Connect or open; idempotent after :meth:`close`."""

    @abstractmethod
    def read(self, timeout_s: float) -> Frame | None: ...

    def close(self) -> None:
        """Release the connection or file (idempotent)."""


class ResultSink(ABC):
    """Consumes each processed pair. ``write`` must not lose already-written data if it raises.

    Attributes
    ----------
    kind : str
        What the sink produces, for the run summary: ``"recorded"`` (MCAP), ``"exported"``
        (tables), ``"viewer"`` (Rerun) or ``"memory"``.
    """

    kind: str = "memory"

    @abstractmethod
    def write(self, frames: tuple[Frame, Frame], result: PairResult) -> None: ...

    def write_status(self, time_utc: datetime | None, stats: dict) -> None:
        """Service status after each pair and on source state changes (default: ignored)."""

    def output_paths(self) -> list[Path]:
        """Files this sink has written so far (default: none)."""
        return []

    def close(self) -> None:
        """Flush and finalize (idempotent)."""
