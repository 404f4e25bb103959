"""Fisheye camera models: raw pixel <-> unit ray, with no undistortion and no rectification.

Frames and units follow docs/conventions.md: pixels are (x = column, y = row) with pixel
centres at integer coordinates; rays are unit vectors in the camera frame (x along columns,
y along rows, z along the optical axis, towards the sky).

Every model here is *radial*: an affine map takes the pixel offset from the centre to sensor
coordinates (u, v), and the angle from the optical axis depends only on r = hypot(u, v).

- :class:`OCamModel`: Scaramuzza's omnidirectional model as calibrated by the OCamCalib
  toolbox (the paper's eq. 2): ray ∝ (u, v, f(r)) with f(r) = a0 + a1 r + a2 r² + …
- :class:`EquidistantModel`: r = R90 · θ / 90°.
- :class:`EquisolidModel`: r = R90 / sin 45° · sin(θ / 2).
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from cbh.errors import CalibrationError, check_shape

__all__ = [
    "CameraModel",
    "OCamModel",
    "EquidistantModel",
    "EquisolidModel",
    "read_ocamcalib",
    "format_ocamcalib",
]


# Whole-image maps (rays, angles) of the lenses used last, shared by every equal model: a
# station loaded again, a scaled copy made again, or the simulator's true camera beside the
# nominal one all get the same lens, and its maps cost a full-image pass to build.
@functools.lru_cache(maxsize=8)
def _lens_map(model: "CameraModel", key: str) -> np.ndarray:
    return _read_only(getattr(model, f"_build_{key}")())


def _read_only(a: np.ndarray) -> np.ndarray:
    a.setflags(write=False)
    return a


def _shared_map(model: "CameraModel", key: str) -> np.ndarray:
    """``model``'s read-only map ``key`` (``_build_<key>``), from its own cache, an equal model's, or
    built; a model with a field that cannot be hashed keeps it in its own cache only."""
    if key not in model._cache:
        try:
            model._cache[key] = _lens_map(model, key)
        except TypeError:
            model._cache[key] = _read_only(getattr(model, f"_build_{key}")())
    return model._cache[key]


def _as_pixels(px) -> np.ndarray:
    px = np.asarray(px, dtype=np.float64)
    if px.ndim == 1:
        px = px[None, :]
    check_shape("pixels", px, (None, 2))
    return px


def _as_rays(rays) -> np.ndarray:
    rays = np.asarray(rays, dtype=np.float64)
    if rays.ndim == 1:
        rays = rays[None, :]
    check_shape("rays", rays, (None, 3))
    return rays


@dataclass(frozen=True)
class CameraModel:
    """Base of the radial fisheye models.

    Attributes
    ----------
    width, height : int
        Image size [px] the calibration belongs to.
    center_xy : tuple of float
        Optical centre (x = column, y = row) [px].
    affine : tuple of float
        OCamCalib's (c, d, e) sensor-to-image affine; (1, 0, 0) for an ideal lens.
    max_theta_deg : float
        Largest angle from the optical axis the model is valid for [deg].
    """

    width: int
    height: int
    center_xy: tuple[float, float]
    affine: tuple[float, float, float] = (1.0, 0.0, 0.0)
    max_theta_deg: float = 90.0
    _cache: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    kind = "base"

    # --- radial profile, implemented by subclasses -----------------------------------
    def theta_from_r(self, r: np.ndarray) -> np.ndarray:
        """Angle from the optical axis [rad] of sensor radius ``r`` [px]."""
        raise NotImplementedError

    def r_from_theta(self, theta: np.ndarray) -> np.ndarray:
        """Sensor radius [px] of the angle from the optical axis ``theta`` [rad]."""
        raise NotImplementedError

    def scaled(self, factor: float) -> "CameraModel":
        """The same lens for an image resized by ``factor`` (x' = (x + 0.5)·s − 0.5)."""
        raise NotImplementedError

    # --- shared geometry ---------------------------------------------------------------
    def _sensor_from_pixel(self, px: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        c, d, e = self.affine
        dx = px[:, 0] - self.center_xy[0]
        dy = px[:, 1] - self.center_xy[1]
        det = c - d * e
        u = (c * dx - e * dy) / det
        v = (dy - d * dx) / det
        return u, v

    def _pixel_from_sensor(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        c, d, e = self.affine
        x = u + e * v + self.center_xy[0]
        y = d * u + c * v + self.center_xy[1]
        return np.stack([x, y], axis=-1)

    def pixel_to_ray(self, px) -> np.ndarray:
        """Unit rays of pixels.

        Parameters
        ----------
        px : array_like, shape (N, 2), float
            Pixel coordinates (x = column, y = row) [px].

        Returns
        -------
        rays : ndarray, shape (N, 3), float64
            Unit vectors in the camera frame.
        """
        px = _as_pixels(px)
        u, v = self._sensor_from_pixel(px)
        r = np.hypot(u, v)
        theta = self.theta_from_r(r)
        s = np.sin(theta)
        with np.errstate(invalid="ignore", divide="ignore"):
            k = np.where(r > 0, s / np.where(r > 0, r, 1.0), 0.0)
        return np.stack([u * k, v * k, np.cos(theta)], axis=-1)

    def ray_to_pixel(self, rays) -> np.ndarray:
        """Pixels of rays (need not be unit length).

        Parameters
        ----------
        rays : array_like, shape (N, 3), float
            Directions in the camera frame.

        Returns
        -------
        px : ndarray, shape (N, 2), float64
            Pixel coordinates (x = column, y = row) [px]; NaN where the model has no
            pixel (beyond its valid angle).
        """
        rays = _as_rays(rays)
        rho = np.hypot(rays[:, 0], rays[:, 1])
        theta = np.arctan2(rho, rays[:, 2])
        r = self.r_from_theta(theta)
        with np.errstate(invalid="ignore", divide="ignore"):
            k = np.where(rho > 0, r / np.where(rho > 0, rho, 1.0), 0.0)
        px = self._pixel_from_sensor(rays[:, 0] * k, rays[:, 1] * k)
        px[theta > math.radians(self.max_theta_deg) + 1e-9] = np.nan
        return px

    def px_per_rad(self, theta_rad: float = 0.0) -> float:
        """The lens's radial scale dr/dθ [px/rad] at ``theta_rad`` from the optical axis: the
        difference of r over the 1° centred on it (from the axis out, at the axis)."""
        h = math.radians(1.0)
        lo = max(theta_rad - 0.5 * h, 0.0)
        r = np.asarray(self.r_from_theta(np.array([lo, lo + h])), np.float64)
        return float((r[1] - r[0]) / h)

    def theta_of_pixel(self, px) -> np.ndarray:
        """Angle from the optical axis [deg] of pixels, shape (N,)."""
        u, v = self._sensor_from_pixel(_as_pixels(px))
        return np.degrees(self.theta_from_r(np.hypot(u, v)))

    def pixel_grid(self) -> np.ndarray:
        """All pixel centres, shape (height·width, 2), row-major."""
        ys, xs = np.mgrid[0 : self.height, 0 : self.width]
        return np.stack([xs.ravel(), ys.ravel()], axis=-1).astype(np.float64)

    def ray_map(self) -> np.ndarray:
        """Unit ray of every pixel, shape (height, width, 3), float64 (cached, read-only)."""
        return _shared_map(self, "ray_map")

    def _build_ray_map(self) -> np.ndarray:
        return self.pixel_to_ray(self.pixel_grid()).reshape(self.height, self.width, 3)

    def theta_map(self) -> np.ndarray:
        """Angle from the optical axis [deg] of every pixel, shape (height, width) (cached, read-only)."""
        return _shared_map(self, "theta_map")

    def _build_theta_map(self) -> np.ndarray:
        u, v = self._sensor_from_pixel(self.pixel_grid())
        return np.degrees(self.theta_from_r(np.hypot(u, v))).reshape(self.height, self.width)

    def image_circle_mask(self, max_theta_deg: float | None = None) -> np.ndarray:
        """Pixels within ``max_theta_deg`` of the optical axis, shape (height, width), bool."""
        limit = self.max_theta_deg if max_theta_deg is None else min(max_theta_deg, self.max_theta_deg)
        return self.theta_map() <= limit

    def contains(self, px, max_theta_deg: float | None = None) -> np.ndarray:
        """Whether pixels lie inside the image and the image circle, shape (N,), bool."""
        px = _as_pixels(px)
        limit = self.max_theta_deg if max_theta_deg is None else min(max_theta_deg, self.max_theta_deg)
        inside = (
            (px[:, 0] >= -0.5) & (px[:, 0] <= self.width - 0.5)
            & (px[:, 1] >= -0.5) & (px[:, 1] <= self.height - 0.5)
        )
        return inside & (self.theta_of_pixel(px) <= limit + 1e-9)

    def _scaled_common(self, factor: float) -> dict:
        cx, cy = self.center_xy
        return dict(
            width=int(round(self.width * factor)),
            height=int(round(self.height * factor)),
            center_xy=((cx + 0.5) * factor - 0.5, (cy + 0.5) * factor - 0.5),
        )

    def resized_to(self, width: int, height: int | None = None) -> "CameraModel":
        """The model for the image resized to ``width`` (× ``height``, same aspect)."""
        factor = width / self.width
        if height is not None and abs(height / self.height - factor) > 1e-6:
            raise CalibrationError(
                f"resize to {width}x{height} changes the aspect ratio of a {self.width}x{self.height} calibration"
            )
        return self.scaled(factor)

    def to_dict(self) -> dict:
        """Inline-intrinsics form, as in a station TOML's ``[cameras.intrinsics]``."""
        raise NotImplementedError


@dataclass(frozen=True)
class OCamModel(CameraModel):
    """Scaramuzza's omnidirectional model (OCamCalib), in the cbh camera frame.

    ``poly`` holds f(r) = a0 + a1 r + a2 r² + … lowest degree first, with a0 > 0 (the
    paper's Table 1 form; OCamCalib's ``ss`` is its negation). ``invpol`` is the toolbox's
    inverse polynomial, kept for writing the file back; :meth:`ray_to_pixel` inverts the
    forward polynomial exactly (Newton's method), so it works with or without it.
    """

    poly: tuple[float, ...] = ()
    invpol: tuple[float, ...] | None = None
    max_theta_deg: float = 90.0

    kind = "ocam"

    def __post_init__(self):
        if len(self.poly) < 2:
            raise CalibrationError("ocam: polynomial needs at least two coefficients")
        if not self.poly[0] > 0:
            raise CalibrationError(f"ocam: a0 must be > 0 in the cbh frame (got {self.poly[0]})")
        c, d, e = self.affine
        if abs(c - d * e) < 1e-9:
            raise CalibrationError("ocam: affine parameters c, d, e are singular (c - d*e = 0)")
        # The valid radial range: θ(r) = atan2(r, f(r)) must increase with r.
        r_lim = self._radius_limit()
        if math.degrees(math.atan2(r_lim, self._f(np.array([r_lim]))[0])) < self.max_theta_deg - 1e-6:
            reached = math.degrees(math.atan2(r_lim, self._f(np.array([r_lim]))[0]))
            object.__setattr__(self, "max_theta_deg", reached)

    def _f(self, r: np.ndarray) -> np.ndarray:
        return np.polynomial.polynomial.polyval(r, self.poly)

    def _df(self, r: np.ndarray) -> np.ndarray:
        return np.polynomial.polynomial.polyval(r, np.polynomial.polynomial.polyder(self.poly))

    def _radius_limit(self) -> float:
        """Largest r [px] up to which θ(r) is increasing, capped near the image diagonal."""
        if "r_lim" in self._cache:
            return self._cache["r_lim"]
        r_cap = 1.5 * math.hypot(self.width, self.height)
        r = np.linspace(0.0, r_cap, 20001)
        th = np.arctan2(r, self._f(r))
        inc = np.diff(th) > 0
        bad = np.flatnonzero(~inc)
        r_lim = float(r[bad[0]]) if bad.size else r_cap
        # stop at the ray that reaches max_theta_deg if that comes first
        over = np.flatnonzero(th > math.radians(self.max_theta_deg) + 0.02)
        if over.size and r[over[0]] < r_lim:
            r_lim = float(r[over[0]])
        self._cache["r_lim"] = r_lim
        self._cache["table"] = (th[r <= r_lim], r[r <= r_lim])
        return r_lim

    def theta_from_r(self, r):
        r = np.asarray(r, dtype=np.float64)
        return np.arctan2(r, self._f(r))

    def r_from_theta(self, theta):
        theta = np.asarray(theta, dtype=np.float64)
        self._radius_limit()
        th_tab, r_tab = self._cache["table"]
        r = np.interp(theta, th_tab, r_tab)
        ct, st = np.cos(theta), np.sin(theta)
        for _ in range(4):  # g(r) = r cosθ − f(r) sinθ = 0
            g = r * ct - self._f(r) * st
            dg = ct - self._df(r) * st
            r = r - g / np.where(np.abs(dg) > 1e-12, dg, 1e-12)
        return r

    def pixel_to_ray(self, px):
        px = _as_pixels(px)
        u, v = self._sensor_from_pixel(px)
        rays = np.stack([u, v, self._f(np.hypot(u, v))], axis=-1)
        return rays / np.linalg.norm(rays, axis=-1, keepdims=True)

    def scaled(self, factor: float) -> "OCamModel":
        poly = tuple(a * factor ** (1 - k) for k, a in enumerate(self.poly))
        invpol = None if self.invpol is None else tuple(p * factor for p in self.invpol)
        return replace(self, poly=poly, invpol=invpol, **self._scaled_common(factor))

    def to_dict(self) -> dict:
        d = {
            "model": "ocam",
            "poly": [float(a) for a in self.poly],
            "center_xy": [float(c) for c in self.center_xy],
            "affine": [float(a) for a in self.affine],
            "width": self.width,
            "height": self.height,
        }
        if self.invpol is not None:
            d["invpol"] = [float(p) for p in self.invpol]
        return d


@dataclass(frozen=True)
class EquidistantModel(CameraModel):
    """Ideal equidistant fisheye: r = R90 · θ / 90°."""

    radius_px: float = 0.0  # R90, the image radius at θ = 90° [px]
    kind = "equidistant"

    def __post_init__(self):
        if not self.radius_px > 0:
            raise CalibrationError(f"{self.kind}: radius_px must be > 0 (got {self.radius_px})")

    def theta_from_r(self, r):
        return np.asarray(r, dtype=np.float64) * (math.pi / 2) / self.radius_px

    def r_from_theta(self, theta):
        return np.asarray(theta, dtype=np.float64) * self.radius_px / (math.pi / 2)

    def scaled(self, factor: float):
        return replace(self, radius_px=self.radius_px * factor, **self._scaled_common(factor))

    def to_dict(self) -> dict:
        return {
            "model": self.kind,
            "radius_px": float(self.radius_px),
            "center_xy": [float(c) for c in self.center_xy],
            "affine": [float(a) for a in self.affine],
            "width": self.width,
            "height": self.height,
            "max_theta_deg": float(self.max_theta_deg),
        }


@dataclass(frozen=True)
class EquisolidModel(EquidistantModel):
    """Ideal equisolid-angle fisheye: r = R90 / sin 45° · sin(θ / 2)."""

    kind = "equisolid"

    def theta_from_r(self, r):
        s = np.asarray(r, dtype=np.float64) * math.sin(math.pi / 4) / self.radius_px
        return 2.0 * np.arcsin(np.clip(s, -1.0, 1.0))

    def r_from_theta(self, theta):
        return self.radius_px / math.sin(math.pi / 4) * np.sin(np.asarray(theta, dtype=np.float64) / 2.0)


MODELS = {"ocam": OCamModel, "equidistant": EquidistantModel, "equisolid": EquisolidModel}


# --- OCamCalib calib_results.txt --------------------------------------------------------

def read_ocamcalib(path: str | Path) -> OCamModel:
    """Read a ``calib_results.txt`` exactly as the OCamCalib toolbox writes it.

    The file's ``ss`` (a0 < 0, toolbox frame) becomes ``poly = -ss`` in the cbh frame;
    its centre "row column" becomes ``center_xy = (column, row)``.
    """
    path = Path(path)
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise CalibrationError(f"calibration file not found: {path}") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise CalibrationError(f"cannot read calibration file {path}: {exc}") from None
    rows = []
    for line in text.splitlines():
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        try:
            rows.append([float(t) for t in line.split()])
        except ValueError:
            raise CalibrationError(f"{path}: not an OCamCalib calib_results file (bad line {line[:40]!r})") from None
    if len(rows) != 5:
        raise CalibrationError(
            f"{path}: expected 5 data lines (ss, invpol, centre, affine, size), found {len(rows)}"
        )
    ss_row, inv_row, centre, aff, size = rows
    for name, row in (("ss", ss_row), ("invpol", inv_row)):
        if not row or int(row[0]) != len(row) - 1:
            raise CalibrationError(f"{path}: {name} line must start with its coefficient count")
    if len(centre) != 2 or len(aff) != 3 or len(size) != 2:
        raise CalibrationError(f"{path}: centre needs 2 values, affine 3, image size 2")
    ss = ss_row[1:]
    return OCamModel(
        width=int(size[1]),
        height=int(size[0]),
        center_xy=(centre[1], centre[0]),
        affine=(aff[0], aff[1], aff[2]),
        poly=tuple(-a for a in ss),
        invpol=tuple(inv_row[1:]),
    )


def format_ocamcalib(model: OCamModel) -> str:
    """The toolbox's ``calib_results.txt`` text for ``model`` (inverse of :func:`read_ocamcalib`)."""
    ss = [-a for a in model.poly]
    inv = list(model.invpol) if model.invpol is not None else fit_invpol(model)
    c, d, e = model.affine

    def line(vals):
        return f"{len(vals)} " + " ".join(f"{v:.6e}" for v in vals) + " \n"

    return (
        "#polynomial coefficients for the DIRECT mapping function (ocam_model.ss in MATLAB). "
        "These are used by cam2world\n\n" + line(ss)
        + "\n#polynomial coefficients for the inverse mapping function (ocam_model.invpol in MATLAB). "
        "These are used by world2cam\n\n" + f"{len(inv)} " + " ".join(f"{v:.6f}" for v in inv) + " \n"
        + '\n#center: "row" and "column", starting from 0 (C convention)\n\n'
        + f"{model.center_xy[1]:.6f} {model.center_xy[0]:.6f}\n"
        + '\n#affine parameters "c", "d", "e"\n\n' + f"{c:.6f} {d:.6f} {e:.6f}\n"
        + '\n#image size: "height" and "width"\n\n' + f"{model.height} {model.width}\n"
    )


def fit_invpol(model: OCamModel, degree: int = 12) -> list[float]:
    """Fit the toolbox's inverse polynomial rho(t), t = atan(z_tb / hypot) = θ − 90° [rad]."""
    theta = np.linspace(0.0, math.radians(model.max_theta_deg), 400)
    rho = model.r_from_theta(theta)
    t = theta - math.pi / 2
    return [float(c) for c in np.polynomial.polynomial.polyfit(t, rho, degree)]
