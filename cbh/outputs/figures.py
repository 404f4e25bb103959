"""Writing matplotlib figures whole or not at all."""
from __future__ import annotations

from pathlib import Path

__all__ = ["save_figure"]


def save_figure(fig, out, dpi: int = 100) -> None:
    """Save ``fig`` to ``out`` (format from its suffix, default PNG) through a temporary file
    beside it, renamed over it (:func:`cbh.fileio.atomic_write`): a full disk leaves the older
    file; errors name ``out`` (:func:`cbh.outputs.export.write_error`). The figure stays open."""
    from cbh.fileio import atomic_write
    from cbh.outputs.export import write_error

    fmt = Path(out).suffix[1:].lower() or "png"
    try:
        with atomic_write(out) as tmp:
            fig.savefig(tmp, dpi=dpi, format=fmt)
    except OSError as exc:
        raise write_error(out, exc) from None
