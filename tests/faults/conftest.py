"""Fault injection: real loopback HTTP cameras that misbehave, real files, a real small tmpfs.

Each test here reproduces one case of issue 10 ("an unattended service") that failed before.
"""
from __future__ import annotations

import os
import subprocess
import threading
import time
import uuid
from datetime import datetime, timedelta, timezone
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import cv2
import numpy as np
import pytest

from cbh.result import Frame, Histogram, Layer, PairResult, PointSet

T0 = datetime(2015, 10, 29, 4, 58, 1, tzinfo=timezone.utc)
JPEG = cv2.imencode(".jpg", np.full((16, 16, 3), 90, np.uint8))[1].tobytes()
LOGIN_PAGE = b"<html><body><form action=/login>user <input name=u> password <input name=p></form></body></html>"


def frame(cam: str, t: datetime, seq: int = 0) -> Frame:
    return Frame(cam, t, np.full((16, 16, 3), 90, np.uint8), JPEG, "jpeg", seq)


def process_fn(delay_s: float = 0.0):
    """Stand-in for Pipeline.process (the faults are in the plumbing, not the numerics)."""
    def process(f1: Frame, f2: Frame) -> PairResult:
        if delay_s:
            time.sleep(delay_s)
        layer = Layer(1000.0, 1000.0, 1.0, 0.5, 10, 1.0)
        return PairResult(f1.time_utc, (f1.camera, f2.camera), [layer], Histogram(np.zeros(2), np.zeros(1)),
                          PointSet.empty(), np.zeros((2, 2), np.float32), {}, {})
    return process


class FaultyCamera:
    """A loopback HTTP "camera" whose behaviour the test switches at run time.

    Modes: ``snapshot`` (a JPEG with status 200), ``html`` (a login page with status 200),
    ``404``, ``500``, ``junk-mjpeg`` (multipart header, then random bytes forever),
    ``mjpeg`` (a proper stream of the test JPEG). ``requests`` counts GETs.
    """

    def __init__(self, mode: str = "snapshot"):
        self.mode = mode
        self.requests = 0
        cam = self

        class Handler(BaseHTTPRequestHandler):
            protocol_version = "HTTP/1.0"

            def log_message(self, *a):
                pass

            def do_GET(self):
                cam.requests += 1
                mode = cam.mode
                try:
                    if mode in ("404", "500"):
                        self.send_response(int(mode))
                        self.send_header("Content-Type", "text/html")
                        self.end_headers()
                        self.wfile.write(b"<html>error</html>")
                    elif mode == "html":
                        self.send_response(200)
                        self.send_header("Content-Type", "text/html; charset=utf-8")
                        self.send_header("Content-Length", str(len(LOGIN_PAGE)))
                        self.end_headers()
                        self.wfile.write(LOGIN_PAGE)
                    elif mode == "snapshot":
                        self.send_response(200)
                        self.send_header("Content-Type", "image/jpeg")
                        self.send_header("Content-Length", str(len(JPEG)))
                        self.end_headers()
                        self.wfile.write(JPEG)
                    elif mode in ("junk-mjpeg", "mjpeg"):
                        self.send_response(200)
                        self.send_header("Content-Type", "multipart/x-mixed-replace; boundary=frame")
                        self.end_headers()
                        rng = np.random.default_rng(0)
                        while cam.mode == mode:
                            if mode == "junk-mjpeg":
                                self.wfile.write(rng.integers(0, 256, 1024, dtype=np.uint8).tobytes())
                            else:
                                self.wfile.write(b"--frame\r\nContent-Type: image/jpeg\r\nContent-Length: "
                                                 + str(len(JPEG)).encode() + b"\r\n\r\n" + JPEG + b"\r\n")
                            self.wfile.flush()
                            time.sleep(0.02)
                except OSError:
                    pass

        self.httpd = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.httpd.daemon_threads = True
        self.thread = threading.Thread(target=self.httpd.serve_forever, daemon=True)
        self.thread.start()

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.httpd.server_address[1]}/video"

    def close(self) -> None:
        self.mode = "closed"
        self.httpd.shutdown()
        self.httpd.server_close()


@pytest.fixture
def camera():
    made = []

    def make(mode: str = "snapshot") -> FaultyCamera:
        c = FaultyCamera(mode)
        made.append(c)
        return c

    yield make
    for c in made:
        c.close()


@pytest.fixture
def tiny_tmpfs(tmp_path):
    """A real 64 KiB tmpfs (needs root and mount); skipped with the reason where unavailable."""
    d = tmp_path / f"tmpfs-{uuid.uuid4().hex[:6]}"
    d.mkdir()
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=64k", "tmpfs", str(d)], capture_output=True, text=True)
    if r.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here ({r.stderr.strip() or 'mount failed'}); needs root")
    try:
        yield d
    finally:
        subprocess.run(["umount", "-l", str(d)], capture_output=True)


def fill(directory: Path, leave_bytes: int) -> None:
    """Fill the file system of ``directory`` until about ``leave_bytes`` are free."""
    st = os.statvfs(directory)
    free = st.f_bavail * st.f_frsize
    n = max(0, free - leave_bytes)
    with open(directory / "filler.bin", "wb") as fh:
        try:
            fh.write(b"\0" * n)
        except OSError:
            pass


def t(seconds: float) -> datetime:
    return T0 + timedelta(seconds=seconds)


@pytest.fixture(autouse=True)
def _fresh_cbh_logger():
    """``cbh.cli.main`` sets up the ``cbh`` logger (handler on the then sys.stderr, no
    propagation); undo that around each test so caplog sees records and no handler writes to
    a closed capture stream."""
    import logging

    lg = logging.getLogger("cbh")
    saved = (list(lg.handlers), lg.propagate, lg.level)
    lg.handlers.clear()
    lg.propagate = True
    yield
    lg.handlers[:] = saved[0]
    lg.propagate, lg.level = saved[1], saved[2]
