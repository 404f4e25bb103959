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
For one stereo match (camera-1 offsets a1, camera-2 offsets a2 as captured, camera-1 motion
w = da1/dt, baseline B, camera-2 height above camera 1 Δz), with q = 1/h::

    q·B' − δ·w = a1 − a2,        B' = B_horizontal − Δz·a2

two equations, two unknowns per match: the component of the parallax *across* the baseline,
which a static scene cannot produce, measures δ, and needs motion across the baseline
(a wind along the baseline leaves δ unobservable: NaN, and heights then absorb it). Each
pair's estimate is the median over matches weighted by ``cross(B', w)²`` (inverse variance),
NaN unless a quarter of the matches see motion across the baseline and the estimate's
standard error is ≤ 0.1 s (:func:`offset_estimate`: with the wind along the baseline only
wrong tracks pass, and they would give a confident wrong number);
``clock_offset_s`` is the median of the last ``offset_history`` pair estimates (positive:
camera 2 captures late). The estimate is always made on camera 2's pixels as captured (a
compensated match is mapped back), so it is exact whatever the compensation did. A track
counts only while its parallax ``a1 − a2`` stays the same between the frames (layers move
horizontally; a track that jumped to another cloud changes it), a test that, unlike a
triangulation of the raw pair, keeps the layer that moved across the baseline during δ: the
one that measures δ best (a 19 m/s layer at 4000 m moves 57 m in 3 s, its rays miss by
1.4 % of the range and no longer triangulate). With δ known, each track's height is the
least-squares q of the same equations (:func:`parallax_heights`).

**Motion profile.** The tracks, at those heights, give camera 2's plane-offset rate as a
function of height (:class:`MotionProfile`, :func:`track_profile`: clusters in ln h, each
node the median of its tracks). It comes from the tracks, not from the layers the pair found:
a pair matched without (or with a wrong) compensation merges or loses layers (3 s, 1000 m at
2 m/s under 4000 m at 19 m/s: one layer at 2860 m), its tracks still sit at their heights.

**Compensation.** With a known offset δ, camera 2 is moved back to camera 1's capture time
before matching, each layer with its own motion ``w_L = v_L / (h_L − z2)``: ``a = a2 + w_L·δ``
(:func:`shift_map`: exact geometry on a coarse grid, interpolated).

- The plane sweep compensates per height hypothesis: plane H is matched against camera 2
  moved with the motion of the profile node nearest to H (:func:`shifted_images`,
  :class:`~cbh.pipeline.sweep.PlaneViews`), so a layer is found however far it moves during
  δ; no pixel of camera 2 needs a layer label. A layer seen through another layer's
  compensation can still match on a wrong plane (where the motion difference runs along the
  baseline); camera 1's own motion rules that out: each plane's score is weighted by how well
  its node's motion carries camera 1's previous frame onto the current one, pixel by pixel.
- The sparse matchers (LK: the points, the tracks) get one image compensated per pixel
  (:func:`compensate_camera2`): which layer a pixel shows is decided photometrically (the
  layer whose motion over the cadence maps it best onto camera 2's previous frame), with
  occlusion (a lower layer hides a higher one; what it uncovers within δ comes from the
  previous frame).

Every matcher and the triangulation then see a synchronised pair. The profile is the
previous pair's. A pair whose estimate moves the running value by more than ``rematch_s``
(the first pairs of a run with an offset) is matched again with the new value and this
pass's profile, up to three more times while the compensation still moves by more than
0.1 px, so the second pair of a run is already compensated; in steady state a pair is
matched once. Offsets below ``compensate_min_s`` (0.2 s) are reported but not compensated:
with agreeing clocks the estimate comes out within ±0.15 s (LK's sub-pixel bias across the
baseline divided by the motion across it), and compensating such a spurious offset costs
more than it saves.

Limits (measured, docs/accuracy.md): what a moving low layer uncovers in δ is only approximated for
the sparse matchers, and resampling blurs camera 2 a little; the sweep on a torch device
matches every plane against the per-pixel compensated image (no per-height views there). An
offset with all motion along the baseline is unobservable (``clock_offset_s`` stays NaN;
heights then absorb it).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace
from datetime import datetime

import cv2
import numpy as np

from cbh.pipeline.peaks import find_peaks, smooth_gaussian, valley_cuts, weighted_median
from cbh.result import Layer

__all__ = ["PairState", "MotionProfile", "Tracks", "track_back", "plane_offsets", "offset_per_match",
           "offset_estimate", "parallax_heights", "track_profile", "shift_map", "shifted_images", "motion_factors",
           "motion_weights", "compensate_camera2", "layer_motion", "running_offset", "update_offsets",
           "jump_threshold"]


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
        Camera 2's plane-offset rate ``v / (h − z2)`` of each node of the pair's motion profile
        (:class:`MotionProfile`, lowest first) [1/s]: the compensation of the next pair moves
        camera 2's pixels by ``rate · δ``.
    rate_heights_m : tuple of float
        The height of each entry of ``layer_rates`` above the ENU origin [m].
    sky_check_in : int
        Pairs until the sky maps (:mod:`.skyclock`) estimate the offset again; 0: the next pair.
    """

    time_utc: datetime | None
    cameras: tuple[str, str]
    gray: tuple[np.ndarray, np.ndarray] | None
    offsets_s: tuple[float, ...] = ()
    layer_rates: tuple[np.ndarray, ...] = ()
    rate_heights_m: tuple[float, ...] = ()
    sky_check_in: int = 0  # pairs until the sky maps estimate the offset again (0: the next pair; .skyclock)

    @property
    def profile(self) -> "MotionProfile":
        """The motion profile the pair left (empty when ``layer_rates`` and ``rate_heights_m``
        differ in length: a state whose rates were cleared carries no motion)."""
        if not self.layer_rates or len(self.layer_rates) != len(self.rate_heights_m):
            return MotionProfile.empty()
        return MotionProfile(np.asarray(self.rate_heights_m, np.float64),
                             np.asarray([np.asarray(r, np.float64) for r in self.layer_rates]).reshape(-1, 2))

    @property
    def clock_offset_s(self) -> float:
        """Running estimate of camera 2's clock offset (median of ``offsets_s``) [s]; NaN = unknown."""
        return running_offset(self.offsets_s)

    @classmethod
    def start(cls) -> "PairState":
        """The state before a run's first pair: a run is under way, nothing is known yet (no
        frames, no offset). A pair processed with it whose matches disagree with the geometry is
        flagged ``clock_unknown`` rather than ``geometry_mismatch``: a clock offset, not yet
        measurable, would look the same."""
        return cls(time_utc=None, cameras=(), gray=None)

    @classmethod
    def resumed(cls, cameras: tuple[str, str], offsets_s, time_utc: datetime | None = None) -> "PairState":
        """The state before a run's first pair that resumes a recorded session's clock-offset
        history (oldest first, [s]) for the same ``cameras``, last estimated at ``time_utc``: no
        frames, the offset known."""
        return cls(time_utc=time_utc, cameras=tuple(cameras), gray=None, offsets_s=tuple(float(o) for o in offsets_s))

    def without_frames(self) -> "PairState":
        """This state with its frames dropped (a lost pair): the offset history is kept."""
        return replace(self, gray=None)


def update_offsets(history, new_s: float, keep: int, jump_s: float) -> tuple[float, ...]:
    """The offset history with this pair's estimate ``new_s`` appended (NaN: unchanged), the last
    ``keep`` kept.

    A camera whose clock jumped (a reboot, a clock set by hand) shows as two pairs in a row that
    agree with each other (within half the threshold: two estimates of one offset, each with the
    scatter of the history) and both differ from the running median by more than the threshold:
    the history is then restarted from those two, so that the new offset is used from the next
    pair instead of after half the history. The threshold is ``jump_s`` or four robust spreads of
    the history, whichever is larger: estimates of a 90 s offset scatter by ±3 s from pair to pair
    (a 3 s threshold alone restarted a steady history twice in half an hour). Outliers come in
    runs (a sky whose layers move apart biases the maps' estimate for minutes): on the real hour
    re-paired one frame later (+29 s), 09:22 and 09:23 read 32.5 and 35.1 s, 2.6 s apart, and
    restarted the history at 33.8 s; the next pairs read 28.4, 26.8, 30.0 s."""
    hist = tuple(o for o in history if math.isfinite(o))
    if not math.isfinite(new_s):
        return hist[-keep:]
    if len(hist) >= 3 and jump_s > 0:
        ref, last = running_offset(hist[:-1]), hist[-1]
        thr = jump_threshold(hist[:-1], jump_s)
        if abs(new_s - ref) > thr and abs(last - ref) > thr and abs(new_s - last) <= 0.5 * thr:
            return (last, new_s)
    return (hist + (new_s,))[-keep:]


def jump_floor_s(jump_s: float, dt_s: float, offset_s: float = math.nan) -> float:
    """The least jump of a camera's clock [s] that pairs ``dt_s`` [s] apart, at a running offset
    ``offset_s`` [s], can tell from the scatter of their own offset estimates: ``jump_s`` per
    minute of interval (at least ``jump_s``), and at least 5 % of the offset. A pair's estimate is
    the offset's motion across the baseline over the sky's rate, and the rate rests on the clouds'
    motion over the interval, while they change shape: on the real Fehmarn half hour the
    estimates scattered by about 1 s about their median (−31 s) at a 1-minute cadence and by about
    3 s (−25 to −36 s) at 2 minutes, where a 3 s floor had called 5 of 14 pairs a possible jump
    (``clock_unknown``); re-paired to −151 s they drifted from −152 to −146 s over the half hour
    with the offset fixed (a rate read 4 % fast), and two of them had restarted the history at
    −145 s (the deck then read 10–30 % high)."""
    floor = float(jump_s) * (max(1.0, dt_s / 60.0) if (math.isfinite(dt_s) and dt_s > 0) else 1.0)
    return max(floor, 0.05 * abs(offset_s)) if math.isfinite(offset_s) else floor


def jump_threshold(offsets_s, jump_s: float) -> float:
    """How far an estimate must be from the running offset to suggest a jumped clock [s]:
    ``jump_s`` or four robust spreads (1.4826 · MAD) of the recent estimates, whichever is larger."""
    v = np.asarray([o for o in offsets_s if math.isfinite(o)], np.float64)
    if v.size < 2:
        return float(jump_s)
    return max(float(jump_s), 4.0 * 1.4826 * float(np.median(np.abs(v - np.median(v)))))


def running_offset(offsets_s) -> float:
    """Median of the recent per-pair offset estimates [s]; NaN when there are none."""
    v = np.asarray([o for o in offsets_s if math.isfinite(o)], np.float64)
    return float(np.median(v)) if v.size else math.nan


@dataclass(frozen=True)
class MotionProfile:
    """Camera 2's view of the sky's motion as a function of height: nodes (height, rate).

    A clock offset δ moves what camera 2 sees of a cloud at height h by ``w(h)·δ`` in plane
    offsets, ``w(h) = v(h) / (h − z2)`` for the wind v(h) at that height; the compensation of a
    plane-sweep plane at height H uses the rate of the node nearest to H in ln h
    (:meth:`rate_at`), so that each layer is compensated with its own motion however far it
    moves during δ. Nodes come from the tracks (:func:`track_profile`), not from the layers a
    pair found: an uncompensated pair can merge or lose layers, its tracks still sit at their
    layers' heights once the offset is known.

    Attributes
    ----------
    heights_m : ndarray, shape (K,), float64
        Node heights above the ENU origin, ascending [m].
    rates : ndarray, shape (K, 2), float64
        Camera 2's plane-offset rate at each node (east, north) [1/s].
    """

    heights_m: np.ndarray
    rates: np.ndarray

    @classmethod
    def empty(cls) -> "MotionProfile":
        """A profile without nodes (no motion known)."""
        return cls(np.zeros(0), np.zeros((0, 2)))

    def __len__(self) -> int:
        return int(len(self.heights_m))

    def nearest(self, height_m) -> np.ndarray:
        """Index of the node nearest in ln h to each height (N,) [m] → (N,) int64."""
        h = np.log(np.maximum(np.atleast_1d(np.asarray(height_m, np.float64)), 1e-3))
        return np.argmin(np.abs(h[:, None] - np.log(np.maximum(self.heights_m, 1e-3))[None, :]), axis=1)

    def rate_at(self, height_m) -> np.ndarray:
        """Camera 2's rate (N, 2) [1/s] at heights (N,) [m]: the nearest node's."""
        return self.rates[self.nearest(height_m)]

    def moved_px(self, other: "MotionProfile", offset_s: float, px_per_rad: float) -> float:
        """How far the compensation of an offset ``offset_s`` [s] moves (camera-2 pixels near the
        zenith, ``px_per_rad`` [px/rad]) between this profile and ``other``, at every node of
        either; inf when only one of them has nodes or the offset is unknown."""
        if not len(self) and not len(other):
            return 0.0
        if not len(self) or not len(other) or not math.isfinite(offset_s):
            return math.inf
        h = np.concatenate([self.heights_m, other.heights_m])
        d = np.linalg.norm(self.rate_at(h) - other.rate_at(h), axis=1)
        return float(d.max()) * abs(offset_s) * px_per_rad


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


def offset_estimate(delta_s: np.ndarray, q_inv_m: np.ndarray, weight: np.ndarray, min_height_m: float,
                    max_height_m: float, max_offset_s: float, dt_s: float, min_matches: int = 20,
                    min_share: float = 0.25, max_error_s: float = 0.1) -> float:
    """One pair's clock offset: weighted median of the plausible per-match offsets [s].

    A match counts when its height 1/q is in the filtering range, |δ| ≤ ``max_offset_s``, and
    the motion across the baseline over the cadence, √weight · dt, is at least 0.01 (1 % of
    the height: a few pixels), so that δ is observable. Weights are capped at twice the median
    weight (a spurious track with a large motion would otherwise dominate).

    NaN (unknown, never a guess) unless at least ``min_matches`` matches and ``min_share`` of
    the matches at a plausible height count, and the estimate's standard error (1.4826 ·
    weighted MAD / √n_eff, n_eff = (Σw)² / Σw²) is at most ``max_error_s``: with all motion
    along the baseline only wrong tracks pass the observability test, few and scattered.
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
    est = weighted_median(d, w)
    # the weighted spread over the effective number of matches: the matches of a slow layer, whose
    # little motion across the baseline makes each a poor measure of δ (0.5 s from 0.1 px of LK
    # noise at 1 m/s across a 50 m baseline), count as little in the error as in the estimate
    n_eff = float(w.sum()) ** 2 / max(float((w * w).sum()), 1e-300)
    if 1.4826 * weighted_median(np.abs(d - est), w) / math.sqrt(n_eff) > max_error_s:
        return math.nan
    return est


def parallax_heights(baseline_m: np.ndarray, dz_m: float, a1: np.ndarray, a2: np.ndarray, w1: np.ndarray,
                     delta_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Inverse height of each stereo match for a known clock offset δ, and what it leaves unexplained.

    With δ known, ``q·B' = a1 − a2 + δ·w1`` (:func:`offset_per_match`) is two equations for q:
    q is their least-squares solution (the parallax along B'), and the component across B' is
    the match's miss (≈ the triangulation's ray miss / range, in plane offsets). Unlike a
    triangulation of the raw pair, a match whose layer moved across the baseline during δ is
    not lost: its height comes out right however far the cloud moved.

    Parameters
    ----------
    baseline_m : ndarray, shape (2,)
        Horizontal ENU baseline camera 1 → camera 2 [m].
    dz_m : float
        Camera 2's height above camera 1 [m].
    a1, a2 : ndarray, shape (N, 2)
        Plane offsets of the matched pixels in cameras 1 and 2 as captured [m/m].
    w1 : ndarray, shape (N, 2)
        Camera 1's plane-offset rate of the feature [1/s] (NaN: not tracked; with δ = 0 not needed).
    delta_s : float
        Camera 2's clock offset [s].

    Returns
    -------
    q_inv_m : ndarray (N,)
        1 / height above camera 1 [1/m].
    miss : ndarray (N,)
        Residual across B' [m/m] (signed).
    """
    b = np.asarray(baseline_m, np.float64)[None, :2] - dz_m * np.asarray(a2, np.float64)
    c = np.asarray(a1, np.float64) - a2
    if delta_s:
        c = c + delta_s * np.asarray(w1, np.float64)
    bb = np.maximum((b ** 2).sum(axis=1), 1e-12)
    q = (b * c).sum(axis=1) / bb
    miss = (b[:, 0] * c[:, 1] - b[:, 1] * c[:, 0]) / np.sqrt(bb)
    return q, miss


def track_profile(height_m: np.ndarray, rates: np.ndarray, min_tracks: int, tolerance_log: float) -> MotionProfile:
    """Nodes of a :class:`MotionProfile` from tracks: clusters in ln h, each node the cluster's
    median height and component-wise median rate.

    The tracks' heights are binned in ln h (bins of ``tolerance_log`` / 2), smoothed over one bin
    and split at the valleys between the histogram's peaks (:mod:`.peaks`, the finder of the
    layer histogram); a cluster with fewer than ``min_tracks`` tracks gives no node.

    Parameters
    ----------
    height_m : ndarray, shape (N,)
        Each track's height above the ENU origin [m] (NaN: none).
    rates : ndarray, shape (N, 2)
        Each track's plane-offset rate as seen from camera 2 [1/s] (NaN: lost).
    min_tracks : int
    tolerance_log : float
        Layer tolerance in ln h (``MotionConfig.layer_tolerance_log``).
    """
    h = np.asarray(height_m, np.float64)
    r = np.asarray(rates, np.float64).reshape(-1, 2)
    ok = np.isfinite(h) & (h > 0) & np.isfinite(r).all(axis=1)
    if int(ok.sum()) < max(int(min_tracks), 1):
        return MotionProfile.empty()
    lh, r = np.log(h[ok]), r[ok]
    bw = 0.5 * max(float(tolerance_log), 1e-3)
    b = np.floor((lh - lh.min()) / bw).astype(np.int64) + 2
    votes = smooth_gaussian(np.bincount(b, minlength=int(b.max()) + 3).astype(np.float64), 1.0)
    peaks = find_peaks(votes)
    edges = np.array([-1] + valley_cuts(votes, peaks) + [len(votes)])
    heights, out = [], []
    for lo, hi in zip(edges[:-1], edges[1:]):
        sel = (b > lo) & (b <= hi)
        if int(sel.sum()) >= min_tracks:
            heights.append(float(np.exp(np.median(lh[sel]))))
            out.append(np.median(r[sel], axis=0))
    if not heights:
        return MotionProfile.empty()
    return MotionProfile(np.asarray(heights), np.asarray(out).reshape(-1, 2))


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
        if len(_GRIDS) >= 4:  # (a camera pair's full and half working sizes)
            _GRIDS.clear()
        _GRIDS[key] = (np.stack([gx.ravel(), gy.ravel()], axis=1), gy.shape, ident)
    return _GRIDS[key]


_OFFSETS: dict = {}  # id(camera) → (camera, grid key, plane offsets of the grid nodes): two cameras per pipeline


def _grid_offsets(cam, grid: np.ndarray, key) -> np.ndarray:
    """:func:`plane_offsets` of the coarse grid nodes of ``cam`` (cached for the camera object)."""
    hit = _OFFSETS.get(id(cam))
    if hit is None or hit[0] is not cam or hit[1] != key:
        if len(_OFFSETS) >= 8:
            _OFFSETS.clear()
        hit = _OFFSETS[id(cam)] = (cam, key, plane_offsets(cam, grid))
    return hit[2]


def shift_map(cam, shape: tuple[int, int], da: np.ndarray, grid_px: int = 8, down: int = 1) -> np.ndarray:
    """Remap table of a camera's pixels whose plane offset moves by ``da``: pixel u is taken from
    where ``a = a(u) + da`` (exact geometry every ``grid_px`` pixels, bilinear in between).

    Parameters
    ----------
    cam : Camera
        The camera at working size.
    shape : (int, int)
        Working image size (H, W) [px].
    da : ndarray, shape (2,)
        Plane-offset shift (east, north) [m/m].
    grid_px : int
        Spacing of the exact nodes at working size [px] (a multiple of ``down``).
    down : int
        The table for the image downsampled by this whole factor (INTER_AREA blocks: pixel i
        is working pixels down·i … down·i + down − 1), (H // down, W // down).

    Returns
    -------
    ndarray, shape (H // down, W // down, 2), float32
        ``cv2.remap`` table (x then y); unchanged pixels where the shifted ray leaves the sky.
    """
    h, w = shape
    grid, gshape, _ = _grids(h, w, grid_px)
    a0 = _grid_offsets(cam, grid, (h, w, grid_px))
    seen = np.isfinite(a0).all(axis=1, keepdims=True)
    a = a0 + np.asarray(da, np.float64)[None, :]
    d = np.concatenate([a, np.ones((len(a), 1))], axis=1)
    p = cam.direction_to_pixel(d / np.linalg.norm(d, axis=1, keepdims=True))
    # the nodes, at working pixel g = grid_px·k + (grid_px − 1)/2, are at (g + 0.5)/down − 0.5 =
    # (grid_px/down)·k + (grid_px/down − 1)/2 downsampled: the same layout, grid_px/down apart
    disp = (np.where(np.isfinite(p) & seen, p - grid, 0.0) / down).reshape(gshape + (2,)).astype(np.float32)
    g, hd, wd = grid_px // down, h // down, w // down
    full = cv2.resize(disp, (gshape[1] * g, gshape[0] * g), interpolation=cv2.INTER_LINEAR)
    return cv2.add(_grids(hd, wd, g)[2], full[:hd, :wd])


def _sample(img: np.ndarray, m: np.ndarray) -> np.ndarray:
    return cv2.remap(img, m, None, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REPLICATE)


def shifted_images(gray: np.ndarray, cam, rates: list[np.ndarray], tau_s: float,
                   grid_px: int = 8) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """A camera's image resampled as if the whole sky moved with each rate for ``tau_s``: pixel u
    shows what the image shows where ``a = a(u) + rate · τ`` (:func:`shift_map`), one image per
    rate (one node of a :class:`MotionProfile` each).

    With camera 2's current frame and τ = δ (its clock offset), each image is camera 2 moved back
    to camera 1's capture time for the clouds of one height: the plane sweep matches each plane
    at height H against the image of the node nearest to H (:class:`~cbh.pipeline.sweep.PlaneViews`),
    so a cloud at H is compensated with its own layer's motion, with no need to tell which layer
    a pixel of camera 2 shows (what :func:`compensate_camera2` decides for the sparse matchers).
    With camera 1's previous frame and τ = −dt, each image is that frame moved on to now with
    one node's motion: where it matches the current frame, the pixel moves with that node.

    Parameters
    ----------
    gray : ndarray, shape (H, W), uint8
        The raw frame (working size).
    cam : Camera
        Its camera at working size.
    rates : list of ndarray (2,)
        The camera's plane-offset rate of each node [1/s].
    tau_s : float
        Time to move the sky by [s].

    Returns
    -------
    images : list of ndarray (H, W) uint8
        The resampled images (bicubic), one per rate.
    maps : list of ndarray (H, W, 2) float32
        Their remap tables (:func:`shift_map` of ``rate · τ``).
    """
    maps = [shift_map(cam, gray.shape[:2], np.asarray(r, np.float64) * tau_s, grid_px) for r in rates]
    return [_sample(gray, m) for m in maps], maps


def motion_factors(scores: list[np.ndarray], min_zncc: float) -> list[np.ndarray]:
    """Each node's weight per pixel, ``max(T_k, 0) / max_j T_j`` in [0, 1], from the nodes' ZNCC
    maps T_k of camera 1's current frame against its previous frame moved on with node k's
    motion; 1 for every node where ``max_j T_j < min_zncc`` (no node explains the pixel, e.g. a
    cloud that changed: the test can then tell nothing, and must not reject the pixel). The
    best node keeps its planes' scores, the others are scaled down by how much worse they move
    the pixel; a pixel that every node explains alike keeps all its scores."""
    t_max = scores[0].copy()
    for x in scores[1:]:
        cv2.max(t_max, x, dst=t_max)
    unsure = cv2.compare(t_max, float(min_zncc), cv2.CMP_LT)
    out = []
    for x in scores:
        f = cv2.min(cv2.divide(cv2.max(x, 0.0), cv2.max(t_max, 1e-6)), 1.0)
        f[unsure > 0] = 1.0
        out.append(f)
    return out


def motion_weights(gray_now: np.ndarray, gray_prev: np.ndarray, cam, rates: list[np.ndarray], dt_s: float,
                   window_px: int, min_zncc: float, grid_px: int = 8) -> list[np.ndarray]:
    """How well each node's motion explains each 2 × 2 block of a camera's current frame: the
    weights of :class:`~cbh.pipeline.sweep.PlaneViews`.

    The previous frame, moved on by ``dt_s`` with node k's plane-offset rate (:func:`shift_map`
    of ``−rate·dt``), is compared with the current frame by ZNCC (:func:`~cbh.pipeline.sweep.zncc_map`)
    at half resolution over ``window_px // 2`` (rounded up to odd) blocks: the sweep's window;
    the ZNCCs become weights by :func:`motion_factors`.

    Parameters
    ----------
    gray_now, gray_prev : ndarray, shape (H, W), uint8
        Camera 1's current and previous frames (working size).
    cam : Camera
        Camera 1 at working size.
    rates : list of ndarray (2,)
        Camera 1's plane-offset rate of each node [1/s].
    dt_s : float
        Time between the frames [s].
    window_px : int
        The sweep's ZNCC window at working size [px].
    min_zncc : float
        The sweep's acceptance (:func:`motion_factors`) [1].

    Returns
    -------
    list of ndarray (H // 2, W // 2) float32
        One weight map in [0, 1] per rate.
    """
    from cbh.pipeline.sweep import zncc_map

    h, w = gray_now.shape[:2]
    half = (w // 2, h // 2)
    now = cv2.resize(gray_now[: h - h % 2, : w - w % 2], half, interpolation=cv2.INTER_AREA).astype(np.float32)
    prev = cv2.resize(gray_prev[: h - h % 2, : w - w % 2], half, interpolation=cv2.INTER_AREA).astype(np.float32)
    k = max(3, (int(window_px) // 2) | 1)
    scores = []
    for r in rates:
        m = shift_map(cam, (h, w), -np.asarray(r, np.float64) * dt_s, grid_px, down=2)
        scores.append(zncc_map(now, cv2.remap(prev, m, None, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE), k))
    return motion_factors(scores, min_zncc)


def compensate_camera2(gray_now: np.ndarray, gray_prev: np.ndarray, cam2, rates: list[np.ndarray],
                       delta_s: float, dt_s: float, grid_px: int = 8, maps: list[np.ndarray] | None = None,
                       images: list[np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Camera 2's current image moved back to camera 1's capture time (δ earlier).

    Each layer L moves camera 2's plane offsets by ``w_L = v_L / (h_L − z2)`` per second, so
    the point seen at pixel u at camera 1's time is seen δ later where ``a = a2(u) + w_L·δ``
    (:func:`shift_map`). Which layer each pixel shows:

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
    maps, images : list of ndarray (H, W, 2) and (H, W), optional
        :func:`shift_map` of each ``w_L · δ`` and ``gray_now`` resampled through it, when already
        made (:func:`shifted_images`): the image is then put together from them (a remap's pixel
        depends on its own table entry only), not resampled again.

    Returns
    -------
    image : ndarray, shape (H, W), uint8
        The compensated image (bicubic resampling).
    map : ndarray, shape (H, W, 2), float32
        Where each pixel was taken from in the current frame (``cv2.remap`` table, x then y).
    """
    h, w = gray_now.shape[:2]
    rates = [np.asarray(r, np.float64) for r in rates]
    if maps is None:
        maps, images = [shift_map(cam2, (h, w), r * delta_s, grid_px) for r in rates], None
    if len(maps) == 1:
        return (_sample(gray_now, maps[0]) if images is None else images[0]), maps[0]
    label_now, best = None, None  # per pixel of the current frame: the layer of the lowest cost
    for i, r in enumerate(rates):
        back = cv2.remap(gray_prev, shift_map(cam2, (h, w), -r * dt_s, grid_px), None, cv2.INTER_LINEAR,
                         borderMode=cv2.BORDER_REPLICATE)
        cost = cv2.boxFilter(cv2.absdiff(back, gray_now), cv2.CV_32F, (9, 9))
        if best is None:
            label_now, best = np.zeros((h, w), np.uint8), cost
        else:
            label_now[cv2.compare(cost, best, cv2.CMP_LT) > 0] = i
            best = cv2.min(best, cost)
    free = np.full((h, w), 255, np.uint8)  # 255: no layer chosen yet
    out = maps[-1].copy()
    image = None if images is None else images[-1].copy()
    for i, m in enumerate(maps):  # lowest first: it hides the ones above
        src = cv2.remap(label_now, m, None, cv2.INTER_NEAREST, borderMode=cv2.BORDER_REPLICATE)
        take = cv2.bitwise_and(cv2.compare(src, i, cv2.CMP_EQ), free)
        cv2.copyTo(m, take, out)
        if image is not None:
            cv2.copyTo(images[i], take, image)
        free = cv2.bitwise_and(free, cv2.bitwise_not(take))
    if image is None:
        image = _sample(gray_now, out)
    if cv2.countNonZero(free):
        cv2.copyTo(_sample(gray_prev, shift_map(cam2, (h, w), -rates[-1] * (dt_s - delta_s), grid_px)), free, image)
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
