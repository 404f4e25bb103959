"""Chessboards rendered through a known lens, so that lens-calibration tests know the exact answer.

Every pixel's ray (:meth:`~cbh.geometry.camera.OCamModel.pixel_to_ray`) is intersected with
the board plane and shaded black or white by the square it hits, averaged over sub-pixel
samples on a Fibonacci lattice (a box filter, so the corner positions carry no half-pixel bias),
then blurred, given
sensor noise and JPEG-compressed. The true corners are the board's inner corners imaged
through the same model (:func:`cbh.geometry.lenscal.project_model`).

Frames follow docs/conventions.md: pixels (x = column, y = row), pixel centres at integers;
the camera frame has z along the optical axis. A pose is ``(rx, ry, rz, tx, ty, tz)``, a
rotation vector [rad] and a translation [mm] with ``P_cam = R · (X, Y, 0) + t``.

Example::

    board = Chessboard(cols=6, rows=8, square_mm=32.5)
    pose = pose_facing(board, zenith_deg=40, azimuth_deg=30, distance_mm=350)
    shot = render_board(model, board, pose, rng=np.random.default_rng(0))
    shot.image          # (H, W) uint8 greyscale
    shot.corners_xy     # (48, 2) true corner pixels, OpenCV's order
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from cbh.geometry.camera import OCamModel
from cbh.geometry.lenscal import board_points, project_model

__all__ = ["Chessboard", "BoardShot", "pose_facing", "hemisphere_poses", "render_board", "catadioptric_model"]


@dataclass(frozen=True)
class Chessboard:
    """A printed chessboard.

    Attributes
    ----------
    cols, rows : int
        Inner corners per row and rows of inner corners (OpenCV's ``patternSize``); the board
        has (cols + 1) × (rows + 1) squares.
    square_mm : float
        Side of a square [mm].
    margin_squares : float
        Width of the white border around the squares [squares].
    """

    cols: int = 6
    rows: int = 8
    square_mm: float = 32.5
    margin_squares: float = 0.75

    def corners(self) -> np.ndarray:
        """Inner corners (X, Y) [mm], shape (cols·rows, 2), OpenCV's order."""
        return board_points(self.cols, self.rows, self.square_mm)

    def extent(self) -> tuple[float, float, float, float]:
        """(x_min, x_max, y_min, y_max) of the paper, border included [mm]."""
        s, m = self.square_mm, self.margin_squares * self.square_mm
        return -s - m, self.cols * s + m, -s - m, self.rows * s + m

    def centre(self) -> np.ndarray:
        """Middle of the inner-corner grid (X, Y) [mm], shape (2,)."""
        return np.array([(self.cols - 1) / 2.0, (self.rows - 1) / 2.0]) * self.square_mm


@dataclass(frozen=True)
class BoardShot:
    """One rendered image and its truth.

    Attributes
    ----------
    image : ndarray, shape (H, W), uint8
        Greyscale image (after blur, noise and JPEG).
    corners_xy : ndarray, shape (cols·rows, 2), float64
        True inner-corner pixels (x, y), OpenCV's order [px].
    pose : ndarray, shape (6,), float64
        Rotation vector [rad] and translation [mm] of the board.
    """

    image: np.ndarray
    corners_xy: np.ndarray
    pose: np.ndarray


def pose_facing(board: Chessboard, zenith_deg: float, azimuth_deg: float, distance_mm: float,
                tilt_deg: float = 0.0, tilt_axis_deg: float = 0.0, roll_deg: float = 0.0) -> np.ndarray:
    """A board whose centre lies in a given direction, turned towards the camera.

    Parameters
    ----------
    board : Chessboard
    zenith_deg : float
        Angle of the board's centre from the optical axis [deg].
    azimuth_deg : float
        Direction about the axis, from the image's +x towards +y [deg].
    distance_mm : float
        Distance of the board's centre from the camera [mm].
    tilt_deg, tilt_axis_deg : float
        Tilt of the board away from facing the camera, about an in-plane axis at this angle [deg].
    roll_deg : float
        Rotation of the board about its own normal [deg].

    Returns
    -------
    pose : ndarray, shape (6,), float64
    """
    from scipy.spatial.transform import Rotation

    z, a = math.radians(zenith_deg), math.radians(azimuth_deg)
    d = np.array([math.sin(z) * math.cos(a), math.sin(z) * math.sin(a), math.cos(z)])
    ref = np.array([0.0, 1.0, 0.0]) if abs(d[1]) < 0.9 else np.array([1.0, 0.0, 0.0])
    r1 = np.cross(ref, d)
    r1 /= np.linalg.norm(r1)
    R = np.column_stack([r1, np.cross(d, r1), d])  # board normal along the line of sight
    axis = Rotation.from_rotvec(d * math.radians(tilt_axis_deg)).apply(r1)
    R = (Rotation.from_rotvec(axis * math.radians(tilt_deg)) * Rotation.from_matrix(R)
         * Rotation.from_rotvec([0.0, 0.0, math.radians(roll_deg)])).as_matrix()
    t = distance_mm * d - R[:, :2] @ board.centre()
    return np.r_[Rotation.from_matrix(R).as_rotvec(), t]


def hemisphere_poses(board: Chessboard, n: int, rng: np.random.Generator, max_zenith_deg: float = 72.0,
                     distance_mm: tuple[float, float] = (300.0, 420.0), max_tilt_deg: float = 30.0) -> list:
    """``n`` poses spread over the field of view: zenith angles evenly in solid angle up to
    ``max_zenith_deg`` (a third of them beyond 60° when it reaches that far), azimuths, distances
    [mm], tilts and rolls drawn at random.

    Returns
    -------
    list of ndarray, each shape (6,)
    """
    cos_max = math.cos(math.radians(max_zenith_deg))
    poses = []
    for i in range(n):
        if i % 3 == 2 and max_zenith_deg > 60.0:
            zen = rng.uniform(60.0, max_zenith_deg)
        else:
            zen = math.degrees(math.acos(rng.uniform(cos_max, 1.0)))
        poses.append(pose_facing(board, zen, rng.uniform(0, 360), rng.uniform(*distance_mm),
                                 tilt_deg=rng.uniform(0, max_tilt_deg), tilt_axis_deg=rng.uniform(0, 360),
                                 roll_deg=rng.uniform(0, 360)))
    return poses


def catadioptric_model(width: int = 1024, height: int = 768, fov_deg: float = 220.0, rim_frac: float = 0.48,
                       center_offset_px: tuple[float, float] = (6.3, -4.1),
                       affine: tuple[float, float, float] = (1.0008, 0.0004, 0.0004)) -> OCamModel:
    """A catadioptric camera (a lens looking into a convex mirror) in Scaramuzza's model.

    The mirror fills a circle of radius ``rim_frac`` × ``height`` about the centre, where the
    view reaches ``fov_deg`` / 2 from the axis (beyond 90°: the field of view passes 180°);
    f(r) = a0 + a2 r² + a4 r⁴ with a0 = half that radius and a4 = 0.15 a2 / R², which images
    the angle from the axis nearly in proportion to the radius (about 31° at a quarter of the
    height). The middle of the image sees the camera itself in the mirror: render boards with
    ``blind_deg`` (e.g. 30°) to blank it.

    Returns
    -------
    OCamModel
        With ``max_theta_deg`` = ``fov_deg`` / 2.
    """
    rim = rim_frac * height
    half = fov_deg / 2.0
    a0 = 0.5 * rim
    a2 = (-rim * math.tan(math.radians(half - 90.0)) - a0) / (rim**2 * 1.15)
    return OCamModel(width=width, height=height,
                     center_xy=((width - 1) / 2.0 + center_offset_px[0], (height - 1) / 2.0 + center_offset_px[1]),
                     affine=affine, poly=(a0, 0.0, a2, 0.0, 0.15 * a2 / rim**2), max_theta_deg=half)


def _lattice(n: int) -> np.ndarray:
    """``n`` sub-pixel offsets in [−½, ½)², a rank-1 lattice with generator round(n / φ).

    Every sample has its own x and its own y, so an edge of any direction, axis-parallel ones
    included, is resolved to ~1/n of a pixel; a regular √n × √n grid resolves axis-parallel
    edges only to 1/√n, the same way along the whole edge, which biases corners by ~0.03 px.
    Random jitter removes that bias but adds ~15 grey levels of noise to every edge pixel.
    """
    g = int(round(n / ((1 + math.sqrt(5)) / 2)))
    i = np.arange(n)
    return np.stack([(i + 0.5) / n, ((i * g) % n + 0.5) / n], axis=-1) - 0.5


def _board_xy(rays: np.ndarray, pose: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Board coordinates (N, 2) [mm] where the rays meet the board plane, and whether they do."""
    from scipy.spatial.transform import Rotation

    R = Rotation.from_rotvec(pose[:3]).as_matrix()
    t = pose[3:]

    def dot(v):  # rays · v, written out: a threaded BLAS product is slow on a busy machine
        return rays[:, 0] * v[0] + rays[:, 1] * v[1] + rays[:, 2] * v[2]

    with np.errstate(divide="ignore", invalid="ignore"):
        lam = float(t @ R[:, 2]) / dot(R[:, 2])
    hit = np.isfinite(lam) & (lam > 0)
    lam = np.where(hit, lam, 0.0)
    xy = np.stack([lam * dot(R[:, k]) - float(t @ R[:, k]) for k in (0, 1)], axis=-1)
    return xy, hit


def _shade(xy: np.ndarray, hit: np.ndarray, board: Chessboard, levels: tuple[float, float, float]) -> np.ndarray:
    """Grey value of board points: black or white squares, white border, background elsewhere."""
    black, white, background = levels
    x0, x1, y0, y1 = board.extent()
    s = board.square_mm
    X, Y = xy[:, 0], xy[:, 1]
    on_paper = hit & (X >= x0) & (X <= x1) & (Y >= y0) & (Y <= y1)
    in_squares = on_paper & (X >= -s) & (X < board.cols * s) & (Y >= -s) & (Y < board.rows * s)
    parity = (np.floor(X / s).astype(np.int64) + np.floor(Y / s).astype(np.int64)) % 2
    out = np.full(len(X), background, dtype=np.float64)
    out[on_paper] = white
    out[in_squares & (parity == 0)] = black
    return out


def _board_bbox(model: OCamModel, board: Chessboard, pose: np.ndarray) -> tuple[int, int, int, int] | None:
    """Pixel box (x0, x1, y0, y1), exclusive ends, of the pixels whose ray meets the paper."""
    xy, hit = _board_xy(model.ray_map().reshape(-1, 3), pose)
    x0, x1, y0, y1 = board.extent()
    pad = board.square_mm
    near = hit & (xy[:, 0] > x0 - pad) & (xy[:, 0] < x1 + pad) & (xy[:, 1] > y0 - pad) & (xy[:, 1] < y1 + pad)
    if not near.any():
        return None
    ys, xs = np.divmod(np.flatnonzero(near), model.width)
    return int(xs.min()), int(xs.max()) + 1, int(ys.min()), int(ys.max()) + 1


def render_board(model: OCamModel, board: Chessboard, pose, rng: np.random.Generator | None = None,
                 samples: int = 34, blur_px: float = 0.7, noise_dn: float = 2.0, jpeg_quality: int | None = 90,
                 levels: tuple[float, float, float] = (35.0, 215.0, 110.0), fov_deg: float = 190.0,
                 blind_deg: float = 0.0) -> BoardShot:
    """Image a chessboard through ``model``.

    Parameters
    ----------
    model : OCamModel
        The lens (the truth).
    board : Chessboard
    pose : array_like, shape (6,), float
        Rotation vector [rad] and translation [mm].
    rng : numpy.random.Generator, optional
        Source of the sensor noise (default: seeded 0).
    samples : int
        Sub-pixel samples per pixel (box filter), on the rank-1 Fibonacci lattice of
        :func:`_lattice`; 34 keeps the corners within ~0.01 px of the truth.
    blur_px : float
        Gaussian blur σ [px] (optics); 0 for none.
    noise_dn : float
        Gaussian sensor noise σ [grey levels of 255].
    jpeg_quality : int or None
        JPEG quality of the final image; None for no compression.
    levels : tuple of float
        Grey values of black squares, white paper and the background [0–255].
    fov_deg : float
        Full field of view of the lens [deg]; pixels beyond it are black.
    blind_deg : float
        Pixels within this angle of the axis are black too: a catadioptric camera sees itself
        in the middle of its mirror [deg].

    Returns
    -------
    BoardShot
    """
    rng = np.random.default_rng(0) if rng is None else rng
    pose = np.asarray(pose, dtype=np.float64)
    img = np.full((model.height, model.width), levels[2], dtype=np.float64)
    box = _board_bbox(model, board, pose)
    if box is not None:
        x0, x1, y0, y1 = box
        ys, xs = np.mgrid[y0:y1, x0:x1]
        lat = _lattice(samples)
        sx = (xs[..., None] + lat[None, None, :, 0]).ravel()
        sy = (ys[..., None] + lat[None, None, :, 1]).ravel()
        xy, hit = _board_xy(model.pixel_to_ray(np.stack([sx, sy], axis=-1)), pose)
        grey = _shade(xy, hit, board, levels).reshape(y1 - y0, x1 - x0, samples)
        img[y0:y1, x0:x1] = grey.mean(axis=-1)
    theta = model.theta_map()
    img[(theta > fov_deg / 2.0) | (theta < blind_deg)] = 0.0
    if blur_px > 0:
        img = cv2.GaussianBlur(img, (0, 0), blur_px)
    img = np.clip(np.round(img + rng.normal(0.0, noise_dn, img.shape)), 0, 255).astype(np.uint8)
    if jpeg_quality is not None:
        ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality)])
        img = cv2.imdecode(buf, cv2.IMREAD_GRAYSCALE)
    from scipy.spatial.transform import Rotation

    R = Rotation.from_rotvec(pose[:3]).as_matrix()
    P = board.corners() @ R[:, :2].T + pose[3:]
    return BoardShot(image=img, corners_xy=project_model(model, P), pose=pose)
