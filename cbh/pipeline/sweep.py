"""Stage 3 (dense): plane-sweep stereo on the raw fisheye images (matching method ``sweep``).

Why: a dense optical flow (DIS) regularises across the occlusion boundary between two cloud
layers and returns heights that exist in neither. A plane sweep instead tests *hypotheses of
the scene*: horizontal planes at height h. For each plane, image 2 is resampled onto camera
1's pixel grid through the plane (p1 → ray of camera 1 → the point at height h → camera 2's
pixel), and photo-consistency is scored per pixel. Every pixel takes the plane that explains
it best, so a pixel of the 1200 m layer beside a pixel of the 3500 m layer gets 1200 m or
3500 m, never a blend.

Plane mapping (exact geometry, no rectification). For a camera-1 ray d (ENU, unit) and a
plane at height h, the point is o1 + d·(h − o1z)/d_z, and its direction from camera 2 is
proportional to ``d − s·d_z·B`` with ``s = 1/(h − o1z)`` [1/m] and ``B = o2 − o1``. The
camera-2 pixel is therefore a smooth function of the single number s. It is evaluated
exactly (``Camera.direction_to_pixel``) for s = 0 (infinity), s_a, 2·s_a and 3·s_a once per
camera pair, and in between by the cubic through those four maps (:class:`PlaneMaps`):
``p2(s) = m0 + a·s + b·s² + c·s³`` — 3 FMAs per pixel per plane instead of a fisheye
projection. ``s_a·|B| = 0.1 rad``: interpolation covers parallaxes up to 0.3 rad
(h ≥ 3.3·|B|); beyond, it extrapolates. Near the zenith camera 2 sees the point at
atan(s·|B|), odd in s; the quadratic through s = 0, s_a, 2·s_a that the maps were until stop 59
over-read the parallax (and so the height) by up to 2/3 · 0.1² ≈ 0.67 % (+0.25 % at 1175 m,
B = 50 m); the cubic leaves 0.02–0.05 %
(``tests/test_sweep_field.py::test_plane_maps_follow_the_exact_projection_near_the_zenith``,
docs/accuracy.md "Stop 58" and "Stop 59").

Planes are spaced uniformly in s, so neighbouring planes shift image 2 by at most
``step_px`` pixels anywhere in the image (``|a|`` is the parallax in pixels per unit s).

Score: zero-mean normalised cross-correlation (ZNCC) over a ``window_px`` box, computed with
box filters (O(1) per pixel per plane). ZNCC is invariant to gain and offset, so the
view-dependent brightness of a cloud seen from two places does not bias it.

Resolution: the ZNCC is evaluated at *half* the working resolution, over 2k × 2k windows (k =
``window_px // 2``; 8 px for the default 9) centred on each 2 × 2 block of working pixels:
such a window's sums are k × k box sums of 2 × 2 block sums, so per plane only the remap and
two products run at working size, and the three box filters and the ZNCC arithmetic on a
quarter of the pixels (:func:`_zncc_half_iter`). Everything downstream (layer votes, labels,
refinement) already worked on 2 × 2 pooled scores; the per-pixel acceptance now uses the
block's score. The fine pass scores its planes band by band (:class:`_ZnccBand`: ~64 half
rows at a time, every plane, then the next band), so that a band's arrays stay in the core's
cache, and each band only between its first and last column with a candidate pixel (a band
with none is skipped: the sky's disc and clear stretches); the numbers are the whole region's,
bit for bit.

The passes (each a function with a typed result; :func:`sweep_field` runs them in order):

1. :func:`coarse_pass` → :class:`CoarseLayers`. At 1/``coarse_factor`` size, all planes from
   ``max_height_m`` down to ``min_height_m`` at one coarse pixel per step; the planes with more
   than ``coarse_near_px`` of parallax at half that size, every second one
   (:func:`coarse_planes`: the low planes, most of the range since the floor is 100 m). Each
   cloud pixel votes for its best plane (if ZNCC ≥ ``min_zncc``; :func:`coarse_votes`); peaks of the vote histogram over s
   (:mod:`.peaks`, the finder the layer histogram uses too) are the layer hypotheses, each with
   the extent of s around it where its votes stay above ``extent_ratio`` × peak. High layers
   (a few pixels of parallax) are not resolved at coarse size, so :func:`fine_planes` takes
   every plane of the *far range* (parallax ≤ ``far_px``, from infinity on) and the union of
   the coarse extents (± 1.5 coarse steps), ``step_px`` apart. *Regions* (issue 33): a deck
   seen only through the gaps of a lower one holds a few per cent of the whole sky's votes,
   under the smear of the windows that straddle both, but most of the votes of the regions
   where its gaps are; so each region (``region_px`` / 2 wide, overlapping by half) proposes
   its own peaks (:func:`regional_peaks`, ≥ 2.5 × ``region_share`` of its votes; above the
   highest peak's extent a peak's votes are its bin and both neighbours, so that a deck between
   two coarse planes counts whole) above the lowest layer, beyond the far range and outside
   every peak's extent; their planes are swept as long as they fit in ``max_planes`` without
   coarsening the step.
2. :func:`fine_pass` → :class:`FineCost`. At working size, every fine plane's ZNCC; a cloud
   pixel is accepted if its window has texture (grey-level standard deviation ≥
   ``min_texture``) and its block's best ZNCC ≥ ``min_zncc``. The planes are streamed: only the
   (planes, h/2, w/2) cost stack (ZNCC × textured fraction of the block) is kept.
3. :func:`label_pass` → :class:`LayerLabels`. The winners of the wide-box (``aggregate_px``)
   cost vote, in bins of half a plane step, for the layers of the image (votes only from the
   boxes whose mean ZNCC is above the ``vote_percentile``: a box that straddles two layers
   correlates worse and would fill the valley between their peaks); each pixel is labelled
   with the layer whose planes its ``label_px`` box cost prefers. The wide box that straddles a
   gap's edge takes the lower deck (its texture is coarser and stronger), so each region of
   ``region_px`` also votes with every block's *own* best plane (:func:`own_plane_peaks`): a
   region's peak with ``region_share`` of its votes (its votes smoothed over half a plane: a
   deck three planes from one with five times its votes is no flank of it) that is a local
   maximum of the whole image's own votes too, as they are or within one plane of one of them
   smoothed over a plane (not the flank of a near layer's noise; :func:`_true_peaks`), inside the
   swept planes and more than 1.5 plane steps from every layer is a layer as well: above the
   image's lowest layer (a deck seen through its gaps), and below it too (a low deck of small
   clouds whose wide boxes all straddle their edges correlates worse than the decks behind it,
   and the top 30 % of boxes leave it no vote). A layer's height
   (:func:`resolved_layers`) counts its pixels inside the height range only: the far range's
   planes match glare at infinity too, in the label of a far deck seen through gaps.
   (A pixel whose own best plane lies in another layer than its label's straddles the two: its
   cost stays out of both layers' refinement, below. Dropping such pixels altogether was tried:
   it gained nothing at 960 px, and on a clear sky without a capture time it left a cluster of
   aureole matches that passed as a layer.)
4. :func:`refine_pass`. Each pixel's height is refined (the Gaussian peak through the three
   best planes, :func:`peak_offset`) on its layer's cost summed over that layer's pixels only — and of those, only the
   ones whose own best plane lies in the layer's range: a pixel labelled into the layer by
   mistake (occluded in camera 2, or at a boundary) has its cost peak outside the range, and
   its sloped cost would pull the peak towards the range's edge (−3 … −5 % bias on the far
   layer at B = 30 m before) — so it is sharp at layer boundaries; the half-resolution s is
   brought back to working size bilinearly (a box average varies smoothly inside a layer).
   A pixel whose best plane is the last before a gap in the planes (a hypothesis's edge) is
   not matched (:func:`truncated`: the maximum is where the sweep stopped).
   With ``aggregate_px`` = 1 each pixel keeps its own best plane (full-resolution ZNCC,
   :func:`zncc_planes`), refined by :func:`peak_offset`.

The same passes run on a torch device in :mod:`.torch_ops` (same 1-D steps:
:func:`coarse_hypotheses`, :func:`fine_planes`, :func:`vote_layers`, :func:`layer_planes`,
:func:`layer_box`).

Far layers (``far_aggregate_px``): the parallax noise of a box average falls like 1/box
side, while 2 % of a far layer's height is a small parallax (2 % of p). A layer whose vote
peak has less than ``far_aggregate_px`` of parallax is refined on a box grown by
``far_aggregate_px`` / p (at most 4×): coarser detail where the parallax is small.

Oblique pixels, the same physics within a layer (``oblique_levels``, 2 by default): a plane
step shifts a pixel near the horizon far less than one at the zenith (its *reach*,
:func:`parallax_reach`: the camera-2 shift per unit s against the image's largest, ≈ cos z for
a horizontal plane), so one pixel of parallax noise is a larger share of its height (one flat
1200 m deck of the two-layers texture, B = 50 m, 1920 px: dense MdAPE 0.16 % at zenith 30–50°,
0.92 % at 60–70°, 7.3 % at 70–80°). With ``oblique_levels`` = n, pixels whose reach is below
1/√2 are refined on the layer's box grown 2×, below 1/(2√2) 4× (n = 2; within the 4× of
``_MAX_GROW``), :func:`reach_levels`: the noise of a box average falls like 1/side. Measured on
that deck: 60–70° 0.92 → 0.45 %, 70–80° 7.3 → 1.1 %, the zenith unchanged; the refinement
≈ 15–20 ms more on one thread. A grown box sums the costs of every pixel labelled with the
layer, and a deck the sweep missed has its pixels labelled with the nearest layer: the grown
box mixes them in (randomized 16981, 480 px, B = 32 m: its 538 m deck read 587 m with two
levels in stop 59, when they were off by default). The windows across a layer's edge weighing
little (:func:`layer_interior`) and the layer's geometry-weighted median
(:func:`~cbh.pipeline.layers.geometry_median`) leave it at 552 m, and the levels are on
(``tests/test_sweep_field.py::test_a_deck_seen_only_near_the_horizon_is_not_pulled_up``).

Resolvability (numbers for the Table 1 lenses at the default working size, lens radius 480 px
for 90°, 305.6 px/rad): parallax at zenith p = 305.6 px · B / h. The aggregated per-pixel
parallax (31 px box) is good to ≈ 0.1 px, so a pixel's height is within 2 % where
0.02·p ≥ 0.1 px, i.e. p ≥ 5 px (B = 50 m: h ≤ 3.0 km; B = 30 m: h ≤ 1.8 km; B = 100 m:
h ≤ 6.1 km); the grown box for far layers extends this to p ≈ 2 px (7000 m at B = 50 m:
2.2 px, dense-map median error 1.4 % with three layers). Two layers are told apart (separate
vote peaks) down to ≈ 2 px of parallax difference: 2800 m and 7000 m are 3.3 px apart at
B = 50 m and 2.0 px at B = 30 m (both separated; layer heights, aggregated over thousands of
pixels, within 2 %). At B = 30 m the pixels of the upper two layers are not resolved to 2 %:
p = 3.3 and 1.3 px, 2 % of which is 0.066 and 0.026 px, and the 7000 m pixels within ≈ 3 px
of a lower cloud (a third of them; many occluded in camera 2) take a lower layer's label:
dense-map median error 2.2 % over all three layers, coverage 69 %. Use a larger
working size (``working_radius_px``: parallax scales with it) or a longer baseline there.

Speed (1920 px pair, working size 960 px, two-layers scene, 2 cores, 2026-12-01): coarse
28 ms (16 far planes at 480 px, 30 near ones at 240 px), fine 77 ms (17 planes, ≈ 5 ms of one
core each: remap ≈ 2, plane map 0.7 (one ``cv2.transform`` per axis), the rest products,
2 × 2 pools, half-size boxes and arithmetic), labels 23 ms, refine 17 ms. The planes of every
pass run on threads (:func:`~cbh.pipeline.threads.pmap`; the caller reduces them in order as
they come); everything per pixel goes through OpenCV (no numpy temporaries); numpy's masked
``copyto`` and ``argmax`` over a stack axis are avoided (20× and 10× slower).

Clock offsets (camera 2 capturing δ late, :mod:`.motion`): image 2 may be a :class:`PlaneViews`,
one image per height of the sky's motion profile, each camera 2 moved back to camera 1's time
with that height's motion; plane H is matched against the image of the height nearest to H,
its scores weighted by how well that motion explains camera 1's own motion. Each layer is then
compensated with its own motion, however far it moves during δ. Every pass takes either.

Output: :class:`SweepField`, the refined s of every accepted pixel of camera 1's region (the
matcher makes the height map from it in closed form, h = o1z + 1/s, and a lattice of
correspondences, :func:`field_points`: px2 = the plane mapping at s; the exact camera-2 ray
follows from s, so triangulation needs no fisheye back-projection of px2). Such a
correspondence lies on the epipolar geometry by construction, so its ray miss is ≈ 0 (not a
measurement of matching quality; the sparse ``lk`` matches carry that).
"""
from __future__ import annotations

import itertools
import math
import threading
import time
from collections import OrderedDict
from dataclasses import dataclass, field

import cv2
import numpy as np

from cbh.pipeline.peaks import find_peaks, peak_extent, smooth_gaussian, valley_cuts
from cbh.pipeline import threads as _threads
from cbh.pipeline.threads import pfold as _pfold, pmap as _pmap

__all__ = ["PlaneMaps", "PlaneViews", "zncc_map", "plane_maps", "sweep_matches", "zncc_planes", "coarse_planes",
           "coarse_votes", "coarse_regions", "coarse_pass",
           "fine_planes", "fine_pass", "SweepField", "PlaneLattice", "plane_lattice", "sweep_field", "field_points",
           "label_pass", "refine_pass", "parallax_reach", "reach_levels", "truncated", "resolved_layers", "regional_peaks", "coarse_layers", "CoarseLayers", "FineCost", "LayerLabels"]

_OUTSIDE = -1.0e5
_REGION_CACHE = 8  # regions whose cut tables PlaneMaps keeps
_REGION_LOCK = threading.Lock()
_BAND_ROWS = 64  # the fine pass scores bands of about this many half-resolution rows (_ZnccBand)
_COL_HALO = 16  # a band's columns start on a multiple of this, and end this much past its halo (_ZnccBand)
_SRC_SCALE = 64.0  # image 2 enters the sweep's remap as uint16 in 1/64 grey levels (see _HalfZncc)
_MAX_GROW = 4.0  # far layers: aggregation box at most this × aggregate_px
#: a grown box (oblique levels) whose best plane lies farther from its layer box's than this shift of
#: camera 2's pixel (planes apart × the pixel's reach, a plane step being ≈ 1 px at full reach) has
#: summed another deck's costs (two decks in one label range): the pixel keeps its layer box's u [px]
_GROWN_APART_PX = 1.0
_REACH_SPLIT = 0.5 ** 0.5  # oblique pixels: a layer's box grown 2× below this reach (the geometric middle of 1×
#                             and 2×), and 2× again below each further half [1] (refine_pass)
_VOTE_SMOOTH_BINS = 0.5  # Gaussian smoothing of the fine vote histogram [bins of half a plane step]
_REGION_APART_BINS = 3  # a region's layer is a new one beyond 1.5 plane steps from the image's [bins of half a step]
_MAX_STEP = 1.25  # PlaneLattice: fine planes at most this × step_px apart (see there)
_COARSE_SHARE = 2.5  # the coarse pass's regions are a quarter of the fine ones: their peak needs this × region_share
_OWN_SMOOTH_PLANES = 0.5  # Gaussian smoothing of a region's own-plane votes (:func:`own_plane_peaks`) [planes]
_REGION_MIN_FILL = 0.25  # a region proposes layers when this share of its cells vote [1]


@dataclass
class PlaneMaps:
    """Camera-2 pixel of each camera-1 pixel as a cubic in s = 1/(h − o1z).

    Attributes
    ----------
    m0, a, b : ndarray, shape (H1, W1, 2), float32
        ``p2(s) = m0 + a·s + b·s² + c·s³`` [px, px·m, px·m², px·m³]; m0 = _OUTSIDE, a = b = c = 0
        where camera 2 cannot see the pixel's ray at s = 0, s_a or 2·s_a.
    s_a : float
        Anchor [1/m].
    scale_px : float
        Largest ``|a|`` over valid pixels: parallax in pixels per unit s [px·m].
    c : ndarray, shape (H1, W1, 2), float32, or None
        The cubic term (None: a quadratic; 0 where camera 2 cannot see the ray at 3·s_a).
    """

    m0: np.ndarray
    a: np.ndarray
    b: np.ndarray
    s_a: float
    scale_px: float
    c: "np.ndarray | None" = None

    @property
    def terms(self) -> tuple:
        """(m0, a, b) or (m0, a, b, c): the polynomial's coefficients, lowest first."""
        return (self.m0, self.a, self.b) if self.c is None else (self.m0, self.a, self.b, self.c)

    def at(self, s: float, sl=np.s_[:, :], rows: slice = np.s_[:], cols: slice = np.s_[:]) -> tuple[np.ndarray, np.ndarray]:
        """Remap tables (map_x, map_y) (h, w) float32 for one plane, on the region ``sl`` (of it,
        only the ``rows`` and ``cols``, counted from the region's first: a band of the region).

        With planes kept (:meth:`keep_planes`), views of the plane's whole-image tables, computed
        once and then reused by later pairs (the planes lie on a fixed lattice of s); else
        computed on the region."""
        root = self.__dict__.get("_kept_root")
        kept = _KEPT
        if root is None or not root["active"] or kept.max_bytes <= 0:
            return self._tables_at(s, sl, rows, cols)
        key = (root["id"], self.__dict__.get("_kept_tag", ()), float(s))
        full = kept.get(key)
        if full is None:
            if not kept.make_room(2 * self.m0.shape[0] * self.m0.shape[1] * 4):
                return self._tables_at(s, sl, rows, cols)  # no room without evicting the last sweeps' own planes
            full = self._tables_at(s, np.s_[:, :])
            for a in full:
                a.flags.writeable = False  # shared by every later pair: nobody writes into them
            kept.put(key, full)
        return full[0][sl][rows, cols], full[1][sl][rows, cols]

    def warm(self, sl) -> None:
        """Build what :meth:`at` will read on the region ``sl``: its cut of the polynomial's
        tables, unless this mapping keeps its planes (then only whole-image tables are read)."""
        root = self.__dict__.get("_kept_root")
        if root is None or not root["active"] or _KEPT.max_bytes <= 0:
            self._region_tables("merged", sl)

    def _tables_at(self, s: float, sl, rows: slice = np.s_[:], cols: slice = np.s_[:]) -> tuple[np.ndarray, np.ndarray]:
        tx, ty = self._region_tables("merged", sl)  # (h, w, 3 or 4) tables (m0, a, b[, c]) per axis
        coef = np.array([[float(s) ** k for k in range(tx.shape[2])]])  # one pass per axis: m0 + a·s + b·s² + c·s³
        return cv2.transform(tx[rows, cols], coef), cv2.transform(ty[rows, cols], coef)

    def keep_planes(self, max_mb: float) -> None:
        """Keep the whole-image remap tables of the planes used, within ``max_mb`` MB for the
        whole process (every mapping and its downsampled versions share one store; the latest
        sweep's budget holds; 0 = off for this mapping, the others unchanged).

        Building a plane's tables (one pass over the (h, w, 4) cubic per axis) is a third of
        a fine plane's ZNCC (measured 7.7 → 5.4 ms per plane at 960 px, one thread), and the
        planes of the sweep lie on a lattice fixed per station (the coarse ones, the far range,
        each layer's ±1.5 coarse steps), so the next pair asks for the same ones. At 960 px a
        fine plane takes 7.4 MB, a coarse one 1.8 MB; a pair needs 150–400 MB (17–48 fine planes).

        Called once per sweep; the budget applies from the second sweep on, so a one-shot
        ``cbh pair`` neither builds whole-image tables nor holds them."""
        root = self._kept_state()
        with _REGION_LOCK:
            first = root["sweeps"] == 0
            root["sweeps"] += 1
        budget = int(max(float(max_mb), 0.0) * 1e6)
        root["active"] = not first and budget > 0
        if root["active"]:
            _KEPT.resize(budget)
        _KEPT.new_sweep()

    def _kept_state(self) -> dict:
        """This mapping's entry in the store (shared with its downsampled versions): a process-wide
        unique id (never reused, unlike ``id()``), its sweeps so far, whether it keeps planes."""
        with _REGION_LOCK:
            return self.__dict__.setdefault("_kept_root", {"id": next(_KEPT_IDS), "sweeps": 0, "active": False})

    def _region_tables(self, kind: str, sl):
        """The tables cut to a region, cached (a few regions: pairs processed side by side each
        have their own; thread-safe: an entry is built before it is published, never changed)."""
        key = (kind,) + tuple((x.start, x.stop, x.step) for x in sl)
        cache = self.__dict__.setdefault("_regions", {})
        hit = cache.get(key)
        if hit is not None:
            return hit
        cut = [[np.ascontiguousarray(m[sl + (k,)]) for m in self.terms] for k in (0, 1)]
        val = [cv2.merge(c) for c in cut] if kind == "merged" else cut
        with _REGION_LOCK:
            while len(cache) >= _REGION_CACHE:
                cache.pop(next(iter(cache)))
            cache[key] = val
        return val

    def points(self, s: np.ndarray, yi: np.ndarray, xi: np.ndarray) -> np.ndarray:
        """Camera-2 pixels (N, 2) float64 at per-pixel s (N,) for camera-1 pixels (yi, xi).

        Evaluated in float32 (the tables' precision; 6e-5 px at 1000 px), returned as float64.
        """
        w = self.m0.shape[1]
        idx = np.asarray(yi, np.int64) * w + np.asarray(xi, np.int64)  # flat gathers: ~3× faster
        s = np.asarray(s, np.float32)[:, None]
        terms = [m.reshape(-1, 2)[idx] for m in self.terms]
        v = terms[-1]
        for m in terms[-2::-1]:  # Horner: ((c·s + b)·s + a)·s + m0
            v *= s
            v += m
        return v.astype(np.float64)

    def pixels(self, s: np.ndarray, sl) -> tuple[np.ndarray, np.ndarray]:
        """Remap tables (map_x, map_y) (h, w) float32 on the region ``sl`` for a per-pixel s (h, w)
        float32; where s is NaN (no plane) the pixel maps far outside (``_OUTSIDE``)."""
        s = np.asarray(s, np.float32)
        out = []
        for terms in self._region_tables("split", sl):
            v = terms[-1]
            for m in terms[-2::-1]:  # Horner: ((c·s + b)·s + a)·s + m0
                v = cv2.add(cv2.multiply(v, s), m)
            cv2.patchNaNs(v, _OUTSIDE)  # in place
            out.append(v)
        return out[0], out[1]

    def downsampled(self, factor: int) -> "PlaneMaps":
        """The same mapping between images downsampled by an integer ``factor`` (INTER_AREA; cached;
        it keeps its planes in this mapping's budget, :meth:`keep_planes`)."""
        cache = self.__dict__.setdefault("_down", {})
        if factor not in cache:
            d = self._downsampled(factor)
            d.__dict__.update(_kept_root=self._kept_state(), _kept_tag=self.__dict__.get("_kept_tag", ()) + (factor,))
            cache[factor] = d
        return cache[factor]

    def _downsampled(self, factor: int) -> "PlaneMaps":
        def rs(m):
            return _area_down(m, factor)

        m0 = rs(self.m0)
        bad = m0[..., 0] < -1.0e3
        m0 = (m0 + 0.5) / factor - 0.5
        a, b = rs(self.a) / factor, rs(self.b) / factor
        c = None if self.c is None else rs(self.c) / factor
        m0[bad], a[bad], b[bad] = _OUTSIDE, 0.0, 0.0
        if c is not None:
            c[bad] = 0.0
            c = c.astype(np.float32)
        return PlaneMaps(m0.astype(np.float32), a.astype(np.float32), b.astype(np.float32), self.s_a, self.scale_px / factor,
                         c)


class _KeptPlanes:
    """Whole-image remap tables of recently used planes, within a byte budget: one store per
    process (``_KEPT``), shared by every :class:`PlaneMaps` and its downsampled versions (keys:
    the mapping's id, its downsampling factors, s); thread-safe (an entry is complete and
    read-only before it is published, and never changed).

    Least recently used out first, but never a plane that this sweep or the one before used:
    with a budget smaller than a sweep's planes, the kept ones stay and the rest are computed on
    their region as without the cache (plain LRU, over planes used in turn, would evict every
    plane before its next use); planes no sweep asked for since go when new ones need room."""

    def __init__(self):
        self.max_bytes = 0
        self.bytes = 0
        self.sweep = 0
        self.items: OrderedDict = OrderedDict()  # key → (tables, sweep that last used it), oldest use first
        self.lock = threading.Lock()

    def new_sweep(self) -> None:
        with self.lock:
            self.sweep += 1

    def get(self, key):
        with self.lock:
            hit = self.items.get(key)
            if hit is None:
                return None
            self.items[key] = (hit[0], self.sweep)
            self.items.move_to_end(key)
            return hit[0]

    def make_room(self, n: int) -> bool:
        """Evict planes unused by this sweep and the one before until ``n`` more bytes fit;
        whether they do."""
        with self.lock:
            return self._evict(self.max_bytes - n, keep_recent=True)

    def put(self, key, v) -> None:
        n = sum(a.nbytes for a in v)
        with self.lock:
            if key not in self.items and self._evict(self.max_bytes - n, keep_recent=True):
                self.items[key] = (v, self.sweep)
                self.bytes += n

    def resize(self, max_bytes: int) -> None:
        with self.lock:
            self.max_bytes = int(max_bytes)
            self._evict(self.max_bytes, keep_recent=False)

    def _evict(self, limit: int, keep_recent: bool) -> bool:
        while self.items and self.bytes > limit:
            key, (old, used) = next(iter(self.items.items()))
            if keep_recent and used >= self.sweep - 1:
                break  # entries are in order of last use: every later one is as recent
            del self.items[key]
            self.bytes -= sum(a.nbytes for a in old)
        return self.bytes <= limit


_KEPT = _KeptPlanes()  # the process's kept plane tables (PlaneMaps.keep_planes)
_KEPT_IDS = itertools.count(1)


@dataclass(frozen=True)
class PlaneViews:
    """Camera 2's image per plane of the sweep: plane s is matched against ``images[k]``,
    ``k = searchsorted(cuts_s, s, side="right")``.

    One image for every plane is the plain sweep. With a clock offset, each image is camera 2
    moved back to camera 1's time with the motion of one height (one node of the motion
    profile, :func:`cbh.pipeline.motion.shifted_images`), and each plane takes the image of the
    node nearest its height (:meth:`nearest`): the sweep's parallax for plane H then includes
    the shift ``w(H)·δ`` of the layer whose height is H.

    That leaves one ambiguity a single pair cannot resolve: a cloud of layer L seen through
    layer M's image is shifted by ``(w_M − w_L)·δ``, and where that shift runs along the
    baseline, L's texture matches perfectly on a plane of M's range (two-layers scene, 3 s: the
    1200 m layer at ≈ 2100 m through the 3500 m layer's image). Camera 1's own motion tells the
    two apart: the hypothesis "at height H" also says "moving with H's wind", so each pixel's
    score on the planes of node k is multiplied by ``weights[k]``, how well node k's motion
    explains the pixel in camera 1 (:func:`cbh.pipeline.motion.motion_weights`).

    Attributes
    ----------
    images : tuple of ndarray (H2, W2)
        Camera 2's images, in ascending s (descending height).
    cuts_s : ndarray, shape (len(images) − 1,), float64
        Ascending boundaries in s = 1/(h − o1z) [1/m].
    weights : tuple of ndarray (H1 // 2, W1 // 2) float32, or None
        Each node's weight in [0, 1] per 2 × 2 block of camera 1's working grid, in the order of
        ``images``; None: every weight 1.
    scale : int
        The images are the working-size ones downsampled by this whole factor (:meth:`map`).
    """

    images: tuple
    cuts_s: np.ndarray = field(default_factory=lambda: np.zeros(0))
    weights: tuple | None = None
    scale: int = 1

    @classmethod
    def single(cls, image: np.ndarray) -> "PlaneViews":
        """The same image for every plane."""
        return cls((image,), np.zeros(0))

    @classmethod
    def nearest(cls, images, heights_m, o1z: float, weights=None) -> "PlaneViews":
        """Each plane takes the image of the height (above the ENU origin [m]) nearest to its
        own in ln(h − o1z): the cuts lie at the geometric means of neighbouring heights.
        ``images`` and ``weights`` (optional) in the order of ``heights_m``."""
        hz = np.maximum(np.asarray(heights_m, np.float64) - o1z, 1.0)
        order = np.argsort(1.0 / hz, kind="stable")  # ascending s
        s = 1.0 / hz[order]
        wt = None if weights is None else tuple(weights[int(i)] for i in order)
        return cls(tuple(images[int(i)] for i in order), np.sqrt(s[:-1] * s[1:]), wt)

    def index(self, s: float) -> int:
        """Index of the image to match plane ``s`` [1/m] against."""
        return int(np.searchsorted(self.cuts_s, s, side="right")) if len(self.images) > 1 else 0

    def for_plane(self, s: float) -> np.ndarray:
        """The image to match plane ``s`` [1/m] against."""
        return self.images[self.index(s)]

    def map(self, fn, factor: int = 1) -> "PlaneViews":
        """These views with ``fn`` applied to every image; ``factor``: ``fn`` downsamples by it."""
        return PlaneViews(tuple(fn(im) for im in self.images), self.cuts_s, self.weights, self.scale * int(factor))

    def weights_on(self, sl, shape: tuple[int, int]) -> list | None:
        """Each node's weights on a half-resolution grid of these images: block i of the region
        ``sl`` (2 × 2 pixels of the images from ``sl``'s start), ``shape`` (h/2, w/2) float32;
        None without weights."""
        if self.weights is None or len(self.images) < 2:
            return None
        out = []
        y0, x0 = sl[0].start // 2, sl[1].start // 2
        for wt in self.weights:
            wd = _area_down(wt, self.scale) if self.scale > 1 else wt
            cut = wd[y0: y0 + shape[0], x0: x0 + shape[1]]
            pad = (shape[0] - cut.shape[0], shape[1] - cut.shape[1])
            if pad[0] or pad[1]:
                cut = cv2.copyMakeBorder(cut, 0, pad[0], 0, pad[1], cv2.BORDER_REPLICATE)
            out.append(np.ascontiguousarray(cut, np.float32))
        return out


def zncc_map(i1: np.ndarray, i2: np.ndarray, window_px: int, mu1=None, var1=None) -> np.ndarray:
    """ZNCC of two images on one grid over a ``window_px`` box (h, w) float32 in [−1, 1] (0 where
    either window is flat): (E[i1·i2] − μ1·μ2) / sqrt(var1·var2 + 1e-3). ``mu1``, ``var1``: image
    1's box mean and variance when already known (the sweep's planes share them)."""
    k = int(window_px)
    i1, i2 = np.asarray(i1, np.float32), np.asarray(i2, np.float32)
    if mu1 is None:
        mu1 = _box(i1, k)
        var1 = cv2.max(cv2.subtract(cv2.sqrBoxFilter(i1, cv2.CV_32F, (k, k), borderType=cv2.BORDER_REFLECT_101),
                                    cv2.multiply(mu1, mu1)), 0.0)
    mu2 = _box(i2, k)
    var2 = cv2.max(cv2.subtract(cv2.sqrBoxFilter(i2, cv2.CV_32F, (k, k), borderType=cv2.BORDER_REFLECT_101),
                                cv2.multiply(mu2, mu2)), 0.0)
    cov = cv2.subtract(_box(cv2.multiply(i1, i2), k), cv2.multiply(mu1, mu2))
    return cv2.divide(cov, cv2.sqrt(cv2.add(cv2.multiply(var1, var2), 1e-3)))


def _as_views(gray2) -> PlaneViews:
    return gray2 if isinstance(gray2, PlaneViews) else PlaneViews.single(gray2)


def plane_maps(cam1, cam2, rays1_world: np.ndarray) -> PlaneMaps:
    """Build :class:`PlaneMaps` for two cameras (working size) and camera 1's ENU rays (H, W, 3)."""
    h, w = rays1_world.shape[:2]
    d = rays1_world.reshape(-1, 3).astype(np.float64)
    base = np.asarray(cam2.position_m, np.float64) - np.asarray(cam1.position_m, np.float64)
    blen = float(np.linalg.norm(base))
    s_a = 0.1 / max(blen, 1e-6)
    maps, seen = [], []
    for s in (0.0, s_a, 2.0 * s_a, 3.0 * s_a):
        p = cam2.direction_to_pixel(d - s * d[:, 2:3] * base[None, :])
        good = np.isfinite(p).all(axis=1)
        good[good] = cam2.model.contains(p[good])
        seen.append(good)
        maps.append(np.nan_to_num(p, nan=0.0))
    ok = (d[:, 2] > 1e-3) & seen[0] & seen[1] & seen[2]
    p0, p1, p2, p3 = maps
    # Newton's forward differences in t = s / s_a: p0 + t·Δ1 + t(t−1)/2·Δ2 + t(t−1)(t−2)/6·Δ3, expanded
    d1, d2 = p1 - p0, p2 - 2.0 * p1 + p0
    d3 = np.where(seen[3][:, None], p3 - 3.0 * p2 + 3.0 * p1 - p0, 0.0)  # (no 4th node: the quadratic)
    a = (d1 - d2 / 2.0 + d3 / 3.0) / s_a
    b = (d2 / 2.0 - d3 / 2.0) / (s_a * s_a)
    c = d3 / (6.0 * s_a ** 3)
    p0[~ok], a[~ok], b[~ok], c[~ok] = _OUTSIDE, 0.0, 0.0, 0.0
    scale = float(np.linalg.norm(a[ok], axis=1).max()) if ok.any() else 1.0
    f32 = lambda m: m.reshape(h, w, 2).astype(np.float32)  # noqa: E731
    return PlaneMaps(f32(p0), f32(a), f32(b), s_a, scale, f32(c))


def _box(img, k):
    return cv2.boxFilter(img, -1, (k, k), normalize=True, borderType=cv2.BORDER_REFLECT_101)


def _zncc_iter(i1: np.ndarray, gray2, maps: PlaneMaps, s_values: np.ndarray, window_px: int, sl):
    """Yield (std1, None) once, then (j, score (h, w) float32) for every plane ``s_values[j]``
    (``gray2``: an image or :class:`PlaneViews`, whose weights are brought to full resolution).

    All per-pixel arithmetic goes through OpenCV (multi-threaded, no numpy temporaries):
    :func:`zncc_map` over a ``window_px`` box.
    """
    views = _as_views(gray2)
    k = int(window_px)
    mu1 = _box(i1, k)
    var1 = cv2.max(cv2.subtract(cv2.sqrBoxFilter(i1, cv2.CV_32F, (k, k), borderType=cv2.BORDER_REFLECT_101), cv2.multiply(mu1, mu1)), 0.0)
    h, w = i1.shape
    half = views.weights_on(sl, (-(-h // 2), -(-w // 2)))
    weight = None if half is None else [cv2.resize(x, (2 * x.shape[1], 2 * x.shape[0]),
                                                   interpolation=cv2.INTER_NEAREST)[:h, :w] for x in half]
    yield cv2.sqrt(var1), None
    for j, s in enumerate(s_values):
        mx, my = maps.at(float(s), sl)
        v = views.index(float(s))
        wimg = cv2.remap(views.images[v], mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        score = zncc_map(i1, wimg, k, mu1, var1)
        yield j, (score if weight is None else cv2.multiply(score, weight[v]))


def zncc_planes(gray1: np.ndarray, gray2, maps: PlaneMaps, s_values: np.ndarray, window_px: int,
                sl=np.s_[:, :]) -> tuple[np.ndarray, np.ndarray]:
    """ZNCC of image 1 against image 2 mapped through each plane, on the region ``sl``.

    Parameters
    ----------
    gray1 : ndarray, shape (H1, W1), float32
    gray2 : ndarray, shape (H2, W2), float32, or PlaneViews of such images
    maps : PlaneMaps (at the same size as the images)
    s_values : ndarray, shape (P,), float [1/m]
    window_px : int, odd

    Returns
    -------
    scores : ndarray, shape (P, h, w), float32
        ZNCC in [-1, 1] (0 where either window is flat).
    std1 : ndarray, shape (h, w), float32
        Grey-level standard deviation of image 1 in each window.
    """
    i1 = np.ascontiguousarray(gray1[sl], np.float32)
    it = _zncc_iter(i1, _as_views(gray2).map(lambda g: np.asarray(g, np.float32)), maps, s_values, window_px, sl)
    std1, _ = next(it)
    out = np.empty((len(s_values),) + i1.shape, np.float32)
    for j, score in it:
        out[j] = score
    return out, std1


def _bbox(mask: np.ndarray, pad: int, even: bool = False, align: int = 1):
    """Bounding box of ``mask`` grown by ``pad``; ``even``: start and size even (for 2× pooling);
    ``align``: start and size multiples of ``align`` (within the image's last whole multiple)."""
    ys, xs = np.nonzero(mask.any(axis=1))[0], np.nonzero(mask.any(axis=0))[0]
    h, w = mask.shape
    y0, y1 = max(ys[0] - pad, 0), min(ys[-1] + pad + 1, h)
    x0, x1 = max(xs[0] - pad, 0), min(xs[-1] + pad + 1, w)
    if align > 1:
        y0, x0 = y0 - y0 % align, x0 - x0 % align
        y1 = min(y0 + -(-(y1 - y0) // align) * align, h - h % align)
        x1 = min(x0 + -(-(x1 - x0) // align) * align, w - w % align)
    elif even:
        y0, x0 = y0 - y0 % 2, x0 - x0 % 2
        y1 = min(y1 + (y1 - y0) % 2, h - (h - y0) % 2)
        x1 = min(x1 + (x1 - x0) % 2, w - (w - x0) % 2)
    return np.s_[int(y0): int(y1), int(x0): int(x1)]


def _area_down(img: np.ndarray, f: int) -> np.ndarray:
    """Mean of each f × f block, (h, w) → (h // f, w // f): a last partial row or column of blocks
    is dropped (as torch's ``avg_pool2d``), so pixel (i, j) is exactly the block (f·i … f·i + f − 1):
    resizing an odd size instead would stretch the image by up to a pixel (OpenCV's exact
    INTER_AREA path for whole factors)."""
    h, w = img.shape[:2]
    if h % f or w % f:
        img = img[: h - h % f, : w - w % f]
    return cv2.resize(img, (w // f, h // f), interpolation=cv2.INTER_AREA)


def _pool2(img: np.ndarray) -> np.ndarray:
    """Mean of each 2 × 2 block, (h, w) → (h // 2, w // 2) (:func:`_area_down` by 2)."""
    return _area_down(img, 2)


class _HalfZncc:
    """ZNCC at half the resolution of the region ``sl``: ``std1`` (h/2, w/2) of image 1, and
    ``self(s)`` → score (h/2, w/2) float32 of the plane s. Thread-safe: the region's plane tables
    are built here, and each call only reads shared arrays.

    Half-resolution pixel i stands for the 2 × 2 block of working pixels (2i, 2i + 1) of the
    region (h, w even), and its window is the 2k × 2k square (k = ``half_window``) centred on
    that block. A box sum over such a window is a k × k box sum over 2 × 2 block sums, so the
    products (w, w², i1·w) are pooled once at full resolution (the remap and two multiplies are
    all that runs there) and the box filters and the ZNCC arithmetic run on a quarter of the
    pixels: ≈ 3× less per plane than a full-resolution ZNCC pooled afterwards (measured 2.3 vs
    6.8 ms per plane on an 860 px region, 2 cores). For odd k the blocks are the region's own
    (OpenCV's box is centred); for even k its box covers blocks i − k/2 … i + k/2 − 1, so the
    blocks are taken one pixel in (rows and columns 1 … h − 2), which centres the window on
    block i again; the last row and column (no full window) repeat their neighbours.
    """

    def __init__(self, i1: np.ndarray, gray2, maps: PlaneMaps, half_window: int, sl):
        k = self.k = int(half_window)
        self.off = 1 - k % 2
        h, w = i1.shape
        if self.off:
            i1 = np.ascontiguousarray(i1[1: h - 1, 1: w - 1])
            sl = np.s_[sl[0].start + 1: sl[0].stop - 1, sl[1].start + 1: sl[1].stop - 1]
        self.i1, self.maps, self.sl = i1, maps, sl
        # image 2 as uint16 in 1/64 grey levels: exact for uint8 images and their 2 × 2 … 8 × 8 block
        # means; the remap reads half the bytes of float32 (a 960 px image then stays in cache: the
        # plane maps of a yawed camera read it along diagonals) and rounds its output to 1/64 grey
        # level (std 0.005, against 0.29 for the 8-bit quantisation of the image itself)
        # (``gray2``: one image, or PlaneViews: each plane's own, see PlaneViews)
        self.src2 = _as_views(gray2).map(lambda g: np.rint(np.asarray(g, np.float32) * _SRC_SCALE).astype(np.uint16))
        self.mu1 = _box(_pool2(i1), k)
        self.var1 = cv2.max(cv2.subtract(_box(_pool2(cv2.multiply(i1, i1)), k), cv2.multiply(self.mu1, self.mu1)), 0.0)
        self.std1 = self._grow(cv2.sqrt(self.var1))
        self.factor = self.src2.weights_on(sl, self.std1.shape)  # each node's motion weight (PlaneViews)
        maps.warm(sl)  # before any thread asks for a plane

    def _grow(self, a):  # (h/2 − 1, w/2 − 1) → (h/2, w/2)
        return cv2.copyMakeBorder(a, 0, 1, 0, 1, cv2.BORDER_REPLICATE) if self.off else a

    def __call__(self, s: float) -> np.ndarray:
        mx, my = self.maps.at(float(s), self.sl)
        j = self.src2.index(float(s))
        w2 = cv2.remap(self.src2.images[j], mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        score = self._score(w2.astype(np.float32))  # in 1/_SRC_SCALE grey levels: ZNCC is gain-invariant
        return score if self.factor is None else cv2.multiply(score, self.factor[j])

    def _score(self, w2: np.ndarray) -> np.ndarray:
        """ZNCC (h/2, w/2) of image 1 against ``w2`` (float32 on the region's grid, in 1/_SRC_SCALE
        grey levels; eps scaled alike)."""
        return self._grow(_zncc_blocks(self.k, self.i1, self.mu1, self.var1, w2))

    def bands(self, need: np.ndarray | None = None) -> list["_ZnccBand"]:
        """The region's half-resolution rows cut into bands (:func:`_band_cuts`), each scored on
        its own (:class:`_ZnccBand`); with ``need`` ((h/2, w/2) bool, the grown grid), each only
        between its first and last column that needs a score, and a band that needs none is left
        out."""
        out = (_ZnccBand(self, a, b, need) for a, b in _band_cuts(self.mu1.shape[0]))
        return [b for b in out if b.cols is not None]


def _zncc_blocks(k: int, i1: np.ndarray, mu1: np.ndarray, var1: np.ndarray, w2: np.ndarray) -> np.ndarray:
    """ZNCC per 2 × 2 block over 2k × 2k windows (h/2, w/2) float32 of image 1 (``i1``, its block
    window means ``mu1`` and variances ``var1``) against ``w2`` (:class:`_HalfZncc`)."""
    mu2 = _box(_pool2(w2), k)
    var2 = cv2.max(cv2.subtract(_box(_pool2(cv2.multiply(w2, w2)), k), cv2.multiply(mu2, mu2)), 0.0)
    cov = cv2.subtract(_box(_pool2(cv2.multiply(i1, w2)), k), cv2.multiply(mu1, mu2))
    den = cv2.sqrt(cv2.add(cv2.multiply(var1, var2), 1e-3 * _SRC_SCALE ** 2))
    # clamped to [−1, 1]: in a flat window of image 2 (var2 ≈ 0), the running box sums' float32
    # rounding left cov ≫ √(var1·var2): scores up to 12.6 in 2 of 2·10⁵ blocks, which then won
    return cv2.min(cv2.max(cv2.divide(cov, den), -1.0), 1.0)


class _ZnccBand:
    """The scores of :class:`_HalfZncc` on a band of its half-resolution rows, ``rows`` (of the
    grown grid, its ``std1``), computed on that band of the region alone: bit for bit the same
    numbers (the band is read with a halo of k // 2 + 1 half rows on each side, one more than the
    box filter reaches; OpenCV's float box filter sums in double).

    Why: a plane's score is some fifteen passes over the region (remap, products, 2 × 2 pools,
    box filters, the ZNCC arithmetic); over a whole 880 px region each pass streams its arrays
    through memory, over a band of ~110 rows they stay in the core's cache from one pass to the
    next, and a band's strip of camera 2 stays there from one plane to the next (measured: the
    scores of the two-layers pair's 17 fine planes alone, 80 → 54 ms on one thread, ≈ 41 → 36 ms
    on two; the whole fine pass in the pipeline, one thread, 78–85 → 59–61 ms).
    """

    def __init__(self, z: "_HalfZncc", a: int, b: int, need: np.ndarray | None = None):
        (hh, ww), halo = z.mu1.shape, z.k // 2 + 1  # the ungrown half-resolution grid; the box reaches k // 2
        pad_row = int(z.off and b == hh)  # the grown grid's last row (last band)
        self.rows = slice(a, b + pad_row)
        c0, c1, pad_col = 0, ww, int(z.off)  # ungrown columns scored; the grown grid's last column
        if need is not None:
            cols = np.flatnonzero(need[self.rows].any(axis=0))
            if cols.size == 0:
                self.cols = None
                return
            c0, c1, pad_col = int(cols[0]), min(int(cols[-1]) + 1, ww), int(z.off and cols[-1] >= ww)
        a0, b0 = max(a - halo, 0), min(b + halo, hh)
        # columns: OpenCV's vector loops leave a row's last few outputs to scalar code, whose
        # rounding differs (the 2 × 2 pool of w2², 1 ulp); so a band starts on a multiple of
        # _COL_HALO and ends at the region's end (the same last columns) or _COL_HALO past its halo
        x0 = max(c0 - halo, 0) // _COL_HALO * _COL_HALO
        x1 = c1 + halo + _COL_HALO
        x1 = ww if x1 >= ww else x1
        self.z, self.crop = z, np.s_[a - a0: b - a0, c0 - x0: c1 - x0]
        self.i1 = np.ascontiguousarray(z.i1[2 * a0: 2 * b0, 2 * x0: 2 * x1])
        self.mu1, self.var1 = (np.ascontiguousarray(m[a0: b0, x0: x1]) for m in (z.mu1, z.var1))
        self.region_rows, self.region_cols = slice(2 * a0, 2 * b0), slice(2 * x0, 2 * x1)  # of z's region
        self.pad = (pad_row, pad_col)
        self.cols = slice(c0, c1 + pad_col)

    def __call__(self, s: float) -> np.ndarray:
        """Score (rows, cols) of the plane s on the band's :attr:`rows` and :attr:`cols` of the grown grid."""
        z = self.z
        mx, my = z.maps.at(float(s), z.sl, self.region_rows, self.region_cols)
        j = z.src2.index(float(s))
        w2 = cv2.remap(z.src2.images[j], mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        score = _zncc_blocks(z.k, self.i1, self.mu1, self.var1, w2.astype(np.float32))[self.crop]
        if self.pad[0] or self.pad[1]:
            score = cv2.copyMakeBorder(score, 0, self.pad[0], 0, self.pad[1], cv2.BORDER_REPLICATE)
        return score if z.factor is None else cv2.multiply(score, z.factor[j][self.rows, self.cols])


def _zncc_half_iter(i1: np.ndarray, gray2: np.ndarray, maps: PlaneMaps, s_values: np.ndarray, half_window: int, sl):
    """:class:`_HalfZncc` as a generator: yield (std1 (h/2, w/2), None) once, then (j, score
    (h/2, w/2) float32) for every plane ``s_values[j]``, computed on :func:`~cbh.pipeline.threads.pmap`'s threads."""
    z = _HalfZncc(i1, gray2, maps, half_window, sl)
    yield z.std1, None
    yield from enumerate(_pmap(z, [float(s) for s in s_values]))


class _Best3:
    """Streaming best plane: after ``add(j, score)`` for j = 0, 1, … (consecutive planes),
    ``result()`` = (index j (h, w) int32, its score, score of plane j−1, score of plane j+1).

    OpenCV masked copies; no (P, h, w) stack is needed. Ties keep the first plane.
    ``neighbours=False``: only the index and the score are tracked (left, right are None).
    """

    def __init__(self, neighbours: bool = True):
        self.best = None
        self.neighbours = neighbours
        self.left = self.right = None

    def add(self, j: int, cur: np.ndarray) -> None:
        if self.best is None:
            self.best = cur.copy()
            if self.neighbours:
                self.left, self.right = cur.copy(), cur.copy()
            self.j = np.zeros(cur.shape, np.int32)
            self._q = np.empty(cur.shape, np.int32)
        else:
            if self.neighbours:
                cv2.copyTo(cur, cv2.compare(self.j, j - 1, cv2.CMP_EQ), self.right)
            gt = cv2.compare(cur, self.best, cv2.CMP_GT)
            if self.neighbours:
                cv2.copyTo(self.prev, gt, self.left)
            cv2.copyTo(cur, gt, self.best)
            self._q.fill(j)  # (np.copyto with where= is ~20x slower than OpenCV's masked copy)
            cv2.copyTo(self._q, gt, self.j)
        self.prev = cur

    def result(self):
        return self.j, self.best, self.left, self.right


def _best3(scores, neighbours: bool = True):
    """Best plane index j, its score and the scores of planes j−1 and j+1 of a stack (P, h, w)."""
    b = _Best3(neighbours)
    for q, sc in enumerate(scores):
        b.add(q, sc)
    return b.result()


@dataclass
class _Best3Part:
    """:class:`_Best3`'s result over the consecutive planes lo … hi, with their first and last scores."""

    j: np.ndarray
    best: np.ndarray
    left: np.ndarray | None
    right: np.ndarray | None
    first: np.ndarray
    last: np.ndarray
    lo: int
    hi: int


def _best3_fold(fn, neighbours: bool):
    def fold(chunk, start):
        b, first, sc = _Best3(neighbours), None, None
        for i, item in enumerate(chunk):
            sc = fn(item)
            b.add(i, sc)
            first = sc if first is None else first
        j, best, left, right = b.result()
        if start:
            j += start
        return _Best3Part(j, best, left, right, first, sc, start, start + len(chunk) - 1)
    return fold


def _best3_merge(a: _Best3Part, b: _Best3Part) -> _Best3Part:
    """The two parts of neighbouring plane ranges (a before b) as one: a's winners on its last plane
    get b's first plane as right neighbour, b's on its first get a's last as left; then b's winners
    take the pixels where they score strictly higher (ties keep the first plane, as :class:`_Best3`)."""
    if a.left is not None:
        cv2.copyTo(b.first, cv2.compare(a.j, a.hi, cv2.CMP_EQ), a.right)
        cv2.copyTo(a.last, cv2.compare(b.j, b.lo, cv2.CMP_EQ), b.left)
    gt = cv2.compare(b.best, a.best, cv2.CMP_GT)
    for x, y in ((b.best, a.best), (b.j, a.j)) + (((b.left, a.left), (b.right, a.right)) if a.left is not None else ()):
        cv2.copyTo(x, gt, y)
    return _Best3Part(a.j, a.best, a.left, a.right, a.first, b.last, a.lo, b.hi)


def _best3_map(fn, items, neighbours: bool = True):
    """:func:`_best3` of the scores ``fn(item)`` of consecutive planes ``items``, computed and
    reduced in chunks side by side (:func:`~cbh.pipeline.threads.pfold`; the same result as the
    serial reduction, ties included)."""
    r = _pfold(_best3_fold(fn, neighbours), items, _best3_merge)
    return r.j, r.best, r.left, r.right


def _band_count(rows: int) -> int:
    """Bands of about ``_BAND_ROWS`` half-resolution rows, a whole number per thread (:func:`~cbh.pipeline.threads.workers`)."""
    n = _threads.workers()
    return n * max(1, -(-int(rows) // (n * _BAND_ROWS)))


def _band_cuts(rows: int) -> list[tuple[int, int]]:
    """:func:`_band_count` bands of ``rows`` rows, as equal as can be: [(first, end), …]."""
    n = max(1, min(_band_count(rows), int(rows)))
    cuts = [round(i * rows / n) for i in range(n + 1)]
    return list(zip(cuts[:-1], cuts[1:]))


def _refine(j: np.ndarray, c0: np.ndarray, cm1: np.ndarray, cp1: np.ndarray, s_values: np.ndarray,
            ds: float) -> np.ndarray:
    """s of the score's peak from planes j−1, j, j+1 (where adjacent), float32: :func:`peak_offset`."""
    n = len(s_values)
    gap = np.diff(s_values, prepend=-np.inf, append=np.inf)
    q = np.arange(n)
    adj = ((q > 0) & (q < n - 1) & (gap[:n] < 1.01 * ds) & (gap[1:] < 1.01 * ds))[j]  # per plane, then looked up
    delta = np.where(adj, peak_offset(c0, cm1, cp1), np.float32(0.0))
    return s_values.astype(np.float32)[j] + delta.astype(np.float32) * np.float32(ds)


def peak_offset(c0, cm1, cp1, xp=np):
    """Where a correlation peak lies between three samples one plane apart, in planes from the
    middle one (its best), within ±0.5: the three-point Gaussian estimator — the vertex of the
    parabola through the scores' logarithms — where all three are positive, else the vertex of
    the parabola through the scores (0 where neither curves down).

    Why Gaussian: the ZNCC of a texture against itself shifted by d falls off as the texture's
    autocorrelation, which for cloud detail blurred by the lens and the resampling is close to a
    Gaussian of d; the log-parabola is exact for a Gaussian at any phase between the samples,
    where the parabola pulls the peak towards the nearest plane ("peak locking", the reason
    particle-image velocimetry uses the Gaussian fit). Measured (`bench_vs_opencv.py --deck-m H`:
    one deck of the two-layers texture at H = 600 / 2000 / 5000 / 7000 / 9000 m, 1920 px): dense
    MdAPE 0.15 / 0.40 / 0.78 / 1.07 / 1.60 % with the parabola, 0.13 / 0.38 / 0.57 / 0.71 / 0.93 %
    with this, the signed bias about halved.

    ``xp``: numpy or torch (same arithmetic, float32 arrays or tensors).
    """
    with np.errstate(all="ignore"):  # (logarithms of non-positive scores, zero curvatures: not selected)
        lm, l0, lp = xp.log(cm1), xp.log(c0), xp.log(cp1)
        dg = lm - 2.0 * l0 + lp
        gauss = (c0 > 0) & (cm1 > 0) & (cp1 > 0) & (dg < 0)
        den = cm1 - 2.0 * c0 + cp1
        delta = xp.where(gauss, 0.5 * (lm - lp) / dg, xp.where(den < 0, 0.5 * (cm1 - cp1) / den, xp.zeros_like(c0)))
    return xp.clip(delta, -0.5, 0.5)


# --- the passes ----------------------------------------------------------------------------

@dataclass
class CoarseLayers:
    """Pass 1: layer hypotheses from the coarse votes."""

    s: np.ndarray  # (Pc,) float64: the coarse planes [1/m]
    ds: float  # their spacing [1/m]
    ranges: list[tuple[int, int]]  # index range [lo, hi] of each hypothesis in ``s``
    layers_m: list[float]  # the hypotheses' heights above the ENU origin [m]
    regional: list[tuple[int, int]] = field(default_factory=list)  # ranges of the regions' hypotheses, strongest first


@dataclass
class FineCost:
    """Pass 2: every fine plane's ZNCC at half resolution over the cloud's bounding region."""

    region: tuple  # (slice y, slice x) of the working-size image (even start and size)
    s: np.ndarray  # (P,) float64: the fine planes [1/m], ascending
    ds: float  # their spacing in the lattice coordinate u [1/m] (:class:`PlaneLattice`)
    cost: np.ndarray  # (P, h/2, w/2) float32: ZNCC × textured-cloud fraction of each 2 × 2 block
    textured: np.ndarray  # (h/2, w/2) float32: textured-cloud fraction of each 2 × 2 block
    ok: np.ndarray  # (h, w) bool: accepted pixels (textured cloud whose best ZNCC ≥ min_zncc)
    ok_frac: np.ndarray  # (h/2, w/2) float32: accepted fraction of each 2 × 2 block
    lattice: "PlaneLattice | None" = None  # u(s) of the planes (None: u = s)
    reach: "np.ndarray | None" = None  # (h/2, w/2) float32: each block's :func:`parallax_reach` (None: ``oblique_levels`` off)

    @property
    def u(self) -> np.ndarray:
        """(P,) float64: the planes' lattice coordinate [1/m], ``ds`` apart where they run on."""
        return self.s if self.lattice is None else self.lattice.u(self.s)

    def to_s(self, u):
        """Lattice coordinate → s (arrays or tensors; NaN stays NaN, 0 stays 0)."""
        return u if self.lattice is None else self.lattice.s(u)


@dataclass
class LayerLabels:
    """Pass 3: the layers of the image in s, and the layer of every half-resolution pixel."""

    cuts_s: np.ndarray  # (L − 1,) the boundaries between neighbouring layers, in the planes' lattice coordinate u [1/m]
    votes: np.ndarray  # (B,) vote histogram over u (bins of ``bin_s``)
    bin_s: float  # [1/m of u]
    vote_ranges: list[tuple[int, int]]  # bins [lo, hi] of each layer (they tile the histogram)
    plane_layer: np.ndarray  # (P,) int: the layer of each fine plane
    label: np.ndarray  # (h/2, w/2) uint8: each pixel's layer
    own_plane: np.ndarray  # (h/2, w/2) int32: each pixel's own best plane (no aggregation)
    s_wide: np.ndarray  # (h/2, w/2) float32: u of the wide-box winner, refined [1/m of u]


@dataclass
class CoarsePlanes:
    """The coarse pass's planes: a uniform vote grid ``s`` (``ds`` apart: one pixel of shift at
    1/``coarse_factor`` size) of which the ``far`` ones (parallax up to ``coarse_near_px`` at
    working size) are swept at 1/``coarse_factor`` size and the ``near`` ones (every second grid
    plane beyond, farther apart where ``coarse_near_rel`` of their parallax is more) at
    1/(2·``coarse_factor``) size."""

    s: np.ndarray  # (G,) float64 [1/m], ascending
    ds: float  # [1/m]
    far: np.ndarray  # (Pf,) int: indices into s
    near: np.ndarray  # (Pn,) int: indices into s, ascending; each stands for the grid planes to its neighbours

    def near_weights(self) -> list[tuple[np.ndarray, np.ndarray]]:
        """Each near plane's vote on the grid: (grid indices, weights), a hat from its plane (1/2)
        down to 0 at its neighbouring near planes (the first and last: two grid steps out), so the
        histogram stays uniform in s; with every second grid plane (two steps apart) 1/4, 1/2, 1/4."""
        q = np.asarray(self.near, np.int64)
        out = []
        for i, c in enumerate(q):
            lo = int(q[i - 1]) if i > 0 else int(c) - 2
            hi = int(q[i + 1]) if i + 1 < len(q) else int(c) + 2
            g = np.arange(max(lo + 1, 0), min(hi - 1, len(self.s) - 1) + 1)
            w = np.where(g <= c, (g - lo) / (c - lo), (hi - g) / (hi - c))
            out.append((g, 0.5 * w))
        return out


def coarse_planes(s_min: float, s_max: float, scale_px: float, cfg) -> CoarsePlanes:
    """The coarse planes from ``s_min`` to ``s_max`` for a working-size parallax scale ``scale_px``
    [px·m] (see :class:`CoarsePlanes`).

    Why two sizes: the planes are uniform in s, so the floor of the sweep (100 m) makes most of
    them near planes: at B = 50 m, 96 % of the parallax range lies below 480 m. A near layer's
    parallax is large (32 … 150 px at working size), so one pixel of shift at half the coarse
    size is still a few per cent of its height, which is all a hypothesis needs (the fine pass
    refines it at working size); each such plane costs a quarter, and half as many are needed.

    Why farther apart beyond: the parallax range grows with the baseline (the 100 m floor: 158 px
    at 50 m, 800 px at the real 241 m station), and one pixel at half the coarse size is 0.5 %
    of the height at 800 px, far finer than a hypothesis needs. So the near planes lie
    ``coarse_near_rel`` (3 %) of their parallax apart where that is more than one such pixel
    (beyond 133 px at 960 px working size): their count grows with the logarithm of the parallax
    range instead of with it (241 m: 192 → 93 near planes; 50 m unchanged). A cell's ZNCC peak
    is then sampled more coarsely there; its vote still goes to the nearest plane, spread to the
    neighbouring planes (:meth:`CoarsePlanes.near_weights`), and the fine pass sweeps that extent.
    """
    f = max(int(cfg.coarse_factor), 1)
    ds = float(cfg.coarse_step_px) * f / scale_px
    s = np.arange(s_min, s_max + ds, ds)
    idx = np.arange(len(s))
    if cfg.coarse_near_px <= 0:
        return CoarsePlanes(s, ds, idx, idx[:0])
    k = int(np.searchsorted(s, cfg.coarse_near_px / scale_px, side="right"))
    near, q = [], k + 1
    grid_px = float(cfg.coarse_step_px) * f  # one grid step at working size [px]
    while q < len(s):
        near.append(q)
        q += max(2, int(cfg.coarse_near_rel * s[q] * scale_px / grid_px))
    return CoarsePlanes(s, ds, idx[:k], np.asarray(near, np.int64))


def coarse_votes(plan: CoarsePlanes, cloud: np.ndarray, j_far, c_far, j_near, c_near, min_zncc: float) -> np.ndarray:
    """Votes of the coarse cloud cells on the grid ``plan.s``: each cell of ``cloud`` (h, w) bool
    votes for its best plane, far (``j_far``, ``c_far``: index into ``plan.far`` and ZNCC, (h, w))
    or near (``j_near``, ``c_near``: into ``plan.near``, (h/2, w/2), one cell per 2 × 2 far
    cells), whichever correlates better, when that ZNCC is ≥ ``min_zncc``. A near plane's vote is
    spread over the grid planes it stands for (:meth:`CoarsePlanes.near_weights`: 1/4, 1/2, 1/4
    over q − 1, q, q + 1 where the near planes are two grid steps apart), so the histogram stays
    uniform in s. Either tier may be None (no planes there). Returns (G,) float64."""
    q, near_wins = coarse_cells(plan, cloud, j_far, c_far, j_near, c_near, min_zncc)
    n = len(plan.s)
    votes = np.bincount(q[(q >= 0) & ~near_wins], minlength=n).astype(np.float64)
    qn = q[(q >= 0) & near_wins]
    if qn.size:
        counts = np.bincount(np.searchsorted(plan.near, qn), minlength=len(plan.near))
        for c, (g, w) in zip(counts, plan.near_weights()):
            if c:
                np.add.at(votes, g, c * w)
    return votes


def coarse_cells(plan: CoarsePlanes, cloud: np.ndarray, j_far, c_far, j_near, c_near, min_zncc: float):
    """Each coarse cell's vote (see :func:`coarse_votes`): (index into ``plan.s`` (h, w) int64, −1
    = none; whether it is a near plane's (h, w) bool)."""
    h, w = cloud.shape
    q = np.full((h, w), -1, np.int64)
    if j_near is not None:
        up = lambda a: np.repeat(np.repeat(a, 2, axis=0), 2, axis=1)[:h, :w]  # noqa: E731
        jn, cn = up(j_near), up(c_near)
        near_wins = cn > c_far if c_far is not None else np.ones((h, w), bool)
        best = np.where(near_wins, cn, c_far) if c_far is not None else cn
    else:
        near_wins, best = np.zeros((h, w), bool), c_far
    good = cloud & (best >= min_zncc)
    if j_far is not None:
        q[good & ~near_wins] = plan.far[j_far[good & ~near_wins]]
    if j_near is not None:
        q[good & near_wins] = plan.near[jn[good & near_wins]]
    return q, near_wins


def coarse_regions(cloud1: np.ndarray, plan: CoarsePlanes, cfg):
    """The swept regions and their cloud: (cloud cells (h/2, w/2) bool: 2 × 2 blocks of the region
    at 1/``coarse_factor`` size that are mostly cloud, the region at that size, the region at half
    that size or None). With near planes the region is aligned to 4 pixels, so that each near
    cell covers exactly 2 × 2 far cells. None: no cloud at coarse size."""
    f = max(int(cfg.coarse_factor), 1)
    ccloud = _area_down(cloud1.astype(np.float32), f) >= 0.5 if f > 1 else cloud1
    if not ccloud.any():
        return None
    two = len(plan.near) > 0
    slc = _bbox(ccloud, cfg.coarse_window_px, even=True, align=4 if two else 1)
    if slc[0].stop <= slc[0].start or slc[1].stop <= slc[1].start:
        return None
    half = np.s_[slc[0].start // 2: slc[0].stop // 2, slc[1].start // 2: slc[1].stop // 2] if two else None
    return _pool2(ccloud[slc].astype(np.float32)) >= 0.5, slc, half


def _best_plane(c1: np.ndarray, c2: np.ndarray, maps: PlaneMaps, s: np.ndarray, half_window: int, sl):
    """Best plane (index into ``s``) and its ZNCC per half-resolution cell of region ``sl``."""
    z = _HalfZncc(np.ascontiguousarray(c1[sl]), c2, maps, half_window, sl)
    best, cbest, _, _ = _best3_map(z, [float(x) for x in s], neighbours=False)
    return best, cbest


def coarse_pass(g1: np.ndarray, g2, cloud1: np.ndarray, maps: PlaneMaps, s_min: float, s_max: float,
                o1z: float, cfg) -> CoarseLayers | None:
    """Pass 1: the planes from ``s_min`` to ``s_max`` one coarse pixel apart (:func:`coarse_planes`:
    near ones at half the coarse size); each cloud cell votes for its best plane (ZNCC ≥
    ``min_zncc``, :func:`coarse_votes`); the vote peaks are the layer hypotheses. None: no cloud
    at coarse size. ``g2``: camera 2's image (float32) or :class:`PlaneViews` of such images."""
    f = max(int(cfg.coarse_factor), 1)
    plan = coarse_planes(s_min, s_max, maps.scale_px, cfg)
    reg = coarse_regions(cloud1, plan, cfg)
    if reg is None:
        return None
    cl, slc, half = reg
    c1 = _area_down(g1, f) if f > 1 else g1
    c2 = _as_views(g2).map(lambda g: _area_down(g, f), f) if f > 1 else _as_views(g2)
    k = cfg.coarse_window_px // 2
    j_far = c_far = j_near = c_near = None
    if len(plan.far):
        j_far, c_far = _best_plane(c1, c2, maps.downsampled(f) if f > 1 else maps, plan.s[plan.far], k, slc)
    if half is not None:
        j_near, c_near = _best_plane(_pool2(c1), c2.map(_pool2, 2), maps.downsampled(2 * f), plan.s[plan.near], k, half)
    return coarse_layers(plan, cl, j_far, c_far, j_near, c_near, o1z, cfg)


def coarse_layers(plan: CoarsePlanes, cloud: np.ndarray, j_far, c_far, j_near, c_near, o1z: float,
                  cfg) -> CoarseLayers:
    """The hypotheses of the coarse cells' best planes (:func:`coarse_votes`): the peaks of the
    whole sky's votes, and of each region's (:func:`regional_peaks`, ``region_px`` at working
    size: a deck seen through the gaps of a lower one; :func:`coarse_hypotheses`)."""
    q, near = coarse_cells(plan, cloud, j_far, c_far, j_near, c_near, cfg.min_zncc)
    votes = coarse_votes(plan, cloud, j_far, c_far, j_near, c_near, cfg.min_zncc)
    # regions half as wide as the fine pass's: a hypothesis costs only planes (the fine pass
    # decides), and a gap of a quarter of a fine region still fills much of a coarse one
    side = int(cfg.region_px) // (4 * max(int(cfg.coarse_factor), 1))  # a cell: 2 coarse pixels
    regional = []
    peaks = find_peaks(votes, cfg.min_vote_fraction * float(cloud.sum()), cfg.valley_ratio)
    if side >= 2 and peaks:
        # wanted: above the lowest peak (a deck below it hides nothing: the whole sky's votes count
        # it), outside every peak's extent, and beyond the far range (swept by the fine pass
        # anyway); no test against the whole sky's votes: a hypothesis only adds planes, the fine
        # pass decides
        allowed = np.zeros(len(plan.s), bool)
        allowed[1: max(peaks) - 1] = True
        extents = [peak_extent(votes, p, cfg.extent_ratio) for p in peaks]
        for lo, hi in extents:
            allowed[max(lo - 1, 0): hi + 2] = False
        s_far = cfg.far_px * plan.ds / (float(cfg.coarse_step_px) * max(int(cfg.coarse_factor), 1))
        allowed &= plan.s > s_far
        # above the highest peak's extent no window straddles two decks: a deck there is weighed
        # by its whole peak, whatever its phase between two planes (:func:`regional_peaks`)
        above = np.arange(len(plan.s)) < min(lo for lo, _ in extents) - 1
        if allowed.any():
            regional = regional_peaks(q, np.ones(q.shape), len(plan.s), side, _COARSE_SHARE * cfg.region_share,
                                      _REGION_MIN_FILL * side * side, cfg.valley_ratio, allowed,
                                      by_mass=above)
    return coarse_hypotheses(votes, float(cloud.sum()), plan.s, plan.ds, o1z, cfg, regional)


def coarse_hypotheses(votes: np.ndarray, n_cloud: float, s: np.ndarray, ds_c: float, o1z: float,
                      cfg, regional=()) -> CoarseLayers:
    """Layer hypotheses from the coarse votes (G,) on the planes ``s`` (:func:`coarse_votes`) of
    ``n_cloud`` cloud cells; peaks need ``min_vote_fraction`` of them. ``regional``: the peaks
    of regions ((index, weight), :func:`coarse_layers`); each one above the lowest peak and
    outside every peak's extent is a hypothesis too (its plane ± 1), swept as long as the fine
    planes stay within ``max_planes`` (:func:`fine_planes`)."""
    votes = np.asarray(votes, np.float64)
    peaks = find_peaks(votes, cfg.min_vote_fraction * n_cloud, cfg.valley_ratio)
    ranges = [peak_extent(votes, p, cfg.extent_ratio) for p in peaks]
    extra: list[tuple[int, int]] = []
    if peaks:
        top = max(peaks) - 1
        for b, _ in sorted(regional, key=lambda e: -e[1]):
            if 0 < b < top and all(not lo - 1 <= b <= hi + 1 for lo, hi in ranges + extra):
                extra.append((max(b - 1, 0), min(b + 1, len(s) - 1)))
    return CoarseLayers(s, ds_c, ranges, [float(o1z + 1.0 / s[(lo + hi) // 2]) for lo, hi in ranges + extra], extra)


@dataclass(frozen=True)
class PlaneLattice:
    """The fine planes' lattice coordinate u(s) [1/m]: s itself up to ``s0``, logarithmic from
    ``s0`` to m·``s0`` (u = s0 · (1 + ln(s / s0))), linear with slope 1/m beyond (m =
    ``_MAX_STEP``, 1.25); continuous with its slope. Planes ``ds`` apart in u are ``step_px`` of
    parallax apart up to p0 = ``step_px`` / ``step_rel`` (20 px by default), ``step_rel`` of their
    parallax from p0 to m·p0 (a height step of 5 %, which the parabola through three planes
    refines), and m·``step_px`` beyond: never wider. Why so narrow a cap: a pixel's cost is
    sampled up to half a step off its peak, which lowers the true plane's score against chance
    matches elsewhere, and a flat layer's pixels all sit at one phase between two planes, so the
    parabola's pixel locking does not average out over the layer. Measured: with planes 2 px apart
    a 1500 m deck at B = 241 m (53 px) read 1479 m (−1.4 %); with 1.5 px, 1497 m, but a 480 px
    network's 630 m pairs took a spurious 8.6 km layer (94 points, confidence 0.19) from their
    2500 m deck's pixels; with 1.25 px, 1497 m and no such layer.

    Why (issue 36): a plane one pixel of shift from the next is 1/p of the height apart, so near
    layers and long baselines (large parallax p) were swept finer than their heights need (the
    real 241 m station's 2300 m deck, 30–40 px: 2.5–3.3 % per plane, 11 planes, now 9; the 50 m
    pair's 1200 m deck, 13 px: 7.7 % per plane, unchanged) and a long baseline cost more planes
    per pair. Everything that needs evenly spaced planes (the refinement's peak, the layer
    votes' bins, the regions' plane lattice, the gaps of :func:`truncated`) works in u."""

    s0: float  # [1/m]; inf: u = s everywhere

    def u(self, s):
        s = np.asarray(s, np.float64)
        if not np.isfinite(self.s0):
            return s
        m = _MAX_STEP
        s0, s1 = self.s0, m * self.s0
        u1 = s0 * (1.0 + math.log(m))
        log = s0 * (1.0 + np.log(np.clip(s, s0, s1) / s0))
        return np.where(s <= s0, s, np.where(s <= s1, log, u1 + (s - s1) / m))

    def s(self, u):
        """The inverse of :meth:`u` (numpy arrays keep their dtype; torch tensors go through torch)."""
        if not np.isfinite(self.s0):
            return u
        m = _MAX_STEP
        s0, s1 = self.s0, m * self.s0
        u1 = s0 * (1.0 + math.log(m))
        if type(u).__module__.startswith("torch"):  # a tensor
            import torch

            log = s0 * torch.exp(torch.clamp(u, s0, u1) / s0 - 1.0)
            return torch.where(u <= s0, u, torch.where(u <= u1, log, s1 + m * (u - u1)))
        u = np.asarray(u)
        with np.errstate(invalid="ignore"):
            log = s0 * np.exp(np.clip(u, s0, u1) / s0 - 1.0)
            return np.where(u <= s0, u, np.where(u <= u1, log, s1 + m * (u - u1))).astype(u.dtype, copy=False)


def plane_lattice(scale_px: float, cfg) -> PlaneLattice | None:
    """The :class:`PlaneLattice` of a pair (working-size parallax scale ``scale_px`` [px·m]), or
    None where ``step_rel`` is 0 (planes uniform in s)."""
    rel = float(getattr(cfg, "step_rel", 0.0))
    if rel <= 0 or scale_px <= 0:
        return None
    return PlaneLattice(float(cfg.step_px) / (rel * scale_px))


def fine_planes(coarse: CoarseLayers, scale_px: float, s_min: float, s_max: float, cfg) -> tuple[np.ndarray, float]:
    """The fine planes (ascending s, ``step_px`` apart): the far range from infinity up to
    ``far_px`` of parallax, and each coarse hypothesis's extent ± 1.5 coarse steps; at most
    ``max_planes`` (and the regions' own hypotheses up to ``regional_planes`` more, at the same
    step, strongest first): beyond, the step grows (a whole multiple of ``step_px``) until they fit, so
    that the planes stay evenly spaced — the refinement's peak needs a pixel's neighbouring
    planes one step away (thinning by index left gaps: a 630 m pair's 3500 m layer fell between
    3575 and 3452 m with no plane at 3512 m, and every pixel snapped to 3452 m, −1.4 %).
    The planes are evenly spaced in the lattice coordinate u (:class:`PlaneLattice`): ``step_px``
    apart up to ``step_px`` / ``step_rel`` of parallax, ``step_rel`` of their parallax beyond.
    Returns (s (P,), step ds in u)."""
    base = cfg.step_px / scale_px
    lat = plane_lattice(scale_px, cfg) or PlaneLattice(np.inf)

    def planes(ranges, ds):
        parts = [np.arange(0.0, float(lat.u(min(cfg.far_px / scale_px, s_max))) + 0.5 * ds, ds)]
        for lo, hi in ranges:
            a = float(lat.u(max(coarse.s[lo] - 1.5 * coarse.ds, s_min)))
            b = float(lat.u(min(coarse.s[hi] + 1.5 * coarse.ds, s_max)))
            parts.append(np.arange(a, b + 0.5 * ds, ds))
        return lat.s(np.unique(np.round(np.concatenate(parts) / ds) * ds))

    for k in range(1, 1 << 12):
        ds = base * k
        s = planes(coarse.ranges, ds)
        if len(s) <= cfg.max_planes:
            break
    kept = list(coarse.ranges)
    budget = cfg.max_planes + cfg.regional_planes  # (randomized 19803 at 960 px: a 4825 m deck seen through two
    #                                                lower ones in 7 % of the sky was proposed by its regions and
    #                                                dropped, its range not fitting the 48 planes the image's took)
    for r in coarse.regional:  # the regions' hypotheses, strongest first, while the step stays
        more = planes(kept + [r], ds)
        if len(more) <= budget:
            kept, s = kept + [r], more
    return s, ds


def fine_pass(g1: np.ndarray, g2, cloud1: np.ndarray, maps: PlaneMaps, s: np.ndarray, ds: float,
              cfg) -> FineCost:
    """Pass 2: at working size, each fine plane's ZNCC (``window_px`` rounded up to even) at half
    resolution; a pixel is accepted when it is textured cloud (window grey-level standard
    deviation ≥ ``min_texture``) and its 2 × 2 block's best ZNCC is ≥ ``min_zncc``. Streamed over
    the planes: only the (P, h/2, w/2) cost stack is kept. ``g2``: an image or :class:`PlaneViews`."""
    sl = _bbox(cloud1, cfg.window_px, even=True)
    i1 = np.ascontiguousarray(g1[sl])
    h, w = i1.shape
    k = int(cfg.window_px)
    mu = _box(i1, k)
    var = cv2.max(cv2.subtract(cv2.sqrBoxFilter(i1, cv2.CV_32F, (k, k), borderType=cv2.BORDER_REFLECT_101),
                               cv2.multiply(mu, mu)), 0.0)
    m0 = cloud1[sl] & (var >= float(cfg.min_texture) ** 2)  # textured cloud pixels: the candidates
    textured = _pool2(m0.astype(np.float32))
    z = _HalfZncc(i1, g2, maps, k // 2, sl)
    cost = np.zeros((len(s), h // 2, w // 2), np.float32)  # (0 wherever no candidate: no band computes it)
    best = np.full((h // 2, w // 2), -np.inf, np.float32)

    def band(b: _ZnccBand) -> None:  # each plane's cost into the band of the stack; the band's best ZNCC
        top, at = None, (b.rows, b.cols)
        for q in range(len(s)):
            score = b(float(s[q]))
            cv2.multiply(score, textured[at], dst=cost[(q,) + at])
            top = score if top is None else cv2.max(top, score, dst=top)
        if top is not None:
            best[at] = top

    for _ in _pmap(band, z.bands(textured > 0)):
        pass
    ok = m0 & (cv2.resize(best, (w, h), interpolation=cv2.INTER_NEAREST) >= cfg.min_zncc)
    return FineCost(sl, s, ds, cost, textured, ok, _pool2(ok.astype(np.float32)), plane_lattice(maps.scale_px, cfg),
                    parallax_reach(maps, sl) if cfg.oblique_levels > 0 else None)


def parallax_reach(maps: PlaneMaps, sl) -> np.ndarray:
    """(h/2, w/2) float32 on the half-resolution grid of region ``sl`` (even start and size): how
    far a change of plane moves each 2 × 2 block in camera 2, against the image's largest —
    |∂p2/∂s| at s = 0 (``maps.a``) over ``maps.scale_px``, in [0, 1]. A pixel's relative height
    noise for a given parallax noise in pixels goes like 1 / its reach."""
    norm = maps.__dict__.get("_reach")
    if norm is None:  # (per mapping, once: the cameras' geometry)
        a = np.ascontiguousarray(maps.a, np.float32)
        norm = maps.__dict__["_reach"] = cv2.magnitude(a[..., 0], a[..., 1]) * np.float32(1.0 / max(maps.scale_px, 1e-12))
    return _pool2(np.ascontiguousarray(norm[sl]))


def regional_peaks(bins: np.ndarray, weight: np.ndarray, nb: int, side: int, share: float, min_votes: float,
                   valley_ratio: float, allowed: np.ndarray | None = None, sigma: float = 1.0,
                   by_mass: "bool | np.ndarray" = False) -> list[tuple[int, float]]:
    """The vote peaks of each region of a grid of votes: a deck seen only through the gaps of a
    lower one holds a few per cent of the whole sky's votes, under the smear of the lower layer's
    and of the windows that straddle both, but most of the votes of the regions where its gaps are.

    Parameters
    ----------
    bins : ndarray, shape (h, w), int
        Each cell's vote (a bin of a uniform grid, 0 … ``nb`` − 1; < 0: no vote).
    weight : ndarray, shape (h, w), float
        Each cell's vote weight.
    side : int
        Region side [cells]; the regions overlap by half (every ``side`` / 2 cells), so that a gap
        is wholly inside at least one of them.
    share, min_votes : float
        A region votes when its votes weigh at least ``min_votes``; its peak needs ``share`` of
        them, and a valley below ``valley_ratio`` × the lower peak to its neighbours
        (:func:`~cbh.pipeline.peaks.find_peaks`, on the histogram smoothed by ``sigma`` bins).
    allowed : ndarray, shape (nb,), bool, optional
        The bins wanted (None: all); only the regions with a candidate there are examined.
    by_mass : bool or ndarray, shape (nb,), bool
        Where true, a peak's share is its mass (its smoothed bin and both neighbours: nearly all
        of a deck's votes, whatever its phase between two planes) rather than its smoothed bin
        alone (with ``sigma`` = 1, 40 % of a deck's votes on a plane and 32 % of one half way
        between two). The smoothed bin keeps flanks out where windows that straddle two decks
        vote between them (randomized sky 16742: regions' flanks at 890 and 1097 m between decks
        at 752 and 1520 m, proposed by their mass, filled the valley that parted the two).

    Returns
    -------
    list of (bin, weight): every region's peaks in ``allowed`` (a bin once, with its largest
    regional weight: the smoothed votes of the bin and its two neighbours), ascending.
    """
    h, w = bins.shape
    c = max(int(side) // 2, 1)
    ny, nx = -(-h // c), -(-w // c)
    ok = (bins >= 0) & (bins < nb) & (weight > 0)
    yy, xx = np.nonzero(ok)
    cell, b_ok, w_ok = (yy // c) * nx + (xx // c), bins[ok], weight[ok]
    r = int(4.0 * sigma + 0.5)  # the smoothing of smooth_gaussian

    def regions(a):  # (ny, nx, ...) per cell → per region of 2 × 2 cells, flattened
        a = a[:-1] + a[1:] if a.shape[0] > 1 else a
        a = a[:, :-1] + a[:, 1:] if a.shape[1] > 1 else a
        return a.reshape(-1, *a.shape[2:])

    tot = regions(np.bincount(cell, weights=w_ok, minlength=ny * nx).reshape(ny, nx))
    use = tot >= min_votes  # the regions that vote, and (a smoothed bin sums the bins within r)
    if allowed is not None:  # could have a wanted peak with share of their votes
        near = np.convolve(np.asarray(allowed, np.float64), np.ones(2 * r + 1), mode="same") > 0
        use &= regions(np.bincount(cell, weights=w_ok * near[b_ok], minlength=ny * nx).reshape(ny, nx)) >= share * tot
    if not use.any():
        return []
    hist = regions(np.bincount(cell * nb + b_ok, weights=w_ok, minlength=ny * nx * nb).reshape(ny, nx, nb))
    hist, tot = hist[use], tot[use]  # (R, nb)
    k = np.exp(-0.5 * (np.arange(-r, r + 1) / sigma) ** 2)
    pad = np.pad(hist, ((0, 0), (r, r)))
    sm = sum((k[d] / k.sum()) * pad[:, d: d + nb] for d in range(2 * r + 1))
    left = np.pad(sm, ((0, 0), (1, 0)), constant_values=-np.inf)[:, :-1]
    right = np.pad(sm, ((0, 0), (0, 1)), constant_values=-np.inf)[:, 1:]
    mass = sm + np.pad(sm, ((0, 0), (1, 0)))[:, :-1] + np.pad(sm, ((0, 0), (0, 1)))[:, 1:]  # bin and neighbours
    held = np.where(np.asarray(by_mass, bool), mass, sm)  # what a peak holds, against share × its region's votes
    cand = (sm > left) & (sm >= right) & (sm > 0) & (held >= share * tot[:, None])  # find_peaks' candidates
    want = cand if allowed is None else cand & np.asarray(allowed, bool)[None, :]
    n_cand, wanted = cand.sum(axis=1), want.any(axis=1)
    found: dict[int, float] = {}
    one = np.flatnonzero(wanted & (n_cand == 1))  # a single candidate is the region's peak
    for p, m in zip(np.argmax(cand[one], axis=1), mass[one, np.argmax(cand[one], axis=1)]):
        found[int(p)] = max(found.get(int(p), 0.0), float(m))
    for i in np.flatnonzero(wanted & (n_cand > 1)):
        for p in find_peaks(sm[i], 0.0 if np.any(by_mass) else share * tot[i], valley_ratio):
            if (allowed is None or allowed[p]) and held[i, p] >= share * tot[i]:
                found[int(p)] = max(found.get(int(p), 0.0), float(mass[i, p]))
    return sorted(found.items())


def merge_peaks(peaks: list[int], extra: list[tuple[int, float]], min_apart: float) -> list[int]:
    """``peaks`` and those of ``extra`` ((bin, weight), strongest first kept) that lie more than
    ``min_apart`` bins from every peak kept, ascending."""
    keep = list(peaks)
    for b, _ in sorted(extra, key=lambda e: -e[1]):
        if all(abs(b - p) > min_apart for p in keep):
            keep.append(int(b))
    return sorted(keep)


def vote_layers(s_vote: np.ndarray, weight: np.ndarray, s: np.ndarray, ds: float, total: float, cfg,
                regional=()):
    """The layers of the image from the wide-box winners' votes (see :func:`label_pass`).

    Parameters
    ----------
    s_vote, weight : ndarray, shape (N,)
        Refined s [1/m] of each voting pixel and its weight (accepted fraction of its block).
    s : ndarray, shape (P,)
        The fine planes [1/m].
    ds : float
        Their nominal spacing [1/m].
    total : float
        Total weight of the accepted pixels (a layer needs ``min_vote_fraction`` of it).
    regional : list of (bin, weight), or a function of the image's peaks (bins) giving one
        Further layers, in bins of half a plane step (:func:`own_plane_peaks`): each one more
        than 1.5 plane steps from every peak of the whole image's votes is a layer too.

    Returns
    -------
    votes (B,), bin width [1/m], bin ranges [lo, hi] of each layer (tiling the histogram),
    cuts (L − 1,) [1/m] between neighbouring layers, plane_layer (P,) int.
    """
    bw = 0.5 * ds
    nb = int(np.ceil(s[-1] / bw)) + 2
    idx = np.clip(np.rint(np.asarray(s_vote, np.float64) / bw).astype(np.int64), 0, nb - 1)
    votes = np.bincount(idx, weights=np.asarray(weight, np.float64), minlength=nb)
    smooth = smooth_gaussian(votes, _VOTE_SMOOTH_BINS)
    peaks = find_peaks(smooth, cfg.min_vote_fraction * total, cfg.valley_ratio)
    if peaks:  # a region's layer, above the image's lowest or below it (see own_plane_peaks)
        extra = regional(peaks) if callable(regional) else regional
        peaks = merge_peaks(peaks, [(int(b), w) for b, w in extra], _REGION_APART_BINS)
    cut_bins = valley_cuts(smooth, peaks)
    ranges = list(zip([0] + [c + 1 for c in cut_bins], cut_bins + [nb - 1])) if peaks else []
    cuts = np.array([bw * (c + 0.5) for c in cut_bins])
    return votes, bw, ranges, cuts, np.searchsorted(cuts, s)


def layer_planes(lab: "LayerLabels", L: int, s: np.ndarray, ds: float) -> np.ndarray:
    """Indices of the fine planes of layer ``L`` (its s range ± one plane step)."""
    edges = np.concatenate([[-np.inf], lab.cuts_s, [np.inf]])
    return np.flatnonzero((s >= edges[L] - 1.01 * ds) & (s <= edges[L + 1] + 1.01 * ds))


def layer_box(lab: "LayerLabels", L: int, scale_px: float, cfg, lattice: "PlaneLattice | None" = None) -> int:
    """Aggregation box [half-resolution px] of layer ``L``: ``aggregate_px`` / 2, grown like
    1/parallax for far layers (``far_aggregate_px``, at most ``_MAX_GROW`` ×). ``lattice``: the
    planes' (the votes' bins are in its coordinate)."""
    k2 = max(3, (int(cfg.aggregate_px) // 2) | 1)
    if cfg.far_aggregate_px > 0 and lab.vote_ranges:
        lo_b, hi_b = lab.vote_ranges[L]
        u_l = lab.bin_s * (lo_b + int(np.argmax(lab.votes[lo_b: hi_b + 1])))
        p_l = float(lattice.s(np.float64(u_l)) if lattice is not None else u_l) * scale_px
        grow = min(max(cfg.far_aggregate_px / max(p_l, 1e-6), 1.0), _MAX_GROW)
        return max(3, int(round(k2 * grow)) | 1)
    return k2


def own_plane_peaks(own: np.ndarray, weight: np.ndarray, s: np.ndarray, ds: float, cfg,
                    peaks=None) -> list[tuple[int, float]]:
    """Layers proposed per region (``region_px`` at working size, :func:`regional_peaks`) by the
    votes of each accepted block's own best plane ``own`` (h/2, w/2) (its ``window_px`` ZNCC, no
    aggregation: a wide box that straddles a gap's edge takes the lower layer, whose texture is
    coarser and stronger), weighted by ``weight`` (accepted fraction). The fine planes lie on a
    lattice of ``ds`` (:func:`fine_planes`), so each plane is its own bin. ``peaks``: the whole
    image's layers (bins of half a plane step, :func:`vote_layers`), if known: only what could be
    a further layer is looked for (1.5 plane steps from every one). Above the lowest, a deck seen
    through its gaps; below it, a low deck of small clouds: its wide boxes straddle their edges,
    correlate worse than the decks behind, and the vote's top 30 % of boxes hold none of them
    (randomized 17160: 386 m over 17 % of the sky under 1333 and 2195 m decks, B = 21 m; 37 of its
    2215 boxes above the 70th percentile, median ZNCC 0.69 against 0.85), while its blocks' own
    planes peak. Returns (bin, weight) in bins of half a plane step, ascending."""
    side = int(cfg.region_px) // 2
    if side < 2 or not len(s):
        return []
    q = np.rint(np.asarray(s, np.float64) / ds).astype(np.int64)
    nb = int(q[-1]) + 1
    bins = np.where(weight > 0, q[own], -1)
    # a region's peak on the flank of a stronger one (the noise of a near layer's own planes, a
    # few planes off) is no local maximum of the whole image's own votes; nor is a cloud beyond
    # the sweep's highest plane (s = 0: no parallax, as glare or obstacles at infinity)
    whole = np.bincount(bins[bins >= 0], weight[bins >= 0], minlength=nb)
    allowed = np.zeros(nb, bool)
    allowed[[b for b, _ in _true_peaks([(i, 1.0) for i in range(nb)], whole, np.isin(np.arange(nb), q),
                                       int(np.ceil(1.0 / (cfg.max_height_m * ds))))]] = True
    if peaks is not None:
        b2 = 2 * np.arange(nb)
        for p in peaks:
            allowed &= np.abs(b2 - p) > _REGION_APART_BINS
    if not allowed.any():
        return []
    # smoothed over half a plane only: a block's own best plane is a whole plane, so a deck's votes
    # lie on one plane or two neighbours; smoothed over one plane, a deck three planes from one
    # with five times its votes in the region is that deck's flank (seed 114: 143 votes on plane 1
    # beside 742 on plane 4)
    found = regional_peaks(bins, weight, nb, side, cfg.region_share, _REGION_MIN_FILL * side * side, cfg.valley_ratio,
                           allowed, sigma=_OWN_SMOOTH_PLANES)
    return [(2 * b, w) for b, w in found]


def _true_peaks(found: list[tuple[int, float]], whole: np.ndarray, swept: np.ndarray, first: int):
    """The regional peaks ``found`` ((bin, weight)) that are peaks of the sky's layers: a local
    maximum of the ``whole`` image's own votes (a region's peak on the flank of a stronger one is
    the noise of a near layer's planes, a few planes off), inside the swept planes (``swept``
    (nb,) bool: a bin with a swept plane on either side; at the edge of a run of planes the
    maximum is where the sweep stopped, not the layer), and at bin ``first`` or beyond (the
    sweep's highest plane: s = 0, no parallax, is glare or an obstacle at infinity).

    A local maximum either way: of the votes as they are, on its own plane (a deck three planes
    from one that holds 70 % of the votes, seed 114: 7401 m and 1773 m at B = 24 m, 1807 votes
    beside 991 and 1417 and three planes from 55 780, is a maximum of the planes' votes but drowns
    in that deck's tail once smoothed over a plane);
    or within one swept plane of a maximum of the votes smoothed over a plane (a deck whose
    parallax lies between two planes peaks on either, the region on one and the whole image on
    the other: seed 106's 6069 m at 4.45 px). Not within one plane of a maximum of the votes as
    they are: those have a maximum a plane from nearly every bin, and an overcast's noise near the
    horizon passed as a deck above it (twice-encoded random seeds 5024, 5025: 6796 m over 1967 m,
    909 m over 722 m). Gaps in the run of planes are skipped in the comparisons (no valley; at
    either end of a run a missing neighbour counts as 0); the smoothing runs over every bin, so a
    gap's empty bins lower the smoothed votes of the planes beside it."""
    nb = len(whole)
    on = np.flatnonzero(swept)  # the swept bins in order: a gap in the planes is no valley
    raw = np.asarray(whole, np.float64)
    ok = np.zeros(nb, bool)
    v = np.pad(raw[on], 1, constant_values=0.0)  # a maximum of the votes as they are
    ok[on[(v[1:-1] > 0) & (v[1:-1] >= np.maximum(v[:-2], v[2:]))]] = True
    v = np.pad(smooth_gaussian(raw, 1.0)[on], 1, constant_values=-np.inf)
    top = (v[1:-1] > 0) & (v[1:-1] > v[:-2]) & (v[1:-1] >= v[2:])  # smoothed: its maxima, ± 1 plane
    ok[on[top | np.r_[top[1:], False] | np.r_[False, top[:-1]]]] = True
    out = []
    for b, w in found:
        if b < first or b <= 0 or b >= nb - 1 or not (swept[b - 1] and swept[b + 1]):
            continue
        if ok[b]:
            out.append((b, w))
    return out


def label_pass(fine: FineCost, cfg) -> LayerLabels:
    """Pass 3: the layers of the image and each pixel's layer (half resolution).

    The winners of the wide-box (``aggregate_px``) cost vote, in bins of half a plane step, for
    the layers (only boxes whose mean ZNCC is above the ``vote_percentile``: a box that
    straddles two layers correlates worse and would fill the valley between their peaks); the
    histogram's peaks, split at the valleys, are the layers; each pixel takes the layer whose
    planes its ``label_px`` box cost prefers.
    """
    s, ds, cost = fine.u, fine.ds, fine.cost  # (the planes' lattice coordinate: evenly spaced)
    k2 = max(3, (int(cfg.aggregate_px) // 2) | 1)
    kl = max(1, (int(cfg.label_px) // 2) | 1)
    jw, cw, lw, rw = _best3_map(lambda c: _box(c, k2), list(cost))
    s_w = _refine(jw, cw, lw, rw, s, ds)
    vote = fine.ok_frac > 0
    if cfg.vote_percentile > 0 and vote.any():
        mean_w = cw / np.maximum(_box(fine.textured, k2), 1e-6)
        vote &= mean_w >= np.percentile(mean_w[vote], cfg.vote_percentile)
    own = _best3_map(lambda c: c, list(cost), neighbours=False)[0]
    votes, bw, ranges, cuts, plane_layer = vote_layers(s_w[vote], fine.ok_frac[vote], s, ds,
                                                       float(fine.ok_frac.sum()), cfg,
                                                       lambda pk: own_plane_peaks(own, fine.ok_frac, s, ds, cfg, pk))
    hh, wh = cost.shape[1:]
    label = np.zeros((hh, wh), np.uint8)
    if len(ranges) > 1:
        def fold(qs, _start):  # each layer's best ``label_px`` box cost over its planes among qs
            best_l: list = [None] * len(ranges)
            for q in qs:
                b, L = (_box(cost[q], kl) if kl > 1 else cost[q]), int(plane_layer[q])
                best_l[L] = b.copy() if best_l[L] is None else cv2.max(best_l[L], b, dst=best_l[L])
            return best_l

        def merge(a, b):
            return [y if x is None else (x if y is None else cv2.max(x, y, dst=x)) for x, y in zip(a, b)]

        best_l = _pfold(fold, range(len(cost)), merge)
        label = _best3([b if b is not None else np.full((hh, wh), -np.inf, np.float32) for b in best_l],
                       neighbours=False)[0].astype(np.uint8)
    return LayerLabels(cuts, votes, bw, ranges, plane_layer, label, own, s_w)


def resolved_layers(ok: np.ndarray, s_px: np.ndarray, label: np.ndarray, o1z: float, s_min: float = 0.0) -> list[float]:
    """The height [m] of each layer the sweep resolved (o1z + 1 / the median s of its accepted
    pixels, every second pixel of the half-resolution lattice of ``label`` (h/2, w/2)),
    ascending; a layer without accepted pixels has none. Only pixels at ``s_min`` or more (the
    sweep's height range, :func:`plane_range`) count: beyond it (glare and aureole at infinity,
    which the far range's planes match too) is no height of a layer, and the triangulation drops
    it; a far deck seen through gaps shares its label with such pixels (seed 106: 164 of 268)."""
    okh, sh = ok[::4, ::4] & (s_px[::4, ::4] >= s_min), s_px[::4, ::4]
    lab = np.asarray(label)[::2, ::2]
    n = min(okh.shape[0], lab.shape[0]), min(okh.shape[1], lab.shape[1])
    okh, sh, lab = okh[:n[0], :n[1]], sh[:n[0], :n[1]], lab[:n[0], :n[1]]
    out = []
    for L in np.unique(lab[okh]):
        v = sh[okh & (lab == L)]
        med = float(np.median(v)) if v.size else 0.0
        if med > 0:
            out.append(o1z + 1.0 / med)
    return sorted(out)


def refine_pass(fine: FineCost, lab: LayerLabels, scale_px: float, cfg) -> np.ndarray:
    """Pass 4: each pixel's s, refined (:func:`peak_offset` of the three best planes) on its layer's cost
    summed over an ``aggregate_px`` box of that layer's pixels only — and of those only the ones
    whose own best plane lies in the layer's range: a pixel labelled into the layer by mistake
    (occluded in camera 2, or at a boundary) has its cost peak outside the range, and its sloped
    cost would pull the peak towards the range's edge (−3 … −5 % bias on the far layer at
    B = 30 m before). Far layers (``far_aggregate_px``) get a box grown like 1/parallax. The
    half-resolution s is brought back to working size bilinearly (a box average varies smoothly
    inside a layer).

    Returns
    -------
    ndarray, shape (h, w), float32
        s [1/m] of every pixel of the region (meaningful where ``fine.ok``).
    """
    s, ds, cost = fine.u, fine.ds, fine.cost  # (the planes' lattice coordinate: evenly spaced)
    h, w = fine.ok.shape
    n_layers = max(len(lab.vote_ranges), 1)
    lab_full = cv2.resize(lab.label, (w, h), interpolation=cv2.INTER_NEAREST)
    s_px = np.zeros((h, w), np.float32)
    for L in range(n_layers):
        here = fine.ok & (lab_full == L)
        if not here.any():
            continue
        sel = layer_planes(lab, L, s, ds)
        kL = layer_box(lab, L, scale_px, cfg, fine.lattice)
        k2 = max(3, (int(cfg.aggregate_px) // 2) | 1)
        levels = reach_levels(kL, k2, lab.label.shape, cfg) if fine.reach is not None else []
        oblique = bool(levels) and bool((fine.reach < levels[0][1]).any())
        if len(sel) < 3 or (n_layers == 1 and kL == k2 and len(sel) == len(s) and not oblique):
            # (one layer on its own box over every plane: exactly the wide-box winner of pass 3)
            s_half = lab.s_wide
        else:
            inL = mL = lab.label == L
            if n_layers > 1:  # only pixels whose own best plane is in this layer, weighed by their window
                mL = (inL & (lab.plane_layer[lab.own_plane] == L)) * layer_interior(inL, cfg.window_px)
            ja, s_half = _oblique_peaks(cost, mL, inL, sel, s, ds, kL, levels, fine.reach if oblique else None)
            cut = truncated(sel[ja], s, ds)
            if cut.any():  # (NaN there: not matched; bilinear on the neighbours' s as before)
                s_half = np.where(cut, lab.s_wide, s_half)
                here = here & ~cv2.resize(cut.view(np.uint8), (w, h), interpolation=cv2.INTER_NEAREST).astype(bool)
                s_px[fine.ok & (lab_full == L) & ~here] = np.nan
        up = cv2.resize(s_half, (w, h), interpolation=cv2.INTER_LINEAR)
        cv2.copyTo(up, here.view(np.uint8), s_px)
    return fine.to_s(s_px)


_EDGE_WEIGHT = 0.05  # a layer pixel whose ZNCC window reaches across the layer's boundary counts this much [1]


def layer_interior(inside: np.ndarray, window_px: int) -> np.ndarray:
    """Weights (h/2, w/2) float32 of a layer's pixels ``inside`` (its label, half resolution) in
    its box sums: 1 where the pixel's ``window_px`` ZNCC window (working size) lies in the layer,
    ``_EDGE_WEIGHT`` where it reaches across the layer's boundary. Such a window holds the other
    deck's texture too, moving with the other deck's parallax: its cost peaks between the two,
    and summed into the layer's box it pulls the layer's heights towards the other deck (the
    bar's 3500 m deck read −2 … −3.4 % at 50–70° from the zenith, its 1200 m deck +1 %, where
    foreshortened gaps leave few pixels far from an edge; a lone deck of either height reads
    within 0.2 % there). Not zero: a sliver of a layer narrower than a window keeps its own sum."""
    r = max(int(window_px) // 2 + 1, 2) // 2  # the window's half side at half resolution, rounded up
    k = cv2.getStructuringElement(cv2.MORPH_RECT, (2 * r + 1, 2 * r + 1))
    core = cv2.erode(inside.view(np.uint8), k, borderType=cv2.BORDER_REPLICATE).astype(bool)
    return np.where(core, 1.0, _EDGE_WEIGHT).astype(np.float32) * inside


def reach_levels(kL: int, k2: int, shape: tuple[int, int], cfg) -> list[tuple[int, float]]:
    """The oblique levels of a layer's box ``kL`` [half-resolution px] on a (h/2, w/2) grid
    ``shape``: (f, reach) — pixels whose :func:`parallax_reach` is below ``reach`` take the box
    f × ``kL`` (f = 2, 4, …: ``cfg.oblique_levels`` at most; within ``_MAX_GROW`` × the base box
    ``k2`` and the grid)."""
    out, f, split = [], 1, _REACH_SPLIT
    for _ in range(int(cfg.oblique_levels)):
        f *= 2
        if f * kL > _MAX_GROW * k2 + 1 or min(shape) < f * kL:
            break
        out.append((f, split))
        split /= 2.0
    return out


def _oblique_peaks(cost: np.ndarray, mL: np.ndarray, label: np.ndarray, sel: np.ndarray, s: np.ndarray, ds: float,
                   kL: int, levels: list, reach: "np.ndarray | None"):
    """Best plane (index into ``sel``) and refined u of the cost of the pixels ``mL`` (bool, or
    float weights: :func:`layer_interior`) summed over
    the layer's box ``kL``; for the oblique pixels of the layer's ``label`` (bool), u of the grown
    boxes of ``levels`` (:func:`reach_levels`). A box f × ``kL`` runs as ``kL`` on the costs
    pooled f × f (the same sums on every f-th pixel, for 1/f² of the work), its u brought back
    bilinearly. The grown boxes only sharpen u: the best plane returned (what decides whether a
    pixel is matched, :func:`truncated`) is the layer box's, and a grown box whose best plane
    ends a run of planes, or lies farther from the layer box's than ``_GROWN_APART_PX`` of
    parallax (planes apart × ``reach``), leaves the pixel its layer box's u. (A label range can
    hold two decks when one of them has no vote peak of its own: randomized 16742, 1520 m and
    5397 m in one range; the grown boxes summed the far deck's costs into the near deck's
    pixels, and the 1520 m deck was lost.)"""
    m = mL.astype(np.float32)
    prods = list(_pmap(lambda q: cv2.multiply(cost[q], m), list(sel)))  # (the layer box's and the grown boxes')
    ja, ca, la, ra = _best3_map(lambda p: _box(p, kL), prods)
    s_half = _refine(ja, ca, la, ra, s[sel], ds)
    levels = levels if reach is not None else []
    if not levels or not (label & (reach < levels[0][1])).any():
        return ja, s_half
    pooled = list(_pmap(_pool2, prods))
    for i, (f, split) in enumerate(levels):
        here = label & (reach < split)
        if not here.any():
            break
        if i:
            pooled = [_pool2(c) for c in pooled]
        jg, cg, lg, rg = _best3_map(lambda c: _box(c, kL), pooled)
        here &= ~_back(truncated(sel[jg], s, ds).view(np.uint8), f, m.shape, cv2.INTER_NEAREST).astype(bool)
        apart = np.abs(_back(jg.astype(np.int16), f, m.shape, cv2.INTER_NEAREST).astype(np.float32) - ja)
        here &= apart * reach <= _GROWN_APART_PX
        s_half = np.where(here, _back(_refine(jg, cg, lg, rg, s[sel], ds), f, m.shape, cv2.INTER_LINEAR), s_half)
    return ja, s_half


def _back(a: np.ndarray, f: int, shape: tuple[int, int], interpolation: int) -> np.ndarray:
    """An array of :func:`_area_down` by ``f`` brought back to ``shape`` (its dropped last rows and
    columns repeat their neighbours)."""
    h, w = shape
    up = cv2.resize(a, (a.shape[1] * f, a.shape[0] * f), interpolation=interpolation)
    return cv2.copyMakeBorder(up, 0, h - up.shape[0], 0, w - up.shape[1], cv2.BORDER_REPLICATE)


def truncated(j: np.ndarray, s: np.ndarray, ds: float) -> np.ndarray:
    """Where the best plane ``j`` (indices into the fine planes ``s``) is the last one of a run of
    planes below a gap in the sweep (a hypothesis's edge, no plane one step lower): the maximum is
    where the sweep stopped, not the match (an artefact of 3–5 % of the points piled on that plane,
    a layer of its own once the sweep proposes layers per region). The sweep's floor (matched there:
    ``below_range``) and infinity are the range's own ends, not a gap."""
    gap = np.diff(s) > 1.01 * ds  # (P − 1,): no plane one step beyond plane i
    edge = np.zeros(len(s), bool)
    edge[:-1] |= gap  # the last plane before a gap (towards lower heights)
    edge[1:] |= gap  # the first plane after it
    return edge[j]


def _per_pixel(g1, g2, cloud1, maps, s, ds, cfg):
    """``aggregate_px`` = 1: each textured cloud pixel's own best plane (full-resolution ZNCC),
    refined by :func:`peak_offset`. Returns (region, ok (h, w) bool, s (h, w) float32)."""
    sl = _bbox(cloud1, cfg.window_px)
    sf, std1 = zncc_planes(g1, g2, maps, s, cfg.window_px, sl)
    j, c0, cm1, cp1 = _best3(sf)
    ok = cloud1[sl] & (std1 >= cfg.min_texture) & (c0 >= cfg.min_zncc)
    lat = plane_lattice(maps.scale_px, cfg)  # (the peak in the lattice coordinate: planes evenly spaced)
    if lat is None:
        return sl, ok, _refine(j, c0, cm1, cp1, s, ds)
    return sl, ok, lat.s(_refine(j, c0, cm1, cp1, lat.u(s), ds))


def plane_range(o1z: float, cfg) -> tuple[float, float]:
    """The sweep's plane parameter range (s_min, s_max), s = 1/(h − o1z) [1/m], from the
    configured height range (``cfg.max_height_m`` → s_min, ``cfg.min_height_m`` → s_max)."""
    return 1.0 / max(cfg.max_height_m - o1z, 1.0), 1.0 / max(cfg.min_height_m - o1z, 1.0)


class PassTimer:
    """Wall time of consecutive passes: ``lap(name)`` stores the time since the previous lap [ms]."""

    def __init__(self):
        self.timing_ms: dict[str, float] = {}
        self._t0 = time.perf_counter()

    def __call__(self, name: str) -> None:
        t1 = time.perf_counter()
        self.timing_ms[name] = (t1 - self._t0) * 1000.0
        self._t0 = t1


@dataclass
class SweepField:
    """The sweep's result on camera 1's working grid: per pixel of ``region`` the plane s =
    1/(h − o1z) [1/m] of its match (meaningful where ``ok``)."""

    region: tuple  # (slice y, slice x) of the working-size image
    ok: np.ndarray  # (h, w) bool: accepted pixels
    s: np.ndarray  # (h, w) float32 [1/m]
    info: dict  # planes, layers_m, timing_ms, and with aggregation votes, vote_bin_s, cuts_s


def sweep_field(gray1: np.ndarray, gray2: "np.ndarray | PlaneViews", cloud1: np.ndarray, maps: PlaneMaps, o1z: float,
                cfg) -> SweepField | None:
    """Dense plane sweep (see module doc): coarse → fine → label → refine, on camera 1's grid.

    Parameters
    ----------
    gray1, gray2 : ndarray, (H1, W1) and (H2, W2), uint8
        Working-size grey images; ``gray2`` may be :class:`PlaneViews` (camera 2 per plane:
        compensated for a clock offset with each height's own motion).
    cloud1 : ndarray, (H1, W1), bool
        Camera 1's cloud mask: the pixels to match.
    maps : PlaneMaps
        Working-size plane mapping camera 1 → camera 2.
    o1z : float
        Height of camera 1 above the ENU origin [m].
    cfg : SweepConfig

    Returns
    -------
    SweepField, or None when nothing was accepted (``info`` then lost: use
    :func:`sweep_matches` for the diagnostics of an empty sweep).
    """
    return _sweep_passes(gray1, gray2, cloud1, maps, o1z, cfg, {})


def _sweep_passes(gray1, gray2, cloud1, maps, o1z, cfg, info: dict) -> SweepField | None:
    lap = PassTimer()
    info.update(planes=np.zeros(0), layers_m=[], timing_ms=lap.timing_ms)
    if not cloud1.any() or maps.scale_px <= 0:
        return None
    g1 = gray1.astype(np.float32)
    g2 = _as_views(gray2).map(lambda g: g.astype(np.float32))
    maps.keep_planes(cfg.map_cache_mb)
    s_min, s_max = plane_range(o1z, cfg)
    coarse = coarse_pass(g1, g2, cloud1, maps, s_min, s_max, o1z, cfg)
    if coarse is None:
        return None
    s_fine, ds = fine_planes(coarse, maps.scale_px, s_min, s_max, cfg)
    info.update(planes=s_fine, layers_m=coarse.layers_m)
    lap("coarse")
    if cfg.aggregate_px > 1:
        fine = fine_pass(g1, g2, cloud1, maps, s_fine, ds, cfg)
        lap("fine")
        if not fine.ok.any():
            return None
        lab = label_pass(fine, cfg)
        info.update(votes=lab.votes, vote_bin_s=lab.bin_s, cuts_s=lab.cuts_s)
        lap("layers")
        region, ok, s_px = fine.region, fine.ok.copy(), refine_pass(fine, lab, maps.scale_px, cfg)
        ok &= np.isfinite(s_px)
        info["resolved_m"] = resolved_layers(ok, s_px, lab.label, o1z, s_min)
        lap("refine")
    else:
        region, ok, s_px = _per_pixel(g1, g2, cloud1, maps, s_fine, ds, cfg)
        lap("fine")
    return SweepField(region, ok, s_px, info)


def field_points(f: SweepField, maps: PlaneMaps, stride: int = 1):
    """Correspondences of the accepted pixels of a :class:`SweepField` on the lattice of working
    pixels whose x and y are multiples of ``stride``: (px1 (N, 2), px2 (N, 2), s (N,) float32)."""
    y0, x0 = f.region[0].start, f.region[1].start
    oy, ox = (-y0) % stride, (-x0) % stride
    ys, xs = np.nonzero(f.ok[oy::stride, ox::stride])
    ys, xs = ys * stride + oy, xs * stride + ox
    yi, xi = ys + y0, xs + x0
    px1 = np.stack([xi, yi], axis=-1).astype(np.float64)
    s_ok = f.s[ys, xs]
    return px1, maps.points(s_ok, yi, xi), s_ok


def sweep_matches(gray1: np.ndarray, gray2: np.ndarray, cloud1: np.ndarray, maps: PlaneMaps, o1z: float, cfg):
    """Dense plane-sweep correspondences: :func:`sweep_field`, one per accepted pixel.

    Returns
    -------
    px1 : ndarray, shape (N, 2), float64 — camera-1 pixels (integer coordinates)
    px2 : ndarray, shape (N, 2), float64 — camera-2 pixels
    info : dict — ``s`` (N,) float32 (each match's plane, s = 1/(h − o1z) [1/m]), ``planes``
        (fine s values), ``layers_m`` (coarse layer hypotheses [m]), ``timing_ms`` (per pass),
        and with aggregation ``votes``, ``vote_bin_s``, ``cuts_s``
    """
    info: dict = {}
    f = _sweep_passes(gray1, gray2, cloud1, maps, o1z, cfg, info)
    if f is None:
        info["s"] = np.zeros(0, np.float32)
        return np.zeros((0, 2)), np.zeros((0, 2)), info
    px1, px2, s_ok = field_points(f, maps)
    info["s"] = s_ok
    return px1, px2, info
