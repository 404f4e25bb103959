"""Vectorized two-ray triangulation in ENU (paper eq. 2–6, Figure 4).

Two rays of one sky point nearly meet. :func:`triangulate` finds, for N ray pairs at once,
the closest approach of the two lines: the midpoint of their common perpendicular is the
point, the perpendicular's length is the ray-miss distance (the paper's quality measure).
:func:`triangulate_svd` is the paper's homogeneous least-squares (SVD) formulation, kept as
a reference; both agree on well-conditioned pairs.

Works on numpy arrays or torch tensors (same API, float32 or float64); the backend follows
the type of ``d1``.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from cbh.errors import ShapeError

__all__ = ["Triangulation", "triangulate", "triangulate_svd", "points_on_epipolar", "TriangulationLimits", "MultiView", "triangulate_views"]


@dataclass(frozen=True)
class TriangulationLimits:
    """Validity thresholds.

    Attributes
    ----------
    min_angle_deg : float
        Smallest angle between the two rays [deg]; below it the pair is near-parallel.
    max_range_m : float
        Largest distance from either camera to the point [m].
    """

    min_angle_deg: float = 0.05
    max_range_m: float = 100_000.0


@dataclass(frozen=True)
class Triangulation:
    """Triangulated ray pairs; every field has leading dimension N, same backend/dtype as input.

    Attributes
    ----------
    point_m : shape (N, 3)
        Closest-approach midpoint in ENU [m].
    height_m : shape (N,)
        Its up component: height above the ENU origin [m].
    miss_m : shape (N,)
        Length of the common perpendicular of the two rays [m].
    range1_m, range2_m : shape (N,)
        Distance along each ray from its camera to its foot of the perpendicular [m];
        negative means behind the camera.
    angle_deg : shape (N,)
        Triangulation angle between the rays [deg].
    valid : shape (N,), bool
        In front of both cameras, not near-parallel, within range.
    """

    point_m: Any
    height_m: Any
    miss_m: Any
    range1_m: Any
    range2_m: Any
    angle_deg: Any
    valid: Any

    def __len__(self) -> int:
        return int(self.height_m.shape[0])


def _backend(x):
    if isinstance(x, np.ndarray):
        return np
    try:
        import torch
    except ImportError:  # pragma: no cover - torch is a dependency
        raise TypeError("triangulate: expected numpy arrays or torch tensors") from None
    if isinstance(x, torch.Tensor):
        return torch
    raise TypeError(f"triangulate: expected numpy arrays or torch tensors, got {type(x).__name__}")


def _check(name, a, n=None):
    shape = tuple(a.shape)
    if len(shape) not in (1, 2) or shape[-1] != 3 or (len(shape) == 2 and n is not None and shape[0] not in (1, n)):
        raise ShapeError(f"{name}: expected shape (N, 3) or (3,), got {shape}")


def triangulate(o1, d1, o2, d2, limits: TriangulationLimits = TriangulationLimits(), *, chunk: int = 1 << 16) -> Triangulation:
    """Closest approach of N ray pairs.

    One core (:func:`_closest_approach`) for numpy and torch: both backends give the same
    numbers (to rounding) and the same answer on degenerate input.

    Parameters
    ----------
    o1, o2 : array, shape (3,) or (N, 3)
        Ray origins (camera projection centres) in ENU [m].
    d1, d2 : array, shape (N, 3), float32 or float64
        Ray directions in ENU (need not be unit length).
    limits : TriangulationLimits
        Validity thresholds.
    chunk : int
        Pairs per block on the CPU (keeps temporaries in cache); a GPU takes all at once.

    Returns
    -------
    Triangulation
        Same backend and dtype as ``d1`` (other dtypes: float64). Degenerate pairs (parallel
        rays, a zero-length direction, NaN input) have no common perpendicular: their point,
        miss distance and ranges are NaN and they are not valid; parallel rays have angle 0°
        (or 180°), a zero-length direction angle NaN.

    Examples
    --------
    >>> import numpy as np
    >>> t = triangulate(np.zeros(3), np.array([[0., 0., 1.]]), np.array([100., 0, 0]), np.array([[-0.1, 0, 1.]]))
    >>> round(float(t.height_m[0]), 6), bool(t.valid[0])
    (1000.0, True)
    """
    xp = _backend(d1)
    n = d1.shape[0] if d1.ndim == 2 else 1
    for name, a in (("o1", o1), ("d1", d1), ("o2", o2), ("d2", d2)):
        _check(name, a, n)
    if xp is np:
        dtype = d1.dtype if d1.dtype in (np.float32, np.float64) else np.float64
        conv = lambda a: np.asarray(a, dtype=dtype)  # noqa: E731
        cols = lambda a: np.ascontiguousarray(a.T)  # noqa: E731 - (3, m) rows: contiguous components
        step, errstate = max(1, int(chunk)), np.errstate(divide="ignore", invalid="ignore")
    else:
        import torch

        dtype = d1.dtype if d1.dtype in (torch.float32, torch.float64) else torch.float64
        dev = d1.device
        conv = lambda a: torch.as_tensor(a, dtype=dtype, device=dev)  # noqa: E731
        cols = lambda a: a.T.contiguous()  # noqa: E731
        step = n if dev.type != "cpu" else max(1, int(chunk))
        from contextlib import nullcontext as errstate_

        errstate = errstate_()
    d1, d2 = conv(d1).reshape(-1, 3), conv(d2).reshape(-1, 3)
    o1, o2 = conv(o1), conv(o2)
    per1 = o1.ndim == 2 and o1.shape[0] == n and n > 1
    per2 = o2.ndim == 2 and o2.shape[0] == n and n > 1
    o1 = o1 if per1 else o1.reshape(3)
    o2 = o2 if per2 else o2.reshape(3)
    # preallocated outputs filled block by block: retaining per-block results makes torch's
    # CPU allocator thrash (measured 30x slower at 1e7 pairs)
    point = xp.empty((n, 3), dtype=dtype) if xp is np else xp.empty((n, 3), dtype=dtype, device=d1.device)
    like = lambda dt: xp.empty(n, dtype=dt) if xp is np else xp.empty(n, dtype=dt, device=d1.device)  # noqa: E731
    miss, r1, r2, angle = like(dtype), like(dtype), like(dtype), like(dtype)
    valid = like(bool if xp is np else xp.bool)
    cos_min = float(np.cos(np.radians(limits.min_angle_deg)))
    with errstate:
        for i in range(0, n, step):
            j = min(i + step, n)
            O1 = cols(o1[i:j]) if per1 else o1
            O2 = cols(o2[i:j]) if per2 else o2
            p, m, a1, a2, ang, v = _closest_approach(xp, O1, cols(d1[i:j]), O2, cols(d2[i:j]), cos_min,
                                                     float(limits.max_range_m))
            for k in range(3):
                point[i:j, k] = p[k]
            miss[i:j], r1[i:j], r2[i:j], angle[i:j], valid[i:j] = m, a1, a2, ang, v
    return Triangulation(point, point[:, 2], miss, r1, r2, angle, valid)


def _closest_approach(xp, O1, a, O2, b, cos_min: float, max_range_m: float):
    """The triangulation core, for numpy (``xp = np``) and torch (``xp = torch``) alike.

    ``a``, ``b``: ray directions as (3, m) component rows; ``O1``, ``O2``: origins, (3,) or
    (3, m). Cross-product form of the closest approach (stable in float32 for near-parallel
    rays, unlike a·c − b²): n = a × b, w = O2 − O1,
    s = ((w × b) · n) / |n|² along ray 1, t = ((w × a) · n) / |n|² along ray 2,
    miss = |w · n| / |n|, angle = asin(|n| / (|a||b|)) mirrored past 90° (asin is ~5x cheaper
    than arctan2 here and as accurate for the small angles that matter).
    Where |n|² is not above the dtype's tiny (parallel rays, a zero direction) or the input
    is NaN, s, t, the point, miss and ranges are NaN and the pair is invalid.

    Returns (point components (3 arrays), miss, range1, range2, angle_deg, valid), each (m,).
    """
    ax, ay, az = a[0], a[1], a[2]
    bx, by, bz = b[0], b[1], b[2]
    wx, wy, wz = O2[0] - O1[0], O2[1] - O1[1], O2[2] - O1[2]
    nx = ay * bz; nx -= az * by  # noqa: E702 - in-place arithmetic, the same in numpy and torch
    ny = az * bx; ny -= ax * bz  # noqa: E702
    nz = ax * by; nz -= ay * bx  # noqa: E702
    nn = nx * nx; nn += ny * ny; nn += nz * nz  # noqa: E702
    ok = nn > xp.finfo(nn.dtype).tiny
    inv = 1.0 / nn  # inf where nn = 0: s, t, miss become NaN (0 · inf, 0 / 0) ...
    if not bool(ok.all()):
        inv[~ok] = float("nan")  # ... and also where nn is subnormal: no common perpendicular
    s = (wy * bz - wz * by) * nx; s += (wz * bx - wx * bz) * ny; s += (wx * by - wy * bx) * nz; s *= inv  # noqa: E702
    t = (wy * az - wz * ay) * nx; t += (wz * ax - wx * az) * ny; t += (wx * ay - wy * ax) * nz; t *= inv  # noqa: E702
    la = ax * ax; la += ay * ay; la += az * az; la = xp.sqrt(la)  # noqa: E702
    lb = bx * bx; lb += by * by; lb += bz * bz; lb = xp.sqrt(lb)  # noqa: E702
    point = []
    for oa, ob, da, db in ((O1[0], O2[0], ax, bx), (O1[1], O2[1], ay, by), (O1[2], O2[2], az, bz)):
        q = s * da; q += oa; q2 = t * db; q2 += ob; q += q2; q *= 0.5  # noqa: E702
        point.append(q)
    nl = xp.sqrt(nn)
    miss = wx * nx; miss += wy * ny; miss += wz * nz; miss = xp.abs(miss); miss *= inv; miss *= nl  # noqa: E702
    r1 = s * la
    r2 = t * lb
    dot = ax * bx; dot += ay * by; dot += az * bz  # noqa: E702
    la *= lb  # |a||b|
    q = nl / la
    angle = _asin_deg(xp, q, dot < 0)
    # angle ≥ min without re-reading the angle: cos(angle) ≤ cos(min)
    la *= cos_min
    valid = dot <= la
    valid &= ok
    valid &= r1 > 0
    valid &= r2 > 0
    valid &= r1 <= max_range_m
    valid &= r2 <= max_range_m
    return point, miss, r1, r2, angle, valid


def _asin_deg(xp, q, obtuse):
    """asin(clip(q, 0, 1)) in degrees, mirrored to 180° − x where ``obtuse``; in place on ``q``."""
    if xp is np:
        np.clip(q, 0.0, 1.0, out=q)
        np.arcsin(q, out=q)
        np.subtract(np.pi, q, out=q, where=obtuse)
    else:
        q = q.clamp_(0.0, 1.0).asin_()
        q = xp.where(obtuse, np.pi - q, q)
    q *= 180.0 / np.pi
    return q


def points_on_epipolar(o1: np.ndarray, d1: np.ndarray, o2: np.ndarray, d2: np.ndarray) -> np.ndarray:
    """Points (N, 3) [m] on camera 1's upward rays ``d1`` at the height that the parallax *along*
    the baseline alone gives: each match moved onto its epipolar line first (NaN: no positive
    height). Numpy, float64.

    The closest approach of two skew rays is biased short: its range is ``b⊥·Δd / |Δd|²``, and a
    miss m across the baseline adds m² to the denominator, so noise across the baseline (a
    carried match has as much of it as along) pulls every height down (a real 241 m station's
    8.4 km deck read 6 % low). In plane offsets ``a = (e, n) / u`` a point at height h above
    camera 1 has ``a2 − a1 = −q·B'`` with q = 1/h and B' = B − Δz·a2 (B the horizontal baseline,
    Δz camera 2's height above camera 1), so ``q = −(a2 − a1)·B' / |B'|²``."""
    o1, o2 = np.asarray(o1, np.float64).reshape(3), np.asarray(o2, np.float64).reshape(3)
    d1, d2 = np.asarray(d1, np.float64), np.asarray(d2, np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        a1, a2 = d1[:, :2] / d1[:, 2:3], d2[:, :2] / d2[:, 2:3]
        bp = (o2 - o1)[None, :2] - (o2[2] - o1[2]) * a2
        q = -((a2 - a1) * bp).sum(1) / (bp * bp).sum(1)
        up = (d1[:, 2] > 0) & (d2[:, 2] > 0) & (q > 0)
        point = o1[None, :] + np.concatenate([a1, np.ones((len(a1), 1))], axis=1) / q[:, None]
    return np.where(up[:, None], point, np.nan)


def triangulate_svd(o1, d1, o2, d2, limits: TriangulationLimits = TriangulationLimits()) -> Triangulation:
    """The paper's formulation (eq. 4–6), one small SVD per pair (numpy, float64).

    For each pair solve ``λ1 v1 − λ2 v2 − T ≈ 0`` homogeneously: A = [v1, −v2, −T] (3×3),
    λ = last right-singular vector, λ1 = v13/v33, λ2 = v23/v33. Batched over N with
    ``np.linalg.svd``; :func:`triangulate_svd_loop` is the per-point loop of the paper.
    """
    o1, o2 = (np.broadcast_to(np.asarray(o, dtype=np.float64), np.shape(d1)) for o in (o1, o2))
    d1 = np.asarray(d1, dtype=np.float64)
    d2 = np.asarray(d2, dtype=np.float64)
    T = o2 - o1
    A = np.stack([d1, -d2, -T], axis=-1)  # (N, 3, 3), columns v1, -v2, -T
    _, _, vt = np.linalg.svd(A)
    lam = vt[:, -1, :]
    return _from_lambdas(o1, d1, o2, d2, lam[:, 0] / lam[:, 2], lam[:, 1] / lam[:, 2], limits)


def triangulate_svd_loop(o1, d1, o2, d2, limits: TriangulationLimits = TriangulationLimits()) -> Triangulation:
    """Per-point loop over 3×3 SVDs, as the paper computes it (reference and benchmark baseline)."""
    o1, o2 = (np.broadcast_to(np.asarray(o, dtype=np.float64), np.shape(d1)) for o in (o1, o2))
    n = len(d1)
    l1 = np.empty(n)
    l2 = np.empty(n)
    for i in range(n):
        A = np.column_stack([d1[i], -d2[i], -(o2[i] - o1[i])])
        _, _, vt = np.linalg.svd(A)
        v = vt[-1]
        l1[i], l2[i] = v[0] / v[2], v[1] / v[2]
    return _from_lambdas(o1, np.asarray(d1, np.float64), o2, np.asarray(d2, np.float64), l1, l2, limits)


def _from_lambdas(o1, d1, o2, d2, l1, l2, limits):
    p1 = o1 + l1[:, None] * d1
    p2 = o2 + l2[:, None] * d2
    point = 0.5 * (p1 + p2)
    miss = np.linalg.norm(p1 - p2, axis=-1)
    r1 = l1 * np.linalg.norm(d1, axis=-1)
    r2 = l2 * np.linalg.norm(d2, axis=-1)
    cross = np.linalg.norm(np.cross(d1, d2), axis=-1)
    angle = np.degrees(np.arctan2(cross, np.einsum("ij,ij->i", d1, d2)))
    valid = (r1 > 0) & (r2 > 0) & (angle >= limits.min_angle_deg) & (r1 <= limits.max_range_m) & (r2 <= limits.max_range_m)
    return Triangulation(point, point[:, 2], miss, r1, r2, angle, valid)


def triangulate_pixels(cam1, px1, cam2, px2, limits: TriangulationLimits = TriangulationLimits()) -> Triangulation:
    """Triangulate pixel correspondences (N, 2) of two station cameras (:class:`cbh.geometry.station.Camera`)."""
    d1 = cam1.pixel_to_world(px1)
    d2 = cam2.pixel_to_world(px2)
    return triangulate(cam1.position_m, d1, cam2.position_m, d2, limits)


@dataclass(frozen=True)
class MultiView:
    """Features seen in K views, triangulated over all their rays (:func:`triangulate_views`).

    Attributes
    ----------
    point_m : shape (N, 3)
        The point nearest to every ray in the least-squares sense, ENU [m] (NaN: fewer than
        two usable rays, or rays too close to parallel for a point).
    residual_rad : shape (N, K)
        Angle between each view's ray and the direction from its camera to the point [rad]
        (NaN for a view that does not see the feature).
    views : shape (N,), int
        Views that see the feature.
    """

    point_m: Any
    residual_rad: Any
    views: Any

    @property
    def height_m(self):
        return self.point_m[:, 2]

    @property
    def max_residual_rad(self):
        """Each feature's worst view [rad] (NaN where it has no point)."""
        r = self.residual_rad
        xp = _backend(r)
        filled = xp.where(xp.isnan(r), xp.zeros_like(r), r)
        worst = filled.max(axis=1) if xp is np else filled.max(dim=1).values
        return xp.where(xp.isnan(self.point_m[:, 0]), self.point_m[:, 0], worst)


def triangulate_views(origins, dirs, seen=None, min_det: float = 1e-10) -> MultiView:
    """Least-squares triangulation of N features over K views (numpy or torch, one core).

    The point X minimises Σ_k ‖(I − d_k d_kᵀ)(X − o_k)‖², the squared distances from X to
    every ray (unit d_k): the normal equations Σ P_k X = Σ P_k o_k, P_k = I − d_k d_kᵀ, one
    3 × 3 system per feature, solved in closed form (adjugate) for all features at once. For
    K = 2 this is the midpoint of the common perpendicular (:func:`triangulate`). A feature's
    angular residuals (the angle between each ray and the direction from its camera to X)
    expose a mismatch: two rays always meet somewhere, three or more wrong ones do not.

    Parameters
    ----------
    origins : shape (K, 3)
        Camera projection centres, ENU [m].
    dirs : shape (N, K, 3)
        Each feature's ray in each view, ENU (any length; NaN for a view that does not see it).
    seen : shape (N, K), bool, optional
        Which views see each feature (default: finite ``dirs``).
    min_det : float
        Systems whose determinant (of the normalised normal matrix) is below this have no
        point (near-parallel rays): NaN.

    Returns
    -------
    MultiView
    """
    xp = _backend(dirs)
    if dirs.ndim != 3 or dirs.shape[-1] != 3 or tuple(origins.shape) != (dirs.shape[1], 3):
        raise ShapeError(f"triangulate_views: expected dirs (N, K, 3) and origins (K, 3), got "
                         f"{tuple(dirs.shape)} and {tuple(origins.shape)}")
    finite = ~xp.isnan(dirs).any(axis=-1) if xp is np else ~torch_isnan_any(dirs)
    seen = finite if seen is None else (seen & finite)
    # components as (N, K) arrays: no (N, K, 3, 3) outer products
    dx, dy, dz = (xp.nan_to_num(dirs[..., i]) for i in range(3))
    n2 = dx * dx + dy * dy + dz * dz
    seen = seen & (n2 > 0)
    w = seen * 1.0
    inv = w / xp.sqrt(xp.where(seen, n2, n2 * 0 + 1))  # unseen views weigh nothing
    dx, dy, dz = dx * inv, dy * inv, dz * inv
    ox, oy, oz = origins[:, 0][None, :], origins[:, 1][None, :], origins[:, 2][None, :]
    k = w.sum(1)
    sm = lambda a: a.sum(1)  # noqa: E731
    # A = Σ_k w_k (I − d dᵀ), b = Σ_k w_k (o − d (d·o)) (w_k = 0 for an unseen view: d = 0 there)
    A = xp.stack([k - sm(dx * dx), -sm(dx * dy), -sm(dx * dz),
                  -sm(dx * dy), k - sm(dy * dy), -sm(dy * dz),
                  -sm(dx * dz), -sm(dy * dz), k - sm(dz * dz)], -1).reshape(-1, 3, 3)
    do = dx * ox + dy * oy + dz * oz
    b = xp.stack([sm(w * ox - dx * do), sm(w * oy - dy * do), sm(w * oz - dz * do)], -1)
    X = _solve3(xp, A, b, seen.sum(1), min_det)
    vx, vy, vz = X[:, 0:1] - ox, X[:, 1:2] - oy, X[:, 2:3] - oz
    # the angle as atan2(|v × d|, v · d): accurate for the small angles that matter (acos is not)
    cx, cy, cz = vy * dz - vz * dy, vz * dx - vx * dz, vx * dy - vy * dx
    res = (xp.arctan2 if xp is np else xp.atan2)(xp.sqrt(cx * cx + cy * cy + cz * cz), vx * dx + vy * dy + vz * dz)
    res = xp.where(seen & ~xp.isnan(X[:, :1]), res, res * float("nan"))
    return MultiView(X, res, seen.sum(1))


def torch_isnan_any(t):
    """``isnan(t).any(-1)`` for a torch tensor."""
    return t.isnan().any(dim=-1)


def _solve3(xp, A, b, k, min_det: float):
    """X = A⁻¹ b for N symmetric 3 × 3 systems (adjugate); NaN where fewer than 2 views see the
    feature or det(A / k) < ``min_det`` (the rays are too close to parallel to fix a point)."""
    a, bb, c = A[:, 0, 0], A[:, 0, 1], A[:, 0, 2]
    e, f, i = A[:, 1, 1], A[:, 1, 2], A[:, 2, 2]
    c00 = e * i - f * f
    c01 = c * f - bb * i
    c02 = bb * f - c * e
    c11 = a * i - c * c
    c12 = bb * c - a * f
    c22 = a * e - bb * bb
    det = a * c00 + bb * c01 + c * c02
    kk = k * 1.0
    ok = (k >= 2) & (det > min_det * kk ** 3)
    inv = 1.0 / xp.where(ok, det, det * 0 + 1)
    x = (c00 * b[:, 0] + c01 * b[:, 1] + c02 * b[:, 2]) * inv
    y = (c01 * b[:, 0] + c11 * b[:, 1] + c12 * b[:, 2]) * inv
    z = (c02 * b[:, 0] + c12 * b[:, 1] + c22 * b[:, 2]) * inv
    X = xp.stack([x, y, z], axis=1) if xp is np else xp.stack([x, y, z], dim=1)
    return xp.where(ok[:, None], X, X * float("nan"))
