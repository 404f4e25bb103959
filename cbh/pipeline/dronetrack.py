"""A drone found in each camera's frames, its log's clock, and its hover positions measured.

The flight log says where the drone is (to a GPS's metre or two) but not when on the cameras'
clock; the frames say where it is seen but not which of the sources it is. Each answers the
other's question:

- **Which source** (:func:`nearest_to_log`): in each frame, the moving source (stars and hot
  pixels removed, :mod:`cbh.pipeline.pointsources`) whose ray is nearest the ray to the log's
  position, within a gate. A star stays put, an aircraft is seen at a direction the log does
  not have in at least one camera, and the hover's median over its frames outvotes a few
  wrong picks.
- **The clock** (:func:`clock_offset`): the offset that makes the most frames agree with the
  log (a truncated quadratic of the angle, summed over frames and cameras, on a grid), then
  Gauss-Newton steps on the moving frames, each of which says how many seconds along its
  track the drone is seen ahead of the log (its angular miss along the track over its angular
  speed). The spread of those gives the offset's uncertainty.
- **The hovers** (:func:`find_hovers`, :func:`measure_hovers`): where the log stands still for
  a while, the median pixel of each camera over the hover's frames; each camera pair's
  median rays are triangulated, and the ray miss is the quality, as for clouds.

Times are seconds after a common origin; ``offset_s`` is the log's clock minus the cameras'
(the log stamps the moment the cameras stamp ``t`` as ``t + offset_s``).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

__all__ = ["CameraTrack", "Hover", "interp_log", "nearest_to_log", "clock_offset", "find_hovers",
           "measure_hovers", "rotation_between", "sector_of"]

GATE_DEG = 4.0  # a detection farther than this from the log's direction is not the drone [deg]
FINE_GATE_DEG = 1.5  # the offset's refinement [deg]
STRONG_SNR = 6.0  # a source this far above the noise is a detection; fainter ones only where the drone must be


@dataclass
class CameraTrack:
    """One camera's moving sources over the flight.

    Attributes
    ----------
    camera : cbh.geometry.station.Camera
    times_s : ndarray, shape (F,)
        Frame times on the cameras' clock [s].
    points : list of F ndarrays, shape (N_i, >=2)
        Each frame's sources that are not stars or hot pixels (``x, y`` [px] first; a fifth
        column, when there is one, is the source's signal-to-noise ratio).
    """

    camera: object
    times_s: np.ndarray
    points: list
    rays: np.ndarray = field(init=False)
    frame_of: np.ndarray = field(init=False)

    def __post_init__(self):
        self.times_s = np.asarray(self.times_s, np.float64)
        xy = [np.asarray(p, np.float64)[:, :2] for p in self.points]
        self.frame_of = np.concatenate([np.full(len(p), i) for i, p in enumerate(xy)] + [np.zeros(0, int)]).astype(int)
        allxy = np.concatenate(xy + [np.zeros((0, 2))])
        self.pixels = allxy
        snr = [np.asarray(p, np.float64)[:, 4] if np.asarray(p).ndim == 2 and np.asarray(p).shape[1] > 4
               else np.full(len(p), np.inf) for p in self.points]
        self.snr = np.concatenate(snr + [np.zeros(0)])
        self.rays = self.camera.pixel_to_world(allxy) if len(allxy) else np.zeros((0, 3))


def interp_log(log_t: np.ndarray, log_enu: np.ndarray, t: np.ndarray) -> np.ndarray:
    """The log's position [m] (N, 3) at times ``t`` (the log's clock) by linear interpolation; NaN
    outside the log."""
    t = np.asarray(t, np.float64)
    out = np.stack([np.interp(t, log_t, log_enu[:, k]) for k in range(3)], axis=1)
    out[(t < log_t[0]) | (t > log_t[-1])] = np.nan
    return out


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def nearest_to_log(track: CameraTrack, log_t, log_enu, offset_s: float, gate_deg: float = GATE_DEG,
                   R_fix: np.ndarray | None = None, min_snr: float = STRONG_SNR):
    """Per frame: the angle [rad] from the log's direction to the nearest source of at least
    ``min_snr`` (NaN: none within the gate or no log), that source's index into
    ``track.pixels`` (-1), and the log's direction (F, 3). ``R_fix`` turns the log's directions
    first (a camera's found turn)."""
    F = track.times_s.size
    pos = interp_log(log_t, log_enu, track.times_s + offset_s)
    pred = _unit(pos - track.camera.position_m)
    if R_fix is not None:
        pred = pred @ R_fix.T
    ang = np.full(F, np.nan)
    idx = np.full(F, -1)
    if len(track.rays):
        cosang = np.einsum("ij,ij->i", track.rays, pred[track.frame_of])
        a = np.arccos(np.clip(cosang, -1.0, 1.0))
        a[~np.isfinite(a) | (track.snr < min_snr)] = np.inf
        order = np.lexsort((a, track.frame_of))  # by frame, then angle: the first of each frame is its nearest
        first = order[np.concatenate([[True], np.diff(track.frame_of[order]) != 0])]
        ok = a[first] <= math.radians(gate_deg)
        ang[track.frame_of[first[ok]]] = a[first[ok]]
        idx[track.frame_of[first[ok]]] = first[ok]
    return ang, idx, pred


def _score(tracks, log_t, log_enu, offset_s: float, gate_deg: float) -> float:
    g = math.radians(gate_deg)
    s = 0.0
    for tr in tracks:
        a, _, _ = nearest_to_log(tr, log_t, log_enu, offset_s, gate_deg)
        a = a[np.isfinite(a)]
        s += float(np.sum(1.0 - (a / g) ** 2))
    return s


def _along_track(tracks, log_t, log_enu, offset_s: float, min_rate_deg_s: float = 0.2) -> np.ndarray:
    """Each moving frame's time lead [s]: the angular miss along the log's track over its rate."""
    out = []
    for tr in tracks:
        a, idx, pred = nearest_to_log(tr, log_t, log_enu, offset_s, FINE_GATE_DEG)
        dtau = 0.25
        ahead = _unit(interp_log(log_t, log_enu, tr.times_s + offset_s + dtau) - tr.camera.position_m)
        behind = _unit(interp_log(log_t, log_enu, tr.times_s + offset_s - dtau) - tr.camera.position_m)
        w = (ahead - behind) / (2 * dtau)  # angular velocity vector [rad/s] (tangent)
        rate = np.linalg.norm(w, axis=1)
        ok = (idx >= 0) & np.isfinite(rate) & (rate > math.radians(min_rate_deg_s))
        if not ok.any():
            continue
        miss = tr.rays[idx[ok]] - pred[ok]
        out.append(np.einsum("ij,ij->i", miss, w[ok]) / rate[ok] ** 2)
    return np.concatenate(out) if out else np.zeros(0)


def clock_offset(tracks, log_t, log_enu, search_s: float = 60.0, step_s: float = 0.25) -> dict:
    """The log's clock minus the cameras' [s]: ``offset_s``, its standard error ``stderr_s``, the
    spread of the moving frames' leads ``spread_s`` and their number ``moving_frames``; NaN
    offset when no offset makes any frame agree (the drone not seen, or no overlap)."""
    grid = np.arange(-search_s, search_s + step_s / 2, step_s)
    scores = np.array([_score(tracks, log_t, log_enu, d, GATE_DEG) for d in grid])
    if not np.any(scores > 0):
        return {"offset_s": math.nan, "stderr_s": math.nan, "spread_s": math.nan, "moving_frames": 0}
    best = float(grid[int(np.argmax(scores))])
    fine = best + np.arange(-2 * step_s, 2 * step_s + 1e-9, step_s / 5)
    fs = np.array([_score(tracks, log_t, log_enu, d, FINE_GATE_DEG) for d in fine])
    best = float(fine[int(np.argmax(fs))])
    lead = np.zeros(0)
    for _ in range(3):  # Gauss-Newton on the along-track leads
        lead = _along_track(tracks, log_t, log_enu, best)
        if lead.size < 3:
            break
        step = float(np.median(lead))
        best += step
        if abs(step) < 0.01:
            break
    spread = 1.4826 * float(np.median(np.abs(lead - np.median(lead)))) if lead.size >= 3 else math.nan
    return {"offset_s": best, "stderr_s": spread / math.sqrt(lead.size) if lead.size >= 3 else math.nan,
            "spread_s": spread, "moving_frames": int(lead.size)}


@dataclass(frozen=True)
class Hover:
    """A stretch of the log where the drone stands still: [start_s, end_s] on the log's clock,
    its median logged position (ENU [m])."""

    start_s: float
    end_s: float
    position_m: np.ndarray


def find_hovers(log_t, log_enu, up_m, max_speed_m_s: float = 0.5, min_s: float = 5.0, min_up_m: float = 5.0,
                window_s: float = 4.0, join_m: float = 3.0) -> list[Hover]:
    """Hovers: speed (the displacement over ``window_s``, which a GPS's fix-to-fix jitter of
    half a metre does not reach) under ``max_speed_m_s`` for at least ``min_s`` s, ``min_up_m``
    above the take-off point (the drone on the ground is not a position). Stretches closer than
    ``join_m`` and a window apart are one hover (a gust, a jittery fix)."""
    t = np.asarray(log_t, np.float64)
    half = window_s / 2
    lo, hi = np.clip(t - half, t[0], t[-1]), np.clip(t + half, t[0], t[-1])
    speed = np.linalg.norm(interp_log(t, log_enu, hi) - interp_log(t, log_enu, lo), axis=1) / np.maximum(hi - lo, 1e-6)
    still = (speed < max_speed_m_s) & (np.asarray(up_m) >= min_up_m)
    edges = np.flatnonzero(np.diff(np.concatenate([[0], still.astype(int), [0]])))
    runs = [[a, b] for a, b in zip(edges[::2], edges[1::2])]
    joined = []
    for a, b in runs:
        if joined:
            pa, pb = joined[-1]
            near = np.linalg.norm(np.median(log_enu[pa:pb], axis=0) - np.median(log_enu[a:b], axis=0)) < join_m
            if near and t[a] - t[pb - 1] <= window_s:
                joined[-1][1] = b
                continue
        joined.append([a, b])
    grow = max(half - 0.5, 0.0)  # the window's own shrinking of each end, less half a second
    out = []
    for a, b in joined:
        t0, t1 = t[a] - grow, t[b - 1] + grow
        if t1 - t0 >= min_s:
            sel = (t >= t0) & (t <= t1)
            out.append(Hover(float(t0), float(t1), np.median(log_enu[sel], axis=0)))
    return out


def measure_hovers(tracks, hovers, log_t, log_enu, offset_s: float, margin_s: float, gate_deg: float = GATE_DEG,
                   R_fix: dict | None = None, min_snr: float = STRONG_SNR) -> list[dict]:
    """Per hover and camera: the median pixel of the drone over the hover's frames (shrunk by
    ``margin_s`` at each end), its ray, the pixels' spread and count. A list (one per hover) of
    {camera name: dict(pixel, ray, spread_px, n)}; a camera that did not see the drone: n = 0."""
    out = []
    for h in hovers:
        per = {}
        for tr in tracks:
            a, idx, _ = nearest_to_log(tr, log_t, log_enu, offset_s, gate_deg,
                                       None if R_fix is None else R_fix.get(tr.camera.name), min_snr)
            sel = (tr.times_s + offset_s >= h.start_s + margin_s) & (tr.times_s + offset_s <= h.end_s - margin_s)
            k = idx[sel & (idx >= 0)]
            n = int(k.size)
            if n == 0:
                per[tr.camera.name] = {"n": 0, "frames": int(sel.sum())}
                continue
            px = np.median(tr.pixels[k], axis=0)
            spread = 1.4826 * float(np.median(np.linalg.norm(tr.pixels[k] - px, axis=1)))
            per[tr.camera.name] = {"n": n, "frames": int(sel.sum()), "pixel": px, "spread_px": spread,
                                   "ray": tr.camera.pixel_to_world(px[None])[0]}
        out.append(per)
    return out


def rotation_between(measured: np.ndarray, predicted: np.ndarray) -> np.ndarray:
    """The rotation R (3, 3) that best turns unit rays ``predicted`` (N, 3) onto ``measured`` (Kabsch)."""
    H = predicted.T @ measured
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(Vt.T @ U.T))
    return Vt.T @ np.diag([1.0, 1.0, d]) @ U.T


def sector_of(position_m: np.ndarray, centre_m: np.ndarray, centre_radius_m: float = 40.0) -> str:
    """``centre`` within ``centre_radius_m`` horizontally of the station's centre, else the
    compass quadrant (N, E, S, W) of the position's azimuth from it (the paper's sectors:
    where the drone is over the ground, whatever its height)."""
    d = np.asarray(position_m, np.float64) - centre_m
    if math.hypot(d[0], d[1]) < centre_radius_m:
        return "centre"
    az = math.degrees(math.atan2(d[0], d[1])) % 360.0
    return "NESW"[int(((az + 45.0) % 360.0) // 90.0)]
