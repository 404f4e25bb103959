"""``cbh calibrate-lens`` in library terms: a fisheye lens's OCamCalib model from chessboard images.

Steps: read the images (one size), find the board's inner corners in each (OpenCV), calibrate
(:mod:`cbh.geometry.lenscal`: linear start, centre search, bundle adjustment), say where the
board poses leave the field of view uncovered (warnings, not refusals), measure the held-out
error, write ``calib_results.txt`` as the toolbox does and read it back with cbh's reader, so
that every number reported is the written file's.

Corners: ``findChessboardCornersSB`` (EXHAUSTIVE | ACCURACY) first, the classic detector as the
fallback (see :func:`detect_corners`); both refined by ``cornerSubPix`` on the image blurred
with σ = 1 px, in a half-window of 0.4 × the distance to the nearest corner. On boards rendered
with known corners (cbh.sim.chessboard, 516 × 389 px) the SB detector's own corners are
0.055–0.09 px RMS off without noise and 0.074 px with 2-DN noise and JPEG; refined, 0.02–0.03
and 0.053 px (a fixed window, or one a fifth of the spacing, does worse; on Fisheye1 the choice
moves the RMS by < 0.001 px).
Pixels are 0-based (x = column, y = row), pixel centres at integers, as OpenCV returns them;
the file stores the centre as the toolbox's (row, column).
"""
from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from cbh.errors import CalibrationError, ImageError, InputError
from cbh.geometry.lenscal import MIN_CORNERS

__all__ = ["LensCalOptions", "parse_board", "parse_order", "detect_corners", "refine_corners", "refine_on_board",
           "calibrate_lens", "MIN_BOARDS"]

log = logging.getLogger(__name__)

MIN_BOARDS = 4  # board poses needed: the polynomial, the centre and the affine need spread, and a
# held-out fit leaves three


@dataclass(frozen=True)
class LensCalOptions:
    """What ``cbh calibrate-lens`` was asked to do.

    Attributes
    ----------
    board : tuple of int
        Inner corners (columns, rows), OpenCV's ``patternSize``.
    square_mm : float
        Side of a board square [mm].
    order : int or None
        Degree of the polynomial f(r); None: chosen by the held-out error
        (:func:`cbh.geometry.lenscal.select_order`; 4 if ``held_out`` is off).
    loss : {"linear", "huber"}
        Least squares, or Huber's robust loss.
    huber_px : float
        Huber's transition [px].
    method : {"auto", "trf", "lm"}
        Solver of the bundle adjustment (see :class:`cbh.geometry.lenscal.LensCalConfig`).
    held_out : bool
        Also measure the leave-one-image-out error (one extra bundle adjustment per image).
    report_dir : Path or None
        Write per-image residuals (CSV, PNG) and the coverage picture here.
    board_refine : bool or None
        After a first fit, refine every corner on its board's own plane (:func:`refine_on_board`)
        and fit again; None: only where corners pass 90° from the axis in the first fit (a
        catadioptric camera, a lens beyond 180°). Rays against the truth, boards rendered through
        a catadioptric model (five sets of 11, ``benchmarks/bench_calibrate_lens.py
        --catadioptric``): 0.028–0.057 px RMS without, 0.014–0.041 px with; through a fisheye
        (two sets of 12 at 1032 × 778): 0.036 and 0.066 px without, 0.054 and 0.041 with, no
        better; Fisheye1 on Urban's corners: 0.3825 px either way.
    """

    board: tuple[int, int]
    square_mm: float
    order: int | None = None
    loss: str = "linear"
    huber_px: float = 1.0
    method: str = "auto"
    held_out: bool = True
    report_dir: Path | None = None
    board_refine: bool | None = None

    def __post_init__(self):
        cols, rows = self.board
        if cols < 2 or rows < 2 or cols * rows < MIN_CORNERS:
            raise InputError(f"--board {cols}x{rows}: a board needs at least 2 inner corners each way and "
                             f"{MIN_CORNERS} in all (e.g. 2x3) to fix its pose")
        if not (math.isfinite(self.square_mm) and SQUARE_MM_RANGE[0] <= self.square_mm <= SQUARE_MM_RANGE[1]):
            raise InputError(f"--square-mm: a board square's side in mm, {SQUARE_MM_RANGE[0]:g} to "
                             f"{SQUARE_MM_RANGE[1]:g}, got {self.square_mm:g}")


#: A board square's side [mm]: a printed board's 1 mm up to a 10 m target (1e-300 ended in a traceback).
SQUARE_MM_RANGE = (0.1, 10_000.0)


def parse_order(text: str) -> int | None:
    """``"auto"`` → None (chosen by the held-out error), ``"5"`` → 5 (2 to 12)."""
    t = str(text).strip().lower()
    if t == "auto":
        return None
    try:
        order = int(t)
    except ValueError:
        raise InputError(f"--order {text!r}: expected auto or a degree from 2 to 12") from None
    if not 2 <= order <= 12:
        raise InputError(f"--order {order}: the polynomial's degree must be 2 to 12 (or auto)")
    return order


def parse_board(text: str) -> tuple[int, int]:
    """``"6x8"`` → (6, 8): inner corners per row × rows (OpenCV's ``patternSize``)."""
    parts = str(text).lower().replace("×", "x").split("x")
    try:
        cols, rows = (int(p) for p in parts)
    except ValueError:
        raise InputError(f"--board {text!r}: expected COLSxROWS of inner corners, e.g. 6x8") from None
    return cols, rows


# --- corners ------------------------------------------------------------------------------

def _grid_spacing(corners: np.ndarray, cols: int, rows: int) -> np.ndarray:
    """Distance from each corner to its nearest grid neighbour [px], shape (N,)."""
    g = corners.reshape(rows, cols, 2)
    d = np.full((rows, cols), np.inf)
    dx = np.linalg.norm(np.diff(g, axis=1), axis=2)
    dy = np.linalg.norm(np.diff(g, axis=0), axis=2)
    d[:, 1:] = np.minimum(d[:, 1:], dx)
    d[:, :-1] = np.minimum(d[:, :-1], dx)
    d[1:, :] = np.minimum(d[1:, :], dy)
    d[:-1, :] = np.minimum(d[:-1, :], dy)
    return d.ravel()


def refine_corners(gray: np.ndarray, corners: np.ndarray, cols: int, rows: int, blur_px: float = 1.0,
                   window_frac: float = 0.4) -> np.ndarray:
    """``cornerSubPix`` on the blurred image, each corner in a window that stays clear of its neighbours.

    Parameters
    ----------
    gray : ndarray, shape (H, W), uint8
    corners : ndarray, shape (cols·rows, 2), float
        Detected corners (x, y) [px], OpenCV's order.
    cols, rows : int
        Board inner corners.
    blur_px : float
        Gaussian σ applied first [px] (JPEG blocks and noise otherwise pull the gradients).
    window_frac : float
        Half-window as a fraction of the nearest-neighbour spacing (clipped to 3…10 px); it must
        stay below 1 or the window takes in the next corner (0.6 already loses accuracy).

    Returns
    -------
    ndarray, shape (cols·rows, 2), float64
    """
    import cv2

    img = cv2.GaussianBlur(gray, (0, 0), blur_px) if blur_px > 0 else gray
    half = np.clip(np.round(window_frac * _grid_spacing(corners, cols, rows)), 3, 10).astype(int)
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 100, 1e-4)
    out = np.asarray(corners, dtype=np.float64).copy()
    for h in np.unique(half):
        m = half == h
        pts = out[m].astype(np.float32).reshape(-1, 1, 2)
        out[m] = cv2.cornerSubPix(img, pts, (int(h), int(h)), (-1, -1), crit).reshape(-1, 2)
    return out


def refine_on_board(gray: np.ndarray, corners: np.ndarray, model, pose, cols: int, rows: int, square: float,
                    blur_px: float = 1.0, window_frac: float = 0.4) -> np.ndarray:
    """``cornerSubPix`` on the board as it lies in its own plane, the image resampled through a lens.

    A strongly distorted board's edges are curved in the raw image, and a corner refined there
    moves towards the hollow side: on boards rendered through a catadioptric lens (no noise)
    :func:`refine_corners` puts them 0.037 px outwards on average. Here the image is resampled
    (bilinear) onto the board plane through a fitted lens and board pose, where every edge is
    straight and every square the same size; each corner is refined there and mapped back through
    the same lens and pose. The lens need not be exact: a small error only bends the resampled
    edges a little, and the mapping back undoes what the mapping forth did.

    Parameters
    ----------
    gray : ndarray, shape (H, W), uint8
    corners : ndarray, shape (cols·rows, 2), float
        Corners (x, y) [px], OpenCV's order, from :func:`detect_corners`.
    model : OCamModel
        A fitted lens.
    pose : array_like, shape (6,), float
        The board's pose through ``model`` (rotation vector [rad], translation [board units]).
    cols, rows : int
    square : float
        Side of a square [board units].
    blur_px, window_frac : float
        As in :func:`refine_corners`, in resampled pixels.

    Returns
    -------
    ndarray, shape (cols·rows, 2), float64
        Refined corners (x, y) [px].
    """
    import cv2
    from scipy.spatial.transform import Rotation

    from cbh.geometry.lenscal import board_points, project_model

    spacing = _grid_spacing(np.asarray(corners, float), cols, rows)
    g = np.asarray(corners, float).reshape(rows, cols, 2)
    longest = max(np.max(np.linalg.norm(np.diff(g, axis=a), axis=2)) for a in (0, 1))  # no square undersampled
    sq_px = float(np.clip(np.round(longest), 12.0, 96.0))  # whole pixels per square
    step = square / sq_px  # board units per resampled pixel
    pad = round(0.75 * sq_px)  # every corner on a resampled pixel's centre, whichever way the board is numbered
    x0 = y0 = -pad * step
    w, h = int((cols - 1) * sq_px) + 2 * pad + 1, int((rows - 1) * sq_px) + 2 * pad + 1
    gy, gx = np.mgrid[0:h, 0:w]
    R = Rotation.from_rotvec(np.asarray(pose[:3], float)).as_matrix()

    def to_image(X, Y):
        return project_model(model, np.outer(X, R[:, 0]) + np.outer(Y, R[:, 1]) + np.asarray(pose[3:], float))

    maps = to_image(x0 + gx.ravel() * step, y0 + gy.ravel() * step).astype(np.float32).reshape(h, w, 2)
    flat = cv2.remap(gray, maps[..., 0], maps[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    if blur_px > 0:
        flat = cv2.GaussianBlur(flat, (0, 0), blur_px * sq_px / float(np.median(spacing)))
    xy = board_points(cols, rows, square)
    start = np.stack([(xy[:, 0] - x0) / step, (xy[:, 1] - y0) / step], axis=-1).astype(np.float32)
    # the window of refine_corners in image pixels (≤ 10 px), expressed in resampled pixels
    half = int(round(float(np.clip(window_frac * np.median(spacing), 3, 10)) * sq_px / float(np.median(spacing))))
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 100, 1e-4)
    got = cv2.cornerSubPix(flat, start.reshape(-1, 1, 2), (half, half), (-1, -1), crit).reshape(-1, 2)
    return to_image(x0 + got[:, 0].astype(np.float64) * step, y0 + got[:, 1].astype(np.float64) * step)


def _locate_factor(shape: tuple[int, ...], min_side_px: int = 500) -> int:
    """Largest power of two that keeps the image's long side at ``min_side_px`` or more."""
    k = 1
    while max(shape[:2]) / (2 * k) >= min_side_px:
        k *= 2
    return k


def _find_sb(gray: np.ndarray, cols: int, rows: int, factor: int) -> np.ndarray | None:
    """``findChessboardCornersSB`` (EXHAUSTIVE | ACCURACY) on the image reduced ``factor`` times
    (area averaging), corners mapped back to full-size pixels; None if no board."""
    import cv2

    h, w = gray.shape[:2]
    img = gray if factor == 1 else cv2.resize(gray, (w // factor, h // factor), interpolation=cv2.INTER_AREA)
    ok, c = cv2.findChessboardCornersSB(img, (cols, rows), flags=cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY)
    if not ok or c is None:
        return None
    c = c.reshape(-1, 2).astype(np.float64)
    scale = np.array([w / img.shape[1], h / img.shape[0]])
    return (c + 0.5) * scale - 0.5  # pixel centres at integers in both images


def detect_corners(gray: np.ndarray, cols: int, rows: int) -> tuple[np.ndarray | None, str | None]:
    """A chessboard's inner corners in a raw fisheye image.

    The SB detector runs first on the image halved (until its long side would drop below
    500 px: four times less work), then at full size, then the classic detector; whichever
    finds the board, its corners are refined twice at full size by :func:`refine_corners` (the
    first pass pulls a located corner in, the second settles it with the corrected spacing; on
    Fisheye1 the result equals full-size detection to 1e-4 px).

    Returns
    -------
    corners : ndarray, shape (cols·rows, 2), float64, or None
        Refined corners (x, y), 0-based [px], row by row as OpenCV orders them; None if no board.
    detector : {"sb", "classic"} or None
        Which OpenCV detector found it.
    """
    import cv2

    factor = _locate_factor(gray.shape)
    c, detector = _find_sb(gray, cols, rows, factor), "sb"
    if c is None and factor > 1:
        c = _find_sb(gray, cols, rows, 1)
    if c is None:
        flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
        ok, found = cv2.findChessboardCorners(gray, (cols, rows), flags=flags)
        if not ok or found is None:
            return None, None
        c, detector = found.reshape(-1, 2).astype(np.float64), "classic"
    return refine_corners(gray, refine_corners(gray, c, cols, rows), cols, rows), detector


def _read_gray(path: Path) -> np.ndarray:
    import cv2

    from cbh.imageio import read_image

    return cv2.cvtColor(read_image(path)[0], cv2.COLOR_BGR2GRAY)


@dataclass
class _Views:
    """The images and what was found in them."""

    paths: list
    size: tuple[int, int]  # (width, height) [px]
    corners: dict = field(default_factory=dict)  # index → (N, 2) corners
    detector: dict = field(default_factory=dict)  # index → "sb" | "classic"
    grays: dict = field(default_factory=dict)  # index → (H, W) uint8 image with a board
    seconds: float = 0.0

    @property
    def found(self) -> list[int]:
        return sorted(self.corners)

    @property
    def missing(self) -> list[int]:
        return [i for i in range(len(self.paths)) if i not in self.corners]


def _read_all(paths: list[Path]) -> tuple[list[np.ndarray], tuple[int, int]]:
    """Every image as greyscale, before any detection: a bad file or size fails at once."""
    grays = []
    for p in paths:
        grays.append(_read_gray(p))
        h, w = grays[-1].shape
        h0, w0 = grays[0].shape
        if (w, h) != (w0, h0):
            raise ImageError(f"{p}: image is {w}x{h} but {paths[0]} is {w0}x{h0}; "
                             "calibrate one camera (one image size) at a time")
    return grays, (grays[0].shape[1], grays[0].shape[0])


def _detect_all(paths: list[Path], board: tuple[int, int]) -> _Views:
    t0 = time.perf_counter()
    grays, size = _read_all(paths)
    views = _Views(paths=paths, size=size)
    for i, (p, gray) in enumerate(zip(paths, grays)):
        corners, det = detect_corners(gray, *board)
        log.info("%s: %s", p, "no board" if corners is None else f"board found ({det})")
        if corners is not None:
            views.corners[i], views.detector[i], views.grays[i] = corners, det, gray
    views.seconds = time.perf_counter() - t0
    return views


def _check_boards(views: _Views, board: tuple[int, int]) -> None:
    n, found = len(views.paths), len(views.found)
    b = f"{board[0]}x{board[1]}"
    if found == 0:
        raise CalibrationError(
            f"no {b} chessboard found in any of the {n} images; --board counts inner corners "
            f"(squares − 1) per row x rows, e.g. 6x8 for a board of 7 x 9 squares")
    if found < MIN_BOARDS:
        none_in = ", ".join(Path(views.paths[i]).name for i in views.missing)
        raise CalibrationError(
            f"a {b} board was found in {found} of {n} images" + (f" (none in {none_in})" if none_in else "")
            + f"; at least {MIN_BOARDS} board poses are needed: add {MIN_BOARDS - found} more, spread from the "
            "centre of the view to its periphery beyond 60°")


# --- the command --------------------------------------------------------------------------

def _write_model(model, out: Path):
    """Write the toolbox's file and read it back: the model as stored, to the digit."""
    from cbh.geometry.camera import format_ocamcalib, read_ocamcalib

    if out.is_dir():
        raise InputError(f"--out {out}: is a directory; give the file name, e.g. {out / 'calib_results.txt'}")
    if not out.parent.is_dir():
        raise InputError(f"--out {out}: folder {out.parent} does not exist")
    from cbh.fileio import atomic_write

    replaced = out.exists()
    with atomic_write(out) as tmp:  # a full disk or Ctrl-C leaves the older file whole
        tmp.write_text(format_ocamcalib(model))
    if replaced:
        log.info("--out %s existed: replaced", out)
    return read_ocamcalib(out)


def calibrate_lens(images, out, opts: LensCalOptions) -> dict:
    """Calibrate one lens from chessboard images and write its ``calib_results.txt``.

    Parameters
    ----------
    images : sequence of str or Path
        Chessboard images of one camera, all the same size.
    out : str or Path
        The ``calib_results.txt`` to write (OCamCalib's layout, which cbh reads).
    opts : LensCalOptions

    Returns
    -------
    dict
        The report (JSON-ready): per-image and overall errors (per-point Euclidean RMS and
        per-coordinate RMS), the held-out error, the model, the coverage, timings, and
        ``summary`` (lines for a person).

    Raises
    ------
    CalibrationError, ImageError, InputError
        Too few images or boards to determine the model (the message says how many more), no
        board anywhere, images of different sizes, an unreadable file. A zone of the field of
        view without boards is not refused: the report's ``coverage`` names the gaps, where the
        model is extrapolated, and ``summary`` warns.
    """
    from cbh.fileio import refuse_inputs
    from cbh.geometry import lenscal

    paths = [Path(p) for p in images]
    refuse_inputs([out], paths, "--out")
    if opts.report_dir is not None:
        refuse_inputs([opts.report_dir], paths, "--report")
    if len(paths) < MIN_BOARDS:
        raise InputError(f"{len(paths)} image{'' if len(paths) == 1 else 's'} given; at least {MIN_BOARDS} are "
                         "needed, each with the board in another part of the view")
    config = lenscal.LensCalConfig(order=opts.order or 4, loss=opts.loss, huber_px=opts.huber_px, method=opts.method)
    views = _detect_all(paths, opts.board)
    _check_boards(views, opts.board)
    width, height = views.size
    corners = [views.corners[i] for i in views.found]
    boards = [lenscal.board_points(*opts.board, opts.square_mm)] * len(corners)
    t0 = time.perf_counter()
    board_refine = opts.board_refine
    if board_refine is not False:  # a first lens and the board poses, to refine the corners on the boards' planes
        calib = lenscal.calibrate(corners, boards, width, height, config)
        if board_refine is None:
            board_refine = max(float(np.max(calib.model.theta_of_pixel(c))) for c in corners) > 90.0
        if board_refine:
            corners = [refine_on_board(views.grays[i], c, calib.model, pose, *opts.board, opts.square_mm)
                       for i, c, pose in zip(views.found, corners, calib.poses)]
    held, orders = None, None
    if opts.order is None and opts.held_out:
        calib, config, held, orders = lenscal.select_order(corners, boards, width, height, config)
    elif board_refine or opts.board_refine is False:  # else the first fit, on the same corners, is the fit
        calib = lenscal.calibrate(corners, boards, width, height, config)
    t_cal = time.perf_counter() - t0
    corners, boards, rejected, ids = _left_out(calib, corners, boards, [paths[i] for i in views.found])
    cov = lenscal.coverage(calib.model, corners)  # gaps are warnings in the report, never a refusal
    t0 = time.perf_counter()
    if held is None and opts.held_out:
        held = lenscal.held_out_residuals(corners, boards, calib, config)
    t_held = time.perf_counter() - t0
    replaced = Path(out).exists()
    stored = _write_model(calib.model, Path(out))
    residuals = lenscal.residuals_of(stored, calib.poses, corners, boards)
    report = _report(paths, views, stored, residuals, held, cov, opts, Path(out))
    report["config"]["order"] = config.order
    report["config"]["refined_on_board"] = bool(board_refine)
    report["order_selection"] = None if orders is None else {
        "criterion": "lowest order whose held-out per-point Euclidean RMS is within 1 % (or 0.002 px) of the best",
        "held_out_rms_euclid_px": {str(k): None if math.isnan(v) else v for k, v in orders.items()}}
    report["out_replaced"] = replaced
    report["rejected_corners"] = rejected
    report["timing_s"] = {"detect": round(views.seconds, 3), "calibrate": round(t_cal, 3),
                          "held_out": round(t_held, 3), "bundle_adjustment_nfev": calib.nfev}
    if opts.report_dir is not None:
        from cbh.outputs.lens_report import write_lens_report

        report["report_files"] = [str(p) for p in write_lens_report(Path(opts.report_dir), report, stored, corners,
                                                                     residuals, held, [paths[i] for i in views.found],
                                                                     ids)]
    report["summary"] = _summary(report)
    return report


def _left_out(calib, corners: list, boards: list, files: list) -> tuple[list, list, list, list]:
    """The corners the fit kept, their board points and their indices on the board (per image), and
    a record of each corner it left out as an outlier."""
    if calib.inliers is None:
        return corners, boards, [], [np.arange(len(c)) for c in corners]
    rejected = []
    for f, c, r, k in zip(files, corners, calib.residuals, calib.inliers):
        for j in np.flatnonzero(~k):
            rejected.append({"file": str(f), "corner": int(j), "x_px": float(c[j, 0]), "y_px": float(c[j, 1]),
                             "dx_px": float(r[j, 0]), "dy_px": float(r[j, 1]), "err_px": float(np.hypot(*r[j]))})
    return ([c[k] for c, k in zip(corners, calib.inliers)], [b[k] for b, k in zip(boards, calib.inliers)], rejected,
            [np.flatnonzero(k) for k in calib.inliers])


def _report(paths, views: _Views, model, residuals, held, cov, opts: LensCalOptions, out: Path) -> dict:
    from cbh import __version__
    from cbh.geometry.lenscal import error_stats

    per_image = []
    for k, i in enumerate(views.found):
        entry = {"file": str(paths[i]), "board_found": True, "detector": views.detector[i], **error_stats(residuals[k])}
        if held is not None:
            h = error_stats(held[k])
            entry["held_out_rms_euclid_px"], entry["held_out_rms_coord_px"] = h["rms_euclid_px"], h["rms_coord_px"]
        entry["max_theta_deg"] = float(np.max(cov.theta_deg[k]))
        per_image.append(entry)
    per_image += [{"file": str(paths[i]), "board_found": False} for i in views.missing]
    overall = error_stats(np.concatenate(residuals))
    overall["mean_of_image_mean_euclid_px"] = float(np.mean([e["mean_euclid_px"] for e in per_image if e["board_found"]]))
    overall["n_images"] = len(views.found)
    return {
        "cbh_version": __version__,
        "out": str(out),
        "config": {"board_inner_corners": list(opts.board), "square_mm": opts.square_mm, "order": opts.order,
                   "loss": opts.loss, "huber_px": opts.huber_px, "method": opts.method},
        "image_size": {"width": model.width, "height": model.height},
        "images": per_image,
        "no_board": [str(paths[i]) for i in views.missing],
        "overall": overall,
        "held_out": None if held is None else error_stats(np.concatenate(held)),
        "model": {"ss": [-a for a in model.poly], "invpol": list(model.invpol),
                  "center_row_col_0based": [model.center_xy[1], model.center_xy[0]],
                  "affine_c_d_e": list(model.affine), "height": model.height, "width": model.width},
        "coverage": {"boards_per_zone": cov.boards_per_zone, "periphery_corners_by_side": cov.periphery_sides,
                     "max_corner_theta_deg": float(max(np.max(t) for t in cov.theta_deg)),
                     "frame_theta_deg": cov.frame_theta_deg, "gaps": cov.gaps(),
                     "extrapolation": cov.extrapolation(), "warnings": cov.warnings()},
    }


def _summary(rep: dict) -> list[str]:
    o, m, c = rep["overall"], rep["model"], rep["coverage"]
    n_all = len(rep["images"])
    lines = [f"{rep['out']}{' (replaced)' if rep.get('out_replaced') else ''}: lens calibrated from {o['n_images']} of {n_all} images "
             f"({o['n_points']} corners, order {rep['config']['order']})"]
    if rep.get("order_selection"):
        tab = rep["order_selection"]["held_out_rms_euclid_px"]
        lines.append(f"order {rep['config']['order']} chosen by the held-out error (px: "
                     + ", ".join(f"{k}: " + ("failed" if v is None else f"{v:.3f}") for k, v in tab.items()) + ")")
    if rep["no_board"]:
        lines.append("no board in: " + ", ".join(Path(p).name for p in rep["no_board"]))
    lines.append(f"reprojection error: {o['rms_euclid_px']:.3f} px per-point Euclidean RMS "
                 f"({o['rms_coord_px']:.3f} px per coordinate), mean {o['mean_euclid_px']:.3f}, max {o['max_euclid_px']:.2f} px")
    if rep.get("rejected_corners"):
        bad = rep["rejected_corners"]
        lines.append(f"left out of the fit as outliers: {len(bad)} corner{'' if len(bad) == 1 else 's'} ("
                     + ", ".join(f"{Path(b['file']).name} #{b['corner']} {b['err_px']:.2f} px" for b in bad[:5])
                     + (", …" if len(bad) > 5 else "") + ")")
    if rep["held_out"] is not None:
        h = rep["held_out"]
        lines.append(f"held out (each image through a lens fitted without it): {h['rms_euclid_px']:.3f} px "
                     f"per-point Euclidean RMS ({h['rms_coord_px']:.3f} px per coordinate)")
    lines.append(f"centre (row, column) = ({m['center_row_col_0based'][0]:.2f}, {m['center_row_col_0based'][1]:.2f}) px, "
                 f"c d e = {m['affine_c_d_e'][0]:.5f} {m['affine_c_d_e'][1]:.5f} {m['affine_c_d_e'][2]:.5f}, "
                 f"invpol {len(m['invpol'])} terms")
    z, x = c["boards_per_zone"], c["extrapolation"]
    lines.append(f"coverage: corners from {x['data_theta_deg'][0]:.0f}° to {x['data_theta_deg'][1]:.0f}° from the "
                 f"axis (the frame reaches {x['frame_theta_deg']:.0f}°); boards: centre (<30°) {z['centre']}, "
                 f"middle (30–60°) {z['middle']}, periphery (>60°) {z['periphery']}")
    lines += [f"warning: {w}" for w in c["warnings"]]
    empty = [s for s, n in c["periphery_corners_by_side"].items() if n == 0]
    if empty and not any(g["zone"] == "periphery" for g in c["gaps"]):
        lines.append("note: no corners beyond 60° towards the image's " + ", ".join(empty))
    if rep.get("report_files"):
        lines.append("report: " + ", ".join(rep["report_files"]))
    return lines
