"""A loopback HTTP camera emulator: serves simulator (or any) frames as MJPEG and snapshots.

Like the IP fisheye cameras used for sky imaging, for each camera it serves

- ``GET /mjpeg/<camera>``: ``multipart/x-mixed-replace`` stream, one JPEG part per frame, each
  part with ``Content-Length`` and ``X-Timestamp`` (frame UTC time, ISO 8601);
- ``GET /snapshot/<camera>.jpg``: the current frame, ``X-Timestamp`` header.

Frame ``k`` (time ``start_utc + k · step_s``) becomes current at wall time ``k / fps`` after
the server started, for both cameras alike, so their frames pair exactly. Faults can be
injected for tests and demos: :meth:`CameraServer.drop` (a camera goes offline for a while:
its connections are cut and new ones refused with 503) and :meth:`CameraServer.corrupt`
(the next frames are garbage bytes).

Run one for a demo (it writes the station scaled to ``--size`` and prints the ``cbh run``
command line to use it)::

    python -m cbh.sim.camera_server --scene two-layers --size 960 --fps 1 --port 8080

:class:`RtspCameraServer` does the same over RTSP (RTP/JPEG), for tests of the RTSP path.
"""
from __future__ import annotations

import sys
import logging
import threading
import time
from collections import OrderedDict
from datetime import datetime, timedelta, timezone
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Callable

__all__ = ["CameraServer", "RtspCameraServer", "sim_frames"]

log = logging.getLogger(__name__)

BOUNDARY = "cbhframe"


def sim_frames(sim) -> Callable[[str, datetime], bytes]:
    """Frame provider from a :class:`cbh.sim.SkySimulator`: (camera, time) → JPEG bytes."""
    lock = threading.Lock()

    def get(camera: str, t: datetime) -> bytes:
        with lock:
            f = sim.frame(camera, t)
        if f.encoded is not None:
            return f.encoded
        from cbh.imageio import encode_jpeg

        return encode_jpeg(f.image)

    return get


def _listen(server_cls, host: str, port: int, handler, what: str):
    """``server_cls((host, port), handler)``; a port in use is one-line :class:`ConfigError`."""
    import errno

    from cbh.errors import ConfigError

    try:
        return server_cls((host, port), handler)
    except OSError as exc:
        if exc.errno == errno.EADDRINUSE:
            raise ConfigError(f"{what}: port {port} on {host} is already in use") from None
        raise ConfigError(f"{what}: cannot listen on {host}:{port}: {exc.strerror or exc}") from None


def _client_host(bound: str) -> str:
    """The address a client on this machine connects to for a server bound to ``bound``: the
    address itself, or the loopback for a wildcard (0.0.0.0 / :: listen on every interface but
    are not an address to connect to)."""
    return "127.0.0.1" if bound in ("", "0.0.0.0", "::") else bound


class CameraServer:
    """HTTP server on 127.0.0.1 serving each camera's frames; use as a context manager.

    Parameters
    ----------
    frames : callable (camera, time_utc) → bytes
        JPEG bytes of a camera at a time (e.g. :func:`sim_frames`).
    cameras : sequence of str
    fps : float
        Frames per wall second (the emulated cameras' rate).
    step_s : float
        Frame time between frames [s] (``step_s`` > 1/fps fast-forwards the sky).
    start_utc : datetime, optional
        Time of frame 0 (default: now, whole second).
    host, port : str, int
        Port 0 picks a free port (see :attr:`port`).
    cache : int
        Frames kept in memory (both cameras).
    """

    def __init__(self, frames: Callable[[str, datetime], bytes], cameras, fps: float = 5.0, step_s: float | None = None,
                 start_utc: datetime | None = None, host: str = "127.0.0.1", port: int = 0, cache: int = 16):
        self.frames, self.cameras = frames, list(cameras)
        self.fps = float(fps)
        self.step_s = 1.0 / self.fps if step_s is None else float(step_s)
        self.start_utc = start_utc or datetime.now(timezone.utc).replace(microsecond=0)
        self._cache: OrderedDict = OrderedDict()
        self._cache_n = int(cache)
        self._lock = threading.Lock()
        self._down_until: dict[str, float] = {}
        self._corrupt: dict[str, int] = {}
        self._gen: dict[str, int] = {c: 0 for c in self.cameras}  # bumps to cut a camera's streams
        self.requests: dict[str, int] = {c: 0 for c in self.cameras}
        self.frames_sent: dict[str, int] = {c: 0 for c in self.cameras}
        self._closing = threading.Event()
        self._t0 = time.monotonic()
        server = self

        class Handler(BaseHTTPRequestHandler):
            protocol_version = "HTTP/1.0"

            def log_message(self, fmt, *args):  # quiet; goes to the cbh logger at debug
                log.debug("camera server: " + fmt % args)

            def do_GET(self):
                server._serve(self)

        self._httpd = _listen(ThreadingHTTPServer, host, port, Handler, "camera server")
        self._httpd.daemon_threads = True
        self._thread: threading.Thread | None = None

    # -- public ------------------------------------------------------------------------------
    @property
    def port(self) -> int:
        return self._httpd.server_address[1]

    def url(self, camera: str, kind: str = "mjpeg") -> str:
        """``http://HOST:PORT/mjpeg/<camera>`` or ``…/snapshot/<camera>.jpg`` (HOST: the bound
        address; the loopback when bound to every interface)."""
        host = _client_host(self._httpd.server_address[0])
        if kind == "mjpeg":
            return f"http://{host}:{self.port}/mjpeg/{camera}"
        if kind == "snapshot":
            return f"http://{host}:{self.port}/snapshot/{camera}.jpg"
        raise ValueError(f"kind must be 'mjpeg' or 'snapshot', got {kind!r}")

    def start(self) -> "CameraServer":
        self._t0 = time.monotonic()
        self._thread = threading.Thread(target=self._httpd.serve_forever, kwargs={"poll_interval": 0.1},
                                        name="cbh-camera-server", daemon=True)
        self._thread.start()
        return self

    def close(self) -> None:
        self._closing.set()
        self._httpd.shutdown()
        self._httpd.server_close()

    def __enter__(self) -> "CameraServer":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()

    def drop(self, camera: str, seconds: float) -> None:
        """Camera goes offline: open streams are cut now, requests refused (503) for ``seconds``."""
        with self._lock:
            self._down_until[camera] = time.monotonic() + seconds
            self._gen[camera] += 1

    def corrupt(self, camera: str, n: int = 1) -> None:
        """The camera's next ``n`` frames (stream parts or snapshots) are garbage bytes."""
        with self._lock:
            self._corrupt[camera] = self._corrupt.get(camera, 0) + int(n)

    def index_now(self) -> int:
        return int((time.monotonic() - self._t0) * self.fps)

    def frame_time(self, k: int) -> datetime:
        return self.start_utc + timedelta(seconds=k * self.step_s)

    # -- serving -----------------------------------------------------------------------------
    def _frame(self, camera: str, k: int) -> bytes:
        key = (camera, k)
        with self._lock:
            if key in self._cache:
                return self._cache[key]
        data = self.frames(camera, self.frame_time(k))
        with self._lock:
            self._cache[key] = data
            while len(self._cache) > self._cache_n:
                self._cache.popitem(last=False)
        return data

    def _payload(self, camera: str, k: int) -> bytes:
        with self._lock:
            bad = self._corrupt.get(camera, 0)
            if bad:
                self._corrupt[camera] = bad - 1
        if bad:
            return b"\x00garbage-not-a-jpeg\x00" * 64
        return self._frame(camera, k)

    def _down(self, camera: str) -> bool:
        return time.monotonic() < self._down_until.get(camera, 0.0)

    def _serve(self, h: BaseHTTPRequestHandler) -> None:
        parts = h.path.split("?", 1)[0].strip("/").split("/")
        if len(parts) != 2 or parts[0] not in ("mjpeg", "snapshot"):
            h.send_error(404, "use /mjpeg/<camera> or /snapshot/<camera>.jpg")
            return
        kind, cam = parts[0], parts[1]
        if kind == "snapshot" and cam.endswith(".jpg"):
            cam = cam[:-4]
        if cam not in self._gen:
            h.send_error(404, f"no camera {cam!r}")
            return
        self.requests[cam] += 1
        if self._down(cam):
            h.send_error(503, "camera offline")
            return
        try:
            if kind == "snapshot":
                k = self.index_now()
                body = self._payload(cam, k)
                h.send_response(200)
                h.send_header("Content-Type", "image/jpeg")
                h.send_header("Content-Length", str(len(body)))
                h.send_header("X-Timestamp", _iso(self.frame_time(k)))
                h.end_headers()
                h.wfile.write(body)
                self.frames_sent[cam] += 1
                return
            gen = self._gen[cam]
            h.send_response(200)
            h.send_header("Content-Type", f"multipart/x-mixed-replace; boundary={BOUNDARY}")
            h.send_header("Cache-Control", "no-cache")
            h.end_headers()
            k = self.index_now()
            while not self._closing.is_set() and self._gen[cam] == gen:
                due = self._t0 + k / self.fps
                wait = due - time.monotonic()
                if wait > 0:
                    time.sleep(min(wait, 0.05))
                    continue
                body = self._payload(cam, k)
                head = (f"--{BOUNDARY}\r\nContent-Type: image/jpeg\r\nContent-Length: {len(body)}\r\n"
                        f"X-Timestamp: {_iso(self.frame_time(k))}\r\n\r\n").encode("ascii")
                h.wfile.write(head + body + b"\r\n")
                h.wfile.flush()
                self.frames_sent[cam] += 1
                k = max(k + 1, self.index_now())  # a slow client gets the current frame, like a camera
        except (BrokenPipeError, ConnectionResetError, ConnectionAbortedError):
            return


def _iso(t: datetime) -> str:
    return t.astimezone(timezone.utc).isoformat(timespec="milliseconds").replace("+00:00", "Z")


def main(argv: list[str] | None = None) -> int:
    """``python -m cbh.sim.camera_server``: serve a simulated station's cameras until Ctrl-C."""
    import argparse

    from cbh.presets import DEFAULT_SCENE, scene_path, station_path
    from cbh.sim import SkySimulator, load_scene
    from cbh.geometry.station import load_station

    ap = argparse.ArgumentParser(prog="python -m cbh.sim.camera_server", description=__doc__.split("\n\n")[0])
    ap.add_argument("--station", default=None, help="station TOML or preset (default unb-lea)")
    ap.add_argument("--scene", default=DEFAULT_SCENE, help="scene TOML or preset")
    ap.add_argument("--size", type=int, default=960, help="image width [px]")
    ap.add_argument("--fps", type=float, default=1.0, help="frames per second")
    ap.add_argument("--step-s", type=float, default=None, help="simulated seconds per frame (default 1/fps)")
    ap.add_argument("--port", type=int, default=8080)
    ap.add_argument("--bind", "--host", dest="host", default="127.0.0.1",
                    help="address to listen on (default 127.0.0.1: this machine only; 0.0.0.0: every interface)")
    ap.add_argument("--write-station", default="camera-server-station.toml",
                    help="write the station scaled to --size here (for cbh run --station)")
    a = ap.parse_args(argv)
    st = load_station(station_path(a.station) if a.station else station_path())
    sim = SkySimulator(st, load_scene(scene_path(a.scene)), size_px=a.size)
    from cbh.errors import CbhError

    try:
        srv = CameraServer(sim_frames(sim), list(sim.station.cameras), fps=a.fps, step_s=a.step_s, host=a.host, port=a.port)
    except CbhError as exc:
        print(f"cbh: error: {exc}", file=sys.stderr)
        return 2
    with srv:
        for c in srv.cameras:
            print(f"{c}: {srv.url(c)}   snapshot: {srv.url(c, 'snapshot')}", flush=True)
        with open(a.write_station, "w") as fh:
            fh.write(sim.station.to_toml())
        srv_sources = " ".join(f"--source {c}={srv.url(c)}" for c in srv.cameras[:2])
        print(f"try: cbh run --station {a.write_station} {srv_sources}", flush=True)
        try:
            while True:
                time.sleep(3600)
        except KeyboardInterrupt:
            pass
    return 0


if __name__ == "__main__":
    raise SystemExit(main())


# --- RTSP (RTP/JPEG, RFC 2435, interleaved over the RTSP TCP connection) ----------------------

def _jpeg_rtp_parts(jpeg: bytes) -> tuple[int, int, int, bytes, bytes]:
    """Split a baseline JPEG into what RFC 2435 carries: (type, width, height, quant tables, scan).

    Only baseline JPEGs with the standard Huffman tables, 4:2:0 or 4:2:2 sampling and no
    restart markers (what OpenCV/libjpeg write by default) can be sent this way.
    """
    i, qt, w = 2, {}, None
    h = typ = 0
    while i < len(jpeg):
        if jpeg[i] != 0xFF:
            raise ValueError("bad JPEG marker")
        m = jpeg[i + 1]
        seg_len = int.from_bytes(jpeg[i + 2:i + 4], "big")
        seg = jpeg[i + 4:i + 2 + seg_len]
        if m == 0xDB:  # DQT: one or more 8-bit tables
            j = 0
            while j < len(seg):
                pq, tq = seg[j] >> 4, seg[j] & 15
                if pq != 0:
                    raise ValueError("16-bit quantisation tables are not supported")
                qt[tq] = seg[j + 1:j + 65]
                j += 65
        elif m == 0xC0:  # SOF0
            h, w = int.from_bytes(seg[1:3], "big"), int.from_bytes(seg[3:5], "big")
            hv = seg[7]  # first component's sampling factors
            typ = {0x21: 0, 0x22: 1}.get(hv)
            if typ is None:
                raise ValueError(f"unsupported sampling 0x{hv:02x}")
        elif m in (0xC1, 0xC2, 0xC3):
            raise ValueError("only baseline JPEG")
        elif m == 0xDD:
            raise ValueError("restart markers are not supported")
        elif m == 0xDA:  # SOS: the scan runs to the EOI
            start = i + 2 + seg_len
            end = jpeg.rfind(b"\xff\xd9")
            return typ, w, h, qt[0] + qt.get(1, qt[0]), jpeg[start:end]
        i += 2 + seg_len
    raise ValueError("no scan in JPEG")


class RtspCameraServer:
    """A minimal RTSP camera on 127.0.0.1: one MJPEG track (RTP/JPEG) per camera, TCP interleaved.

    Enough for FFmpeg's RTSP client (OpenCV ``cv2.VideoCapture("rtsp://…")``): OPTIONS,
    DESCRIBE, SETUP (TCP interleaved only; UDP is refused with 461 and the client falls back),
    PLAY, GET_PARAMETER, TEARDOWN. URL: ``rtsp://127.0.0.1:PORT/<camera>``.
    """

    def __init__(self, frames: Callable[[str, datetime], bytes], cameras, fps: float = 5.0, step_s: float | None = None,
                 start_utc: datetime | None = None, host: str = "127.0.0.1", port: int = 0):
        import socketserver

        self.frames, self.cameras, self.fps = frames, list(cameras), float(fps)
        self.step_s = 1.0 / self.fps if step_s is None else float(step_s)
        self.start_utc = start_utc or datetime.now(timezone.utc).replace(microsecond=0)
        self._closing = threading.Event()
        self._t0 = time.monotonic()
        self.frames_sent: dict[str, int] = {c: 0 for c in self.cameras}
        server = self

        class Handler(socketserver.StreamRequestHandler):
            def handle(self):
                server._session(self)

        class TCP(socketserver.ThreadingTCPServer):
            daemon_threads = True
            allow_reuse_address = True

        self._srv = _listen(TCP, host, port, Handler, "RTSP server")
        self._thread: threading.Thread | None = None

    @property
    def port(self) -> int:
        return self._srv.server_address[1]

    def url(self, camera: str) -> str:
        """``rtsp://HOST:PORT/<camera>`` (HOST as for :meth:`CameraServer.url`)."""
        return f"rtsp://{_client_host(self._srv.server_address[0])}:{self.port}/{camera}"

    def start(self) -> "RtspCameraServer":
        self._t0 = time.monotonic()
        self._thread = threading.Thread(target=self._srv.serve_forever, kwargs={"poll_interval": 0.1}, daemon=True)
        self._thread.start()
        return self

    def close(self) -> None:
        self._closing.set()
        self._srv.shutdown()
        self._srv.server_close()

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc):
        self.close()

    def _session(self, h) -> None:
        import random

        cam, playing, session = None, False, f"{random.getrandbits(32):08x}"
        rfile, wfile = h.rfile, h.wfile
        while not self._closing.is_set() and not playing:
            line = rfile.readline()
            if not line:
                return
            if not line.strip():
                continue
            method, url = line.decode("latin-1").split()[:2]
            hdr = {}
            while True:
                ln = rfile.readline().decode("latin-1").strip()
                if not ln:
                    break
                k, _, v = ln.partition(":")
                hdr[k.strip().lower()] = v.strip()
            cseq = hdr.get("cseq", "0")
            path = _rtsp_path(url)
            base = path.split("/")[0]
            extra, body, status = {}, b"", "200 OK"
            if base not in self.frames_sent and method != "OPTIONS":
                status = "404 Not Found"
            elif method == "OPTIONS":
                extra["Public"] = "OPTIONS, DESCRIBE, SETUP, PLAY, TEARDOWN, GET_PARAMETER"
            elif method == "DESCRIBE":
                cam = base
                body = (f"v=0\r\no=- 0 0 IN IP4 127.0.0.1\r\ns=cbh {cam}\r\nc=IN IP4 0.0.0.0\r\nt=0 0\r\n"
                        f"m=video 0 RTP/AVP 26\r\na=control:track0\r\n").encode()
                extra["Content-Type"] = "application/sdp"
                extra["Content-Base"] = url.rstrip("/") + "/"
            elif method == "SETUP":
                cam = base
                if "interleaved" not in hdr.get("transport", "") and "TCP" not in hdr.get("transport", ""):
                    status = "461 Unsupported Transport"
                else:
                    extra["Transport"] = "RTP/AVP/TCP;unicast;interleaved=0-1"
                    extra["Session"] = session
            elif method == "PLAY":
                extra["Session"] = session
                playing = True
            elif method == "TEARDOWN":
                status = "200 OK"
            resp = f"RTSP/1.0 {status}\r\nCSeq: {cseq}\r\n" + "".join(f"{k}: {v}\r\n" for k, v in extra.items())
            if body:
                resp += f"Content-Length: {len(body)}\r\n"
            wfile.write(resp.encode("latin-1") + b"\r\n" + body)
            wfile.flush()
            if method == "TEARDOWN":
                return
        if not playing or cam is None:
            return
        self._stream(cam, h)

    def _stream(self, cam: str, h) -> None:
        import struct

        seq, ssrc = 0, 0x0CB40001
        k = int((time.monotonic() - self._t0) * self.fps)
        sock = h.connection
        sock.setblocking(True)
        try:
            while not self._closing.is_set():
                due = self._t0 + k / self.fps
                wait = due - time.monotonic()
                if wait > 0:
                    time.sleep(min(wait, 0.05))
                    continue
                t = self.start_utc + timedelta(seconds=k * self.step_s)
                typ, w, hh, qt, scan = _jpeg_rtp_parts(self.frames(cam, t))
                ts = int(k / self.fps * 90000) & 0xFFFFFFFF
                off, mtu = 0, 1400
                while off < len(scan):
                    q = b""
                    if off == 0:
                        q = struct.pack("!BBH", 0, 0, len(qt)) + qt
                    chunk = scan[off:off + mtu - len(q)]
                    last = off + len(chunk) >= len(scan)
                    jh = struct.pack("!B", 0) + off.to_bytes(3, "big") + struct.pack("!BBBB", typ, 255, w // 8, hh // 8)
                    rtp = struct.pack("!BBHII", 0x80, (0x80 if last else 0) | 26, seq & 0xFFFF, ts, ssrc)
                    pkt = rtp + jh + q + chunk
                    sock.sendall(b"$\x00" + struct.pack("!H", len(pkt)) + pkt)
                    seq += 1
                    off += len(chunk)
                self.frames_sent[cam] += 1
                k = max(k + 1, int((time.monotonic() - self._t0) * self.fps))
        except OSError:
            return


def _rtsp_path(url: str) -> str:
    """Path of an RTSP URL without the leading slash (``rtsp://h:p/cam1/track0`` → ``cam1/track0``)."""
    import urllib.parse

    return urllib.parse.urlsplit(url).path.lstrip("/")
