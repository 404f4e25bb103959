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
    from cbh.errors import RecordingError
    from cbh.outputs.record import open_session, recover
    from cbh.outputs.record.describe import describe_session, format_description

    paths = session
    repaired = None
    if repair is not None:
        if len(session) != 1:
            raise RecordingError("--repair takes exactly one SESSION.mcap")
        rep = recover(session[0], repair)
        repaired = {"source": str(rep.source), "out": str(rep.out), "messages": rep.messages, "pairs": rep.pairs,
                    "bytes_read": rep.bytes_read, "bytes_total": rep.bytes_total, "source_complete": rep.complete}
        if not as_json:
            state = "complete file rewritten" if rep.complete else (
                f"truncated at byte {rep.bytes_read} of {rep.bytes_total}; the torn last record was dropped")
            print(f"repaired {rep.source} -> {rep.out}: {rep.pairs} complete pairs, {rep.messages} messages ({state})")
        paths = [repair]
    s = open_session(paths if len(paths) > 1 else paths[0])
    d = describe_session(s)
    if as_json:
        if repaired:
            d["repair"] = repaired
        print(json.dumps(d))
    else:
        print(format_description(d))
