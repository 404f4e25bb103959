"""`cbh mask`: a camera's static obstacle mask, found automatically from a sequence of frames."""
from __future__ import annotations

from pathlib import Path

import typer


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
    """Find buildings, trees and masts on the horizon (dark, static, standing on the horizon).

    Reference the written PNG as the camera's `mask` in the station file.
    """
    import time

    import cv2

    from cbh.errors import ImageError, RecordingError
    from cbh.imageio import check_image_size
    from cbh.pipeline.obstacles import obstacle_mask_from_frames
    from cbh.presets import station_path
    from cbh.live.sources import EndOfStream, open_source
    from cbh.geometry.station import load_station

    st = load_station(station_path(station) if station else station_path())
    cam = st.camera(camera)
    src = open_source(cam, source, base_dir=Path.cwd())
    images, deadline = [], time.monotonic() + timeout_s
    src.open()
    try:
        while len(images) < frames and time.monotonic() < deadline:
            try:
                f = src.read(1.0)
            except EndOfStream:
                break
            except ImageError:
                continue  # a corrupt frame: skip it
            if f is not None:
                check_image_size(f.image, cam.model, f"{camera} frame {len(images)}")
                images.append(f.image)
    finally:
        src.close()
    mask = obstacle_mask_from_frames(images, cam.model)
    out.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(out), mask):
        raise RecordingError(f"cannot write mask image {out}")
    usable = (mask > 0).sum() / max(1, cam.model.image_circle_mask().sum())
    print(f"{camera}: {len(images)} frames -> {out} ({100 * (1 - usable):.1f} % of the image circle masked)")
