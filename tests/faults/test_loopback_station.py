"""Issue 10, cases 4 and 10: servers listen on loopback only; the station file rejects nonsense."""
from __future__ import annotations

import socket
from pathlib import Path

import cv2
import numpy as np
import pytest

from cbh.errors import ConfigError
from cbh.geometry.station import load_station


def listening(port: int) -> set[str]:
    """Local addresses in LISTEN state on ``port``, from /proc/net/tcp and tcp6."""
    out = set()
    for name, v6 in (("/proc/net/tcp", False), ("/proc/net/tcp6", True)):
        try:
            lines = Path(name).read_text().splitlines()[1:]
        except OSError:
            continue
        for ln in lines:
            f = ln.split()
            addr, p = f[1].split(":")
            if int(p, 16) != port or f[3] != "0A":  # 0A = LISTEN
                continue
            if v6:
                out.add("::" if int(addr, 16) == 0 else addr)
            else:
                b = bytes.fromhex(addr)[::-1]
                out.add(socket.inet_ntoa(b))
    return out


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.slow
def test_rerun_serve_listens_on_loopback_only(unb_station):
    from cbh.outputs.rerun_view import RerunSink

    port = free_port()
    sink = RerunSink(unb_station, "serve", grpc_port=port)
    try:
        import time

        for _ in range(50):
            if listening(port):
                break
            time.sleep(0.1)
        assert listening(port) == {"127.0.0.1"}, listening(port)  # rerun's own default: 0.0.0.0
        assert sink.url == f"rerun+http://127.0.0.1:{port}/proxy"
    finally:
        sink.close()


def test_rerun_serve_port_in_use_is_one_config_error(unb_station):
    from cbh.outputs.rerun_view import RerunSink

    with socket.socket() as blocker:
        blocker.bind(("127.0.0.1", 0))
        blocker.listen()
        port = blocker.getsockname()[1]
        with pytest.raises(ConfigError, match=f"port {port} on 127.0.0.1 is already in use"):
            RerunSink(unb_station, "serve", grpc_port=port)


def test_camera_emulator_listens_on_loopback_and_reports_a_busy_port():
    from cbh.sim.camera_server import CameraServer

    img = np.zeros((8, 8, 3), np.uint8)
    with CameraServer(lambda cam, t: img, ["cam1", "cam2"], fps=1.0) as srv:
        assert listening(srv.port) == {"127.0.0.1"}
        with pytest.raises(ConfigError, match="already in use"):
            CameraServer(lambda cam, t: img, ["cam1", "cam2"], fps=1.0, port=srv.port)


# --- case 10: station validation ----------------------------------------------------------------

STATION = """
[station]
name = "t"
latitude_deg = 1.0
longitude_deg = 2.0
altitude_m = 3.0
{extra}

[[cameras]]
name = "cam1"
position_m = [0.0, 0.0, 0.0]
intrinsics = {{ model = "equidistant", width = 480, height = 480, center_xy = [239.5, 239.5], radius_px = 230.0 }}
{mask}

[[cameras]]
name = "cam2"
position_m = [{x}, 0.0, 0.0]
intrinsics = {{ model = "equidistant", width = 480, height = 480, center_xy = [239.5, 239.5], radius_px = 230.0 }}
"""


def station_file(tmp_path, x=50.0, extra="", mask=""):
    p = tmp_path / "st.toml"
    p.write_text(STATION.format(x=x, extra=extra, mask=mask))
    return p


@pytest.mark.parametrize("x, shown", [(0.0, "zero"), (2.0, "2.00 m"), (10_000.0, "10.0 km")])
def test_implausible_baseline_is_an_error_naming_the_key(tmp_path, x, shown):
    with pytest.raises(ConfigError, match=rf"cameras\[cam2\]\.position_m: baseline to cam1 is {shown}.*allow_baseline"):
        load_station(station_file(tmp_path, x))


def test_allow_baseline_overrides_and_round_trips(tmp_path):
    from cbh.geometry.station import parse_station
    import tomllib

    st = load_station(station_file(tmp_path, 2.0, extra="allow_baseline = true"))
    assert st.allow_baseline
    again = parse_station(tomllib.loads(st.to_toml()))  # e.g. read back from a recording
    assert again.allow_baseline
    assert load_station(station_file(tmp_path, 50.0)).allow_baseline is False


def test_mask_of_another_size_is_an_error(tmp_path):
    cv2.imwrite(str(tmp_path / "m640.png"), np.full((480, 640), 255, np.uint8))
    cv2.imwrite(str(tmp_path / "m480.png"), np.full((480, 480), 255, np.uint8))
    with pytest.raises(ConfigError, match=r"cameras\[cam1\]\.mask: image is 640x480 px but .* 480x480 px"):
        load_station(station_file(tmp_path, mask='mask = "m640.png"'))
    assert load_station(station_file(tmp_path, mask='mask = "m480.png"')).cameras["cam1"].mask.name == "m480.png"
