"""Rerun over the network: cbh's gRPC server on an address of its choosing (loopback unless the
user says otherwise), and the check that a viewer to connect to is listening.

``RecordingStream.serve_grpc`` of rerun-sdk 0.41 always binds ``0.0.0.0`` (every interface);
:class:`rerun.GrpcServerSink` takes the address (``bind_ip``), so cbh serves through it.
``RecordingStream.connect_grpc`` returns at once and retries in the background: with no viewer
listening, the first flush waits without end (and Ctrl-C does not reach Python), so cbh knocks
on the viewer's port first (:func:`check_viewer`).
"""
from __future__ import annotations

from cbh.errors import ConfigError

__all__ = ["serve_grpc", "check_port", "check_viewer", "DEFAULT_URL", "CONNECT_TIMEOUT_S"]

DEFAULT_URL = "rerun+http://127.0.0.1:9876/proxy"  # the local viewer (Rerun's default)
CONNECT_TIMEOUT_S = 3.0  # a viewer that does not accept the connection within this is not there [s]


def check_port(bind: str, port: int, what: str) -> int:
    """The port (a free one for 0) if ``bind:port`` can be listened on; else one-line :class:`ConfigError`."""
    import errno
    import socket

    try:
        fam = socket.AF_INET6 if ":" in bind else socket.AF_INET
        with socket.socket(fam, socket.SOCK_STREAM) as probe:
            probe.bind((bind, port))
            return probe.getsockname()[1]
    except OSError as exc:
        if exc.errno == errno.EADDRINUSE:
            raise ConfigError(f"{what}: port {port} on {bind} is already in use (another cbh or Rerun server?)") from None
        raise ConfigError(f"{what}: cannot listen on {bind}:{port}: {exc.strerror or exc}") from None


def serve_grpc(rec, blueprint, bind: str = "127.0.0.1", port: int = 9876) -> str:
    """Serve ``rec`` over gRPC on ``bind:port``; returns the URL viewers connect to.

    A port in use is a :class:`ConfigError` (Rerun itself only logs it and serves nothing).
    """
    import rerun as rr

    port = check_port(bind, port, "--rerun serve")
    rec.set_sinks(rr.GrpcServerSink(bind_ip=bind, port=port))
    rec.send_blueprint(blueprint, make_active=False, make_default=True)
    host = "127.0.0.1" if bind in ("0.0.0.0", "::") else bind
    return f"rerun+http://{host}:{port}/proxy"


def check_viewer(url: str | None, timeout_s: float = CONNECT_TIMEOUT_S) -> str:
    """The URL (default: the local viewer) if something accepts a connection on its host and
    port within ``timeout_s`` [s]; else a one-line :class:`ConfigError` saying what to do."""
    import socket
    from urllib.parse import urlsplit

    url = url or DEFAULT_URL
    try:
        u = urlsplit(url)
        host, port = u.hostname, u.port
    except ValueError as exc:
        raise ConfigError(f"--rerun connect: malformed URL {url!r}: {exc}") from None
    if not host:
        raise ConfigError(f"--rerun connect: no host in {url!r} (e.g. {DEFAULT_URL})")
    if port is None:
        port = 443 if u.scheme in ("rerun", "rerun+https") else 80
    hint = "start a viewer (`rerun`), or use --rerun spawn or --rerun save OUT.rrd"
    try:
        with socket.create_connection((host, port), timeout=timeout_s):
            return url
    except socket.gaierror as exc:
        raise ConfigError(f"--rerun connect: cannot resolve {host!r} in {url}: {exc.strerror or exc}") from None
    except (socket.timeout, TimeoutError):
        raise ConfigError(f"--rerun connect: no viewer answered at {url} within {timeout_s:g} s; {hint}") from None
    except OSError as exc:
        raise ConfigError(f"--rerun connect: no viewer at {url} ({exc.strerror or exc}); {hint}") from None
