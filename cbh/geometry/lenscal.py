"""Scaramuzza omnidirectional lens calibration from planar chessboards (numerics only).

The model is OCamCalib's (Scaramuzza, Martinelli & Siegwart 2006), written in the cbh camera
frame of docs/conventions.md: a pixel (x = column, y = row) maps through the affine

    x = u + e·v + cx,    y = d·u + c·v + cy

to sensor coordinates (u, v), whose ray is ∝ (u, v, f(r)), r = hypot(u, v), with
f(r) = a0 + a2 r² + … + aN r^N (a0 > 0, a1 = 0 as in the toolbox). This is the same model as
:class:`cbh.geometry.camera.OCamModel`, which the result is returned as.

Method:

1. **Linear initialisation** as OCamCalib's ``calibrate.m``: per view, the rotation's first two
   columns and the in-plane translation from the cross-product constraint (SVD), completed to a
   rotation; then one linear least-squares problem for the polynomial and every view's t3.
   OCamCalib's ``findcenter`` grid search picks the centre that reprojects best.
2. **Bundle adjustment** over all intrinsics and every board pose (Urban, Leitloff & Hinz 2015),
   minimising the reprojection error in pixels with :func:`scipy.optimize.least_squares`
   ("trf" with a sparse Jacobian structure and an optional Huber loss, or "lm").

Gauge: a rotation of every board about the optical axis can be traded against the rotational
part of a general (c, d, e) affine (Urban's published runs drift along it: d ≈ −e). The fit
therefore keeps the affine symmetric, d = e, which removes the gauge and loses nothing.

Board poses are ``(rx, ry, rz, tx, ty, tz)``: a rotation vector [rad] and a translation [board
units, e.g. mm], with ``P_cam = R · (X, Y, 0) + t``.
"""
from __future__ import annotations

import math
import warnings
from dataclasses import dataclass

import numpy as np

from cbh.errors import CalibrationError, check_shape
from cbh.geometry.camera import OCamModel

__all__ = [
    "LensCalConfig",
    "LensCalibration",
    "board_points",
    "xy_from_ocam_rowcol",
    "ocam_rowcol_from_xy",
    "project",
    "project_model",
    "linear_init",
    "find_centre",
    "bundle_adjust",
    "calibrate",
    "fit_pose",
    "held_out_residuals",
    "error_stats",
    "residuals_of",
    "inverse_polynomial",
    "model_from_params",
    "ray_error_px",
    "Coverage",
    "coverage",
    "check_determined",
    "MIN_CORNERS",
    "select_order",
    "inlier_views",
    "ORDERS",
]

_P = np.polynomial.polynomial
LOSSES = ("linear", "huber")
METHODS = ("auto", "trf", "lm")


@dataclass(frozen=True)
class LensCalConfig:
    """Settings of the lens calibration.

    Attributes
    ----------
    order : int
        Degree N of the polynomial f(r) (OCamCalib's "Taylor order"; 4 by default).
    loss : {"linear", "huber"}
        Plain least squares, or Huber's robust loss (method "trf" only).
    huber_px : float
        Residual [px] where the Huber loss turns from quadratic to linear.
    method : {"auto", "trf", "lm"}
        "lm": Levenberg–Marquardt (MINPACK, as OCamCalib and Urban et al.), dense analytic
        Jacobian, plain least squares only; "trf": trust-region reflective with the sparse
        analytic Jacobian, any loss; "auto": "lm" for loss "linear", else "trf". On Fisheye1
        both need 5–6 evaluations from the linear start; on rendered boards "trf" needs ~40
        where "lm" needs 5.
    centre_search : bool
        Run OCamCalib's ``findcenter`` grid search before the bundle adjustment.
    max_nfev : int or None
        Cap on residual evaluations of one bundle adjustment (None: scipy's default).
    reject_sigma : float
        A corner whose residual exceeds ``reject_sigma`` robust standard deviations (1.4826 ×
        the median absolute residual coordinate) and ``reject_floor_px`` is left out and the
        adjustment rerun (at most 3 rounds); 0 keeps every corner. A corner refined against the
        blind centre of a catadioptric image or a lens's rim lands pixels off; Gaussian noise
        passes 8 σ (Euclidean) once in 10¹⁴ corners.
    reject_floor_px : float
        Residuals below this are never outliers [px] (corner detection is not that good).
    """

    order: int = 4
    loss: str = "linear"
    huber_px: float = 1.0
    method: str = "auto"
    centre_search: bool = True
    max_nfev: int | None = None
    reject_sigma: float = 8.0
    reject_floor_px: float = 0.1

    def __post_init__(self):
        if not 2 <= int(self.order) <= 12:
            raise CalibrationError(f"lens calibration: order must be 2…12, got {self.order}")
        if self.loss not in LOSSES:
            raise CalibrationError(f"lens calibration: loss must be one of {', '.join(LOSSES)}, got {self.loss!r}")
        if self.method not in METHODS:
            raise CalibrationError(f"lens calibration: method must be one of {', '.join(METHODS)}, got {self.method!r}")
        if self.method == "lm" and self.loss != "linear":
            raise CalibrationError("lens calibration: Levenberg–Marquardt (method 'lm') supports only loss 'linear'")
        if not self.huber_px > 0:
            raise CalibrationError(f"lens calibration: huber_px must be > 0, got {self.huber_px}")


@dataclass(frozen=True)
class LensCalibration:
    """A calibrated lens and the board poses it was fitted with.

    Attributes
    ----------
    model : OCamModel
        The lens (cbh frame), with ``invpol`` fitted as the toolbox's ``findinvpoly``.
    poses : ndarray, shape (K, 6), float64
        Per view: rotation vector [rad] and translation [board units].
    residuals : tuple of ndarray, each shape (N_i, 2), float64
        Reprojected minus detected corner, per view [px] (outliers included).
    nfev : int
        Residual evaluations of the bundle adjustment.
    inliers : tuple of ndarray, each shape (N_i,), bool, or None
        Corners the final adjustment used (None: all); see ``LensCalConfig.reject_sigma``.
    """

    model: OCamModel
    poses: np.ndarray
    residuals: tuple
    nfev: int = 0
    inliers: tuple | None = None


# --- conventions --------------------------------------------------------------------------

def board_points(cols: int, rows: int, square: float) -> np.ndarray:
    """Inner-corner coordinates of a chessboard in OpenCV's order.

    Parameters
    ----------
    cols, rows : int
        Inner corners per row and number of rows (OpenCV's ``patternSize``).
    square : float
        Side of a square [board units, e.g. mm].

    Returns
    -------
    xy : ndarray, shape (cols·rows, 2), float64
        (X, Y) in the board plane: corner k = j·cols + i lies at (i·square, j·square).
    """
    j, i = np.mgrid[0:rows, 0:cols]
    return np.stack([i.ravel(), j.ravel()], axis=-1).astype(np.float64) * float(square)


def xy_from_ocam_rowcol(rowcol_1based) -> np.ndarray:
    """OCamCalib / MATLAB corners (row, column), 1-based → cbh pixels (x = column, y = row), 0-based.

    >>> xy_from_ocam_rowcol([[1.0, 2.0]]).tolist()
    [[1.0, 0.0]]
    """
    rc = np.asarray(rowcol_1based, dtype=np.float64).reshape(-1, 2)
    return rc[:, ::-1] - 1.0


def ocam_rowcol_from_xy(xy) -> np.ndarray:
    """Inverse of :func:`xy_from_ocam_rowcol`: 0-based (x, y) → 1-based (row, column)."""
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    return xy[:, ::-1] + 1.0


# --- forward model ------------------------------------------------------------------------

def _horner(coef: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Σ coef[k]·x^k by Horner's rule (cheaper than ``polyval`` for the short, hot loops here)."""
    y = np.full_like(x, coef[-1], dtype=np.float64)
    for a in coef[-2::-1]:
        y = y * x + a
    return y


def _radius_of_angle(theta: np.ndarray, poly: np.ndarray, r_max: float) -> np.ndarray:
    """Sensor radius [px] whose ray makes ``theta`` [rad] with the axis: r cosθ = f(r) sinθ.

    A 512-sample table of θ(r) over the increasing part of [0, r_max] gives the start; five
    Newton steps make it exact to rounding. Angles beyond the table's end clamp to its radius.
    """
    r_tab = np.linspace(0.0, r_max, 512)
    th_tab = np.arctan2(r_tab, _horner(poly, r_tab))
    stop = np.flatnonzero(np.diff(th_tab) <= 0)
    n = int(stop[0]) + 1 if stop.size else r_tab.size
    r_tab, th_tab = r_tab[:n], th_tab[:n]
    r = np.interp(theta, th_tab, r_tab)
    ct, st = np.cos(theta), np.sin(theta)
    dpoly = _P.polyder(poly)
    for _ in range(5):
        g = r * ct - _horner(poly, r) * st
        dg = ct - _horner(dpoly, r) * st
        r = np.clip(r - g / np.where(np.abs(dg) > 1e-12, dg, 1e-12), 0.0, r_tab[-1])
    return r


def _sensor_jacobian(P: np.ndarray, poly: np.ndarray, r_max: float):
    """Sensor coordinates of camera-frame points and their derivatives.

    Implicit differentiation of g(r, θ) = r cosθ − f(r) sinθ = 0 gives dr/dθ and dr/da_k;
    (u, v) = r · (Px, Py) / ρ.

    Returns
    -------
    uv : ndarray, shape (M, 2)
        Sensor coordinates [px].
    duv_dP : ndarray, shape (M, 2, 3)
        d(u, v)/dP [px per board unit].
    duv_da : ndarray, shape (M, 2, len(poly))
        d(u, v)/da_k [px per coefficient unit].
    """
    rho = np.maximum(np.hypot(P[:, 0], P[:, 1]), 1e-12)
    n2 = rho**2 + P[:, 2] ** 2
    theta = np.arctan2(rho, P[:, 2])
    r = _radius_of_angle(theta, poly, r_max)
    ct, st = np.cos(theta), np.sin(theta)
    f, fp = _horner(poly, r), _horner(_P.polyder(poly), r)
    D = ct - fp * st
    D = np.where(np.abs(D) > 1e-12, D, 1e-12)
    dth_dP = np.stack([P[:, 2] * P[:, 0] / (rho * n2), P[:, 2] * P[:, 1] / (rho * n2), -rho / n2], axis=-1)
    dr_dP = ((r * st + f * ct) / D)[:, None] * dth_dP
    dr_da = r[:, None] ** np.arange(len(poly))[None, :] * (st / D)[:, None]
    cp, sp = P[:, 0] / rho, P[:, 1] / rho
    zero = np.zeros_like(cp)
    dcp = np.stack([(1 - cp**2) / rho, -cp * sp / rho, zero], axis=-1)
    dsp = np.stack([-cp * sp / rho, (1 - sp**2) / rho, zero], axis=-1)
    uv = np.stack([r * cp, r * sp], axis=-1)
    duv_dP = np.stack([cp[:, None] * dr_dP + r[:, None] * dcp, sp[:, None] * dr_dP + r[:, None] * dsp], axis=1)
    duv_da = np.stack([cp[:, None] * dr_da, sp[:, None] * dr_da], axis=1)
    return uv, duv_dP, duv_da


def project(points_cam, poly, center_xy, affine, r_max: float) -> np.ndarray:
    """Pixels of camera-frame points through the polynomial model (no angle cap).

    Parameters
    ----------
    points_cam : array_like, shape (N, 3), float
        Points or directions in the cbh camera frame (z along the optical axis).
    poly : array_like, shape (M,), float
        f(r) coefficients, lowest degree first, a0 > 0 [px^(1-k)].
    center_xy : array_like, shape (2,), float
        Optical centre (x = column, y = row) [px].
    affine : array_like, shape (3,), float
        (c, d, e) as in :class:`~cbh.geometry.camera.OCamModel`.
    r_max : float
        Largest sensor radius searched [px] (e.g. the image diagonal).

    Returns
    -------
    px : ndarray, shape (N, 2), float64
        Pixel coordinates (x, y) [px].
    """
    P = np.asarray(points_cam, dtype=np.float64).reshape(-1, 3)
    rho = np.hypot(P[:, 0], P[:, 1])
    r = _radius_of_angle(np.arctan2(rho, P[:, 2]), np.asarray(poly, dtype=np.float64), r_max)
    k = np.where(rho > 0, r / np.where(rho > 0, rho, 1.0), 0.0)
    u, v = P[:, 0] * k, P[:, 1] * k
    c, d, e = affine
    return np.stack([u + e * v + center_xy[0], d * u + c * v + center_xy[1]], axis=-1)


def project_model(model: OCamModel, points_cam) -> np.ndarray:
    """:func:`project` with an :class:`OCamModel`'s parameters (no 90° cap, unlike ``ray_to_pixel``)."""
    return project(points_cam, model.poly, model.center_xy, model.affine, math.hypot(model.width, model.height))


def _rotations(rotvecs: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.from_rotvec(np.asarray(rotvecs).reshape(-1, 3)).as_matrix()


def _board_to_cam(poses: np.ndarray, board_xy: np.ndarray, view: np.ndarray) -> np.ndarray:
    """Camera-frame points of stacked board points; ``view[m]`` indexes ``poses``."""
    R = _rotations(poses[:, :3])[view]
    return R[:, :, 0] * board_xy[:, :1] + R[:, :, 1] * board_xy[:, 1:] + poses[view, 3:]


# --- parameter vector of the bundle adjustment --------------------------------------------

@dataclass(frozen=True)
class _Layout:
    """x = [cx, cy, c, d(=e), b0, b2, …, bN, pose_1 (6), …, pose_K (6)], a_k = b_k · r_ref^(1−k)."""

    n_views: int
    order: int
    r_ref: float  # [px] radius that normalises the polynomial coefficients

    @property
    def n_intr(self) -> int:
        return 4 + self.order

    def pack(self, center_xy, c: float, d: float, poly, poses) -> np.ndarray:
        poly = np.asarray(poly, dtype=np.float64)
        k = np.r_[0, np.arange(2, self.order + 1)]
        b = poly[k] * self.r_ref ** (k - 1.0)
        return np.concatenate([[center_xy[0], center_xy[1], c, d], b, np.asarray(poses, float).ravel()])

    def intrinsics(self, x: np.ndarray):
        """(center_xy (2,), affine (c, d, e), poly (order+1,)) of ``x``."""
        k = np.r_[0, np.arange(2, self.order + 1)]
        poly = np.zeros(self.order + 1)
        poly[k] = x[4 : self.n_intr] * self.r_ref ** (1.0 - k)
        return x[:2], (x[2], x[3], x[3]), poly

    def poses(self, x: np.ndarray) -> np.ndarray:
        return x[self.n_intr :].reshape(self.n_views, 6)


@dataclass(frozen=True)
class _Problem:
    """Stacked observations: board point, view index and detected pixel of every corner."""

    board_xy: np.ndarray  # (M, 2) [board units]
    view: np.ndarray  # (M,) int
    obs: np.ndarray  # (M, 2) [px]
    n_views: int
    r_max: float  # [px]

    @classmethod
    def of(cls, views_xy, boards_xy, width: int, height: int) -> "_Problem":
        if len(views_xy) != len(boards_xy):
            raise CalibrationError(f"lens calibration: {len(views_xy)} views but {len(boards_xy)} boards")
        for i, (v, b) in enumerate(zip(views_xy, boards_xy)):
            check_shape(f"view {i} corners", np.asarray(v), (None, 2))
            check_shape(f"view {i} board points", np.asarray(b), (len(v), 2))
        return cls(
            board_xy=np.concatenate([np.asarray(b, float) for b in boards_xy]),
            view=np.concatenate([np.full(len(v), i) for i, v in enumerate(views_xy)]),
            obs=np.concatenate([np.asarray(v, float) for v in views_xy]),
            n_views=len(views_xy),
            r_max=math.hypot(width, height),
        )

    def split(self, per_point: np.ndarray) -> tuple:
        return tuple(per_point[self.view == i] for i in range(self.n_views))


def _reprojection(x: np.ndarray, lay: _Layout, prob: _Problem) -> np.ndarray:
    centre, affine, poly = lay.intrinsics(x)
    P = _board_to_cam(lay.poses(x), prob.board_xy, prob.view)
    return project(P, poly, centre, affine, prob.r_max) - prob.obs


def _skew(w: np.ndarray) -> np.ndarray:
    """[w]×, shape (..., 3, 3), of vectors w, shape (..., 3)."""
    z = np.zeros(w.shape[:-1])
    return np.stack([np.stack([z, -w[..., 2], w[..., 1]], -1), np.stack([w[..., 2], z, -w[..., 0]], -1),
                     np.stack([-w[..., 1], w[..., 0], z], -1)], -2)


def _left_jacobian(rotvecs: np.ndarray) -> np.ndarray:
    """SO(3) left Jacobians, shape (K, 3, 3): R(ω + δ) ≈ Exp(J_l(ω) δ) R(ω)."""
    th = np.linalg.norm(rotvecs, axis=-1)
    small = th < 1e-6
    ts = np.where(small, 1.0, th)
    a = np.where(small, 0.5 - th**2 / 24.0, (1.0 - np.cos(ts)) / ts**2)
    b = np.where(small, 1.0 / 6.0 - th**2 / 120.0, (ts - np.sin(ts)) / ts**3)
    W = _skew(rotvecs)
    return np.eye(3) + a[:, None, None] * W + b[:, None, None] * (W @ W)


def _jacobian(x: np.ndarray, lay: _Layout, prob: _Problem, dense: bool = False):
    """Analytic Jacobian of :func:`_reprojection` (rows x0, y0, x1, y1, …), sparse CSR or dense."""
    from scipy.sparse import coo_matrix

    centre, (c, d, e), poly = lay.intrinsics(x)
    poses = lay.poses(x)
    R = _rotations(poses[:, :3])[prob.view]
    RX = R[:, :, 0] * prob.board_xy[:, :1] + R[:, :, 1] * prob.board_xy[:, 1:]
    uv, duv_dP, duv_da = _sensor_jacobian(RX + poses[prob.view, 3:], poly, prob.r_max)
    A = np.array([[1.0, e], [d, c]])
    dpx_dP = A @ duv_dP  # (M, 2, 3)
    m = len(uv)
    k = np.r_[0, np.arange(2, lay.order + 1)]
    J_in = np.zeros((m, 2, lay.n_intr))
    J_in[:, 0, 0] = 1.0
    J_in[:, 1, 1] = 1.0
    J_in[:, 1, 2] = uv[:, 1]
    J_in[:, 0, 3], J_in[:, 1, 3] = uv[:, 1], uv[:, 0]
    J_in[:, :, 4:] = (A @ duv_da[:, :, k]) * lay.r_ref ** (1.0 - k)
    J_w = dpx_dP @ (-_skew(RX) @ _left_jacobian(poses[:, :3])[prob.view])
    J_pose = np.concatenate([J_w, dpx_dP], axis=2)  # (M, 2, 6)
    rows = np.arange(2 * m)
    r_in = np.repeat(rows, lay.n_intr)
    c_in = np.tile(np.arange(lay.n_intr), 2 * m)
    r_po = np.repeat(rows, 6)
    c_po = (lay.n_intr + 6 * np.repeat(prob.view, 2)[:, None] + np.arange(6)[None, :]).ravel()
    J = coo_matrix((np.r_[J_in.ravel(), J_pose.ravel()], (np.r_[r_in, r_po], np.r_[c_in, c_po])),
                   shape=(2 * m, lay.n_intr + 6 * lay.n_views)).tocsr()
    return J.toarray() if dense else J


# --- linear initialisation (Scaramuzza 2006, OCamCalib calibrate.m) ----------------------

def _padded(arrays) -> tuple[np.ndarray, np.ndarray]:
    """Views of unequal length as one (K, N_max, 2) stack and a (K, N_max) 0/1 weight."""
    n = max(len(a) for a in arrays)
    out = np.zeros((len(arrays), n, 2))
    w = np.zeros((len(arrays), n))
    for i, a in enumerate(arrays):
        out[i, : len(a)] = a
        w[i, : len(a)] = 1.0
    return out, w


def _lstsq(A: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Least squares of tall, thin systems through their column-scaled normal equations.

    ``A`` is (..., M, n) and ``b`` (..., M). LAPACK's factorisations of a tall matrix run
    multi-threaded in OpenBLAS and are ~100× slower on a busy 2-core machine than this n × n
    solve; with unit columns the squared condition number stays far inside float64.
    """
    norm = np.sqrt(np.einsum("...mi,...mi->...i", A, A))
    norm[norm == 0] = 1.0
    An = A / norm[..., None, :]
    G = np.einsum("...mi,...mj->...ij", An, An)  # einsum: no threaded BLAS call
    rhs = np.einsum("...mi,...m->...i", An, b)
    if G.ndim == 2:
        return np.linalg.lstsq(G, rhs, rcond=None)[0] / norm
    return np.linalg.solve(G, rhs[..., None])[..., 0] / norm


def _in_plane(uv, XY, w, r1, r2, t12):
    """Per corner: P1', P2' (in-plane parts of P), r31 X + r32 Y, each (K, N)."""
    X, Y = XY[..., 0], XY[..., 1]
    p1 = r1[:, None, 0] * X + r2[:, None, 0] * Y + t12[:, None, 0]
    p2 = r1[:, None, 1] * X + r2[:, None, 1] * Y + t12[:, None, 1]
    p3 = r1[:, None, 2] * X + r2[:, None, 2] * Y
    return p1, p2, p3


def _poly_rows(uv, XY, w, extr, k: np.ndarray, r_ref):
    """Rows of f(ρ)·P2' − v·t3 = v·p3 and f(ρ)·P1' − u·t3 = u·p3 (a1 = 0).

    Returns the polynomial block (K, 2N, len(k)), the t3 column (K, 2N) and the right side (K, 2N).
    """
    u, v = uv[..., 0], uv[..., 1]
    p1, p2, p3 = _in_plane(uv, XY, w, *extr)
    rr = np.asarray(r_ref, float).reshape(-1, 1, 1)
    s = (np.hypot(u, v)[..., None] / rr) ** k * rr  # (K, N, nk)
    poly = np.concatenate([s * (p2 * w)[..., None], s * (p1 * w)[..., None]], axis=1)
    return poly, np.concatenate([-v * w, -u * w], axis=1), np.concatenate([v * p3 * w, u * p3 * w], axis=1)


def _views_extrinsics(uv: np.ndarray, XY: np.ndarray, w: np.ndarray):
    """r1, r2 (K, 3) and (t1, t2) (K, 2) of every view up to the polynomial, from v·P1 − u·P2 = 0."""
    u, v = uv[..., 0], uv[..., 1]
    X, Y = XY[..., 0], XY[..., 1]
    A = np.stack([X * v, Y * v, -X * u, -Y * u, v, -u], axis=-1) * w[..., None]
    norm = np.sqrt(np.einsum("kni,kni->ki", A, A))
    norm[norm == 0] = 1.0
    An = A / norm[:, None, :]
    sol = np.linalg.eigh(np.einsum("kni,knj->kij", An, An))[1][:, :, 0] / norm  # null vector of A
    R11, R12, R21, R22, T1, T2 = sol.T
    # |r1| = |r2| and r1·r2 = 0 fix the third components: (R31 + i·R32)² = q − 2i·p.
    z = np.sqrt(((R12**2 + R22**2) - (R11**2 + R21**2)) - 2j * (R11 * R12 + R21 * R22))
    scale = 1.0 / np.sqrt(R11**2 + R21**2 + z.real**2)
    r1 = scale[:, None] * np.stack([R11, R21, z.real], axis=-1)
    r2 = scale[:, None] * np.stack([R12, R22, z.imag], axis=-1)
    t12 = scale[:, None] * np.stack([T1, T2], axis=-1)
    # The board must appear in the direction it lies in: (P1, P2) parallel to (u, v).
    p1, p2, _ = _in_plane(uv, XY, w, r1, r2, t12)
    sgn = np.where(np.sum(w * (u * p1 + v * p2), axis=1) < 0, -1.0, 1.0)[:, None]
    r1[:, :2] *= sgn
    r2[:, :2] *= sgn
    t12 *= sgn
    # Of the two tilts ±(R31, R32), keep the one whose own fit f = a0 + a2 ρ² has a0 > 0.
    r_ref = np.maximum(np.max(np.hypot(u, v) * w, axis=1), 1.0)
    poly, t3col, rhs = _poly_rows(uv, XY, w, (r1, r2, t12), np.array([0, 2]), r_ref)
    a0 = _lstsq(np.concatenate([poly, t3col[..., None]], axis=2), rhs)[:, 0]
    tilt = np.where(a0 < 0, -1.0, 1.0)
    r1[:, 2] *= tilt
    r2[:, 2] *= tilt
    return r1, r2, t12


def _linear(uv: np.ndarray, XY: np.ndarray, w: np.ndarray, order: int):
    """OCamCalib's linear calibration on padded, centred views: (poly (order+1,), poses (K, 6))."""
    from scipy.spatial.transform import Rotation

    r1, r2, t12 = _views_extrinsics(uv, XY, w)
    k = np.r_[0, np.arange(2, order + 1)]
    r_ref = max(float(np.max(np.hypot(uv[..., 0], uv[..., 1]) * w)), 1.0)
    poly_rows, t3col, rhs = _poly_rows(uv, XY, w, (r1, r2, t12), k, r_ref)
    n_views, m = t3col.shape
    t3_block = np.zeros((n_views, m, n_views))
    t3_block[np.arange(n_views), :, np.arange(n_views)] = t3col
    A = np.concatenate([poly_rows, t3_block], axis=2).reshape(n_views * m, -1)
    sol = _lstsq(A, rhs.ravel())
    poly = np.zeros(order + 1)
    poly[k] = sol[: len(k)] * r_ref ** (1.0 - k)
    R = np.stack([r1, r2, np.cross(r1, r2)], axis=-1)
    return poly, np.column_stack([Rotation.from_matrix(R).as_rotvec(), t12, sol[len(k) :]])


def linear_init(views_xy, boards_xy, center_xy, order: int):
    """OCamCalib's linear calibration for a given centre (affine identity).

    Parameters
    ----------
    views_xy : sequence of ndarray, each shape (N_i, 2), float
        Detected corners (x, y) [px].
    boards_xy : sequence of ndarray, each shape (N_i, 2), float
        Their board coordinates [board units].
    center_xy : array_like, shape (2,), float
        Assumed optical centre [px].
    order : int
        Polynomial degree N.

    Returns
    -------
    poly : ndarray, shape (order+1,), float64
        f(r) coefficients (a1 = 0).
    poses : ndarray, shape (K, 6), float64
        Rotation vector [rad] and translation [board units] per view.
    """
    obs, w = _padded(views_xy)
    XY, _ = _padded(boards_xy)
    return _linear((obs - np.asarray(center_xy, float)) * w[..., None], XY, w, order)


def _linear_rms(obs, XY, w, center_xy, order: int, r_max: float) -> float:
    """Reprojection RMS [px] of the linear calibration at ``center_xy`` (inf if it fails)."""
    poly, poses = _linear((obs - center_xy) * w[..., None], XY, w, order)
    if not poly[0] > 0:
        return math.inf
    keep = w.ravel() > 0
    view = np.repeat(np.arange(len(obs)), obs.shape[1])[keep]
    P = _board_to_cam(poses, XY.reshape(-1, 2)[keep], view)
    err = project(P, poly, center_xy, (1.0, 0.0, 0.0), r_max) - obs.reshape(-1, 2)[keep]
    rms = float(np.sqrt(np.mean(np.sum(err**2, axis=1))))
    return rms if math.isfinite(rms) else math.inf


def find_centre(views_xy, boards_xy, width: int, height: int, order: int, rounds: int = 3) -> np.ndarray:
    """OCamCalib's ``findcenter``: 5 × 5 grid searches of the centre, each round twice as fine.

    It only has to bring the bundle adjustment within reach: on Fisheye1 and on rendered
    boards the adjustment reaches the same optimum even from the image's middle (28 px off on
    Fisheye1), so three rounds (to ±1/32 of the image) suffice; a lens whose centre lies far
    from the middle is what the search is for.

    Returns
    -------
    center_xy : ndarray, shape (2,), float64
        The centre [px] whose linear calibration reprojects best (first round: ±¼ of the image
        about its middle).
    """
    obs, w = _padded(views_xy)
    XY, _ = _padded(boards_xy)
    r_max = math.hypot(width, height)
    best = np.array([(width - 1) / 2.0, (height - 1) / 2.0])
    span = np.array([width / 4.0, height / 4.0])
    for _ in range(rounds):
        grid = [best + span * np.array([a, b]) for a in np.linspace(-1, 1, 5) for b in np.linspace(-1, 1, 5)]
        rms = [_linear_rms(obs, XY, w, g, order, r_max) for g in grid]
        if math.isfinite(min(rms)):
            best = grid[int(np.argmin(rms))]
        span = span / 2.0
    return best


# --- bundle adjustment --------------------------------------------------------------------

def _least_squares(x0: np.ndarray, lay: _Layout, prob: _Problem, config: LensCalConfig):
    from scipy.optimize import least_squares

    def fun(x):
        return _reprojection(x, lay, prob).ravel()

    # Huber's loss has no continuous second derivative and trf's rescaled steps then creep: on a
    # Fisheye1 held-out fit ftol = 1e-8 takes 384 evaluations, 1e-6 takes 4 and ends 5e-6 px
    # (RMS) from the end point of the long run.
    tol = 1e-10 if config.loss == "linear" else 1e-6
    kw = dict(x_scale="jac", xtol=tol, ftol=tol, gtol=min(tol, 1e-8), max_nfev=config.max_nfev)
    if config.method == "lm" or (config.method == "auto" and config.loss == "linear"):
        return least_squares(fun, x0, jac=lambda x: _jacobian(x, lay, prob, dense=True), method="lm", **kw)
    # lsmr's default tolerances (1e-8) leave the steps so inexact that trf needs ~50× more iterations
    return least_squares(fun, x0, jac=lambda x: _jacobian(x, lay, prob), method="trf", tr_solver="lsmr",
                         tr_options={"atol": 1e-12, "btol": 1e-12}, loss=config.loss, f_scale=config.huber_px, **kw)


def bundle_adjust(views_xy, boards_xy, width: int, height: int, center_xy, affine_cd, poly, poses,
                  config: LensCalConfig = LensCalConfig()):
    """Refine intrinsics and every board pose together (Urban et al. 2015).

    Parameters
    ----------
    views_xy, boards_xy : sequence of ndarray, each shape (N_i, 2), float
        Detected corners [px] and their board coordinates [board units].
    width, height : int
        Image size [px].
    center_xy : array_like, shape (2,), float
        Starting centre [px].
    affine_cd : tuple of float
        Starting (c, d); e is kept equal to d (see the module's note on the gauge).
    poly : array_like, shape (order+1,), float
        Starting f(r) coefficients (a1 is held at 0).
    poses : array_like, shape (K, 6), float
        Starting board poses.
    config : LensCalConfig
        Loss, method and evaluation cap.

    Returns
    -------
    center_xy : ndarray, shape (2,); affine : tuple (c, d, e); poly : ndarray, shape (order+1,);
    poses : ndarray, shape (K, 6); nfev : int
    """
    prob = _Problem.of(views_xy, boards_xy, width, height)
    lay = _Layout(prob.n_views, config.order, r_ref=math.hypot(width, height) / 2.0)
    poly = np.r_[np.asarray(poly, float), np.zeros(max(0, config.order + 1 - len(poly)))][: config.order + 1]
    x0 = lay.pack(center_xy, affine_cd[0], affine_cd[1], poly, poses)
    res = _least_squares(x0, lay, prob, config)
    if not np.all(np.isfinite(res.x)):
        raise CalibrationError("lens calibration: the bundle adjustment diverged (non-finite parameters)")
    centre, affine, poly = lay.intrinsics(res.x)
    return np.array(centre), tuple(float(a) for a in affine), poly, lay.poses(res.x).copy(), int(res.nfev)


MIN_CORNERS = 6
"""Corners a board view needs: its linear start solves 6 unknowns up to scale, one equation per corner."""


def check_determined(corners_per_view, order: int) -> None:
    """Refuse what cannot be fitted: fewer than 2 views, a view with fewer than
    :data:`MIN_CORNERS` corners, or fewer observations (2 per corner) than unknowns
    (4 + ``order`` intrinsics, 6 per view). Each message says how many more are needed.

    Raises
    ------
    CalibrationError
    """
    n = [int(k) for k in corners_per_view]
    if len(n) < 2:
        raise CalibrationError(f"lens calibration needs at least 2 board views, got {len(n)}: add {2 - len(n)} more")
    few = [i for i, k in enumerate(n) if k < MIN_CORNERS]
    if few:
        raise CalibrationError(f"lens calibration: board view {few[0]} has {n[few[0]]} corners; a view's pose needs at "
                               f"least {MIN_CORNERS}: add {MIN_CORNERS - n[few[0]]} more corners to it")
    unknowns, obs = 4 + order + 6 * len(n), 2 * sum(n)
    if obs <= unknowns:
        per_view = 2 * max(n) - 6  # what one more view of the largest board adds
        more = math.ceil((unknowns + 1 - obs) / per_view)
        raise CalibrationError(f"lens calibration: {sum(n)} corners in {len(n)} views give {obs} equations for "
                               f"{unknowns} unknowns (order {order}): add {more} more board view{'' if more == 1 else 's'}")


def _check_monotone(poly: np.ndarray, r_obs_max: float) -> None:
    r = np.linspace(0.0, r_obs_max, 2001)
    if not poly[0] > 0 or np.any(np.diff(np.arctan2(r, _P.polyval(r, poly))) <= 0):
        raise CalibrationError(
            "lens calibration failed: the fitted polynomial does not map radius to angle one-to-one over "
            "the detected corners; try a lower --order or more board poses"
        )


def calibrate(views_xy, boards_xy, width: int, height: int, config: LensCalConfig = LensCalConfig()) -> LensCalibration:
    """Calibrate a lens from detected chessboard corners: linear start, centre search, bundle adjustment.

    Parameters
    ----------
    views_xy : sequence of ndarray, each shape (N_i, 2), float
        Detected corners (x = column, y = row), 0-based [px], one array per image.
    boards_xy : sequence of ndarray, each shape (N_i, 2), float
        Board coordinates of those corners [board units, e.g. mm].
    width, height : int
        Image size [px].
    config : LensCalConfig
        Polynomial order, loss, method.

    Returns
    -------
    LensCalibration
        The model (with its inverse polynomial), the poses and the residuals [px].
    """
    check_determined([len(v) for v in views_xy], config.order)
    if config.centre_search:
        centre = find_centre(views_xy, boards_xy, width, height, config.order)
    else:
        centre = np.array([(width - 1) / 2.0, (height - 1) / 2.0])
    poly, poses = linear_init(views_xy, boards_xy, centre, config.order)
    if not poly[0] > 0:
        raise CalibrationError("lens calibration: the linear initialisation failed (a0 ≤ 0); are the corners ordered?")
    fit = bundle_adjust(views_xy, boards_xy, width, height, centre, (1.0, 0.0), poly, poses, config)
    fit, inliers = _reject_outliers(views_xy, boards_xy, width, height, fit, config)
    centre, affine, poly, poses, nfev = fit
    model = model_from_params(poly, centre, affine, width, height)
    r_obs = max(float(np.max(np.hypot(*(np.asarray(v) - centre).T))) for v in views_xy)
    _check_monotone(poly, r_obs)
    return LensCalibration(model=model, poses=poses, residuals=residuals_of(model, poses, views_xy, boards_xy),
                           nfev=nfev, inliers=inliers)


def _reject_outliers(views_xy, boards_xy, width: int, height: int, fit: tuple, config: LensCalConfig):
    """Leave out corners far beyond the robust spread of the residuals and refit (≤ 3 rounds).

    Returns the final ``bundle_adjust`` result and the inlier masks (None if none was left out).
    A view keeps at least its :data:`MIN_CORNERS` best corners.
    """
    if not config.reject_sigma > 0:
        return fit, None
    keep = [np.ones(len(v), bool) for v in views_xy]
    nfev = fit[4]
    for _ in range(3):
        centre, affine, poly, poses, _ = fit
        model = OCamModel(width=int(width), height=int(height), center_xy=tuple(centre), affine=affine,
                          poly=tuple(poly))
        res = residuals_of(model, poses, views_xy, boards_xy)
        inl = np.concatenate([r[k] for r, k in zip(res, keep)])
        limit = max(config.reject_sigma * 1.4826 * float(np.median(np.abs(inl))), config.reject_floor_px)
        new = []
        for r in res:  # every corner is judged anew: one left out earlier may fit the new lens
            e = np.hypot(r[:, 0], r[:, 1])
            k2 = e <= limit
            if k2.sum() < MIN_CORNERS:
                k2 = e <= np.sort(e)[MIN_CORNERS - 1]
            new.append(k2)
        if all(np.array_equal(a, b) for a, b in zip(new, keep)):
            break
        keep = new
        vs = [np.asarray(v)[k] for v, k in zip(views_xy, keep)]
        bs = [np.asarray(b)[k] for b, k in zip(boards_xy, keep)]
        fit = bundle_adjust(vs, bs, width, height, centre, affine[:2], poly, poses, config)
        nfev += fit[4]
    if all(k.all() for k in keep):
        return fit, None
    return (*fit[:4], nfev), tuple(keep)


def residuals_of(model: OCamModel, poses, views_xy, boards_xy) -> tuple:
    """Reprojected minus detected corners of every view through ``model`` and ``poses``.

    Parameters
    ----------
    model : OCamModel
    poses : array_like, shape (K, 6), float
        Rotation vector [rad] and translation [board units] per view.
    views_xy, boards_xy : sequence of ndarray, each shape (N_i, 2), float
        Detected corners [px] and board coordinates [board units].

    Returns
    -------
    tuple of ndarray, each shape (N_i, 2), float64 [px]
    """
    prob = _Problem.of(views_xy, boards_xy, model.width, model.height)
    P = _board_to_cam(np.asarray(poses, float), prob.board_xy, prob.view)
    return prob.split(project_model(model, P) - prob.obs)


# --- a fixed model: poses, held-out error -------------------------------------------------

def fit_pose(model: OCamModel, view_xy, board_xy, pose0=None, loss: str = "linear", huber_px: float = 1.0):
    """The board pose that best reprojects one view through a fixed model.

    Parameters
    ----------
    model : OCamModel
        The lens, held fixed.
    view_xy, board_xy : ndarray, shape (N, 2), float
        Detected corners [px] and board coordinates [board units].
    pose0 : array_like, shape (6,), optional
        Starting pose; by default the linear per-view estimate with t3 from the model.
    loss, huber_px
        As in :class:`LensCalConfig`.

    Returns
    -------
    pose : ndarray, shape (6,), float64
    residual : ndarray, shape (N, 2), float64
        Reprojected minus detected [px].
    """
    from scipy.optimize import least_squares

    view_xy, board_xy = np.asarray(view_xy, float), np.asarray(board_xy, float)
    if pose0 is None:
        pose0 = _pose_guess(model, view_xy, board_xy)
    zeros = np.zeros(len(view_xy), dtype=int)

    def fun(p):
        P = _board_to_cam(p[None, :], board_xy, zeros)
        return (project_model(model, P) - view_xy).ravel()

    res = least_squares(fun, np.asarray(pose0, float), method="trf", x_scale="jac", loss=loss, f_scale=huber_px,
                        xtol=1e-12, ftol=1e-12, gtol=1e-12)
    return res.x, res.fun.reshape(-1, 2)


def _pose_guess(model: OCamModel, view_xy: np.ndarray, board_xy: np.ndarray) -> np.ndarray:
    """Linear pose of one view through a known model: in-plane part by SVD, t3 by least squares."""
    from scipy.spatial.transform import Rotation

    rays = model.pixel_to_ray(view_xy)
    # sensor coordinates (u, v): the pixel's offset from the centre through the inverse affine (exact
    # at any angle; a model read from a file stops its angle-to-radius table at 90°)
    c, d, e = model.affine
    dx, dy = view_xy[:, 0] - model.center_xy[0], view_xy[:, 1] - model.center_xy[1]
    uv = np.stack([(c * dx - e * dy) / (c - d * e), (dy - d * dx) / (c - d * e)], axis=-1)
    r1, r2, t12 = (a[0] for a in _views_extrinsics(uv[None], board_xy[None], np.ones((1, len(uv)))))
    R = np.column_stack([r1, r2, np.cross(r1, r2)])
    w = (R[:, :2] @ board_xy.T).T  # in-plane parts of P, (N, 3)
    # rays × P = 0 with P = w + (t1, t2, t3): linear in t3 via the x and y components of the cross product
    a = np.r_[rays[:, 0], rays[:, 1]]
    b = np.r_[rays[:, 2] * (w[:, 0] + t12[0]) - rays[:, 0] * w[:, 2],
              rays[:, 2] * (w[:, 1] + t12[1]) - rays[:, 1] * w[:, 2]]
    t3 = float(a @ b / max(a @ a, 1e-12))
    return np.r_[Rotation.from_matrix(R).as_rotvec(), t12, t3]


def held_out_residuals(views_xy, boards_xy, calib: LensCalibration, config: LensCalConfig = LensCalConfig()) -> tuple:
    """Leave-one-image-out residuals: each view reprojected through a lens fitted without it.

    For each view i the bundle adjustment is rerun on the other views (starting from ``calib``),
    then view i's pose alone is fitted through that model, and its residuals are kept.

    Returns
    -------
    residuals : tuple of ndarray, each shape (N_i, 2), float64
        Held-out reprojected minus detected corner, per view [px].
    """
    m = calib.model
    out = []
    for i in range(len(views_xy)):
        keep = [j for j in range(len(views_xy)) if j != i]
        vs, bs = [views_xy[j] for j in keep], [boards_xy[j] for j in keep]
        centre, affine, poly, _, _ = bundle_adjust(vs, bs, m.width, m.height, m.center_xy, m.affine[:2], m.poly,
                                                   calib.poses[keep], config)
        loo = model_from_params(poly, centre, affine, m.width, m.height, invpol=False)
        out.append(fit_pose(loo, views_xy[i], boards_xy[i], calib.poses[i])[1])
    return tuple(out)


ORDERS = (3, 4, 5, 6, 7, 8)
"""Polynomial degrees :func:`select_order` tries."""


def inlier_views(calib: LensCalibration, views_xy, boards_xy) -> tuple[list, list]:
    """The corners (and their board points) that ``calib``'s final adjustment used, per view."""
    if calib.inliers is None:
        return list(views_xy), list(boards_xy)
    return ([np.asarray(v)[k] for v, k in zip(views_xy, calib.inliers)],
            [np.asarray(b)[k] for b, k in zip(boards_xy, calib.inliers)])


def select_order(views_xy, boards_xy, width: int, height: int, config: LensCalConfig = LensCalConfig(),
                 orders=ORDERS, tolerance: float = 0.01, tolerance_px: float = 0.002):
    """The polynomial degree chosen by cross-validation: the lowest whose leave-one-image-out error
    is within ``tolerance`` (relative) or ``tolerance_px`` of the lowest of all.

    A degree too low leaves a systematic error in every image; one too high fits the corners of
    the images it has and strays between them, which the held-out error shows. On Fisheye1:
    degree 3, 4, 5, 6 give 0.594, 0.430, 0.415, 0.414 px held out (per-point Euclidean RMS).
    Degrees that cannot be determined from the corners, or whose fit fails, are skipped.

    Returns
    -------
    calib : LensCalibration
        The chosen degree's calibration.
    config : LensCalConfig
        ``config`` with that degree.
    held : tuple of ndarray
        Its held-out residuals, per view, inlier corners only [px].
    table : dict
        Degree → held-out per-point Euclidean RMS [px] (NaN where the fit failed).
    """
    from dataclasses import replace

    fits, table, failure = {}, {}, None
    for order in orders:
        cfg = replace(config, order=int(order))
        try:
            calib = calibrate(views_xy, boards_xy, width, height, cfg)
            vs, bs = inlier_views(calib, views_xy, boards_xy)
            held = held_out_residuals(vs, bs, calib, cfg)
        except CalibrationError as exc:
            failure, table[int(order)] = exc, math.nan
            continue
        table[int(order)] = error_stats(np.concatenate(held))["rms_euclid_px"]
        fits[int(order)] = (calib, cfg, held)
    if not fits:
        raise failure
    best = min(table[o] for o in fits)
    chosen = min(o for o in fits if table[o] <= max(best * (1.0 + tolerance), best + tolerance_px))
    return (*fits[chosen], table)


def error_stats(residuals) -> dict:
    """Reprojection error statistics of a set of residual vectors.

    Parameters
    ----------
    residuals : array_like, shape (N, 2), float
        Reprojected minus detected [px].

    Returns
    -------
    dict
        ``rms_euclid_px`` (per-point Euclidean RMS, OCamCalib's definition), ``rms_coord_px``
        (per-coordinate RMS, Urban's: smaller by √2), ``mean_euclid_px``, ``max_euclid_px``
        [px], and ``n_points``.
    """
    r = np.asarray(residuals, dtype=np.float64).reshape(-1, 2)
    e = np.hypot(r[:, 0], r[:, 1])
    return {
        "rms_euclid_px": float(np.sqrt(np.mean(e**2))),
        "rms_coord_px": float(np.sqrt(np.mean(r**2))),
        "mean_euclid_px": float(np.mean(e)),
        "max_euclid_px": float(np.max(e)),
        "n_points": int(len(e)),
    }


# --- the toolbox's inverse polynomial -----------------------------------------------------

def _radius_of_t(poly: np.ndarray, t: np.ndarray, radius: float) -> np.ndarray:
    """OCamCalib's ``invFUN``: smallest root r ∈ [0, radius) of f(r) = −tan(t)·r (NaN if none)."""
    out = np.full(t.shape, np.nan)
    for i, ti in enumerate(t):
        p = np.array(poly, dtype=np.float64)
        p[1] += math.tan(ti)
        roots = np.roots(p[::-1])
        real = roots[np.abs(roots.imag) < 1e-9].real
        ok = real[(real >= 0) & (real < radius)]
        if ok.size:
            out[i] = ok.min()
    return out


def inverse_polynomial(poly, width: int, height: int, max_err_px: float = 0.01, max_degree: int = 30) -> tuple:
    """The toolbox's ``findinvpoly``: ρ(t) of the lowest degree whose largest error is < ``max_err_px``.

    t = θ − 90° [rad] (the toolbox's ``atan(z / hypot(x, y))``), sampled as the toolbox does
    (−π/2 … 1.2 rad in 0.01 steps) where the radius stays within half the image diagonal.

    Returns
    -------
    invpol : tuple of float
        Coefficients of ρ(t), lowest degree first [px·rad^-k].
    """
    t = np.arange(-math.pi / 2, 1.2 + 1e-9, 0.01)
    r = _radius_of_t(np.asarray(poly, float), t, math.hypot(width / 2.0, height / 2.0))
    t, r = t[np.isfinite(r)], r[np.isfinite(r)]
    if t.size < 3:
        raise CalibrationError("lens calibration: the model reaches no angle within the image")
    rank_warning = getattr(np, "exceptions", np).RankWarning
    for n in range(2, max_degree + 1):
        with warnings.catch_warnings():  # a high degree is ill-conditioned; the error check below decides
            warnings.simplefilter("ignore", rank_warning)
            coef = _P.polyfit(t, r, n)
        if np.max(np.abs(_P.polyval(t, coef) - r)) < max_err_px:
            return tuple(float(c) for c in coef)
    raise CalibrationError(f"lens calibration: no inverse polynomial up to degree {max_degree} is within {max_err_px} px")


def model_from_params(poly, center_xy, affine, width: int, height: int, invpol: bool = True) -> OCamModel:
    """An :class:`OCamModel` (cbh frame) with the toolbox's inverse polynomial (``invpol=True``)."""
    poly = tuple(float(a) for a in poly)
    if poly[1] == 0.0:
        poly = (poly[0], -0.0, *poly[2:])  # the file's ss = −poly then reads "0.000000e+00", not "-0.000000e+00"
    inv = inverse_polynomial(poly, width, height) if invpol else None
    return OCamModel(width=int(width), height=int(height), center_xy=(float(center_xy[0]), float(center_xy[1])),
                     affine=tuple(float(a) for a in affine), poly=poly, invpol=inv)


# --- checks against a known lens ----------------------------------------------------------

def ray_error_px(estimate: OCamModel, truth: OCamModel, max_theta_deg: float, step_px: float = 4.0,
                 min_theta_deg: float = 0.0) -> dict:
    """How far the estimated rays land from where the true lens images them [px].

    Every ``step_px``-th pixel between ``min_theta_deg`` and ``max_theta_deg`` (true lens; a
    catadioptric camera's annulus has a blind centre) is cast through
    ``estimate``, turned about the optical axis by the single best angle (the one gauge a
    chessboard calibration cannot fix when the true affine has d ≠ e), and imaged through
    ``truth``.

    Returns
    -------
    dict
        ``rms_px``, ``max_px`` [px], ``rotation_deg`` (the alignment angle) and ``n_pixels``.
    """
    ys, xs = np.mgrid[0 : truth.height : step_px, 0 : truth.width : step_px]
    px = np.stack([xs.ravel(), ys.ravel()], axis=-1).astype(float)
    th = truth.theta_of_pixel(px)
    px = px[(th <= max_theta_deg) & (th >= min_theta_deg)]
    a, b = estimate.pixel_to_ray(px), truth.pixel_to_ray(px)
    phi = math.atan2(np.sum(a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]), np.sum(a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1]))
    cs, sn = math.cos(phi), math.sin(phi)
    a = np.stack([cs * a[:, 0] - sn * a[:, 1], sn * a[:, 0] + cs * a[:, 1], a[:, 2]], axis=-1)
    err = np.hypot(*(project_model(truth, a) - px).T)
    return {"rms_px": float(np.sqrt(np.mean(err**2))), "max_px": float(err.max()),
            "rotation_deg": math.degrees(phi), "n_pixels": int(len(err))}


# --- coverage of the field of view --------------------------------------------------------

ZONES = (("centre", 0.0, 30.0, 1), ("middle", 30.0, 60.0, 1), ("periphery", 60.0, math.inf, 2))
"""(name, from [deg], to [deg], boards wanted): a board counts for a zone if a quarter of its corners lie there."""

SIDES = ("right", "bottom", "left", "top")  # image directions of the azimuth quadrants, x right, y down


@dataclass(frozen=True)
class Coverage:
    """Where the corners fell in the field of view, and where the model goes beyond them.

    A zone with too few boards is a gap, not a failure: the polynomial is still fitted, but
    between the axis and the innermost corner, and beyond the outermost one, it is
    extrapolated (a catadioptric camera never sees its centre: the mirror shows the camera).

    Attributes
    ----------
    theta_deg : tuple of ndarray
        Angle from the optical axis of every corner, per view [deg].
    frame_theta_deg : float
        Largest angle the model reaches inside the image frame, on the part of the image where
        the angle still grows with the radius [deg].
    boards_per_zone : dict
        Zone name → number of boards with at least a quarter of their corners in it.
    periphery_sides : dict
        Image side → corners beyond 60° towards it.
    """

    theta_deg: tuple
    frame_theta_deg: float
    boards_per_zone: dict
    periphery_sides: dict

    @property
    def data_theta_deg(self) -> tuple[float, float]:
        """Smallest and largest angle of any corner from the axis [deg]."""
        return (float(min(np.min(t) for t in self.theta_deg)), float(max(np.max(t) for t in self.theta_deg)))

    def gaps(self) -> list[dict]:
        """The zones the frame reaches that have too few boards.

        Returns
        -------
        list of dict
            ``zone``, ``from_deg``, ``to_deg`` (None: no outer limit), ``boards``, ``wanted``,
            ``extrapolated_deg`` ([from, to] of the zone's angles no corner backs, [deg]) and
            ``empty_sides`` (image sides without corners beyond 60°; periphery only).
        """
        lo_data, hi_data = self.data_theta_deg
        out = []
        for name, lo, hi, need in ZONES:
            if self.frame_theta_deg < lo + 10.0 or self.boards_per_zone[name] >= need:
                continue  # the lens does not reach this zone within the frame, or it is covered
            top = min(hi, self.frame_theta_deg)
            span = [lo, min(top, lo_data)] if lo < lo_data else [max(lo, hi_data), top] if top > hi_data else None
            out.append({"zone": name, "from_deg": lo, "to_deg": None if math.isinf(hi) else hi,
                        "boards": self.boards_per_zone[name], "wanted": need,
                        "extrapolated_deg": None if span is None or span[1] <= span[0] else [round(span[0], 1), round(span[1], 1)],
                        "empty_sides": [s for s in SIDES if self.periphery_sides[s] == 0] if name == "periphery" else []})
        return out

    def extrapolation(self) -> dict:
        """How far the model reaches beyond the corners that back it [deg].

        Returns
        -------
        dict
            ``data_theta_deg`` ([innermost, outermost] corner), ``frame_theta_deg``, ``inward_deg``
            (from the axis to the innermost corner) and ``outward_deg`` (from the outermost corner
            to the frame's reach; 0 if the corners reach it).
        """
        lo, hi = self.data_theta_deg
        return {"data_theta_deg": [round(lo, 2), round(hi, 2)], "frame_theta_deg": round(self.frame_theta_deg, 2),
                "inward_deg": round(lo, 2), "outward_deg": round(max(0.0, self.frame_theta_deg - hi), 2)}

    def warnings(self) -> list[str]:
        """One sentence per gap: which zone, where the model is extrapolated, what to add (empty if none)."""
        out = []
        for g in self.gaps():
            span = (f"between {g['from_deg']:.0f}° and {g['to_deg']:.0f}°" if g["to_deg"] is not None
                    else f"beyond {g['from_deg']:.0f}°")
            have, need = g["boards"], g["wanted"]
            text = (f"the {g['zone']} of the field of view ({span} from the axis) is covered by {have} board"
                    f"{'' if have == 1 else 's'} ({need} wanted)")
            if g["extrapolated_deg"] is not None:
                a, b = g["extrapolated_deg"]
                text += f": the model is extrapolated from {a:.0f}° to {b:.0f}° there"
            text += f"; add {need - have} more there" + (f", towards the image's {', '.join(g['empty_sides'])}"
                                                       if g["empty_sides"] else "")
            out.append(text)
        return out


def _increasing_radius(poly, r_max: float) -> float:
    """Largest r ≤ ``r_max`` [px] up to which θ(r) = atan2(r, f(r)) grows from the axis."""
    r = np.linspace(0.0, r_max, 4001)
    stop = np.flatnonzero(np.diff(np.arctan2(r, _P.polyval(r, np.asarray(poly, float)))) <= 0)
    return float(r[stop[0]]) if stop.size else float(r_max)


def coverage(model: OCamModel, views_xy) -> Coverage:
    """Where the detected corners fall in the field of view of a calibrated lens.

    Parameters
    ----------
    model : OCamModel
        The calibrated lens.
    views_xy : sequence of ndarray, each shape (N_i, 2), float
        Detected corners (x, y) [px], one array per board.

    Returns
    -------
    Coverage
        Angles of the corners [deg], boards per zone of :data:`ZONES`, corners beyond 60° per
        image side; :meth:`Coverage.gaps` and :meth:`Coverage.warnings` say what is missing,
        :meth:`Coverage.extrapolation` how far the model goes beyond the corners.
    """
    thetas = tuple(model.theta_of_pixel(np.asarray(v, float)) for v in views_xy)
    w, h = model.width, model.height
    frame = np.array([[x, y] for x in np.linspace(0, w - 1, 33) for y in np.linspace(0, h - 1, 25)])
    c, d, e = model.affine
    dx, dy = frame[:, 0] - model.center_xy[0], frame[:, 1] - model.center_xy[1]
    r_frame = float(np.max(np.hypot((c * dx - e * dy) / (c - d * e), (dy - d * dx) / (c - d * e))))
    r_top = _increasing_radius(model.poly, r_frame)
    frame_theta = math.degrees(math.atan2(r_top, float(_P.polyval(r_top, np.asarray(model.poly)))))
    per_zone = {}
    for name, lo, hi, _ in ZONES:
        per_zone[name] = int(sum(np.mean((t >= lo) & (t < hi)) >= 0.25 for t in thetas))
    sides = dict.fromkeys(SIDES, 0)
    for v, t in zip(views_xy, thetas):
        off = np.asarray(v, float)[t >= 60.0] - np.asarray(model.center_xy)
        q = (np.round(np.arctan2(off[:, 1], off[:, 0]) / (math.pi / 2)).astype(int)) % 4
        for k in range(4):
            sides[SIDES[k]] += int(np.sum(q == k))
    return Coverage(theta_deg=thetas, frame_theta_deg=frame_theta, boards_per_zone=per_zone, periphery_sides=sides)
