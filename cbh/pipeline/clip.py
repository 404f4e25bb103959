"""The clip (white) level of an image, and its saturated pixels: one function for the whole pipeline.

A camera clips at its own white level, not necessarily at 255: limited-range video (IP
cameras streaming H.264 over RTSP) puts white at 235, some sensors clip at 235-250, and a
limited-range stream of such a sensor lower still (a 235 clip squeezed into 16..235 reads
218). A fixed "every channel ≥ 250" test then finds no saturated pixel at all, so neither
the sun nor its glare. :func:`clip_level` estimates the level from the image itself and
:func:`saturated_pixels` tests against it; every saturation test of the pipeline (the sun
detector, the glare mask) goes through these two.

Method (:func:`clip_level`): clipping maps every scene value above the white level ``L`` to
``L``, so the histogram of the image's luma (Y = 0.299 R + 0.587 G + 0.114 B, what JPEG and
H.264 store at full resolution, free of their chroma subsampling) piles up in a spike at ``L``
(smeared over a few DN by compression) with (almost) nothing above it, while natural bright
content (cloud, haze) has a tail that falls off towards the top. From the brightest pixels
down (``top``: the luma that the ``min_pixels`` brightest reach, so a few compression
overshoots above the clip do not count), each local maximum of the histogram within
``search_dn`` is tried, and the first that holds a spike is the clip level. A spike at ``L``,
for a window ``L ± hw`` (hw = 0: an uncompressed clip sits in one DN; 2, 4: compression
smear; see ``spike_halfwidths_dn``):

- its excess over the background (the mean count per DN of the ``background_dn`` DN just
  below the window, times the window's width) is at least ``min_pixels`` and 4 standard
  deviations of that background's Poisson count;
- its count per DN is at least ``min_spike_ratio`` × the background's;
- at most ``max_above_ratio`` of its count lies above the window;
- ``L`` ≥ ``min_level_dn``: darker spikes are bright content of a dim image, not a white level.

Frames encoded twice (limited-range video saved again as JPEG by a recorder) smear the clip
over ±10 DN: ringing lifts the clipped disk's edge to 243-246 while its luma histogram has as
much above the clip as in it, so no window passes the test above. A clipped area is flat,
though, and its ringing oscillates about the clip: when the raw histogram holds no spike, the
same search runs on the luma smoothed by a ``flat_px`` box filter, counting only the pixels
whose smoothed neighbourhood (``flat_px`` square) spans at most ``flat_range_dn``: the clipped
plateau piles up within a DN of its level (235 in 1044 of 1300 flat pixels of a sunny frame,
against 2016 of 19 000 pixels within ±10 DN raw) while sloped glow and textured cloud drop out.

Without a spike the nominal full-range white (255) is returned with ``found=False``: an image
that never clips has nothing saturated, as before. Most cameras clip white to white (their
processing desaturates highlights; limited-range video clips luma at 235 with neutral chroma),
and then one level serves every channel: the luma of the clip, while a channel's own histogram
near the top mixes in compression overshoots (blue sky's blue piles up at 255). A camera that
applies its white balance or exposure gain after the sensor has clipped gives a tinted plateau
instead (randomized sky 19982: camera 2's sun disk and aureole at B, G, R = 220, 242, 237, luma
238): its blue never reaches the luma's level, no pixel passed the test below, the glare went
unmasked and a 25° ring of aureole round it was read as cloud (0.125 of the sky, truth 0.03). So
the plateau's colour is read too (:func:`_plateau_colour`: each channel's median over the spike's
pixels), and a channel more than 4 DN below the luma's level that has nothing above it clips at
its own level (``ClipLevel.channels_dn``).

Limits: a large uniform region brighter than ``min_level_dn`` with nothing brighter in the
image (a bright, even overcast and no sun) looks the same as a clip and is taken for one; a
clipped area much smaller than ``min_pixels`` or drowned in textured near-white cloud (JPEG
quality 75, no sun) is not found, and the nominal level applies.

Saturated (:func:`saturated_pixels`): every channel at least its level (``L``, or its own on a
tinted clip) less ``margin_dn``. JPEG's chroma subsampling spreads a clipped disk's colour by a
few DN (its smallest channel 1-6 DN below the clip at quality 92), hence the margin (5 DN: the
pipeline's historical 250 for a 255 clip).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import math

import cv2
import numpy as np

__all__ = ["ClipConfig", "ClipLevel", "clip_level", "saturated_pixels", "FULL_RANGE_WHITE_DN"]

FULL_RANGE_WHITE_DN = 255  # white of an 8-bit full-range image [DN]
_TINT_WINDOW_DN = 4  # a channel of the clipped plateau further than this below its luma clips at its own level (JPEG's
#                      chroma smear pulls a white 255 clip's red to 251-252 at Fehmarn) [DN]


@dataclass(frozen=True)
class ClipConfig:
    """Thresholds of :func:`clip_level` (DN of 8-bit images; pixels at the size given)."""

    min_pixels: int = 10  # pixels a clip spike holds at least (above its background) [px]
    search_dn: int = 24  # the spike's mode is looked for this far below the brightest pixels [DN]
    spike_halfwidths_dn: tuple[int, ...] = (0, 2, 4)  # spike windows tried: ± this around the mode [DN]
    background_dn: int = 12  # width of the band just below the spike it is compared with [DN]
    min_spike_ratio: float = 1.3  # the spike's count per DN / the background's per DN, at least [1]
    max_above_ratio: float = 0.5  # pixels above the spike window / pixels in it, at most [1]
    min_level_dn: int = 192  # a spike below this (75 % of full scale) is taken for bright content, not a clip [DN]
    flat_px: int = 5  # second pass: box filter and neighbourhood of the flat (plateau) pixels [px]; 0 = none
    flat_range_dn: int = 3  # … whose smoothed luma spans at most this over the neighbourhood [DN]


@dataclass(frozen=True)
class ClipLevel:
    """Result of :func:`clip_level`.

    Attributes
    ----------
    level_dn : int
        The image's clip (white) level [DN]: that of its luma, and of every channel unless
        ``channels_dn`` says otherwise.
    found : bool
        True when the image shows a clip spike; False: the nominal full-range white (255).
    pixels : int
        Pixels in the spike [px] (0 when not found).
    smeared : bool
        True when the level was found only on the smoothed plateau (a clip smeared by a second
        encoding: the saturated area's edge is blocky and ragged).
    channels_dn : (int, int, int) or None
        Each channel's own level (B, G, R) where the clip is tinted (white balance or gain applied
        after the sensor clipped); None: ``level_dn`` for all three.
    """

    level_dn: int
    found: bool
    pixels: int = 0
    smeared: bool = field(default=False, repr=False)
    channels_dn: "tuple[int, int, int] | None" = field(default=None, repr=False)

    def channel_levels(self) -> tuple[int, int, int]:
        """Each channel's clip level (B, G, R) [DN]: ``channels_dn`` where the clip is tinted
        (see :func:`clip_level`), else ``level_dn`` for all three."""
        return self.channels_dn if self.channels_dn is not None else (self.level_dn,) * 3

    @classmethod
    def nominal(cls) -> "ClipLevel":
        """Full-range white (no clip seen)."""
        return cls(FULL_RANGE_WHITE_DN, False, 0)


def clip_level(image_bgr: np.ndarray, cfg: ClipConfig = ClipConfig(), mask: np.ndarray | None = None) -> ClipLevel:
    """The clip (white) level of one image (see the module docstring).

    Parameters
    ----------
    image_bgr : ndarray, shape (H, W, 3), uint8
        The image as the camera delivered it (any size).
    cfg : ClipConfig
    mask : ndarray, shape (H, W), bool or uint8, optional
        Pixels to look at (default: all).

    Returns
    -------
    ClipLevel

    Examples
    --------
    >>> import numpy as np
    >>> img = np.full((40, 40, 3), 120, np.uint8)
    >>> img[10:20, 10:20] = 218                     # a clipped disk of limited-range video
    >>> clip_level(img)
    ClipLevel(level_dn=218, found=True, pixels=100)
    >>> clip_level(np.full((40, 40, 3), 120, np.uint8)).found   # an unclipped image's top is no clip
    False
    """
    img = np.asarray(image_bgr)
    if img.ndim != 3 or img.shape[2] != 3 or img.dtype != np.uint8:
        raise ValueError(f"clip_level: expected an (H, W, 3) uint8 image, got {img.shape} {img.dtype}")
    m8 = None if mask is None else np.asarray(mask).astype(np.uint8)
    luma = cv2.cvtColor(np.ascontiguousarray(img), cv2.COLOR_BGR2GRAY)
    h = cv2.calcHist([luma], [0], m8, [256], [0, 256]).ravel()
    spike = _spike_level(h, cfg)
    smeared = False
    if spike is None and cfg.flat_px > 1:  # a clip smeared by a second encoding: its flat plateau
        h = _plateau_histogram(luma, m8, cfg)
        spike, smeared = _spike_level(h, cfg), True
    if spike is None:
        return ClipLevel.nominal()
    level, hw = spike
    return ClipLevel(int(level), True, int(h[level - hw:level + hw + 1].sum()), smeared,
                     _plateau_colour(img, luma, m8, int(level), hw, cfg))


def _plateau_colour(img: np.ndarray, luma: np.ndarray, m8: np.ndarray | None, level: int, hw: int,
                    cfg: ClipConfig) -> "tuple[int, int, int] | None":
    """Each channel's clip level (B, G, R) where the clip is tinted, else None (every channel
    at the luma's level; see the module docstring).

    A channel's level is its median over the pixels whose luma lies within ``hw`` of the clip's;
    it is the channel's own where that lies more than ``_TINT_WINDOW_DN`` below the luma's level
    (a channel above it passes the luma's test anyway) and the channel has (almost) nothing above
    it anywhere (at most ``max_above_ratio`` × the spike's pixels more than ``_TINT_WINDOW_DN``
    above: the top of its own histogram, as a clip is; a bright even patch of colour taken for a
    clip has brighter pixels of that channel elsewhere), else the luma's."""
    spike = cv2.inRange(luma, max(level - hw, 0), min(level + hw, 255))
    if m8 is not None:
        spike &= (m8 > 0).view(np.uint8) * 255
    n = cv2.countNonZero(spike)
    if not n:
        return None
    x, y, w, h = cv2.boundingRect(spike)
    colour = np.median(img[y:y + h, x:x + w][spike[y:y + h, x:x + w] > 0], axis=0)
    levels = []
    for c in range(3):
        v = int(colour[c])
        if v < level - _TINT_WINDOW_DN:
            above = cv2.calcHist([img], [c], m8, [256], [0, 256]).ravel()[v + _TINT_WINDOW_DN + 1:].sum()
            v = v if above <= cfg.max_above_ratio * n else level
        levels.append(v if v < level - _TINT_WINDOW_DN else level)
    return None if levels == [level] * 3 else tuple(levels)


def _plateau_histogram(luma: np.ndarray, m8: np.ndarray | None, cfg: ClipConfig) -> np.ndarray:
    """Histogram (256,) of the box-smoothed luma over its flat pixels (see the module docstring);
    only the bright part of the image is filtered (the clip is at least ``min_level_dn``)."""
    bright = cv2.inRange(luma, cfg.min_level_dn - cfg.search_dn, 255)
    if not cv2.countNonZero(bright):
        return np.zeros(256, np.float32)
    x, y, w, hh = cv2.boundingRect(bright)
    g = cfg.flat_px
    y0, y1, x0, x1 = max(y - g, 0), min(y + hh + g, luma.shape[0]), max(x - g, 0), min(x + w + g, luma.shape[1])
    crop = luma[y0:y1, x0:x1]
    smooth = cv2.blur(crop, (g, g))
    k = np.ones((g, g), np.uint8)
    flat = cv2.inRange(cv2.subtract(cv2.dilate(smooth, k), cv2.erode(smooth, k)), 0, cfg.flat_range_dn)
    if m8 is not None:
        flat &= (m8[y0:y1, x0:x1] > 0).view(np.uint8) * 255
    return cv2.calcHist([smooth], [0], flat, [256], [0, 256]).ravel()


def _spike_level(h: np.ndarray, cfg: ClipConfig) -> tuple[int, int] | None:
    """(luma, half-width) of the clip spike in the histogram ``h`` (256,), or None.

    The candidates are the local maxima within ``search_dn`` below the brightest pixels,
    tried from the brightest down: a small clipped sun above a large bright natural mode
    (haze at the horizon) is still the clip.
    """
    above = np.cumsum(h[::-1])[::-1]  # pixels at or above each value
    if above[0] < cfg.min_pixels:
        return None
    top = int(np.nonzero(above >= cfg.min_pixels)[0][-1])
    brightest = int(np.nonzero(h)[0][-1])
    for level in range(top, max(top - cfg.search_dn, cfg.min_level_dn) - 1, -1):
        if h[level] == 0 or h[level] < h[level - 1] or (level < 255 and h[level] < h[level + 1]):
            continue  # not a local maximum
        hw = _spike_halfwidth(h, level, brightest, cfg)
        if hw is not None:
            return level, hw
    return None


def _spike_halfwidth(h: np.ndarray, level: int, brightest: int, cfg: ClipConfig) -> int | None:
    """The narrowest window ``level ± hw`` that holds a clip spike (see the module docstring), or None."""
    for hw in cfg.spike_halfwidths_dn:  # one DN (uncompressed), then wider (compression smear)
        s0, s1 = level - hw, min(level + hw, brightest)
        b0 = s0 - cfg.background_dn
        if b0 < 0:
            return None
        spike = float(h[s0:s1 + 1].sum())
        width = s1 - s0 + 1
        background = float(h[b0:s0].sum()) / cfg.background_dn  # count per DN just below the spike
        excess = spike - background * width  # what the clip piled up
        significant = excess >= max(cfg.min_pixels, 4.0 * math.sqrt(background * width + 1.0))  # 4 sigma (Poisson)
        if significant and spike >= cfg.min_spike_ratio * background * width \
                and float(h[s1 + 1:].sum()) <= cfg.max_above_ratio * spike:
            return hw
    return None


def saturated_pixels(image_bgr: np.ndarray, margin_dn: int = 5, clip: ClipLevel | None = None) -> np.ndarray:
    """Pixels whose every channel is at least the image's clip level minus ``margin_dn``.

    Parameters
    ----------
    image_bgr : ndarray, shape (H, W, 3), uint8
    margin_dn : int
        How far below each channel's clip level a pixel still counts as saturated [DN].
    clip : ClipLevel, optional
        The image's clip level (default: :func:`clip_level` of ``image_bgr``); pass it when
        it is known, e.g. estimated on the whole image for a crop.

    Returns
    -------
    ndarray, shape (H, W), uint8
        255 where saturated, 0 elsewhere (``cv2.inRange`` convention).
    """
    if clip is None:
        clip = clip_level(image_bgr)
    lo = tuple(max(int(v) - int(margin_dn), 0) for v in clip.channel_levels())
    return cv2.inRange(image_bgr, lo, (255, 255, 255))
