"""Logging set-up for the CLI (the library only ever calls logging.getLogger(__name__))."""
from __future__ import annotations

import json
import logging
import sys
import time


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


def setup_logging(verbose: bool = False, log_file: str | None = None) -> None:
    root = logging.getLogger("cbh")
    root.handlers.clear()
    root.setLevel(logging.DEBUG)
    h = logging.StreamHandler(sys.stderr)
    h.setLevel(logging.DEBUG if verbose else logging.WARNING)
    h.setFormatter(logging.Formatter("cbh: %(levelname)s: %(message)s"))
    root.addHandler(h)
    if log_file:
        fh = logging.FileHandler(log_file)
        fh.setLevel(logging.DEBUG)
        fh.setFormatter(JsonFormatter())
        root.addHandler(fh)
    root.propagate = False
