"""Photometric invariance between the two cameras of a pair.

Two cameras of a station expose independently: their gain (exposure time × ISO × aperture),
tone curve (gamma) and white balance differ, frame by frame. Left in, the difference makes
the two cameras' cloud masks disagree (the same sky gives different cloud fractions) and the
intensity-based matchers (LK and DIS compare grey levels) lose or bias their matches.

Model. Camera 2's value ``I2`` in channel c maps onto camera 1's response as

    I1 = 255 · (k_c · I2 / 255)^γ            (k_c = gain · white-balance gain of channel c)

i.e. ln(I1/255) = γ · ln(I2/255) + β_c with β_c = γ · ln k_c: one shared tone-curve exponent
γ and one offset per channel. It is estimated by *quantile matching* inside the common field
of view: camera 1's usable pixels whose direction (at infinity, :class:`PairGeometry`'s remap)
falls inside camera 2's usable sky, and camera 2's pixels at those same directions. The two
cameras see the same sky there, displaced only by the parallax (a few degrees for clouds a
kilometre up and a 100 m baseline), so the *distributions* of the values agree even where
single pixels do not: the p-th percentile of camera 1 is camera 2's p-th percentile under the
response. Percentiles 0.5 … 99.5 % are used, leaving out values at or near black (≤ 4) and
saturation (≥ 250) in either camera; γ and the β_c are a linear least-squares fit. With too
narrow a range of values (overcast, uniform sky: γ is not determined) γ is fixed to 1.

Reported (``PairResult.diagnostics``): ``exposure_gain`` = k_G (camera 2 → camera 1; > 1:
camera 2 is darker), ``exposure_gamma`` = γ, ``wb_red`` = k_R / k_G, ``wb_blue`` = k_B / k_G;
:meth:`ColourResponse.is_large` decides the ``exposure_mismatch`` flag. The brighter camera's
working image is then mapped through the lookup table, so that segmentation and matching
see both cameras with one response. The mapping always goes *down*: when camera 2 is the
darker one, camera 1 is mapped onto camera 2's response instead (the inverse), because
brightening a camera pushes its bright cloud into saturation and stretches its noise, and
neither can be undone.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np

from cbh.pipeline.clip import clip_level

__all__ = ["ColourResponse", "estimate_response", "channel_percentiles"]

_QUANTILES = np.linspace(0.5, 99.5, 100)  # percentiles matched [%]
_DARK, _BRIGHT = 4.0, 250.0  # values outside (_DARK, _BRIGHT) are not fitted [DN]
_CLIP_MARGIN = 5  # … nor within this of the image's own clip level (cbh.pipeline.clip) [DN]
_MIN_PIXELS = 2000  # fewer common pixels: no estimate (identity)
_MIN_LOG_RANGE = 0.25  # spread of ln(I2) over the fitted quantiles below which γ is fixed to 1
_GAMMA_LIMITS = (0.4, 2.5)  # estimates outside this are not a camera response: clamp
_SAMPLES = 30_000  # camera-1 pixels sampled (on a regular grid) for the quantiles
MAX_LUT_SLOPE = 2.0  # the table segmentation reads (matching_luts(capped=True)) rises at most this many levels per level … [1]
LUT_SLOPE_SPAN = 4  # … over any span of this many levels or more (a shorter one: this × the slope) [levels]


@dataclass(frozen=True)
class ColourResponse:
    """Camera 2's colour response relative to camera 1 (see the module docstring).

    Attributes
    ----------
    gain : float
        k_G: multiplies camera 2's green values before the tone curve [1].
    gamma : float
        Tone-curve exponent γ [1].
    wb_red, wb_blue : float
        Red and blue gains relative to green, k_R / k_G and k_B / k_G [1].
    pixels : int
        Common-view pixels behind the estimate (0 = no estimate: identity).
    """

    gain: float = 1.0
    gamma: float = 1.0
    wb_red: float = 1.0
    wb_blue: float = 1.0
    pixels: int = 0
    q1: np.ndarray | None = field(default=None, repr=False, compare=False)  # (Q, 3) camera 1 percentiles, BGR
    q2: np.ndarray | None = field(default=None, repr=False, compare=False)  # (Q, 3) camera 2 percentiles, BGR

    def matching_luts(self, capped: bool = False) -> tuple[np.ndarray, np.ndarray] | None:
        """Histogram-matching lookup tables (camera 2 → 1, camera 1 → 2), each (256, 1, 3) uint8.

        Monotone piecewise-linear maps through the matched percentiles of the common view
        (the parametric model fitted to the same percentiles is what is *reported*; the
        tables also follow a tone curve's knee and shoulder, which a power law does not).
        ``capped``: each table's rise limited by :func:`capped_slope` (``MAX_LUT_SLOPE`` per level
        over ``LUT_SLOPE_SPAN`` levels), for the colours that segmentation reads.
        None without percentiles.
        """
        if self.q1 is None or self.q2 is None:
            return None
        x = np.arange(256, dtype=np.float64)
        out = []
        for src, dst in ((self.q2, self.q1), (self.q1, self.q2)):
            chans = []
            for c in range(3):
                s = np.concatenate([[0.0], np.maximum.accumulate(src[:, c]), [255.0]])
                d = np.concatenate([[0.0], np.maximum.accumulate(dst[:, c]), [255.0]])
                s, keep = np.unique(s, return_index=True)  # strictly increasing abscissae
                t = np.interp(x, s, d[keep])
                chans.append(capped_slope(t, MAX_LUT_SLOPE, LUT_SLOPE_SPAN) if capped else t)
            out.append(np.clip(np.round(np.stack(chans, axis=-1)), 0, 255).astype(np.uint8).reshape(256, 1, 3))
        return out[0], out[1]

    def lut(self) -> np.ndarray:
        """Lookup table (256, 1, 3) uint8 mapping camera 2's BGR values onto camera 1's response."""
        x = np.arange(256, dtype=np.float64) / 255.0
        ks = (self.gain * self.wb_blue, self.gain, self.gain * self.wb_red)  # B, G, R
        chans = [np.clip(k * x, 0.0, 1.0) ** self.gamma for k in ks]
        return np.clip(np.round(255.0 * np.stack(chans, axis=-1)), 0, 255).astype(np.uint8).reshape(256, 1, 3)

    def apply(self, image_bgr: np.ndarray) -> np.ndarray:
        """Camera 2's image (H, W, 3) uint8 as camera 1 would have recorded it."""
        return cv2.LUT(image_bgr, self.lut())

    def inverse(self) -> "ColourResponse":
        """Camera 1's response relative to camera 2 (I2 = 255 · (k'_c · I1 / 255)^(1/γ), k'_c = k_c^−γ)."""
        g = self.gamma
        return ColourResponse(gain=self.gain ** -g, gamma=1.0 / g, wb_red=self.wb_red ** -g,
                              wb_blue=self.wb_blue ** -g, pixels=self.pixels)

    def brightens(self) -> bool:
        """True when the mapping makes camera 2 brighter at mid-grey (it would push values into saturation)."""
        return float(self.lut()[128, 0, 1]) > 128.0

    @property
    def is_identity(self) -> bool:
        """True when applying the response changes no value by more than half a level."""
        return bool(np.abs(self.lut().astype(np.int16) - np.arange(256, dtype=np.int16)[:, None, None]).max() == 0)

    def is_large(self, max_gain: float = 1.5, max_gamma: float = 1.25, max_wb: float = 1.15) -> bool:
        """Whether the difference deserves the ``exposure_mismatch`` flag.

        Large = gain beyond ×/÷ ``max_gain`` (half a photographic stop is 1.41), γ beyond
        ×/÷ ``max_gamma``, or a white-balance gain beyond ×/÷ ``max_wb``.
        """
        def off(v, lim):
            return abs(math.log(max(v, 1e-9))) > math.log(lim)

        return off(self.gain, max_gain) or off(self.gamma, max_gamma) or off(self.wb_red, max_wb) or off(self.wb_blue, max_wb)

    def diagnostics(self) -> dict[str, float]:
        """``PairResult.diagnostics`` entries (unit-less ratios)."""
        return {"exposure_gain": float(self.gain), "exposure_gamma": float(self.gamma),
                "wb_red": float(self.wb_red), "wb_blue": float(self.wb_blue)}




def capped_slope(table: np.ndarray, max_slope: float, span: int = 1) -> np.ndarray:
    """The largest table under ``table`` (256,), non-decreasing, whose rise over any n levels is
    at most ``max_slope`` · max(n, ``span``): t'[x] = min(t[x], min over y < x of
    t'[y] + max_slope · max(x − y, span)).

    A camera near its clip compresses a channel's top into a few levels (its tone curve's
    shoulder: randomized 19871 at 480 px, camera 2's blue 246–250 DN over the sky where camera 1's
    spans 182–236); matching its percentiles onto the other camera's stretches each of its levels,
    and every JPEG block step with it, 10× (NBR blocks 0.05–0.1 apart on a clear sky, half of it
    then read as cloud). The levels it lost are not restored by stretching: the capped table
    leaves that top compressed. Single steps of a few levels are the percentiles' own
    quantization (one level of the compressed camera between two knots), hence the span.
    Only segmentation reads the capped tables (its colour thresholds are absolute); the
    matchers keep the full match (their ZNCC does not see a monotone stretch's gain, and the
    real Fehmarn hour re-paired 3 minutes apart lost two pairs when they read the capped one)."""
    t = [float(v) for v in np.asarray(table, np.float64)]  # (plain floats: 256 steps, 20× faster than numpy scalars)
    out = t[:1]
    best, rise, inf = math.inf, float(max_slope) * span, math.inf  # best: min over y ≤ x − span of out[y] − max_slope·y
    for x in range(1, len(t)):
        y = x - span
        if y >= 0:
            best = min(best, out[y] - max_slope * y)
        near = min(out[max(y + 1, 0):x], default=inf) + rise
        out.append(min(t[x], max_slope * x + best, near))
    return np.asarray(out, np.float64)


def channel_percentiles(values: np.ndarray, q: np.ndarray) -> np.ndarray:
    """``np.percentile(values, q, axis=0)`` (linear), (Q, C) float64, of pixel values (N, C).

    For uint8 values, from each channel's 256-bin histogram: the same numbers to the bit (the
    order statistics read off the cumulative counts, then NumPy's own interpolation), 20× faster
    than sorting 30 000 samples (0.3 against 5.4 ms per camera)."""
    v = np.asarray(values)
    if v.dtype != np.uint8 or v.ndim != 2 or v.shape[0] == 0:
        return np.percentile(v.astype(np.float64), q, axis=0)
    n = v.shape[0]
    pos = np.asarray(q, np.float64) / 100.0 * (n - 1)
    lo = np.floor(pos).astype(np.int64)
    hi = np.minimum(lo + 1, n - 1)
    t = pos - lo
    out = np.empty((len(pos), v.shape[1]))
    for c in range(v.shape[1]):
        cum = np.cumsum(np.bincount(v[:, c], minlength=256))
        a = np.searchsorted(cum, lo, side="right").astype(np.float64)  # the lo-th smallest value
        b = np.searchsorted(cum, hi, side="right").astype(np.float64)
        d = b - a
        out[:, c] = np.where(t >= 0.5, b - d * (1.0 - t), a + d * t)  # numpy's _lerp, both halves
    return out


def estimate_response(image1: np.ndarray, image2: np.ndarray, geometry, usable1: np.ndarray,
                      usable2: np.ndarray, clips=(None, None)) -> ColourResponse:
    """Camera 2's colour response relative to camera 1 from the common field of view.

    Parameters
    ----------
    image1, image2 : ndarray, shape (H1, W1, 3) and (H2, W2, 3), uint8
        BGR working-size images of camera 1 and camera 2.
    geometry : PairGeometry
        The pair's infinity remap (camera 1's grid → camera 2's pixels).
    usable1, usable2 : ndarray, bool
        Each camera's usable sky (the sun and saturated glare already removed).
    clips : (ClipLevel or None, ClipLevel or None)
        Each image's clip level where already found (:func:`~.clip.clip_level`; None: found here).

    Returns
    -------
    ColourResponse
        The identity (``pixels`` = 0) when fewer than 2000 common pixels exist.
    """
    # a regular subsample of camera 1's grid (every s-th pixel), looked up in camera 2 through
    # the infinity map: the quantiles need ~10⁵ values, not the whole image
    H, W = usable1.shape
    s = max(1, int(math.sqrt(H * W / _SAMPLES)))
    mx = np.ascontiguousarray(geometry.map_x[::s, ::s])
    my = np.ascontiguousarray(geometry.map_y[::s, ::s])
    kw = dict(interpolation=cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    u2 = cv2.remap(usable2.view(np.uint8), mx, my, **kw) > 0
    common = usable1[::s, ::s] & u2
    n = int(np.count_nonzero(common)) * s * s
    if n < _MIN_PIXELS:
        return ColourResponse()
    q1 = channel_percentiles(image1[::s, ::s][common], _QUANTILES)  # (Q, 3) B, G, R
    q2 = channel_percentiles(cv2.remap(image2, mx, my, **kw)[common], _QUANTILES)
    # quantiles at a camera's own clip level (235 on limited-range video, not only 255) say nothing
    # of its response: each channel's bright limit is its clip level (its own on a tinted clip) less
    # _CLIP_MARGIN
    c1, c2 = (c if c is not None else clip_level(im) for c, im in zip(clips, (image1, image2)))
    b1, b2 = (np.minimum(_BRIGHT, np.asarray(c.channel_levels(), np.float64) - _CLIP_MARGIN) for c in (c1, c2))
    ok = (q1 > _DARK) & (q1 < b1) & (q2 > _DARK) & (q2 < b2)
    if ok.sum(axis=0).min() < 3:
        return ColourResponse(pixels=n)
    y = np.log(np.maximum(q1, 0.5) / 255.0)  # (quantiles of black pixels are not used: ``ok``)
    x = np.log(np.maximum(q2, 0.5) / 255.0)
    spread = min(float(np.ptp(x[ok[:, c], c])) for c in range(3))
    rows, rhs = [], []
    for c in range(3):
        for xi, yi in zip(x[ok[:, c], c], y[ok[:, c], c]):
            r = np.zeros(4)
            r[0], r[1 + c] = xi, 1.0
            rows.append(r)
            rhs.append(yi)
    A, b = np.asarray(rows), np.asarray(rhs)
    if spread >= _MIN_LOG_RANGE:
        sol = np.linalg.lstsq(A, b, rcond=None)[0]
        gamma = float(np.clip(sol[0], *_GAMMA_LIMITS))
    else:
        gamma = 1.0
    beta = [float(np.mean(b[A[:, 1 + c] > 0] - gamma * A[A[:, 1 + c] > 0, 0])) for c in range(3)]
    k = [math.exp(bc / gamma) for bc in beta]  # B, G, R
    return ColourResponse(gain=k[1], gamma=gamma, wb_red=k[2] / k[1], wb_blue=k[0] / k[1], pixels=n, q1=q1, q2=q2)
