"""Camera networks: three or more cameras of one station, fused into one answer.

A pair's height precision is δH ≈ H² δθ / B (δθ the angular matching noise, B the baseline):
a 50 m pair measures a 1500 m base to a few metres but sees an 8000 m layer with 2 px of
parallax; a 630 m pair measures the high layer well, and the low one too while the two
cameras still see the same cloud (their overlap). And a pair cannot tell which of its two
cameras is wrong when the geometry check fails; three cameras can.

:class:`StationPipeline` runs one :class:`~cbh.pipeline.run.Pipeline` per selected pair:

1. **Pair selection** (:func:`plan_pairs`, once per station). Every two cameras: baseline and
   *overlap* at heights from ``OVERLAP_HEIGHTS_M`` (:func:`pair_overlap`: the share of the
   first camera's usable sky whose point at that height the second camera sees too). A pair
   whose overlap stays under ``MIN_OVERLAP`` at every height is skipped, and the reason said
   (``skipped``); a camera left without a usable pair is an error. The pairs run are the
   *star*: the reference camera (the first) with each other camera, so every pixel of the
   reference's sky has one height per baseline; a camera that overlaps only others joins
   through its longest usable pair.
2. **Per-pair results**, each with its own geometry check (the station's rays against the
   images). The pairs run side by side.
3. **Per-camera verdict** (:func:`camera_verdict`). A camera is ``mismatched`` when every
   judged pair that holds it fails the check while a judged pair without it passes: the
   others agree with each other and not with it. A pair too broken to judge (its matches
   gone: it measured under :data:`UNMATCHED_RATIO` of the cloud a passing pair on the same
   reference measured) fails (:func:`pair_verdicts`), and one that measured the reference's
   cloud at a passing pair's heights (median within ``HEIGHT_AGREEMENT``) passes; the pairs that
   passed carry the result, pairs without a verdict only where none passed. When every star pair fails, the reference
   camera is the suspect: the pairs among the other cameras are run too (the tie-breakers)
   and, if they pass, carry the result on with the next camera as the reference.
4. **Fusion** (:func:`fuse_layers`). The layers of the agreeing pairs, grouped by height
   (within ``LAYER_MATCH_LOG`` in ln height), are averaged with weights 1/σ², σ = H² δθ / B
   (δθ is common to the pairs: the weight is B²); a pair counts for a layer only where its
   overlap at that height is at least ``MIN_OVERLAP``. A group is a layer of the station when
   the pairs reporting it hold at least ``MIN_SUPPORT_SHARE`` of the weight of all pairs
   that could have seen it (a layer only a 50 m pair reports, and a 630 m pair that saw that
   sky does not, is an alias of the short pair, not cloud). Each layer keeps its support from
   every pair (:class:`~cbh.result.Layer` ``support``).
5. **One dense height map** for the reference camera: each pixel from the longest baseline
   that measured it (the most precise; all star pairs share the reference's grid).
6. **Multi-view points** (:func:`multiview_points`). A reference pixel of the sweep's point
   lattice that two or more star pairs matched is a feature seen in k ≥ 3 views: it is
   triangulated by least squares over all its rays
   (:func:`~cbh.geometry.triangulate.triangulate_views`), and dropped when a view's ray
   misses the point by more than ``MULTIVIEW_MAX_RESIDUAL_DEG``: a mismatch in one pair
   triangulates somewhere with two rays, not with three.

The result is a :class:`~cbh.result.PairResult` whose ``cameras`` are the cameras used,
reference first; ``diagnostics`` holds the per-pair results (keys ``"<a>+<b>.<name>"``), each
camera's verdict (``geometry_mismatch_<name>``: 1 mismatched, 0 agrees, NaN not judged), the
``mismatched_cameras`` (a list of names) and the multi-view counts. Two cameras: exactly
:class:`~cbh.pipeline.run.Pipeline` (no overhead).
"""
from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field, replace
from datetime import datetime

import numpy as np

from cbh.errors import ConfigError, InputError
from cbh.geometry.station import Camera, Station
from cbh.pipeline.config import PipelineConfig
from cbh.pipeline.threads import pmap
from cbh.result import Enlarged, Layer, PairResult, PointSet

log = logging.getLogger(__name__)

__all__ = ["StationPipeline", "PairPlan", "NetworkState", "plan_pairs", "pair_overlap", "camera_verdict",
           "fuse_layers", "multiview_points", "station_cameras"]

#: Heights at which a pair's overlap is evaluated [m] (above the ENU origin).
OVERLAP_HEIGHTS_M = (300.0, 600.0, 1000.0, 1500.0, 2500.0, 4000.0, 6000.0, 8000.0, 11000.0, 15000.0)
#: A pair counts at a height where the cameras share at least this share of the sky [1].
MIN_OVERLAP = 0.25
#: Two pairs' layers are one layer within this difference of ln height (≈ 12 %; the layer
#: histogram separates layers 18 % apart, :mod:`.layers`) [1].
LAYER_MATCH_LOG = 0.12
#: A layer needs the pairs reporting it to hold this share of the weight of all pairs that
#: overlap at its height [1].
MIN_SUPPORT_SHARE = 0.5
#: The largest angle between two cameras' views of one cloud the matching is given [deg]: a
#: pair's sweep starts at the height B / tan(this) (a 630 m pair at 900 m; a 50 m pair at its
#: 100 m floor). Beyond, the two views of a cloud base differ too much for 9 px correlation
#: windows (at 35° a window's footprint is foreshortened by 18 %), and the planes below cost
#: the most (a 630 m pair swept 100 m – 15 km in 447 ms, 900 m – 15 km in 255 ms).
MAX_PARALLAX_DEG = 35.0
#: Plain LK (started at the point at infinity) finds matches within about this parallax [deg]
#: (a 50 m pair at 1500 m, 1.9°: 600 of 600 features; a 630 m pair, 23°: 24). A pair with more
#: at 3 km, a typical cloud, runs LK started at the sweep's matches only (``_seeded_lk``).
LK_REACH_DEG = 10.0
#: A multi-view feature is a mismatch when a view misses its point by more than this [deg]
#: (≈ 3 px at the default 960 px working size; matching noise is 0.1–0.3 px).
MULTIVIEW_MAX_RESIDUAL_DEG = 0.5


@dataclass(frozen=True)
class PairPlan:
    """One pair of station cameras and what the planner found about it."""

    cameras: tuple[str, str]
    baseline_m: float
    overlap: tuple[float, ...]  # at OVERLAP_HEIGHTS_M [1]
    skipped: str = ""  # why the pair is not used ("" = usable)
    floor_m: float = 0.0  # the pair sweeps from this height up (MAX_PARALLAX_DEG) [m above the first camera]
    px_per_rad: float = 305.0  # the first camera's radial scale at the zenith, at working size [px/rad]

    @property
    def agree_rad(self) -> float:
        """Two heights of one pixel agree within this parallax difference in this pair [rad]:
        ``AGREE_PX`` working pixels of its first camera."""
        return AGREE_PX / self.px_per_rad

    @property
    def name(self) -> str:
        return f"{self.cameras[0]}+{self.cameras[1]}"

    def overlap_at(self, height_m: float) -> float:
        """Overlap at ``height_m``, interpolated in ln height; 0 below the pair's floor [1]."""
        if height_m < self.floor_m:
            return 0.0
        h = np.log(np.asarray(OVERLAP_HEIGHTS_M))
        return float(np.interp(math.log(max(height_m, 1.0)), h, np.asarray(self.overlap)))


@dataclass
class NetworkState:
    """What a processed station frame set leaves for the next: each pair's own state."""

    time_utc: datetime | None
    pairs: dict[str, object] = field(default_factory=dict)  # pair name → PairState

    @property
    def gray(self):
        """A pair's frames, None when no pair kept any (the motion chain's test for a hole)."""
        return next((s.gray for s in self.pairs.values() if s is not None and s.gray is not None), None)

    def without_frames(self) -> "NetworkState":
        """The state with every pair's frames dropped (no motion across a hole; offsets kept)."""
        return NetworkState(self.time_utc, {k: (s.without_frames() if s is not None else None)
                                            for k, s in self.pairs.items()})


def station_cameras(station: Station, cameras=None) -> list[str]:
    """The camera names a network runs on: ``"a,b,c"`` or a list (default: all, file order)."""
    if cameras is None:
        names = list(station.cameras)
    else:
        names = [p.strip() for p in cameras.split(",")] if isinstance(cameras, str) else list(cameras)
    if len(names) < 2 or not all(names):
        raise ConfigError(f"a station needs at least two cameras, got {', '.join(names) or 'none'}")
    if len(set(names)) != len(names):
        raise ConfigError(f"a camera is named twice: {', '.join(names)}")
    for n in names:
        station.camera(n)
    return names


def pair_overlap(cam_a: Camera, cam_b: Camera, heights_m, max_zenith_deg: float = 80.0, n: int = 64) -> np.ndarray:
    """Share of camera a's usable sky (zenith ≤ ``max_zenith_deg``, in its image circle) whose
    point at each height is in camera b's usable sky too, (len(heights_m),) [1].

    Directions on an ``n`` × ``n`` grid uniform in solid angle over the cap."""
    u, v = np.meshgrid((np.arange(n) + 0.5) / n, (np.arange(n) + 0.5) / n)
    cosz = 1.0 - u.ravel() * (1.0 - math.cos(math.radians(max_zenith_deg)))
    az = 2 * math.pi * v.ravel()
    sinz = np.sqrt(1.0 - cosz ** 2)
    d = np.stack([sinz * np.sin(az), sinz * np.cos(az), cosz], 1)
    seen_a = cam_a.model.contains(cam_a.direction_to_pixel(d))
    d = d[seen_a]
    out = []
    for h in heights_m:
        dz = float(h) - float(cam_a.position_m[2])
        if not len(d) or dz <= 0:
            out.append(0.0)
            continue
        p = cam_a.position_m + d * (dz / d[:, 2])[:, None]
        v2 = p - cam_b.position_m
        ok = v2[:, 2] > np.linalg.norm(v2, axis=1) * math.cos(math.radians(max_zenith_deg))
        ok[ok] = cam_b.model.contains(cam_b.direction_to_pixel(v2[ok]))
        out.append(float(ok.mean()))
    return np.asarray(out)


def plan_pairs(station: Station, names: list[str], max_zenith_deg: float = 80.0,
               working_radius_px: float | None = None) -> list[PairPlan]:
    """Every two of ``names``, with baseline, overlap and why a pair is skipped.

    Raises
    ------
    ConfigError
        Two cameras at one place, or a camera that overlaps no other (every pair holding it
        skipped)."""
    plans = []
    for j, b in enumerate(names):
        for a in names[:j]:
            ca, cb = station.camera(a), station.camera(b)
            base = float(np.linalg.norm(cb.position_m - ca.position_m))
            if base < 1e-3:
                raise ConfigError(f"cameras {a} and {b} are at one place ({base:.3g} m apart): a pair needs a baseline")
            ov = pair_overlap(ca, cb, OVERLAP_HEIGHTS_M, max_zenith_deg)
            best = int(np.argmax(ov))
            skipped = "" if ov[best] >= MIN_OVERLAP else (
                f"no shared sky from {OVERLAP_HEIGHTS_M[0]:g} m to {OVERLAP_HEIGHTS_M[-1]:g} m" if ov[best] <= 0 else
                f"overlap at most {100 * ov[best]:.0f} % (at {OVERLAP_HEIGHTS_M[best]:g} m), under "
                f"{100 * MIN_OVERLAP:.0f} %")
            floor = base / math.tan(math.radians(MAX_PARALLAX_DEG))
            plans.append(PairPlan((a, b), base, tuple(float(x) for x in ov), skipped, floor,
                                  _zenith_px_per_rad(ca, working_radius_px)))
    for n in names:
        mine = [p for p in plans if n in p.cameras]
        if mine and all(p.skipped for p in mine):
            raise ConfigError(f"camera {n} overlaps no other camera: "
                              + "; ".join(f"{p.name}: {p.skipped}" for p in mine))
    return plans


# --- verdicts --------------------------------------------------------------------------------

def pair_verdict(result: PairResult) -> bool | None:
    """True: the pair agrees with the station's geometry; False: it does not
    (``geometry_mismatch``); None: no verdict (too few 2-D matches, a clear sky, or a clock that
    may stand behind whatever it found: ``clock_unknown``, ``clock_too_far``, whose pairs lose
    ``geometry_mismatch`` to the clock but keep their residual)."""
    if "geometry_mismatch" in result.flags:
        return False
    if {"clock_unknown", "clock_too_far"} & set(result.flags):
        return None
    return True if math.isfinite(result.diagnostics.get("geometry_residual_px", math.nan)) else None


#: A pair without a verdict of its own that measured under this share of the cloud that a
#: passing pair on the same reference camera measured disagrees with the station: the cloud is
#: the same, only its geometry differs (a camera rolled 2° about the long baseline left the
#: sweep 9 % of the cloud and the seeded LK too few matches to judge, while the agreeing pair
#: measured 92 %) [1].
UNMATCHED_RATIO = 0.5


def pair_verdicts(done: list[tuple[PairPlan, PairResult]], promoted: set | None = None
                  ) -> dict[tuple[str, str], bool | None]:
    """Each pair's :func:`pair_verdict`, and False for a pair without one that matched far less
    of the cloud than a passing pair on its reference camera (:data:`UNMATCHED_RATIO`); True for
    one whose heights agree with a passing pair's (:func:`_agrees_by_heights`; its name then
    goes into ``promoted``)."""
    v = {p.cameras: pair_verdict(r) for p, r in done}
    passing = any(x is True for x in v.values())
    best: dict[str, tuple[float, list]] = {}  # reference → (measured fraction, layers) of its best passing pair
    for p, r in done:
        mf = r.diagnostics.get("measured_fraction", math.nan)
        # no pair passes: the best pair not failing stands in, on any reference (one sky)
        key = p.cameras[0] if passing else "*"
        if v[p.cameras] is (True if passing else None) and math.isfinite(mf) and mf > best.get(key, (0.0, []))[0]:
            best[key] = (mf, r.layers)
    for p, r in done:
        mf = r.diagnostics.get("measured_fraction", math.nan)
        ref, layers = best.get(p.cameras[0] if passing else "*", (math.nan, []))
        # only the cloud above this pair's floor is expected of it (cloud below is below_range, not a
        # geometry error: a 432 m layer under an 886 m pair's 1265 m floor)
        cover = sum(L.cover for L in layers)
        above = sum(L.cover for L in layers if L.height_m >= p.floor_m) / cover if cover > 0 else 0.0
        if (v[p.cameras] is None and math.isfinite(mf) and math.isfinite(ref) and above >= 0.5
                and mf < UNMATCHED_RATIO * ref * above):
            v[p.cameras] = False
    for p, _ in done:
        if v[p.cameras] is None and _agrees_by_heights(p, done, v):
            v[p.cameras] = True
            if promoted is not None:
                promoted.add(p.name)
    return v


#: A pair without a 2-D verdict agrees with the station when its heights of the reference's
#: pixels are, in the median, within this of a passing pair's (a 2° tilt moves a 630 m pair's
#: 1500 m by 8 %; the passing 50 m-class pairs' own errors: p90 0.9 % at 1–3 km) [1].
HEIGHT_AGREEMENT = 0.02


def _agrees_by_heights(p: PairPlan, done, v: dict) -> bool:
    """Whether pair ``p`` measured the reference's cloud where a passing pair on the same
    reference did, at the same heights: at least ``MIN_COMPARED_PX`` pixels in common, their
    median height ratio within ``HEIGHT_AGREEMENT`` of 1 and most of them within
    ``PairPlan.agree_rad`` of the passing pair's parallax. (A long pair often has too few
    2-D matches for the geometry check of its own: LK between views 20–30° apart.)"""
    maps = _reference_maps(done, p.cameras[0])
    if p.name not in maps:
        return False
    hp = maps[p.name]
    if not any(v.get(q.cameras) is True and q.name in maps for q, _ in done):
        return _layers_agree(p, done, v)  # no passing pair on this grid: compare the layers
    for q, _ in done:
        if q is p or v.get(q.cameras) is not True or q.name not in maps:
            continue
        hq = maps[q.name]
        both = np.isfinite(hp) & np.isfinite(hq)
        if both.sum() < MIN_COMPARED_PX:
            continue
        a, b = hp[both], hq[both]
        close = np.abs(q.baseline_m * (1.0 / a - 1.0 / b)) <= q.agree_rad
        if abs(float(np.median(a / b)) - 1.0) <= HEIGHT_AGREEMENT and close.mean() >= 0.5:
            return True
    return False


def camera_verdict(names: list[str], verdicts: dict[tuple[str, str], bool | None],
                   stand_in=None) -> dict[str, bool | None]:
    """Each camera's verdict from its pairs': True = mismatched (every judged pair holding it
    fails, and a judged pair without it passes: the others agree with each other, not with it;
    where no pair passes, one without a verdict that does not fail stands in, if that blames
    one camera only; ``stand_in``: the pairs that may, default all), False = agrees (a pair
    holding it passes), None = cannot tell."""
    passing = [p for p, v in verdicts.items() if v is True]
    # no pair passes: a pair that does not fail (no verdict of its own) stands in, when that
    # blames exactly one camera
    standing = passing or [p for p, v in verdicts.items() if v is None and (stand_in is None or p in stand_in)]
    out: dict[str, bool | None] = {}
    for n in names:
        mine = [v for p, v in verdicts.items() if n in p and v is not None]
        if any(mine):
            out[n] = False
        elif mine and any(n not in p for p in standing):
            out[n] = True
        else:
            out[n] = None
    if not passing and sum(v is True for v in out.values()) > 1:
        out = {n: (None if v is True else v) for n, v in out.items()}
    return out


# --- fusion ----------------------------------------------------------------------------------

#: A pair flagged ``below_range`` reports cloud below its floor on its lowest planes: its layers
#: under this × its floor are left to the shorter pairs [1].
_FLOOR_MARGIN = 1.2


def _weight(plan: PairPlan) -> float:
    """A pair's weight for a layer it overlaps at: 1/σ² with σ = H² δθ / B, up to the factor
    (H² δθ)² common to the pairs at one height: B² [m²]."""
    return plan.baseline_m ** 2


def _groups(entries: list[tuple[PairPlan, Layer]]) -> list[list[tuple[PairPlan, Layer]]]:
    """The pairs' layers grouped by height: ascending; a layer joins the group whose running
    weighted ln-height mean is within ``LAYER_MATCH_LOG`` (one layer per pair and group: a
    second one of the same pair starts a new group)."""
    groups: list[list[tuple[PairPlan, Layer]]] = []
    for plan, L in sorted(entries, key=lambda e: e[1].height_m):
        if groups:
            g = groups[-1]
            w = np.array([_weight(p) for p, _ in g])
            centre = float(np.sum(w * np.log([x.height_m for _, x in g])) / w.sum())
            if abs(math.log(L.height_m) - centre) <= LAYER_MATCH_LOG and all(p is not plan for p, _ in g):
                g.append((plan, L))
                continue
        groups.append([(plan, L)])
    return groups


def fuse_layers(pairs: list[tuple[PairPlan, PairResult]], reference: str,
                promoted=frozenset(), station: Station | None = None) -> tuple[list[Layer], list[dict]]:
    """One set of layers from the pairs' (see the module doc): ascending, each with its
    ``support``; and the groups left out (as dicts: height, share of the weight, pairs, why)
    for the diagnostics. A group that another pair on the reference's grid contradicts pixel by
    pixel (:func:`_contradicted`) is left out; one without such evidence needs
    ``MIN_SUPPORT_SHARE`` of the weight of the pairs that overlap at its height."""
    entries = [(plan, L) for plan, r in pairs for L in r.layers if L.height_m > 0
               and not ("below_range" in r.flags and L.height_m < _FLOOR_MARGIN * plan.floor_m)]
    maps = _reference_maps(pairs, reference)
    layers, dropped = [], []
    for g in _groups(entries):
        w = np.array([_weight(p) for p, _ in g])
        h = float(np.sum(w * np.array([L.height_m for _, L in g])) / w.sum())
        eligible = [p for p, _ in pairs if p.overlap_at(h) >= MIN_OVERLAP] or [p for p, _ in g]
        total = sum(_weight(p) for p in {id(p): p for p in eligible + [p for p, _ in g]}.values())
        share = float(w.sum()) / total
        verdict = _contradicted(g, h, maps, eligible)
        if not verdict and station is not None:  # the pairs on other grids, through the layer's points
            verdict = _contradicted_across(g, h, pairs, eligible, station) or verdict
        why = (f"contradicted by {verdict}" if verdict else
               "" if verdict == "" or share >= MIN_SUPPORT_SHARE else f"{100 * share:.1f} % of the weight")
        if not why and verdict is None and _unconfirmed(g, h, eligible, promoted):
            why = "reported only by pairs passed on their heights, not by another pair that resolves it"
        if why:
            dropped.append({"height_m": h, "share": share, "pairs": [p.name for p, _ in g], "why": why})
            continue
        layers.append(_fused_layer(g, w, reference))
    return layers, dropped


def _unconfirmed(g, h: float, eligible: list[PairPlan], promoted) -> bool:
    """Whether every pair reporting group ``g`` passed on its heights only (``promoted``: no 2-D
    verdict of its own) while another pair that resolves height ``h`` (2 px of parallax,
    ``PairPlan.agree_rad``) and overlaps there does not report it. Their agreement holds on the
    layers both see; a layer only they see is unconfirmed (a far reference's 630 m pairs swept a
    500 m base, under their floors, onto 7477 m and 12973 m; the 50 m pair, or the other 630 m
    pair, saw no such layer)."""
    if not all(p.name in promoted for p, _ in g):
        return False
    return any(all(q is not p for p, _ in g) and q.baseline_m / h >= q.agree_rad for q in eligible)


#: Pixels two pairs must both have measured for one to contradict the other's layer [1].
MIN_COMPARED_PX = 200
#: The same across reference grids, in a layer's points (the sweep's lattice: 1 point per 9 px) [1].
MIN_COMPARED_POINTS = 50
#: Two pairs' heights of one reference pixel agree within this parallax difference [working px]
#: (:attr:`PairPlan.agree_rad`: 6.3 mrad for the Table 1 lens at 960 px): matching noise is
#: 0.1–0.3 px, so 2 px is a mismatch, not noise (a 341 m cloud under a 372 m pair's floor read as
#: 7051 m by that pair, 0.14 rad of parallax off the 51 m pair's 341 m) [px].
AGREE_PX = 2.0


def _contradicted_across(g, h: float, pairs, eligible: list[PairPlan], station: Station) -> str | None:
    """:func:`_contradicted` for the pairs on another reference camera: the heaviest reporting
    pair's points of this layer, seen from that pair's reference camera, looked up in its height
    map. The pair that measured at least ``MIN_COMPARED_POINTS`` of them, most at a parallax more
    than its ``agree_rad`` away from the layer's, is returned (a far reference's two 630 m pairs
    both put a 500 m base, under their floors, at 13 km; the 50 m pair on cam1's grid had 500 m
    there); "" when one compared and agreed; None without evidence."""
    top = max(g, key=lambda e: _weight(e[0]))[0]
    res = dict((p.name, x) for p, x in pairs)[top.name]
    band = math.exp(2 * LAYER_MATCH_LOG)
    xyz = np.asarray(res.points.xyz_m, np.float64)
    xyz = xyz[(xyz[:, 2] >= h / band) & (xyz[:, 2] <= h * band)]
    evidence = None
    for q in eligible:
        if q.cameras[0] == top.cameras[0] or any(q is p for p, _ in g):
            continue
        e = dict((p.name, x) for p, x in pairs)[q.name]
        m = e.enlarged("height_map")
        hm = np.asarray(m.small if m is not None else e.height_map, np.float32)
        cam = station.camera(q.cameras[0])
        px = cam.world_to_pixel(xyz)
        f = hm.shape[1] / cam.model.width
        ok = np.isfinite(px).all(axis=1)
        xi = np.clip(np.rint((px[ok, 0] + 0.5) * f - 0.5).astype(int), 0, hm.shape[1] - 1)
        yi = np.clip(np.rint((px[ok, 1] + 0.5) * f - 0.5).astype(int), 0, hm.shape[0] - 1)
        hq = hm[yi, xi]
        hq = hq[np.isfinite(hq) & (hq > 0)]
        if hq.size < MIN_COMPARED_POINTS:
            continue
        if (np.abs(q.baseline_m * (1.0 / hq - 1.0 / h)) <= q.agree_rad).mean() < 0.5:
            return q.name
        evidence = ""
    return evidence


def _reference_maps(pairs, reference: str) -> dict[str, np.ndarray]:
    """Pair name → its height map on the reference's working grid (pairs on that reference)."""
    out = {}
    for p, r in pairs:
        if p.cameras[0] != reference:
            continue
        e = r.enlarged("height_map")
        m = np.asarray(e.small if e is not None else r.height_map, np.float32)
        out[p.name] = m if not (m <= 0).any() else np.where(m > 0, m, np.float32(np.nan))
    shapes = {m.shape for m in out.values()}
    return out if len(shapes) == 1 else {}


def _contradicted(g, h: float, maps: dict[str, np.ndarray], eligible: list[PairPlan]) -> str | None:
    """The pair that contradicts group ``g`` at height ``h``: the pixels its heaviest pair puts
    in this layer were measured by that other pair too (at least ``MIN_COMPARED_PX``), and most
    of them at a parallax more than ``PairPlan.agree_rad`` away from the layer's. "" when some
    other pair could compare and none contradicts, None when there is no such evidence."""
    top = max(g, key=lambda e: _weight(e[0]))[0]
    if top.name not in maps:
        return None
    hm = maps[top.name]
    band = math.exp(2 * LAYER_MATCH_LOG)
    with np.errstate(invalid="ignore"):
        near = (hm >= h / band) & (hm <= h * band)
    evidence = None
    for q in eligible:
        if any(q is p for p, _ in g) or q.name not in maps:
            continue
        hq = maps[q.name][near]
        hq = hq[np.isfinite(hq)]
        if hq.size < MIN_COMPARED_PX:
            continue
        agree = np.abs(q.baseline_m * (1.0 / hq - 1.0 / h)) <= q.agree_rad
        if agree.mean() < 0.5:
            return q.name
        evidence = ""
    return evidence


def _fused_layer(g: list[tuple[PairPlan, Layer]], w: np.ndarray, reference: str) -> Layer:
    """The weighted layer of one group; its cover from the heaviest pair on the reference's sky."""
    wn = w / w.sum()
    avg = lambda attr: float(sum(x * getattr(L, attr) for x, (_, L) in zip(wn, g)))  # noqa: E731
    # the cover from the pair on the reference's sky with the lowest floor: a pair splits the cloud
    # among the layers it sees, and one with a high floor counts lower cloud into its lowest layer
    # (a 4.4 km pair, floor 6.3 km, gave an 8 km layer 0.48 of the sky; its 630 m partner 0.14)
    on_ref = [i for i, (p, _) in enumerate(g) if p.cameras[0] == reference] or list(range(len(g)))
    cover = g[min(on_ref, key=lambda i: (g[i][0].floor_m, -w[i]))][1].cover
    moving = [(x, L) for x, (_, L) in zip(w, g) if math.isfinite(L.motion_east_ms) and math.isfinite(L.motion_north_ms)]
    mw = sum(x for x, _ in moving)
    motion = {}
    if moving:
        motion = dict(motion_east_ms=sum(x * L.motion_east_ms for x, L in moving) / mw,
                      motion_north_ms=sum(x * L.motion_north_ms for x, L in moving) / mw,
                      motion_spread_ms=sum(x * L.motion_spread_ms for x, L in moving) / mw,
                      motion_tracks=int(sum(L.motion_tracks for _, L in moving)))
    height = avg("height_m")
    # the band: what the best-resolving pair cannot tell apart (a layer that one pair splits is two groups)
    los = [L.height_lo_m for _, L in g if math.isfinite(L.height_lo_m)]
    his = [L.height_hi_m for _, L in g if math.isfinite(L.height_hi_m)]
    band = dict(height_lo_m=min(max(los), height), height_hi_m=max(min(his), height)) if los and his else {}
    alt = avg("altitude_m") - avg("height_m") if all(math.isfinite(L.altitude_m) for _, L in g) else math.nan
    return Layer(height_m=height, median_height_m=avg("median_height_m"), spread_m=avg("spread_m"), cover=cover,
                 points=int(sum(L.points for _, L in g)), confidence=avg("confidence"), altitude_m=height + alt,
                 support=tuple((p.name, int(L.points), float(L.height_m), float(x)) for x, (p, L) in zip(wn, g)),
                 **band, **motion)


def fused_height_map(pairs: list[tuple[PairPlan, PairResult]], reference: str):
    """The reference camera's height map: each pixel from the longest baseline that measured it
    consistently (an :class:`~cbh.result.Enlarged` map when the pairs' are; None without a pair
    on it).

    From the shortest pair up, a longer pair's height replaces the one so far where it is above
    ``_FLOOR_MARGIN`` × its floor and within ``PairPlan.agree_rad`` of it in the parallax of
    the pair that gave it (the longer pair is the more precise; a disagreement that large is a
    mismatch: cloud under the longer pair's floor swept onto its lowest planes), and fills the
    pixels no shorter pair measured."""
    mine = sorted([(p, r) for p, r in pairs if p.cameras[0] == reference], key=lambda e: e[0].baseline_m)
    if not mine:
        return None
    small = [r.enlarged("height_map") for _, r in mine]
    if all(e is not None for e in small) and len({e.small.shape for e in small}) == 1:
        maps, wrap = [e.small for e in small], lambda m: Enlarged(m, small[0].width, small[0].height)  # noqa: E731
    else:
        maps, wrap = [np.asarray(r.height_map, np.float32) for _, r in mine], lambda m: m  # noqa: E731
    out = np.array(maps[0], np.float32, copy=True)
    base = np.where(np.isfinite(out), np.float32(mine[0][0].baseline_m), np.float32(np.nan))
    for (p, _), hp in zip(mine[1:], maps[1:]):
        with np.errstate(invalid="ignore", divide="ignore"):
            ok = np.isfinite(hp) & (hp >= _FLOOR_MARGIN * p.floor_m)
            had = np.isfinite(out)
            agree = np.abs(base * (1.0 / hp - 1.0 / out)) <= p.agree_rad  # (one reference camera: one px scale)
        take = ok & (~had | agree)
        out[take] = hp[take]
        base[take] = p.baseline_m
    return wrap(out)


def _pixel_keys(px: np.ndarray) -> np.ndarray:
    """An integer key per pixel (N, 2) to 1/8 px: the star pairs' lattice pixels coincide exactly."""
    q = np.rint(np.asarray(px, np.float64) * 8.0).astype(np.int64)
    return q[:, 0] * 1_000_003 + q[:, 1]


def multiview_points(station: Station, pairs: list[tuple[PairPlan, PairResult]], reference: str,
                     max_residual_deg: float = MULTIVIEW_MAX_RESIDUAL_DEG) -> tuple[PointSet, dict[str, float]]:
    """The station's point set from the pairs on the reference camera (see the module doc).

    A reference pixel matched by two or more pairs is one feature in k ≥ 3 views: its point is
    the least-squares point of all its rays (:func:`~cbh.geometry.triangulate.triangulate_views`),
    kept when every view's ray passes within ``max_residual_deg`` of it. A pixel matched by one
    pair keeps that pair's point. ``px2`` of a point: its pixel in the longest-baseline pair's
    second camera that saw it. Returns (points, diagnostics: ``multiview_tracks``,
    ``multiview_rejected``, ``multiview_median_residual_deg``)."""
    from cbh.geometry.triangulate import triangulate_views

    mine = sorted([(p, r) for p, r in pairs if p.cameras[0] == reference], key=lambda e: -e[0].baseline_m)
    if not mine:
        return PointSet.empty(), {}
    keys = [_pixel_keys(r.points.px1) for _, r in mine]
    allk, inv = np.unique(np.concatenate(keys), return_inverse=True)
    n, K = len(allk), len(mine) + 1
    px1 = np.zeros((n, 2), np.float64)
    px2 = np.full((n, 2), np.nan, np.float64)
    dirs = np.full((n, K, 3), np.nan, np.float64)
    two_view = np.full((n, 3), np.nan, np.float64)
    miss2 = np.zeros(n, np.float64)
    off = 0
    for k, ((plan, r), kk) in enumerate(zip(mine, keys)):
        idx = inv[off: off + len(kk)]
        off += len(kk)
        P = r.points
        first = np.isnan(px2[idx, 0])  # (longest baseline first: its px2 and two-view point win)
        px1[idx] = P.px1
        px2[idx[first]] = P.px2[first]
        two_view[idx[first]] = P.xyz_m[first]
        miss2[idx[first]] = P.miss_m[first]
        dirs[idx, k + 1] = station.camera(plan.cameras[1]).pixel_to_world(P.px2.astype(np.float64))
    ref = station.camera(reference)
    dirs[:, 0] = ref.pixel_to_world(px1)
    origins = np.stack([ref.position_m] + [station.camera(p.cameras[1]).position_m for p, _ in mine])
    views = np.isfinite(dirs[..., 0]).sum(1)
    multi = views >= 3
    mv = triangulate_views(origins, dirs[multi])
    worst = np.degrees(mv.max_residual_rad)
    good = np.isfinite(worst) & (worst <= max_residual_deg)
    xyz = two_view.copy()
    xyz[np.flatnonzero(multi)[good]] = mv.point_m[good]
    miss = miss2.copy()
    rng = np.linalg.norm(mv.point_m - ref.position_m, axis=1)
    miss[np.flatnonzero(multi)[good]] = (np.radians(worst) * rng)[good]
    keep = ~multi
    keep[np.flatnonzero(multi)[good]] = True
    keep &= np.isfinite(xyz).all(1)
    pts = PointSet(xyz[keep].astype(np.float32), miss[keep].astype(np.float32), px1[keep].astype(np.float32),
                   px2[keep].astype(np.float32), np.full(int(keep.sum()), -1, np.int16))
    diag = {"multiview_tracks": float(multi.sum()), "multiview_rejected": float((~good).sum()),
            "multiview_median_residual_deg": float(np.median(worst[good])) if good.any() else math.nan}
    return pts, diag


def label_points(points: PointSet, layers: list[Layer]) -> PointSet:
    """Each point's layer: the nearest in ln height within ``2 · LAYER_MATCH_LOG`` (−1: none)."""
    if not layers or not len(points):
        return points
    lh = np.log(np.array([L.height_m for L in layers]))
    with np.errstate(invalid="ignore", divide="ignore"):
        d = np.abs(np.log(np.maximum(points.height_m.astype(np.float64), 1e-3))[:, None] - lh[None, :])
    lab = np.argmin(d, axis=1).astype(np.int16)
    lab[d.min(axis=1) > 2 * LAYER_MATCH_LOG] = -1
    return replace(points, layer=lab)


# --- the station pipeline ----------------------------------------------------------------------

def pair_config(config: PipelineConfig, plan: PairPlan, o1z_m: float, cam1: Camera | None = None) -> PipelineConfig:
    """A network pair's pipeline configuration: the sweep from the pair's floor up
    (:data:`MAX_PARALLAX_DEG`), no plain LK on a pair beyond its reach (:data:`LK_REACH_DEG`),
    and (with camera 1, whose lens gives the pixels per radian) no far range of fine planes
    where even the sweep's highest height has more than ``far_px`` of parallax: those planes lie
    above it (a 630 m pair's six far planes were at 33–200 km, of its 37)."""
    m = config.matching
    floor = max(m.sweep.min_height_m, o1z_m + plan.floor_m)
    methods = m.methods
    if math.degrees(math.atan(plan.baseline_m / 3000.0)) > LK_REACH_DEG and "sweep" in methods:
        methods = tuple(x for x in methods if x != "lk")
    sweep = replace(m.sweep, min_height_m=floor)
    if cam1 is not None and _zenith_px_per_rad(cam1, config.working_radius_px) * plan.baseline_m / max(
            m.sweep.max_height_m - o1z_m, 1.0) > m.sweep.far_px:
        sweep = replace(sweep, far_px=0.0)
    return replace(config, matching=replace(m, methods=methods, sweep=sweep))


def _zenith_px_per_rad(cam: Camera, working_radius_px: float | None = None) -> float:
    """Camera ``cam``'s radial scale at the zenith at the pipeline's working size [px/rad]
    (``working_radius_px``: default the pipeline's)."""
    from cbh.pipeline.run import working_factor

    if working_radius_px is None:
        working_radius_px = PipelineConfig().working_radius_px
    r = np.asarray(cam.model.r_from_theta(np.array([0.0, 0.01])), np.float64)
    return float((r[1] - r[0]) / 0.01) * working_factor(cam, working_radius_px)


def _layers_agree(p: PairPlan, done, v: dict) -> bool:
    """Whether pair ``p`` reports, within 2 × ``HEIGHT_AGREEMENT``, every layer (cover ≥ 5 %) that
    a passing pair on another reference reports above ``p``'s floor, and at least one."""
    mine = [L.height_m for q, r in done if q is p for L in r.layers]
    for q, r in done:
        if v.get(q.cameras) is not True:
            continue
        theirs = [L.height_m for L in r.layers if L.cover >= 0.05 and L.height_m >= _FLOOR_MARGIN * p.floor_m]
        if theirs and all(any(abs(h / m - 1.0) <= 2 * HEIGHT_AGREEMENT for m in mine) for h in theirs):
            return True
    return False


def _star(plans: list[PairPlan], names: list[str]) -> list[PairPlan]:
    """The pairs run first: the reference with each camera it overlaps; a camera it does not
    overlap joins through its longest usable pair with a camera already joined; the station's
    shortest usable pair joins when the reference's pairs are all longer (it sees the lowest
    cloud). A camera that no such chain reaches (cameras looking at another sky) is a
    :class:`ConfigError`."""
    usable = [p for p in plans if not p.skipped]
    ref = names[0]
    star = [p for p in usable if ref in p.cameras]
    joined = {ref, *(c for p in star for c in p.cameras)}
    for n in names:
        if n in joined:
            continue
        links = [p for p in usable if n in p.cameras and (set(p.cameras) - {n}) & joined]
        if links:
            star.append(max(links, key=lambda p: p.baseline_m))
            joined.add(n)
    # low cloud: the station's shortest usable pair sees lowest (its sweep floor); when it does not
    # hold the reference (a far camera listed first), it runs too, for the layers
    shortest = min(usable, key=lambda p: p.floor_m, default=None)
    if shortest is not None and star and all(p.floor_m > shortest.floor_m for p in star):
        star.append(shortest)
    apart = [n for n in names if n not in joined]
    if apart:
        raise ConfigError(f"camera(s) {', '.join(apart)} share no sky with {ref}'s cameras "
                          f"({', '.join(n for n in names if n in joined)}): one station looks at one sky; "
                          "give them a station file of their own")
    return star


class StationPipeline:
    """Cloud-base heights from one synchronized frame set of N ≥ 2 station cameras.

    Parameters
    ----------
    station : Station
    cameras : str, list of str or None
        The cameras, reference first (``"cam1,cam2,cam3"``; default: all, in file order).
    config, device, backend
        As :class:`~cbh.pipeline.run.Pipeline` (one per pair, sharing them).

    Raises
    ------
    ConfigError
        Fewer than two cameras, two at one place, a camera that overlaps no other.
    """

    def __init__(self, station: Station, cameras=None, config: PipelineConfig | None = None,
                 device: str = "cpu", backend: str = "auto"):
        from cbh.pipeline.run import Pipeline

        self.station = station
        self.names = station_cameras(station, cameras)
        self.single = Pipeline(station, ",".join(self.names), config, device, backend) if len(self.names) == 2 else None
        self.config = self.single.config if self.single is not None else (
            config if config is not None else PipelineConfig.from_dict(station.sections.get("pipeline", {})))
        self._make = lambda plan: Pipeline(  # noqa: E731
            station, ",".join(plan.cameras),
            pair_config(self.config, plan, float(station.camera(plan.cameras[0]).position_m[2]),
                        station.camera(plan.cameras[0])), device, backend)
        self.plans = [] if self.single is not None else plan_pairs(
            station, self.names, self.config.masks.max_zenith_deg, self.config.working_radius_px)
        self.star = _star(self.plans, self.names) if self.plans else []
        for p in self.plans:
            if p.skipped:
                log.warning("pair %s not used: %s", p.name, p.skipped)
        self._pipes: dict[tuple[str, str], object] = {}

    @property
    def cameras(self) -> tuple[str, ...]:
        return tuple(self.names)

    def forget_learned(self) -> None:
        """Every pair pipeline's :meth:`Pipeline.forget_learned`."""
        for pipe in ([self.single] if self.single is not None else []) + list(self._pipes.values()):
            pipe.forget_learned()

    def pipeline(self, plan: PairPlan):
        """The :class:`~cbh.pipeline.run.Pipeline` of one pair (made on first use)."""
        if plan.cameras not in self._pipes:
            self._pipes[plan.cameras] = self._make(plan)
        return self._pipes[plan.cameras]

    def process(self, images, time_utc: datetime | str | None = None, *, channels: str | None = None,
                previous: "NetworkState | object | None" = None) -> PairResult:
        """Run the station on one frame set.

        Parameters
        ----------
        images : sequence or dict
            One image per camera, in :attr:`cameras` order (or a dict name → image); paths or
            arrays as :meth:`Pipeline.process <cbh.pipeline.run.Pipeline.process>`. None for a
            camera that delivered nothing: the result is from the cameras present (flag
            ``camera_missing``).
        time_utc, channels
            As :meth:`Pipeline.process <cbh.pipeline.run.Pipeline.process>`.
        previous : NetworkState or None
            The previous frame set's ``state``: motion and clock offsets per pair.
        """
        frames = self._frames(images, channels)
        if self.single is not None:
            if any(v is None for v in frames.values()):
                raise InputError(f"a two-camera station needs both images ({', '.join(self.names)})")
            prev = previous if not isinstance(previous, NetworkState) else None
            return self.single.process(frames[self.names[0]], frames[self.names[1]], time_utc, channels="bgr",
                                       previous=prev)
        t0 = time.perf_counter()
        present = [n for n in self.names if frames[n] is not None]
        done = self._run_pairs(self._star_of(present), frames, time_utc, previous)
        promoted: set = set()
        verdicts = pair_verdicts(done, promoted)
        if verdicts and not any(v is True for v in verdicts.values()) and any(v is False for v in verdicts.values()):
            run = {p.cameras for p, _ in done}
            extra = [p for p in self.plans if not p.skipped and p.cameras not in run and set(p.cameras) <= set(present)]
            done += self._run_pairs(extra, frames, time_utc, previous)  # the tie-breakers
            promoted = set()
            verdicts = pair_verdicts(done, promoted)
        if not done:
            raise InputError("no usable camera pair among the cameras present: "
                             + (", ".join(present) or "none"))
        return self._fuse(done, verdicts, present, (time.perf_counter() - t0) * 1000.0, promoted)

    def _star_of(self, present: list[str]) -> list[PairPlan]:
        """The pairs to run first among the cameras ``present``: the station's star, or — a camera
        missing, the reference perhaps — the star of the cameras that delivered, the first of
        them the reference (a camera left out by it: not run; fewer than two: none)."""
        if len(present) == len(self.names):
            return self.star
        plans = [p for p in self.plans if set(p.cameras) <= set(present) and not p.skipped]
        if len(present) < 2 or not plans:
            return []
        order = [present[0]] + [n for n in present[1:] if any(n in p.cameras for p in plans)]
        try:
            return _star(plans, order)
        except ConfigError:  # a camera present shares no sky with the new reference's: the pairs that do
            return [p for p in plans if present[0] in p.cameras]

    def _frames(self, images, channels) -> dict:
        """Each camera's image decoded once (BGR), None where missing."""
        from cbh.imageio import as_bgr

        if isinstance(images, dict):
            unknown = set(images) - set(self.names)
            if unknown:
                raise InputError(f"images for cameras not in this run: {', '.join(sorted(unknown))}")
            seq = [images.get(n) for n in self.names]
        else:
            seq = list(images)
            if len(seq) != len(self.names):
                raise InputError(f"{len(seq)} images for {len(self.names)} cameras ({', '.join(self.names)}): "
                                 "give one per camera, in the station's order")
        return {n: (None if im is None else as_bgr(im, channels, n, self.station.camera(n).model))
                for n, im in zip(self.names, seq)}

    def _run_pairs(self, plans: list[PairPlan], frames: dict, time_utc, previous) -> list[tuple[PairPlan, PairResult]]:
        from cbh.pipeline.run import FrameMemo

        states = previous.pairs if isinstance(previous, NetworkState) else {}
        memo = FrameMemo()  # camera 1's masks, sun check and segmentation, once for its pairs
        for p in plans:  # made here, not on the threads (a pipeline's first use loads its tables)
            self.pipeline(p).frame_memo = memo

        def one(p: PairPlan):
            a, b = p.cameras
            return p, self.pipeline(p).process(frames[a], frames[b], time_utc, channels="bgr",
                                                       previous=states.get(p.name))

        return list(pmap(one, plans, pool="pairs"))

    def _fuse(self, done: list[tuple[PairPlan, PairResult]], verdicts: dict, present: list[str],
              wall_ms: float, promoted: set = frozenset()) -> PairResult:
        """The station's result from the processed pairs (see the module doc)."""
        from cbh.flags import INVALIDATING

        # pairs that may stand in for a verdict: they measured the cloud (not below_range, not
        # cloud_unmatched: an overcast without texture measured nothing and proves nothing)
        sound = {p.cameras for p, r in done if not (INVALIDATING | {"cloud_unmatched"}) & set(r.flags)}
        cams_v = camera_verdict(present, verdicts, stand_in=sound)
        mismatched = [n for n in present if cams_v[n] is True]
        clean = [(p, r) for p, r in done if verdicts[p.cameras] is not False and not set(p.cameras) & set(mismatched)]
        # the pairs that passed carry the result; pairs without a verdict only where none passed,
        # and then the sound ones first
        used = ([(p, r) for p, r in clean if verdicts[p.cameras] is True]
                or [(p, r) for p, r in clean if p.cameras in sound] or clean)
        used = used or done  # every pair disagrees and no camera can be blamed: flagged, as a pair would be
        firsts = [p.cameras[0] for p, _ in used]
        reference = next((n for n in present if n not in mismatched and n in firsts), firsts[0])
        layers, dropped = fuse_layers(used, reference, promoted, self.station)
        for d in dropped:
            log.debug("network: layer at %.0f m left out (%s: %s)", d["height_m"], d["why"], ", ".join(d["pairs"]))
        points, mv = multiview_points(self.station, used, reference)
        points = label_points(points, layers)
        on_ref = [(p, r) for p, r in used if p.cameras[0] == reference]
        head = on_ref[0][1] if on_ref else used[0][1]
        cams = [reference, *(c for p, _ in used for c in p.cameras)]
        cams = tuple(dict.fromkeys(head.cameras[:1] + head.cameras[1:2] + tuple(cams)))
        masks, fractions = {}, {}
        for _, r in used:
            for c in r.cameras:
                if c not in fractions:
                    fractions[c] = r.cloud_fraction[c]
                    masks[c] = r.enlarged("cloud_masks", c) or r.cloud_masks[c]
        edges = head.histogram.edges_m
        counts = (np.histogram(points.height_m, edges)[0].astype(np.float64) if len(edges) > 1
                  else head.histogram.counts)
        flags = [f for f in dict.fromkeys(f for _, r in used for f in r.flags)]
        if mismatched:
            flags.append("camera_mismatch")
        floor = min(p.floor_m for p, _ in used)
        if (all("cloud_unmatched" in r.flags for _, r in used) and floor > self.config.matching.sweep.min_height_m
                and "below_range" not in flags):
            # the pairs left sweep from their floor up only (MAX_PARALLAX_DEG): most of the cloud
            # unmatched by all of them is cloud below it (an overcast 494 m base under 1265 m
            # floors, after the 86 m pair's camera was knocked), not a layer to report
            flags.append("below_range")
        if len(present) < len(self.names):
            flags.append("camera_missing")
        hmap = fused_height_map(used, reference)
        from cbh.result import Histogram

        result = PairResult(
            time_utc=head.time_utc, cameras=cams, layers=layers, histogram=Histogram(edges, counts), points=points,
            height_map=hmap if hmap is not None else head.height_map, cloud_masks=masks, cloud_fraction=fractions,
            timing_ms={"total": wall_ms, **{f"{p.name}.total": r.timing_ms.get("total", math.nan) for p, r in done}},
            flags=flags, matches=head.matches,
            diagnostics=self._diagnostics(head, done, cams_v, mismatched, mv, len(used)),
            pairs={p.name: r for p, r in done},
        )
        result.state = NetworkState(head.time_utc, {p.name: r.state for p, r in done})
        return result

    def _diagnostics(self, head: PairResult, done, cams_v: dict, mismatched: list[str], mv: dict,
                     n_used: int) -> dict:
        """The reference pair's own diagnostics, every pair's under ``"<a>+<b>."``, the per-camera
        verdicts and the network's counts."""
        d = dict(head.diagnostics)
        for p, r in done:
            d.update({f"{p.name}.{k}": v for k, v in r.diagnostics.items()})
            d[f"{p.name}.baseline_m"] = p.baseline_m
        for n in self.names:
            v = cams_v.get(n)
            d[f"geometry_mismatch_{n}"] = math.nan if v is None else float(v)
        d.update(mv)
        d["pairs_used"] = float(n_used)
        d["mismatched_cameras"] = list(mismatched)
        d["skipped_pairs"] = [f"{p.name}: {p.skipped}" for p in self.plans if p.skipped]  # (not stored in files)
        return d
