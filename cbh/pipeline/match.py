"""Stage 3: correspondences camera 1 → camera 2 on the raw fisheye images.

No undistortion, no rectification, no epipolar curves. The one geometric aid is the
*point-at-infinity mapping*: a pixel p1 of camera 1 and the pixel of camera 2 that sees the
same direction, ``p2_inf = cam2.direction_to_pixel(cam1.pixel_to_world(p1))``. It depends only
on the two rotations and lenses, is precomputed once per camera pair as a remap table
(:class:`PairGeometry`), and leaves only the parallax (≈ baseline / range) to be searched.

Contract of every method in :data:`MATCHERS`::

    method(inp: MatchInput, cfg: MatchingConfig) -> Matches

``Matches.px1`` / ``px2`` are (N, 2) float64 pixel coordinates in the working-size images of
camera 1 and camera 2. Geometric rejection (ray miss / range, triangulation angle, height) is
done afterwards by :func:`triangulate_matches`, the same for every method.

- ``lk``: pyramidal Lucas-Kanade on corner features inside camera 1's cloud mask, started at
  the infinity prediction. By default it tracks into image 2 *warped onto camera 1's grid with
  the infinity mapping* (so the start is zero displacement and the camera rotation and lens
  differences are undone); ``space = "raw"`` tracks on the raw image 2 from ``p2_inf``. Both
  check forward-backward consistency.
- ``orb``: ORB features on both raw images, Hamming matching with cross check.
- ``dis``: dense DIS optical flow between image 1 and the warped image 2: p2 = map(p1 + flow);
  forward-backward checked. Gives one correspondence per cloud pixel (the dense height map),
  but smooths across the boundary between two layers (heights in neither).
- ``sweep`` (default dense method): plane sweep over horizontal planes with ZNCC
  (:mod:`.sweep`): one correspondence per textured cloud pixel, each on the plane (layer
  hypothesis) that explains it best, refined between planes; sharp at layer boundaries.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import cv2
import numpy as np

from cbh.errors import ConfigError
from cbh.geometry.station import Camera
from cbh.geometry.triangulate import TriangulationLimits, triangulate
from cbh.pipeline.config import FilteringConfig, MatchingConfig

__all__ = ["EPIPOLAR_METHODS", "PairGeometry", "MatchInput", "Matches", "DenseField", "MATCHERS", "MATCHER_BACKENDS",
           "get_matcher", "triangulate_matches", "stereo_heights", "field_heights", "sample_map", "window_zncc",
           "corner_ratio", "match_scores"]

#: Methods whose matches lie on the epipolar curve by construction: their ray miss says
#: nothing about the matching noise (the pipeline's angular-noise estimate skips them).
EPIPOLAR_METHODS = frozenset({"sweep"})

_OUTSIDE = -1.0e5  # map value for "no pixel": far outside any image


def sample_map(map_x: np.ndarray, map_y: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Bilinear lookup of a remap table at sub-pixel points (N, 2) → (N, 2) float64."""
    if len(pts) == 0:
        return np.zeros((0, 2))
    n = len(pts)
    cols = 1024  # remap wants fewer than 32767 rows and columns: lay the points out as a block
    rows = -(-n // cols)
    p = np.full((rows * cols, 2), _OUTSIDE, np.float32)
    p[:n] = pts
    p = p.reshape(rows, cols, 2)
    px, py = np.ascontiguousarray(p[..., 0]), np.ascontiguousarray(p[..., 1])
    kw = dict(interpolation=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=_OUTSIDE)
    mx = cv2.remap(np.ascontiguousarray(map_x, np.float32), px, py, **kw).ravel()[:n]
    my = cv2.remap(np.ascontiguousarray(map_y, np.float32), px, py, **kw).ravel()[:n]
    return np.stack([mx, my], axis=-1).astype(np.float64)


@dataclass
class PairGeometry:
    """Per-pair precomputation at working size (cached by :class:`~cbh.pipeline.Pipeline`).

    Attributes
    ----------
    cam1, cam2 : Camera
        The two cameras, models scaled to the working image sizes.
    map_x, map_y : ndarray, shape (H1, W1), float32
        Pixel of camera 2 seeing the direction of each camera-1 pixel (point at infinity);
        a large negative value where camera 2 has no pixel.
    rays1_world : ndarray, shape (H1, W1, 3), float32
        Unit ENU ray of every camera-1 pixel.
    """

    cam1: Camera
    cam2: Camera
    map_x: np.ndarray = field(init=False)
    map_y: np.ndarray = field(init=False)
    rays1_world: np.ndarray = field(init=False)
    _planes: object = field(init=False, default=None)

    def __post_init__(self):
        m = self.cam1.model
        rays = self._rays1()
        px2 = self.cam2.direction_to_pixel(rays.reshape(-1, 3).astype(np.float64))
        ok = np.isfinite(px2).all(axis=1) & self.cam2.model.contains(np.nan_to_num(px2, nan=-1e6))
        px2[~ok] = _OUTSIDE
        self.map_x = px2[:, 0].reshape(m.height, m.width).astype(np.float32)
        self.map_y = px2[:, 1].reshape(m.height, m.width).astype(np.float32)

    def _rays1(self) -> np.ndarray:
        m = self.cam1.model
        rays = (m.ray_map().reshape(-1, 3) @ self.cam1.R_world_from_cam.T)
        self.rays1_world = rays.reshape(m.height, m.width, 3).astype(np.float32)
        return rays

    @classmethod
    def from_tables(cls, cam1: Camera, cam2: Camera, map_x: np.ndarray, map_y: np.ndarray, planes=None,
                    rays1_world: np.ndarray | None = None) -> "PairGeometry":
        """The geometry from cached tables (:mod:`.tables`): the remap table and the rays as
        stored (the rays recomputed if absent), the plane maps if given."""
        g = cls.__new__(cls)
        g.cam1, g.cam2 = cam1, cam2
        g.map_x, g.map_y = map_x, map_y
        if rays1_world is None:
            g._rays1()
        else:
            g.rays1_world = rays1_world
        g._planes = planes
        return g

    def tables(self) -> dict[str, np.ndarray]:
        """The expensive tables, for :func:`~cbh.pipeline.tables.save_tables`."""
        out = {"map_x": self.map_x, "map_y": self.map_y, "rays1_world": self.rays1_world}
        if self._planes is not None:
            p = self._planes
            out.update(plane_m0=p.m0, plane_a=p.a, plane_b=p.b, plane_scalars=np.array([p.s_a, p.scale_px]))
            if p.c is not None:
                out["plane_c"] = p.c
        return out

    @property
    def planes(self):
        """:class:`~cbh.pipeline.sweep.PlaneMaps` camera 1 → camera 2 (built on first use)."""
        if self._planes is None:
            from cbh.pipeline.sweep import plane_maps

            self._planes = plane_maps(self.cam1, self.cam2, self.rays1_world)
        return self._planes

    def baseline_terms(self) -> tuple[np.ndarray, np.ndarray, float, np.ndarray]:
        """Per camera-1 pixel (H1, W1) float32: |d × B| and d · B for its ENU ray d and the
        baseline B = o2 − o1 [m]; |B|² [m²]; and d's up component (cached; :func:`field_heights`)."""
        cache = self.__dict__.get("_baseline_terms")
        if cache is None:
            b = (self.cam2.position_m - self.cam1.position_m).astype(np.float32)
            d = self.rays1_world
            cross = np.linalg.norm(np.cross(d, b), axis=-1).astype(np.float32)
            dot = (d @ b).astype(np.float32)
            cache = (cross, dot, float(b @ b), np.ascontiguousarray(d[..., 2]))
            self.__dict__["_baseline_terms"] = cache
        return cache

    def torch_planes(self, device):
        """The plane tables on a torch ``device`` (:class:`~cbh.pipeline.torch_ops.TorchPlaneMaps`),
        uploaded on first use and kept: one upload per camera pair and device."""
        cache = self.__dict__.setdefault("_torch_planes", {})
        key = str(device)
        if key not in cache:
            from cbh.pipeline.torch_ops import TorchPlaneMaps

            m2 = self.cam2.model
            cache[key] = TorchPlaneMaps(self.planes, (m2.width, m2.height), device)
        return cache[key]

    def infinity(self, px1: np.ndarray) -> np.ndarray:
        """Camera-2 pixels (N, 2) of the points at infinity seen at camera-1 pixels ``px1`` (N, 2)."""
        return sample_map(self.map_x, self.map_y, px1)

    def warp2(self, image2: np.ndarray) -> np.ndarray:
        """Image 2 resampled onto camera 1's grid with the infinity mapping (0 where unseen)."""
        return cv2.remap(image2, self.map_x, self.map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)


@dataclass
class MatchInput:
    """What every matcher gets (working size; grey images uint8)."""

    geometry: PairGeometry
    gray1: np.ndarray  # (H1, W1) uint8
    gray2: np.ndarray  # (H2, W2) uint8
    cloud1: np.ndarray  # (H1, W1) bool, camera 1 cloud mask
    usable1: np.ndarray  # (H1, W1) bool
    usable2: np.ndarray  # (H2, W2) bool
    cloud2: np.ndarray  # (H2, W2) bool
    device: object = None  # torch.device for the methods with a torch backend; None = OpenCV/numpy
    # camera 2 per plane of the sweep (sweep.PlaneViews: with a clock offset, compensated with each height's own
    # motion); None = gray2 for every plane. The sparse matchers, and the sweep on a torch device, use gray2
    views2: object = None
    _warped2: np.ndarray | None = None

    @property
    def warped2(self) -> np.ndarray:
        """Image 2 warped onto camera 1's grid (computed once, shared by lk and dis)."""
        if self._warped2 is None:
            self._warped2 = self.geometry.warp2(self.gray2)
        return self._warped2


@dataclass
class Matches:
    """Correspondences of one method (working-size pixel coordinates)."""

    method: str
    px1: np.ndarray  # (N, 2) float64
    px2: np.ndarray  # (N, 2) float64
    dense: bool = False  # one correspondence per camera-1 pixel at integer coordinates
    ray2_world: np.ndarray | None = None  # (N, 3) float32: camera-2 ENU ray, where the method knows it exactly
    ray1_world: np.ndarray | None = None  # (N, 3) float32: camera-1 ENU ray, where the method has it at hand
    # a method that measures every pixel of a region (the sweep): s = 1/(h − o1z) per pixel (NaN = none), with
    # px1/px2 then a subsample of it on the point lattice (``point_stride_px``): the point set; the height map is
    # made from the field
    field: "DenseField | None" = None
    # where the method measured them (LK), each match's ZNCC (its windows, image 2 warped onto camera 1's grid at
    # infinity) and its window's corner ratio in image 1 (:func:`match_scores`): the geometry
    # check judges only those above ``geometry_check.min_zncc`` and ``min_corner_ratio``
    zncc: np.ndarray | None = None
    corner: np.ndarray | None = None

    def __len__(self) -> int:
        return int(self.px1.shape[0])

    def take(self, keep: np.ndarray) -> "Matches":
        r1 = None if self.ray1_world is None else self.ray1_world[keep]
        r2 = None if self.ray2_world is None else self.ray2_world[keep]
        z, c = (None if a is None else a[keep] for a in (self.zncc, self.corner))
        return Matches(self.method, self.px1[keep], self.px2[keep], self.dense, r2, r1, self.field, z, c)


@dataclass(frozen=True)
class DenseField:
    """Heights of a plane-sweep match at every pixel of a region of camera 1's working grid."""

    region: tuple  # (slice y, slice x)
    s: np.ndarray  # (h, w) float32: s = 1/(h − o1z) of the pixel's plane [1/m]; NaN = no match
    floor_fraction: float = 0.0  # share of the accepted pixels that sat on the lowest plane (dropped from s)
    resolved_m: tuple = ()  # heights of the layers the sweep resolved, each matched within its own planes [m]


def _in_cam2(inp: MatchInput, px2: np.ndarray) -> np.ndarray:
    """Inside camera 2's image and usable mask."""
    ok = np.isfinite(px2).all(axis=1)
    xi = np.round(np.where(ok, px2[:, 0], -1)).astype(np.int64)
    yi = np.round(np.where(ok, px2[:, 1], -1)).astype(np.int64)
    h, w = inp.usable2.shape
    ok &= (xi >= 0) & (xi < w) & (yi >= 0) & (yi < h)
    ok[ok] = inp.usable2[yi[ok], xi[ok]]
    return ok


def _windows(img: np.ndarray, p: np.ndarray, side: int) -> np.ndarray:
    """The ``side`` × ``side`` windows (N, side · side) float32 of ``img`` centred on ``p`` (N, 2),
    bilinear at sub-pixel centres (outside the image: 0). A uint8 image is read as it is (OpenCV's
    bilinear rounds to whole levels: ±0.5 DN, against 1–3 DN of sensor noise), not converted whole."""
    o = np.arange(side, dtype=np.float32) - (side - 1) / 2.0
    ox, oy = (a.ravel() for a in np.meshgrid(o, o))
    p = np.asarray(p, np.float32)
    mx = np.ascontiguousarray(p[:, :1] + ox[None, :])
    my = np.ascontiguousarray(p[:, 1:2] + oy[None, :])
    img = img if img.dtype in (np.uint8, np.float32) else np.asarray(img, np.float32)
    w = cv2.remap(img, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    return w.astype(np.float32, copy=False)


def _zncc_rows(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """ZNCC of each row of ``a`` with the same row of ``b`` (N, K): 0 where either is flat."""
    a, b = a - a.mean(axis=1, keepdims=True), b - b.mean(axis=1, keepdims=True)
    den = np.sqrt((a * a).sum(axis=1) * (b * b).sum(axis=1))
    return np.where(den > 0, (a * b).sum(axis=1) / np.maximum(den, 1e-12), 0.0)


def _corner_rows(w: np.ndarray, side: int) -> np.ndarray:
    """λ_min / λ_max of the structure tensor of each window (N, side · side) (:func:`corner_ratio`)."""
    gy, gx = np.gradient(w.reshape(-1, side, side), axis=(1, 2))
    a, b, c = (gx * gx).sum(axis=(1, 2)), (gy * gy).sum(axis=(1, 2)), (gx * gy).sum(axis=(1, 2))
    half = 0.5 * (a + b)
    disc = np.sqrt(np.maximum(half * half - (a * b - c * c), 0.0))
    return np.where(half + disc > 0, (half - disc) / np.maximum(half + disc, 1e-12), 0.0)


def window_zncc(img1: np.ndarray, p1: np.ndarray, img2: np.ndarray, p2: np.ndarray, side: int) -> np.ndarray:
    """ZNCC (N,) of the ``side`` × ``side`` windows of ``img1`` centred on ``p1`` (N, 2) and of
    ``img2`` on ``p2`` (N, 2), bilinear at sub-pixel centres (outside an image: 0 there). A flat
    window (no variance) scores 0."""
    if len(p1) == 0:
        return np.zeros(0)
    return _zncc_rows(_windows(img1, p1, side), _windows(img2, p2, side))


def corner_ratio(img: np.ndarray, p: np.ndarray, side: int) -> np.ndarray:
    """λ_min / λ_max (N,) of the structure tensor (summed gradient products) of ``img``'s
    ``side`` × ``side`` window on each of ``p`` (N, 2): 1 for texture that varies alike in every
    direction, near 0 for a line or an edge (a contrail), along which a window matches itself
    anywhere: the aperture problem. 0 for a flat window."""
    if len(p) == 0:
        return np.zeros(0)
    return _corner_rows(_windows(img, p, side), side)


def match_scores(g: PairGeometry, gray1: np.ndarray, warped2: np.ndarray, px1: np.ndarray, px2: np.ndarray,
                 side: int) -> tuple[np.ndarray, np.ndarray]:
    """(ZNCC (N,), corner ratio (N,)) of 2-D matches, camera-1 pixels ``px1`` and camera-2 pixels
    ``px2`` (N, 2): :func:`window_zncc` judged on camera 1's grid, image 2 warped there at infinity
    (``warped2``, :meth:`PairGeometry.warp2`: both windows face the same way whatever the cameras'
    yaws), and :func:`corner_ratio` of camera 1's window (read once for both)."""
    if len(px1) == 0:
        return np.zeros(0), np.zeros(0)
    q = np.nan_to_num(g.cam1.direction_to_pixel(g.cam2.pixel_to_world(np.asarray(px2, np.float64))), nan=_OUTSIDE)
    w1 = _windows(gray1, px1, side)
    return _zncc_rows(w1, _windows(warped2, q, side)), _corner_rows(w1, side)


def _lk(inp: MatchInput, cfg: MatchingConfig) -> Matches:
    c = cfg.lk
    feats = cv2.goodFeaturesToTrack(
        inp.gray1, maxCorners=c.max_points, qualityLevel=c.quality, minDistance=c.min_distance_px,
        mask=inp.cloud1.astype(np.uint8), blockSize=7,
    )
    if feats is None:
        return Matches("lk", np.zeros((0, 2)), np.zeros((0, 2)))
    p1 = feats.reshape(-1, 2).astype(np.float32)
    g = inp.geometry
    lk = dict(winSize=(c.window_px, c.window_px), maxLevel=c.levels,
              criteria=(cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01), flags=cv2.OPTFLOW_USE_INITIAL_FLOW)
    if c.space == "warped":
        w2 = inp.warped2
        q, st, _ = cv2.calcOpticalFlowPyrLK(inp.gray1, w2, p1, p1.copy(), **lk)
        b, st2, _ = cv2.calcOpticalFlowPyrLK(w2, inp.gray1, q, q.copy(), **lk)
        ok = (st.ravel() == 1) & (st2.ravel() == 1) & (np.linalg.norm(b - p1, axis=1) <= c.fb_max_px)
        p1, q = p1[ok], q[ok]
        px2 = g.infinity(q)
    else:  # raw: start at the infinity prediction in image 2, come back from its inverse
        init = g.infinity(p1)
        ok0 = _in_cam2(inp, init)
        p1, init = p1[ok0], init[ok0].astype(np.float32)
        if not len(p1):
            return Matches("lk", np.zeros((0, 2)), np.zeros((0, 2)))
        p2, st, _ = cv2.calcOpticalFlowPyrLK(inp.gray1, inp.gray2, p1, init.copy(), **lk)
        back0 = g.cam1.direction_to_pixel(g.cam2.pixel_to_world(p2.astype(np.float64)))
        back0 = np.nan_to_num(back0, nan=-1e5).astype(np.float32)
        b, st2, _ = cv2.calcOpticalFlowPyrLK(inp.gray2, inp.gray1, p2, back0, **lk)
        ok = (st.ravel() == 1) & (st2.ravel() == 1) & (np.linalg.norm(b - p1, axis=1) <= c.fb_max_px)
        p1, px2 = p1[ok], p2[ok].astype(np.float64)
    keep = _in_cam2(inp, px2)
    p1, px2 = p1[keep].astype(np.float64), px2[keep]
    z, corner = match_scores(g, inp.gray1, inp.warped2, p1, px2, c.window_px)
    return Matches("lk", p1, px2, zncc=z, corner=corner)


def _orb(inp: MatchInput, cfg: MatchingConfig) -> Matches:
    c = cfg.orb
    orb = cv2.ORB_create(nfeatures=c.max_features, fastThreshold=5)
    k1, d1 = orb.detectAndCompute(inp.gray1, inp.cloud1.astype(np.uint8))
    k2, d2 = orb.detectAndCompute(inp.gray2, inp.usable2.astype(np.uint8))
    empty = Matches("orb", np.zeros((0, 2)), np.zeros((0, 2)))
    if d1 is None or d2 is None or len(k1) == 0 or len(k2) == 0:
        return empty
    bf = cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True)
    ms = [m for m in bf.match(d1, d2) if m.distance <= c.max_hamming]
    if not ms:
        return empty
    p1 = np.array([k1[m.queryIdx].pt for m in ms], np.float64)
    p2 = np.array([k2[m.trainIdx].pt for m in ms], np.float64)
    g = inp.geometry
    # parallax gate: the camera-2 ray must be within max_parallax_deg of the infinity direction
    cosang = np.einsum("ij,ij->i", g.cam1.pixel_to_world(p1), g.cam2.pixel_to_world(p2))
    keep = cosang >= np.cos(np.radians(c.max_parallax_deg))
    return Matches("orb", p1[keep], p2[keep])


_DIS_PRESETS = {"ultrafast": 0, "fast": 1, "medium": 2}


def _dis(inp: MatchInput, cfg: MatchingConfig) -> Matches:
    c = cfg.dis
    dis = cv2.DISOpticalFlow.create(_DIS_PRESETS[c.preset])
    w2 = inp.warped2
    flow = dis.calc(inp.gray1, w2, None)
    ys, xs = np.nonzero(inp.cloud1)
    p1 = np.stack([xs, ys], axis=-1).astype(np.float32)
    q = p1 + flow[ys, xs]
    ok = np.ones(len(p1), bool)
    if c.fb_max_px > 0:
        back = dis.calc(w2, inp.gray1, None)
        bq = sample_map(back[..., 0], back[..., 1], q)
        ok &= np.linalg.norm(flow[ys, xs] + bq, axis=1) <= c.fb_max_px
    # the warped image is black where camera 2 sees nothing: drop flows that land there
    p1, q = p1[ok], q[ok]
    px2 = inp.geometry.infinity(q)
    keep = _in_cam2(inp, px2)
    return Matches("dis", p1[keep].astype(np.float64), px2[keep], dense=True)


def _sweep(inp: MatchInput, cfg: MatchingConfig) -> Matches:
    g = inp.geometry
    o1z = float(g.cam1.position_m[2])
    if inp.device is not None:
        from cbh.pipeline.torch_ops import sweep_field_torch

        f = sweep_field_torch(inp.gray1, inp.gray2, inp.cloud1, g.torch_planes(inp.device), o1z, cfg.sweep)
    else:
        from cbh.pipeline.sweep import sweep_field

        f = sweep_field(inp.gray1, inp.gray2 if inp.views2 is None else inp.views2, inp.cloud1, g.planes, o1z,
                        cfg.sweep)
    if f is None:
        return Matches("sweep", np.zeros((0, 2)), np.zeros((0, 2)), dense=True)
    from cbh.pipeline.sweep import field_points

    # every accepted pixel whose camera-2 pixel lies inside camera 2's image and usable mask
    s = np.where(f.ok, f.s, np.float32(np.nan)).astype(np.float32)
    mx, my = g.planes.pixels(s, f.region)
    _exact_beyond_tables(g, s, mx, my, f.region)
    at2 = lambda m: cv2.remap(m.view(np.uint8), mx, my, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT,  # noqa: E731
                              borderValue=0) > 0
    s[~at2(inp.usable2)] = np.nan
    seen2 = at2(inp.cloud2) if _camera1_alone_calls_cloud(inp) else None
    field = DenseField(f.region, s, floor_fraction=_drop_floor(s, f.info.get("planes"), g.planes.scale_px, o1z,
                                                                cfg.sweep, seen2=seen2),
                       resolved_m=tuple(f.info.get("resolved_m", ())))
    # the point set: the same matches on the point lattice
    # (camera 2's pixels from the sweep's own s; their heights from the field's, exact beyond the tables)
    px1, px2, _ = field_points(replace(f, ok=np.isfinite(s)), g.planes, max(1, int(cfg.sweep.point_stride_px)))
    y0, x0 = f.region[0].start, f.region[1].start
    s_pt = s[px1[:, 1].astype(np.int64) - y0, px1[:, 0].astype(np.int64) - x0]
    # the camera-2 ray of a plane-sweep match is known exactly: the point o1 + d·(h − o1z)/d_z
    # seen from o2 is along d − s·d_z·B (s = 1/(h − o1z)); no fisheye back-projection of px2 needed
    d1 = g.rays1_world.reshape(-1, 3)[px1[:, 1].astype(np.int64) * g.rays1_world.shape[1] + px1[:, 0].astype(np.int64)]
    base = (g.cam2.position_m - g.cam1.position_m).astype(np.float32)
    d2 = d1 - (s_pt * d1[:, 2])[:, None] * base[None, :]
    return Matches("sweep", px1, px2, dense=True, ray2_world=d2, ray1_world=d1, field=field)


def _exact_beyond_tables(g: PairGeometry, s: np.ndarray, mx: np.ndarray, my: np.ndarray, region) -> None:
    """Re-triangulate, in place, the field's s where the plane tables extrapolate.

    The tables interpolate camera 2's pixel up to s = 3·s_a (a parallax of 0.3 rad; for atan
    within 0.06 %) and extrapolate beyond (−0.1 % at 0.4 rad, −0.4 % at 0.5 rad); the pixels
    past s = 2·s_a (heights under 5·|B|: for a 50 m pair, cloud under 250 m) are re-triangulated,
    where the quadratic the maps were until stop 59 extrapolated. The sweep still finds the right
    pixel there (the texture matches at p2(s)), but the s that the extrapolated table put at that pixel is not the height of the two rays through it: on a
    630 m pair a flat 1500 m base read 1528 m at the zenith and 1498 m at 60° (true rays: within
    ±5 m). So pixels beyond the tables get s from camera 1's ray and camera 2's back-projected
    ray through their matched pixel (closest approach: :func:`~cbh.geometry.triangulate.triangulate`)."""
    far = np.isfinite(s) & (s > 2.0 * g.planes.s_a)
    if not far.any():
        return
    ys, xs = np.nonzero(far)
    d1 = g.rays1_world[region][ys, xs].astype(np.float64)
    px2 = np.stack([mx[ys, xs], my[ys, xs]], axis=1).astype(np.float64)
    d2 = g.cam2.pixel_to_world(px2)
    t = triangulate(g.cam1.position_m, d1, g.cam2.position_m, d2, TriangulationLimits(max_range_m=1e7))
    dz = t.height_m - float(g.cam1.position_m[2])
    ok = t.valid & np.isfinite(dz) & (dz > 0)
    s[ys, xs] = np.where(ok, 1.0 / np.where(ok, dz, 1.0), np.nan).astype(np.float32)


#: Camera 2 calling cloud less than this share of what camera 1 does: camera 1's cloud is its own
#: segmentation's (two cameras tens of metres apart see the same sky, fog included); see :func:`_drop_floor`.
ONE_CAMERA_CLOUD_RATIO = 0.2


def _camera1_alone_calls_cloud(inp: MatchInput) -> bool:
    """Whether camera 2 calls cloud under ``ONE_CAMERA_CLOUD_RATIO`` of the share of its usable sky
    that camera 1 does."""
    share = [float(np.count_nonzero(c & u)) / max(float(np.count_nonzero(u)), 1.0)
             for c, u in ((inp.cloud1, inp.usable1), (inp.cloud2, inp.usable2))]
    return share[1] < ONE_CAMERA_CLOUD_RATIO * share[0]


def _drop_floor(s: np.ndarray, planes, scale_px: float, o1z: float, cfg, seen2: np.ndarray | None = None) -> float:
    """Drop (set NaN in ``s``) the pixels on the sweep's lowest plane; their share of the measured ones.

    A pixel whose best plane is the lowest one (``min_height_m``, within one plane step) has its
    cost still rising at the edge of the search: the cloud is there or lower, and its height is
    not measured. Cloud below the floor (fog at 60–85 m with a 100 m floor, simulated) puts
    20–55 % of the measured pixels there, and the rest alias onto false layers at 400 m–3.5 km
    with full confidence; a cloud base above 120 m puts none there. The share is the pair's
    ``below_range_fraction``; above ``BELOW_RANGE_FRACTION`` it flags ``below_range``.

    ``seen2`` (same shape as ``s``, bool; given where camera 2 calls cloud under
    ``ONE_CAMERA_CLOUD_RATIO`` of camera 1's share, :func:`_camera1_alone_calls_cloud`): whether
    camera 2 calls each pixel's match cloud; a pixel on the floor that it does not is dropped but
    not counted.
    Fog is cloud in both cameras; cloud that camera 1 alone calls so is its segmentation's
    (randomized 18125, hard options, 480 px: a pale clear sky, cloud over 30 % of camera 1 and
    1.6 % of camera 2, put 16 % of its chance matches on the floor and was flagged
    ``below_range``). Not pixel by pixel on every pair: the floor plane is not where patchy fog
    below it lies in camera 2 (fog at 10 m over 40 % of the sky: 14 % of the matches land on
    camera 2's cloud), so its matches there would not count.
    """
    from cbh.pipeline.sweep import plane_range

    planes = np.asarray(planes if planes is not None else [], np.float64)
    n = int(np.count_nonzero(np.isfinite(s)))
    if not len(planes) or n == 0:
        return 0.0
    s_max = plane_range(o1z, cfg)[1]
    ds = cfg.step_px / scale_px
    if len(planes) > 1:  # the planes' own step there (wider than step_px on a log lattice, sweep.PlaneLattice)
        ds = max(ds, float(planes[-1] - planes[-2]))
    if planes[-1] < s_max - ds:  # the fine planes stop short of the floor: nothing can sit on it
        return 0.0
    with np.errstate(invalid="ignore"):
        on = s >= np.float32(planes[-1] - ds)
    k = int(np.count_nonzero(on if seen2 is None else on & seen2))
    s[on] = np.nan
    return k / n


#: Share of the sweep's measured pixels on its lowest plane above which the pair is flagged
#: ``below_range`` (see :func:`_drop_floor`).
BELOW_RANGE_FRACTION = 0.05
#: … and where the measured pixels are chance matches only (a featureless sky's: ``Pipeline._chance_matches_only``),
#: above this share: chance matches spread over the planes (randomized 9339, a featureless clear sky
#: at 480 px: 6.2 % on the floor), so a fifth of them on the one lowest plane is no chance. Simulated
#: fog at 480 px (``eval_flags.py fog``): 45 and 80 m fogs with 25–50 % of their few matches on the
#: floor were flagged only ``cloud_unmatched``.
BELOW_RANGE_CHANCE_FRACTION = 0.2
#: A pair whose lowest layer lies within this factor of the sweep's floor while less than
#: ``FLOOR_LAYER_MATCHED`` of camera 1's cloud was measured is flagged ``below_range`` too: fog
#: well below the floor (10–80 m under a 100 m floor, B = 50 m: 60–100° of parallax) matches
#: almost nowhere (6–36 % of its pixels), too few pixels land on the lowest plane to pass
#: ``BELOW_RANGE_FRACTION``, and the chance matches pile up just above the floor (layers at
#: 101–114 m); a real base at 105–130 m is measured over 89–97 % of its pixels (simulated, 960 px).
FLOOR_LAYER_RATIO = 1.15
FLOOR_LAYER_MATCHED = 0.5
#: Below this share of camera 1's cloud measured (by a dense method), a pair is flagged
#: ``cloud_unmatched`` (not invalidating: the layers describe the matched part, and may be false).
#: Simulated presets: 0.77–0.94; real texture (stereo pairs from a WAHRSIS photograph): 0.61–0.98;
#: the real WAHRSIS pair (thin cloud, JPEG, a lens calibration off by degrees): 0.23–0.33; fog far
#: below the floor: 0.00–0.30 (flagged ``below_range`` from 0.15 up).
UNMATCHED_FRACTION = 0.15

MATCHERS = {"lk": _lk, "orb": _orb, "dis": _dis, "sweep": _sweep}

# The backends each method runs on. "opencv": numpy/OpenCV on the CPU (always available; the
# sparse matchers stay there: a few thousand features, nothing for a GPU to gain); "torch": any
# torch device (CPU or CUDA), used when the pipeline runs on a device (Pipeline(device=...)).
MATCHER_BACKENDS = {"lk": ("opencv",), "orb": ("opencv",), "dis": ("opencv",), "sweep": ("opencv", "torch")}


def get_matcher(name: str):
    """The matching function registered as ``name`` (case-insensitive)."""
    try:
        return MATCHERS[name.lower()]
    except KeyError:
        raise ConfigError(f"unknown matching method {name!r} (valid: {', '.join(MATCHERS)})") from None


@dataclass
class TriangulatedMatches:
    """Triangulated correspondences that passed :class:`FilteringConfig` (working-size pixels)."""

    matches: Matches
    point_m: np.ndarray  # (N, 3) float64 ENU [m]
    miss_m: np.ndarray  # (N,) float64 [m]
    n_in: int  # correspondences before filtering
    grid_m: np.ndarray | None = None  # (H1, W1) float32: the method's dense field as heights [m], NaN = none
    angle_deg: np.ndarray | None = None  # (N,) triangulation angle of each match [deg] (``keep_all`` only)

    @property
    def height_m(self) -> np.ndarray:
        return self.point_m[:, 2]


def _rays_world(cam: Camera, px: np.ndarray) -> np.ndarray:
    """ENU unit rays (N, 3) float32 of pixels (N, 2): ``cam.pixel_to_world`` without the BLAS
    matmul (an (N, 3) @ (3, 3) product is slow and thread-hungry; three broadcasts are not)."""
    r = cam.model.pixel_to_ray(px)
    R = cam.R_world_from_cam
    return (r[:, 0:1] * R[:, 0] + r[:, 1:2] * R[:, 1] + r[:, 2:3] * R[:, 2]).astype(np.float32)


def triangulate_matches(geom: PairGeometry, m: Matches, cfg: FilteringConfig, keep_all: bool = False) -> TriangulatedMatches:
    """Triangulate and reject by ray miss / range, triangulation angle and height range
    (``keep_all``: keep every match, the rejected ones as NaN points)."""
    n = len(m)
    if m.ray1_world is not None:
        d1 = m.ray1_world
    elif m.dense:
        idx = m.px1[:, 1].astype(np.int64) * geom.rays1_world.shape[1] + m.px1[:, 0].astype(np.int64)
        d1 = geom.rays1_world.reshape(-1, 3)[idx]
    else:
        d1 = _rays_world(geom.cam1, m.px1)
    d2 = _rays_world(geom.cam2, m.px2) if m.ray2_world is None else m.ray2_world
    tri = triangulate(geom.cam1.position_m.astype(np.float32), d1, geom.cam2.position_m.astype(np.float32), d2,
                      TriangulationLimits(min_angle_deg=cfg.min_angle_deg, max_range_m=1e6))
    with np.errstate(invalid="ignore", divide="ignore"):
        keep = (
            tri.valid
            & (tri.miss_m <= cfg.max_miss_ratio * tri.range1_m)
            & (tri.height_m >= cfg.min_height_m)
            & (tri.height_m <= cfg.max_height_m)
        )
    grid = None if m.field is None else field_heights(geom, m.field, cfg)
    if keep_all:
        point = tri.point_m.astype(np.float64)
        point[~keep] = np.nan
        return TriangulatedMatches(m, point, np.where(keep, tri.miss_m, np.nan).astype(np.float64), n, grid,
                                   np.asarray(tri.angle_deg, np.float64))
    if keep.all():  # (the dense sweep: usually every match passes; skip the copies)
        return TriangulatedMatches(m, tri.point_m.astype(np.float64), tri.miss_m.astype(np.float64), n, grid)
    return TriangulatedMatches(m.take(keep), tri.point_m[keep].astype(np.float64), tri.miss_m[keep].astype(np.float64),
                               n, grid)


def stereo_heights(geom: PairGeometry, px1: np.ndarray, px2: np.ndarray,
                   cfg: FilteringConfig) -> tuple[np.ndarray, np.ndarray]:
    """Heights [m] (N,) of correspondences (N, 2) + (N, 2) at working size, NaN where
    :func:`triangulate_matches` would reject them, and their triangulation angles [rad] (N,)."""
    if len(px1) == 0:
        return np.zeros(0), np.zeros(0)
    tr = triangulate_matches(geom, Matches("", np.asarray(px1, np.float64), np.asarray(px2, np.float64)), cfg,
                             keep_all=True)
    return tr.height_m, np.radians(tr.angle_deg)


def field_heights(geom: PairGeometry, field: DenseField, cfg: FilteringConfig) -> np.ndarray:
    """A sweep's dense field as heights on camera 1's working grid (H1, W1) float32 [m], NaN =
    none, with :func:`triangulate_matches`'s rejection applied per pixel, in closed form.

    A plane-sweep pixel's two rays meet exactly on its plane (d2 = d1 − s·d1z·B passes through
    o1 + d1/(s·d1z)), so the point's height is o1z + 1/s and the ray miss is 0. What is left to
    check: the height range, and the triangulation angle, whose sine is
    |d1 × d2| / |d2| = k·|d1 × B| / |d1 − k·B| with k = s·d1z (|d1| = 1).
    """
    ry, rx = field.region
    s = np.ascontiguousarray(field.s, np.float32)
    o1z = float(geom.cam1.position_m[2])
    cross, dot, b2, d1z = geom.baseline_terms()
    cross, dot = cross[ry, rx], dot[ry, rx]
    k = cv2.multiply(s, d1z[ry, rx])  # OpenCV arithmetic: no numpy temporaries (NaN compares false below)
    kd = cv2.multiply(k, dot)
    d2n = cv2.sqrt(cv2.max(cv2.add(cv2.subtract(1.0, cv2.multiply(kd, 2.0)), cv2.multiply(cv2.multiply(k, k), b2)), 0.0))
    h = cv2.add(cv2.divide(1.0, s), o1z)
    ok = cv2.compare(cv2.multiply(k, cross), cv2.multiply(d2n, math.sin(math.radians(cfg.min_angle_deg))), cv2.CMP_GE)
    ok &= cv2.compare(kd, 1.0, cv2.CMP_LT)  # the angle below 90°: the point in front of camera 2
    ok &= cv2.compare(h, float(cfg.min_height_m), cv2.CMP_GE)
    ok &= cv2.compare(h, float(cfg.max_height_m), cv2.CMP_LE)
    out = np.full(geom.rays1_world.shape[:2], np.nan, np.float32)
    out[ry, rx] = np.where(ok > 0, h, np.float32(np.nan))
    return out
