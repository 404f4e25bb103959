"""Frame sources (cbh.live.sources) against a loopback HTTP camera, files and directories."""
from __future__ import annotations

import os
import time
from datetime import datetime, timedelta, timezone

import cv2
import numpy as np
import pytest

from cbh.sim.camera_server import CameraServer
from cbh.errors import ConfigError, ImageError, SourceError
from cbh.result import Frame
from cbh.live.sources import (
    DirectorySource, EndOfStream, HttpSource, MemorySource, VideoSource, open_source, parse_time_header,
    time_from_name,
)

T0 = datetime(2015, 10, 29, 4, 58, 1, tzinfo=timezone.utc)


def jpeg_of(cam: str, t: datetime, size: int = 48) -> bytes:
    """A small JPEG whose content depends on (camera, time): frames are distinguishable."""
    rng = np.random.default_rng(abs(hash((cam, t.isoformat()))) % 2**32)
    img = rng.integers(0, 255, (size, size, 3), dtype=np.uint8)
    return cv2.imencode(".jpg", img)[1].tobytes()


@pytest.fixture
def server():
    with CameraServer(jpeg_of, ["cam1", "cam2"], fps=20, step_s=1.0, start_utc=T0) as srv:
        yield srv


def read_n(src, n, timeout_s=5.0):
    out, deadline = [], time.monotonic() + timeout_s
    while len(out) < n and time.monotonic() < deadline:
        f = src.read(0.5)
        if f is not None:
            out.append(f)
    assert len(out) == n, f"only {len(out)} of {n} frames within {timeout_s} s"
    return out


# --- time stamps ----------------------------------------------------------------------------

@pytest.mark.parametrize("name, expected", [
    ("cam1_20151029T045801.000Z.jpg", T0),
    ("cam1_20151029T045801.250Z.jpg", T0 + timedelta(milliseconds=250)),
    ("2015-10-29_04-58-01.jpg", T0),
    ("2015-10-29T04:58:01Z.png", T0),
    ("img-20151029045801.jpg", T0),
    ("cam2.2015-10-29 04:58:01,5.jpeg", T0 + timedelta(milliseconds=500)),
    ("cam1_0001.jpg", None),
    ("cam1_20151329T045801.jpg", None),  # month 13: not a time
])
def test_time_from_name(name, expected):
    assert time_from_name(name) == expected


def test_time_header_forms():
    assert parse_time_header("2015-10-29T04:58:01.000Z") == T0
    assert parse_time_header(str(T0.timestamp())) == T0
    assert parse_time_header("2015-10-29T06:58:01+02:00") == T0
    assert parse_time_header("yesterday") is None and parse_time_header(None) is None


# --- HTTP ---------------------------------------------------------------------------------

def test_mjpeg_frames_are_the_bytes_sent_with_the_camera_time_stamp(server):
    src = open_source("cam1", server.url("cam1"))
    assert isinstance(src, HttpSource) and src.live
    src.open()
    try:
        assert src.kind == "mjpeg"
        frames = read_n(src, 4)
    finally:
        src.close()
    for f in frames:
        assert f.camera == "cam1" and f.format == "jpeg"
        assert f.time_utc.tzinfo is not None
        # frame k's time stamp is T0 + k·step, and its bytes are exactly what the server sent
        k = round((f.time_utc - T0).total_seconds())
        assert f.time_utc == T0 + timedelta(seconds=k)
        assert f.encoded == jpeg_of("cam1", f.time_utc)
        assert f.image.shape == (48, 48, 3)
    ks = [round((f.time_utc - T0).total_seconds()) for f in frames]
    assert ks == sorted(ks) and len(set(ks)) == 4


def test_snapshot_url_polls_and_skips_unchanged_images(server):
    src = open_source("cam2", server.url("cam2", "snapshot"), interval_s=0.01)
    assert src.mode == "snapshot"
    src.open()
    frames = read_n(src, 3)
    src.close()
    times = [f.time_utc for f in frames]
    assert len(set(times)) == 3, "a snapshot whose time stamp did not change must not come twice"
    assert all(f.encoded == jpeg_of("cam2", f.time_utc) for f in frames)


def test_auto_mode_detects_a_snapshot_url(server):
    # the path does not look like an image: the Content-Type decides
    url = server.url("cam1", "snapshot").replace(".jpg", "")
    src = open_source("cam1", url)
    assert src.mode == "auto"
    src.open()
    assert src.kind == "snapshot"
    f = read_n(src, 1)[0]
    src.close()
    assert f.encoded == jpeg_of("cam1", f.time_utc)


def test_corrupt_part_raises_image_error_and_the_stream_goes_on(server):
    src = open_source("cam1", server.url("cam1"))
    src.open()
    try:
        read_n(src, 1)
        server.corrupt("cam1", 1)
        with pytest.raises(ImageError, match="corrupt"):
            for _ in range(40):
                src.read(0.5)
        assert read_n(src, 2)[0].image is not None  # same connection, next frames fine
    finally:
        src.close()


def test_lazy_decoding_still_rejects_non_jpeg_bytes(server):
    src = open_source("cam1", server.url("cam1"), decode=False)
    src.open()
    try:
        f = read_n(src, 1)[0]
        assert f.image is None and f.encoded[:2] == b"\xff\xd8"
        server.corrupt("cam1", 1)
        with pytest.raises(ImageError):
            for _ in range(40):
                src.read(0.5)
    finally:
        src.close()


def test_camera_dropping_raises_source_error_and_reopen_works_after(server):
    src = open_source("cam2", server.url("cam2"))
    src.open()
    read_n(src, 1)
    server.drop("cam2", 0.6)
    with pytest.raises(SourceError, match="closed"):
        for _ in range(40):
            src.read(0.5)
    src.close()
    with pytest.raises(SourceError, match="503"):
        src.open()
    time.sleep(0.7)
    src.open()
    assert len(read_n(src, 2)) == 2
    src.close()


def test_unreachable_camera_is_a_source_error():
    import socket

    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()  # nothing listens there now
    src = open_source("cam1", f"http://127.0.0.1:{port}/video", stall_timeout_s=1.0)
    with pytest.raises(SourceError, match="cannot connect"):
        src.open()


def test_stalled_stream_times_out(server):
    src = HttpSource("cam1", server.url("cam1"), mode="mjpeg", stall_timeout_s=0.4)
    src.open()
    read_n(src, 1)
    server.fps = 0.01  # the camera freezes
    server._t0 -= 0  # keep index; next frame due in ~100 s
    with pytest.raises(SourceError, match="no data"):
        for _ in range(20):
            src.read(0.2)
    src.close()


def test_password_is_never_in_messages():
    src = open_source("cam1", "http://user:s3cret@127.0.0.1:9/video", stall_timeout_s=0.5)
    with pytest.raises(SourceError) as ei:
        src.open()
    assert "s3cret" not in str(ei.value) and "***" in str(ei.value)


# --- directories ----------------------------------------------------------------------------

def write_img(path, value=100):
    cv2.imwrite(str(path), np.full((32, 32, 3), value, np.uint8))


def test_directory_in_time_order_from_names_with_camera_prefix(tmp_path):
    for s in (2, 0, 1):
        write_img(tmp_path / f"cam1_20151029T0458{s:02d}.000Z.jpg", 50 + s)
        write_img(tmp_path / f"cam2_20151029T0458{s:02d}.000Z.jpg", 150 + s)
    src = open_source("cam1", str(tmp_path))
    assert isinstance(src, DirectorySource) and not src.live
    src.open()
    frames = [src.read(1.0) for _ in range(3)]
    with pytest.raises(EndOfStream):
        src.read(0.1)
    assert [f.time_utc for f in frames] == [T0 - timedelta(seconds=1) + timedelta(seconds=s) for s in range(3)]
    assert all(f.camera == "cam1" for f in frames)
    assert [int(f.image[0, 0, 0]) for f in frames] == pytest.approx([50, 51, 52], abs=2)  # JPEG error


def test_directory_without_time_in_names_uses_mtime(tmp_path):
    for i, name in enumerate(["b.jpg", "a.jpg"]):
        write_img(tmp_path / name)
        os.utime(tmp_path / name, (T0.timestamp() + i, T0.timestamp() + i))
    src = DirectorySource("cam1", tmp_path)
    src.open()
    frames = [src.read(1.0) for _ in range(2)]
    assert [f.time_utc for f in frames] == [T0, T0 + timedelta(seconds=1)]


def test_watched_directory_picks_up_new_files(tmp_path):
    write_img(tmp_path / "cam1_20151029T045801Z.jpg")
    src = DirectorySource("cam1", tmp_path, watch=True, poll_s=0.05)
    assert src.live
    src.open()
    f0 = read_n(src, 1)[0]
    assert src.read(0.2) is None  # nothing new: waits, does not end
    write_img(tmp_path / "cam1_20151029T045811Z.jpg")
    write_img(tmp_path / "cam2_20151029T045811Z.jpg")  # another camera's: ignored
    f1 = read_n(src, 1)[0]
    assert (f1.time_utc - f0.time_utc).total_seconds() == 10.0
    assert src.read(0.3) is None


def test_directory_corrupt_file_is_an_image_error_then_continues(tmp_path):
    (tmp_path / "cam1_20151029T045801Z.jpg").write_bytes(b"not a jpeg at all")
    write_img(tmp_path / "cam1_20151029T045802Z.jpg")
    src = DirectorySource("cam1", tmp_path)
    src.open()
    with pytest.raises(ImageError):
        src.read(1.0)
    assert src.read(1.0).time_utc == T0 + timedelta(seconds=1)


# --- video files ----------------------------------------------------------------------------

def test_video_file_frames_with_time_from_name_and_position(tmp_path):
    path = tmp_path / "cam1_20151029T045801Z.avi"
    w = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 5.0, (64, 48))
    assert w.isOpened()
    for k in range(6):
        w.write(np.full((48, 64, 3), 30 * k, np.uint8))
    w.release()
    src = open_source("cam1", str(path))
    assert isinstance(src, VideoSource) and not src.live
    src.open()
    frames = []
    with pytest.raises(EndOfStream):
        while True:
            frames.append(src.read(1.0))
    src.close()
    assert len(frames) == 6
    # 5 fps: frame k at 0.2·k s after the time in the file name (to the millisecond)
    for k, f in enumerate(frames):
        assert abs((f.time_utc - T0).total_seconds() - 0.2 * k) < 1e-3
        assert f.image.shape == (48, 64, 3)
        assert cv2.imdecode(np.frombuffer(f.encoded, np.uint8), cv2.IMREAD_COLOR).shape == (48, 64, 3)
    assert abs(int(frames[3].image.mean()) - 90) <= 3  # MJPG round trip


def test_missing_video_file_is_a_source_error(tmp_path):
    src = VideoSource("cam1", tmp_path / "gone.mp4")
    with pytest.raises(SourceError, match="not found"):
        src.open()


# --- factory and memory ---------------------------------------------------------------------

def test_open_source_errors_name_the_problem(tmp_path):
    with pytest.raises(ConfigError, match="unsupported source scheme 'ftp'"):
        open_source("cam1", "ftp://host/x")
    with pytest.raises(ConfigError, match="no such file"):
        open_source("cam1", str(tmp_path / "nope"))
    with pytest.raises(ConfigError, match="caller builds"):  # the live wing never imports the simulator
        open_source("cam1", "sim")
    write_img(tmp_path / "one.jpg")
    with pytest.raises(ConfigError, match="single image"):
        open_source("cam1", str(tmp_path / "one.jpg"))
    assert open_source("cam1", "snapshot+http://127.0.0.1:1/x").mode == "snapshot"
    assert open_source("cam1", "mjpeg+http://127.0.0.1:1/x").mode == "mjpeg"
    assert open_source("cam1", "rtsp://127.0.0.1:1/x").kind == "rtsp"


def test_memory_source_ends():
    frames = [Frame("cam1", T0 + timedelta(seconds=k), np.zeros((2, 2, 3), np.uint8)) for k in range(2)]
    src = MemorySource("cam1", frames)
    src.open()
    assert [src.read(0.1), src.read(0.1)] == frames
    with pytest.raises(EndOfStream):
        src.read(0.1)


# --- RTSP (loopback RTP/JPEG server, OpenCV's FFmpeg client) ----------------------------------

@pytest.mark.slow
def test_rtsp_stream_frames_in_order_with_stream_clock():
    from cbh.sim.camera_server import RtspCameraServer

    def pattern(cam, t):  # a white bar whose column moves with time: decoded content is checkable
        k = round((t - T0).total_seconds())
        img = np.zeros((96, 128, 3), np.uint8)
        img[:, 8 * (k % 14):8 * (k % 14) + 8] = 255
        return cv2.imencode(".jpg", img)[1].tobytes()

    with RtspCameraServer(pattern, ["cam1"], fps=10, step_s=1.0, start_utc=T0) as srv:
        src = open_source("cam1", srv.url("cam1"), stall_timeout_s=5.0)
        assert isinstance(src, VideoSource) and src.live and src.kind == "rtsp"
        src.open()
        try:
            frames = read_n(src, 6, timeout_s=10)
        finally:
            src.close()
    cols = [int(np.argmax(f.image[48, :, 1])) // 8 for f in frames]
    # consecutive frames: the bar advances one step per frame (frames are whole and in order)
    steps = [(b - a) % 14 for a, b in zip(cols, cols[1:])]
    assert steps.count(1) >= len(steps) - 1, cols
    ts = [f.time_utc for f in frames[1:]]
    dts = [(b - a).total_seconds() for a, b in zip(ts, ts[1:])]
    assert all(abs(d - 0.1) < 0.02 for d in dts), dts  # 10 fps on the stream's clock
    assert all(f.encoded[:2] == b"\xff\xd8" for f in frames)
