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
import warnings

import typer

from cbh.errors import CbhError

COMMANDS = ("triangulate", "simulate", "pair", "run", "replay", "export", "inspect", "mask", "quicklook", "segment",
            "calibrate", "reprocess", "calibrate_lens", "validate")

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


def _exceptions(name: str) -> tuple[type, ...]:
    """Exception class ``name`` from every click that can raise it here: the installed typer may
    bundle its own click (``typer._click``, with Exit/Abort in ``typer.exceptions``) besides,
    or instead of, the standalone ``click``."""
    found = []
    for mod in ("typer.exceptions", "typer._click.exceptions", "click.exceptions"):
        try:
            cls = getattr(importlib.import_module(mod), name, None)
        except ImportError:
            continue
        if isinstance(cls, type) and cls not in found:
            found.append(cls)
    return tuple(found)


_EXIT = _exceptions("Exit")
_ABORT = _exceptions("Abort")
_CLICK_ERROR = _exceptions("ClickException")
_NO_ARGS = _exceptions("NoArgsIsHelpError")  # bare `cbh`: the help text is the answer


def _one_line(text: str) -> str:
    return " ".join(str(text).split())


def _usage_message(exc) -> str:
    """A click usage error as one line: what is wrong, and where to read more."""
    msg = _one_line(exc.format_message())
    ctx = getattr(exc, "ctx", None)
    path = ctx.command_path if ctx is not None and ctx.command_path else "cbh"
    return f"{msg} (see `{path} --help`)" if hasattr(exc, "ctx") else msg


def _os_message(exc: OSError) -> str:
    if exc.errno == errno.ENOSPC:
        return f"disk full while writing {exc.filename or 'output'}"
    return f"{exc.strerror or exc}" + (f": {exc.filename}" if exc.filename else "")


class _HeldWarnings:
    """Python warnings (numpy's ``RuntimeWarning: Mean of empty slice`` …) shown during a command
    are held, not printed where they happen: after a command that succeeded each distinct one
    is logged once as a one-line warning; after one that failed only the log file gets them
    (debug), so the error stays the one line on stderr. Warnings that filters turn into errors
    (``-W error``, pytest's ``filterwarnings = error``) are raised as before."""

    def __enter__(self) -> "_HeldWarnings":
        self.held: list[str] = []
        self._old = warnings.showwarning
        warnings.showwarning = self._hold
        return self

    def _hold(self, message, category, filename, lineno, file=None, line=None) -> None:
        self.held.append(f"{category.__name__}: {_one_line(message)}")

    def __exit__(self, *exc) -> None:
        warnings.showwarning = self._old

    def report(self, failed: bool) -> None:
        log = logging.getLogger("cbh.warnings")
        for text in dict.fromkeys(self.held):
            if failed:
                log.debug(text)
            else:
                log.warning(text)


def main(argv: list[str] | None = None) -> int:
    """Run the CLI; every error ends as ONE line ``cbh: error: …`` on stderr and exit code 2."""
    with _HeldWarnings() as held:
        code = _run(argv)
    held.report(failed=code not in (0, 130))
    logging.shutdown()
    if argv is None:
        sys.exit(code)
    return code


def _run(argv: list[str] | None) -> int:
    """The command's exit code; errors printed as one line."""
    code = 0
    try:
        rv = app(args=argv, standalone_mode=False, prog_name="cbh")
        code = rv if isinstance(rv, int) else 0
    except _EXIT as exc:
        code = exc.exit_code
    except _ABORT:
        print("cbh: aborted", file=sys.stderr)
        code = 130
    except _NO_ARGS as exc:
        print(exc.format_message(), file=sys.stderr)
        code = 2
    except _CLICK_ERROR as exc:  # usage errors: bad option values, missing arguments, unknown commands
        print(f"cbh: error: {_usage_message(exc)}", file=sys.stderr)
        code = 2
    except CbhError as exc:
        print(f"cbh: error: {_one_line(exc)}", file=sys.stderr)
        code = 2
    except OSError as exc:
        print(f"cbh: error: {_one_line(_os_message(exc))}", file=sys.stderr)
        code = 2
    except KeyboardInterrupt:
        code = 130
    return code


if __name__ == "__main__":
    main()
