"""Fractal cloud texture: a function of world (east, north) only, evaluated fast on pixel grids.

A layer's texture is a sum of *octaves*. Octave k is a periodic band-limited noise tile
(:data:`TILE_PX` square, dominant wavelength :data:`TILE_WAVELENGTH_PX` tile pixels) laid on
the ground plane with wavelength ``λ_k = texture_scale_m / 2**k`` metres, a random offset and
one of four orientations (two independent tiles, each optionally transposed). Two sums of the
same octaves are kept:

- the *shape* field ``D = Σ a_k T_k`` with ``a_k ∝ 0.5**k`` (a fractal, unit variance): the
  cloud is where ``D > threshold``, the threshold being the quantile that makes ``coverage``
  of the layer's area cloud (exact: every octave is periodic over the base octave's period);
- the *detail* field ``G = Σ b_k T_k`` with ``b_k ∝ 0.85**k`` for k ≥ 1 (unit variance):
  internal brightness texture down to the finest octave, a few pixels at the zenith.

Because every camera samples the same world function, the texture is stereo-consistent by
construction. Two things make it fast and keep it from aliasing:

- *pyramid evaluation*: an octave is sampled (``cv2.remap`` of its tile, bilinear, wrapped) on
  the coarsest pixel-grid level that still has :data:`MIN_PX_PER_WAVELENGTH` samples per
  wavelength at the zenith (coarse octaves: :data:`HORIZON_PX_PER_WAVELENGTH`, so that they
  stay resolved towards the horizon where the footprint grows); each level's sum is upsampled (bilinear) into the next finer one.
  Each level's sample positions are exactly where that upsampling puts them, so the
  coarse octaves are a smooth interpolation of the exact world texture;
- *footprint fade*: an octave's weight goes from 1 to 0 as its wavelength shrinks from 3 to 1.5
  samples of the level's grid (towards the horizon a pixel covers more ground), like the
  integration of a real pixel.
"""
from __future__ import annotations

import functools
import math
import threading
from dataclasses import dataclass

import cv2
import numpy as np

__all__ = ["TILE_PX", "TILE_WAVELENGTH_PX", "MIN_PX_PER_WAVELENGTH", "Octave", "LayerTexture", "make_tiles", "sample_tile"]

TILE_PX = 512  # tile side [tile px]; a power of two
TILE_WAVELENGTH_PX = 8.0  # dominant wavelength of a tile [tile px]
MIN_PX_PER_WAVELENGTH = 6.0  # an octave is sampled on a level with ≥ this many px per wavelength at the zenith
HORIZON_PX_PER_WAVELENGTH = 24.0  # … and, down to level HORIZON_LEVEL, this many (resolved to ~75° zenith)
HORIZON_LEVEL = 2
FINEST_PX_PER_WAVELENGTH = 3.0  # the finest octave has about this many full-res px per wavelength at the zenith
MAX_OCTAVES = 12
SHAPE_PERSISTENCE = 0.5  # amplitude ratio of successive shape octaves
DETAIL_PERSISTENCE = 0.85  # amplitude ratio of successive detail octaves (k ≥ 1)
FADE_FULL_PX = 3.0  # octave weight 1 at ≥ this many grid px per wavelength …
FADE_ZERO_PX = 1.5  # … and 0 at ≤ this many


@functools.lru_cache(maxsize=16)  # a scene's layers are rebuilt for every renderer of it
def make_tiles(seed: int) -> np.ndarray:
    """Two independent periodic band-pass noise tiles (read-only: one array per seed is shared).

    Returns
    -------
    tiles : ndarray, shape (2, TILE_PX, TILE_PX), float32
        Zero mean, unit variance, dominant wavelength :data:`TILE_WAVELENGTH_PX` [tile px];
        periodic (they wrap seamlessly).
    """
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0x5C1E5]))
    n = TILE_PX
    white = rng.standard_normal((n, n)) + 1j * rng.standard_normal((n, n))
    f = np.hypot(*np.meshgrid(np.fft.fftfreq(n), np.fft.fftfreq(n), indexing="ij"))
    f0 = 1.0 / TILE_WAVELENGTH_PX
    with np.errstate(divide="ignore"):
        lg = np.log2(np.where(f > 0, f / f0, 1e-9))
    band = np.exp(-0.5 * (lg / 0.55) ** 2)  # log-Gaussian band, ~1 octave wide
    band[0, 0] = 0.0
    field = np.fft.ifft2(np.fft.fft2(white) * band)
    tiles = np.stack([field.real, field.imag]).astype(np.float64)
    tiles -= tiles.mean(axis=(1, 2), keepdims=True)
    tiles /= tiles.std(axis=(1, 2), keepdims=True)
    tiles = tiles.astype(np.float32)
    tiles.setflags(write=False)
    return tiles


@functools.lru_cache(maxsize=16)
def _padded(seed: int) -> np.ndarray:
    """:func:`make_tiles`, wrap-padded by one sample so that bilinear reads at u in [511, 512)
    stay inside (read-only)."""
    out = np.ascontiguousarray(np.pad(make_tiles(seed), ((0, 0), (0, 1), (0, 1)), mode="wrap"))
    out.setflags(write=False)
    return out


_QUANTILES: dict = {}  # (seed, texture_scale_m, octaves) → (probabilities, quantiles)
_QUANTILES_LOCK = threading.Lock()


@dataclass(frozen=True)
class Octave:
    """One octave of a layer texture."""

    wavelength_m: float  # λ_k [m]
    scale: float  # tile px per metre (TILE_WAVELENGTH_PX / λ_k)
    offset_px: tuple[float, float]  # tile offset (u, v) [tile px]
    tile: int  # which of the two tiles
    transpose: bool  # swap east/north on the tile
    shape_amp: float  # a_k
    detail_amp: float  # b_k
    level: int  # pyramid level it is sampled on


class LayerTexture:
    """The texture of one cloud layer (a world function), with its octave plan.

    Parameters
    ----------
    texture_scale_m : float
        Wavelength of the coarsest octave [m].
    seed : int
    finest_m : float
        Smallest wavelength worth rendering [m] (≈ 3 pixel footprints at the zenith).
    level_px_m : float
        Zenith footprint of one full-resolution pixel on this layer [m]; sets each octave's
        pyramid level.
    max_level : int
        Coarsest pyramid level available.
    """

    def __init__(self, texture_scale_m: float, seed: int, finest_m: float, level_px_m: float, max_level: int):
        self.texture_scale_m = float(texture_scale_m)
        self.seed = int(seed)
        self.tiles = make_tiles(seed)
        self.tiles_padded = _padded(seed)
        n_oct = 1
        while n_oct < MAX_OCTAVES and texture_scale_m / 2 ** n_oct >= finest_m:
            n_oct += 1
        rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0x0C7A]))
        a = np.array([SHAPE_PERSISTENCE ** k for k in range(n_oct)])
        a /= math.sqrt((a ** 2).sum())
        b = np.array([0.0] + [DETAIL_PERSISTENCE ** k for k in range(n_oct - 1)]) if n_oct > 1 else np.array([1.0])
        b /= math.sqrt((b ** 2).sum())
        octs = []
        for k in range(n_oct):
            lam = texture_scale_m / 2 ** k
            px_per_wl = lam / level_px_m
            coarsest = math.floor(math.log2(max(px_per_wl / MIN_PX_PER_WAVELENGTH, 1e-9)))
            horizon = math.floor(math.log2(max(px_per_wl / HORIZON_PX_PER_WAVELENGTH, 1e-9)))
            level = int(min(max_level, max(0, horizon, min(HORIZON_LEVEL, coarsest))))
            octs.append(Octave(
                wavelength_m=lam,
                scale=TILE_WAVELENGTH_PX / lam,
                offset_px=(float(rng.uniform(0, TILE_PX)), float(rng.uniform(0, TILE_PX))),
                tile=k % 2,
                transpose=bool((k // 2) % 2),
                shape_amp=float(a[k]),
                detail_amp=float(b[k]),
                level=level,
            ))
        self.octaves: tuple[Octave, ...] = tuple(octs)

    # --- exact evaluation at points (reference; threshold statistics) -----------------------
    def evaluate(self, east_m, north_m) -> tuple[np.ndarray, np.ndarray]:
        """Unfaded shape and detail fields at world points.

        Parameters
        ----------
        east_m, north_m : array_like, shape (N,), float
            Texture-frame coordinates [m] (world position minus the layer offset).

        Returns
        -------
        shape, detail : ndarray, shape (N,), float32
        """
        e = np.asarray(east_m, dtype=np.float64).ravel()
        n = np.asarray(north_m, dtype=np.float64).ravel()
        size = e.size
        cols = 256  # cv2.remap wants maps under 32767 on a side
        pad = (-size) % cols
        e = np.pad(e, (0, pad))
        n = np.pad(n, (0, pad))
        shape = np.zeros(e.shape, np.float32)
        detail = np.zeros(e.shape, np.float32)
        for o in self.octaves:
            u = np.mod(e * o.scale + o.offset_px[0], TILE_PX).astype(np.float32).reshape(-1, cols)
            v = np.mod(n * o.scale + o.offset_px[1], TILE_PX).astype(np.float32).reshape(-1, cols)
            if o.transpose:
                u, v = v, u
            t = sample_tile(self.tiles_padded[o.tile], u, v).ravel()
            shape += o.shape_amp * t
            detail += o.detail_amp * t
        return shape[:size], detail[:size]

    def quantiles(self) -> tuple[np.ndarray, np.ndarray]:
        """(probabilities, shape-field quantiles) over one full period (cached: the shape field
        depends only on the seed, the coarsest wavelength and the number of octaves)."""
        key = (self.seed, self.texture_scale_m, len(self.octaves))
        found = _QUANTILES.get(key)
        if found is None:
            period = TILE_PX / self.octaves[0].scale  # every octave's period divides this
            rng = np.random.default_rng(np.random.SeedSequence([self.seed, 0x9A47]))
            pts = rng.uniform(0.0, period, size=(2, 1 << 17))
            shape, _ = self.evaluate(pts[0], pts[1])
            p = np.linspace(0.0, 1.0, 2001)
            found = (p, np.quantile(shape.astype(np.float64), p))
            with _QUANTILES_LOCK:
                if len(_QUANTILES) >= 256:
                    _QUANTILES.pop(next(iter(_QUANTILES)))
                _QUANTILES[key] = found
        return found

    def threshold(self, coverage: float) -> float:
        """Shape-field value above which ``coverage`` of the layer's area is cloud."""
        if coverage <= 0.0:
            return math.inf
        if coverage >= 1.0:
            return -math.inf
        p, q = self.quantiles()
        return float(np.interp(1.0 - coverage, p, q))

    def shape_max(self) -> float:
        """99.9 % quantile of the shape field (the thickest cloud)."""
        p, q = self.quantiles()
        return float(np.interp(0.999, p, q))

    def shape_min(self) -> float:
        p, q = self.quantiles()
        return float(np.interp(0.001, p, q))


def sample_tile(tile_padded: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Bilinear, wrapped read of a padded tile at texture coordinates (u, v) [tile px].

    Coordinates go to OpenCV's fixed-point map form (1/32 px), their integer parts are
    wrapped with a bit mask (``TILE_PX`` is a power of two) and the read stays inside the
    padded tile, which keeps ``cv2.remap`` on its fast path. Where |u| or |v| exceed 32767
    the result is meaningless (callers give such pixels zero weight).

    Parameters
    ----------
    tile_padded : ndarray, shape (TILE_PX + 1, TILE_PX + 1), float32
    u, v : ndarray, shape (h, w), float32

    Returns
    -------
    ndarray, shape (h, w), float32
    """
    m1, m2 = cv2.convertMaps(u, v, cv2.CV_16SC2)
    np.bitwise_and(m1, TILE_PX - 1, out=m1)
    return cv2.remap(tile_padded, m1, m2, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


def fade_weight(inv_footprint: np.ndarray, wavelength_over_dh: float, out: np.ndarray) -> np.ndarray:
    """Octave weight from the grid's footprint: clip((q − 1.5) / 1.5, 0, 1), q = px per wavelength.

    ``inv_footprint`` is 1 / (footprint per metre of height) of each grid pixel, so that
    ``q = inv_footprint · λ / Δh``.
    """
    np.multiply(inv_footprint, wavelength_over_dh / (FADE_FULL_PX - FADE_ZERO_PX), out=out)
    out -= FADE_ZERO_PX / (FADE_FULL_PX - FADE_ZERO_PX)
    np.clip(out, 0.0, 1.0, out=out)
    return out
