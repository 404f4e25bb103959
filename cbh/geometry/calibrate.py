"""Camera orientation from the sun track and from cloud correspondences (numerics, no I/O).

Two kinds of observation fix the rotations ``R_world_from_cam`` of a station's cameras:

- **Sun**: a camera-frame unit ray ``s`` towards the detected sun and the apparent ENU sun
  direction ``d`` (pvlib) at the frame's time: ``R · s = d``. A track over enough of the day
  fixes all three angles of that camera (absolute orientation).
- **Epipolar** (clouds): a correspondence between camera ``a`` and camera ``b`` whose
  positions are known, so the baseline ``t = p_b − p_a`` is known: the two ENU rays and the
  baseline are coplanar, ``(R_b r_b) · (t × R_a r_a) = 0``. Many correspondences over the sky
  fix the rotation of ``b`` relative to ``a`` (all three angles; the cloud heights need not be
  known), and also all of the pair's common rotation except the turn about the baseline.

:func:`fit_orientations` fits every camera jointly, each rotation as a small rotation vector
``ω`` applied in the camera frame to its starting value (``R = R0 · exp(ω)``), by robust
least squares (scipy ``least_squares``, Huber loss) on residuals in units of their expected
noise. When no camera has a sun track, the reference camera is held at its starting value
(relative orientation only). Uncertainty: the Gauss-Newton covariance of the inliers, scaled by
the measured residual level, mapped onto (yaw, pitch, roll); an angle whose standard deviation
exceeds ``max_sigma_deg`` is *not determined* (:class:`~cbh.errors.CalibrationError`).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from cbh.errors import CalibrationError
from cbh.geometry.station import angles_from_rotation

__all__ = [
    "SunObservations", "PairObservations", "SunPairObservations", "CameraFit", "OrientationFit",
    "epipolar_angle_rad", "fit_orientations", "rotation_from_far_matches", "rotvec_to_matrix",
]

_ANGLES = ("yaw", "pitch", "roll")


def rotvec_to_matrix(w) -> np.ndarray:
    """Rotation matrix (3, 3) of a rotation vector ``w`` (3,) [rad] (Rodrigues)."""
    w = np.asarray(w, dtype=np.float64)
    th = float(np.linalg.norm(w))
    if th < 1e-15:
        return np.eye(3)
    k = w / th
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + math.sin(th) * K + (1 - math.cos(th)) * (K @ K)


def epipolar_angle_rad(d1_world: np.ndarray, d2_world: np.ndarray, baseline_m: np.ndarray) -> np.ndarray:
    """Signed angle [rad] of ray 2 off the epipolar plane spanned by the baseline and ray 1.

    Parameters
    ----------
    d1_world, d2_world : ndarray, shape (N, 3)
        Unit ENU rays of camera 1 and camera 2.
    baseline_m : ndarray, shape (3,)
        Camera 2's position minus camera 1's [m].

    Returns
    -------
    ndarray, shape (N,), float64
        ``asin(d2 · n̂)`` with ``n̂ = t × d1 / |t × d1|``; 0 for a perfect geometry. A ray miss
        of ``m`` metres at range ``ρ`` is an epipolar angle of about ``m / ρ``.
    """
    n = np.cross(np.asarray(baseline_m, np.float64)[None, :], np.asarray(d1_world, np.float64))
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    return np.arcsin(np.clip(np.einsum("ij,ij->i", np.asarray(d2_world, np.float64), n), -1.0, 1.0))


@dataclass
class SunObservations:
    """Sun detections of one camera: ``rays_cam`` (N, 3) camera-frame unit rays to the detected
    sun, ``sun_enu`` (N, 3) unit ENU directions of the apparent sun at the frames' times,
    ``sigma_deg`` the expected per-frame detection noise [deg]."""

    rays_cam: np.ndarray
    sun_enu: np.ndarray
    sigma_deg: float = 0.05


@dataclass
class PairObservations:
    """Correspondences between camera ``cam_a`` and camera ``cam_b``: ``rays_a``, ``rays_b``
    (N, 3) camera-frame unit rays, ``baseline_m`` (3,) = position b − position a [m],
    ``sigma_rad`` the expected epipolar noise of one correspondence [rad]."""

    cam_a: str
    cam_b: str
    rays_a: np.ndarray
    rays_b: np.ndarray
    baseline_m: np.ndarray
    sigma_rad: float
    method: str = ""


@dataclass
class SunPairObservations:
    """The sun seen by camera ``cam_a`` and camera ``cam_b`` in the same frame pair: ``rays_a``,
    ``rays_b`` (N, 3) camera-frame unit rays. The sun is at infinity, so ``R_a · rays_a =
    R_b · rays_b`` whatever the station's true north: this pins the relative rotation about the
    axes across the sun direction, including the turn that shifts clouds along their epipolar
    curves (which the epipolar constraint cannot tell from a height change)."""

    cam_a: str
    cam_b: str
    rays_a: np.ndarray
    rays_b: np.ndarray
    sigma_deg: float = 0.07


@dataclass
class CameraFit:
    """One camera's result: angles [deg] before/after, their standard deviations [deg], the sun
    residuals [deg] per detection (NaN where not fitted), the sun residual RMS [deg]."""

    name: str
    angles_before_deg: tuple[float, float, float]
    angles_deg: tuple[float, float, float]
    sigma_deg: tuple[float, float, float]
    R_world_from_cam: np.ndarray
    sun_residual_deg: np.ndarray = field(default_factory=lambda: np.zeros(0))
    sun_inliers: int = 0

    @property
    def sun_rms_deg(self) -> float:
        r = self.sun_residual_deg
        return float(np.sqrt(np.mean(r ** 2))) if len(r) else math.nan


@dataclass
class OrientationFit:
    """Result of :func:`fit_orientations`: per camera, and per PairObservations the epipolar
    residuals [rad] after the fit, and whether the absolute frame came from the sun."""

    cameras: dict[str, CameraFit]
    epipolar_rad: list[np.ndarray]  # per PairObservations, in order
    absolute: bool
    reference: str
    cost: float = math.nan  # final robust cost (½ Σ ρ(r²), residuals in noise units)


def _angle_jacobian(R0: np.ndarray, w: np.ndarray) -> np.ndarray:
    """d(yaw, pitch, roll)/dω [deg/rad] at ``R0 · exp(ω)``, shape (3, 3) (central differences)."""
    J = np.zeros((3, 3))
    h = 1e-6
    for k in range(3):
        dw = np.zeros(3)
        dw[k] = h
        a = np.array(angles_from_rotation(R0 @ rotvec_to_matrix(w + dw)))
        b = np.array(angles_from_rotation(R0 @ rotvec_to_matrix(w - dw)))
        d = (a - b + 180.0) % 360.0 - 180.0
        J[:, k] = d / (2 * h)
    return J


def fit_orientations(
    R0: dict[str, np.ndarray],
    sun: dict[str, SunObservations],
    pairs: list[PairObservations],
    *,
    reference: str,
    sun_pairs: list[SunPairObservations] = (),
    huber: float = 2.0,
    max_sigma_deg: float = 0.5,
    loss: str = "huber",
) -> OrientationFit:
    """Fit every camera's rotation to the sun detections and the correspondences, jointly.

    Parameters
    ----------
    R0 : dict of str → ndarray (3, 3)
        Starting rotation ``R_world_from_cam`` of every camera to fit (the station file's).
    sun : dict of str → SunObservations
        Sun tracks (cameras without one are absent). Empty: relative orientation only, the
        ``reference`` camera is held at ``R0``.
    pairs : list of PairObservations
        Correspondences; every camera except a sun-fixed one must appear in some pair.
    sun_pairs : list of SunPairObservations
        The sun seen by two cameras at once (relative constraint, no absolute frame needed).
        Trusted (plain least squares, not down-weighted): each detection passed the shape
        tests of :func:`~cbh.pipeline.sundetect.detect_sun`, and one frame with the sun in both
        cameras must be able to pin the turn the clouds cannot; the caller removes outliers.
    reference : str
        The camera that is held fixed when no sun track exists.
    huber : float
        Robust loss scale in units of each residual's expected noise.
    loss : str
        scipy loss: "huber" (default), or "cauchy" for a first fit through many mismatches.
    max_sigma_deg : float
        An angle with a larger standard deviation is not determined: CalibrationError.

    Returns
    -------
    OrientationFit
    """
    problem = _OrientationProblem(R0, sun, pairs, reference, tuple(sun_pairs))
    sol = problem.solve(loss, huber)
    cov, degenerate = _covariance(sol, huber)
    R = problem.rotations(sol.x)
    fits = {}
    for n in problem.names:
        sig = problem.sigma_deg(n, sol.x, cov, degenerate)
        bad = [a for a, s in zip(_ANGLES, sig) if not s <= max_sigma_deg]
        if bad:
            raise CalibrationError(
                f"camera {n!r}: the data cannot determine its {', '.join(bad)} "
                f"(standard deviation {max(sig):.2g} deg > {max_sigma_deg} deg); "
                "give frames with the sun over more of the day, or more cloud pairs")
        sres, ninl = problem.sun_residuals_deg(n, R[n], huber)
        fits[n] = CameraFit(n, angles_from_rotation(R0[n]), angles_from_rotation(R[n]), sig, R[n], sres, ninl)
    return OrientationFit(fits, problem.epipolar(R), problem.absolute, reference, float(sol.cost))


class _OrientationProblem:
    """The least-squares problem of :func:`fit_orientations`: the free cameras (every camera
    with a sun track; without any, all but the reference), each a rotation vector ``ω``
    applied in the camera frame to its start, and the residuals in units of their noise."""

    def __init__(self, R0, sun, pairs, reference, sun_pairs):
        self.R0, self.sun, self.sun_pairs = R0, sun, sun_pairs
        self.names = list(R0)
        self.absolute = bool(sun)
        free = [n for n in self.names if self.absolute or n != reference]
        self.idx = {n: i for i, n in enumerate(free)}
        for n in self.names:
            if n not in sun and not any(n in (p.cam_a, p.cam_b) for p in pairs) and n in self.idx:
                raise CalibrationError(f"camera {n!r}: neither a sun track nor correspondences determine its orientation")
        self.sun_data = {n: (np.asarray(o.rays_cam, np.float64), np.asarray(o.sun_enu, np.float64),
                             1.0 / math.radians(o.sigma_deg)) for n, o in sun.items() if n in R0}
        self.pair_data = [(p.cam_a, p.cam_b, np.asarray(p.rays_a, np.float64), np.asarray(p.rays_b, np.float64),
                           np.asarray(p.baseline_m, np.float64), 1.0 / p.sigma_rad) for p in pairs]

    def rotations(self, x: np.ndarray) -> dict[str, np.ndarray]:
        """Every camera's ``R_world_from_cam`` at the parameters ``x`` (3 per free camera)."""
        idx = self.idx
        return {n: self.R0[n] @ rotvec_to_matrix(x[3 * idx[n]: 3 * idx[n] + 3]) if n in idx else self.R0[n]
                for n in self.names}

    def residuals(self, x: np.ndarray) -> np.ndarray:
        """Sun rows (cross product of fitted and apparent sun), epipolar rows, then the
        sun-pair rows, each in units of its expected noise."""
        R = self.rotations(x)
        parts = []
        for n, (s, d, wgt) in self.sun_data.items():
            parts.append((np.cross(s @ R[n].T, d) * wgt).ravel())
        for a, b, ra, rb, t, wgt in self.pair_data:
            parts.append(epipolar_angle_rad(ra @ R[a].T, rb @ R[b].T, t) * wgt)
        for sp in self.sun_pairs:
            parts.append((np.cross(sp.rays_a @ R[sp.cam_a].T, sp.rays_b @ R[sp.cam_b].T)
                          / math.radians(sp.sigma_deg)).ravel())
        return np.concatenate(parts) if parts else np.zeros(0)

    def solve(self, loss: str, huber: float):
        """Robust least squares (scipy ``least_squares``), twice: the second pass starts at the
        first solution, so the robust weights fit the final residuals."""
        from scipy.optimize import least_squares

        x0 = np.zeros(3 * len(self.idx))
        n_res = len(self.residuals(x0))
        if n_res < len(x0) + 1:
            raise CalibrationError(f"too few observations ({n_res} residuals) for {len(self.idx)} camera orientations")
        # the sun-pair rows (last) are trusted: plain least squares; every other row gets the robust loss
        n_trusted = sum(3 * len(sp.rays_a) for sp in self.sun_pairs)
        robust = np.ones(n_res, bool)
        if n_trusted:
            robust[n_res - n_trusted:] = False
        rloss = _row_loss(loss, robust)
        sol = least_squares(self.residuals, x0, loss=rloss, f_scale=huber, x_scale=1e-2, method="trf")
        return least_squares(self.residuals, sol.x, loss=rloss, f_scale=huber, x_scale=1e-2, method="trf")

    def sigma_deg(self, n: str, x: np.ndarray, cov: np.ndarray, degenerate: bool) -> tuple[float, float, float]:
        """Standard deviations of camera ``n``'s (yaw, pitch, roll) [deg] (0 for a held camera)."""
        if n not in self.idx:
            return (0.0, 0.0, 0.0)
        if degenerate:
            return (math.inf,) * 3
        i = self.idx[n]
        Ja = _angle_jacobian(self.R0[n], x[3 * i: 3 * i + 3])
        c = Ja @ cov[3 * i: 3 * i + 3, 3 * i: 3 * i + 3] @ Ja.T
        return tuple(float(math.sqrt(max(v, 0.0))) for v in np.diag(c))

    def sun_residuals_deg(self, n: str, R: np.ndarray, huber: float) -> tuple[np.ndarray, int]:
        """Camera ``n``'s angle between fitted and apparent sun per detection [deg], and how many
        are inliers (within 3 × ``huber`` noise levels)."""
        if n not in self.sun_data:
            return np.zeros(0), 0
        s, d, _ = self.sun_data[n]
        sres = np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", s @ R.T, d), -1.0, 1.0)))
        return sres, int(np.sum(sres <= 3.0 * huber * self.sun[n].sigma_deg))

    def epipolar(self, R: dict[str, np.ndarray]) -> list[np.ndarray]:
        """Epipolar residuals [rad] of every PairObservations under the rotations ``R``."""
        return [epipolar_angle_rad(ra @ R[a].T, rb @ R[b].T, t) for a, b, ra, rb, t, _ in self.pair_data]


def _covariance(sol, huber: float) -> tuple[np.ndarray, bool]:
    """Gauss-Newton covariance of the parameters from the inlier rows of a ``least_squares``
    solution, and whether the problem is degenerate (a singular value 1e-6 of the largest).

    The measured noise level (robust: 1.4826 × median |r|, in units of the expected noise)
    scales the covariance, so a data set noisier than assumed gets wider uncertainties (never
    below the expected noise: a suspiciously clean fit does not shrink the uncertainty).
    """
    r = sol.fun
    inl = np.abs(r) <= 3.0 * huber
    J = sol.jac[inl]
    s2 = max(float((1.4826 * np.median(np.abs(r))) ** 2) * len(r) / max(int(inl.sum()), 1), 1.0)
    try:
        cov = np.linalg.pinv(J.T @ J) * s2
        sv = np.linalg.svd(J, compute_uv=False)
    except np.linalg.LinAlgError:  # pragma: no cover
        raise CalibrationError("the orientation fit is degenerate") from None
    return cov, bool(sv.min() < 1e-6 * sv.max())


def _row_loss(kind: str, robust: np.ndarray):
    """A scipy ``least_squares`` loss callable: ``kind`` ("huber" or "cauchy") on the rows where
    ``robust`` is True, plain squares elsewhere. Returns rho, rho', rho'' of z = (f / f_scale)²."""
    if kind not in ("huber", "cauchy"):
        raise ValueError(f"unknown loss {kind!r}")

    def loss(z):
        out = np.empty((3, z.size))
        out[0], out[1], out[2] = z, 1.0, 0.0
        zr = z[robust]
        if kind == "huber":
            big = zr > 1.0
            sq = np.sqrt(np.where(big, zr, 1.0))
            out[0, robust] = np.where(big, 2.0 * sq - 1.0, zr)
            out[1, robust] = np.where(big, 1.0 / sq, 1.0)
            out[2, robust] = np.where(big, -0.5 / (sq * np.where(big, zr, 1.0)), 0.0)
        else:
            out[0, robust] = np.log1p(zr)
            out[1, robust] = 1.0 / (1.0 + zr)
            out[2, robust] = -1.0 / (1.0 + zr) ** 2
        return out

    return loss


def rotation_from_far_matches(rays_a: np.ndarray, rays_b: np.ndarray, threshold_deg: float,
                              iterations: int = 300, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """``R_a_from_b`` with ``rays_a ≈ R · rays_b`` for distant points, by RANSAC over pairs of
    correspondences (Kabsch on the inliers). A starting value for the epipolar fit, robust to
    mismatches; parallax up to ``threshold_deg`` counts as agreement.

    Returns
    -------
    R : ndarray (3, 3)
    inliers : ndarray (N,) bool
    """
    a = np.asarray(rays_a, np.float64)
    b = np.asarray(rays_b, np.float64)
    n = len(a)
    if n < 3:
        raise CalibrationError(f"only {n} correspondences between the cameras; need at least 3")
    rng = np.random.default_rng(seed)
    cos_thr = math.cos(math.radians(threshold_deg))
    best, best_n = None, -1
    for _ in range(iterations):
        i, j = rng.choice(n, 2, replace=False)
        if abs(float(a[i] @ a[j])) > 0.995:
            continue
        R = _kabsch(a[[i, j]], b[[i, j]])
        cnt = int(np.sum(np.einsum("ij,ij->i", b @ R.T, a) >= cos_thr))
        if cnt > best_n:
            best, best_n = R, cnt
    if best is None:
        raise CalibrationError("the correspondences are degenerate (all in one direction)")
    inl = np.einsum("ij,ij->i", b @ best.T, a) >= cos_thr
    R = _kabsch(a[inl], b[inl])
    inl = np.einsum("ij,ij->i", b @ R.T, a) >= cos_thr
    return R, inl


def _kabsch(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Rotation R minimizing Σ |a_i − R b_i|² (Wahba), det +1."""
    H = b.T @ a
    u, _, vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(vt.T @ u.T))
    return vt.T @ np.diag([1.0, 1.0, d]) @ u.T
