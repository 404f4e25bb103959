"""Reading and decoding images with one-line errors (missing, corrupt, wrong size)."""
from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np

from cbh.errors import ImageError

if TYPE_CHECKING:  # only for the annotation: shared helpers import no wing
    from cbh.geometry.camera import CameraModel

__all__ = ["read_image", "decode_image", "encode_jpeg", "check_image_size", "as_bgr", "is_greyscale", "CHANNEL_ORDERS"]

#: Channel orders an array argument may declare: "rgb" (PIL, imageio, matplotlib), "bgr" (OpenCV).
CHANNEL_ORDERS = ("rgb", "bgr")


def _is_grey(img: np.ndarray) -> bool:
    """True if the three channels are equal (a greyscale image stored as colour)."""
    sub = img[::7, ::7]  # cheap test first: colour shows up in any subsample
    if not (np.array_equal(sub[..., 0], sub[..., 1]) and np.array_equal(sub[..., 1], sub[..., 2])):
        return False
    return bool(np.array_equal(img[..., 0], img[..., 1]) and np.array_equal(img[..., 1], img[..., 2]))


def is_greyscale(image: np.ndarray) -> bool:
    """True for a 2-D or one-channel image, or a three-channel one whose channels are all equal."""
    a = np.asarray(image)
    if a.ndim == 2 or (a.ndim == 3 and a.shape[2] == 1):
        return True
    return a.ndim == 3 and a.shape[2] == 3 and _is_grey(a)


def as_bgr(image, channels: str | None = None, what: str = "image", model: CameraModel | None = None) -> np.ndarray:
    """An image argument → BGR uint8 (H, W, 3), the order the pipeline works in.

    Parameters
    ----------
    image : str, Path or ndarray
        A file path (JPEG/PNG, read as BGR), or a uint8 array (H, W, 3) whose channel order
        ``channels`` declares.
    channels : {"rgb", "bgr"}, optional
        Required for arrays: a bare array is never guessed to be BGR (an RGB array read as BGR
        swaps blue and red, and the blue/red cloud test then sees cloud everywhere).
    what : str
        Names the image in error messages.
    model : CameraModel, optional
        If given, the image must have its calibration size (checked before the colour test).

    Raises
    ------
    ImageError
        Unreadable file, an array without ``channels``, wrong shape or dtype, or a greyscale
        image (2-D, one channel, or three equal channels): cloud segmentation needs colour.
    """
    if isinstance(image, (str, Path)):
        img = read_image(image)[0]
    elif isinstance(image, np.ndarray):
        if channels is None:
            raise ImageError(f"{what}: an array has no declared channel order; pass channels='rgb' "
                             "(PIL, imageio, matplotlib) or channels='bgr' (OpenCV), or give the file path")
        if str(channels).lower() not in CHANNEL_ORDERS:
            raise ImageError(f"{what}: channels must be 'rgb' or 'bgr', got {channels!r}")
        if image.ndim == 2 or (image.ndim == 3 and image.shape[2] == 1):
            raise ImageError(f"{what}: greyscale image {image.shape}: cloud segmentation needs a colour image")
        if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
            raise ImageError(f"{what}: expected a uint8 (H, W, 3) colour image, got {image.dtype} {image.shape}")
        img = image[..., ::-1] if str(channels).lower() == "rgb" else image
    else:
        raise ImageError(f"{what}: expected a file path or a uint8 (H, W, 3) array, got {type(image).__name__}")
    if model is not None:
        check_image_size(img, model, what)
    if _is_grey(img):
        lo, hi = int(img.min()), int(img.max())
        if hi - lo <= _BLANK_DN:  # not a greyscale camera: no picture at all
            why = ("over-exposed or blinded" if lo >= 200 else "dark: lens covered, night or no signal" if hi <= 40
                   else "uniform grey: no picture from the camera")
            raise ImageError(f"{what}: blank frame (every pixel {lo}…{hi} of 255): nothing to measure ({why})")
        raise ImageError(f"{what}: greyscale image (its three channels are equal): cloud segmentation needs colour")
    return np.ascontiguousarray(img)


_BLANK_DN = 8  # a frame whose pixels all lie within this many grey levels is blank (JPEG noise is smaller)


def decode_image(data: bytes, what: str = "image") -> np.ndarray:
    """Decode JPEG/PNG bytes to a BGR uint8 (H, W, 3) array; :class:`ImageError` if corrupt."""
    if not data:
        raise ImageError(f"{what}: empty image data")
    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
    if img is None:
        raise ImageError(f"{what}: corrupt or unsupported image data ({len(data)} bytes)")
    return img


def read_image(path: str | Path) -> tuple[np.ndarray, bytes]:
    """Read an image file: (BGR uint8 (H, W, 3) array, the file's bytes)."""
    from cbh.fileio import read_input

    data = read_input(path, "image", ImageError)
    return decode_image(data, what=str(path)), data


def encode_jpeg(image: np.ndarray, quality: int = 92) -> bytes:
    """BGR uint8 image → JPEG bytes."""
    ok, buf = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:  # pragma: no cover - OpenCV always encodes uint8 BGR
        raise ImageError("JPEG encoding failed")
    return buf.tobytes()


def check_image_size(image: np.ndarray, model: CameraModel, what: str) -> None:
    """:class:`ImageError` unless ``image`` is ``model.width`` × ``model.height``."""
    h, w = image.shape[:2]
    if (w, h) != (model.width, model.height):
        raise ImageError(
            f"{what}: image is {w}x{h} but its calibration is for {model.width}x{model.height}"
        )
