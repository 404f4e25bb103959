"""How the CLI shows a running service: a live status line on a terminal, one line per pair otherwise."""
from __future__ import annotations

import sys

from cbh.timeutil import format_utc


def run_with_status(setup, status: bool = True):
    """Run ``setup.service()`` (a :class:`cbh.actions.run.RunSetup`) and return its stats."""
    for n in setup.notes:
        print(n, file=sys.stderr)
    if not status:
        return setup.service().run()
    from rich.console import Console

    console = Console(stderr=True)
    if console.is_terminal:
        from rich.live import Live
        from rich.text import Text

        with Live(Text("starting…"), console=console, refresh_per_second=4, transient=False) as live:
            return setup.service(on_pair=lambda st, result: live.update(Text(st.line()))).run()

    def plain(st, result):
        if result is not None:
            print(f"{format_utc(result.time_utc)}  {st.line()}", file=sys.stderr, flush=True)

    return setup.service(on_pair=plain).run()
