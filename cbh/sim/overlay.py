"""A camera's on-screen display (OSD): the date, time and name an IP camera stamps on its frames.

Drawn by the camera onto the pixel grid after the optics, before its encoder: sharp, white (or
yellow) text, made legible on any sky by a one-pixel black outline, a drop shadow, or a black
banner behind it. Where the lens's image circle is wider than the frame (or the overlay sits
inside the circle) the text lies on the sky; each camera stamps its own clock, so the two
frames of a pair differ in their seconds when the clocks do.

:func:`draw_overlay` draws an :class:`Overlay` onto a finished frame and passes the block it
touched through the camera's JPEG again (at ``quality``), as the encoder would have seen it;
the truth is unchanged (text is no cloud).
"""
from __future__ import annotations

from dataclasses import dataclass
from datetime import datetime, timedelta

import cv2
import numpy as np

from cbh.sim.render import reencode

__all__ = ["Overlay", "draw_overlay", "OVERLAY_STYLES", "OVERLAY_FORMATS"]

OVERLAY_STYLES = ("outline", "shadow", "banner")
OVERLAY_FORMATS = ("%Y-%m-%d %H:%M:%S", "%d.%m.%Y %H:%M:%S", "%a %d %b %Y %H:%M:%S", "%H:%M:%S")
_FONT = cv2.FONT_HERSHEY_SIMPLEX
_CAP_HEIGHT = 22.0  # Hershey simplex's cap height at scale 1 [px]


@dataclass(frozen=True)
class Overlay:
    name: str  # the camera's name, printed before the time ("" for none)
    time_format: str  # strftime format of the camera's clock
    style: str  # one of OVERLAY_STYLES
    height_frac: float  # cap height as a share of the frame's height [1]
    x_frac: float  # the text's left edge as a share of the frame's width [1]
    y_frac: float  # its baseline as a share of the frame's height [1]
    yellow: bool = False  # yellow text instead of white
    clock_offset_s: float = 0.0  # the camera's clock less the true time [s]

    def text(self, time_utc: datetime) -> str:
        t = (time_utc + timedelta(seconds=self.clock_offset_s)).strftime(self.time_format)
        return f"{self.name} {t}" if self.name else t


def draw_overlay(image: np.ndarray, overlay: Overlay, time_utc: datetime, quality: int = 90) -> np.ndarray:
    """``image`` (H, W, 3) uint8 BGR with ``overlay``'s text for ``time_utc`` stamped on it (a new array)."""
    H, W = image.shape[:2]
    scale = max(overlay.height_frac * H / _CAP_HEIGHT, 0.25)
    thick = max(1, int(round(scale * 1.4)))
    text = overlay.text(time_utc)
    (tw, th), base = cv2.getTextSize(text, _FONT, scale, thick)
    x, y = int(overlay.x_frac * W), int(overlay.y_frac * H)
    out = image.copy()
    colour = (0, 255, 255) if overlay.yellow else (255, 255, 255)
    if overlay.style == "banner":
        pad = max(2, th // 4)
        cv2.rectangle(out, (x - pad, y - th - pad), (x + tw + pad, y + base + pad), (0, 0, 0), -1)
    elif overlay.style == "shadow":
        d = max(1, thick)
        cv2.putText(out, text, (x + d, y + d), _FONT, scale, (0, 0, 0), thick, cv2.LINE_AA)
    else:  # a one-pixel outline: the text in black at the eight neighbouring offsets
        for dx in (-1, 0, 1):
            for dy in (-1, 0, 1):
                if dx or dy:
                    cv2.putText(out, text, (x + dx, y + dy), _FONT, scale, (0, 0, 0), thick, cv2.LINE_AA)
    cv2.putText(out, text, (x, y), _FONT, scale, colour, thick, cv2.LINE_AA)
    return _encode_block(out, (x - th, y - 2 * th, x + tw + th, y + base + th), quality)


def _encode_block(image: np.ndarray, box: tuple[int, int, int, int], quality: int) -> np.ndarray:
    """``image`` with the 16-px-aligned block around ``box`` (x0, y0, x1, y1) through JPEG at ``quality``."""
    H, W = image.shape[:2]
    x0, y0 = max(box[0] // 16 * 16, 0), max(box[1] // 16 * 16, 0)
    x1, y1 = min(-(-box[2] // 16) * 16, W), min(-(-box[3] // 16) * 16, H)
    if x1 <= x0 or y1 <= y0:
        return image
    image[y0:y1, x0:x1] = reencode(np.ascontiguousarray(image[y0:y1, x0:x1]), quality)
    return image
