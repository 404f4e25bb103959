"""``cbh segment`` in library terms: cloud masks of single images, with or without a station.

Without a station every pixel of the image is sky (crops, any JPEG/PNG): the segmentation
adapts over image regions. With a station and a camera, the image must be at the camera's
calibration size and the pipeline's masks apply (image circle, zenith limit, obstacle mask,
the sun disk when the time is known, saturated glare); the segmentation then works, like the
pipeline's, at working size (``[pipeline] working_radius_px``) on zenith × sun-angle regions,
and the mask is brought back to the image's size.
"""
from __future__ import annotations

from dataclasses import dataclass
from datetime import datetime
from pathlib import Path

import cv2
import numpy as np

from cbh.errors import RecordingError

__all__ = ["SegmentedImage", "segment_image", "segment_files", "write_mask", "mask_paths"]


@dataclass(frozen=True)
class SegmentedImage:
    """One image's cloud mask.

    Attributes
    ----------
    cloud : ndarray, shape (H, W), bool
        Cloud at the image's size (False: clear sky or not usable).
    usable : ndarray, shape (H, W), bool
        Pixels that were classified.
    cloud_fraction : float
        Cloud share of the usable pixels, 0..1 (0 when nothing is usable).
    """

    cloud: np.ndarray
    usable: np.ndarray
    cloud_fraction: float


def segment_image(image: np.ndarray, station=None, camera: str | None = None, time_utc: datetime | None = None,
                  config=None, what: str = "image") -> SegmentedImage:
    """Cloud mask of one BGR uint8 (H, W, 3) colour image.

    Parameters
    ----------
    image : ndarray, shape (H, W, 3), uint8
        A colour image (greyscale is refused: :class:`~cbh.errors.ImageError`).
    station : Station or None
        None: the whole image is sky.
    camera : str or None
        The station's camera that took the image (default: the station's first camera).
    time_utc : datetime or None
        Capture time (aware); with a station it places the sun (masked disk, sun-angle regions).
    config : PipelineConfig or None
        Default: the station's ``[pipeline]`` table, or all defaults without a station.
    what : str
        Name of the image in error messages.
    """
    from cbh.pipeline.config import PipelineConfig
    from cbh.pipeline.segment import check_colour, segment

    check_colour(image, what)
    if station is None:
        cfg = config or PipelineConfig()
        usable = np.ones(image.shape[:2], bool)
        cloud, frac = segment(image, usable, None, None, cfg.segmentation, what=what)
        return SegmentedImage(cloud=cloud, usable=usable & _bright(image, cfg), cloud_fraction=frac)

    from cbh.imageio import check_image_size
    from cbh.geometry.sun import sun_position
    from cbh.pipeline.masks import angle_map_deg, glare_mask, load_obstacle_mask, static_sky_mask
    from cbh.pipeline.run import working_factor

    cfg = config or PipelineConfig.from_dict(station.sections.get("pipeline", {}))
    cam_full = station.camera(camera) if camera else next(iter(station.cameras.values()))
    check_image_size(image, cam_full.model, what)
    f = working_factor(cam_full, cfg.working_radius_px)
    cam = cam_full.scaled(f) if f != 1.0 else cam_full
    H, W = cam.model.height, cam.model.width
    work = image if f == 1.0 else cv2.resize(image, (W, H), interpolation=cv2.INTER_AREA)
    obstacle = None
    if cam.mask is not None and cfg.masks.static_mask:
        obstacle = load_obstacle_mask(cam.mask, W, H)
    usable = static_sky_mask(cam, cfg.masks, obstacle)
    sun_angle = None
    if time_utc is not None:
        sun = sun_position(station.latitude_deg, station.longitude_deg, station.altitude_m, time_utc)
        sun_dir, sun_zen = sun.direction_enu, sun.zenith_deg
        if sun_zen < 90.0:
            sun_angle = angle_map_deg(cam, sun_dir)
            if cfg.masks.sun:
                usable &= sun_angle > cfg.masks.sun_radius_deg
    if cfg.masks.saturation:  # as the pipeline: with a known sun, only saturation near it is glare
        usable &= ~glare_mask(work, cfg.masks, sun_angle)
    zenith = np.asarray(cam.zenith_map(), np.float32)
    cloud, frac = segment(work, usable, zenith, sun_angle, cfg.segmentation, what=what)
    usable &= _bright(work, cfg)
    if f != 1.0:
        size = (cam_full.model.width, cam_full.model.height)
        cloud = cv2.resize(cloud.view(np.uint8), size, interpolation=cv2.INTER_NEAREST) > 0
        usable = cv2.resize(usable.view(np.uint8), size, interpolation=cv2.INTER_NEAREST) > 0
    return SegmentedImage(cloud=cloud, usable=usable, cloud_fraction=frac)


def _bright(image: np.ndarray, cfg) -> np.ndarray:
    return image.max(axis=2) >= cfg.segmentation.min_brightness


def write_mask(path: Path, cloud: np.ndarray) -> Path:
    """Write a cloud mask as an 8-bit PNG: 255 cloud, 0 clear or unusable.

    ``path`` must end in ``.png``. The file appears whole or not at all (a temporary file
    beside it is renamed); errors name ``path``.
    """
    from cbh.fileio import atomic_write

    path = Path(path)
    if path.suffix.lower() != ".png":
        raise RecordingError(f"{path}: a mask is written as PNG; give a .png name")
    ok, png = cv2.imencode(".png", np.where(cloud, 255, 0).astype(np.uint8))
    if not ok:  # pragma: no cover - encoding a uint8 image does not fail
        raise RecordingError(f"cannot encode mask {path}")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with atomic_write(path) as tmp:
            tmp.write_bytes(png.tobytes())
    except OSError as exc:
        raise RecordingError(f"cannot write mask {path}: {exc.strerror or exc}") from None
    return path


#: Suffixes of image files: an ``--out`` ending in one names a file, not a folder.
_IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp", ".webp", ".gif")


def mask_paths(images: list[Path], out: Path) -> list[Path]:
    """Where the masks of ``images`` go (the ``--out`` rule of ``cbh segment``), checked before
    any image is read.

    - ``out`` ending in ``.png`` (and not an existing folder): the mask of the one image;
    - otherwise ``out`` is a folder (created if missing) and each mask is ``out/<stem>.png``;
    - refused, as one :class:`~cbh.errors.InputError`: several images and a ``.png`` file name,
      another image suffix (``x.jpg``: masks are PNG), an existing file that is not a PNG,
      two images with the same stem, and a mask that would overwrite one of the images.
    """
    from cbh.errors import InputError

    out = Path(out)
    if out.is_dir() or (not out.exists() and out.suffix.lower() not in _IMAGE_SUFFIXES):
        stems = [p.stem for p in images]
        dup = sorted({st for st in stems if stems.count(st) > 1})
        if dup:
            raise InputError(f"two images share the name {dup[0]!r}: their masks would overwrite each other")
        dests = [out / f"{p.stem}.png" for p in images]
    elif out.suffix.lower() != ".png":
        raise InputError(f"--out {out}: a mask is written as PNG; give a .png name (or a folder)")
    elif len(images) > 1:
        raise InputError(f"--out {out}: {len(images)} images need a folder (each mask is <stem>.png in it), "
                         "not a .png file name")
    else:
        dests = [out]
    inputs = {p.resolve(): p for p in images}
    for d in dests:
        if d.resolve() in inputs:
            raise InputError(f"--out {out}: the mask would overwrite the input image {inputs[d.resolve()]}")
    return dests


def segment_files(paths: list[Path], out: Path, station_file: Path | None = None, camera: str | None = None,
                  time_utc: datetime | None = None) -> list[dict]:
    """Segment image files and write their masks (the ``cbh segment`` command).

    ``out``: the mask's ``.png`` path (one image), or a folder that gets ``<image stem>.png``
    per image (:func:`mask_paths`). Returns one dict per image: ``image``, ``mask`` (paths as
    str), ``cloud_fraction``, ``usable_fraction`` (share of the image's pixels that were
    classified).
    """
    from cbh.errors import InputError
    from cbh.imageio import read_image

    station = None
    if station_file is not None:
        from cbh.actions.station import load_station
        from cbh.presets import station_path

        station = load_station(station_path(str(station_file)))
    elif camera is not None or time_utc is not None:
        raise InputError("--camera and --time need --station")
    paths = [Path(p) for p in paths]
    if not paths:
        raise InputError("give at least one image")
    from cbh.fileio import refuse_inputs

    dests = mask_paths(paths, Path(out))  # (its own checks first: a .png name, the inputs by path)
    refuse_inputs(dests, [*paths, station_file], "--out")
    rows = []
    for p, dest in zip(paths, dests):
        img, _ = read_image(p)
        seg = segment_image(img, station, camera, time_utc, what=str(p))
        write_mask(dest, seg.cloud)
        rows.append({"image": str(p), "mask": str(dest), "cloud_fraction": round(seg.cloud_fraction, 4),
                     "usable_fraction": round(float(seg.usable.mean()), 4)})
    return rows
