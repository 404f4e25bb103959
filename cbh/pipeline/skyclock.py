"""Camera 2's clock offset from the sky itself: dense flow on sky maps, no stereo match that must
already triangulate.

**Why sky maps.** Both cameras' images are resampled onto one north-up grid of *plane offsets*
``a = (r_e, r_n) / r_u`` (the horizontal offset per metre of height of a ray; the gnomonic
projection of the sky onto a horizontal plane). On that grid a flat cloud layer at height h
moving at v over the ground is a pure translation, everywhere in the map:

- between two frames of one camera ``dt`` apart, by ``w·dt`` with ``w = v / (h − z)``;
- between camera 1 and camera 2 at one instant, by the parallax ``−q·B'`` (q = 1/h above camera 1,
  B' the horizontal baseline corrected for camera 2's height, :mod:`.motion`);
- and camera 2 capturing δ late adds ``w·δ``.

So the flow f from camera 1's map to camera 2's, at each pixel a, is ``f = −q·B' + w·δ``, and camera
1's own backward flow to its previous frame is ``−w·dt``. The component of f *across* the baseline
has no parallax in it: ``n·f = δ·(n·w)``, n ⟂ B. Each pixel with motion across the baseline gives δ;
nothing has to triangulate first (a 30 s offset moves a cirrus deck 4–6° while its parallax over 241 m
is 1.7°: the stereo matches of the raw pair are then mostly wrong, and a matcher that keeps only those
that triangulate keeps none). Static things (masts, the other camera, overlay text, the sun's flare)
have w = 0 and carry no weight. Layers moving in different directions each give δ with their own w.

**Large offsets, long cadences.** f can be tens of map pixels (a 120 s offset, a fast layer):
before the dense flow (DIS, :func:`cv2.DISOpticalFlow`), camera 2's map is shifted by the dominant
translation found by phase correlation, and the flow measures only what is left. A camera's own
motion between its frames can be as large (a deck at 20 m/s moves ≈ 45 map px in 2 min), and there
phase correlation finds what does not move (the sun's flare, masts): each camera's motions are
found in the difference of its two frames, where everything static cancels
(:func:`_motion_shifts`), one candidate per layer moving apart, and each pixel keeps the flow that
passes its forward-backward check best.

**Estimate.** Per tile of the map (one value per tile: neighbouring pixels of a flow are not
independent), δ = median(n·f) / median(n·w) over its matched pixels, weighted by the tile's
(n·w)² (inverse variance) and kept where its n·w moves ``min_tile_motion_px`` in the pairs'
interval; δ is the median of the tiles, with a standard error from their spread. The tile's
median rate, not each pixel's: a pixel's n·w is as noisy as its flow, and chosen and weighed by
its own noisy value the pixels whose noise added to a slow drift across the baseline won, so |n·w|
read large and δ short (randomized 16782 over the real station's lenses: a 2201 m deck drifting
0.42 map px across a 37 m baseline per 10 s frame, every chosen pixel ≥ 0.5: +42.4 s "± 1.35 s"
for +62.5 s, and its deck valid at 674 m; tile medians: +61.4 s ± 2.0 s, unknown at that error).
NaN (unknown, never a guess) when too few tiles see motion across the baseline or the error is
above ``max_error_s``. With δ, each pixel's height follows from the along-baseline component, and
the (height, rate) pairs give camera 2's motion profile, the input of the compensation
(:func:`~cbh.pipeline.motion.compensate_camera2`).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import lru_cache

import cv2
import numpy as np

from cbh.pipeline.threads import pmap

__all__ = ["SkyGrid", "SkyClock", "sky_grid", "sky_clock"]


@dataclass(frozen=True)
class SkyGrid:
    """A north-up grid of plane offsets (x east, y north up) and each camera's remap onto it.

    res : float
        Plane-offset step per map pixel [m/m].
    a_max : float
        The grid covers |a_e|, |a_n| ≤ a_max (zenith ≤ atan(a_max) on the axes).
    maps : tuple of (mapx, mapy) float32 per camera (working-size pixels; −1 outside its view)
    """

    res: float
    a_max: float
    maps: tuple

    @property
    def size(self) -> int:
        return int(self.maps[0][0].shape[0])

    def offsets(self) -> tuple[np.ndarray, np.ndarray]:
        """(a_e, a_n) of each map pixel, each (S, S) float64."""
        n = self.size
        ax = (np.arange(n) - (n - 1) / 2.0) * self.res
        return np.meshgrid(ax, -ax)

    def sample(self, k: int, image: np.ndarray, interpolation=cv2.INTER_LINEAR) -> np.ndarray:
        mx, my = self.maps[k]
        return cv2.remap(image, mx, my, interpolation, borderMode=cv2.BORDER_CONSTANT, borderValue=0)


def sky_grid(cams, max_zenith_deg: float = 60.0, res: float | None = None) -> SkyGrid:
    """The grid for working-size cameras ``cams`` (their lens and ENU orientation).

    The step defaults to the lens's own angular pixel size at the zenith, doubled: fine enough
    that a flow of 0.1 map px is a few hundredths of a degree, coarse enough that the map holds
    a few hundred pixels (the flow's cost)."""
    a_max = math.tan(math.radians(max_zenith_deg))
    if res is None:
        m = cams[0].model
        px_per_rad = float(np.atleast_1d(m.r_from_theta(np.array([0.05])))[0]) / 0.05
        res = 2.0 / px_per_rad
    n = int(2 * math.ceil(a_max / res)) + 1
    ax = (np.arange(n) - (n - 1) / 2.0) * res
    ae, an = np.meshgrid(ax, -ax)
    rays = np.stack([ae, an, np.ones_like(ae)], axis=-1).reshape(-1, 3)
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    maps = []
    for cam in cams:
        rc = rays @ np.asarray(cam.R_world_from_cam, np.float64)  # world → camera frame
        px = cam.model.ray_to_pixel(rc).reshape(n, n, 2)
        inside = cam.model.contains(px.reshape(-1, 2)).reshape(n, n) & (rc[:, 2].reshape(n, n) > 0.02)
        px = np.where(inside[..., None] & np.isfinite(px), px, -1.0)
        maps.append((np.ascontiguousarray(px[..., 0], np.float32), np.ascontiguousarray(px[..., 1], np.float32)))
    return SkyGrid(res=float(res), a_max=float(a_max), maps=tuple(maps))


@dataclass(frozen=True)
class SkyClock:
    """One pair's sky-map estimate (see the module docstring).

    offset_s : float
        Camera 2's clock offset (positive: it captures late) [s]; NaN = not observable here.
    error_s : float
        Its standard error (tile spread / √tiles, with the frames' timing share |ratio − 1|·|δ|,
        :func:`interval_ratio`) [s].
    tiles : int
        Tiles that saw motion across the baseline.
    heights_m : ndarray (N,)
        Sampled pixels' heights above the ENU origin for that offset [m] (NaN: none).
    rates2 : ndarray (N, 2)
        Their plane-offset rates as camera 2 sees them [1/s].
    a1, flow, rate : ndarray (M, 2)
        Correspondences on the sky maps: camera 1's plane offset a1 [m/m], the flow to camera 2 as
        captured f [m/m] and the pixel's own motion w [1/s], so that camera 2 carried to camera 1's
        capture time sees it at ``a1 + f − w·δ`` (:meth:`matched`): the pair's matches once its
        offset is known (only flow outliers, a miss across the baseline above ``max_miss_deg``, are
        left out: the geometry check and the triangulation judge the rest).
    """

    offset_s: float
    error_s: float
    tiles: int
    heights_m: np.ndarray
    rates2: np.ndarray
    a1: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    flow: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    rate: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))

    carry_noise_rad: float = 0.0  # the carry's noise along the baseline near the zenith [rad] (:func:`_carry_noise`)
    rate_map: np.ndarray | None = None  # (S, S, 2) each lattice point's rate [1/s]; NaN where none: only the
    # points that could be usable are refined (their matches' a1 among them), the rest are NaN
    res: float = math.nan  # the map's step [m/m]
    # the maps matched (at least the tiles an estimate needs) and under ``min_share`` of what matched moved
    # by ``min_motion_px`` in the pairs' interval: the offset is unobservable, and harmless (a calm sky)
    still: bool = False
    # the maps matched and the sky drifted, but under ``min_share`` of it across the baseline: the offset is
    # unobservable, and cannot take matches off their epipolar curves (a wind along the baseline)
    along: bool = False
    # camera 2's frame interval over camera 1's, from their own skies' motions (:func:`interval_ratio`):
    # 1 for frames captured on their stamps; NaN where not measured
    interval_ratio: float = math.nan

    def rate_at(self, a: np.ndarray) -> np.ndarray:
        """The measured rate (N, 2) [1/s] at plane offsets a (N, 2) (the nearest map pixel's): meant
        for the matches' own offsets ``a1``; NaN at a lattice point that was not refined."""
        n = self.rate_map.shape[0]
        c = np.clip(np.round(a[:, 0] / self.res + (n - 1) / 2.0).astype(np.int64), 0, n - 1)
        r = np.clip(np.round(-a[:, 1] / self.res + (n - 1) / 2.0).astype(np.int64), 0, n - 1)
        return self.rate_map[r, c]

    def matched(self, offset_s: float) -> np.ndarray:
        """Camera 2's plane offsets (M, 2) of the matches at camera 1's capture time, for the offset
        ``offset_s`` [s] (the running estimate rather than this pair's own)."""
        return self.a1 + self.flow - self.rate * offset_s

    @classmethod
    def unknown(cls, tiles: int = 0, still: bool = False, along: bool = False) -> "SkyClock":
        return cls(math.nan, math.nan, tiles, np.zeros(0), np.zeros((0, 2)), still=still, along=along)


def _texture(img: np.ndarray, valid: np.ndarray, weight: np.ndarray | None = None) -> np.ndarray:
    """Grey sky map → uint8 with its large-scale brightness removed (clouds' texture, not the sky's
    gradient or vignetting), invalid pixels at the mean. ``weight``: :func:`_texture_weight` of
    ``valid``, when already made (a camera's two frames share their usable mask)."""
    f = img.astype(np.float32)
    v = valid.astype(np.float32)
    k = (0, 0)
    s = _texture_sigma(img.shape[0])
    mean = cv2.GaussianBlur(f * v, k, s) / (_texture_weight(valid) if weight is None else weight)
    hp = np.where(valid, f - mean, 0.0)
    sd = float(np.std(hp[valid])) if valid.any() else 1.0
    return np.clip(128.0 + hp * (40.0 / max(sd, 1e-3)), 0, 255).astype(np.uint8)


def _texture_sigma(n: int) -> float:
    """The σ of :func:`_texture`'s large-scale brightness [map px] for an n px map."""
    return max(3.0, n / 40.0)


def _texture_weight(valid: np.ndarray) -> np.ndarray:
    """:func:`_texture`'s normaliser: the valid mask blurred like the map, at least 1e-3."""
    s = _texture_sigma(valid.shape[0])
    return np.maximum(cv2.GaussianBlur(valid.astype(np.float32), (0, 0), s), 1e-3)


def _dominant_shift(s1: np.ndarray, s2: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Translation (dx, dy) [map px] taking s1's content to s2's (phase correlation)."""
    f1 = np.where(valid, s1.astype(np.float32) - 128.0, 0.0).astype(np.float32)
    f2 = np.where(valid, s2.astype(np.float32) - 128.0, 0.0).astype(np.float32)
    win = cv2.createHanningWindow(f1.shape[::-1], cv2.CV_32F)
    (dx, dy), _ = cv2.phaseCorrelate(f1, f2, win)
    return np.array([dx, dy], np.float64)


def _half_spectra(a: np.ndarray, b: np.ndarray, valid: np.ndarray):
    """Two maps' spectra (``rfft2``) at half the map's size (DIS takes the last pixels), windowed,
    masked to ``valid``, at a size the FFT is fast at; with that size."""
    win = np.where(valid, cv2.createHanningWindow(a.shape[::-1], cv2.CV_32F), np.float32(0.0))
    half = (a.shape[1] // 2, a.shape[0] // 2)
    fa, fb = (cv2.resize((f.astype(np.float32) - np.float32(128.0)) * win, half, interpolation=cv2.INTER_AREA)
              for f in (a, b))
    shape = tuple(cv2.getOptimalDFTSize(n) for n in fa.shape)
    return np.fft.rfft2(fa, s=shape), np.fft.rfft2(fb, s=shape), shape


def _peaks(surface: np.ndarray, min_z: float, r0_px: float, symmetric: bool, count: int):
    """The highest peaks of a correlation ``surface`` (half-size px, origin at [0, 0]) beyond
    ``r0_px`` of the origin, at most ``count``, each (dy, dx, z) with z its height in robust
    deviations of the surface; the first needs ``min_z``, the others 1.5 ``min_z``. A peak's
    neighbourhood is spent once taken (and its mirror image's, for a ``symmetric`` surface)."""
    n0, n1 = surface.shape
    far = _beyond(n0, n1, float(r0_px))
    rest = surface[far][::7]  # (a sample is enough for the noise's level)
    med = float(np.median(rest))
    spread = 1.4826 * float(np.median(np.abs(rest - med)))
    search, out = np.where(far, surface, -np.inf), []
    rad = 2.0 * max(r0_px, 1.0) + 1.0
    k = int(math.floor(rad))
    dk = np.arange(-k, k + 1)
    disk = np.hypot(dk[:, None], dk[None, :]) <= rad
    while len(out) < count and spread > 0:
        iy, ix = np.unravel_index(int(np.argmax(search)), search.shape)
        z = (float(search[iy, ix]) - med) / spread
        if z < (1.5 if out else 1.0) * min_z:
            break
        dy, dx = (iy if iy <= n0 // 2 else iy - n0), (ix if ix <= n1 // 2 else ix - n1)
        for sy, sx in ((dy, dx), (-dy, -dx))[:2 if symmetric else 1]:
            rows, cols = np.ix_((sy + dk) % n0, (sx + dk) % n1)
            search[rows, cols] = np.where(disk, -np.inf, search[rows, cols])
        out.append((dy, dx, z))
    return out


@lru_cache(maxsize=8)
def _beyond(n0: int, n1: int, r0_px: float) -> np.ndarray:
    """Where an (n0, n1) surface with its origin at [0, 0] (wrapping around) is beyond ``r0_px``
    of it (read-only)."""
    ar0, ar1 = np.arange(n0), np.arange(n1)
    far = np.hypot(np.minimum(ar0, n0 - ar0)[:, None], np.minimum(ar1, n1 - ar1)[None, :]) > r0_px
    far.setflags(write=False)
    return far


def _add_candidate(out: list, v: np.ndarray, reach_px: float, snap: bool = True) -> None:
    """Append motion ``v`` [map px] to the candidates ``out`` unless one is within ``reach_px`` (what
    DIS follows unaided); with ``snap``, one within it of no motion is the candidate 0."""
    if snap and np.hypot(*v) <= reach_px:
        v = np.zeros(2)
    if not any(np.hypot(*(v - w)) <= reach_px for w in out):
        out.append(v)


def _motion_shifts(now: np.ndarray, prev: np.ndarray, valid: np.ndarray, most: int = 2, min_z: float = 10.0,
                   r0_px: float = 2.0, reach_px: float = 16.0) -> list[np.ndarray]:
    """The motions (dx, dy) [map px] of one camera's sky from ``now`` to ``prev`` (content at x in
    ``now`` is at x + d in ``prev``) that stand out, at most ``most`` moving ones, the strongest
    first; none where nothing moved.

    Phase correlation of the two frames finds the static things (the sun's flare, masts, the lens's
    own pattern) as well as the clouds, and on the real Fehmarn maps 2 min apart it picked "no
    motion" under a deck that had moved 45 map px. In the difference of the frames everything
    static cancels: for a pattern m moved by v, D = m(x − v) − m(x), whose autocorrelation is
    2·C(d) − C(d − v) − C(d + v), a positive peak at 0 and negative ones at ±v (whitened by the
    frames' mean power spectrum, so the peaks are sharp); layers moving apart give a pair each.
    The deepest ones beyond ``r0_px`` (at half size) give ±v when they stand ``min_z`` robust
    deviations below the rest of the autocorrelation (noise alone: 6–7 on a 573 px map; the real
    deck: 16–22), a further layer 1.5 ``min_z`` (the ridges of one deck's trough on the real maps
    reached 8–10.5; the preset's two decks moving apart give 22–27 each); the sign is where the
    frames' own cross-correlation is larger (their static part correlates alike at ±v). A motion
    within ``reach_px`` (map px, what DIS follows unaided) of no motion is the candidate 0, one
    within it of another candidate adds nothing (:func:`_add_candidate`)."""
    ta, tb, shape = _half_spectra(now, prev, valid)
    power = 0.5 * (ta.real ** 2 + ta.imag ** 2 + tb.real ** 2 + tb.imag ** 2)
    power += 1e-3 * float(power.mean()) + 1e-30
    dd = tb - ta
    ac = np.fft.irfft2((dd.real ** 2 + dd.imag ** 2) / power, s=shape)
    cc, out = None, []
    for dy, dx, _ in _peaks(-ac, min_z, r0_px, True, most + 3):  # (a few more: one within reach adds nothing)
        if sum(bool(w.any()) for w in out) == most:
            break
        if cc is None:
            cc = np.fft.irfft2(tb * np.conj(ta) / power, s=shape)
        if cc[-dy % shape[0], -dx % shape[1]] > cc[dy % shape[0], dx % shape[1]]:
            dx, dy = -dx, -dy
        _add_candidate(out, 2.0 * np.array([dx, dy], np.float64), reach_px)
    return out


def _cross_shifts(t1: np.ndarray, t2: np.ndarray, valid: np.ndarray, most: int = 2, min_z: float = 10.0,
                  reach_px: float = 16.0) -> list[np.ndarray]:
    """The translations (dx, dy) [map px] taking camera 1's map to camera 2's: the dominant one by
    phase correlation (:func:`_dominant_shift`, to a fraction of a pixel), then each further layer
    whose own phase-correlation peak stands 1.5 ``min_z`` robust deviations out, beyond
    ``reach_px`` of every other candidate. Layers far apart in height, or moving apart, are
    translated differently (each by its parallax and its motion over the clock offset): on the
    real station's geometry, 1500 m and 8000 m decks 89 s apart were 48 map px apart, beyond
    DIS's reach from one shift, and the 1500 m deck was never found; their peaks stood 50 and 82
    deviations out, the real deck's 22–78 with nothing else above 10.5. Where the phase
    correlation locked onto what is still (the real hour re-paired one frame later, 09:12: the
    deck 14 map px off), the strongest peak is taken instead."""
    d0 = _dominant_shift(t1, t2, valid)
    ta, tb, shape = _half_spectra(t1, t2, valid)
    x = tb * np.conj(ta)
    x /= np.abs(x) + 1e-9 * float(np.abs(x).max()) + 1e-30
    peaks = _peaks(np.fft.irfft2(x, s=shape), min_z, -1.0, False, most + 3)
    vs = [2.0 * np.array([dx, dy], np.float64) for dy, dx, _ in peaks]
    out = [d0 if not vs or np.hypot(*(d0 - vs[0])) <= 4.0 else vs[0]]
    for v in vs[1:]:
        if len(out) == most:
            break
        _add_candidate(out, v, reach_px, snap=False)
    return out


def _shifted(img: np.ndarray, d: np.ndarray) -> np.ndarray:
    """``img`` moved by −d [map px] (content at x + d comes to x), mid-grey where it has none."""
    n = img.shape[0]
    return cv2.warpAffine(img, np.float32([[1, 0, -d[0]], [0, 1, -d[1]]]), (n, n), flags=cv2.INTER_LINEAR,
                          borderMode=cv2.BORDER_CONSTANT, borderValue=128)


def _flow(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
    return dis.calc(a, b, None)


def _sample(field: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    return cv2.remap(field, x.astype(np.float32), y.astype(np.float32), cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_CONSTANT, borderValue=np.nan)


def sky_clock(grid: SkyGrid, now: tuple, prev: tuple, usable: tuple, baseline_m: np.ndarray, dz_m: float,
              dt_s: float, *, tile_px: int = 24, min_tiles: int = 6, min_motion_px: float = 0.5,
              fb_max_px: float = 0.5, max_error_s: float = 2.0, height_range_m=(50.0, 20000.0),
              min_tile_motion_px: float = 0.25,
              max_miss_deg: float = 2.0, lattice: int = 2, min_share: float = 0.25,
              known_offset_s: float = math.nan, max_offset_s: float = math.inf, min_in_range: float = 0.1) -> SkyClock:
    """Camera 2's clock offset from one pair and the pair before (see the module docstring).

    With ``known_offset_s`` (the running offset of the pairs before), a pair whose own estimate
    fails (too few tiles moving across the baseline, or a spread over ``max_error_s``) still gives
    its maps' matches carried by that offset (``offset_s`` and ``error_s`` NaN; so does an estimate
    beyond ``max_offset_s``, which is not believed): on the real
    Fehmarn hour re-paired 3 frames later (149 s) one pair in three lost its own estimate, and the
    raw-image compensation, whose error grows with the carry, then reported layers at 1.5–2.3 km
    under a deck at 8 km.

    Parameters
    ----------
    grid : SkyGrid
    now, prev : (gray1, gray2)
        Both cameras' working-size grey frames, now and at the previous pair (``dt_s`` earlier on
        camera 1's clock; each camera's own frames are ``dt_s`` apart on its own clock).
    usable : (mask1, mask2)
        Working-size usable-sky masks (obstacles, sun, outside the circle: False).
    baseline_m : ndarray (2,)
        Camera 2 minus camera 1, east and north [m].
    dz_m : float
        Camera 2's height above camera 1 [m].
    min_tile_motion_px : float
        A tile's median motion across the baseline per interval for it to give δ [map px].
    """
    if not (dt_s > 0):
        return SkyClock.unknown()
    u = [grid.sample(k, usable[k].astype(np.uint8), cv2.INTER_NEAREST) > 0 for k in (0, 1)]
    wts = list(pmap(_texture_weight, u))  # both frames of a camera are read through its usable mask now
    maps = list(pmap(lambda ik: _texture(grid.sample(ik[1], ik[0][ik[1]]), u[ik[1]], wts[ik[1]]),
                     [(img, k) for img in (now, prev) for k in (0, 1)]))
    f12, g1, g2_at, ok, disagree = _lattice_flows(*maps, u, fb_max_px, lattice)
    ae, an = (a[::lattice, ::lattice] for a in grid.offsets())
    tile_px = max(2, tile_px // lattice)
    # map px → plane offsets (x east, y south: the map's rows run north to south)
    to_a = np.array([grid.res, -grid.res])
    f = f12 * to_a  # a2 − a1
    w = -0.5 * (g1 + g2_at) * to_a / dt_s  # rate [1/s]
    b = np.asarray(baseline_m, np.float64)
    # the parallax lies along B' = B − Δz·a2, not along B: across B' is what has none in it (with
    # camera 2 9 m below camera 1 (Fehmarn), across B held ±1 % of a 900 m deck's parallax, and its
    # offset read 9 % long in simulation; the cross product is the stereo tracks' own,
    # :func:`~.motion.offset_per_match`)
    bp = b[None, None, :] - dz_m * (np.stack([ae, an], -1) + f)
    nrm = np.stack([-bp[..., 1], bp[..., 0]], -1) / np.linalg.norm(bp, axis=-1, keepdims=True)
    nw = (w * nrm).sum(-1)
    nf = (f * nrm).sum(-1)
    moving = ok & (np.abs(nw) * dt_s >= min_motion_px * grid.res)
    # observable only when much of the moving sky moves across the baseline: a wind along it leaves
    # n·w at the flow's noise, a few pixels pass by chance, and the ratio of two noises has a median
    # near 0 with a small spread (−0.7 s "± 0.1" for a wind along a 50 m baseline: a confident number)
    drifting = ok & (np.hypot(w[..., 0], w[..., 1]) * dt_s >= min_motion_px * grid.res)
    matched = ok.sum() >= min_tiles * tile_px ** 2
    still = bool(matched and drifting.sum() < min_share * ok.sum())
    along = bool(matched and not still and moving.sum() < min_share * drifting.sum())
    est, err, tiles = math.nan, math.nan, 0
    if moving.sum() >= min_share * max(int(drifting.sum()), 1):
        est, err, tiles, nw_tiles = _tile_ratio(nf, nw, ok, tile_px, min_tiles, min_tile_motion_px * grid.res / dt_s)
        err = math.hypot(err, _floor_error_s(est, nw_tiles, grid.res, dt_s))  # (shared by the tiles)
    def in_range(offset_s: float) -> tuple[np.ndarray, np.ndarray]:
        h = _heights(w, f, bp, offset_s)
        return h, ok & np.isfinite(h) & (h >= height_range_m[0]) & (h <= height_range_m[1])

    own = math.isfinite(est) and err <= max_error_s and abs(est) <= max_offset_s  # (beyond: not believed)
    # a first offset that leaves almost none of the matched sky at a height in range is not the offset:
    # the maps matched something else (a randomized deck carried 2 km by a 112 s offset, beyond the
    # map's half: −14.0 s "± 0.9" with none of its 263 matches in range). The real hour's own estimates
    # keep 16–99 % (the low ones are the wavering ones, which the running offset then judges)
    if not math.isfinite(known_offset_s):
        own = own and int(in_range(est)[1].sum()) >= min_in_range * int(ok.sum())
    if not own:
        if not (math.isfinite(known_offset_s) and ok.any()):
            return SkyClock.unknown(tiles, still, along)
        est = float(known_offset_s)  # carried by the running offset; this pair's own is unknown
    h, sel = in_range(est)
    ratio = interval_ratio(g1, g2_at, h, dz_m, ok)  # (δ is read over the mean rate's timing error: reported)
    err = math.hypot(err, abs(ratio - 1.0) * abs(est)) if own and math.isfinite(ratio) else err
    carry = _carry_noise(0.5 * 1.4826 * float(np.median(disagree[ok])) * grid.res / dt_s, est, w[ok], nw[ok],
                         b / max(float(np.linalg.norm(b)), 1e-9), ratio)
    # the matches: the residual across B' once δ is out is the rays' miss (as an angle: a
    # plane-offset step at a is cos²θ = 1 / (1 + |a|²) of a radian)
    miss = np.abs(nf - est * nw) / (1.0 + ae ** 2 + an ** 2)
    good = ok & np.isfinite(miss) & (miss <= math.radians(max_miss_deg))
    a1m = np.stack([ae[good], an[good]], -1)
    step = max(1, int(math.sqrt(max(int(sel.sum()), 1) / 3000.0)))
    sub = np.zeros_like(sel)
    sub[::step, ::step] = True
    sel &= sub
    hh = h[sel]
    w2 = w[sel] * ((hh / (hh - dz_m)))[:, None]  # camera 2's rate: v / (h − z2), heights above camera 1
    return SkyClock(offset_s=est if own else math.nan, error_s=err if own else math.nan, tiles=tiles, heights_m=hh,
                    rates2=w2, a1=a1m, flow=f[good],
                    rate=w[good], carry_noise_rad=carry, rate_map=w, res=grid.res * lattice, still=still,
                    along=along, interval_ratio=ratio)


def _rms(v: np.ndarray) -> float:
    """Root mean square of ``v`` (0 when empty): the size of n·w that the estimate's (n·w)² weights pool."""
    return float(np.sqrt(np.mean(v ** 2))) if len(v) else 0.0


def _floor_error_s(offset_s: float, nw: np.ndarray, res: float, dt_s: float) -> float:
    """The error [s] that the flows' floor (:data:`FLOW_FLOOR_PX`, a bias every tile shares) puts on
    an offset δ = n·f / n·w read from motion across the baseline ``nw`` [1/s] (the tiles' rates),
    ``res`` [plane units per map px], rates from flows ``dt_s`` apart.

    Both flows have it: the flow between the cameras, n·f, by FLOW_FLOOR_PX·res / |n·w| seconds;
    the rate, n·w, read from each camera's flow over ``dt_s``, by a relative error FLOW_FLOOR_PX·res
    / (|n·w|·dt), which δ takes |δ| times. The second part is |δ| / dt times the first: at 10 s
    frames and a 46 s offset, 4.6 times. Measured on a randomized 4174 m deck (8.5 m/s, 2.7 m/s of it
    across the baseline) without noise or JPEG: offsets of +20, +46, +90 and −46 s read 2.6–3.9 %
    short with frames every 10 s, 0.5 % every 30 s, and exact every 60 s: |n·w| reads large by a
    share of a map pixel that the interval divides (the tiles weigh and choose their pixels by
    their own noisy n·w: docs/accuracy.md, Limits). Two randomized clocks that had read confidently
    wrong: −102.5 s every 10 s over the real station's lenses read −90.3 s within its tiles' error
    (now unknown), and the 4174 m deck, camera 2 46.0 s late, +42.6 s "± 0.51 s" with its deck 14 %
    low (now ± 1.0 s; still valid: its rate's bias, 0.06 px with the camera's noise and JPEG, is
    four times the floor)."""
    nw_rms = _rms(nw)
    if not (nw_rms > 0 and dt_s > 0):
        return math.inf
    return FLOW_FLOOR_PX * res / nw_rms * math.hypot(1.0, offset_s / dt_s)


def interval_ratio(g1: np.ndarray, g2: np.ndarray, h: np.ndarray, dz_m: float, ok: np.ndarray,
                   min_points: int = 50, min_flow_px: float = 2.0) -> float:
    """Camera 2's frame interval over camera 1's, from how far each camera's own sky moved
    between its two frames: ``g1`` and ``g2`` (S, S, 2) [map px], camera 2's at the point that
    camera 1's pixel matched, ``h`` (S, S) those points' heights above camera 1 [m], ``dz_m``
    camera 2's height above camera 1, ``ok`` the usable lattice points. NaN: fewer than
    ``min_points`` with a height that moved at least ``min_flow_px`` along the sky's mean motion.

    Both cameras see one cloud move by v·dt, camera 1 as v·dt₁/h and camera 2 as v·dt₂/(h − dz)
    in plane offsets, so along the sky's mean motion each point's ratio is dt₂/dt₁ · h/(h − dz);
    the height factor is taken out, and the median of the points' ratios is returned. Frames
    captured on their stamps give 1 (the real Fehmarn hour: 0.989–1.014 over 30 pairs a minute
    apart; randomized skies 0.995–1.002). IP cameras fetched by a script capture each frame a
    little off its stamp: each camera's rate, read over its nominal interval, is then off by its
    own interval's error, and this ratio shows their difference (randomized clock sky 16910 with
    frames up to ±3 s off, every 30 s: 0.77–1.07)."""
    sel = ok & np.isfinite(h) & (h > 0) & (h - dz_m > 0)
    if int(sel.sum()) < min_points:
        return math.nan
    m = np.median(g1[sel], axis=0)
    n = float(np.linalg.norm(m))
    if not n >= min_flow_px:
        return math.nan
    u = m / n
    p1 = g1[sel] @ u
    p2 = (g2[sel] @ u) * (h[sel] - dz_m) / h[sel]
    moving = p1 >= min_flow_px  # (each point's own ratio: two decks at two speeds have no middle to share)
    return float(np.median(p2[moving] / p1[moving])) if int(moving.sum()) >= min_points else math.nan


def _carry_noise(rate_noise: float, offset_s: float, w: np.ndarray, nw: np.ndarray, b_unit: np.ndarray,
                 ratio: float = math.nan) -> float:
    """The noise of carrying camera 2 by ``offset_s`` along the baseline, near the zenith [rad].

    Two parts. The rate's own noise ``rate_noise`` [1/s] (the two cameras measure one rate: half
    their difference is the noise of the mean) times |δ|. And the offset's: δ is read across the
    baseline, δ = n·f / n·w, so the same rate noise puts a relative error σ_w / |n·w| on it
    (``nw``: n·w of the matched pixels; its RMS, as the estimate's (n·w)² weights pool them), and the
    carry along the baseline, (b·w)·δ, takes |b·w| times that (``w``: the matched rates, the 90th
    percentile of |b·w|). With a wind nearly along the baseline the second part dominates: a
    randomized 4773 m deck 97 m apart, wind 5 m/s across and 12 m/s along, carried 98 s every
    30 s, read its offset 1.0 s long (a 1 % error in n·w) and its height 5640 m with the first
    part alone at a sixth of its parallax (the second part is five times the first). The real
    Fehmarn station's wind has |b·w| ≈ 0.8 |n·w|: its noise grows by 1.3.

    And the frames' timing (``ratio``, :func:`interval_ratio`): a rate read over an interval that
    was not the stamps' is off by that interval's error, which both cameras' rates share in their
    mean and no disagreement between them shows; their intervals' ratio shows its size (for two
    cameras each off by an independent amount, |ratio − 1| is twice the typical error of their
    mean, taken whole here), and the carry is off by that share of |w|·|δ| (the 90th percentile
    of the matched |w|). Randomized clock sky 16910, frames up to ±3 s off every 30 s, camera 2
    107 s late at 21 m/s: a 2476 m deck read 475 m and 1551 m, valid, its carry's noise the rate's
    alone."""
    if not (math.isfinite(offset_s) and len(w)):
        return 0.0
    timing = 0.0
    if math.isfinite(ratio):
        timing = abs(ratio - 1.0) * abs(offset_s) * float(np.percentile(np.hypot(w[:, 0], w[:, 1]), 90))
    if not rate_noise > 0:
        return timing
    own = rate_noise * abs(offset_s)
    nw_rms = _rms(nw)
    wb = float(np.percentile(np.abs(w @ b_unit), 90))
    via_offset = own * wb / nw_rms if nw_rms > 0 else math.inf
    return float(math.hypot(own, via_offset, timing))


def _heights(w: np.ndarray, f: np.ndarray, bp: np.ndarray, offset_s: float) -> np.ndarray:
    """Heights above camera 1 [m] of map matches with flow f and rate w (…, 2) for camera 2's
    offset ``offset_s``: ``q·B' = w·δ − f``, along B' (``bp``, …, 2)."""
    rhs = w * offset_s - f
    with np.errstate(invalid="ignore", divide="ignore"):
        return 1.0 / ((rhs * bp).sum(-1) / (bp * bp).sum(-1))


def _lattice_flows(t1, t2, tp1, tp2, u, fb_max_px: float, step: int):
    """The three flows of :func:`sky_clock` on every ``step``-th map pixel [map px]: camera 1 →
    camera 2 as captured (f12), camera 1 back to its previous frame (g1), camera 2 back to its
    previous frame where it sees the camera-1 pixel (g2); a usable mask (forward-backward checks,
    both cameras' motions agreeing) and that disagreement.

    DIS gives each dense field after the motion it cannot reach is taken out: camera 2's dominant
    shift by phase correlation (so that a 120 s offset is in reach), and each camera's own motion
    over the interval by :func:`_motion_shifts` (a deck at 20 m/s moves ≈ 45 map px in 2 min);
    where two layers move apart, each motion is a candidate and every pixel keeps the flow that
    passes its forward-backward check best (the preset's decks 2 min apart move 30 and 65 map px
    in directions 100° apart: one shift lost the other deck, whose wrong but consistent flows gave
    an offset 7 s off). Its variational smoothing pulls a layer's flow towards its
    neighbour's across their edges (a 1200 m layer read 8 % high beside a 3500 m one, its rate
    4 % slow), so each lattice point is then refined by Lucas–Kanade in a 9 px window from there."""
    n = t1.shape[0]
    yy, xx = np.mgrid[0:n, 0:n].astype(np.float32)
    s0, s1, s2 = pmap(lambda f: f[0](*f[1:]), ((_cross_shifts, t1, t2, u[0] & u[1]), (_motion_shifts, t1, tp1, u[0]),
                                             (_motion_shifts, t2, tp2, u[1])))
    s1, s2 = s1 or [np.zeros(2)], s2 or [np.zeros(2)]
    back2 = len(s2) > 1  # camera 2's candidates are told apart by their backward flows too
    tasks = []
    for d in s0:
        t2s = _shifted(t2, d)
        tasks += [(t1, t2s), (t2s, t1)]
    for d in s1:
        tp = _shifted(tp1, d)
        tasks += [(t1, tp), (tp, t1)]
    for d in s2:
        tp = _shifted(tp2, d)
        tasks += [(t2, tp), (tp, t2)] if back2 else [(t2, tp)]
    # the dense flows are independent: side by side on the pipeline's threads
    flows = list(pmap(lambda ab: _flow(*ab), tasks))
    k0 = 2 * len(s0)
    f12, fb12 = _best_flow(flows[:k0], s0, xx, yy)  # camera 1 → camera 2 as captured
    k = k0 + 2 * len(s1)
    g1, fbg1 = _best_flow(flows[k0:k], s1, xx, yy)  # camera 1 → its previous frame
    if back2:
        g2, _ = _best_flow(flows[k:], s2, xx, yy)
    else:
        g2 = flows[k] + s2[0].astype(np.float32)
    sl = (slice(None, None, step), slice(None, None, step))
    p0 = np.stack([xx[sl], yy[sl]], -1)
    # only the lattice points that can still be usable are refined (camera 1 sees sky there and
    # both dense flows pass their forward-backward checks; each chain of refinements stops where
    # one fails): the same values where usable, a third of the sky clock's time on the real
    # station (Lucas–Kanade on every lattice point of the square map took 65 ms a flow)
    cand = u[0][sl] & (fb12[sl] <= fb_max_px) & (fbg1[sl] <= fb_max_px)
    f12, ok12 = _refine(t1, t2, p0, f12[sl], cand)
    g1, ok1 = _refine(t1, tp1, p0, g1[sl], cand & ok12)
    p2 = p0 + f12
    g2_at, ok2 = _refine(t2, tp2, p2, _sample(g2, p2[..., 0], p2[..., 1]), cand & ok12 & ok1)
    ok = (cand & ok12 & ok1 & ok2 & (_sample(u[1].astype(np.float32), p2[..., 0], p2[..., 1]) > 0.5))
    # the two cameras' own motions agree (the same cloud, nearly the same height above each)
    disagree = np.hypot(*np.moveaxis(g1 - g2_at, -1, 0))
    ok &= disagree <= max(1.0, 0.25 * float(np.median(np.hypot(*np.moveaxis(g1, -1, 0))[ok])) if ok.any() else 1.0)
    return f12, g1, g2_at, ok, disagree


def _best_flow(flows: list, shifts: list, xx: np.ndarray, yy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per pixel, the candidate flow with the smallest forward-backward error, and that error [map
    px]; ``flows`` alternate forward and backward DIS fields, one pair per shift in ``shifts``
    (each taken out before the flow: added back here)."""
    best = err = None
    for i, d in enumerate(shifts):
        fw, bw = flows[2 * i], flows[2 * i + 1]
        fb = np.hypot(*np.moveaxis(_sample(bw, xx + fw[..., 0], yy + fw[..., 1]) + fw, -1, 0))
        g = fw + d.astype(np.float32)
        if best is None:
            best, err = g, fb
            continue
        with np.errstate(invalid="ignore"):
            take = fb < np.where(np.isnan(err), np.inf, err)
        best, err = np.where(take[..., None], g, best), np.where(take, fb, err)
    return best, err


def _refine(a: np.ndarray, b: np.ndarray, p0: np.ndarray, flow0: np.ndarray,
            where: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Lucas–Kanade from points p0 (..., 2) of ``a`` into ``b``, started at ``p0 + flow0``, its
    peak locking taken out (:func:`_unlocked`): the refined flow and where it converged; ``where``
    (...) bool: only these points (the others NaN, not converged; each point is tracked on its
    own, so the rest are as without it)."""
    shape = p0.shape[:-1]
    sel = np.ones(shape, bool) if where is None else np.asarray(where, bool)
    flow = np.full((*shape, 2), np.nan, np.float32)
    st = np.zeros(shape, np.uint8)
    if sel.any():
        start = np.nan_to_num(p0[sel] + flow0[sel], nan=-1e4).reshape(-1, 1, 2).astype(np.float32)
        pts = p0[sel].reshape(-1, 1, 2).astype(np.float32)
        p1, s1, _ = cv2.calcOpticalFlowPyrLK(a, b, pts, start.copy(), winSize=(9, 9), maxLevel=0,
                                             flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
                                             criteria=(cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 10, 0.01))
        lk = (p1 - pts).reshape(-1, 2)
        conv = s1.ravel() == 1
        fix = np.zeros_like(lk)
        fix[conv] = _unlocked(a, b, p0[sel].reshape(-1, 2)[conv], lk[conv])
        flow[sel] = lk + fix
        st[sel] = conv & (np.hypot(fix[:, 0], fix[:, 1]) <= _MAX_UNLOCK_PX)
    with np.errstate(invalid="ignore"):
        ok = (st == 1) & np.isfinite(flow0).all(-1) & (np.hypot(*np.moveaxis(flow - flow0, -1, 0)) <= 2.0)
    return np.where(ok[..., None], flow, np.nan).astype(np.float32), ok


#: What the map flows can be trusted to, shared by every tile [map px]: shifts read through
#: :func:`_unlocked` within 0.013 px on a texture as fine as the maps'. An offset read from motion
#: across the baseline of m map px per second has this / m seconds of error at least, √(1 + (δ/dt)²)
#: times that with the rate's own flows (:func:`_floor_error_s`): a randomized
#: 9667 m deck at 1.6 m/s, 0.9 map px across in 180 s, read +58.3 s for +62.6 s "± 1.4 s"; now
#: its error is 3 s and the estimate not believed (``max_error_s``).
FLOW_FLOOR_PX = 0.015
_UNLOCK_HALF = 4  # the window of :func:`_unlocked`: 9 × 9 map px, as Lucas–Kanade's
_UNLOCK_STEPS = 2  # its Gauss–Newton steps from Lucas–Kanade's flow
_MAX_UNLOCK_PX = 0.5  # a point that it moves further did not converge [map px]


def _unlocked(a: np.ndarray, b: np.ndarray, p: np.ndarray, flow: np.ndarray) -> np.ndarray:
    """The correction (N, 2) [map px] to Lucas–Kanade's ``flow`` from points ``p`` (N, 2) of ``a``
    into ``b`` that removes its peak locking.

    OpenCV's Lucas–Kanade reads its second image bilinearly, and bilinear interpolation shifts the
    finest texture by part of its fractional offset: on a sky map shifted by a known amount the
    flow read 0.10 → 0.12, 0.25 → 0.28, 0.75 → 0.72, 0.92 → 0.90 map px (exact at 0.5 and 1.5),
    which read a randomized 6079 m deck's parallax 2.4 % short with no clock offset at all, and
    its offset 0.5 s short with one (the carry then moved its height 15 %). The same windows are
    moved by inverse-compositional Gauss–Newton steps, each window read by bicubic interpolation
    (its phase error at a quarter pixel is a third of bilinear's on this texture, and each step's
    fixed point is where the windows agree): on band-limited noise as fine as the maps' (σ 0.8
    px) shifts then read within 0.013 px, against up to 0.037 px before."""
    if not len(p):
        return np.zeros((0, 2), np.float32)
    A, B = np.asarray(a, np.float32), np.asarray(b, np.float32)
    h = _UNLOCK_HALF
    on_grid = bool(np.all(p == np.round(p)))  # camera 1's lattice: its windows need no interpolation
    ta = _windows(A, p, h + 1, cv2.INTER_NEAREST if on_grid else cv2.INTER_CUBIC)  # one pixel wider: differences
    gx = 0.5 * (ta[:, 1:-1, 2:] - ta[:, 1:-1, :-2])
    gy = 0.5 * (ta[:, 2:, 1:-1] - ta[:, :-2, 1:-1])
    ta = ta[:, 1:-1, 1:-1]
    sxx, syy, sxy = (gx * gx).sum((1, 2)), (gy * gy).sum((1, 2)), (gx * gy).sum((1, 2))
    det = sxx * syy - sxy * sxy
    inv = np.where(det > 1e-6, 1.0 / np.where(det > 1e-6, det, 1.0), 0.0)
    f = np.asarray(flow, np.float32).copy()
    for _ in range(_UNLOCK_STEPS):
        d = _windows(B, p + f, h) - ta  # b(p + f + x) − a(p + x) ≈ ∇a(x)·e, the flow being f − e
        bx, by = (gx * d).sum((1, 2)), (gy * d).sum((1, 2))
        f -= np.stack([inv * (syy * bx - sxy * by), inv * (sxx * by - sxy * bx)], -1).astype(np.float32)
    return f - flow


def _windows(img: np.ndarray, c: np.ndarray, half: int, interpolation: int = cv2.INTER_CUBIC,
             rows: int = 16384) -> np.ndarray:
    """The (2·half + 1)² windows of ``img`` centred on points ``c`` (N, 2), read bicubically (or
    as ``interpolation`` says): (N, 2·half + 1, 2·half + 1) float32 (``rows`` windows per remap:
    OpenCV's maps stay under 32 767 rows)."""
    k = 2 * half + 1
    oy, ox = np.mgrid[-half:half + 1, -half:half + 1].astype(np.float32)
    mx = (c[:, 0, None, None] + ox[None]).reshape(len(c), k * k).astype(np.float32, copy=False)
    my = (c[:, 1, None, None] + oy[None]).reshape(len(c), k * k).astype(np.float32, copy=False)
    out = np.empty((len(c), k * k), np.float32)
    for i in range(0, len(c), rows):
        out[i:i + rows] = cv2.remap(img, mx[i:i + rows], my[i:i + rows], interpolation,
                                    borderMode=cv2.BORDER_REPLICATE)
    return out.reshape(len(c), k, k)


def _tile_ratio(nf: np.ndarray, nw: np.ndarray, ok: np.ndarray, tile: int, min_tiles: int,
                min_nw: float) -> tuple[float, float, int, np.ndarray]:
    """δ per tile of ``tile`` × ``tile`` map pixels with ≥ 10 % of them matched (``ok``): the
    median of n·f over the median of n·w (``nf``, ``nw``), where |median n·w| ≥ ``min_nw``, weighted
    by its square × the tile's matched pixels; then their weighted median (see the module
    docstring). Returns (estimate, standard error, tiles, each tile's n·w)."""
    n = nf.shape[0]
    vals, weights, rates = [], [], []
    for y in range(0, n - tile + 1, tile):
        for x in range(0, n - tile + 1, tile):
            m = ok[y:y + tile, x:x + tile]
            k = int(m.sum())
            if k < 0.1 * tile * tile:
                continue
            nw_t = float(np.median(nw[y:y + tile, x:x + tile][m]))
            if not abs(nw_t) >= min_nw:
                continue
            vals.append(float(np.median(nf[y:y + tile, x:x + tile][m])) / nw_t)
            weights.append(nw_t * nw_t * k)
            rates.append(nw_t)
    if len(vals) < min_tiles:
        return math.nan, math.nan, len(vals), np.asarray(rates)
    v, wv = np.asarray(vals), np.asarray(weights)
    wv = np.minimum(wv, 2.0 * np.median(wv))  # no tile dominates
    est = _wmedian(v, wv)
    mad = _wmedian(np.abs(v - est), wv)
    return est, 1.4826 * mad * 1.25 / math.sqrt(len(v)), len(v), np.asarray(rates)


def _wmedian(v: np.ndarray, w: np.ndarray) -> float:
    o = np.argsort(v)
    c = np.cumsum(w[o])
    return float(v[o][np.searchsorted(c, 0.5 * c[-1])])
