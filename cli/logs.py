"""Logging set-up for the CLI (the library only ever calls logging.getLogger(__name__))."""
from __future__ import annotations

import errno
import json
import logging
import sys
import time

from cbh.errors import ConfigError


class JsonFormatter(logging.Formatter):
    def format(self, record: logging.LogRecord) -> str:
        d = {
            "t": time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(record.created)) + f".{int(record.msecs):03d}Z",
            "level": record.levelname.lower(),
            "logger": record.name,
            "msg": record.getMessage(),
        }
        for k, v in record.__dict__.items():
            if k.startswith("cbh_"):
                d[k[4:]] = v
        if record.exc_info:
            d["exc"] = self.formatException(record.exc_info)
        return json.dumps(d, default=str)


class _LogFileHandler(logging.FileHandler):
    """A JSON-lines log file that never floods stderr: on the first failed write (disk full,
    device gone) it warns once on stderr and stops logging to the file; the run goes on."""

    def __init__(self, path: str):
        try:
            super().__init__(path, encoding="utf-8")
        except OSError as exc:
            raise ConfigError(f"cannot open log file {path}: {exc.strerror or exc}") from None
        self.failed = False

    def handleError(self, record: logging.LogRecord) -> None:
        if self.failed:
            return
        self.failed = True
        exc = sys.exc_info()[1]
        why = "disk full" if isinstance(exc, OSError) and exc.errno == errno.ENOSPC else (
            getattr(exc, "strerror", None) or str(exc) or type(exc).__name__)
        print(f"cbh: warning: cannot write log file {self.baseFilename} ({why}); logging to it stopped",
              file=sys.stderr)
        logging.getLogger("cbh").removeHandler(self)
        try:
            self.stream and self.stream.close()
        except OSError:
            pass
        self.stream = None

    def emit(self, record: logging.LogRecord) -> None:
        if not self.failed:
            super().emit(record)

    def flush(self) -> None:
        try:
            super().flush()
        except OSError:
            self.handleError(None)

    def close(self) -> None:
        try:
            super().close()
        except OSError:
            pass


def setup_logging(verbose: bool = False, log_file: str | None = None) -> None:
    root = logging.getLogger("cbh")
    root.handlers.clear()
    root.setLevel(logging.DEBUG)
    h = logging.StreamHandler(sys.stderr)
    h.setLevel(logging.DEBUG if verbose else logging.WARNING)
    h.setFormatter(logging.Formatter("cbh: %(levelname)s: %(message)s"))
    root.addHandler(h)
    if log_file:
        fh = _LogFileHandler(log_file)
        fh.setLevel(logging.DEBUG)
        fh.setFormatter(JsonFormatter())
        root.addHandler(fh)
    root.propagate = False
