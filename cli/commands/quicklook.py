"""`cbh quicklook`: a ceilometer-style PNG of recorded sessions (layer bases, cover, motion)."""
from __future__ import annotations

from pathlib import Path

import typer


def register(app: typer.Typer) -> None:
    app.command("quicklook")(quicklook_cmd)


def quicklook_cmd(
    sessions: list[Path] = typer.Argument(..., help="One or more SESSION.mcap files (or directories of rotated files)."),
    out: Path = typer.Option(..., "--out", "-o", help="Output PNG (replaced if it exists)."),
    title: str = typer.Option(None, "--title", help="Figure title (default: station and position)."),
    pyranometer: Path = typer.Option(None, "--pyranometer", help="The station's GHI record (CSV): adds measured and nowcast GHI."),
) -> None:
    """Layer bases against time coloured by cover (okta), cloud fraction, layer speed and direction."""
    from cbh.actions.quicklook import quicklook

    print(quicklook(sessions, out, title=title, pyranometer=pyranometer))
