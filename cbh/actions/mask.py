"""``cbh mask`` in library terms: a camera's static obstacle mask found from a sequence of its frames."""
from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import cv2

from cbh.errors import ImageError, RecordingError

__all__ = ["MaskReport", "obstacle_mask"]


@dataclass
class MaskReport:
    camera: str
    frames: int  # frames used
    out: Path
    masked_fraction: float  # share of the image circle marked as obstacle, 0..1

    def line(self) -> str:
        return f"{self.camera}: {self.frames} frames -> {self.out} ({100 * self.masked_fraction:.1f} % of the image circle masked)"


def _check_out(out: Path) -> None:
    if out.is_dir():
        raise RecordingError(f"{out}: is a directory; give the mask's file name (e.g. {out / 'cam1_mask.png'})")
    if out.suffix.lower() not in (".png", ".bmp", ".tif", ".tiff"):
        raise RecordingError(f"{out}: the mask is written lossless; use a .png file name")


def obstacle_mask(source: str, camera: str, out, station=None, frames: int = 30, timeout_s: float = 60.0,
                  base_dir=None) -> MaskReport:
    """Collect up to ``frames`` frames of ``camera`` from ``source`` (image directory, video
    file or stream URL), find the static obstacles and write the mask image (255 = usable sky).

    A live source is given up on after ``timeout_s`` [s]; corrupt frames are skipped.
    """
    from cbh.actions.station import load_station
    from cbh.imageio import check_image_size
    from cbh.interfaces import EndOfStream
    from cbh.live.sources import open_source
    from cbh.pipeline.obstacles import obstacle_mask_from_frames
    from cbh.presets import station_path

    from cbh.fileio import refuse_inputs

    out = Path(out)
    _check_out(out)
    refuse_inputs([out], [source, station if isinstance(station, (str, Path)) else None], "--out")
    st = load_station(station_path(station) if station else station_path())
    cam = st.camera(camera)
    src = open_source(cam, source, base_dir=base_dir if base_dir is not None else Path.cwd())
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
    from cbh.fileio import atomic_write

    ok, png = cv2.imencode(".png", mask)
    if not ok:
        raise RecordingError(f"cannot encode the mask image {out}")
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        with atomic_write(out) as tmp:  # whole or not at all: a full disk leaves an older mask
            tmp.write_bytes(png.tobytes())
    except OSError as exc:
        from cbh.outputs.export import write_error

        raise write_error(out, exc) from None
    usable = (mask > 0).sum() / max(1, cam.model.image_circle_mask().sum())
    return MaskReport(camera, len(images), out, float(1.0 - usable))
