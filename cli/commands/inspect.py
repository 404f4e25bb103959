"""`cbh inspect`: what a recording holds; repair of a file whose writer was killed."""
from __future__ import annotations

import json
from pathlib import Path

import typer



def register(app: typer.Typer) -> None:
    app.command("inspect")(inspect_cmd)


def inspect_cmd(
    session: list[Path] = typer.Argument(..., help="SESSION.mcap (several rotated files, or a directory of them)."),
    repair: Path = typer.Option(None, "--repair", help="Rewrite every complete message of a truncated file into OUT.mcap."),
    as_json: bool = typer.Option(False, "--json", help="Print one JSON object."),
) -> None:
    """Time span, frames, drops, topics and layer statistics of a recording."""
    from cbh.actions.inspect import inspect_session
    from cbh.outputs.record.describe import format_description  # on use (cold start of the other commands)
    d, notes = inspect_session(session, repair)
    if as_json:
        print(json.dumps(d))
    else:
        print("\n".join(notes + [format_description(d)]))
