"""`cbh calibrate-lens`: a fisheye lens's OCamCalib model (calib_results.txt) from chessboard images."""
from __future__ import annotations

import json
from pathlib import Path
from typing import Optional

import typer


def register(app: typer.Typer) -> None:
    app.command("calibrate-lens")(calibrate_lens_cmd)


def calibrate_lens_cmd(
    images: list[Path] = typer.Argument(..., help="Chessboard images of one camera (same size), the board in a different place in each."),
    board: str = typer.Option(..., "--board", help="Inner corners COLSxROWS (OpenCV's patternSize), e.g. 6x8 for 7 x 9 squares."),
    square_mm: float = typer.Option(..., "--square-mm", help="Side of a board square [mm]."),
    out: Path = typer.Option(..., "--out", help="calib_results.txt to write (OCamCalib's layout; cbh and the toolbox read it; an existing one is replaced, never one of the images)."),
    order: str = typer.Option("auto", "--order", help="Degree of the polynomial f(r), 2 to 12, or auto: the lowest whose held-out error is within 1 % of the best of 3 to 8 (4 with --no-held-out)."),
    loss: str = typer.Option("linear", "--loss", help="linear (least squares) or huber (robust)."),
    huber_px: float = typer.Option(1.0, "--huber-px", help="Huber loss: residual where it turns linear [px]."),
    method: str = typer.Option("auto", "--method", help="lm (Levenberg-Marquardt, linear loss), trf (sparse trust region, any loss) or auto (lm unless --loss huber)."),
    no_held_out: bool = typer.Option(False, "--no-held-out", help="Skip the leave-one-image-out error."),
    refine_on_board: Optional[bool] = typer.Option(None, "--refine-on-board/--no-refine-on-board", help="After a first fit, refine the corners again on each board's own plane (curved edges of strongly distorted boards bias the refinement in the raw image) and fit again; by default only where corners pass 90° from the axis (mirrors, lenses beyond 180°)."),
    json_out: bool = typer.Option(False, "--json", help="Print the full report as JSON."),
    report: Path = typer.Option(None, "--report", help="Folder for residuals per image (CSV, PNG) and the coverage picture."),
) -> None:
    """Calibrate a fisheye lens (Scaramuzza's model): linear start as OCamCalib, then bundle adjustment."""
    from cbh.actions.calibrate_lens import LensCalOptions, calibrate_lens, parse_board, parse_order

    opts = LensCalOptions(board=parse_board(board), square_mm=square_mm, order=parse_order(order), loss=loss,
                          huber_px=huber_px, method=method, held_out=not no_held_out, report_dir=report,
                          board_refine=refine_on_board)
    rep = calibrate_lens(images, out, opts)
    if json_out:
        print(json.dumps(rep, indent=1))
        return
    for line in rep["summary"]:
        print(line)
