"""Entry point of the ``cbh`` console script.

Each command lives in ``cli/commands/<name>.py`` and exposes ``register(app)``. Errors that
cbh raises for bad input (:class:`cbh.errors.CbhError`) become one line on stderr and exit
code 2; no traceback reaches the user.
"""
from __future__ import annotations

import errno
import importlib
import logging
import sys

import click
import typer

from cbh.errors import CbhError

COMMANDS = ("triangulate", "simulate", "pair", "run", "replay", "export", "inspect", "mask", "reprocess")

app = typer.Typer(
    name="cbh",
    help="Cloud-base height from two upward-looking fisheye cameras.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
    rich_markup_mode=None,
)


def _show_version(value: bool) -> None:
    if value:
        import cbh

        print(f"cbh {cbh.__version__}")
        raise typer.Exit(0)


@app.callback()
def _root(
    verbose: bool = typer.Option(False, "--verbose", "-v", help="Log debug messages to stderr."),
    log_file: str = typer.Option(None, "--log-file", help="Also write structured (JSON lines) logs to this file."),
    version: bool = typer.Option(False, "--version", callback=_show_version, is_eager=True, help="Print the version and exit."),
) -> None:
    """Cloud-base height from two upward-looking fisheye cameras."""
    from cbh.cli.logs import setup_logging

    setup_logging(verbose=verbose, log_file=log_file)


for _name in COMMANDS:
    importlib.import_module(f"cbh.cli.commands.{_name}").register(app)


def fail(message: str, code: int = 2) -> "typer.Exit":
    """Print ``cbh: error: message`` on stderr and return the Exit to raise."""
    print(f"cbh: error: {message}", file=sys.stderr)
    return typer.Exit(code)


def main(argv: list[str] | None = None) -> int:
    try:
        rv = app(args=argv, standalone_mode=False, prog_name="cbh")
        return rv if isinstance(rv, int) else 0
    except click.exceptions.Exit as exc:
        code = exc.exit_code
    except click.ClickException as exc:
        exc.show()
        code = exc.exit_code
    except click.exceptions.Abort:
        print("cbh: aborted", file=sys.stderr)
        code = 130
    except CbhError as exc:
        print(f"cbh: error: {exc}", file=sys.stderr)
        code = 2
    except OSError as exc:
        if exc.errno == errno.ENOSPC:
            msg = f"disk full while writing {exc.filename or 'output'}"
        else:
            msg = f"{exc.strerror or exc}" + (f": {exc.filename}" if exc.filename else "")
        print(f"cbh: error: {msg}", file=sys.stderr)
        code = 2
    except KeyboardInterrupt:
        code = 130
    logging.shutdown()
    if argv is None:
        sys.exit(code)
    return code


if __name__ == "__main__":
    main()
