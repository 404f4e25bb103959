"""Frame sources: where one camera's frames come from (:class:`cbh.interfaces.FrameSource`).

Every source yields :class:`cbh.result.Frame` objects with a timezone-aware UTC ``time_utc``
and, where the camera sends compressed bytes, those bytes unchanged in ``Frame.encoded`` (the
MCAP recorder stores them without re-encoding).

=================  ============================================  ==================================
kind               spec (``--source cam=SPEC`` or ``source =``)  time stamp of each frame
=================  ============================================  ==================================
HTTP MJPEG         ``http://host/video.mjpg`` (or ``mjpeg+http``) part header ``X-Timestamp``, else receive time
HTTP snapshot      ``http://host/snap.jpg`` (or ``snapshot+http``) ``X-Timestamp`` header, else receive time
(auto)             any other ``http(s)://`` URL: the reply's       as above
                   Content-Type picks MJPEG (multipart) or
                   snapshot (image/*)
RTSP               ``rtsp://host/stream``                          stream clock + smallest receive lag
video file         ``clip.mp4`` (any file OpenCV/FFmpeg reads)     start + position in the file
image directory    ``path/to/dir/`` (``--watch``: keep polling)    time in the file name, else mtime
simulator          ``sim`` (built by the caller: cbh.sim.SimSource) simulated time
in-memory list     (API only: :class:`MemorySource`)               the frames' own
=================  ============================================  ==================================

File-name time stamps: the first ``YYYY-MM-DD[T_ ]HH:MM:SS[.fff][Z]`` in the name, with or
without the ``-`` and ``:`` separators (``cam1_20151029T045801.000Z.jpg``,
``2015-10-29_04-58-01.jpg``, ``img-20151029045801.jpg``), read as UTC; a name without one uses
the file's modification time. A directory holding several cameras' files must name them
``<camera>_…`` (or ``<camera>-…``, ``<camera>.…``): as soon as one such file is seen, the source
keeps only its camera's files (``cbh run`` sets this from the start when both cameras share a
directory).

``read(timeout_s)`` returns a frame, ``None`` (nothing yet), raises :class:`SourceError` when
the source failed (the service reconnects with backoff by calling ``open()`` again),
:class:`cbh.errors.ImageError` for one corrupt frame (skipped, counted) or
:class:`EndOfStream` when a finite source (file, directory without watch, list) is exhausted.
Sources whose ``live`` attribute is False (files, lists, the simulator running as fast as
possible) are lossless: the service waits for their frames instead of dropping them.
"""
from __future__ import annotations

import base64
import logging
import os
import re
import socket
import time
import urllib.parse
from collections import deque
from datetime import datetime, timedelta, timezone
from pathlib import Path
from typing import Iterable

import cv2

from cbh.errors import ConfigError, ImageError, SourceError
from cbh.interfaces import EndOfStream, FrameSource
from cbh.result import Frame
from cbh.timeutil import parse_time_header, time_from_name, wait_until as _wait_until

__all__ = [
    "EndOfStream", "HttpSource", "MjpegSource", "SnapshotSource", "VideoSource", "DirectorySource",
    "MemorySource", "open_source", "is_sim_spec", "parse_time_header", "time_from_name", "SOURCE_KINDS",
    "IMAGE_SUFFIXES", "VIDEO_SUFFIXES", "camera_prefixed", "quiet_video_logs",
]

log = logging.getLogger(__name__)

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png")
VIDEO_SUFFIXES = (".mp4", ".avi", ".mkv", ".mov", ".m4v", ".mjpg", ".mjpeg", ".webm", ".ts")


_EPOCH = datetime(1970, 1, 1, tzinfo=timezone.utc)


def _now() -> datetime:
    return datetime.now(timezone.utc)


def _finish(frame_bytes: bytes, camera: str, t: datetime, seq: int, decode: bool, what: str) -> Frame:
    """Frame from received bytes: decoded now (``decode``) or left for the consumer (``image=None``).

    Without decoding, a cheap magic-number check still rejects bytes that are no image at all.
    """
    fmt = "png" if frame_bytes[:8] == b"\x89PNG\r\n\x1a\n" else "jpeg"
    if decode:
        from cbh.imageio import decode_image

        img = decode_image(frame_bytes, what=what)
    else:
        if not frame_bytes:
            raise ImageError(f"{what}: empty image data")
        if fmt == "jpeg" and frame_bytes[:2] != b"\xff\xd8":
            raise ImageError(f"{what}: corrupt image data ({len(frame_bytes)} bytes, no JPEG/PNG header)")
        img = None
    return Frame(camera=camera, time_utc=t, image=img, encoded=frame_bytes, format=fmt, sequence=seq)


# --- HTTP (MJPEG stream and snapshots) --------------------------------------------------------

class _HttpConn:
    """A minimal blocking HTTP/1.0 GET on a raw socket whose body can be read incrementally.

    http.client/urllib cannot resume after a socket timeout; an MJPEG stream needs
    ``read(timeout_s)`` to return None and keep the connection.
    """

    def __init__(self, url: str, connect_timeout_s: float):
        u = urllib.parse.urlsplit(url)
        if u.scheme not in ("http", "https"):
            raise SourceError(f"{url}: not an http(s) URL")
        self.url = url
        host = u.hostname or ""
        port = u.port or (443 if u.scheme == "https" else 80)
        path = (u.path or "/") + (f"?{u.query}" if u.query else "")
        try:
            sock = socket.create_connection((host, port), timeout=connect_timeout_s)
            if u.scheme == "https":
                import ssl

                sock = ssl.create_default_context().wrap_socket(sock, server_hostname=host)
        except OSError as exc:
            raise SourceError(f"{_redact(url)}: cannot connect: {exc.strerror or exc}") from None
        self.sock = sock
        hdr = [f"GET {path} HTTP/1.0", f"Host: {u.netloc.rsplit('@', 1)[-1]}", "User-Agent: cbh", "Accept: */*"]
        if u.username is not None:
            cred = f"{urllib.parse.unquote(u.username)}:{urllib.parse.unquote(u.password or '')}"
            hdr.append("Authorization: Basic " + base64.b64encode(cred.encode()).decode())
        self.buf = bytearray()
        try:
            sock.sendall(("\r\n".join(hdr) + "\r\n\r\n").encode("latin-1"))
            head = self._read_until(b"\r\n\r\n", connect_timeout_s, limit=65536)
        except OSError as exc:
            self.close()
            raise SourceError(f"{_redact(url)}: {exc.strerror or exc}") from None
        if head is None:
            self.close()
            raise SourceError(f"{_redact(url)}: no HTTP reply within {connect_timeout_s:g} s")
        lines = head.decode("latin-1").split("\r\n")
        parts = lines[0].split(" ", 2)
        if len(parts) < 2 or not parts[0].startswith("HTTP/") or not parts[1].isdigit():
            self.close()
            raise SourceError(f"{_redact(url)}: not an HTTP reply ({lines[0][:60]!r})")
        self.status = int(parts[1])
        self.headers = _parse_headers(lines[1:])
        if self.status != 200:
            self.close()
            raise SourceError(f"{_redact(url)}: HTTP {self.status} {parts[2] if len(parts) > 2 else ''}".rstrip())

    def _recv(self, timeout_s: float) -> bool:
        """Receive more bytes into ``buf``; False on timeout. SourceError when the peer closed."""
        self.sock.settimeout(max(timeout_s, 1e-3))
        try:
            chunk = self.sock.recv(262144)
        except (socket.timeout, TimeoutError):
            return False
        except OSError as exc:
            raise SourceError(f"{_redact(self.url)}: connection lost: {exc.strerror or exc}") from None
        if not chunk:
            raise EOFError
        self.buf += chunk
        return True

    def _read_until(self, token: bytes, timeout_s: float, limit: int) -> bytes | None:
        deadline = time.monotonic() + timeout_s
        while True:
            i = self.buf.find(token)
            if i >= 0:
                out = bytes(self.buf[:i])
                del self.buf[: i + len(token)]
                return out
            if len(self.buf) > limit:
                raise SourceError(f"{_redact(self.url)}: malformed reply (no {token!r} in {limit} bytes)")
            left = deadline - time.monotonic()
            if left <= 0:
                return None
            try:
                self._recv(left)
            except EOFError:
                raise SourceError(f"{_redact(self.url)}: connection closed by the camera") from None

    def read_body(self, timeout_s: float, max_bytes: int) -> bytes:
        """The whole body (Content-Length or until close)."""
        n = self.headers.get("content-length")
        deadline = time.monotonic() + timeout_s
        want = int(n) if n and n.isdigit() else None
        while want is None or len(self.buf) < want:
            if len(self.buf) > max_bytes:
                raise SourceError(f"{_redact(self.url)}: reply larger than {max_bytes} bytes")
            left = deadline - time.monotonic()
            if left <= 0:
                raise SourceError(f"{_redact(self.url)}: reply incomplete after {timeout_s:g} s")
            try:
                self._recv(left)
            except EOFError:
                if want is not None:
                    raise SourceError(
                        f"{_redact(self.url)}: reply truncated ({len(self.buf)} of {want} bytes)"
                    ) from None
                break
        return bytes(self.buf if want is None else self.buf[:want])

    def close(self) -> None:
        try:
            self.sock.close()
        except OSError:
            pass


def _parse_headers(lines: Iterable[str]) -> dict[str, str]:
    out = {}
    for ln in lines:
        if ":" in ln:
            k, v = ln.split(":", 1)
            out[k.strip().lower()] = v.strip()
    return out


def _redact(url: str) -> str:
    """URL without the password (it goes into logs and error messages)."""
    u = urllib.parse.urlsplit(url)
    if u.password is None:
        return url
    netloc = f"{u.username}:***@{u.hostname}" + (f":{u.port}" if u.port else "")
    return urllib.parse.urlunsplit((u.scheme, netloc, u.path, u.query, u.fragment))


#: Bytes allowed before the first part boundary of an MJPEG stream (RFC 2046 preamble).
_MJPEG_PREAMBLE = 4096

#: Content types a camera may label an image with (besides image/*); an empty header is
#: accepted too (the bytes are checked).
_IMAGE_TYPES = ("application/octet-stream", "binary/octet-stream")


def _check_image_type(url: str, content_type: str) -> None:
    """:class:`SourceError` when a reply is labelled as something other than an image
    (an HTML login or error page served with status 200 is a failed source, not a corrupt frame)."""
    ct = content_type.split(";", 1)[0].strip().lower()
    if ct and not ct.startswith("image/") and ct not in _IMAGE_TYPES:
        hint = " (a login or error page? check the URL and credentials)" if ct in ("text/html", "text/plain") else ""
        raise SourceError(f"{_redact(url)}: the camera replied with Content-Type {ct!r}, not an image{hint}")


def _boundary(content_type: str) -> bytes | None:
    m = re.search(r'boundary="?([^";]+)"?', content_type, re.I)
    if not m:
        return None
    b = m.group(1).strip()
    return (b if b.startswith("--") else "--" + b).encode("latin-1")


class HttpSource(FrameSource):
    """An IP camera over HTTP: MJPEG stream (multipart/x-mixed-replace) or snapshot polling.

    Parameters
    ----------
    camera : str
    url : str
        ``http://[user:pass@]host[:port]/path`` (HTTP Basic auth from the URL).
    mode : {"auto", "mjpeg", "snapshot"}
        ``auto``: the reply's Content-Type decides (multipart → stream; image/* → snapshots).
    interval_s : float
        Snapshot mode: time between polls [s].
    stall_timeout_s : float
        No byte for this long → :class:`SourceError` (the service reconnects) [s].
    decode : bool
        Decode each JPEG (``Frame.image``); False leaves ``image=None`` for the consumer.
    max_frame_bytes : int
        Larger parts are refused as corrupt.
    """

    live = True

    def __init__(self, camera: str, url: str, mode: str = "auto", interval_s: float = 1.0,
                 stall_timeout_s: float = 10.0, decode: bool = True, max_frame_bytes: int = 32 << 20):
        if mode not in ("auto", "mjpeg", "snapshot"):
            raise ConfigError(f"HTTP source mode {mode!r}: choose auto, mjpeg or snapshot")
        self.camera, self.url, self.mode = camera, url, mode
        self.interval_s, self.stall_timeout_s = float(interval_s), float(stall_timeout_s)
        self.decode, self.max_frame_bytes = decode, int(max_frame_bytes)
        self.kind = "http"
        self._conn: _HttpConn | None = None
        self._boundary: bytes | None = None
        self._pending: Frame | None = None  # snapshot fetched by open() in auto mode
        self._last_data = 0.0
        self._next_poll = 0.0
        self._seq = 0
        self._parts = 0  # parts parsed since the stream was opened
        self._last_stamp: datetime | None = None

    def __repr__(self) -> str:
        return f"HttpSource({self.camera!r}, {_redact(self.url)!r}, mode={self.mode!r})"

    def open(self) -> None:
        self.close()
        if self.mode == "snapshot":
            self.kind = "snapshot"
            self._next_poll = 0.0
            return
        conn = _HttpConn(self.url, self.stall_timeout_s)
        ctype = conn.headers.get("content-type", "")
        if "multipart" not in ctype.lower():
            try:
                _check_image_type(self.url, ctype)
            except SourceError:
                conn.close()
                raise
        if "multipart" in ctype.lower():
            b = _boundary(ctype)
            if b is None:
                conn.close()
                raise SourceError(f"{_redact(self.url)}: multipart reply without a boundary")
            self._conn, self._boundary, self.kind = conn, b, "mjpeg"
            self._last_data = time.monotonic()
            self._parts = 0
            return
        if self.mode == "mjpeg":
            conn.close()
            raise SourceError(f"{_redact(self.url)}: expected an MJPEG stream, got Content-Type {ctype!r}")
        # auto mode and a single image: this is a snapshot URL; keep the image as the first frame
        try:
            self.kind = "snapshot"
            self._pending = self._snapshot_frame(conn)
            self._next_poll = time.monotonic() + self.interval_s
        finally:
            conn.close()

    def _snapshot_frame(self, conn: _HttpConn) -> Frame | None:
        _check_image_type(self.url, conn.headers.get("content-type", ""))
        body = conn.read_body(self.stall_timeout_s, self.max_frame_bytes)
        t = parse_time_header(conn.headers.get("x-timestamp"))
        if t is not None and t == self._last_stamp:
            return None  # the camera has no new image since the last poll
        self._last_stamp = t
        t = t or _now()
        self._seq += 1
        return _finish(body, self.camera, t, self._seq, self.decode, f"{self.camera} snapshot")

    def read(self, timeout_s: float) -> Frame | None:
        if self.kind == "snapshot":
            return self._read_snapshot(timeout_s)
        if self._conn is None:
            raise SourceError(f"{self.camera}: source not open")
        return self._read_part(timeout_s)

    def _read_snapshot(self, timeout_s: float) -> Frame | None:
        if self._pending is not None:
            f, self._pending = self._pending, None
            return f
        if not _wait_until(self._next_poll, timeout_s):
            return None
        self._next_poll = max(self._next_poll + self.interval_s, time.monotonic())
        conn = _HttpConn(self.url, self.stall_timeout_s)
        try:
            return self._snapshot_frame(conn)
        finally:
            conn.close()

    def _read_part(self, timeout_s: float) -> Frame | None:
        """One part of the multipart stream; None when it is not complete within ``timeout_s``."""
        conn = self._conn
        deadline = time.monotonic() + timeout_s
        while True:
            frame = self._parse_part()
            if frame is not None:
                return frame
            now = time.monotonic()
            if now - self._last_data > self.stall_timeout_s:
                raise SourceError(f"{_redact(self.url)}: no data for {self.stall_timeout_s:g} s")
            if now >= deadline:
                return None
            try:
                got = conn._recv(min(deadline - now, self.stall_timeout_s))
            except EOFError:
                raise SourceError(f"{_redact(self.url)}: stream closed by the camera") from None
            if got:
                self._last_data = time.monotonic()
            if len(conn.buf) > self.max_frame_bytes + 65536:
                raise SourceError(f"{_redact(self.url)}: no part boundary in {len(conn.buf)} bytes (corrupt stream)")

    def _parse_part(self) -> Frame | None:
        buf, b = self._conn.buf, self._boundary
        # a part starts right at its boundary (after the previous part's CRLF; the first may
        # follow a short preamble): anything else is not an MJPEG stream, however long it runs
        lead = _MJPEG_PREAMBLE if self._parts == 0 else 64
        i = buf.find(b, 0, lead + len(b))
        if i < 0:
            if len(buf) >= lead + len(b):
                raise SourceError(f"{_redact(self.url)}: junk in the MJPEG stream (no part boundary "
                                  f"{b.decode('latin-1')!r} where a part should start)")
            return None
        h_end = buf.find(b"\r\n\r\n", i)
        if h_end < 0:
            return None
        headers = _parse_headers(bytes(buf[i + len(b):h_end]).decode("latin-1").split("\r\n"))
        start = h_end + 4
        n = headers.get("content-length", "")
        if n.isdigit():
            end = start + int(n)
            if int(n) > self.max_frame_bytes:
                raise SourceError(f"{_redact(self.url)}: part of {n} bytes exceeds the limit")
            if len(buf) < end:
                return None
            body = bytes(buf[start:end])
            del buf[:end]
        else:  # no length: the part ends at the next boundary
            j = buf.find(b, start)
            if j < 0:
                return None
            body = bytes(buf[start:j]).rstrip(b"\r\n")
            del buf[:j]
        t = parse_time_header(headers.get("x-timestamp")) or _now()
        self._seq += 1
        self._parts += 1
        return _finish(body, self.camera, t, self._seq, self.decode, f"{self.camera} frame {self._seq}")

    def close(self) -> None:
        if self._conn is not None:
            self._conn.close()
            self._conn = None


def MjpegSource(camera: str, url: str, **kw) -> HttpSource:
    """An HTTP MJPEG (multipart/x-mixed-replace) stream; see :class:`HttpSource`."""
    return HttpSource(camera, url, mode="mjpeg", **kw)


def SnapshotSource(camera: str, url: str, interval_s: float = 1.0, **kw) -> HttpSource:
    """An HTTP snapshot URL polled every ``interval_s`` seconds; see :class:`HttpSource`."""
    return HttpSource(camera, url, mode="snapshot", interval_s=interval_s, **kw)


# --- OpenCV: RTSP and video files -------------------------------------------------------------

def quiet_video_logs() -> None:
    """Silence FFmpeg's and OpenCV's own stderr lines (``moov atom not found``, ``[ WARN:0@…]
    cap.cpp``): a video or RTSP failure is reported once, as our :class:`SourceError` (one
    ``cbh: error:`` line), not as library noise around it. ``OPENCV_FFMPEG_LOGLEVEL`` set by the
    user wins."""
    os.environ.setdefault("OPENCV_FFMPEG_LOGLEVEL", "-8")  # AV_LOG_QUIET; read when FFmpeg opens
    cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_ERROR)


class VideoSource(FrameSource):
    """RTSP stream or video file through OpenCV's FFmpeg backend.

    There are no compressed bytes per frame, so each frame is JPEG-encoded (quality
    ``jpeg_quality``) for recording. Files: time = ``start_utc`` (default: time in the file
    name, else the file's modification time minus its duration) + position in the file; the
    file is read as fast as it is consumed (lossless). RTSP: receive time; live. RTSP goes
    over TCP unless ``OPENCV_FFMPEG_CAPTURE_OPTIONS`` says otherwise (UDP loses packets and
    tears JPEG frames on busy networks).
    """

    def __init__(self, camera: str, uri: str, start_utc: datetime | None = None, jpeg_quality: int = 92,
                 stall_timeout_s: float = 10.0):
        self.camera, self.uri = camera, str(uri)
        self.live = "://" in self.uri
        self.kind = "rtsp" if self.live else "video"
        self.start_utc = start_utc
        self.jpeg_quality = int(jpeg_quality)
        self.stall_timeout_s = float(stall_timeout_s)
        self._cap = None
        self._seq = 0
        self._done = 0  # frames of a file already delivered (for reopening)
        self._lag: float | None = None  # RTSP: receive time − stream time, smallest seen [s]
        self._synced, self._last_pos, self._burst = False, None, 0

    def __repr__(self) -> str:
        return f"VideoSource({self.camera!r}, {_redact(self.uri)!r})"

    def open(self) -> None:
        self.close()
        if not self.live and not Path(self.uri).is_file():
            raise SourceError(f"{self.camera}: video file not found: {self.uri}")
        if self.live and "OPENCV_FFMPEG_CAPTURE_OPTIONS" not in os.environ:
            os.environ["OPENCV_FFMPEG_CAPTURE_OPTIONS"] = "rtsp_transport;tcp"
        quiet_video_logs()
        ms = int(self.stall_timeout_s * 1000)
        params = [cv2.CAP_PROP_OPEN_TIMEOUT_MSEC, ms, cv2.CAP_PROP_READ_TIMEOUT_MSEC, ms]
        cap = cv2.VideoCapture(self.uri, cv2.CAP_FFMPEG, params)
        if not cap.isOpened():
            cap.release()
            raise SourceError(f"{self.camera}: cannot open {_redact(self.uri)} (OpenCV/FFmpeg)")
        self._cap = cap
        self._lag, self._synced, self._last_pos, self._burst = None, False, None, 0
        if not self.live:
            if self.start_utc is None:
                self.start_utc = time_from_name(Path(self.uri).name)
            if self.start_utc is None:
                fps = cap.get(cv2.CAP_PROP_FPS) or 0.0
                n = cap.get(cv2.CAP_PROP_FRAME_COUNT) or 0.0
                dur = n / fps if fps > 0 else 0.0
                mtime = datetime.fromtimestamp(Path(self.uri).stat().st_mtime, tz=timezone.utc)
                self.start_utc = mtime - timedelta(seconds=dur)
            if self._done:  # reopened after an error: skip what was delivered
                cap.set(cv2.CAP_PROP_POS_FRAMES, self._done)

    def read(self, timeout_s: float) -> Frame | None:
        from cbh.imageio import encode_jpeg

        if self._cap is None:
            raise SourceError(f"{self.camera}: source not open")
        t_call = time.monotonic()
        ok, img = self._cap.read()
        waited = time.monotonic() - t_call
        if not ok or img is None:
            if self.live:
                raise SourceError(f"{self.camera}: {_redact(self.uri)}: stream ended or timed out")
            raise EndOfStream(self.camera)
        if img.ndim == 2:
            img = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)
        if self.live:
            pos_s = float(self._cap.get(cv2.CAP_PROP_POS_MSEC)) / 1000.0
            now = _now()
            if not self._synced:
                # FFmpeg hands over the frames it buffered while connecting in one burst; their
                # receive time says nothing about their capture time, so they are skipped until
                # a read has to wait for the camera (then frames arrive as they are sent)
                step = pos_s - self._last_pos if self._last_pos is not None else None
                self._last_pos = pos_s
                self._burst += 1
                if not (step and step > 0 and waited >= 0.5 * step) and self._burst < 200:
                    return None
                self._synced = True
            # capture time = stream clock (RTP time stamps) + the smallest receive lag seen, so
            # network jitter does not jitter the stamps; re-anchored after a stall (lag > 2 s)
            lag = (now - _EPOCH).total_seconds() - pos_s
            if self._lag is None or lag < self._lag or lag - self._lag > 2.0:
                self._lag = lag
            t = _EPOCH + timedelta(seconds=pos_s + self._lag)
        else:
            t = self.start_utc + timedelta(milliseconds=float(self._cap.get(cv2.CAP_PROP_POS_MSEC)))
            self._done += 1
        self._seq += 1
        return Frame(self.camera, t, img, encode_jpeg(img, self.jpeg_quality), "jpeg", self._seq)

    def close(self) -> None:
        if self._cap is not None:
            self._cap.release()
            self._cap = None


# --- directory of timestamped images ---------------------------------------------------------

def camera_prefixed(name: str, camera: str) -> bool:
    """Whether a file name belongs to ``camera`` by the ``<camera>_…`` / ``<camera>-…`` /
    ``<camera>.…`` naming rule of shared image directories."""
    return name.startswith(camera) and name[len(camera):len(camera) + 1] in ("_", "-", ".")


class DirectorySource(FrameSource):
    """Images in a directory, in time order; with ``watch`` new files are picked up as they arrive.

    Time stamps from the file names (module docstring), else modification times. A watched
    file is taken once its size and mtime are unchanged over one poll (so a file being written
    is not read half-way). Without ``watch`` the source ends after the last file.
    """

    def __init__(self, camera: str, path: str | Path, watch: bool = False, poll_s: float = 0.5,
                 decode: bool = True, prefix: str | None = None):
        self.camera, self.path, self.prefix = camera, Path(path), prefix
        self.watch, self.poll_s, self.decode = bool(watch), float(poll_s), decode
        self.live = self.watch
        self.kind = "directory"
        self._seen: set[str] = set()
        self._sizes: dict[str, tuple[int, float]] = {}
        self._queue: deque[tuple[datetime, Path]] = deque()
        self._last_t: datetime | None = None
        self._seq = 0
        self._next_poll = 0.0
        self._scanned = False

    def __repr__(self) -> str:
        return f"DirectorySource({self.camera!r}, {str(self.path)!r}, watch={self.watch})"

    @staticmethod
    def _mine(name: str, prefix: str) -> bool:
        return camera_prefixed(name, prefix)

    def open(self) -> None:
        if not self.path.is_dir():
            raise SourceError(f"{self.camera}: image directory not found: {self.path}")
        self._next_poll = 0.0

    def _scan(self) -> None:
        try:
            entries = [p for p in self.path.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file()]
        except OSError as exc:
            raise SourceError(f"{self.camera}: cannot list {self.path}: {exc.strerror}") from None
        if self.prefix is None and any(self._mine(p.name, self.camera) for p in entries):
            self.prefix = self.camera  # sticky: this directory names its files by camera
        if self.prefix is not None:
            entries = [p for p in entries if self._mine(p.name, self.prefix)]
        new = []
        for p in entries:
            if p.name in self._seen:
                continue
            try:
                st = p.stat()
            except OSError:
                continue
            sig = (st.st_size, st.st_mtime)
            if self.watch and self._sizes.get(p.name) != sig:
                self._sizes[p.name] = sig  # wait one poll for the file to settle
                continue
            t = time_from_name(p.name) or datetime.fromtimestamp(st.st_mtime, tz=timezone.utc)
            new.append((t, p))
        for t, p in sorted(new):
            self._seen.add(p.name)
            self._sizes.pop(p.name, None)
            # a file older than the last one delivered is delivered too: a slightly late file
            # is dropped by the pairer (counted as unpaired), a clock that stepped back is
            # flagged by the service and pairing resynchronizes; never skipped in silence
            self._queue.append((t, p))

    def read(self, timeout_s: float) -> Frame | None:
        deadline = time.monotonic() + timeout_s
        while True:
            if self._queue:
                t, p = self._queue.popleft()
                self._last_t = t
                try:
                    data = p.read_bytes()
                except OSError as exc:
                    raise ImageError(f"{p}: cannot read: {exc.strerror}") from None
                self._seq += 1
                return _finish(data, self.camera, t, self._seq, self.decode, str(p))
            now = time.monotonic()
            if not self.watch and self._scanned:
                raise EndOfStream(self.camera)
            if now >= self._next_poll:
                self._scan()
                self._scanned = True
                self._next_poll = now + self.poll_s
                if self._queue:
                    continue
                if not self.watch:
                    raise EndOfStream(self.camera)
            if now >= deadline:
                return None
            time.sleep(max(0.0, min(self._next_poll, deadline) - now))

    def close(self) -> None:
        pass


# --- in-memory list ---------------------------------------------------------------------------

class MemorySource(FrameSource):
    """Frames from a list (tests, replays); ``live`` makes it behave like a camera for the service.

    ``pace_s`` > 0 delays each frame by that many wall seconds.
    """

    kind = "memory"

    def __init__(self, camera: str, frames: Iterable[Frame], live: bool = False, pace_s: float = 0.0):
        self.camera = camera
        self.frames = list(frames)
        self.live, self.pace_s = bool(live), float(pace_s)
        self._i = 0
        self._next = 0.0

    def open(self) -> None:
        self._next = time.monotonic()

    def read(self, timeout_s: float) -> Frame | None:
        if self._i >= len(self.frames):
            raise EndOfStream(self.camera)
        if self.pace_s > 0:
            if not _wait_until(self._next, timeout_s):
                return None
            self._next = max(self._next + self.pace_s, time.monotonic() - self.pace_s)
        f = self.frames[self._i]
        self._i += 1
        return f

    def close(self) -> None:
        pass


# --- factory ---------------------------------------------------------------------------------

SOURCE_KINDS = ("http", "mjpeg", "snapshot", "rtsp", "video", "directory", "sim")


def is_sim_spec(spec: str) -> bool:
    """True for the source spec that names the simulator (``sim``), which the live wing does not build."""
    return str(spec).strip().lower() in ("sim", "sim:", "simulator")


def open_source(camera, spec: str, *, watch: bool = False, decode: bool = True, interval_s: float = 1.0,
                stall_timeout_s: float = 10.0, base_dir: str | Path | None = None, prefix: str | None = None):
    """The source for one camera from a spec string (URL scheme or path kind).

    Parameters
    ----------
    camera : Camera or str
        Station camera (or its name).
    spec : str
        ``rtsp://…``; ``http(s)://…`` (auto: MJPEG or snapshot by Content-Type),
        ``mjpeg+http://…``, ``snapshot+http://…``; a directory; a video file. Relative paths
        are taken from ``base_dir`` (e.g. the station file's folder) when given.

    Returns
    -------
    FrameSource
        Not yet opened.
    """
    name = camera if isinstance(camera, str) else camera.name
    spec = str(spec).strip()
    if not spec:
        raise ConfigError(f"{name}: empty source")
    low = spec.lower()
    if is_sim_spec(low):
        raise ConfigError(f"{name}: source 'sim' is the simulator, which the caller builds (cbh.sim.SimSource)")
    scheme = low.split("://", 1)[0] if "://" in low else ""
    if scheme in ("rtsp", "rtsps", "rtmp"):
        return VideoSource(name, spec, stall_timeout_s=stall_timeout_s)
    if scheme in ("http", "https", "mjpeg+http", "mjpeg+https", "snapshot+http", "snapshot+https"):
        mode = "auto"
        if "+" in scheme:
            mode, _, rest = scheme.partition("+")
            spec = rest + spec[len(scheme):]
        elif urllib.parse.urlsplit(spec).path.lower().endswith(IMAGE_SUFFIXES):
            mode = "snapshot"
        return HttpSource(name, spec, mode=mode, interval_s=interval_s, stall_timeout_s=stall_timeout_s,
                          decode=decode)
    if scheme:
        raise ConfigError(
            f"{name}: unsupported source scheme {scheme!r} in {_redact(spec)!r} "
            "(use rtsp://, http(s)://, mjpeg+http://, snapshot+http://, a directory, a video file or 'sim')"
        )
    path = Path(spec).expanduser()
    if not path.is_absolute() and base_dir is not None and not path.exists():
        path = Path(base_dir) / path
    if path.is_dir():
        return DirectorySource(name, path, watch=watch, decode=decode, prefix=prefix)
    if path.is_file():
        if path.suffix.lower() in IMAGE_SUFFIXES:
            raise ConfigError(f"{name}: source {spec!r} is a single image; give its directory instead")
        return VideoSource(name, path, start_utc=None, stall_timeout_s=stall_timeout_s)
    raise ConfigError(f"{name}: source {spec!r} is not a URL, and no such file or directory")


def decode_frame(frame: Frame, what: str | None = None) -> Frame:
    """Decode ``frame.encoded`` into ``frame.image`` if not yet decoded (ImageError if corrupt)."""
    if frame.image is None:
        from cbh.imageio import decode_image

        frame.image = decode_image(frame.encoded or b"", what=what or f"{frame.camera} frame {frame.sequence}")
    return frame
