"""Rerun's gRPC server on an address of cbh's choosing (loopback unless the user says otherwise).

``RecordingStream.serve_grpc`` of rerun-sdk 0.41 always binds ``0.0.0.0`` (every interface);
:class:`rerun.GrpcServerSink` takes the address (``bind_ip``), so cbh serves through it.
"""
from __future__ import annotations

from cbh.errors import ConfigError

__all__ = ["serve_grpc", "check_port"]


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
