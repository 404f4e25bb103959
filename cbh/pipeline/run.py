"""The orchestrator: one synchronized frame pair in, one :class:`~cbh.result.PairResult` out.

Stages (each a pure function in its own module; timed into ``PairResult.timing_ms``):

1. ``resize``: both images are downsampled so each lens's 90° radius is at most
   ``working_radius_px`` (INTER_AREA). The camera models are scaled by the *same exact* factor
   (chosen so that width and height scale identically), so the geometry stays exact.
2. ``masks``: image circle ∩ zenith limit ∩ obstacle mask (cached per camera), minus the sun
   disk (pvlib) and saturated blobs.
3. ``segmentation``: cloud mask and fraction per camera.
4. ``match_<method>``: correspondences per configured method (:mod:`.match`).
5. ``triangulation``: all correspondences at once, geometric rejection.
6. ``height_map``: dense map on camera 1's grid, returned at camera 1's full image size.
7. ``layers``: log-height histogram → layers with support checks; each layer's ``cover`` is
   the share of camera 1's usable sky whose cloud pixels (own or nearest measured height) lie
   in its height interval, so the covers add up to the cloud fraction (flag
   ``cover_incomplete`` when over 10 % of the cloud is in no reported layer).

Per-camera caches (scaled models, static masks, the infinity remap table) live in the
:class:`Pipeline` object; ``process`` itself keeps no state between frames.
"""
from __future__ import annotations

import logging
import math
import time
from datetime import datetime, timezone

import numpy as np

from cbh.errors import ConfigError, ImageError
from cbh.imageio import check_image_size
from cbh.result import Histogram, PairResult, PointSet
from cbh.geometry.station import Camera, Station
from cbh.pipeline.config import PipelineConfig
from cbh.pipeline.heightmap import nearest_fill, rasterize_heights, upsample_map
from cbh.pipeline.layers import angular_noise, get_layer_method, height_noise, layer_covers, layer_stats
from cbh.pipeline.masks import angle_map_deg, load_obstacle_mask, saturation_mask, static_sky_mask, sun_direction_enu
from cbh.pipeline.match import MatchInput, PairGeometry, get_matcher, triangulate_matches
from cbh.pipeline.segment import segment

__all__ = ["Pipeline", "working_factor"]

log = logging.getLogger(__name__)

_MAX_DISPLAY_MATCHES = 5000
_COVER_SLACK = 0.1  # flag cover_incomplete when more than this share of the cloud is in no layer
_RADIUS_SLACK = 1.05  # working_factor: the working radius may exceed working_radius_px by 5 %


def working_factor(cam: Camera, working_radius_px: float) -> float:
    """Exact downsampling factor (≤ 1) for a camera: its 90° radius becomes ≤ ``working_radius_px``
    (up to 5 % more, so that an image is not resampled by a hair, e.g. 960 → 959 px, which
    only blurs it).

    Preferred: 1 or 1/n with n a whole divisor of width and height (1920 → 960: each working
    pixel is the mean of a 2 × 2 block). Otherwise n / gcd(width, height), so that width and
    height scale by exactly the same ratio (OpenCV's resize then matches
    :meth:`CameraModel.scaled` to the pixel).
    """
    m = cam.model
    if working_radius_px <= 0:
        return 1.0
    r90 = float(np.atleast_1d(m.r_from_theta(np.array([math.pi / 2])))[0])
    if not r90 > 0 or not math.isfinite(r90):
        r90 = 0.5 * min(m.width, m.height)
    f = working_radius_px / r90
    if f >= 1.0 / _RADIUS_SLACK:
        return 1.0
    n = math.ceil(1.0 / (f * _RADIUS_SLACK))  # a whole divisor: exact, and the fast INTER_AREA path
    if m.width % n == 0 and m.height % n == 0 and n * f <= 1.25:  # not much below the target
        return 1.0 / n
    g = math.gcd(m.width, m.height)
    n = max(1, round(f * g))
    exact = n / g
    if abs(exact - f) / f > 0.1:  # awkward sizes: scale by width (≤ half a pixel off in height)
        exact = round(m.width * f) / m.width
    return exact


class Pipeline:
    """Cloud-base heights from frame pairs of two station cameras.

    Parameters
    ----------
    station : Station
    cameras : str or None
        ``"cam1,cam2"`` (default: the first two cameras of the station).
    config : PipelineConfig or None
        Default: the station's ``[pipeline]`` table (or all defaults).

    Examples
    --------
    >>> pipe = Pipeline(station)                       # doctest: +SKIP
    >>> result = pipe.process(img1, img2, time_utc)     # doctest: +SKIP
    >>> result.summary()["layers"]                      # doctest: +SKIP
    """

    def __init__(self, station: Station, cameras: str | None = None, config: PipelineConfig | None = None):
        self.station = station
        self.config = config if config is not None else PipelineConfig.from_dict(station.sections.get("pipeline", {}))
        if not isinstance(self.config, PipelineConfig):
            raise ConfigError(f"pipeline config: expected a PipelineConfig, got {type(self.config).__name__}")
        self.cam1_full, self.cam2_full = station.pair(cameras)
        self.cameras = (self.cam1_full.name, self.cam2_full.name)
        self.factors = tuple(working_factor(c, self.config.working_radius_px) for c in (self.cam1_full, self.cam2_full))
        self.cam1, self.cam2 = (c.scaled(f) if f != 1.0 else c for c, f in zip((self.cam1_full, self.cam2_full), self.factors))
        self._static: dict[int, np.ndarray] = {}
        self._rays: dict[int, np.ndarray] = {}
        self._zenith: dict[int, np.ndarray] = {}
        self._geometry: PairGeometry | None = None
        self._layers = get_layer_method(self.config.layers.method)
        for name in self.config.matching.methods:
            get_matcher(name)

    # --- caches ---------------------------------------------------------------------------
    @property
    def geometry(self) -> PairGeometry:
        """Infinity remap table and camera-1 rays at working size (built on first use)."""
        if self._geometry is None:
            self._geometry = PairGeometry(self.cam1, self.cam2)
        return self._geometry

    def static_mask(self, i: int) -> np.ndarray:
        """Static usable-sky mask of camera ``i`` (0 or 1) at working size, (H, W) bool."""
        if i not in self._static:
            cam = (self.cam1, self.cam2)[i]
            obstacle = None
            if cam.mask is not None and self.config.masks.static_mask:
                obstacle = load_obstacle_mask(cam.mask, cam.model.width, cam.model.height)
            self._static[i] = static_sky_mask(cam, self.config.masks, obstacle)
        return self._static[i]

    def rays_cam(self, i: int) -> np.ndarray:
        """Ray map of camera ``i`` at working size in its own frame, (H, W, 3) float32 (cached)."""
        if i not in self._rays:
            self._rays[i] = (self.cam1, self.cam2)[i].model.ray_map().astype(np.float32)
        return self._rays[i]

    def zenith(self, i: int) -> np.ndarray:
        """Zenith angle of camera ``i``'s pixels at working size, (H, W) float32 [deg] (cached)."""
        if i not in self._zenith:
            self._zenith[i] = np.asarray((self.cam1, self.cam2)[i].zenith_map(), np.float32)
        return self._zenith[i]

    def to_working(self, i: int, image: np.ndarray) -> np.ndarray:
        """Resize a full-size image of camera ``i`` to working size."""
        import cv2

        cam = (self.cam1, self.cam2)[i]
        if self.factors[i] == 1.0:
            return image
        return cv2.resize(image, (cam.model.width, cam.model.height), interpolation=cv2.INTER_AREA)

    def to_full_px(self, i: int, px: np.ndarray) -> np.ndarray:
        """Working-size pixel coordinates of camera ``i`` → full-size coordinates."""
        f = self.factors[i]
        return px if f == 1.0 else (px + 0.5) / f - 0.5

    # --- the pair -------------------------------------------------------------------------
    def process(self, image1: np.ndarray, image2: np.ndarray, time_utc: datetime | None) -> PairResult:
        """Run every stage on one synchronized pair.

        Parameters
        ----------
        image1, image2 : ndarray, shape (H, W, 3), uint8
            BGR images of camera 1 and camera 2 at their calibration sizes.
        time_utc : datetime or None
            Capture time (timezone-aware; used for the sun position). None: unknown; the sun is
            then masked only where it saturates, the result is stamped with the current time
            and flagged ``time_unknown``.

        Returns
        -------
        PairResult
            Heights above the ENU origin; ``height_map`` on camera 1's full pixel grid.

        Raises
        ------
        ImageError
            An image is not (H, W, 3) uint8 or does not match its calibration size.
        """
        cfg = self.config
        for img, cam in ((image1, self.cam1_full), (image2, self.cam2_full)):
            if not isinstance(img, np.ndarray) or img.ndim != 3 or img.shape[2] != 3 or img.dtype != np.uint8:
                shape = getattr(img, "shape", None)
                raise ImageError(f"{cam.name}: expected a BGR uint8 (H, W, 3) image, got {shape}")
            check_image_size(img, cam.model, cam.name)
        timing: dict[str, float] = {}
        flags: list[str] = []
        known_time = time_utc is not None
        if not known_time:
            time_utc = datetime.now(timezone.utc)
            flags.append("time_unknown")
        elif time_utc.tzinfo is None:
            raise ConfigError("process: time_utc must be timezone-aware (UTC)")
        time_utc = time_utc.astimezone(timezone.utc)
        t_all = time.perf_counter()

        t = time.perf_counter()
        w1, w2 = self.to_working(0, image1), self.to_working(1, image2)
        timing["resize"] = _ms(t)

        # masks
        t = time.perf_counter()
        usable, sun_angle = [], []
        sun_dir = None
        if known_time and (cfg.masks.sun or cfg.segmentation.method == "nbr_adaptive"):
            sun_dir, sun_zen = sun_direction_enu(self.station.latitude_deg, self.station.longitude_deg, time_utc)
            if sun_zen >= 90.0:
                sun_dir = None
        for i, (cam, img) in enumerate(((self.cam1, w1), (self.cam2, w2))):
            u = self.static_mask(i)
            ang = angle_map_deg(cam, sun_dir, self.rays_cam(i)) if sun_dir is not None else None
            if cfg.masks.sun and ang is not None:
                u = u & (ang > cfg.masks.sun_radius_deg)
            if cfg.masks.saturation:
                sat = saturation_mask(img, cfg.masks)
                if sat.any():
                    u = u & ~sat
                    if i == 0:
                        flags.append("sun_glare")
            usable.append(u)
            sun_angle.append(ang)
        timing["masks"] = _ms(t)

        # segmentation
        t = time.perf_counter()
        clouds, fractions = [], {}
        for i, (cam, img) in enumerate(((self.cam1, w1), (self.cam2, w2))):
            c, frac = segment(img, usable[i], self.zenith(i), sun_angle[i], cfg.segmentation)
            clouds.append(c)
            fractions[cam.name] = frac
        timing["segmentation"] = _ms(t)

        # correspondences
        import cv2

        geom = self.geometry
        inp = MatchInput(
            geometry=geom,
            gray1=cv2.cvtColor(w1, cv2.COLOR_BGR2GRAY), gray2=cv2.cvtColor(w2, cv2.COLOR_BGR2GRAY),
            cloud1=clouds[0], usable1=usable[0], usable2=usable[1], cloud2=clouds[1],
        )
        raw = []
        if clouds[0].any():
            for name in cfg.matching.methods:
                t = time.perf_counter()
                raw.append(get_matcher(name)(inp, cfg.matching))
                timing[f"match_{name}"] = _ms(t)

        # triangulation and rejection
        t = time.perf_counter()
        tris = [triangulate_matches(geom, m, cfg.filtering) for m in raw]
        timing["triangulation"] = _ms(t)

        # dense height map (working size, then camera 1's full grid)
        t = time.perf_counter()
        shape1 = (self.cam1.model.height, self.cam1.model.width)
        dense = [tr for tr in tris if tr.matches.dense]
        src = dense if dense else tris
        if src:
            px = np.concatenate([tr.matches.px1 for tr in src])
            hh = np.concatenate([tr.height_m for tr in src])
        else:
            px, hh = np.zeros((0, 2)), np.zeros(0)
        hmap_w = rasterize_heights(shape1, px, hh)
        known = np.isfinite(hmap_w)
        nearest, dist = nearest_fill(hmap_w)
        if cfg.height_map.fill == "nearest":
            fill = clouds[0] & ~known & (dist <= cfg.height_map.fill_max_px)
            hmap_w = hmap_w.copy()
            hmap_w[fill] = nearest[fill]
        hmap_full = upsample_map(hmap_w, self.cam1_full.model.width, self.cam1_full.model.height)
        timing["height_map"] = _ms(t)

        # point set (dense correspondences thinned to a regular grid)
        t = time.perf_counter()
        parts = []
        for tr in tris:
            m = tr.matches
            stride = getattr(cfg.matching, m.method).point_stride_px if m.dense else 1
            keep = np.ones(len(m), bool)
            if m.dense and stride > 1:
                xi, yi = m.px1[:, 0].astype(np.int64), m.px1[:, 1].astype(np.int64)
                keep = (xi % stride == 0) & (yi % stride == 0)
            parts.append((m.method, tr.point_m[keep], tr.miss_m[keep], m.px1[keep], m.px2[keep]))
        if parts:
            xyz = np.concatenate([p[1] for p in parts])
            miss = np.concatenate([p[2] for p in parts])
            p1 = self.to_full_px(0, np.concatenate([p[3] for p in parts]))
            p2 = self.to_full_px(1, np.concatenate([p[4] for p in parts]))
        else:
            xyz, miss, p1, p2 = np.zeros((0, 3)), np.zeros(0), np.zeros((0, 2)), np.zeros((0, 2))
        heights = xyz[:, 2]
        noise = height_noise(xyz, self.cam1.position_m, self.cam2.position_m,
                             angular_noise(np.concatenate([tr.miss_m for tr in tris if not tr.matches.dense] or [np.zeros(0)]),
                                           np.concatenate([np.linalg.norm(tr.point_m - self.cam1.position_m, axis=1)
                                                           for tr in tris if not tr.matches.dense] or [np.zeros(0)])))

        # layers
        hist, intervals = self._layers(heights, cfg.layers, cfg.filtering)
        label = np.full(len(heights), -1, np.int16)
        cover_of, unassigned = layer_covers(clouds[0], usable[0], nearest, intervals)
        layers = []
        ly = cfg.layers
        for k, (lo, hi) in enumerate(intervals):
            sel = (heights >= lo) & (heights < hi)
            n = int(sel.sum())
            if n < ly.min_points or n < ly.min_fraction * len(heights) or cover_of[k] < ly.min_cover:
                unassigned += cover_of[k]  # cloud of an unsupported height interval: in no layer
                continue
            label[sel] = len(layers)
            layers.append(layer_stats(heights[sel], cover_of[k], ly, noise[sel]))
        frac1 = fractions[self.cam1.name]
        if layers and unassigned > max(_COVER_SLACK * frac1, 0.005):
            flags.append("cover_incomplete")  # the layers' covers add up to less than the cloud fraction
        timing["layers"] = _ms(t)

        if len(heights) < cfg.layers.min_points:
            flags.append("few_points")
        if fractions[self.cam1.name] < 0.01:
            flags.append("clear_sky")
        elif fractions[self.cam1.name] > 0.9 and len(heights) < cfg.layers.min_points:
            flags.append("overcast_no_texture")
        timing["total"] = _ms(t_all)

        matches = {}
        off = 0
        for method, pts, _, _, _ in parts:
            n = len(pts)
            step = max(1, int(math.ceil(n / _MAX_DISPLAY_MATCHES)))
            sl = slice(off, off + n, step)
            matches[method] = np.concatenate([p1[sl], p2[sl]], axis=1).astype(np.float32)
            off += n

        return PairResult(
            time_utc=time_utc,
            cameras=self.cameras,
            layers=layers,
            histogram=hist if isinstance(hist, Histogram) else Histogram(np.zeros(1), np.zeros(0)),
            points=PointSet(
                xyz_m=xyz.astype(np.float32), miss_m=miss.astype(np.float32),
                px1=p1.astype(np.float32), px2=p2.astype(np.float32), layer=label,
            ),
            height_map=hmap_full.astype(np.float32, copy=False),
            cloud_masks={
                self.cam1.name: upsample_map(clouds[0].view(np.uint8), self.cam1_full.model.width, self.cam1_full.model.height).astype(bool),
                self.cam2.name: upsample_map(clouds[1].view(np.uint8), self.cam2_full.model.width, self.cam2_full.model.height).astype(bool),
            },
            cloud_fraction=fractions,
            timing_ms=timing,
            flags=flags,
            matches=matches,
        )


def _ms(t0: float) -> float:
    return (time.perf_counter() - t0) * 1000.0
