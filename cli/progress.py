"""Terminal progress for long commands (presentation only; the actions report through callbacks)."""
from __future__ import annotations

import json
import sys


class ReprocessProgress:
    """Rich progress bar on stderr (only on a terminal) and one JSON line per finished day on stdout
    (shown above the bar when stdout is the same terminal)."""

    def __init__(self):
        self.bar = self.task = None
        self.failures = 0

    def __call__(self, e: dict) -> None:
        if e["event"] == "start" and e["pairs"] and sys.stderr.isatty():
            from rich.console import Console
            from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

            self.bar = Progress(TextColumn("reprocess"), BarColumn(), MofNCompleteColumn(),
                                TextColumn("{task.fields[rate]:.2f} pairs/s"), TimeRemainingColumn(),
                                TextColumn("failures {task.fields[failures]}"), console=Console(stderr=True),
                                redirect_stdout=sys.stdout.isatty(), redirect_stderr=False,  # piped stdout stays clean
                                refresh_per_second=2)  # rich's 10 Hz took 1.5 % of a core from the workers; 2 Hz 0.3 %
            self.task = self.bar.add_task("pairs", total=e["pairs"], rate=0.0, failures=0)
            self.bar.start()
        elif e["event"] == "chunk" and self.bar is not None:
            self.failures += e["failures"]
            self.bar.advance(self.task, e["pairs"])
            t = self.bar.tasks[0]
            self.bar.update(self.task, failures=self.failures, rate=(t.completed / t.elapsed) if t.elapsed else 0.0)
        elif e["event"] == "day":
            line = {k: e[k] for k in ("station", "day", "pairs", "records", "time_span_utc", "files")}
            line["failures"] = len(e["failures"])
            print(json.dumps(line), flush=True)

    def stop(self):
        if self.bar is not None:
            self.bar.stop()
