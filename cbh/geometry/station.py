"""A station: two or more fisheye cameras with ENU positions and orientations (TOML).

Any number of cameras (a camera network: :mod:`cbh.pipeline.network`); cameras kilometres apart
may give their positions as latitude, longitude and altitude instead of ENU metres.

See docs/conventions.md for the frames. The file format::

    [station]
    name = "unb-lea"
    latitude_deg = -15.7634
    longitude_deg = -47.8703
    altitude_m = 1050.0                      # ENU origin above mean sea level

    [station.metadata]                       # optional; NetCDF global attributes (E-PROFILE style)
    institution = "University of Brasília"   # all optional strings; other keys are an error
    instrument = "two Mobotix Q25 fisheye cameras"
    site = "Brasília, LEA rooftop"
    # contact, comment, references, wigos_station_id

    [ground]                                 # optional; cloud and shadow maps on the ground
    resolution_m = 50.0                      # grid cell size [m]
    extent_m = 6000.0                        # half width of the square grid around the station [m]

    [[cameras]]
    name = "cam1"
    calibration = "cam1_calib_results.txt"   # OCamCalib file, relative to this TOML
    position_m = [0.0, 0.0, 0.0]             # east, north, up of the projection centre
    # latitude_deg, longitude_deg, altitude_m  # instead of position_m: WGS 84 latitude and
    #                                        # longitude [deg] and altitude [m, as the station's],
    #                                        # converted to ENU about [station] (pymap3d)
    yaw_deg = 0.0                            # azimuth the image top faces, clockwise from north
    pitch_deg = 0.0
    roll_deg = 0.0
    # rotation = [[..], [..], [..]]          # R_world_from_cam, rows; instead of the angles
    # [cameras.intrinsics]                   # inline instead of `calibration`
    # model = "ocam" | "equidistant" | "equisolid", poly / radius_px, center_xy, width, height

Other top-level tables (``pipeline``, ``service``, ``scene``) are kept raw in
:attr:`Station.sections` and validated by the module that owns them.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from cbh.geometry.camera import MODELS, CameraModel, OCamModel, read_ocamcalib
from cbh.geometry.ground import GroundGrid, parse_ground
from cbh.errors import CalibrationError, ConfigError
from cbh.tomlio import check_keys, dumps_toml, number, read_toml, string, table, vector

__all__ = ["Camera", "Station", "load_station", "parse_station", "rotation_from_angles", "angles_from_rotation", "rot_x", "rot_y", "rot_z", "B_LEVEL_NORTH_UP"]

#: The level camera whose image top faces north: columns are camera x → west, y → south, z → up.
B_LEVEL_NORTH_UP = np.array([[-1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, 1.0]])

#: Top-level tables a station file may have besides [station] and [[cameras]].
EXTRA_SECTIONS = ("pipeline", "service", "scene", "ground", "ceilometer")  # ceilometer: cbh/actions/validate.py
#: Keys of the optional [station.metadata] table (strings; NetCDF global attributes).
METADATA_KEYS = ("institution", "instrument", "site", "contact", "comment", "references", "wigos_station_id")

_CAMERA_KEYS = {
    "name", "calibration", "intrinsics", "position_m", "yaw_deg", "pitch_deg", "roll_deg",
    "rotation", "mask", "source", "latitude_deg", "longitude_deg", "altitude_m", "clock_offset_s",
}
#: A camera's geodetic position, instead of ``position_m`` (converted with pymap3d about the station).
_GEODETIC_KEYS = ("latitude_deg", "longitude_deg", "altitude_m")
_STATION_KEYS = {"name", "latitude_deg", "longitude_deg", "altitude_m"}
_STATION_OPTIONAL = {"allow_baseline", "pyranometer"}
#: Plausible camera separation [m]: below, a pair cannot triangulate clouds km away (the
#: parallax of a 5 m baseline at 5 km is 0.06°, about the fisheye's pixel size); above, the
#: two cameras no longer see the same cloud base. ``[station] allow_baseline = true`` lifts it.
BASELINE_RANGE_M = (5.0, 5000.0)


def rot_x(a: float) -> np.ndarray:
    """Right-handed rotation by ``a`` [rad] about x, shape (3, 3)."""
    c, s = math.cos(a), math.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]], dtype=np.float64)


def rot_y(a: float) -> np.ndarray:
    """Right-handed rotation by ``a`` [rad] about y, shape (3, 3)."""
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]], dtype=np.float64)


def rot_z(a: float) -> np.ndarray:
    """Right-handed rotation by ``a`` [rad] about z, shape (3, 3)."""
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]], dtype=np.float64)


def rotation_from_angles(yaw_deg: float = 0.0, pitch_deg: float = 0.0, roll_deg: float = 0.0) -> np.ndarray:
    """``R_world_from_cam = Rz(−yaw) · B · Rx(pitch) · Ry(roll)``, shape (3, 3).

    ``yaw_deg`` is the azimuth (clockwise from north) the image's top edge faces; pitch and
    roll tilt the camera about its own x and y axes [deg].
    """
    return rot_z(-math.radians(yaw_deg)) @ B_LEVEL_NORTH_UP @ rot_x(math.radians(pitch_deg)) @ rot_y(math.radians(roll_deg))


def angles_from_rotation(R_world_from_cam) -> tuple[float, float, float]:
    """(yaw_deg, pitch_deg, roll_deg) with ``rotation_from_angles(*angles) == R`` (inverse).

    Unique for |pitch| < 90°; every rotation has such angles.
    """
    R = np.asarray(R_world_from_cam, dtype=np.float64)
    Q = B_LEVEL_NORTH_UP @ R  # = Rz(−yaw) · Rx(pitch) · Ry(roll)  (B is its own inverse and commutes with Rz)
    yaw = math.atan2(Q[0, 1], Q[1, 1])  # Rz(yaw) · Q = Rx · Ry, whose [0, 1] element is 0
    A = rot_z(yaw) @ Q
    pitch = math.atan2(A[2, 1], A[1, 1])
    roll = math.atan2(A[0, 2], A[0, 0])
    return math.degrees(yaw), math.degrees(pitch), math.degrees(roll)


@dataclass(frozen=True)
class Camera:
    """One camera of a station: a lens model plus its pose in ENU.

    Attributes
    ----------
    name : str
    model : CameraModel
        Pixel <-> camera-frame ray.
    position_m : ndarray, shape (3,), float64
        Projection centre in ENU [m].
    R_world_from_cam : ndarray, shape (3, 3), float64
        Rotation taking camera-frame vectors to ENU.
    mask : Path or None
        Static obstacle mask image (non-zero = sky usable), if configured.
    source : str or None
        Where live frames come from (URL, file, directory, ``sim``), if configured.
    clock_offset_s : float or None
        How many seconds late the camera captures against its own time stamps, when the station
        states it (``cbh calibrate`` reports it); the pipeline starts its offset estimate from the
        difference of two cameras' values and goes on estimating. None: not stated.
    """

    name: str
    model: CameraModel
    position_m: np.ndarray
    R_world_from_cam: np.ndarray
    mask: Path | None = None
    source: str | None = None
    clock_offset_s: float | None = None  # how late the camera captures against its own stamps [s]; None = not stated

    def pixel_to_world(self, px) -> np.ndarray:
        """Unit ray directions in ENU of pixels (N, 2) → (N, 3) float64."""
        return self.model.pixel_to_ray(px) @ self.R_world_from_cam.T

    def world_to_pixel(self, points_m) -> np.ndarray:
        """Pixels (N, 2) of ENU points (N, 3) [m]; NaN where outside the model's field."""
        pts = np.asarray(points_m, dtype=np.float64).reshape(-1, 3)
        return self.direction_to_pixel(pts - self.position_m)

    def direction_to_pixel(self, dirs_world) -> np.ndarray:
        """Pixels (N, 2) of ENU directions (N, 3) (points at infinity)."""
        d = np.asarray(dirs_world, dtype=np.float64).reshape(-1, 3)
        return self.model.ray_to_pixel(d @ self.R_world_from_cam)

    def zenith_map(self) -> np.ndarray:
        """Zenith angle [deg] of every pixel's ray, shape (height, width), float32 (cached)."""
        cache = self.model._cache
        key = ("zenith_map", self.R_world_from_cam.tobytes())
        if key not in cache:
            up_cam = self.R_world_from_cam[2]  # world up expressed in the camera frame
            cosz = self.model.ray_map() @ up_cam
            z = np.degrees(np.arccos(np.clip(cosz, -1.0, 1.0))).astype(np.float32)
            z.setflags(write=False)
            cache[key] = z
        return cache[key]

    def scaled(self, factor: float) -> "Camera":
        return replace(self, model=self.model.scaled(factor))


@dataclass(frozen=True)
class Station:
    """Site and cameras. ``cameras`` keeps file order; ``sections`` holds the raw extra tables."""

    name: str
    latitude_deg: float
    longitude_deg: float
    altitude_m: float
    cameras: dict[str, Camera]
    path: Path | None = None
    sections: dict[str, dict] = field(default_factory=dict)
    allow_baseline: bool = False  # accept camera separations outside BASELINE_RANGE_M
    metadata: dict[str, str] = field(default_factory=dict)  # [station.metadata]: keys of METADATA_KEYS
    pyranometer: Path | None = None  # [station] pyranometer = FILE: the site's GHI record (irradiance nowcast levels)

    @property
    def ground(self) -> GroundGrid:
        """The ground grid of the cloud and shadow maps (``[ground]``, defaults when absent)."""
        return parse_ground(self.sections.get("ground", {}), self.latitude_deg, self.longitude_deg)

    def camera(self, name: str) -> Camera:
        try:
            return self.cameras[name]
        except KeyError:
            raise ConfigError(
                f"camera {name!r} is not in station {self.name!r} (cameras: {', '.join(self.cameras)})"
            ) from None

    def pair(self, names: str | tuple[str, str] | list[str] | None = None) -> tuple[Camera, Camera]:
        """The two cameras named ``"a,b"`` (default: the first two in the file)."""
        if names is None:
            if len(self.cameras) < 2:
                raise ConfigError(f"station {self.name!r} needs at least two cameras")
            a, b = list(self.cameras)[:2]
        else:
            parts = [p.strip() for p in names.split(",")] if isinstance(names, str) else list(names)
            if len(parts) != 2 or not all(parts):
                raise ConfigError(f"a camera pair needs two names separated by a comma, got {names!r}")
            a, b = parts
        if a == b:
            raise ConfigError(f"the two cameras of a pair must differ (got {a!r} twice)")
        return self.camera(a), self.camera(b)

    def scaled(self, size_px: int) -> "Station":
        """The station for images resized so that the first camera is ``size_px`` wide."""
        first = next(iter(self.cameras.values()))
        factor = size_px / first.model.width
        return replace(self, cameras={n: c.scaled(factor) for n, c in self.cameras.items()})

    def to_dict(self) -> dict:
        """Self-contained TOML-ready dict (intrinsics inline, rotation as matrix)."""
        cams = []
        for c in self.cameras.values():
            d: dict[str, Any] = {
                "name": c.name,
                "position_m": [float(v) for v in c.position_m],
                "rotation": [[float(v) for v in row] for row in c.R_world_from_cam],
                "intrinsics": c.model.to_dict(),
            }
            if c.mask is not None:
                d["mask"] = str(Path(c.mask).resolve())
            if c.source is not None:
                d["source"] = c.source
            if c.clock_offset_s is not None:
                d["clock_offset_s"] = float(c.clock_offset_s)
            cams.append(d)
        out = {
            "station": {
                "name": self.name,
                "latitude_deg": self.latitude_deg,
                "longitude_deg": self.longitude_deg,
                "altitude_m": self.altitude_m,
                **({"allow_baseline": True} if self.allow_baseline else {}),
                **({"pyranometer": str(Path(self.pyranometer).resolve())} if self.pyranometer else {}),
                **({"metadata": dict(self.metadata)} if self.metadata else {}),
            },
            "cameras": cams,
        }
        out.update({k: v for k, v in self.sections.items()})
        return out

    def to_toml(self) -> str:
        """TOML text that :func:`parse_station` reads back to an equal station."""
        return dumps_toml(self.to_dict())


# --- parsing ------------------------------------------------------------------------------

def _num(where: str, value, *, positive: bool = False) -> float:
    return number(where, value, positive=positive)


def _vec(where: str, value, n: int) -> list[float]:
    return list(vector(where, value, n))


def _unknown(where: str, table: dict, allowed: set) -> None:
    check_keys(where, table, allowed)


def parse_intrinsics(where: str, d: dict) -> CameraModel:
    """Inline intrinsics table → camera model. ``where`` prefixes error messages."""
    if not isinstance(d, dict):
        raise ConfigError(f"{where}: expected a table")
    model = d.get("model", "ocam")
    if model not in MODELS:
        raise ConfigError(f"{where}.model: unknown model {model!r} (choose from {', '.join(MODELS)})")
    common = {"model", "center_xy", "width", "height", "affine"}
    allowed = common | ({"poly", "invpol"} if model == "ocam" else {"radius_px", "max_theta_deg"})
    _unknown(where, d, allowed)
    for key in ("center_xy", "width", "height", "poly" if model == "ocam" else "radius_px"):
        if key not in d:
            raise ConfigError(f"{where}.{key}: missing")
    width = int(_num(f"{where}.width", d["width"], positive=True))
    height = int(_num(f"{where}.height", d["height"], positive=True))
    center = tuple(_vec(f"{where}.center_xy", d["center_xy"], 2))
    affine = tuple(_vec(f"{where}.affine", d.get("affine", [1.0, 0.0, 0.0]), 3))
    try:
        if model == "ocam":
            poly = d["poly"]
            if not isinstance(poly, list) or len(poly) < 2:
                raise ConfigError(f"{where}.poly: expected a list of at least 2 coefficients (a0, a1, …)")
            inv = d.get("invpol")
            return OCamModel(
                width=width, height=height, center_xy=center, affine=affine,
                poly=tuple(_num(f"{where}.poly[{i}]", v) for i, v in enumerate(poly)),
                invpol=None if inv is None else tuple(_num(f"{where}.invpol[{i}]", v) for i, v in enumerate(inv)),
            )
        return MODELS[model](
            width=width, height=height, center_xy=center, affine=affine,
            radius_px=_num(f"{where}.radius_px", d["radius_px"], positive=True),
            max_theta_deg=_num(f"{where}.max_theta_deg", d.get("max_theta_deg", 90.0), positive=True),
        )
    except CalibrationError as exc:
        raise ConfigError(f"{where}: {exc}") from None


def _rotation(where: str, value) -> np.ndarray:
    if not isinstance(value, list) or len(value) != 3:
        raise ConfigError(f"{where}: expected 3 rows of 3 numbers (R_world_from_cam)")
    R = np.array([_vec(f"{where}[{i}]", row, 3) for i, row in enumerate(value)])
    err = np.abs(R @ R.T - np.eye(3)).max()
    if err > 1e-4 or np.linalg.det(R) < 0:
        raise ConfigError(
            f"{where}: not a rotation (|R Rᵀ − I| = {err:.2g}, det = {np.linalg.det(R):.4f}); "
            "it must be orthonormal with det +1"
        )
    # re-orthonormalise the few 1e-6 of rounding a TOML file carries
    u, _, vt = np.linalg.svd(R)
    return u @ vt


def _mask_size(where: str, mask: Path) -> tuple[int, int]:
    """(width, height) of a mask image [px]."""
    img = cv2.imread(str(mask), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise ConfigError(f"{where}.mask: not a readable image: {mask}")
    return int(img.shape[1]), int(img.shape[0])


def _check_baselines(cameras: dict[str, Camera], allow: bool) -> None:
    names = list(cameras)
    lo, hi = BASELINE_RANGE_M
    for j, b in enumerate(names):
        for a in names[:j]:
            d = float(np.linalg.norm(cameras[b].position_m - cameras[a].position_m))
            if allow or lo <= d <= hi:
                continue
            what = ("zero (both cameras at one place)" if d < 1e-6 else
                    f"{d:.2f} m" if d < 1000 else f"{d / 1000:.1f} km")
            raise ConfigError(
                f"cameras[{b}].position_m: baseline to {a} is {what}, outside the plausible "
                f"{lo:g} m – {hi / 1000:g} km (positions are metres east, north, up); "
                "set [station] allow_baseline = true if this is really meant")


def parse_station(data: dict, base_dir: Path | None = None, path: Path | None = None,
                  check_masks: bool = True) -> Station:
    """Validate a station dict (as read from TOML) into a :class:`Station`.

    Besides types and ranges: every two cameras must be 5 m – 5 km apart
    (:data:`BASELINE_RANGE_M`) unless ``[station] allow_baseline = true``, and a camera's
    ``mask`` image must have its calibration's size (``check_masks``; off for stations read
    back from a recording, whose cameras may be scaled).
    """
    label = path.name if path is not None else "station"
    _unknown(label, data, {"station", "cameras", *EXTRA_SECTIONS})
    st = data.get("station")
    if not isinstance(st, dict):
        raise ConfigError(f"{label}: [station] table missing")
    allow_baseline, metadata, lat, lon = _parse_site(st)
    cams_raw = data.get("cameras")
    if not isinstance(cams_raw, list) or len(cams_raw) < 2:
        raise ConfigError(f"{label}: needs at least two [[cameras]] entries")
    base_dir = base_dir or Path.cwd()
    cameras: dict[str, Camera] = {}
    site = (lat, lon, _num("station.altitude_m", st["altitude_m"]))
    for i, c in enumerate(cams_raw):
        cam = _parse_camera(i, c, base_dir, check_masks, cameras, site)
        cameras[cam.name] = cam
    sections = _extra_sections(data, lat, lon)
    _check_baselines(cameras, allow_baseline)
    pyr = st.get("pyranometer")
    if pyr is not None and (not isinstance(pyr, str) or not pyr.strip()):
        raise ConfigError(f"station.pyranometer: expected a file path, got {pyr!r}")
    return Station(
        name=st["name"], latitude_deg=lat, longitude_deg=lon,
        altitude_m=_num("station.altitude_m", st["altitude_m"]),
        cameras=cameras, path=path, sections=sections, metadata=dict(metadata), allow_baseline=allow_baseline,
        pyranometer=(base_dir / pyr).resolve() if pyr else None,
    )


def _parse_site(st: dict) -> tuple[bool, dict, float, float]:
    """The ``[station]`` table: (allow_baseline, metadata, latitude [deg], longitude [deg]),
    every required key present and in range."""
    _unknown("station", st, _STATION_KEYS | _STATION_OPTIONAL | {"metadata"})
    allow_baseline = st.get("allow_baseline", False)
    if not isinstance(allow_baseline, bool):
        raise ConfigError(f"station.allow_baseline: expected true or false, got {allow_baseline!r}")
    metadata = table("station.metadata", st.get("metadata", {}))
    check_keys("station.metadata", metadata, METADATA_KEYS)
    for key, value in metadata.items():
        string(f"station.metadata.{key}", value)
    for key in _STATION_KEYS:
        if key not in st:
            raise ConfigError(f"station.{key}: missing")
    if not isinstance(st["name"], str) or not st["name"]:
        raise ConfigError("station.name: expected a non-empty string")
    lat = _num("station.latitude_deg", st["latitude_deg"])
    lon = _num("station.longitude_deg", st["longitude_deg"])
    if not -90 <= lat <= 90:
        raise ConfigError(f"station.latitude_deg: {lat} is outside -90..90")
    if not -180 <= lon <= 360:
        raise ConfigError(f"station.longitude_deg: {lon} is outside -180..180")
    return allow_baseline, metadata, lat, lon


def _parse_camera(i: int, c, base_dir: Path, check_masks: bool, seen: dict,
                  site: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> Camera:
    """``[[cameras]]`` entry ``i``: its name (not in ``seen``), lens model, pose, mask, source."""
    where = f"cameras[{i}]"
    if not isinstance(c, dict):
        raise ConfigError(f"{where}: expected a table")
    _unknown(where, c, _CAMERA_KEYS)
    name = c.get("name")
    if not isinstance(name, str) or not name:
        raise ConfigError(f"{where}.name: missing or not a string")
    if name in seen:
        raise ConfigError(f"{where}.name: duplicate camera name {name!r}")
    where = f"cameras[{name}]"
    model = _camera_model(where, c, base_dir)
    pos, R = _camera_pose(where, c, site)
    mask = _camera_mask(where, c, base_dir, model, check_masks)
    source = c.get("source")
    if source is not None and not isinstance(source, str):
        raise ConfigError(f"{where}.source: expected a string (URL, file, directory or 'sim')")
    clock = c.get("clock_offset_s")
    if clock is not None:
        clock = _num(f"{where}.clock_offset_s", clock)
        if not abs(clock) <= 3600.0:
            raise ConfigError(f"{where}.clock_offset_s: expected seconds within ±3600, got {clock}")
    return Camera(name=name, model=model, position_m=pos, R_world_from_cam=R, mask=mask, source=source,
                  clock_offset_s=clock)


def _camera_model(where: str, c: dict, base_dir: Path) -> CameraModel:
    """The lens: an OCamCalib ``calibration`` file (relative to the station file) or inline ``intrinsics``."""
    if ("calibration" in c) == ("intrinsics" in c):
        raise ConfigError(f"{where}: give exactly one of 'calibration' (file) or 'intrinsics' (inline table)")
    if "intrinsics" in c:
        return parse_intrinsics(f"{where}.intrinsics", c["intrinsics"])
    if not isinstance(c["calibration"], str):
        raise ConfigError(f"{where}.calibration: expected a file path string")
    cal = Path(c["calibration"])
    cal = cal if cal.is_absolute() else base_dir / cal
    try:
        return read_ocamcalib(cal)
    except CalibrationError as exc:
        raise ConfigError(f"{where}.calibration: {exc}") from None


def _camera_pose(where: str, c: dict, site: tuple[float, float, float] = (0.0, 0.0, 0.0)
                 ) -> tuple[np.ndarray, np.ndarray]:
    """(position_m (3,) ENU [m], R_world_from_cam (3, 3)): ``position_m`` or the geodetic
    position (:func:`_geodetic_position`); ``rotation`` rows or yaw/pitch/roll [deg]."""
    geo = [k for k in _GEODETIC_KEYS if k in c]
    if geo and "position_m" in c:
        raise ConfigError(f"{where}: give either position_m or {', '.join(_GEODETIC_KEYS)}, not both")
    if geo:
        pos = _geodetic_position(where, c, site)
    elif "position_m" not in c:
        raise ConfigError(f"{where}.position_m: missing (or give {', '.join(_GEODETIC_KEYS)})")
    else:
        pos = np.array(_vec(f"{where}.position_m", c["position_m"], 3))
    angles = [k for k in ("yaw_deg", "pitch_deg", "roll_deg") if k in c]
    if "rotation" in c:
        if angles:
            raise ConfigError(f"{where}.rotation: give either 'rotation' or the angles ({', '.join(angles)}), not both")
        return pos, _rotation(f"{where}.rotation", c["rotation"])
    return pos, rotation_from_angles(*(_num(f"{where}.{k}", c.get(k, 0.0)) for k in ("yaw_deg", "pitch_deg", "roll_deg")))


def _geodetic_position(where: str, c: dict, site: tuple[float, float, float]) -> np.ndarray:
    """A camera's ``latitude_deg``, ``longitude_deg``, ``altitude_m`` → ENU [m] about the station's
    site (``pymap3d.geodetic2enu`` on WGS 84: exact at any distance, unlike a flat-earth
    approximation, which is 8 m off in height 10 km away)."""
    import pymap3d

    missing = [k for k in _GEODETIC_KEYS if k not in c]
    if missing:
        raise ConfigError(f"{where}: a geodetic position needs {', '.join(_GEODETIC_KEYS)} (missing: {', '.join(missing)})")
    lat, lon, alt = (_num(f"{where}.{k}", c[k]) for k in _GEODETIC_KEYS)
    if not -90 <= lat <= 90:
        raise ConfigError(f"{where}.latitude_deg: {lat} is outside -90..90")
    if not -180 <= lon <= 360:
        raise ConfigError(f"{where}.longitude_deg: {lon} is outside -180..180")
    e, n, u = pymap3d.geodetic2enu(lat, lon, alt, *site)
    return np.array([float(e), float(n), float(u)])


def _camera_mask(where: str, c: dict, base_dir: Path, model, check_masks: bool) -> Path | None:
    """The obstacle ``mask`` image (relative to the station file), at the calibration's size."""
    if "mask" not in c:
        return None
    if not isinstance(c["mask"], str):
        raise ConfigError(f"{where}.mask: expected an image path string")
    mask = Path(c["mask"]) if Path(c["mask"]).is_absolute() else base_dir / c["mask"]
    if not mask.is_file():
        raise ConfigError(f"{where}.mask: file not found: {mask}")
    if check_masks:
        mw, mh = _mask_size(where, mask)
        if (mw, mh) != (model.width, model.height):
            raise ConfigError(f"{where}.mask: image is {mw}x{mh} px but the camera's calibration is for "
                              f"{model.width}x{model.height} px: {mask}")
    return mask


def _extra_sections(data: dict, lat: float, lon: float) -> dict[str, dict]:
    """The other top-level tables, raw (``[ground]`` checked here: it needs the site)."""
    sections = {}
    for key in EXTRA_SECTIONS:
        if key in data:
            if not isinstance(data[key], dict):
                raise ConfigError(f"{key}: expected a table")
            sections[key] = data[key]
    if "ground" in sections:
        parse_ground(sections["ground"], lat, lon)  # strict keys, checked when the station is read
    return sections


def load_station(path: str | Path) -> Station:
    """Read and validate a station TOML file. Raises :class:`ConfigError` naming the key.

    Validates what this layer owns: ``[station]``, the cameras and ``[ground]``. The tables
    higher layers own (``[pipeline]``, ``[service]``) are kept raw in :attr:`Station.sections`;
    the commands read a station with :func:`cbh.actions.station.load_station` (also
    ``cbh.load_station``), which validates those too, so a station that one command refuses is
    refused by all.
    """
    path = Path(path)
    return parse_station(read_toml(path, "station"), base_dir=path.parent, path=path)
