"""Reading and decoding images with one-line errors (missing, corrupt, wrong size)."""
from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from cbh.errors import ImageError

if TYPE_CHECKING:  # only for the annotation: shared helpers import no wing
    from cbh.geometry.camera import CameraModel

__all__ = ["read_image", "decode_image", "encode_jpeg", "check_image_size"]


def decode_image(data: bytes, what: str = "image") -> np.ndarray:
    """Decode JPEG/PNG bytes to a BGR uint8 (H, W, 3) array; :class:`ImageError` if corrupt."""
    import cv2

    if not data:
        raise ImageError(f"{what}: empty image data")
    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
    if img is None:
        raise ImageError(f"{what}: corrupt or unsupported image data ({len(data)} bytes)")
    return img


def read_image(path: str | Path) -> tuple[np.ndarray, bytes]:
    """Read an image file: (BGR uint8 (H, W, 3) array, the file's bytes)."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise ImageError(f"image not found: {path}") from None
    except IsADirectoryError:
        raise ImageError(f"not an image file (a directory): {path}") from None
    except OSError as exc:
        raise ImageError(f"cannot read image {path}: {exc.strerror}") from None
    return decode_image(data, what=str(path)), data


def encode_jpeg(image: np.ndarray, quality: int = 92) -> bytes:
    """BGR uint8 image → JPEG bytes."""
    import cv2

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
