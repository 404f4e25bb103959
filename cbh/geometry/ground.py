"""Cloud and shadow maps on the ground: camera 1's cloud mask projected onto a regular grid.

The grid is square, in local ENU metres around the station's ENU origin (x east, y north, both
ascending), with 2-D latitude/longitude of every cell centre. Pure numerics: no I/O, no sun
model (callers pass the sun's ENU unit vector from the one sun function).

How a cell gets its value (inverse mapping, so every cell is sampled exactly once):

* **Layer labels.** Every cloud pixel of camera 1 is given to a layer: the layer whose
  ``height_m`` is nearest to the pixel's dense height (``PairResult.height_map``); a cloud pixel
  without a height goes to the layer with the largest cover (the most likely one). Labels:
  ``k >= 0`` cloud of layer k, ``CLEAR`` usable clear sky, ``UNKNOWN`` outside the usable sky
  (image circle, zenith limit, the masked sun disk).
* **Cloud map of layer k** (what is overhead): the cell centre lifted to the layer height,
  ``(x, y, h_k)``, is projected into camera 1 and the label at that pixel (nearest) decides:
  ``1`` cloud of layer k; ``0`` clear sky or a higher layer's cloud (seen through layer k's
  gap); NaN unknown (outside the usable sky, or hidden behind a lower layer's cloud).
* **Shadow map** (what is shaded): a ground cell ``g`` is shaded when the ray from ``g``
  towards the sun meets a layer's cloud, i.e. when layer k's cloud map is 1 at
  ``g + s_xy · h_k / s_z`` (s: unit vector to the sun). 1 = shaded by some layer, 0 = every
  layer is known clear on the sun ray, NaN = unknown (and not shaded by a known cloud).
  A sun at or below the horizon gives NaN everywhere.

Approximations (stated, small at the ranges a sky camera sees): the ground is the plane
``z = 0`` of the ENU frame; each layer is flat at its ``height_m`` (points of a layer with
spread ``σ`` land ``σ · tan(zenith)`` off); latitude/longitude come from the local tangent
plane on the WGS84 ellipsoid (error ≈ r²/(2R) ≈ 3 m at r = 6 km).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from cbh.errors import ConfigError
from cbh.tomlio import check_keys, number, table

__all__ = ["GroundGrid", "parse_ground", "GROUND_KEYS", "layer_labels", "cloud_maps", "shadow_map", "layer_shadows",
           "combine_layers",
           "sun_blocked", "lookup_layer", "CLEAR", "UNKNOWN"]

#: Keys of the station file's optional ``[ground]`` table and their defaults.
GROUND_KEYS = {"resolution_m": 50.0, "extent_m": 5000.0}
MAX_CELLS_PER_SIDE = 2001
CLEAR = -1  # label: usable clear sky
UNKNOWN = -2  # label: outside the usable sky

_WGS84_A = 6378137.0  # semi-major axis [m]
_WGS84_E2 = 6.69437999014e-3  # first eccentricity squared


@dataclass(frozen=True)
class GroundGrid:
    """A square ground grid centred on the station's ENU origin.

    Attributes
    ----------
    resolution_m : float
        Cell size [m].
    extent_m : float
        Half width [m]: cell centres run from −extent to +extent (rounded to whole cells).
    latitude_deg, longitude_deg : float
        The ENU origin (the station).
    """

    resolution_m: float
    extent_m: float
    latitude_deg: float
    longitude_deg: float

    @property
    def n(self) -> int:
        """Cells per side (odd: the station is the centre cell)."""
        return 2 * int(math.floor(self.extent_m / self.resolution_m + 1e-9)) + 1

    @property
    def x_m(self) -> np.ndarray:
        """Cell-centre east coordinates, shape (n,), float64, ascending [m]."""
        h = self.n // 2
        return np.arange(-h, h + 1, dtype=np.float64) * self.resolution_m

    @property
    def y_m(self) -> np.ndarray:
        """Cell-centre north coordinates, shape (n,), float64, ascending [m]."""
        return self.x_m

    def lat_lon(self) -> tuple[np.ndarray, np.ndarray]:
        """Latitude and longitude [deg] of every cell centre, shape (n, n) each (rows = y)."""
        phi = math.radians(self.latitude_deg)
        w = 1.0 - _WGS84_E2 * math.sin(phi) ** 2
        m_r = _WGS84_A * (1.0 - _WGS84_E2) / w ** 1.5  # meridional radius of curvature [m]
        n_r = _WGS84_A / math.sqrt(w)  # prime-vertical radius of curvature [m]
        X, Y = np.meshgrid(self.x_m, self.y_m)
        lat = self.latitude_deg + np.degrees(Y / m_r)
        lon = self.longitude_deg + np.degrees(X / (n_r * math.cos(phi)))
        return lat, lon

    def index(self, x_m: float, y_m: float) -> tuple[int, int] | None:
        """(row, column) of the cell holding ENU point (x, y), None outside the grid."""
        h = self.n // 2
        j = int(round(x_m / self.resolution_m)) + h
        i = int(round(y_m / self.resolution_m)) + h
        return (i, j) if 0 <= i < self.n and 0 <= j < self.n else None


def parse_ground(d: dict, latitude_deg: float, longitude_deg: float) -> GroundGrid:
    """Validate a ``[ground]`` table (strict keys; defaults in :data:`GROUND_KEYS`)."""
    table("ground", d)
    check_keys("ground", d, GROUND_KEYS)
    vals = {key: number(f"ground.{key}", d.get(key, default), positive=True) for key, default in GROUND_KEYS.items()}
    g = GroundGrid(vals["resolution_m"], vals["extent_m"], float(latitude_deg), float(longitude_deg))
    if vals["extent_m"] < vals["resolution_m"]:
        raise ConfigError(f"ground.extent_m: {vals['extent_m']} is smaller than ground.resolution_m {vals['resolution_m']}")
    if g.n > MAX_CELLS_PER_SIDE:
        raise ConfigError(f"ground: extent_m / resolution_m gives {g.n} cells per side (at most {MAX_CELLS_PER_SIDE})")
    return g


def layer_labels(cloud_mask, usable, height_map, layer_heights_m, layer_covers) -> np.ndarray:
    """Which layer each of camera 1's pixels shows.

    Parameters
    ----------
    cloud_mask, usable : ndarray, shape (H, W), bool
        Cloud pixels and usable-sky pixels of camera 1.
    height_map : ndarray, shape (H, W), float
        Dense cloud-base height [m above the ENU origin], NaN where unknown.
    layer_heights_m, layer_covers : sequence of float, length L
        The pair's layers (``Layer.height_m``, ``Layer.cover``).

    Returns
    -------
    ndarray, shape (H, W), int16
        Layer index ``k >= 0`` for cloud pixels, :data:`CLEAR` for usable clear sky,
        :data:`UNKNOWN` elsewhere (also for cloud pixels when there is no layer).
    """
    cloud = np.asarray(cloud_mask, bool)
    use = np.asarray(usable, bool)
    lab = np.full(cloud.shape, UNKNOWN, np.int16)
    lab[use & ~cloud] = CLEAR
    hs = np.asarray(layer_heights_m, np.float64)
    if hs.size == 0:
        return lab
    hm = np.asarray(height_map, np.float64)
    c = cloud & use
    has_h = c & np.isfinite(hm)
    if has_h.any():
        lab[has_h] = np.argmin(np.abs(hm[has_h][:, None] - hs[None, :]), axis=1).astype(np.int16)
    lab[c & ~has_h] = int(np.argmax(np.asarray(layer_covers, np.float64)))
    return lab


def lookup_layer(camera, labels: np.ndarray, k: int, points_m: np.ndarray) -> np.ndarray:
    """Layer k's cloud value at ENU points seen by ``camera``.

    Parameters
    ----------
    camera : cbh.geometry.station.Camera
        Camera 1 at the size of ``labels``.
    labels : ndarray, shape (H, W), int16
        From :func:`layer_labels`.
    k : int
        Layer index.
    points_m : ndarray, shape (..., 3), float
        ENU points on layer k [m].

    Returns
    -------
    ndarray, shape (...), float32
        1 = cloud of layer k, 0 = clear or a higher layer, NaN = unknown.
    """
    pts = np.asarray(points_m, np.float64)
    shape = pts.shape[:-1]
    px = camera.world_to_pixel(pts.reshape(-1, 3))
    H, W = labels.shape
    out = np.full(px.shape[0], np.nan, np.float32)
    ok = np.isfinite(px).all(axis=1)
    col = np.full(px.shape[0], -1, np.int64)
    row = np.full(px.shape[0], -1, np.int64)
    col[ok] = np.floor(px[ok, 0] + 0.5).astype(np.int64)
    row[ok] = np.floor(px[ok, 1] + 0.5).astype(np.int64)
    ok &= (col >= 0) & (col < W) & (row >= 0) & (row < H)
    # in front of the camera only: the layer must be above the camera
    ok &= pts.reshape(-1, 3)[:, 2] > float(camera.position_m[2])
    lab = labels[row[ok], col[ok]]
    v = np.full(lab.shape, np.nan, np.float32)
    v[lab == k] = 1.0
    v[(lab == CLEAR) | (lab > k)] = 0.0
    out[ok] = v
    return out.reshape(shape)


def _cells(grid: GroundGrid) -> tuple[np.ndarray, np.ndarray]:
    return np.meshgrid(grid.x_m, grid.y_m)


def cloud_maps(camera, labels: np.ndarray, layer_heights_m, grid: GroundGrid) -> np.ndarray:
    """Cloud overhead per layer on the grid, shape (L, n, n), float32 (1 / 0 / NaN, see module doc)."""
    X, Y = _cells(grid)
    out = np.empty((len(layer_heights_m), grid.n, grid.n), np.float32)
    for k, h in enumerate(layer_heights_m):
        out[k] = lookup_layer(camera, labels, k, np.stack([X, Y, np.full_like(X, float(h))], axis=-1))
    return out


def combine_layers(values: list[np.ndarray], shape) -> np.ndarray:
    """Per-layer maps → one: any layer 1 → 1; every layer 0 → 0; else NaN."""
    if not values:
        return np.full(shape, np.nan, np.float32)
    v = np.stack(values)
    out = np.full(shape, np.nan, np.float32)
    out[(v == 0).all(axis=0)] = 0.0
    out[(v == 1).any(axis=0)] = 1.0
    return out


def layer_shadows(camera, labels: np.ndarray, layer_heights_m, sun_dir_enu, grid: GroundGrid) -> np.ndarray:
    """Each layer's shadow on the ground, shape (L, n, n), float32 (1 / 0 / NaN).

    Layer k shades cell ``g`` when its cloud map is 1 at ``g + s_xy · h_k / s_z``.
    """
    X, Y = _cells(grid)
    out = np.full((len(layer_heights_m), grid.n, grid.n), np.nan, np.float32)
    if sun_dir_enu is None or float(sun_dir_enu[2]) <= 0.0:
        return out
    s = np.asarray(sun_dir_enu, np.float64)
    for k, h in enumerate(layer_heights_m):
        t = float(h) / s[2]
        pts = np.stack([X + s[0] * t, Y + s[1] * t, np.full_like(X, float(h))], axis=-1)
        out[k] = lookup_layer(camera, labels, k, pts)
    return out


def shadow_map(camera, labels: np.ndarray, layer_heights_m, sun_dir_enu, grid: GroundGrid,
               cloud_fraction: float | None = None, by_layer: np.ndarray | None = None) -> np.ndarray:
    """Cloud shadow on the ground, shape (n, n), float32: 1 shaded, 0 sunlit, NaN unknown.

    ``sun_dir_enu``: unit vector towards the sun (3,), None = unknown. ``cloud_fraction``:
    camera 1's cloud fraction; 0 (a clear sky) makes the whole grid sunlit even without layers.
    ``by_layer``: :func:`layer_shadows` if already computed.
    """
    shape = (grid.n, grid.n)
    if sun_dir_enu is None or float(sun_dir_enu[2]) <= 0.0:
        return np.full(shape, np.nan, np.float32)
    if len(layer_heights_m) == 0:
        return np.zeros(shape, np.float32) if cloud_fraction == 0 else np.full(shape, np.nan, np.float32)
    if by_layer is None:
        by_layer = layer_shadows(camera, labels, layer_heights_m, sun_dir_enu, grid)
    return combine_layers(list(by_layer), shape)


def sun_blocked(camera, labels: np.ndarray, layer_heights_m, motions_ms, sun_dir_enu, lead_s: float,
                at_m=(0.0, 0.0), cloud_fraction: float | None = None) -> float:
    """Is the sun behind cloud at ground point ``at_m`` (ENU x, y) ``lead_s`` seconds from now?

    Frozen-cloud advection: the cloud of layer k that will be on the sun ray at ``t + lead`` is
    now at ``at + s_xy · h_k / s_z − v_k · lead`` (``s`` = the sun direction at ``t + lead``,
    ``v_k`` = the layer's motion). Returns 1.0 (blocked), 0.0 (every layer known clear on the
    ray) or NaN (unknown: a layer's point is outside the usable sky, or its motion is unknown
    for ``lead_s > 0``).

    Parameters
    ----------
    motions_ms : sequence of (east, north) [m/s], length L; NaN = unknown.
    sun_dir_enu : ndarray (3,) or None
        Unit vector to the sun at ``t + lead_s``.
    """
    if sun_dir_enu is None or float(sun_dir_enu[2]) <= 0.0:
        return math.nan
    if len(layer_heights_m) == 0:
        return 0.0 if cloud_fraction == 0 else math.nan
    s = np.asarray(sun_dir_enu, np.float64)
    vals = []
    for k, h in enumerate(layer_heights_m):
        ve, vn = (float(v) for v in motions_ms[k])
        if lead_s:
            if not (math.isfinite(ve) and math.isfinite(vn)):
                vals.append(np.array(np.nan, np.float32))
                continue
        else:
            ve = vn = 0.0
        t = float(h) / s[2]
        p = np.array([at_m[0] + s[0] * t - ve * lead_s, at_m[1] + s[1] * t - vn * lead_s, float(h)])
        vals.append(lookup_layer(camera, labels, k, p))
    return float(combine_layers(vals, ()))
