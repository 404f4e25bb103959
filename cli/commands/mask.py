"""`cbh mask`: a camera's static obstacle mask, found automatically from a sequence of frames."""
from __future__ import annotations

from pathlib import Path

import typer

from cbh.actions.mask import obstacle_mask


def register(app: typer.Typer) -> None:
    app.command("mask")(mask_cmd)


def mask_cmd(
    source: str = typer.Argument(..., help="The camera's frames: image directory, video file, or stream URL."),
    station: str = typer.Option(None, "--station", help="Station TOML or preset name (default: unb-lea)."),
    camera: str = typer.Option(..., "--camera", help="Camera name in the station."),
    out: Path = typer.Option(..., "--out", help="Mask image to write (PNG; 255 = usable sky, 0 = obstacle)."),
    frames: int = typer.Option(30, "--frames", min=3, help="Frames to use (spread over minutes is best)."),
    timeout_s: float = typer.Option(60.0, "--timeout-s", help="Give up on a live source after this long [s]."),
) -> None:
    """Find buildings, trees and masts on the horizon (dark, static, standing on the horizon),
    and the camera's own on-screen text (its clock, its name) on the sky.

    Reference the written PNG as the camera's `mask` in the station file.
    """
    print(obstacle_mask(source, camera, out, station=station, frames=frames, timeout_s=timeout_s).line())
