"""Cloud motion per layer and camera 2's clock offset, from two consecutive frame pairs.

**Temporal state, apart from configuration.** :class:`MotionConfig` (``[pipeline.motion]``) says
*how* to track; :class:`PairState` is *what the last pair left behind*: its capture time, both
cameras' working-size grey images and the history of clock-offset estimates. The pipeline stays
a function of its inputs::

    state = None
    for img1, img2, t in pairs:
        result = pipeline.process(img1, img2, t, previous=state)
        state = result.state            # hand it to the next pair

A run that loses a pair (processing failed) continues with ``state.without_frames()``: no motion
is computed across the hole, but the clock-offset history (a camera's offset is near-constant)
is kept. ``cbh run`` holds the state in its processor (:mod:`cbh.actions.run`), ``cbh replay
--reprocess`` in its loop, ``cbh pair --previous`` builds it from the previous pair. The first
pair of a run, a pair without a capture time, and a pair more than ``max_gap_s`` after the
previous one have no motion (NaN).

**Tracks.** The features are the LK stereo matcher's correspondences (corners inside camera 1's
cloud mask, with their camera-2 partners). Each camera tracks its own features back to its
previous frame (pyramidal LK, ``levels`` deep so a cloud may move tens of pixels over a 10–30 s
cadence) and forward again; a track is kept when the forward-backward disagreement is at most
``fb_max_px``. Identical consecutive frames give exactly zero displacement, hence exactly 0 m/s.

**Image motion → ground motion.** A pixel's ENU ray r is written ``a = (r_e, r_n) / r_u``: the
horizontal offset per metre of height. A cloud point at height h above the camera sits at
``C + h·a``; its ground velocity is ``v = h·(a(t) − a(t − dt)) / dt``. Each track is assigned
to the layer whose height its camera-1 pixel shows on the dense height map (within
``layer_tolerance_log`` in ln h, or 3 spreads), camera-2 tracks through their stereo partner;
``h`` is then that layer's median height (not the pixel's noisy own height). A layer's motion is
the component-wise median of its tracks' velocities (both cameras pooled), its spread
1.4826 · median |v − median| (``Layer.motion_spread_ms``); fewer than ``min_tracks`` tracks:
NaN.

**Clock offset.** Camera 2 capturing δ seconds late sees each cloud point moved by ``v·δ``.
For one stereo match (camera-1 offsets a1, camera-2 offsets a2, camera-1 motion w = da1/dt,
baseline B, camera-2 height above camera 1 Δz), with q = 1/h::

    q·B' − δ·w = a1 − a2,        B' = B_horizontal − Δz·a2

two equations, two unknowns per match: the component of the parallax *across* the baseline,
which a static scene cannot produce, measures δ, and needs motion across the baseline
(a wind along the baseline leaves δ unobservable: NaN, and heights then absorb it). Each
pair's estimate is the median over matches weighted by ``cross(B', w)²`` (inverse variance),
NaN unless a quarter of the matches see motion across the baseline and the estimate's
standard error is ≤ 0.1 s (:func:`offset_estimate`: with the wind along the baseline only
wrong tracks pass, and they would give a confident wrong number);
``clock_offset_s`` is the median of the last ``offset_history`` pair estimates (positive:
camera 2 captures late).

**Compensation.** With a known offset δ, camera 2's image is moved back to camera 1's capture
time before matching (:func:`compensate_camera2`): a pixel showing layer L is taken from where
that layer's motion carries it in δ, ``a = a2 + w_L·δ`` with ``w_L = v_L / (h_L − z2)`` (exact
geometry on a coarse grid, interpolated); which layer a pixel shows is decided photometrically
(the layer whose motion over the cadence maps it best onto camera 2's previous frame), with
occlusion (a lower layer hides a higher one; what it uncovers within δ comes from the
previous frame). Every
matcher and the triangulation then see a synchronised pair. The layer motions are the
previous pair's. Estimates are made on the compensated pair (the residual offset, added to
the one used). A pair whose estimate moves the running value by more than ``rematch_s`` (the
first pairs of a run with an offset) is matched again with the new value and this pass's layer
motions, up to three more times while the compensation still moves by more than 0.1 px, so
the second pair of a run is already compensated; in steady state a pair is matched once.
Offsets below ``compensate_min_s`` (0.2 s) are reported but not compensated: with agreeing
clocks the estimate comes out within ±0.15 s (LK's sub-pixel bias across the baseline divided
by the motion across it), and compensating such a spurious offset costs more than it saves.

Limits (measured, README): what a moving low layer uncovers in δ (a band of about
|w_low − w_high|·δ along its edges) is only approximated from the previous frame, and
resampling blurs camera 2 a little; at
960 px working size both layers of the two-layer scene come out within 0.8 % at a 3 s offset,
at 640 px the high layer (2.9 px of parallax) is 2.6–3.2 % low. An offset with all motion along
the baseline is unobservable (``clock_offset_s`` stays NaN; heights then absorb it).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace
from datetime import datetime

import cv2
import numpy as np

from cbh.result import Layer

__all__ = ["PairState", "Tracks", "track_back", "plane_offsets", "offset_per_match", "offset_estimate",
           "compensate_camera2", "layer_motion", "running_offset"]


@dataclass(frozen=True)
class PairState:
    """What one processed pair leaves for the next (see the module docstring).

    Attributes
    ----------
    time_utc : datetime or None
        Camera 1's capture time of the pair.
    cameras : tuple of str
        (camera 1, camera 2) names: a state is only used by a pipeline of the same pair.
    gray : tuple of ndarray (H, W) uint8, or None
        Both cameras' raw (uncompensated) grey images at working size; None = no frames
        (after a lost pair): no motion across it.
    offsets_s : tuple of float
        Camera 2's clock offset estimated on recent pairs, oldest first [s].
    layer_rates : tuple of ndarray (2,)
        Each moving layer's plane-offset rate seen from camera 2, ``v / (h − z2)`` [1/s]:
        the compensation of the next pair moves camera 2's pixels by ``rate · δ``.
    """

    time_utc: datetime | None
    cameras: tuple[str, str]
    gray: tuple[np.ndarray, np.ndarray] | None
    offsets_s: tuple[float, ...] = ()
    layer_rates: tuple[np.ndarray, ...] = ()

    @property
    def clock_offset_s(self) -> float:
        """Running estimate of camera 2's clock offset (median of ``offsets_s``) [s]; NaN = unknown."""
        return running_offset(self.offsets_s)

    def without_frames(self) -> "PairState":
        """This state with its frames dropped (a lost pair): the offset history is kept."""
        return replace(self, gray=None)


def running_offset(offsets_s) -> float:
    """Median of the recent per-pair offset estimates [s]; NaN when there are none."""
    v = np.asarray([o for o in offsets_s if math.isfinite(o)], np.float64)
    return float(np.median(v)) if v.size else math.nan


@dataclass(frozen=True)
class Tracks:
    """Features of one camera followed back to its previous frame (working-size pixels).

    px_now, px_prev : ndarray, shape (N, 2), float64
    ok : ndarray, shape (N,), bool (forward-backward check passed)
    """

    px_now: np.ndarray
    px_prev: np.ndarray
    ok: np.ndarray


def track_back(gray_now: np.ndarray, gray_prev: np.ndarray, px: np.ndarray, cfg) -> Tracks:
    """Pyramidal LK from the current frame back to the previous one, and forward again.

    Parameters
    ----------
    gray_now, gray_prev : ndarray, shape (H, W), uint8
    px : ndarray, shape (N, 2)
        Feature pixels in ``gray_now`` (working size).
    cfg : MotionConfig
    """
    px = np.asarray(px, np.float32).reshape(-1, 2)
    n = len(px)
    if n == 0:
        z = np.zeros((0, 2))
        return Tracks(z, z.copy(), np.zeros(0, bool))
    lk = dict(winSize=(cfg.window_px, cfg.window_px), maxLevel=cfg.levels,
              criteria=(cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 20, 0.01))
    prev, st, _ = cv2.calcOpticalFlowPyrLK(gray_now, gray_prev, px, None, **lk)
    back, st2, _ = cv2.calcOpticalFlowPyrLK(gray_prev, gray_now, prev, px.copy(),
                                            flags=cv2.OPTFLOW_USE_INITIAL_FLOW, **lk)
    h, w = gray_now.shape[:2]
    inside = (prev[:, 0] >= 0) & (prev[:, 0] <= w - 1) & (prev[:, 1] >= 0) & (prev[:, 1] <= h - 1)
    ok = (st.ravel() == 1) & (st2.ravel() == 1) & inside & (np.linalg.norm(back - px, axis=1) <= cfg.fb_max_px)
    return Tracks(px.astype(np.float64), prev.astype(np.float64), ok)


def plane_offsets(cam, px: np.ndarray) -> np.ndarray:
    """Horizontal ENU offset per metre of height of each pixel's ray, ``(r_e, r_n) / r_u``.

    Parameters
    ----------
    cam : Camera (working-size model)
    px : ndarray, shape (N, 2)

    Returns
    -------
    ndarray, shape (N, 2), float64 [m/m]; NaN for rays at or below the horizon.
    """
    px = np.asarray(px, np.float64).reshape(-1, 2)
    r = cam.model.pixel_to_ray(px) @ np.asarray(cam.R_world_from_cam, np.float64).T
    with np.errstate(invalid="ignore", divide="ignore"):
        up = np.where(r[:, 2] > 1e-3, r[:, 2], np.nan)
        return r[:, :2] / up[:, None]


def offset_per_match(baseline_m: np.ndarray, dz_m: float, a1: np.ndarray, a2: np.ndarray, w1: np.ndarray):
    """Per-match clock offset δ and inverse height q from ``q·B' − δ·w = a1 − a2``.

    Parameters
    ----------
    baseline_m : ndarray, shape (2,)
        Horizontal ENU baseline camera 1 → camera 2 [m].
    dz_m : float
        Camera 2's height above camera 1 [m].
    a1, a2 : ndarray, shape (N, 2)
        Plane offsets (:func:`plane_offsets`) of the matched pixels in cameras 1 and 2.
    w1 : ndarray, shape (N, 2)
        Camera 1's plane-offset rate of the same feature, da1/dt [1/s].

    Returns
    -------
    delta_s : ndarray (N,)
        Camera 2's clock offset [s] (positive: captures late).
    q_inv_m : ndarray (N,)
        1 / height above camera 1 [1/m].
    weight : ndarray (N,)
        ``cross(B', w)² / |B'|²`` [1/s²]: inverse variance of δ up to the pixel noise.
    """
    b = np.asarray(baseline_m, np.float64)[None, :2] - dz_m * a2
    c = a1 - a2
    cross_bw = b[:, 0] * w1[:, 1] - b[:, 1] * w1[:, 0]
    cross_bc = b[:, 0] * c[:, 1] - b[:, 1] * c[:, 0]
    cross_cw = c[:, 0] * w1[:, 1] - c[:, 1] * w1[:, 0]
    with np.errstate(invalid="ignore", divide="ignore"):
        delta = -cross_bc / cross_bw
        q = cross_cw / cross_bw
        weight = cross_bw ** 2 / np.maximum((b ** 2).sum(axis=1), 1e-12)
    return delta, q, weight


def _weighted_median(v: np.ndarray, w: np.ndarray) -> float:
    o = np.argsort(v)
    cw = np.cumsum(w[o])
    return float(v[o][np.searchsorted(cw, 0.5 * cw[-1])])


def offset_estimate(delta_s: np.ndarray, q_inv_m: np.ndarray, weight: np.ndarray, min_height_m: float,
                    max_height_m: float, max_offset_s: float, dt_s: float, min_matches: int = 20,
                    min_share: float = 0.25, max_error_s: float = 0.1) -> float:
    """One pair's clock offset: weighted median of the plausible per-match offsets [s].

    A match counts when its height 1/q is in the filtering range, |δ| ≤ ``max_offset_s``, and
    the motion across the baseline over the cadence, √weight · dt, is at least 0.01 (1 % of
    the height: a few pixels), so that δ is observable. Weights are capped at twice the median
    weight (a spurious track with a large motion would otherwise dominate).

    NaN (unknown, never a guess) unless at least ``min_matches`` matches and ``min_share`` of
    the matches at a plausible height count, and the estimate's standard error (1.4826 · MAD
    / √n) is at most ``max_error_s``: with all motion along the baseline only wrong tracks
    pass the observability test, few and scattered.
    """
    with np.errstate(invalid="ignore", divide="ignore"):
        h = 1.0 / q_inv_m
        plausible = np.isfinite(delta_s) & np.isfinite(h) & (h >= min_height_m) & (h <= max_height_m)
        ok = plausible & (np.abs(delta_s) <= max_offset_s) & (np.sqrt(weight) * dt_s >= 0.01)
    n = int(ok.sum())
    if n < min_matches or n < min_share * int(plausible.sum()):
        return math.nan
    d = delta_s[ok]
    w = np.minimum(weight[ok], 2.0 * np.median(weight[ok]))
    est = _weighted_median(d, w)
    if 1.4826 * float(np.median(np.abs(d - est))) / math.sqrt(n) > max_error_s:
        return math.nan
    return est


_GRIDS: dict = {}  # (h, w, grid_px) → identity map and coarse-grid lookups (shared by every pair)


def _grids(h: int, w: int, grid_px: int):
    """Coarse grid nodes placed where ``cv2.resize`` (INTER_LINEAR, × grid_px) samples: node k
    at pixel ``grid_px·k + (grid_px − 1)/2``; and the identity remap table (H, W, 2)."""
    key = (h, w, grid_px)
    if key not in _GRIDS:
        nh, nw = -(-h // grid_px), -(-w // grid_px)
        c = (grid_px - 1) / 2.0
        gy, gx = np.mgrid[0:nh, 0:nw].astype(np.float64) * grid_px + c
        ident = np.dstack(np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32)))
        _GRIDS.clear()
        _GRIDS[key] = (np.stack([gx.ravel(), gy.ravel()], axis=1), gy.shape, ident)
    return _GRIDS[key]


def compensate_camera2(gray_now: np.ndarray, gray_prev: np.ndarray, cam2, rates: list[np.ndarray],
                       delta_s: float, dt_s: float, grid_px: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """Camera 2's current image moved back to camera 1's capture time (δ earlier).

    Each layer L moves camera 2's plane offsets by ``w_L = v_L / (h_L − z2)`` per second, so
    the point seen at pixel u at camera 1's time is seen δ later where ``a = a2(u) + w_L·δ``:
    exact geometry, evaluated on a grid every ``grid_px`` pixels and interpolated (smooth within
    a layer). Which layer each pixel shows:

    1. in the current frame, photometrically: the layer whose motion over ``dt_s`` maps the
       pixel onto the most similar place of the previous frame (absolute difference, 9 × 9
       box mean);
    2. at camera 1's time, pixel u shows layer L if L's source pixel in the current frame shows
       L; the lowest such layer wins (a lower cloud hides a higher one);
    3. a pixel that no layer explains was uncovered by a lower layer within δ: its look at
       camera 1's time is not in the current frame, so it is taken from the previous frame
       (δ − dt later there, with the highest layer's motion).

    Parameters
    ----------
    gray_now, gray_prev : ndarray, shape (H, W), uint8
        Camera 2's current and previous raw frames (working size).
    cam2 : Camera
        Camera 2 at working size.
    rates : list of ndarray (2,)
        ``w_L`` of each layer with a known motion, lowest layer first [1/s].
    delta_s, dt_s : float
        Clock offset of camera 2 [s]; time between the frames [s].

    Returns
    -------
    image : ndarray, shape (H, W), uint8
        The compensated image (bicubic resampling).
    map : ndarray, shape (H, W, 2), float32
        Where each pixel was taken from in the current frame (``cv2.remap`` table, x then y).
    """
    h, w = gray_now.shape[:2]
    grid, gshape, ident = _grids(h, w, grid_px)
    a2 = plane_offsets(cam2, grid)
    seen = np.isfinite(a2).all(axis=1, keepdims=True)

    def field(da):  # remap table of the pixels whose plane offset moves by da
        a = a2 + da[None, :]
        d = np.concatenate([a, np.ones((len(a), 1))], axis=1)
        p = cam2.direction_to_pixel(d / np.linalg.norm(d, axis=1, keepdims=True))
        disp = np.where(np.isfinite(p) & seen, p - grid, 0.0).reshape(gshape + (2,)).astype(np.float32)
        full = cv2.resize(disp, (gshape[1] * grid_px, gshape[0] * grid_px), interpolation=cv2.INTER_LINEAR)
        return cv2.add(ident, full[:h, :w])

    def sample(img, m):
        return cv2.remap(img, m, None, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REPLICATE)

    rates = [np.asarray(r, np.float64) for r in rates]
    maps = [field(r * delta_s) for r in rates]
    if len(maps) == 1:
        return sample(gray_now, maps[0]), maps[0]
    label_now, best = None, None  # per pixel of the current frame: the layer of the lowest cost
    for i, r in enumerate(rates):
        back = cv2.remap(gray_prev, field(-r * dt_s), None, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        cost = cv2.boxFilter(cv2.absdiff(back, gray_now), cv2.CV_32F, (9, 9))
        if best is None:
            label_now, best = np.zeros((h, w), np.uint8), cost
        else:
            label_now[cv2.compare(cost, best, cv2.CMP_LT) > 0] = i
            best = cv2.min(best, cost)
    free = np.full((h, w), 255, np.uint8)  # 255: no layer chosen yet
    out = maps[-1].copy()
    for i, m in enumerate(maps):  # lowest first: it hides the ones above
        src = cv2.remap(label_now, m, None, cv2.INTER_NEAREST, borderMode=cv2.BORDER_REPLICATE)
        take = cv2.bitwise_and(cv2.compare(src, i, cv2.CMP_EQ), free)
        cv2.copyTo(m, take, out)
        free = cv2.bitwise_and(free, cv2.bitwise_not(take))
    image = sample(gray_now, out)
    if cv2.countNonZero(free):
        cv2.copyTo(sample(gray_prev, field(-rates[-1] * (dt_s - delta_s))), free, image)
    return image, out


def layer_motion(layers: list[Layer], samples: list[tuple[np.ndarray, np.ndarray, float]], min_tracks: int) -> list[Layer]:
    """Each layer with its motion over the ground (median of its tracks, both cameras pooled).

    Layers are taken from the lowest up. A track of a layer that moves at a lower layer's
    angular rate (plane-offset rate within ``_SAME_RATE_REL`` of it, or 3 of its spreads) is
    taken to follow that layer and dropped: the lower cloud hid the feature in the previous
    frame (and moved on since) or crosses its window, and as both cameras see the lower cloud's
    shift alike, even the track's stereo height can stay put (60 s cadence, two-layers scene:
    the 3500 m deck got (+18, +5) m/s, the 1200 m layer's rate × 2.9, instead of (−3, 8)). The
    price: a layer whose wind is the lower one's scaled by the height ratio, in the same
    direction, stays without motion (NaN), never a wrong one.

    Parameters
    ----------
    layers : list of Layer
    samples : list of (w, label, camera_z_m)
        Per camera: plane-offset rates ``w`` (N, 2) [1/s], each track's layer index (N,) int
        (-1 = none) and the camera's ENU height [m].
    min_tracks : int

    Returns
    -------
    list of Layer
        With ``motion_east_ms``, ``motion_north_ms``, ``motion_spread_ms``, ``motion_tracks``
        (NaN and 0 where a layer has fewer than ``min_tracks`` tracks), in the given order.
    """
    out: dict[int, Layer] = {}
    lower: list[tuple[np.ndarray, float]] = []  # (rate, tolerance) of each layer below with motion
    for i in np.argsort([L.median_height_m for L in layers], kind="stable"):
        L = layers[int(i)]
        ws = [w[(lab == i) & np.isfinite(w).all(axis=1)] for w, lab, _ in samples]
        for rate, tol in lower:
            ws = [w[np.linalg.norm(w - rate, axis=1) > tol] for w in ws]
        v = np.concatenate([w * (L.median_height_m - cz) for w, (_, _, cz) in zip(ws, samples)] or [np.zeros((0, 2))])
        if len(v) < min_tracks:
            out[int(i)] = replace(L, motion_east_ms=math.nan, motion_north_ms=math.nan, motion_spread_ms=math.nan,
                                  motion_tracks=0)
            continue
        med = np.median(v, axis=0)
        spread = 1.4826 * float(np.median(np.linalg.norm(v - med, axis=1)))
        out[int(i)] = replace(L, motion_east_ms=float(med[0]), motion_north_ms=float(med[1]), motion_spread_ms=spread,
                              motion_tracks=int(len(v)))
        w_all = np.concatenate(ws)
        w_med = np.median(w_all, axis=0)
        w_mad = 1.4826 * float(np.median(np.linalg.norm(w_all - w_med, axis=1)))
        if float(np.linalg.norm(w_med)) > 3.0 * w_mad:  # it moves (a still layer drags nothing)
            lower.append((w_med, max(_SAME_RATE_REL * float(np.linalg.norm(w_med)), 3.0 * w_mad)))
    return [out[k] for k in range(len(layers))]


#: A track moves "at a lower layer's rate" within this fraction of that rate (see :func:`layer_motion`).
_SAME_RATE_REL = 0.15


def assign_layers(height_m: np.ndarray, layers: list[Layer], tolerance_log: float) -> np.ndarray:
    """Index of the layer each height belongs to (nearest in ln h within the tolerance or
    3 spreads), -1 for none. ``height_m``: (N,) [m]; returns (N,) int64."""
    h = np.asarray(height_m, np.float64)
    lab = np.full(h.shape, -1, np.int64)
    if not layers or not h.size:
        return lab
    med = np.array([L.median_height_m for L in layers])
    tol = np.array([max(tolerance_log, 3.0 * L.spread_m / max(L.median_height_m, 1.0)) for L in layers])
    with np.errstate(invalid="ignore", divide="ignore"):
        d = np.abs(np.log(np.maximum(h, 1e-3))[:, None] - np.log(med)[None, :])
    d[~np.isfinite(d)] = np.inf
    best = np.argmin(d, axis=1)
    ok = d[np.arange(len(h)), best] <= tol[best]
    lab[ok] = best[ok]
    return lab
