"""``cbh inspect`` in library terms: what a recording holds, after an optional repair."""
from __future__ import annotations

from pathlib import Path

from cbh.errors import RecordingError

__all__ = ["inspect_session"]


def inspect_session(paths, repair=None) -> tuple[dict, list[str]]:
    """Describe a session (one file, rotated files or a directory).

    With ``repair`` (exactly one input file), every complete message of a truncated file is
    first rewritten into ``repair`` and that file is described; the description then has a
    ``repair`` entry. Returns (description dict, human-readable note lines).
    """
    from cbh.outputs.record import open_session, recover
    from cbh.outputs.record.describe import describe_session

    paths = [Path(p) for p in paths]
    notes, repaired = [], None
    if repair is not None:
        if len(paths) != 1:
            raise RecordingError("a repair takes exactly one SESSION.mcap")
        rep = recover(paths[0], repair)
        repaired = {"source": str(rep.source), "out": str(rep.out), "messages": rep.messages, "pairs": rep.pairs,
                    "bytes_read": rep.bytes_read, "bytes_total": rep.bytes_total, "source_complete": rep.complete}
        state = "complete file rewritten" if rep.complete else (
            f"truncated at byte {rep.bytes_read} of {rep.bytes_total}; the torn last record was dropped")
        notes.append(f"repaired {rep.source} -> {rep.out}: {rep.pairs} complete pairs, {rep.messages} messages ({state})")
        paths = [Path(repair)]
    d = describe_session(open_session(paths if len(paths) > 1 else paths[0]))
    if repaired:
        d["repair"] = repaired
    return d, notes
