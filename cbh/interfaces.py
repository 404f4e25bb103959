"""The small I/O interfaces between the service and the world (OpenSfM's DataSet idea).

- :class:`FrameSource`: where one camera's frames come from (RTSP, HTTP MJPEG/snapshot,
  video file, directory, simulator, in-memory list).
- :class:`ResultSink`: where frame pairs and their results go (MCAP recorder, Rerun,
  CSV/Parquet export, in-memory list).
"""
from __future__ import annotations

from typing import Protocol, runtime_checkable

from cbh.result import Frame, PairResult


@runtime_checkable
class FrameSource(Protocol):
    """One camera's frames. ``read`` blocks up to ``timeout_s`` and returns a Frame or None
    (no frame yet); it raises :class:`cbh.errors.SourceError` when the camera failed (the
    caller reconnects with backoff by calling ``open`` again)."""

    camera: str

    def open(self) -> None: ...

    def read(self, timeout_s: float) -> Frame | None: ...

    def close(self) -> None: ...


@runtime_checkable
class ResultSink(Protocol):
    """Consumes each processed pair. ``write`` must not lose already-written data if it raises."""

    def write(self, frames: tuple[Frame, Frame], result: PairResult) -> None: ...

    def close(self) -> None: ...
