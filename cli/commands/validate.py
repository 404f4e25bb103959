"""`cbh validate`: cbh against a co-located ceilometer (cbh/actions/validate.py)."""
from __future__ import annotations

from pathlib import Path

import typer


def register(app: typer.Typer) -> None:
    app.command("validate")(validate_cmd)


def validate_cmd(
    recordings: list[Path] = typer.Argument(..., help="SESSION.mcap recordings to check."),
    ceilometer: list[Path] = typer.Option(..., "--ceilometer", help="Ceilometer file(s): CL31/CL51 messages, CL61, "
                                          "CHM15k, ARM ceil or E-PROFILE NetCDF (repeat the option)."),
    out: Path = typer.Option(Path("validation.json"), "--out", "-o", help="Report (JSON); PNGs are written beside it."),
    match_s: float = typer.Option(30.0, "--match-s", help="Ceilometer profiles within this many seconds of a pair."),
) -> None:
    """MAE, RMSE, bias, R² and the fraction within 150 m of cbh's base above the ceilometer."""
    from cbh.actions.validate import validate

    print(validate(ceilometer, recordings, out, match_s)[1])
