"""A recording as a :class:`~cbh.interfaces.FrameSource`: one camera's recorded frames, in order.

``cbh replay --reprocess`` runs the same service loop as ``cbh run`` over two of these (one
per camera). Frames keep their recorded capture time, bytes (as received) and pair index
(``sequence``); images are decoded by the service, like any other source's.
"""
from __future__ import annotations

from cbh.errors import RecordingError
from cbh.interfaces import EndOfStream, FrameSource
from cbh.result import Frame

__all__ = ["RecordingSource"]


class RecordingSource(FrameSource):
    """One camera's frames from a cbh MCAP recording (non-live: nothing is dropped).

    Parameters
    ----------
    session : Session
        An opened recording (:func:`cbh.outputs.record.open_session`).
    camera : str
        The recorded camera's name.
    """

    kind = "recording"
    live = False

    def __init__(self, session, camera: str):
        if session.count(f"/{camera}/image/compressed") == 0:
            raise RecordingError(f"{session.paths[0]}: no recorded images of camera {camera!r}")
        self.session, self.camera = session, camera
        self._it = None

    def __repr__(self) -> str:
        return f"RecordingSource({self.session.paths[0].name!r}, {self.camera!r})"

    def open(self) -> None:
        if self._it is None:
            self._it = self.session.images(self.camera)

    def read(self, timeout_s: float) -> Frame | None:
        if self._it is None:
            self.open()
        try:
            seq, im = next(self._it)
        except StopIteration:
            raise EndOfStream(self.camera) from None
        return Frame(self.camera, im.time_utc, None, encoded=im.data, format=im.format, sequence=seq)

    def close(self) -> None:
        if self._it is not None:
            self._it.close()
            self._it = None
