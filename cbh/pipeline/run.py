"""The orchestrator: one synchronized frame pair in, one :class:`~cbh.result.PairResult` out.

Stages (each a pure function in its own module; timed into ``PairResult.timing_ms``):

1. ``resize``: both images are downsampled so each lens's 90° radius is at most
   ``working_radius_px`` (INTER_AREA). The camera models are scaled by the *same exact* factor
   (chosen so that width and height scale identically), so the geometry stays exact.
2. ``masks``: image circle ∩ zenith limit ∩ obstacle mask (cached per camera), minus the sun
   disk (pvlib) and saturated blobs.
   ``sun_check``: the sun detected in each image against the sun predicted from the time and
   the calibrated rotation (:mod:`.sundetect`): diagnostics ``sun_residual_deg`` (worst camera),
   ``sun_residual_cam1_deg``, ``sun_residual_cam2_deg``, flag ``sun_misaligned``.
2b. ``photometric``: camera 2's gain, gamma and white balance relative to camera 1, estimated
   in the common field of view, reported in ``diagnostics`` (flag ``exposure_mismatch`` when
   large) and removed from camera 2's image before segmentation and matching.
3. ``segmentation``: cloud mask and fraction per camera (colour images only).
4. ``match_<method>``: correspondences per configured method (:mod:`.match`).
5. ``triangulation``: all correspondences at once, geometric rejection.
   ``geometry_check``: the 2-D correspondences against the calibrated rotations and the
   baseline (:mod:`.geocheck`): diagnostics ``geometry_residual_px`` and
   ``geometry_inlier_fraction``, flags ``geometry_mismatch`` and ``identical_images``.
6. ``height_map``: dense map on camera 1's grid, returned at camera 1's full image size.
7. ``layers``: log-height histogram → layers with support checks; each layer's ``cover`` is
   the share of camera 1's usable sky whose cloud pixels (own or nearest measured height) lie
   in its height interval, so the covers add up to the cloud fraction (flag
   ``cover_incomplete`` when over 10 % of the cloud is in no reported layer).

8. ``motion`` (with ``previous``, :mod:`.motion`): each camera's features tracked back to the
   previous pair, converted to each layer's motion over the ground [m/s]; camera 2's clock
   offset estimated from the parallax across the baseline, and compensated (``compensation``:
   camera 2's image moved back to camera 1's capture time) before the matching: the sweep's
   planes each with the motion of their own height (the tracks' motion profile), the sparse
   matchers on one image compensated per pixel.

Per-camera caches (scaled models, static masks, the infinity remap table) live in the
:class:`Pipeline` object; ``process`` itself keeps no state between frames: what one pair leaves
for the next is an explicit :class:`~cbh.pipeline.motion.PairState`, passed in as ``previous``
and handed back as ``PairResult.state``.
"""
from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from datetime import datetime
from functools import cached_property, partial

import cv2
import numpy as np

from cbh.errors import ConfigError
from cbh.flags import HIDDEN_OFFSET_SHARE
from cbh.imageio import as_bgr
from cbh.timeutil import parse_utc
from cbh.result import Enlarged, PairResult, PointSet
from cbh.geometry.station import Camera, Station
from cbh.geometry.triangulate import points_on_epipolar
from cbh.pipeline.config import PipelineConfig
from cbh.pipeline.geocheck import (CARRIED_METHODS, CHECK_METHODS, check_geometry, images_identical, seeded_matches,
                                   window_height_spread)
from cbh.pipeline.sundetect import detect_sun
from cbh.pipeline.heightmap import HeightMap, dense_height_map
from cbh.pipeline.layers import (LayerSet, angular_noise, cover_incomplete, get_layer_method, height_noise, parallax_px,
                                 supported_layers)
from cbh.pipeline.masks import (angle_map_deg, glare_and_sunlit, load_obstacle_mask, near_clip, saturation_mask,
                                static_sky_mask)
from cbh.pipeline.clip import FULL_RANGE_WHITE_DN, clip_level
from cbh.pipeline.ccl import components_with_stats
from cbh.pipeline.overlay import overlay_text, search_area
from cbh.pipeline.obstacles import FrameObstacleConfig, darkest_of_four, horizon_grid, obstacle_rings, obstacles_in_frame
from cbh.pipeline.support import FLARE_BAND_DEG, alias_layers, flare_layers, unseen_layers, without_layers
from cbh.geometry.sun import sun_position
from cbh.pipeline.match import (BELOW_RANGE_CHANCE_FRACTION, BELOW_RANGE_FRACTION, EPIPOLAR_METHODS, FLOOR_LAYER_MATCHED, FLOOR_LAYER_RATIO,
                                UNMATCHED_FRACTION, Matches, MatchInput, PairGeometry, TriangulatedMatches,
                                get_matcher, match_scores, sample_map, triangulate_matches)
from cbh.pipeline.motion import (MotionProfile, PairState, assign_layers, compensate_camera2, layer_motion,
                                 motion_weights, offset_estimate, offset_per_match, parallax_heights, plane_offsets,
                                 running_offset, shifted_images, track_back, track_profile, update_offsets,
                                 jump_floor_s, jump_threshold)
from cbh.pipeline.skyclock import SkyClock, sky_clock, sky_grid
from cbh.pipeline.photometric import estimate_response
from cbh.pipeline.segment import (chroma, local_contrast, normalized_blue_red, one_class_pair_is_clear, sample_lattice,
                                  segment)
from cbh.pipeline.threads import pmap

__all__ = ["Pipeline", "working_factor", "PairContext", "Prepared", "Masks", "Segmentation", "Correspondences",
           "Points"]

log = logging.getLogger(__name__)

_MAX_DISPLAY_MATCHES = 5000
_FLOOR_LAYER_COVER = 0.05  # a layer at the sweep's floor counts for below_range from this cover up (see match.FLOOR_LAYER_RATIO)
NIGHT_SUN_DEPRESSION_DEG = 6.0  # an underexposed pair with the sun this far below the horizon (civil twilight over) is night
CLEAR_SKY_FRACTION = 0.01  # camera 1's cloud fraction below this is a clear sky (flag clear_sky; no geometry verdict)
#: A barely matched sky (under ``UNMATCHED_FRACTION`` of camera 1's cloud measured) whose largest
#: patch of measured pixels spans fewer than this many matching windows (``sweep.window_px``²)
#: holds chance matches only: no layer. On a featureless sky (a hazy clear sky one camera
#: over-exposes, read as overcast) the few windows whose noise and JPEG blocks reach the sweep's
#: ``min_texture`` match some plane by chance, in patches of at most 1.5–1.7 windows (118–140 px
#: at 9 px windows; randomized sky 9339 at 480 and 960 px: 2.0 and 0.1 % of the cloud measured,
#: a layer at 374 or 893 m on a clear sky). Real texture is measured in patches of ≥ 15 windows
#: even where little of the cloud is (randomized dense skies with 6–7 % measured: 1205–1276 px).
CHANCE_PATCH_WINDOWS = 4
#: … and so does one with under this share of its cloud measured, whatever its patches: a clear
#: sky over-exposed to white round a large aureole (randomized 10034, twice encoded, 960 px: both
#: cameras at their 242 DN clip, read as one cloud) matched 0.6 % of it along the smooth edge of the
#: white, in a patch of 10 windows, and made a layer at 243 m. The least matched real texture of the
#: randomized sets was measured over 6 % of the cloud (dense 9475).
CHANCE_MEASURED_FRACTION = 0.01
CLEAR_PAIR_MAX_FRACTION = 0.15  # one camera under CLEAR_SKY_FRACTION and the other under this: a clear pair (masks emptied)
_PALE_PARTNER_MAX_FRACTION = 0.5  # one camera calls the sky one cloud, the other under this and blue: the first is pale (Pipeline._pale_camera)
_OVERCAST_FRACTION = 0.9  # a camera whose cloud fraction reaches this calls its sky one cloud
# the defaults' pixels at half size; crowns up to 3° (8 px at a 480 px lens radius) above what stands (a trunk
# thinner than a pixel is not seen below its crown: randomized clear skyline seeds 7020, 7025; 8 is the least that
# keeps seed 5 clear); hang_max_px: crowns, not cloud (uncapped, on the real Fehmarn hour dark cloud bases beside the
# mast and lamp joined them: a valid pair lost as recorded, one phantom-led at -1 frame; the skyline tests pass capped)
_HALF_SIZE_OBSTACLES = FrameObstacleConfig(min_area_px=3, dilate_px=1, fill_px=1, hang_px=8, hang_max_px=1000, grid_deg=0.5)
_SKYLINE_CLOUD_SHARE = 0.9  # a pair without a layer whose cloud is this much on its skylines is clear (_only_on_skylines)
_OBSTACLE_LEARN_FRAMES = 10  # frames of a camera after which its persistent obstacles stay masked
_OBSTACLE_LEARN_SHARE = 0.6  # … those found in at least this share of its frames
_MAX_PASSES = 4  # matching passes of one pair: the first pairs with a clock offset refine it (see .motion)
_RATES_SETTLED_PX = 0.1  # … until the compensation moves by less than this between passes [px]
MIN_PARALLAX_OVER_CARRY = 1.0  # a layer matched on the sky maps needs this × the carry's noise of parallax near the zenith (Pipeline._carry_swamps) [1]
_MIN_NOISE_MATCHES = 20  # fewer sparse matches: the angular noise comes from the dense 2-D ones
_RADIUS_SLACK = 1.05  # working_factor: the working radius may exceed working_radius_px by 5 %
_TRACK_NOISE_PX = 0.1  # LK stereo match noise for the motion tracks' height check [px at working size]


def _resolve_backend(device: str, backend: str):
    """(torch device or "cpu", "opencv" | "torch") from the user's ``device`` and ``backend``."""
    if backend not in ("auto", "opencv", "torch"):
        raise ConfigError(f"backend must be auto, opencv or torch, got {backend!r}")
    if str(device) == "cpu" and backend in ("auto", "opencv"):
        return "cpu", "opencv"
    if backend == "opencv":
        raise ConfigError(f"backend opencv runs on device cpu only, not {device!r}")
    from cbh.pipeline.torch_ops import resolve_device

    return resolve_device(device), "torch"


def _sky_median(feature, image: np.ndarray, where: np.ndarray, neighbourhood: bool = False) -> float:
    """Median of the per-pixel ``feature`` (a colour map of a BGR image; ``neighbourhood``: one that
    reads each pixel's surroundings, run on the whole image) over ``where``, on its sampling lattice
    (:func:`.segment.sample_lattice`); NaN where nothing is left (every comparison then fails)."""
    sl = sample_lattice(np.count_nonzero(where))
    w = where[sl]
    if not w.any():
        return math.nan
    values = feature(image)[sl] if neighbourhood else feature(image[sl])
    return float(np.median(values[w]))


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
    device : str
        ``"cpu"`` (default) or a torch device (``"cuda"``, ``"cuda:1"``): where the dense
        per-pair work runs (the plane sweep, the sun angle maps). Its per-camera tables (plane
        maps, ray maps) are uploaded once, on first use.
    backend : str
        ``"auto"`` (default): numpy/OpenCV on ``"cpu"`` (the faster there), torch elsewhere;
        ``"torch"``: torch on any device (also the CPU: the parity tests use it);
        ``"opencv"``: numpy/OpenCV (``device="cpu"`` only). The sparse matchers (lk, orb, dis)
        always run on OpenCV (:data:`~cbh.pipeline.match.MATCHER_BACKENDS`).

    Examples
    --------
    >>> pipe = Pipeline(station)                       # doctest: +SKIP
    >>> result = pipe.process("cam1.jpg", "cam2.jpg", time_utc)     # doctest: +SKIP
    >>> result.summary()["layers"]                      # doctest: +SKIP
    """

    def __init__(self, station: Station, cameras: str | None = None, config: PipelineConfig | None = None,
                 device: str = "cpu", backend: str = "auto"):
        if not isinstance(station, Station):
            raise ConfigError(f"Pipeline: expected a Station, got {type(station).__name__} "
                              f"(read a station file with cbh.load_station(path))")
        self.station = station
        self.device, self.backend = _resolve_backend(device, backend)
        self.config = config if config is not None else PipelineConfig.from_dict(station.sections.get("pipeline", {}))
        if not isinstance(self.config, PipelineConfig):
            raise ConfigError(f"pipeline config: expected a PipelineConfig, got {type(self.config).__name__}")
        self.cam1_full, self.cam2_full = station.pair(cameras)
        self.cameras = (self.cam1_full.name, self.cam2_full.name)
        self.factors = tuple(working_factor(c, self.config.working_radius_px) for c in (self.cam1_full, self.cam2_full))
        self.cam1, self.cam2 = (c.scaled(f) if f != 1.0 else c for c, f in zip((self.cam1_full, self.cam2_full), self.factors))
        self._static: dict[int, np.ndarray] = {}
        self._circles: dict[int, tuple] = {}  # per camera: obstacle rings and horizon band (working size)
        self._inside: dict[int, np.ndarray] = {}  # per camera: its image circle less its rim (working size)
        self._obstacle_votes: dict[int, tuple[np.ndarray, int]] = {}  # frames in which each pixel was an obstacle, of n
        self._obstacle_lock = threading.Lock()
        self._rays: dict[int, np.ndarray] = {}
        self._zenith: dict[int, np.ndarray] = {}
        self._geometry: PairGeometry | None = None
        self._tables_key: str | None = None  # set once the disk cache was consulted (cbh.pipeline.tables)
        self._sky_grid = None  # both cameras' sky-map remap tables (cbh.pipeline.skyclock), built at first use
        self._tables_loaded = False
        self._layers = get_layer_method(self.config.layers.method)
        # a camera network's per-frame-set memo of camera 1's own stages, shared by the pipelines of
        # the pairs that hold it as camera 1 (cbh.pipeline.network sets it per frame set; None: off)
        self.frame_memo: FrameMemo | None = None
        for name in self.config.matching.methods:
            get_matcher(name)

    # --- caches ---------------------------------------------------------------------------
    def _load_tables(self) -> None:
        """Fill the per-camera caches from the disk cache (:mod:`cbh.pipeline.tables`), if there."""
        from cbh.pipeline.sweep import PlaneMaps
        from cbh.pipeline.tables import load_tables, tables_key

        self._tables_key = tables_key(self.cam1, self.cam2, self.config.masks)
        t = load_tables(self._tables_key)
        if t is None:
            return
        try:
            planes = None
            if "plane_m0" in t:
                s_a, scale = (float(v) for v in t["plane_scalars"])
                planes = PlaneMaps(t["plane_m0"], t["plane_a"], t["plane_b"], s_a, scale, t.get("plane_c"))
            self._geometry = PairGeometry.from_tables(self.cam1, self.cam2, t["map_x"], t["map_y"], planes,
                                                      t.get("rays1_world"))
            self._static = {0: t["static0"], 1: t["static1"]}
            for i in (0, 1):  # the per-camera ray and zenith maps (each a fisheye back-projection of every pixel)
                if f"rays_cam{i}" in t:
                    self._rays[i] = t[f"rays_cam{i}"]
                if f"zenith{i}" in t:
                    self._zenith[i] = t[f"zenith{i}"]
            self._tables_loaded = True
        except (KeyError, ValueError) as e:  # an entry of another layout: rebuild
            log.warning("table cache entry unusable (%s); rebuilding", e)
            self._geometry, self._static = None, {}

    def _save_tables(self) -> None:
        from cbh.pipeline.tables import save_tables

        if self._geometry is None or len(self._static) < 2:
            return
        save_tables(self._tables_key, {**self._geometry.tables(), "static0": self._static[0], "static1": self._static[1],
                                       **{f"rays_cam{i}": self.rays_cam(i) for i in (0, 1)},
                                       **{f"zenith{i}": self.zenith(i) for i in (0, 1)}})

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

    def inside_circle(self, i: int) -> np.ndarray:
        """Camera ``i``'s image circle at working size less a 3 px rim, (H, W) bool: where its
        on-screen text is looked for (the rim's step from black to bright sky is no text) and
        its clip level is read (less the text)."""
        if i not in self._inside:
            self._inside[i] = search_area((self.cam1, self.cam2)[i].model.image_circle_mask())
        return self._inside[i]

    def auto_obstacles(self, i: int, image: np.ndarray) -> np.ndarray | None:
        """Horizon obstacles of camera ``i`` found in this frame (working size, (H, W) bool), or
        None when the station gives the camera a mask (or ``masks.auto_obstacles`` is off).

        Each frame's dark horizon objects (:func:`~.obstacles.obstacles_in_frame`), together with
        what the run has learned: a pixel found in at least ``_OBSTACLE_LEARN_SHARE`` of the
        camera's frames, after ``_OBSTACLE_LEARN_FRAMES`` of them, stays masked (a building
        under a dark cloud, or at dusk, is still a building)."""
        cam = (self.cam1, self.cam2)[i]
        if not self.config.masks.auto_obstacles or (cam.mask is not None and self.config.masks.static_mask):
            return None
        H, W = image.shape[:2]
        half = ((W + 1) // 2, (H + 1) // 2)  # found at half size (4x cheaper), brought back with its margin
        if i not in self._circles:
            z = cv2.resize(self.zenith(i), half, interpolation=cv2.INTER_NEAREST)
            circle = cv2.resize(cam.model.image_circle_mask().view(np.uint8), half, interpolation=cv2.INTER_NEAREST) > 0
            self._circles[i] = (*obstacle_rings(z, circle), horizon_grid(cam, half, _HALF_SIZE_OBSTACLES))
        ring, band, grid = self._circles[i]
        small = obstacles_in_frame(cv2.resize(image, half, interpolation=cv2.INTER_AREA), ring, band,
                                   _HALF_SIZE_OBSTACLES, grid, darkest_of_four(image))
        found = cv2.resize(small.view(np.uint8), (W, H), interpolation=cv2.INTER_NEAREST) > 0
        with self._obstacle_lock:  # process_batch runs pairs side by side on one Pipeline
            votes, n = self._obstacle_votes.get(i, (np.zeros(found.shape, np.uint16), 0))
            if n < np.iinfo(np.uint16).max:
                np.add(votes, found, out=votes)
                n += 1
                self._obstacle_votes[i] = (votes, n)
            if n >= _OBSTACLE_LEARN_FRAMES:
                found = found | (votes >= _OBSTACLE_LEARN_SHARE * n)
        return found

    def forget_learned(self) -> None:
        """Forget what earlier frames taught (the horizon obstacles of :meth:`auto_obstacles`), so
        that the next frames' results depend on them alone: ``cbh reprocess`` calls it at each
        chunk, whichever actor takes it."""
        with self._obstacle_lock:
            self._obstacle_votes = {}

    def rays_cam_device(self, i: int):
        """:meth:`rays_cam` as a tensor on the pipeline's device (uploaded once)."""
        key = ("dev", i)
        if key not in self._rays:
            from cbh.pipeline.torch_ops import upload

            self._rays[key] = upload(self.rays_cam(i), self.device)
        return self._rays[key]

    def rays_cam(self, i: int) -> np.ndarray:
        """Ray map of camera ``i`` at working size in its own frame, (H, W, 3) float32 (cached)."""
        if i not in self._rays:
            self._rays[i] = (self.cam1, self.cam2)[i].model.ray_map().astype(np.float32)
        return self._rays[i]

    def zenith_device(self, i: int):
        """:meth:`zenith` as a tensor on the pipeline's device (uploaded once)."""
        key = ("dev", i)
        if key not in self._zenith:
            from cbh.pipeline.torch_ops import upload

            self._zenith[key] = upload(self.zenith(i), self.device)
        return self._zenith[key]

    def zenith(self, i: int) -> np.ndarray:
        """Zenith angle of camera ``i``'s pixels at working size, (H, W) float32 [deg] (cached)."""
        if i not in self._zenith:
            self._zenith[i] = np.asarray((self.cam1, self.cam2)[i].zenith_map(), np.float32)
        return self._zenith[i]

    def to_working(self, i: int, image: np.ndarray) -> np.ndarray:
        """Resize a full-size image of camera ``i`` to working size."""
        cam = (self.cam1, self.cam2)[i]
        if self.factors[i] == 1.0:
            return image
        return cv2.resize(image, (cam.model.width, cam.model.height), interpolation=cv2.INTER_AREA)

    def to_full_px(self, i: int, px: np.ndarray) -> np.ndarray:
        """Working-size pixel coordinates of camera ``i`` → full-size coordinates."""
        f = self.factors[i]
        return px if f == 1.0 else (px + 0.5) / f - 0.5

    def _camera1_once(self, i: int, stage: str, fn):
        """``fn()``; for camera 1 under a network's :class:`FrameMemo`, computed once per frame
        set by whichever of its pairs gets there first."""
        if i != 0 or self.frame_memo is None:
            return fn()
        return self.frame_memo.get((self.cameras[0], stage), fn)

    # --- the pair -------------------------------------------------------------------------
    def process(self, image1, image2, time_utc: datetime | str | None = None, *,
                channels: str | None = None, previous: PairState | None = None) -> PairResult:
        """Run every stage on one synchronized pair.

        Parameters
        ----------
        image1, image2 : str, Path or ndarray, shape (H, W, 3), uint8
            Camera 1's and camera 2's images at their calibration sizes: file paths, or arrays
            whose channel order ``channels`` declares.
        time_utc : datetime, str or None
            Capture time (timezone-aware, or ISO 8601 text with a zone; used for the sun
            position). None: unknown; the sun is then masked only where it saturates and the
            result is flagged ``time_unknown`` (its ``time_utc`` stays None: cbh never invents
            a capture time).
        channels : {"rgb", "bgr"}, optional
            Channel order of array inputs: ``"rgb"`` for PIL/imageio/matplotlib arrays,
            ``"bgr"`` for OpenCV's. Required for arrays (a bare array is refused, never guessed).
        previous : PairState or None
            ``state`` of the previous pair's result (:mod:`.motion`): with it, each layer gets
            its motion and camera 2's clock offset is estimated and compensated. None (the
            first pair of a run): no motion (NaN).

        Returns
        -------
        PairResult
            Heights above the ENU origin; ``height_map`` on camera 1's full pixel grid;
            ``diagnostics``: ``clock_offset_s`` (running estimate of camera 2's clock minus
            camera 1's, NaN = unknown), ``clock_offset_pair_s`` (this pair's own estimate),
            ``motion_dt_s`` (time to the previous pair used for motion, NaN = none);
            ``state`` for the next pair.

        Raises
        ------
        ImageError
            An array without ``channels``, a greyscale image, wrong shape/dtype, or an image
            that does not match its calibration size.
        InputError
            ``time_utc`` without a zone.
        """
        return self.finish(self.prepare(image1, image2, time_utc, channels=channels), previous=previous)

    def prepare(self, image1, image2, time_utc: datetime | str | None = None, *,
                channels: str | None = None) -> "Prepared":
        """The first half of :meth:`process`: everything that does not depend on the pair before
        (reading, masks, sun check, photometric correction, segmentation). ``finish(prepare(…),
        previous)`` is ``process(…, previous=previous)``; the service prepares the next pair
        while this one finishes. Parameters and errors as :meth:`process`."""
        image1 = as_bgr(image1, channels, self.cam1_full.name, self.cam1_full.model)
        image2 = as_bgr(image2, channels, self.cam2_full.name, self.cam2_full.model)
        if time_utc is not None:
            time_utc = parse_utc(time_utc, "time_utc")
        ctx = PairContext(time_utc=time_utc)
        if time_utc is None:
            ctx.flags.append("time_unknown")
        t_all = time.perf_counter()
        first = self._tables_key is None
        if first:
            self._load_tables()
        with _timed(ctx, "resize"):
            work = (self.to_working(0, image1), self.to_working(1, image2))
        with _timed(ctx, "masks"):
            masks = self.stage_masks(work, ctx)  # (and each camera's sky brightness: the exposure check)
        with _timed(ctx, "sun_check"):
            self.stage_sun_check(work, masks, ctx)
        received = (image1, image2)  # as the cameras delivered them, full size (the identical-image check)
        with _timed(ctx, "photometric"):
            taken = work
            work, coloured = self.stage_photometric(work, masks, ctx)
            masks = self._clip_contours(taken, masks, ctx)
        with _timed(ctx, "segmentation"):
            seg = self.stage_segment(coloured, masks, as_received1=coloured[0] is taken[0], taken=taken)
            gray = (cv2.cvtColor(work[0], cv2.COLOR_BGR2GRAY), cv2.cvtColor(work[1], cv2.COLOR_BGR2GRAY))
        return Prepared(ctx=ctx, t_all=t_all, first=first, work=work, masks=masks, seg=seg, gray=gray, received=received,
                        prepare_ms=_ms(t_all))

    def finish(self, prep: "Prepared", previous: PairState | None = None) -> PairResult:
        """The second half of :meth:`process` (matching, heights, layers, motion) on a
        prepared pair (:meth:`prepare`), with the previous pair's state."""
        ctx, first, work, masks, seg, gray, received = (prep.ctx, prep.first, prep.work, prep.masks, prep.seg, prep.gray,
                                                         prep.received)
        t_all = time.perf_counter() - prep.prepare_ms / 1000.0  # total: both halves' own time, not a wait between
        mmasks, mseg = masks.for_matching(seg)  # what the matchers see: no saturated contours
        time_utc = ctx.time_utc
        mot = self._motion_input(previous, time_utc, gray)
        mcfg = self.config.motion
        if not mot.offsets_s and math.isfinite(self._stated_offset()) and mcfg.clock_offset:
            mot = replace(mot, offsets_s=(self._stated_offset(),))  # the station states the clocks
        sky = self._sky_clock(gray, mmasks, mot, ctx)  # this pair's offset from the sky maps (no stereo needed)
        history = update_offsets(mot.offsets_s, sky.offset_s, mcfg.offset_history, self._jump_s(mot))
        used = running_offset(history) if (mot.prev_gray is not None and mcfg.clock_offset) else math.nan
        profile = mot.profile  # (the tracks' of the pair before; the sky maps' where there is none yet)
        sky_seeded = False
        if not len(profile) and len(sky.heights_m) and math.isfinite(used):
            profile = track_profile(sky.heights_m, sky.rates2, mcfg.min_tracks, mcfg.layer_tolerance_log)
            sky_seeded = bool(len(profile))
        pair_s = sky.offset_s  # (this pair's latest own offset estimate; the LK tracks' where the sky has none)
        n_flags = len(ctx.flags)
        for attempt in range(_MAX_PASSES):  # more passes only when this pair moved the offset estimate (.motion)
            del ctx.flags[n_flags:]
            sky_mode = self._sky_mode(sky, used, profile)
            if sky_mode:  # camera 2 carried to camera 1's time pixel by pixel (.skyclock)
                corr, comp = self._sky_correspondences(sky, used, mseg, ctx), None
            else:
                corr, comp = self._match_compensated(work, mmasks, mseg, ctx, gray, mot, used, profile)

            def height_map():
                with _timed(ctx, "height_map"):
                    return self.stage_height_map(seg, corr)

            def points():
                with _timed(ctx, "points"):
                    return self.stage_points(corr)

            def geometry():
                with _timed(ctx, "geometry_check"):
                    return self.geometry_findings(received, corr, mseg, sky.carry_noise_rad if sky_mode else 0.0,
                                                  masks.near_clip, self._near_obstacles(masks))

            hmap, pts, geo = pmap(lambda f: f(), (height_map, points, geometry), pool="stages")  # side by side
            with _timed(ctx, "layers"):
                lay = self.stage_layers(pts, seg, masks, hmap, ctx, gray=gray, comp=comp, judge_unseen=not sky_mode)
            est = MotionEstimate()
            if mot.prev_gray is not None:
                with _timed(ctx, "motion"):
                    est = (self._sky_tracks(corr, sky, mot) if sky_mode else
                           self._stereo_tracks(corr, gray, mmasks, mseg, mot, comp))
                    lay = self.stage_motion(lay, hmap, est, mseg.clouds[0])
            if not sky_mode:  # a short carry: the compensated stereo tracks refine the sky maps' start
                pair_s = est.pair_offset_s if math.isfinite(est.pair_offset_s) else pair_s
            new = running_offset(update_offsets(mot.offsets_s, pair_s, mcfg.offset_history, self._jump_s(mot)))
            moved = math.isfinite(new) and abs(new - (used if comp is not None else 0.0)) > mcfg.rematch_s
            if attempt and comp is not None:  # start-up passes: also until the motion profile settles
                moved = moved or profile.moved_px(est.profile, new, self._px_per_rad2()) > _RATES_SETTLED_PX
            # a pass started from the sky maps' estimate and profile is matched again with the
            # compensated tracks' (the maps' flow smooths across layer edges: 2.84 s for 3.0)
            moved = moved or (attempt == 0 and sky_seeded and comp is not None and math.isfinite(new))
            if (attempt == _MAX_PASSES - 1 or not mcfg.clock_offset or not moved or not len(est.profile) or sky_mode
                    or not math.isfinite(new)):
                break
            used, profile = new, est.profile
        seg, geo = self._nothing_to_judge(seg, masks, lay, hmap, geo)
        self._apply_geometry(geo, ctx)  # (found beside the height map, on the last pass's correspondences)
        if (self._uncarried(used, profile, comp) if not sky_mode else
                self._carry_swamps(lay, sky.carry_noise_rad, ctx)):
            ctx.flags.append("clock_too_far")
        self._quality_flags(pts, seg, ctx, hmap, lay)
        if "geometry_mismatch" in ctx.flags and not math.isfinite(sky.offset_s):  # not checked this pair: now
            sky = self._sky_clock(gray, mmasks, replace(mot, sky_check_in=0), ctx)
            pair_s = sky.offset_s if math.isfinite(sky.offset_s) else pair_s
        before = running_offset(mot.offsets_s)
        offsets = update_offsets(mot.offsets_s, pair_s, mcfg.offset_history, self._jump_s(mot))
        running = running_offset(offsets)
        self._clock_flags(previous, mot, sky, before, running, used, ctx, lay)
        ctx.diagnostics.update(clock_offset_s=running, clock_offset_pair_s=pair_s, motion_dt_s=mot.dt_s,
                               clock_offset_error_s=sky.error_s, clock_interval_ratio=sky.interval_ratio)
        if math.isfinite(running) and abs(running) > mcfg.offset_tolerance_s:
            ctx.flags.append("clock_offset")
        if first and not self._tables_loaded:
            self._save_tables()
        ctx.timing["total"] = _ms(t_all)
        result = self._assemble(ctx, seg, hmap, pts, lay)
        result.state = PairState(time_utc=ctx.time_utc, cameras=self.cameras, gray=gray, offsets_s=offsets,
                                 layer_rates=tuple(est.profile.rates), rate_heights_m=tuple(est.profile.heights_m),
                                 sky_check_in=self._next_sky_check(mot, sky, sky_mode, running, ctx.flags))
        return result

    # --- motion and clock offset (see cbh.pipeline.motion) ---------------------------------
    def _motion_input(self, previous: PairState | None, time_utc: datetime | None, gray) -> "MotionInput":
        """What the previous pair offers this one: frames (when usable) and the offset history."""
        if previous is None or not isinstance(previous, PairState) or previous.cameras != self.cameras:
            return MotionInput()
        cfg = self.config.motion
        offsets = previous.offsets_s if cfg.clock_offset else ()
        if (not cfg.enabled or previous.gray is None or time_utc is None or previous.time_utc is None
                or previous.gray[0].shape != gray[0].shape or previous.gray[1].shape != gray[1].shape):
            return MotionInput(offsets_s=offsets)
        dt = (time_utc - previous.time_utc).total_seconds()
        if not 0.0 < dt <= cfg.max_gap_s:
            return MotionInput(offsets_s=offsets)
        return MotionInput(prev_gray=previous.gray, dt_s=dt, offsets_s=offsets, profile=previous.profile,
                           sky_check_in=previous.sky_check_in)

    def _stated_offset(self) -> float:
        """Camera 2's offset against camera 1 as the station states it (``clock_offset_s`` of
        both cameras, a missing one read as 0 when the other is stated) [s]; NaN: not stated."""
        a, b = self.cam1.clock_offset_s, self.cam2.clock_offset_s
        if a is None and b is None:
            return math.nan
        return float(b or 0.0) - float(a or 0.0)

    def _sky_clock(self, gray, masks: "Masks", mot: "MotionInput", ctx: "PairContext") -> SkyClock:
        """Camera 2's clock offset from this pair and the previous one on sky maps
        (:mod:`.skyclock`); unknown without a previous pair, with the estimate switched off, or
        when it is not due (:meth:`_next_sky_check`: the offset is known and the compensated
        stereo tracks follow it)."""
        mcfg = self.config.motion
        if mot.prev_gray is None or not mcfg.clock_offset:
            return SkyClock.unknown()
        if mot.sky_check_in > 0 and math.isfinite(running_offset(mot.offsets_s)):
            return SkyClock.unknown()
        with _timed(ctx, "clock"):
            return self.sky_offset(gray, masks.usable, mot.prev_gray, mot.dt_s, running_offset(mot.offsets_s))

    def sky_offset(self, gray, usable, prev_gray, dt_s: float, known_offset_s: float = math.nan) -> SkyClock:
        """Camera 2's clock offset on the sky maps (:func:`~.skyclock.sky_clock`) from this pair's
        working-size grey frames ``gray`` and usable masks and the pair ``dt_s`` [s] before
        (``prev_gray``); unknown beyond ``max_offset_s``; with ``known_offset_s`` (the running
        offset), the maps' matches carried by it when this pair's own estimate fails. (Also what
        `cbh calibrate` reports.)"""
        if self._sky_grid is None:
            self._sky_grid = sky_grid((self.cam1, self.cam2))
        c1, c2 = self.cam1.position_m, self.cam2.position_m
        filt = self.config.filtering
        sc = sky_clock(self._sky_grid, gray, prev_gray, usable, np.asarray(c2 - c1, np.float64)[:2],
                       float(c2[2] - c1[2]), dt_s, height_range_m=(filt.min_height_m, filt.max_height_m),
                       known_offset_s=known_offset_s, max_offset_s=self.config.motion.max_offset_s)
        return sc

    def _clock_explains(self, previous, mot: "MotionInput", sky: SkyClock, running_before: float) -> bool:
        """Whether a geometry mismatch may be the clock's, not yet measured: in a run (``previous``
        given) before any motion (a run's first pair: no offset can be measured, and one would look
        the same; or one resumed from a recording, which cannot be taken out without motion), or
        when this pair's own offset from the sky maps is further from the running one than a jump
        (:func:`~.motion.jump_threshold`) that compensated it (a clock that jumped; the next pair
        confirms it), or, with motion, while no offset was ever measured and this pair's maps did
        not measure one either, unless they saw a calm sky or a wind along the baseline (then no
        offset moves a match off its curve). The price: a camera knocked at the start of a run is
        reported ``clock_unknown``, not ``geometry_mismatch``, until the offset is measured (from the
        first pair whose maps match; `cbh calibrate` or a stated offset settles it at once)."""
        mcfg = self.config.motion
        if previous is None or not mcfg.clock_offset:
            return False
        if mot.prev_gray is None:  # (an offset known from a recording is not taken out without motion)
            return not math.isfinite(running_before) or abs(running_before) > mcfg.offset_tolerance_s
        if not math.isfinite(running_before) and not math.isfinite(sky.offset_s):
            # never measured yet, and this pair's maps did not measure it either: the clock may still explain
            # it, unless the maps saw a calm sky or a wind along the baseline (then an offset moves no match off
            # its curve). The real Fehmarn hour at a 2-minute cadence: the first pairs' maps, 120 s apart,
            # did not match, and their mismatches were flagged as the geometry's.
            return not (sky.still or sky.along)
        return (math.isfinite(sky.offset_s) and math.isfinite(running_before)
                and abs(sky.offset_s - running_before) > jump_threshold(mot.offsets_s, self._jump_s(mot)))

    def _clock_flags(self, previous, mot: "MotionInput", sky: SkyClock, before: float, running: float, used: float,
                     ctx: "PairContext", lay) -> None:
        """Whose a pair's disagreement with the geometry is, and whether its clock can be vouched for:
        a mismatch of matches not carried over the known offset (``clock_too_far``: already
        invalidating) is the clock's and is dropped (the real hour at a 2-minute cadence had both
        flags on its last pairs); one the clock may explain (:meth:`_clock_explains`,
        :meth:`_carry_explains`) is ``clock_unknown``; so is a pair that nothing could judge while
        the clock is unknown (:meth:`_clock_unverified`)."""
        if "geometry_mismatch" in ctx.flags and "clock_too_far" in ctx.flags:
            ctx.flags.remove("geometry_mismatch")
        elif "geometry_mismatch" in ctx.flags and (self._clock_explains(previous, mot, sky, before)
                                                   or self._carry_explains(sky, used, ctx)):
            ctx.flags[ctx.flags.index("geometry_mismatch")] = "clock_unknown"
        elif self._clock_unverified(previous, mot, sky, running, ctx, lay):
            ctx.flags.append("clock_unknown")

    def _clock_unverified(self, previous, mot: "MotionInput", sky: SkyClock, running: float, ctx: "PairContext",
                          lay) -> bool:
        """Whether a pair's layers rest on a clock nothing has checked: in a run, the geometry check
        had too few 2-D matches for a verdict (or, under a wind along the baseline, could not have
        seen an offset: below), and camera 2's clock offset is unknown, either before
        any motion (a run's first pair, or the first after a gap; also an offset known from a
        recording, which is not taken out without motion) or because the moving sky did not give
        it. An offset moves every cloud by wind × offset between the two frames; across the
        baseline that takes the matches off their epipolar curves, which is what the check would
        have seen, and LK, started at the point at infinity or at the sweep's match, loses them
        beyond a few window widths. Seen on the real Fehmarn hour re-paired two and three frames
        apart (offsets of ±150 and −211 s): the first pair's LK kept 0–2 of 300 features, the
        seeded LK 1–4 of several hundred, no verdict, and the sweep's best planes along the
        curves gave a 1.6–1.9 km deck for the real 8–9 km one, with no flag; at −211 s the second
        pair's sky maps matched too (7 of 82 000 lattice points), so the offset stayed unknown and
        its layers were as wrong. A calm sky (the maps matched, little of it moved:
        ``SkyClock.still``) carries little whatever the offset: it is flagged only when what an
        offset could hide moves a layer (below); no pair of a station whose motion is off
        (``motion.enabled``: nothing could ever measure it) is flagged. Maps that did not match at
        all (the −211 s pair above, 7 of 82 000 lattice points) are: a clock minutes off is what
        makes them fail.

        While the offset was never measured, a passed check does not vouch for the clock either:
        a pair is flagged when its maps saw a wind along the baseline (``SkyClock.along``: the
        offset unobservable, but not harmless), or when an offset the check could not see would
        move a layer by more than :data:`HIDDEN_OFFSET_SHARE` (:meth:`_hidden_offset_share`). An
        offset δ carries every cloud by wind × δ; along the baseline that moves no match off its
        epipolar curve and adds wholly to the parallax (randomized clock sky 16805: decks at 2142,
        3756 and 8268 m drifting 10–13 m/s within 20° of a 106 m baseline, camera 2 119 s late,
        read 593, 2308 and 7421 m, valid). A station whose clocks are right says so
        (``clock_offset_s``) and is never flagged for it; a pair that disagrees with the geometry
        keeps ``geometry_mismatch`` alone here (under such a wind no offset explains it)."""
        mcfg = self.config.motion
        if (previous is None or not mcfg.clock_offset or not mcfg.enabled or not lay.layers
                or not self.config.geometry_check.enabled or "night" in ctx.flags):
            return False
        verdict = math.isfinite(ctx.diagnostics.get("geometry_residual_px", math.nan))
        if mot.prev_gray is None:
            return not verdict and (not math.isfinite(running) or abs(running) > mcfg.offset_tolerance_s)
        if math.isfinite(running) or "geometry_mismatch" in ctx.flags:  # (a mismatch: the geometry's)
            return False
        share = self._hidden_offset_share(lay, ctx, verdict)
        if math.isfinite(share):
            ctx.diagnostics["clock_hidden_share"] = share
        hides = share > HIDDEN_OFFSET_SHARE
        return hides if sky.still else (sky.along or not verdict or hides)

    def _hidden_offset_share(self, lay, ctx: "PairContext", seen: bool) -> float:
        """The largest share of a layer's parallax that an offset the geometry check could not see
        would move (NaN: no layer's wind known; ``clock_hidden_share`` in the diagnostics). With the
        layer's wind v (its tracks') split along and across the baseline B, an offset δ carries its
        matches v_across·δ / h across their curves, unseen while under the check's tolerance (up to
        ``motion.max_offset_s`` where nothing saw them: ``seen`` False, no verdict), and v_along·δ
        along them, a share v_along·δ / B of the parallax. Randomized clock sky 16844 over the real
        Fehmarn lenses: a 9987 m overcast at 0.6 m/s, B 46 m, camera 2 76 s late, no offset believed:
        0.17° across (under 1 px), 6846 m reported valid."""
        b = np.asarray(self.cam2.position_m - self.cam1.position_m, np.float64)[:2]
        base = float(np.linalg.norm(b))
        tol_rad = ctx.geometry_tolerance_px / self._px_per_rad2() if seen else math.inf
        shares = []
        for L in lay.layers if base > 0 and tol_rad > 0 else ():
            v = np.array([L.motion_east_ms, L.motion_north_ms], np.float64)
            if not np.isfinite(v).all():
                continue
            along = abs(float(v @ b)) / base
            across = math.sqrt(max(float(v @ v) - along * along, 0.0))
            hidden_s = self.config.motion.max_offset_s
            if across > 0 and math.isfinite(tol_rad):
                hidden_s = min(hidden_s, tol_rad * max(L.height_m, 1.0) / across)
            shares.append(along * hidden_s / base)
        return max(shares) if shares else math.nan

    def _carry_explains(self, sky: SkyClock, used_s: float, ctx: "PairContext") -> bool:
        """Whether a geometry mismatch of a pair matched on the sky maps (camera 2 carried to camera
        1's time by each pixel's motion, :mod:`.skyclock`, or compensated by it) is the clock's:
        this pair's own offset disagrees with the one ``used_s`` that carried camera 2 (NaN: none
        was) by Δ, so the matches sit |rate| · Δ off (a deck at 8 km moving 15 m/s: 0.35° for
        Δ = 3.3 s), and that is at least the median distance's excess over its tolerance. Only a
        median over its tolerance is explained so: a fitted turn or too few inliers with the median
        within it stay the geometry's. Seen on the real Fehmarn hour re-paired one frame later
        (pair 22: its own offset 32.3 s against the running 29.0 s, the carried matches 2.18 px off
        their curves against 1.60 px allowed): a clock that wavered, not a geometry."""
        if not (len(sky.rate) and math.isfinite(sky.offset_s) and math.isfinite(used_s)):
            return False
        res, tol = ctx.diagnostics.get("geometry_residual_px", math.nan), ctx.geometry_tolerance_px
        if not (math.isfinite(res) and math.isfinite(tol) and res > tol):
            return False
        rate = float(np.median(np.linalg.norm(np.asarray(sky.rate, np.float64), axis=1)))  # [rad/s]
        carry_px = abs(sky.offset_s - used_s) * rate * self._px_per_rad2()
        return carry_px >= res - tol

    def _next_sky_check(self, mot: "MotionInput", sky: SkyClock, sky_mode: bool, running: float, flags) -> int:
        """Pairs until the sky maps estimate the offset again. Every pair while the offset is
        unknown, the pair is matched on the maps (a long carry), it disagreed with the geometry
        (the tracks may have lost the offset), or the maps just disagreed with the running offset
        as a jump would (:func:`~.motion.jump_threshold`; two pairs confirm a jump); otherwise every
        ``sky_check_pairs``: the compensated stereo tracks follow a known offset at no cost, and
        the maps' check catches a clock that jumped beyond their reach. (The maps cost ≈ 200–300 ms
        at 1920 px, about as much as the rest of the pair.)"""
        mcfg = self.config.motion
        if sky_mode or not math.isfinite(running) or "geometry_mismatch" in flags:
            return 0
        if (math.isfinite(sky.offset_s)
                and abs(sky.offset_s - running) > jump_threshold(mot.offsets_s, self._jump_s(mot))):
            return 0  # perhaps a jump: the next pair confirms it (update_offsets) or not
        if math.isfinite(sky.offset_s):
            return mcfg.sky_check_pairs - 1
        return max(mot.sky_check_in - 1, 0)

    def _sky_mode(self, sky: SkyClock, used_s: float, profile: MotionProfile) -> bool:
        """Whether the pair is matched on the sky maps: its offset is known, the maps gave matches,
        and the carry is long: the fastest layer moves more than ``sky_matching_min_px`` (working
        size, near the zenith) in ``used_s``. The raw-image compensation moves each pixel with one
        motion per height node; the motion within a layer varies by 10–20 %, so its error is that
        share of the carry, and past ≈ 8 px it is more than a pixel. Below, it is the better
        matcher (every method, the whole sky, layers seen through gaps)."""
        return bool(self.config.motion.sky_matching and len(sky.a1) and self._long_carry(used_s, profile))

    def _uncarried(self, used_s: float, profile: MotionProfile, comp) -> bool:
        """Whether a pair matched on the raw images (not on the sky maps) could not be carried to
        camera 1's time: a long carry (:meth:`_long_carry`) that the sky maps could not match, or a
        known offset of at least ``compensate_min_s`` left in (``comp`` None) because no motion was
        known to carry camera 2 with. Such a pair's matches mix the clock into the parallax: on the
        real Fehmarn hour re-paired to 150–210 s, one pair in three gave layers at 1.5–2.3 km under
        an 8 km deck, with no flag (flag ``clock_too_far``)."""
        mcfg = self.config.motion
        if mcfg.sky_matching and self._long_carry(used_s, profile):
            return True
        return comp is None and math.isfinite(used_s) and abs(used_s) >= mcfg.compensate_min_s and not len(profile)

    def _carry_swamps(self, lay: LayerSet, carry_noise_rad: float, ctx: "PairContext") -> bool:
        """Whether a pair matched on the sky maps reports a layer whose parallax near the zenith,
        |B| / (h − z1), is less than ``MIN_PARALLAX_OVER_CARRY`` × the carry's own noise (the rate's
        noise × the offset, :class:`~.skyclock.SkyClock`): each of its points' parallax is then
        mostly that noise, and its height is not measured (diagnostic ``carry_parallax_ratio``,
        the least layer's). A randomized 9979 m deck seen 22 m apart, carried 79 s at 19 m/s with
        frames 10 s apart: parallax 0.0022 rad under 0.014 rad of carry noise, read 3164–3239 m with
        no flag (with frames 60–180 s apart the rates are measured better, the ratio is 1.3–3.7, and
        it reads 6300–7200 m: a limit, docs/accuracy.md). On the real Fehmarn hour re-paired 211 s
        apart it flags three of the seven pairs led by a 10–14 km phantom over the 8–9 km deck, and
        one valid pair; the pairings within ±151 s keep every layer they had."""
        if not (lay.layers and carry_noise_rad > 0):
            return False
        o1 = np.asarray(self.cam1.position_m, np.float64)
        b = float(np.linalg.norm((np.asarray(self.cam2.position_m, np.float64) - o1)[:2]))
        ratio = min(b / max(L.height_m - o1[2], 1.0) for L in lay.layers) / carry_noise_rad
        ctx.diagnostics["carry_parallax_ratio"] = float(ratio)
        return bool(ratio < MIN_PARALLAX_OVER_CARRY)

    def _long_carry(self, used_s: float, profile: MotionProfile) -> bool:
        """Whether carrying camera 2 by ``used_s`` moves the fastest layer of ``profile`` by at least
        ``sky_matching_min_px`` (working size, near the zenith): past it the raw-image compensation's
        error is more than a pixel, and the pair is matched on the sky maps or not at all."""
        if not (math.isfinite(used_s) and len(profile)):
            return False
        carry_px = abs(used_s) * float(np.linalg.norm(profile.rates, axis=1).max()) * self._px_per_rad2()
        return carry_px >= self.config.motion.sky_matching_min_px

    def _sky_correspondences(self, sky: SkyClock, used_s: float, seg: "Segmentation",
                             ctx: "PairContext") -> "Correspondences":
        """The sky maps' matches (:mod:`.skyclock`) as the pair's correspondences, method
        ``skyflow``: each carries camera 2 to camera 1's time by its own pixel's motion (the
        raw-image matchers would see camera 2 resampled with one motion per height node, whose error
        grows with the offset), on camera 1's cloud, carried by the running offset ``used_s`` (this
        pair's own estimate scatters by 1–4 s, and a second moves an 8 km deck over 241 m by 8 %;
        carried by its own, the geometry check flagged 3 of 29 real pairs, by the running one none)."""
        with _timed(ctx, "match_skyflow"):
            m = self._carried_matches(sky, used_s, seg.clouds[0])
        with _timed(ctx, "triangulation"):
            tri = triangulate_matches(self.geometry, m, self.config.filtering)
            tri = self._on_epipolar(tri)
        return Correspondences(triangulated=[tri], raw=[m])

    def _carried_matches(self, sky: SkyClock, offset_s: float, cloud1: np.ndarray) -> Matches:
        """The sky maps' matches with camera 2 carried by ``offset_s`` [s], on camera 1's cloud."""
        r1 = np.concatenate([sky.a1, np.ones((len(sky.a1), 1))], axis=1)
        r2 = np.concatenate([sky.matched(offset_s), np.ones((len(sky.a1), 1))], axis=1)
        r1 /= np.linalg.norm(r1, axis=1, keepdims=True)
        r2 /= np.linalg.norm(r2, axis=1, keepdims=True)
        px1 = self.cam1.model.ray_to_pixel(r1 @ np.asarray(self.cam1.R_world_from_cam, np.float64))
        px2 = self.cam2.model.ray_to_pixel(r2 @ np.asarray(self.cam2.R_world_from_cam, np.float64))
        m = Matches("skyflow", px1.astype(np.float64), px2.astype(np.float64),
                    ray2_world=r2.astype(np.float32), ray1_world=r1.astype(np.float32))
        return m.take(_on_mask(cloud1, m.px1))

    def _on_epipolar(self, tri: TriangulatedMatches) -> TriangulatedMatches:
        """Sky-map matches' points moved onto their epipolar lines (:func:`points_on_epipolar`:
        the closest approach of skew rays is biased short by the carry's noise across the
        baseline); each keeps its miss as measured (the geometry check, the noise)."""
        m = tri.matches
        if not len(m):
            return tri
        point = points_on_epipolar(self.cam1.position_m, m.ray1_world, self.cam2.position_m, m.ray2_world)
        filt = self.config.filtering
        with np.errstate(invalid="ignore"):
            keep = np.isfinite(point).all(1) & (point[:, 2] >= filt.min_height_m) & (point[:, 2] <= filt.max_height_m)
        return replace(tri, matches=m.take(keep), point_m=point[keep], miss_m=tri.miss_m[keep])

    def _sky_tracks(self, corr: "Correspondences", sky: SkyClock, mot: "MotionInput") -> "MotionEstimate":
        """The motion estimate of a pair matched on the sky maps: every kept match is a track, with
        its own pixel's motion (camera 1's rate, and camera 2's at the match's height)."""
        tr = corr.triangulated[0]
        m = tr.matches
        if not len(m):
            return MotionEstimate(dt_s=mot.dt_s, pair_offset_s=sky.offset_s)
        r1 = np.asarray(m.ray1_world, np.float64)
        w1 = sky.rate_at(r1[:, :2] / r1[:, 2:3])  # camera 1's own rate at each kept match
        h = tr.height_m
        z1, z2 = float(self.cam1.position_m[2]), float(self.cam2.position_m[2])
        with np.errstate(invalid="ignore", divide="ignore"):
            w2 = w1 * ((h - z1) / (h - z2))[:, None]
        cfg = self.config.motion
        profile = track_profile(h, w2, cfg.min_tracks, cfg.layer_tolerance_log)
        return MotionEstimate(dt_s=mot.dt_s, px1=m.px1, w1=w1, w2=w2, pair_offset_s=sky.offset_s, height_m=h,
                              profile=profile)

    def _jump_s(self, mot: "MotionInput") -> float:
        """The least clock jump that this pair's interval and the running offset can tell from its
        estimate's scatter (:func:`~.motion.jump_floor_s`)."""
        return jump_floor_s(self.config.motion.offset_jump_s, mot.dt_s, running_offset(mot.offsets_s))

    def _px_per_rad2(self) -> float:
        """Camera 2's lens scale near the zenith at working size [px/rad]."""
        return float(np.atleast_1d(self.cam2.model.r_from_theta(np.array([0.05])))[0]) / 0.05

    def _match_compensated(self, work, masks: "Masks", seg: "Segmentation", ctx: "PairContext", gray,
                           mot: "MotionInput", used_s: float, profile: MotionProfile):
        """:meth:`stage_match` with camera 2 moved back to camera 1's capture time by the offset
        ``used_s`` [s] (when known and at least ``compensate_min_s``, and ``profile`` has nodes):
        the sparse matchers on one image compensated per pixel (:func:`compensate_camera2`), the
        sweep's planes each on the image compensated with its own height's motion
        (:func:`shifted_images`, ``motion.plane_compensation``). Returns (Correspondences,
        the per-pixel remap table or None when uncompensated)."""
        mcfg = self.config.motion
        if not (math.isfinite(used_s) and abs(used_s) >= mcfg.compensate_min_s and len(profile)):
            return self.stage_match(work, masks, seg, ctx, gray=gray), None
        with _timed(ctx, "compensation"):
            rates = list(profile.rates)  # lowest first
            images, maps = shifted_images(gray[1], self.cam2, rates, used_s)
            g2, comp = compensate_camera2(gray[1], mot.prev_gray[1], self.cam2, rates, used_s, mot.dt_s, maps=maps,
                                          images=images)
            c2 = self._cloud2_as_matched(seg, comp)
            views = None
            if mcfg.plane_compensation and len(images) > 1 and self.backend != "torch":  # (the torch sweep: g2)
                from cbh.pipeline.sweep import PlaneViews

                z1, z2 = float(self.cam1.position_m[2]), float(self.cam2.position_m[2])
                rates1 = [r * (h - z2) / (h - z1) for r, h in zip(rates, profile.heights_m)]  # as camera 1 sees them
                sw = self.config.matching.sweep
                weights = motion_weights(gray[0], mot.prev_gray[0], self.cam1, rates1, mot.dt_s, sw.window_px,
                                         sw.min_zncc)
                views = PlaneViews.nearest(images, profile.heights_m, z1, weights)
        return self.stage_match(work, masks, seg, ctx, gray=(gray[0], g2), cloud2=c2, views2=views), comp

    def _jumped(self, a1: np.ndarray, a2: np.ndarray, a1_prev: np.ndarray, a2_prev: np.ndarray) -> np.ndarray:
        """Tracks whose two cameras no longer follow one thing (N,) bool: their stereo parallax
        ``c = a1 − a2`` changed between the frames.

        Layers move horizontally, so a feature keeps its c (``q·B' − δ·w``, :mod:`.motion`)
        whatever its motion and camera 2's clock offset. A track that jumped (its feature hidden by
        a lower cloud that moved in front: at a 60 s cadence, 3500 m features latched onto the
        1200 m layer, which gave the deck the low layer's motion × 2.9) has another c. The test
        is on c itself, not on a triangulation of the raw pair: a layer that moves across the
        baseline during the offset does not triangulate (its rays miss by v·δ), yet it is the
        one that measures the offset. Tolerance: the layer tolerance of |c|, or 3 σ of the
        difference of two parallaxes, each off by σ_θ·(1 + |a|²) (σ_θ: ``_TRACK_NOISE_PX`` of LK
        at the lens's scale; 1 + |a|² = 1/cos²θ: plane offsets stretch away from the zenith): at
        480 px a 3500 m track at B = 50 m has 2 px of parallax, good to ≈ 15 %, not 10 %."""
        m1 = self.cam1.model
        sigma_theta = _TRACK_NOISE_PX * 0.05 / float(np.atleast_1d(m1.r_from_theta(np.array([0.05])))[0])
        c_now, c_prev = a1 - a2, a1_prev - a2_prev
        stretch = 1.0 + (a1 ** 2).sum(axis=1)
        with np.errstate(invalid="ignore"):
            tol = np.maximum(self.config.motion.layer_tolerance_log * np.linalg.norm(c_now, axis=1),
                             3.0 * math.sqrt(2.0) * sigma_theta * stretch)
            return ~(np.linalg.norm(c_now - c_prev, axis=1) <= tol)

    def _track_heights(self, a1: np.ndarray, a2: np.ndarray, w1: np.ndarray, delta_s: float) -> np.ndarray:
        """Each stereo feature's height above the ENU origin (N,) [m] for camera 2's clock offset
        ``delta_s`` [s] (:func:`parallax_heights`); NaN where :func:`triangulate_matches` would
        reject it: outside the height range, or a miss across the baseline above
        ``max_miss_ratio`` (as a ratio of the range: plane offsets × cos θ)."""
        c1, c2 = self.cam1.position_m, self.cam2.position_m
        q, miss = parallax_heights(np.asarray(c2 - c1, np.float64)[:2], float(c2[2] - c1[2]), a1, a2, w1, delta_s)
        filt = self.config.filtering
        with np.errstate(invalid="ignore", divide="ignore"):
            h = float(c1[2]) + 1.0 / q
            ok = ((q > 0) & (h >= filt.min_height_m) & (h <= filt.max_height_m)
                  & (np.abs(miss) <= filt.max_miss_ratio * np.sqrt(1.0 + (a1 ** 2).sum(axis=1))))
        return np.where(ok, h, np.nan)

    def _stereo_tracks(self, corr: "Correspondences", gray, masks: "Masks", seg: "Segmentation", mot: "MotionInput",
                       comp) -> "MotionEstimate":
        """Track the LK stereo features back in both cameras (camera 2's as captured: ``comp`` maps
        the compensated image's pixels back, None = uncompensated); this pair's clock offset, each
        feature's height for it and the motion profile of the tracks."""
        cfg = self.config.motion
        raw = next((m for m in corr.raw if m.method == "lk"), None)
        if raw is None:  # LK is not a configured matcher: its features are still the best to track
            inp = MatchInput(geometry=self.geometry, gray1=gray[0], gray2=gray[1], cloud1=seg.clouds[0],
                             usable1=masks.usable[0], usable2=masks.usable[1], cloud2=seg.clouds[1])
            raw = get_matcher("lk")(inp, self.config.matching) if seg.clouds[0].any() else None
        if raw is None or not len(raw):
            return MotionEstimate(dt_s=mot.dt_s)
        idx = np.unique(np.linspace(0, len(raw) - 1, min(len(raw), cfg.max_points)).round().astype(np.int64))
        px1, dt = raw.px1[idx], mot.dt_s
        px2 = raw.px2[idx] if comp is None else sample_map(comp[..., 0], comp[..., 1], raw.px2[idx])  # as captured
        t1 = track_back(gray[0], mot.prev_gray[0], px1, cfg)
        t2 = track_back(gray[1], mot.prev_gray[1], px2, cfg)
        a1, a2 = plane_offsets(self.cam1, px1), plane_offsets(self.cam2, px2)
        a1_prev, a2_prev = plane_offsets(self.cam1, t1.px_prev), plane_offsets(self.cam2, t2.px_prev)
        w1, w2 = (a1 - a1_prev) / dt, (a2 - a2_prev) / dt
        w1[~t1.ok] = np.nan
        w2[~t2.ok] = np.nan
        jumped = self._jumped(a1, a2, a1_prev, a2_prev)
        w1[jumped] = np.nan
        w2[jumped] = np.nan
        pair = math.nan
        if cfg.clock_offset:  # on the pair as captured: exact whatever the compensation did
            c1, c2 = self.cam1.position_m, self.cam2.position_m
            d, q, wt = offset_per_match(np.asarray(c2 - c1, np.float64)[:2], float(c2[2] - c1[2]), a1, a2, w1)
            pair = offset_estimate(d, q, wt, self.config.filtering.min_height_m, self.config.filtering.max_height_m,
                                   cfg.max_offset_s, dt)
        delta = running_offset((mot.offsets_s + (pair,))[-cfg.offset_history:])
        delta = delta if math.isfinite(delta) and abs(delta) >= cfg.compensate_min_s else 0.0
        h = self._track_heights(a1, a2, w1, delta)
        z1, z2 = float(self.cam1.position_m[2]), float(self.cam2.position_m[2])
        with np.errstate(invalid="ignore", divide="ignore"):
            w1_as2 = w1 * ((h - z1) / (h - z2))[:, None]  # camera 1's rate as camera 2 sees it
        profile = track_profile(np.concatenate([h, h]), np.concatenate([w2, w1_as2]), cfg.min_tracks,
                                cfg.layer_tolerance_log)
        return MotionEstimate(dt_s=dt, px1=px1, w1=w1, w2=w2, pair_offset_s=pair, height_m=h, profile=profile)

    def stage_motion(self, lay: LayerSet, hmap: HeightMap, est: "MotionEstimate", cloud1: np.ndarray) -> LayerSet:
        """Each layer's motion over the ground from the tracks (NaN without a previous pair)."""
        if est.px1 is None or not lay.layers:
            return lay
        if est.height_m is not None:
            # a track belongs to the layer of what it tracks: the feature's own stereo height. The
            # height map at its centre pixel is not that at a layer's edge: a corner on a low
            # cloud's edge over a high deck moves with the low cloud, and read as the deck's it
            # gave the 3500 m layer (6, 2) m/s × 2.9 at a 60 s cadence (two-layers scene)
            h_track = est.height_m
        else:
            h, w = hmap.nearest_m.shape
            xi = np.clip(np.round(est.px1[:, 0]).astype(np.int64), 0, w - 1)
            yi = np.clip(np.round(est.px1[:, 1]).astype(np.int64), 0, h - 1)
            h_track = hmap.nearest_m[yi, xi]
        lab = assign_layers(h_track, lay.layers, self.config.motion.layer_tolerance_log)
        # and only tracks whose LK window sees no lower cloud: a window across a lower layer's edge
        # follows that edge (the lower cloud is in front), in both cameras alike, so even its stereo
        # height stays put (60 s cadence, two-layers: 5 of 5 tracks of the 3500 m deck moved with
        # the 1200 m layer's rate)
        mcfg = self.config.motion
        k = 2 * (mcfg.window_px // 2) + 1
        # min filter of the cloud's heights (each cloud pixel: its own or nearest measured height;
        # clear sky hides nothing), after a 3 × 3 median (a single noisy pixel is no cloud); a track
        # goes only when that lowest height belongs to a lower layer than its own, not when it is
        # its own layer's noise (a 4 %-noisy single layer kept a quarter of its tracks otherwise)
        heights = np.where(cloud1, np.nan_to_num(hmap.nearest_m, nan=np.inf), np.inf).astype(np.float32)
        heights = cv2.medianBlur(np.minimum(heights, np.float32(1e9)), 3)
        lowest = cv2.erode(heights, np.ones((k, k), np.uint8))
        h, w = lowest.shape
        xi = np.clip(np.round(est.px1[:, 0]).astype(np.int64), 0, w - 1)
        yi = np.clip(np.round(est.px1[:, 1]).astype(np.int64), 0, h - 1)
        low = lowest[yi, xi].astype(np.float64)
        low_lab = assign_layers(np.where(low < 1e8, low, np.nan), lay.layers, mcfg.layer_tolerance_log)
        med = np.array([L.median_height_m for L in lay.layers])
        edge = (lab >= 0) & (low_lab >= 0) & (low_lab != lab)
        edge[edge] = med[low_lab[edge]] < med[lab[edge]]
        lab[edge] = -1
        samples = []
        for wv, cam in ((est.w1, self.cam1), (est.w2, self.cam2)):
            ok = np.isfinite(wv).all(axis=1)
            samples.append((wv[ok], lab[ok], float(cam.position_m[2])))
        return replace(lay, layers=layer_motion(lay.layers, samples, self.config.motion.min_tracks))

    def process_batch(self, pairs, *, channels: str | None = None) -> list[PairResult]:
        """:meth:`process` for several independent pairs ``[(image1, image2, time_utc), …]`` (paths or
        arrays of ``channels`` order, as :meth:`process`), results in order.

        The first pair runs alone (it builds or loads the per-camera tables and, on a device,
        uploads them once); the others run side by side on :func:`~cbh.pipeline.threads.workers`
        threads (``cv2.getNumThreads()``, at most 8), sharing the tables: each pair's CPU stages
        (decoding, segmentation, sparse matching, layers) overlap the others' and, on a GPU, its
        plane sweep. Pairs are not stacked into one kernel: each pair's planes and cloud region
        differ. No motion is handed between them (use :meth:`process` with ``previous`` for a
        sequence).
        """
        pairs = list(pairs)
        if not pairs:
            return []
        first = self.process(pairs[0][0], pairs[0][1], pairs[0][2], channels=channels)
        rest = pmap(lambda p: self.process(p[0], p[1], p[2], channels=channels), pairs[1:], pool="pairs")
        return [first, *rest]

    # --- stages ---------------------------------------------------------------------------
    def stage_masks(self, work: tuple[np.ndarray, np.ndarray], ctx: "PairContext") -> "Masks":
        """Usable sky per camera (static mask, sun disk, saturated glare) and the sun angle maps."""
        cfg = self.config
        sun_dir, known = None, None
        if ctx.time_utc is not None and (cfg.masks.sun or cfg.segmentation.method in ("nbr_adaptive", "hybrid")):
            st = self.station
            sun = sun_position(st.latitude_deg, st.longitude_deg, st.altitude_m, ctx.time_utc)
            sun_dir, sun_zen = sun.direction_enu, sun.zenith_deg
            if sun_zen >= 90.0:
                sun_dir = None
            known = sun_dir
        elif ctx.time_utc is None and cfg.masks.sun and cfg.masks.saturation:
            sun_dir = self._sun_from_image(work[0])  # its aureole masked and modelled as with a time
            if sun_dir is not None:
                ctx.diagnostics["sun_from_image"] = 1.0

        def one(i):
            u = self.static_mask(i)
            obst = self.auto_obstacles(i, work[i])
            if obst is not None:
                u = u & ~obst
            text = overlay_text(work[i], self.inside_circle(i)) if cfg.masks.overlay_text else None
            if text is not None:  # the camera's clock stamped on the sky: no cloud, and its white no clip
                u = u & ~text
            ang = self._angle_map(i, sun_dir) if sun_dir is not None else None
            glare, sunlit = False, None
            if cfg.masks.sun and ang is not None:
                u = u & (ang > cfg.masks.sun_radius_deg)
            # (the glare mask's, and the sky's over-exposure): read inside the image circle, less
            # the text (a camera's white stamp in a corner, as at Fehmarn, is no clip)
            inside = self.inside_circle(i) if text is None else self.inside_circle(i) & ~text
            clip = clip_level(work[i], mask=inside)
            if cfg.masks.saturation:  # the sun's glare; other saturation is over-exposed cloud
                seen = work[i] if text is None else np.where(text[..., None], np.uint8(0), work[i])  # (its white is no glare)
                sat, sunlit = glare_and_sunlit(seen, cfg.masks, ang, clip)
                if sat.any():
                    u, glare = u & ~sat, True
            margin = FULL_RANGE_WHITE_DN - int(cfg.masks.saturation_level)
            return u, ang, glare, SkyExposure(*_sky_dn(work[i], u, clip, margin), clip), sunlit, obst

        (u1, a1, glare1, dn1, s1, o1), (u2, a2, _, dn2, s2, o2) = pmap(
            lambda i: self._camera1_once(i, "masks", lambda: one(i)), (0, 1), pool="stages")
        if glare1:
            ctx.flags.append("sun_glare")
        self._exposure_check((dn1, dn2), ctx)
        return Masks(usable=(u1, u2), sun_angle=(a1, a2), sun_dir_enu=known,  # (the sun check: a known time only)
                     sunlit=(s1, s2), obstacles=(o1, o2), clips=(dn1.clip, dn2.clip))

    def _sun_from_image(self, image_bgr: np.ndarray) -> np.ndarray | None:
        """The sun's ENU direction from camera 1's image when the capture time is unknown: the
        centroid of its largest saturated blob, if that blob is compact (a disk and its glare,
        not an over-exposed cloud deck) and above the horizon. Without it the sun was masked only
        where it saturates, and its aureole was called cloud: a clear sky gave a layer at 2 km and
        a geometry_mismatch. None: no such blob (an overcast or night sky: nothing to mask)."""
        sat = saturation_mask(image_bgr, self.config.masks).astype(np.uint8)
        if not sat.any():  # a camera whose white clips low or not at all: the brightest 0.1 % of the sky
            grey = cv2.cvtColor(image_bgr, cv2.COLOR_BGR2GRAY)
            inside = self.static_mask(0)
            if not inside.any():
                return None
            sat = ((grey >= np.percentile(grey[inside], 99.9)) & inside).astype(np.uint8)
        n, lab, stats, cent = components_with_stats(sat)
        if n < 2:
            return None
        k = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
        w, h, area = stats[k, cv2.CC_STAT_WIDTH], stats[k, cv2.CC_STAT_HEIGHT], stats[k, cv2.CC_STAT_AREA]
        # ragged or a sixth of the view: an over-exposed deck, not a sun's glare (a low sun's glare at
        # the image's edge spans 150–230 px of 480 and fills 0.8 of its box)
        if area < 0.4 * w * h or area > 0.12 * image_bgr.shape[0] * image_bgr.shape[1]:
            return None
        ray = self.cam1.model.pixel_to_ray(np.asarray(cent[k:k + 1], np.float64))[0]
        d = np.asarray(self.cam1.R_world_from_cam, np.float64) @ ray
        d /= np.linalg.norm(d)
        return d if d[2] > 0.05 else None

    def _exposure_check(self, sky: tuple["SkyExposure", "SkyExposure"], ctx: "PairContext") -> None:
        """``sky_cam1_dn``, ``sky_cam2_dn``: median brightest channel of each camera's usable sky (as
        received, before the photometric correction: :func:`_sky_dn`); flag ``underexposed`` below
        ``segmentation.min_sky_dn``. Clear sky is told from cloud by a blue-red difference of a
        few DN there (≈ 4 DN at 26 DN on the real WAHRSIS low exposure), which 1–2 DN of sensor and
        JPEG noise swamp: that exposure's mask agrees with the medium one's on 85 % of the sky
        (the high one's: 96 %), and a simulated clear sky at 24 DN reads as a textured overcast.

        Flag ``overexposed`` where half the sky or more has two channels at the camera's own clip
        level (:func:`~.clip.clip_level` of the image, found in it; each channel's own on a tinted
        clip) less the saturation margin (``255 − masks.saturation_level``): its colour is gone
        (randomized sky 9339: a hazy clear sky at 218 / 245 / 249 DN under a 249 DN clip, 59 % of
        it two channels clipped, read as one overcast cloud). One clipped
        channel is common and harmless: the blue of a clear sky at a camera's white, the other two
        still apart (in 8 other skies of the same 40, ≤ 30 % of the sky had two channels clipped,
        and every clear one was read clear)."""
        for role, e in zip(("cam1", "cam2"), sky):
            ctx.diagnostics[f"sky_{role}_dn"] = e.bright_dn
        if any(e.clip is not None and e.clip.found and e.two_clipped >= 0.5 for e in sky):
            ctx.flags.append("overexposed")  # (NaN compares False: no usable sky)
        seen = [e.bright_dn for e in sky if math.isfinite(e.bright_dn)]
        if seen and min(seen) < self.config.segmentation.min_sky_dn:
            ctx.flags.append("underexposed")
            if ctx.time_utc is not None:  # at night: stars and noise, nothing the colours can call cloud
                st = self.station
                zen = sun_position(st.latitude_deg, st.longitude_deg, st.altitude_m, ctx.time_utc).zenith_deg
                if zen > 90.0 + NIGHT_SUN_DEPRESSION_DEG:
                    ctx.flags.append("night")

    def _angle_map(self, i: int, sun_dir: np.ndarray) -> np.ndarray:
        cam = (self.cam1, self.cam2)[i]
        if self.backend == "torch":
            from cbh.pipeline.torch_ops import angle_map_deg_torch

            d_cam = np.asarray(sun_dir, np.float64) @ cam.R_world_from_cam
            return angle_map_deg_torch(self.rays_cam_device(i), d_cam).cpu().numpy()
        return angle_map_deg(cam, sun_dir, self.rays_cam(i))

    def _clip_contours(self, taken: tuple[np.ndarray, np.ndarray], masks: "Masks", ctx: "PairContext") -> "Masks":
        """``masks`` with each camera's pixels near its clipping (:func:`~.masks.near_clip` of the
        images as ``taken``, within half an LK window) where the two cameras clip one cloud along
        different contours, their responses unlike (flag ``exposure_mismatch``); else unchanged.
        Cameras of one response clip the same radiance: a clipped area's edge is then one line of
        the sky in both views and its matches are as good as any (a simulated network sky whose
        cloud clips had 70 % of its LK matches within half a window of it, and without them too few
        to name a camera 2° off level)."""
        if "exposure_mismatch" not in ctx.flags:
            return masks
        reach = int(self.config.matching.lk.window_px) // 2
        return replace(masks, near_clip=tuple(near_clip(taken[i], self.config.masks, masks.clips[i], reach)
                                              for i in (0, 1)))

    def _near_obstacles(self, masks: "Masks") -> tuple:
        """Per camera, the pixels within half an LK window of a horizon obstacle found in the frame
        (:meth:`auto_obstacles`; None: none found): an LK window there holds a near object's
        texture (:func:`~.geocheck.check_geometry`'s ``beside``)."""
        k = 2 * (int(self.config.matching.lk.window_px) // 2) + 1
        el = cv2.getStructuringElement(cv2.MORPH_RECT, (k, k))
        return tuple(None if o is None or not o.any() else cv2.dilate(o.view(np.uint8), el) > 0
                     for o in masks.obstacles)

    def stage_photometric(self, work: tuple[np.ndarray, np.ndarray], masks: "Masks",
                          ctx: "PairContext") -> tuple[tuple[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]:
        """Camera 2's colour response relative to camera 1, reported and removed (:mod:`.photometric`).

        Returns (for matching, for segmentation): the working images with the brighter camera
        mapped onto the darker one's response, by the full matching tables and by the tables
        with their slope capped (:func:`~.photometric.capped_slope`); ``work`` twice when
        ``photometric.correct`` is off or nothing could be estimated.
        """
        pc = self.config.photometric
        if not pc.correct:
            return work, work
        resp = estimate_response(work[0], work[1], self.geometry, masks.usable[0], masks.usable[1], masks.clips)
        if not resp.pixels:
            return work, work
        ctx.diagnostics.update(resp.diagnostics())
        if resp.is_large(pc.max_gain, pc.max_gamma, pc.max_wb):
            ctx.flags.append("exposure_mismatch")
        if resp.is_identity:
            return work, work
        down1 = resp.brightens()  # camera 2 is the darker one: camera 1 mapped down onto it instead

        def mapped(capped: bool):
            lut21, lut12 = resp.matching_luts(capped)
            return (cv2.LUT(work[0], lut12), work[1]) if down1 else (work[0], cv2.LUT(work[1], lut21))

        return mapped(False), mapped(True)

    def stage_segment(self, work: tuple[np.ndarray, np.ndarray], masks: "Masks", as_received1: bool = False,
                      taken: tuple[np.ndarray, np.ndarray] | None = None) -> "Segmentation":
        """Cloud mask and cloud fraction of each camera's usable sky (``as_received1``: camera 1's
        image is as delivered, not mapped onto camera 2's response: its mask is its own, and a
        network's pairs share it, unless a pair finds camera 1 pale (:meth:`_pale_camera`) and
        segments it again for itself; ``taken``: the working images before the photometric step,
        None = ``work``)."""
        cams = (self.cam1, self.cam2)

        def one(i, sky_clear=False):
            if self.backend == "torch":
                from cbh.pipeline.torch_segment import segment_torch

                return segment_torch(work[i], masks.usable[i], self.zenith_device(i), masks.sun_angle[i],
                                     self.config.segmentation, device=self.device, what=cams[i].name,
                                     sky_clear=sky_clear)
            return segment(work[i], masks.usable[i], self.zenith(i), masks.sun_angle[i], self.config.segmentation,
                           what=cams[i].name, sky_clear=sky_clear)

        (c1, f1), (c2, f2) = pmap(lambda i: self._camera1_once(i, "segment", lambda: one(i)) if as_received1 else one(i),
                                  (0, 1), pool="stages")
        pale = self._pale_camera((f1, f2), (c1, c2), work, masks, work if taken is None else taken)
        if pale == 0:
            c1, f1 = one(0, sky_clear=True)
        elif pale == 1:
            c2, f2 = one(1, sky_clear=True)
        if self._clear_pair((f1, f2), (c1, c2), work, masks, work if taken is None else taken):
            c1, c2, f1, f2 = np.zeros_like(c1), np.zeros_like(c2), 0.0, 0.0
        return Segmentation(clouds=(c1, c2), fractions={cams[0].name: f1, cams[1].name: f2},
                            smooth_test=partial(self._smooth_pair, (f1, f2), work, masks))

    def _smooth_pair(self, fractions: tuple[float, float], work, masks: "Masks") -> bool:
        """Whether both cameras call their sky one cloud (``_OVERCAST_FRACTION``) and see it smooth
        (median local contrast under ``segmentation.texture_cv``): what matches there is no cloud
        texture but a smooth gradient's contours (ZNCC of a ramp is 1 at any shift along it) or
        JPEG steps, and a height from under ``UNMATCHED_FRACTION`` of it is chance
        (:meth:`_chance_matches_only`). Randomized pale hazy clear skies twice encoded (15300,
        15326 at 480 px, B = 146 and 178 m; local contrast 0.003–0.005): layers at 315 m over 81 %
        and 535 m over 70 % from 11 % of the sky matched, flagged only ``cloud_unmatched``."""
        if min(fractions) < _OVERCAST_FRACTION:
            return False
        tcv = self.config.segmentation.texture_cv
        return all(_sky_median(local_contrast, work[i], masks.usable[i], neighbourhood=True) < tcv for i in (0, 1))

    def _pale_camera(self, fractions: tuple[float, float], clouds, work, masks: "Masks", taken) -> int | None:
        """The camera that calls the whole sky one smooth cloud (median local contrast under
        ``segmentation.texture_cv``) while the other sees most of it clear (cloud on
        ``CLEAR_SKY_FRACTION`` … ``_PALE_PARTNER_MAX_FRACTION`` of it) and that clear part is blue
        as ``taken`` (median NBR ≥ ``segmentation.fixed_threshold``, before the photometric step
        made the bluer camera as pale as the other; grey cloud does not turn blue in the other
        camera, and a bluish cast lifts it to NBR 0.125 at most, the rule of
        :func:`.segment.one_class_pair_is_clear`): that camera renders clear sky pale or colour-cast,
        and is segmented again with its sky taken as clear (``segment(…, sky_clear=True)``,
        ``hybrid`` only), so that what stands out from it (the cloud the other camera sees) stays
        cloud. None otherwise.

        (Under ``CLEAR_SKY_FRACTION`` in the other camera, or when the re-segmented camera is left
        with under that, :meth:`_clear_pair` empties both, and a contrail of 1 % goes with them.)
        Randomized clear skies with contrails drawn in: 13016, camera 1's pale sky read as one
        cloud, camera 2 found the contrail (1.4 % of its sky), so the pair was not called clear,
        and camera 1's whole sky took the contrail's height, 1088 m (along the baseline, its
        aperture problem), as a layer covering 15 %; 14512 (480 px), camera 2 found its contrail
        and the aureole (16 %), blue as taken (NBR 0.159) but pale once mapped onto camera 1 (0.091), and
        camera 1's whole sky took the contrail's 6023 m (7350 m in truth) as a layer over 79 %. (Both
        partners' clear parts read NBR 0.25 and 0.159 as taken, the pale cameras' local contrast
        0.0015–0.006.)"""
        lo, hi = min(fractions), max(fractions)
        cfg = self.config.segmentation
        if not (cfg.method.lower() == "hybrid" and hi >= _OVERCAST_FRACTION
                and CLEAR_SKY_FRACTION <= lo < _PALE_PARTNER_MAX_FRACTION):
            return None
        k = int(np.argmin(fractions))
        smooth = _sky_median(local_contrast, work[1 - k], masks.usable[1 - k], neighbourhood=True) < cfg.texture_cv
        return 1 - k if self._blue_as_taken(k, clouds, masks, taken) and smooth else None

    def _blue_as_taken(self, k: int, clouds, masks: "Masks", taken) -> bool:
        """Whether camera ``k``'s clear part is blue as ``taken`` (median NBR ≥ ``segmentation.fixed_threshold``)."""
        clear = masks.usable[k] & ~clouds[k]
        return _sky_median(normalized_blue_red, taken[k], clear) >= self.config.segmentation.fixed_threshold

    def _clear_pair(self, fractions: tuple[float, float], clouds, work, masks: "Masks", taken) -> bool:
        """Whether the pair sees a clear sky although one camera's mask says otherwise.

        Both cameras look at one sky, so cloud over 1 % of it is in both: when one camera finds
        under ``CLEAR_SKY_FRACTION`` and the other under ``CLEAR_PAIR_MAX_FRACTION``, what only
        the second calls cloud is its aureole, glare or noise. And when one camera calls the
        whole sky one cloud (overcast) while the other finds it clear *and* its sky has a
        clear sky's colour (median chroma ≥ ``segmentation.clear_chroma``), the overcast one is
        a pale or colour-cast camera: grey cloud does not turn blue in the other camera. When both
        call it one cloud, the images as ``taken`` (before the photometric step made the bluer
        one as pale as the other) decide (:func:`.segment.one_class_pair_is_clear`).

        Between the two (the second camera finds ``CLEAR_PAIR_MAX_FRACTION`` … ``_OVERCAST_FRACTION``
        cloud), the pair is clear when the first camera's sky is blue as ``taken`` (median NBR ≥
        ``segmentation.fixed_threshold``) and what the second calls cloud is smooth (median local
        contrast under ``segmentation.texture_cv``): a strong aureole, its JPEG rings around a
        clipped sun, or a pale camera's two shades of clear sky, not cloud, which is textured and
        which the first camera would see too (:meth:`_aureole_pair`)."""
        lo, hi = min(fractions), max(fractions)
        if lo >= _OVERCAST_FRACTION:
            return one_class_pair_is_clear(taken, masks.usable, self.config.segmentation)
        if lo >= CLEAR_SKY_FRACTION:
            return False
        if hi < CLEAR_PAIR_MAX_FRACTION:
            return True
        i = int(np.argmin(fractions))
        if hi < _OVERCAST_FRACTION:
            return self._aureole_pair(i, clouds, work, masks, taken)
        return _sky_median(chroma, work[i], masks.usable[i]) >= self.config.segmentation.clear_chroma

    def _aureole_pair(self, k: int, clouds, work, masks: "Masks", taken) -> bool:
        """Whether camera ``k`` sees a clear blue sky (cloud under ``CLEAR_SKY_FRACTION``, median
        NBR as ``taken`` ≥ ``segmentation.fixed_threshold``) where the other camera's cloud (a
        share of its sky from ``CLEAR_PAIR_MAX_FRACTION`` to ``_OVERCAST_FRACTION``) is smooth
        (median local contrast under ``segmentation.texture_cv``).

        Two cameras tens or hundreds of metres apart see the same clouds: in randomized broken
        skies their cloud fractions agree within 0.02, and cloud is textured (median local
        contrast of cloud pixels 0.045–0.064). Randomized clear skies with a strong aureole
        (3.4–4.0×) had one camera at 0.000–0.002 and blue (NBR 0.157–0.363 as taken) while the
        other read 16–64 % cloud, smooth (0.0075–0.0145): the aureole's JPEG rings around a clipped
        sun, which the aureole's texture test took for sunlit cloud (15009, 15130), or a pale
        camera's two shades of clear sky (15119, 15153)."""
        cfg = self.config.segmentation
        if cfg.method.lower() != "hybrid":
            return False
        smooth = _sky_median(local_contrast, work[1 - k], clouds[1 - k], neighbourhood=True) < cfg.texture_cv
        return self._blue_as_taken(k, clouds, masks, taken) and smooth

    def stage_match(self, work, masks: "Masks", seg: "Segmentation", ctx: "PairContext", gray=None,
                    cloud2: np.ndarray | None = None, views2=None) -> "Correspondences":
        """Correspondences of every configured method, triangulated and geometrically checked.

        ``gray``: the two working-size grey images (default: from ``work``); ``cloud2``: camera
        2's cloud mask (default: the segmentation's), both given when camera 2 is compensated
        for its clock offset; ``views2``: camera 2 per plane of the sweep
        (:class:`~cbh.pipeline.sweep.PlaneViews`; None: ``gray[1]`` for every plane)."""
        cfg = self.config
        geom = self.geometry
        if gray is None:
            gray = (cv2.cvtColor(work[0], cv2.COLOR_BGR2GRAY), cv2.cvtColor(work[1], cv2.COLOR_BGR2GRAY))
        inp = MatchInput(
            geometry=geom, gray1=gray[0], gray2=gray[1],
            cloud1=seg.clouds[0], usable1=masks.usable[0], usable2=masks.usable[1],
            cloud2=seg.clouds[1] if cloud2 is None else cloud2,
            device=self.device if self.backend == "torch" else None, views2=views2,
        )
        raw = []
        if seg.clouds[0].any():  # the matchers run side by side (their times overlap)
            def one(name):
                with _timed(ctx, f"match_{name}"):
                    return get_matcher(name)(inp, cfg.matching)

            raw = list(pmap(one, cfg.matching.methods, pool="stages"))
            raw = self._seeded_lk(raw, gray, seg, ctx)
        with _timed(ctx, "triangulation"):
            tris = [triangulate_matches(geom, m, cfg.filtering) for m in raw]
        floor = max((m.field.floor_fraction for m in raw if m.field is not None), default=math.nan)
        if math.isfinite(floor):  # (flagged below_range, or not, by _quality_flags)
            ctx.diagnostics["below_range_fraction"] = floor
        return Correspondences(triangulated=tris, raw=raw)

    def _seeded_lk(self, raw: list, gray, seg: "Segmentation", ctx: "PairContext") -> list:
        """``raw`` with LK's matches replaced by LK started at the sweep's
        (:func:`~.geocheck.seeded_matches`) where the 2-D methods found fewer than the geometry
        check's ``min_matches``: a long baseline (a 630 m pair sees 1500 m cloud 100–200 px from
        the point at infinity, where plain LK starts and loses it). They give the pair its
        geometry verdict and its angular noise (the layer bases)."""
        n2d = sum(len(m) for m in raw if m.method in CHECK_METHODS)
        sweep = [m for m in raw if m.method == "sweep" and len(m)]
        if n2d >= self.config.geometry_check.min_matches or not sweep:
            return raw
        with _timed(ctx, "match_lk_seeded"):
            c = self.config.matching.lk
            seeded, tried = seeded_matches(gray[0], gray[1], sweep[0], seg.clouds[0], c.max_points, c.window_px,
                                           fb_max_px=c.fb_max_px)
            if len(seeded):  # scored as plain LK's are (the check judges the well-correlated corners)
                g = self.geometry
                seeded.zncc, seeded.corner = match_scores(g, gray[0], g.warp2(gray[1]), seeded.px1, seeded.px2,
                                                          c.window_px)
        ctx.diagnostics["geometry_seeded_tracked"] = len(seeded) / tried if tried else math.nan
        ctx.diagnostics["geometry_seeded_tried"] = float(tried)
        return [m for m in raw if m.method != "lk"] + [seeded]

    def stage_sun_check(self, work, masks: "Masks", ctx: "PairContext") -> None:
        """Detected vs predicted sun per camera → ``sun_residual_*_deg``, flag ``sun_misaligned``."""
        cfg = self.config.sun_check
        if not cfg.enabled or masks.sun_dir_enu is None:
            return
        cams = (self.cam1, self.cam2)

        def one(i):
            expected = masks.sun_dir_enu @ cams[i].R_world_from_cam
            det = detect_sun(work[i], cams[i], expected, cfg.search_deg, usable=self.static_mask(i), clip=masks.clips[i])
            return math.degrees(math.acos(min(1.0, float(det.ray_cam @ expected)))) if det.ok else math.nan

        res = list(pmap(lambda i: self._camera1_once(i, "sun_check", lambda: one(i)), (0, 1), pool="stages"))
        for role, r in zip(("cam1", "cam2"), res):
            ctx.diagnostics[f"sun_residual_{role}_deg"] = r
        seen = [r for r in res if math.isfinite(r)]
        ctx.diagnostics["sun_residual_deg"] = max(seen) if len(seen) == 2 else math.nan
        # The pair's residual and its flag need the sun found in BOTH cameras: a single detection can be a saturated
        # cloud next to a hidden sun (seen on simulated broken cumulus: 3-5 deg "residuals" in
        # one camera while the other found nothing). A knocked camera still shows as soon as
        # the sun is clear in both, which at a 10-30 s cadence is within minutes.
        if len(seen) == 2 and max(seen) > cfg.max_residual_deg:
            ctx.flags.append("sun_misaligned")

    def stage_geometry_check(self, work, corr: "Correspondences", ctx: "PairContext") -> None:
        """Correspondences vs station geometry → ``geometry_*`` diagnostics and flags."""
        self._apply_geometry(self.geometry_findings(work, corr), ctx)

    def geometry_findings(self, work, corr: "Correspondences", seg: "Segmentation | None" = None,
                          carry_noise_rad: float = 0.0, near_clip: tuple = (None, None),
                          near_obstacle: tuple = (None, None)) -> "tuple[bool, object] | None":
        """The geometry check's findings (identical images, :func:`check_geometry`'s result);
        None when the check is off. Reads only its arguments: runs beside the height map.

        With ``seg``, the geometry is judged on real cloud only: correspondences whose camera-2
        pixel is cloud in camera 2 too (a match from cloud onto clear sky, glare or an unmasked
        obstacle is a mismatch of the matcher, not of the station), and not at all when
        camera 1's sky is clear (``clear_sky``: whatever matched there is not cloud; nor on a
        smooth one-cloud sky's chance matches: :meth:`finish`).

        ``carry_noise_rad``: the angular noise of carrying camera 2 to camera 1's time (a pair
        matched on the sky maps with a clock offset, :mod:`.skyclock`), added in quadrature to the
        miss the station's calibration is expected to leave: a miss that the carry explains is not
        the geometry's.

        ``near_clip``: per camera, the pixels within half an LK window of a clipped one
        (:func:`~.masks.near_clip`, None = none): a match there is left out, in either camera (its
        window's texture is cut where that camera's exposure clips).

        ``near_obstacle``: per camera, the pixels within half an LK window of a horizon obstacle
        found in the frame (:meth:`_near_obstacles`, None = none): a match there still counts,
        but a rotation verdict needs enough others (:func:`check_geometry`'s ``beside``)."""
        cfg = self.config.geometry_check
        if not cfg.enabled:
            return None
        if carry_noise_rad > 0:
            cfg = replace(cfg, expected_miss_ratio=math.hypot(cfg.expected_miss_ratio, carry_noise_rad))
        raw = corr.raw
        if seg is not None:
            if seg.fractions[self.cam1.name] < CLEAR_SKY_FRACTION:
                raw = []
            else:
                raw = [m.take(_on_mask(seg.clouds[1], m.px2)) for m in raw]
        raw = [_off_clip(m, near_clip) if m.method in CHECK_METHODS else m for m in raw]
        grid = next((tr.grid_m for tr in corr.triangulated if tr.grid_m is not None), None)
        if grid is not None:
            raw = [self._within_one_deck(m, grid) if m.method in CHECK_METHODS and m.method not in CARRIED_METHODS
                   else m for m in raw]
        beside = [_on_either(near_obstacle, m) for m in raw]
        return (images_identical(work[0], work[1], cfg.identical_max_dn),
                check_geometry(self.geometry, raw, self.config.filtering, cfg, self.config.matching.lk.window_px,
                               beside))

    def _within_one_deck(self, m: Matches, grid_m: np.ndarray) -> Matches:
        """The matches whose matching window holds one deck of the dense heights ``grid_m`` (its
        heights' 10–90 % spread under ``layers.min_separation_log``, what the layers call one
        layer; a window with no heights is kept): a window across the edge of a nearer deck holds
        two parallaxes, a T-junction of two edges that moves between the views as neither does,
        and a translation fits it with a bias off the epipolar curve. Randomized 18601 (480 px, decks at
        430, 1211 and 2201 m, B = 172 m): 71 of its 72 judged LK windows held two decks; their
        fit turned a correct camera by 0.39° ± 0.07° (tolerance 0.18°) and flagged ``geometry_mismatch``."""
        spread = window_height_spread(grid_m, m.px1, self.config.matching.lk.window_px)
        keep = ~(spread > self.config.layers.min_separation_log)
        return m if keep.all() else m.take(keep)

    def _nothing_to_judge(self, seg: "Segmentation", masks: "Masks", lay: LayerSet, hmap: HeightMap, geo):
        """(seg, geo) with the geometry check's verdict withdrawn where the pair's matches witness
        nothing: a clear sky over a skyline (:func:`_only_on_skylines`; its cloud emptied too), and
        a smooth one-cloud sky's chance matches (:meth:`_smooth_pair`, :meth:`_chance_matches_only`:
        a ramp matches at any shift along it, and noise on it passes the corner test; randomized
        18361, its pale clear sky read as one cloud: 69 LK matches 0.3–17 px from infinity, inliers
        0.41, ``geometry_mismatch`` on a correct station)."""
        if not lay.layers and _only_on_skylines(seg, masks):
            seg = Segmentation(clouds=tuple(np.zeros_like(c) for c in seg.clouds), fractions=dict.fromkeys(seg.fractions, 0.0))
        elif not (seg.smooth and self._chance_matches_only(hmap, seg)):
            return seg, geo
        return seg, geo and (geo[0], check_geometry(self.geometry, [], self.config.filtering, self.config.geometry_check))

    @staticmethod
    def _apply_geometry(found, ctx: "PairContext") -> None:
        """The geometry check's findings into the pair's ``geometry_*`` diagnostics and flags."""
        if found is None:
            return
        identical, chk = found
        if identical:
            ctx.flags.append("identical_images")
        ctx.diagnostics["geometry_residual_px"] = chk.residual_px
        ctx.geometry_tolerance_px = chk.tolerance_px
        ctx.diagnostics["geometry_inlier_fraction"] = chk.inlier_fraction
        ctx.diagnostics["geometry_rotation_deg"] = chk.rotation_deg
        ctx.diagnostics["geometry_rotation_sigma_deg"] = chk.rotation_sigma_deg
        if chk.mismatch and "night" not in ctx.flags:  # (at night the matches are of stars and noise: no verdict)
            ctx.flags.append("geometry_mismatch")

    def stage_height_map(self, seg: "Segmentation", corr: "Correspondences") -> HeightMap:
        """Dense height map on camera 1's working grid (dense matches preferred), and at full size."""
        dense = [tr for tr in corr.triangulated if tr.matches.dense]
        src = dense if dense else corr.triangulated
        grids = [tr.grid_m for tr in src if tr.grid_m is not None]  # a sweep's field: every pixel it measured
        pts = [tr for tr in src if tr.grid_m is None]
        if pts:
            px = np.concatenate([tr.matches.px1 for tr in pts])
            hh = np.concatenate([tr.height_m for tr in pts])
        else:
            px, hh = np.zeros((0, 2)), np.zeros(0)
        shape1 = (self.cam1.model.height, self.cam1.model.width)
        fill = None
        if self.backend == "torch":
            from cbh.pipeline.torch_heightmap import nearest_fill_torch

            fill = partial(nearest_fill_torch, device=self.device)
        hm = dense_height_map(shape1, px, hh, seg.clouds[0], self.config.height_map,
                              (self.cam1_full.model.width, self.cam1_full.model.height), grids=grids, nearest=fill)
        # the share of the cloud measured means something only for a dense method (sparse
        # matches cover a few hundred pixels of any cloud): unknown otherwise, and no flag hangs on it
        return hm if dense else replace(hm, measured_fraction=math.nan)

    def stage_points(self, corr: "Correspondences") -> "Points":
        """All kept correspondences as points (dense ones thinned to a grid), with predicted noise."""
        cfg = self.config
        parts = []
        for tr in corr.triangulated:
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
        sparse = [tr for tr in corr.triangulated if not tr.matches.dense]
        if sum(len(tr.miss_m) for tr in sparse) < _MIN_NOISE_MATCHES:  # none survived: dense 2-D matches
            sparse = [tr for tr in corr.triangulated if tr.matches.method not in EPIPOLAR_METHODS]
        dtheta = angular_noise(
            np.concatenate([tr.miss_m for tr in sparse] or [np.zeros(0)]),
            np.concatenate([np.linalg.norm(tr.point_m - self.cam1.position_m, axis=1) for tr in sparse] or [np.zeros(0)]))
        noise = height_noise(xyz, self.cam1.position_m, self.cam2.position_m, dtheta)
        resolved = tuple(h for tr in corr.triangulated if tr.matches.field is not None for h in tr.matches.field.resolved_m)
        return Points(xyz_m=xyz, miss_m=miss, px1=p1, px2=p2, noise_m=noise,
                      per_method=[(p[0], len(p[1])) for p in parts], resolved_m=resolved,
                      parallax_px=parallax_px(xyz, self.cam1.position_m, self.cam2.position_m, self._px_per_rad2()))

    def stage_layers(self, pts: "Points", seg: "Segmentation", masks: "Masks", hmap: HeightMap,
                     ctx: "PairContext", gray=None, comp=None, judge_unseen: bool = False) -> LayerSet:
        """Height histogram → candidate intervals → supported layers with covers → less the
        aliases of other layers (:mod:`.support`; with the working grey images ``gray`` and
        camera 2's clock compensation ``comp``, as matched) → with ``judge_unseen``, less the
        layers camera 2 does not see as cloud (:func:`~.support.unseen_layers`; not for matches
        whose camera-2 pixels were carried by the sky maps). A clear sky has no layer."""
        hist, intervals = self._layers(pts.xyz_m[:, 2], self.config.layers, self.config.filtering)
        if seg.fractions[self.cam1.name] < CLEAR_SKY_FRACTION or self._chance_matches_only(hmap, seg):
            intervals = []  # whatever matched on a clear sky is not cloud, nor chance matches on a featureless one
        rel = pts.xyz_m - np.asarray(self.cam1.position_m, np.float64)[None, :]
        with np.errstate(invalid="ignore", divide="ignore"):
            offsets = rel[:, :2] / rel[:, 2:3]
        lay = supported_layers(pts.xyz_m[:, 2], pts.noise_m, hist, intervals, seg.clouds[0], masks.usable[0],
                               hmap.nearest_m, seg.fractions[self.cam1.name], self.config.layers, offsets,
                               resolved_m=pts.resolved_m, parallax=pts.parallax_px,
                               camera_z_m=float(self.cam1.position_m[2]))
        if gray is not None and len(lay.layers) > 1 and self.config.layers.reject_aliases:
            g2 = gray[1] if comp is None else cv2.remap(gray[1], comp, None, cv2.INTER_LINEAR,
                                                        borderMode=cv2.BORDER_REPLICATE)
            f = self.factors[0]
            aliases = alias_layers(gray[0], g2, self.geometry.planes, float(self.cam1.position_m[2]),
                                   [L.height_m for L in lay.layers], (pts.px1 + 0.5) * f - 0.5, lay.label)
            if aliases:
                ctx.diagnostics["alias_layers_m"] = float(sum(lay.layers[k].height_m for k in aliases) / len(aliases))
            lay = without_layers(lay, aliases)
        if judge_unseen and lay.layers:  # a layer camera 2 does not see is camera 1's aureole or glare
            px2 = (pts.px2 + 0.5) * self.factors[1] - 0.5
            unseen = unseen_layers(self._cloud2_as_matched(seg, comp), px2, lay.label, len(lay.layers))
            lay = self._drop_unseen(lay, unseen, "unseen_layers_m", seg, ctx)
            lines = self._sun_lines(masks)
            if lay.layers and lines is not None:  # … and one on both sun lines a lens-flare ghost
                flare = flare_layers(((pts.px1 + 0.5) * self.factors[0] - 0.5, px2), lines, lay.label,
                                     [L.cover for L in lay.layers], self._flare_band_px())
                lay = self._drop_unseen(lay, flare, "flare_layers_m", seg, ctx)
        if lay.cover_incomplete:
            ctx.flags.append("cover_incomplete")
        alt = self.station.altitude_m
        return replace(lay, layers=[replace(L, altitude_m=L.height_m + alt) for L in lay.layers])

    def _sun_lines(self, masks: "Masks") -> tuple | None:
        """Per camera (the sun's pixel, the optical centre), working size: the line a lens's ghosts
        of the sun lie on (:func:`~.support.flare_layers`); None when the sun is unknown or down."""
        if masks.sun_dir_enu is None:
            return None
        return tuple((cam.direction_to_pixel(masks.sun_dir_enu[None, :])[0], cam.model.center_xy)
                     for cam in (self.cam1, self.cam2))

    def _flare_band_px(self) -> float:
        """``support.FLARE_BAND_DEG`` at working size [px] (the lens scale near the zenith)."""
        return math.radians(FLARE_BAND_DEG) * self._px_per_rad2()

    def _drop_unseen(self, lay: LayerSet, which: list[int], key: str, seg: "Segmentation", ctx: "PairContext") -> LayerSet:
        """``lay`` less the layers ``which`` that are not cloud (their cover to no layer), their mean
        height in the diagnostic ``key``."""
        if not which:
            return lay
        ctx.diagnostics[key] = float(sum(lay.layers[k].height_m for k in which) / len(which))
        gone = lay.unassigned + sum(lay.layers[k].cover for k in which)
        lay = without_layers(lay, dict.fromkeys(which))
        return replace(lay, unassigned=gone,
                       cover_incomplete=cover_incomplete(bool(lay.layers), gone, seg.fractions[self.cam1.name]))

    @staticmethod
    def _cloud2_as_matched(seg: "Segmentation", comp) -> np.ndarray:
        """Camera 2's cloud mask in the frame its matches were made in (carried to camera 1's
        time by the clock compensation ``comp``, as :meth:`_match_compensated` does)."""
        if comp is None:
            return seg.clouds[1]
        return cv2.remap(seg.clouds[1].view(np.uint8), comp, None, cv2.INTER_NEAREST,
                         borderMode=cv2.BORDER_REPLICATE).astype(bool)

    def _chance_matches_only(self, hmap: HeightMap, seg: "Segmentation") -> bool:
        """Whether a dense method's matches are chance ones (:data:`CHANCE_PATCH_WINDOWS`,
        :data:`CHANCE_MEASURED_FRACTION`, or under ``UNMATCHED_FRACTION`` of a smooth one-cloud
        sky, :meth:`_smooth_pair`)."""
        m = hmap.measured_fraction
        if not (math.isfinite(m) and m < UNMATCHED_FRACTION):
            return False
        return (m < CHANCE_MEASURED_FRACTION
                or hmap.largest_patch_px < CHANCE_PATCH_WINDOWS * self.config.matching.sweep.window_px ** 2
                or seg.smooth)

    def _quality_flags(self, pts: "Points", seg: "Segmentation", ctx: "PairContext", hmap: HeightMap,
                       lay: LayerSet) -> None:
        n = len(pts.xyz_m)
        frac1 = seg.fractions[self.cam1.name]
        measured = hmap.measured_fraction
        ctx.diagnostics["measured_fraction"] = measured  # NaN: no dense method, or no cloud
        if math.isfinite(measured):
            if measured < UNMATCHED_FRACTION and frac1 >= 0.01:
                ctx.flags.append("cloud_unmatched")
            floor_m = self.config.matching.sweep.min_height_m
            # the share of the matches on the floor plane, unless they are chance ones: a featureless
            # sky's few chance matches put one plane or another ahead (seed 9339, 480 px: 6.2 % of 1.9 %
            # measured on the floor once the floor plane's map was exact, a cubic in stop 59)
            floor = ctx.diagnostics.get("below_range_fraction", 0.0)
            if (floor > BELOW_RANGE_FRACTION and "below_range" not in ctx.flags
                    and (floor > BELOW_RANGE_CHANCE_FRACTION or not self._chance_matches_only(hmap, seg))):
                ctx.flags.append("below_range")
            # the lowest layer that covers a share of the sky (fog's floor layers: 13–24 %), not a
            # small chance one
            lowest = min((L.height_m for L in lay.layers if L.cover >= _FLOOR_LAYER_COVER), default=math.inf)
            if ("below_range_fraction" in ctx.diagnostics and "below_range" not in ctx.flags
                    and lowest <= FLOOR_LAYER_RATIO * floor_m and measured < FLOOR_LAYER_MATCHED):
                ctx.flags.append("below_range")  # see FLOOR_LAYER_RATIO
        if frac1 < CLEAR_SKY_FRACTION:
            ctx.flags.append("clear_sky")  # (and not few_points: a clear sky has nothing to match)
        elif n < self.config.layers.min_points:
            ctx.flags.append("few_points")
        if frac1 > 0.9 and (n < self.config.layers.min_points or self._chance_matches_only(hmap, seg)):
            ctx.flags.append("overcast_no_texture")

    def _assemble(self, ctx: "PairContext", seg: "Segmentation", hmap: HeightMap, pts: "Points",
                  lay: LayerSet) -> PairResult:
        matches, off = {}, 0
        for method, n in pts.per_method:
            step = max(1, int(math.ceil(n / _MAX_DISPLAY_MATCHES)))
            sl = slice(off, off + n, step)
            matches[method] = np.concatenate([pts.px1[sl], pts.px2[sl]], axis=1).astype(np.float32)
            off += n
        full = (self.cam1_full.model, self.cam2_full.model)
        return PairResult(
            time_utc=ctx.time_utc,
            cameras=self.cameras,
            layers=lay.layers,
            histogram=lay.histogram,
            points=PointSet(
                xyz_m=pts.xyz_m.astype(np.float32), miss_m=pts.miss_m.astype(np.float32),
                px1=pts.px1.astype(np.float32), px2=pts.px2.astype(np.float32), layer=lay.label,
            ),
            height_map=hmap.full(),  # full size when read (Enlarged)
            cloud_masks={c: Enlarged(np.asarray(m, bool), f.width, f.height)
                         for c, m, f in zip(self.cameras, seg.clouds, full)},
            cloud_fraction=seg.fractions,
            timing_ms=ctx.timing,
            flags=ctx.flags,
            diagnostics=dict(ctx.diagnostics),
            matches=matches,
        )


class FrameMemo:
    """Values computed once per frame set and shared between threads: the first caller of a key
    computes it, later callers wait for it (and see its exception, if it raised)."""

    def __init__(self):
        self._lock = threading.Lock()
        self._slots: dict = {}

    def get(self, key, fn):
        with self._lock:
            slot = self._slots.get(key)
            owner = slot is None
            if owner:
                slot = self._slots[key] = [threading.Event(), None, None]
        if owner:
            try:
                slot[1] = fn()
            except BaseException as exc:
                slot[2] = exc
                raise
            finally:
                slot[0].set()
            return slot[1]
        slot[0].wait()
        if slot[2] is not None:
            raise slot[2]
        return slot[1]


def _on_either(masks: tuple, m: Matches) -> np.ndarray:
    """Which matches have camera 1's pixel on ``masks[0]`` or camera 2's on ``masks[1]`` (None:
    an empty mask), (N,) bool."""
    on = np.zeros(len(m), bool)
    for mask, px in zip(masks, (m.px1, m.px2)):
        if mask is not None:
            on |= _on_mask(mask, px)
    return on


def _off_clip(m: Matches, near_clip: tuple) -> Matches:
    """The matches whose pixels are off each camera's ``near_clip`` mask (None: nothing clipped)."""
    keep = ~_on_either(near_clip, m)
    return m if keep.all() else m.take(keep)


def _on_mask(mask: np.ndarray, px: np.ndarray) -> np.ndarray:
    """Which of the pixels ``px`` (N, 2) [x, y] fall on True pixels of ``mask`` (H, W), (N,) bool."""
    if len(px) == 0:
        return np.zeros(0, bool)
    H, W = mask.shape
    x = np.clip(np.rint(px[:, 0]).astype(np.int64), 0, W - 1)
    y = np.clip(np.rint(px[:, 1]).astype(np.int64), 0, H - 1)
    ok = np.isfinite(px).all(axis=1)
    return ok & mask[y, x]


# --- typed intermediate results -------------------------------------------------------------

@dataclass
class PairContext:
    """Per-pair mutable state: the capture time (None = unknown), flags and stage timings."""

    time_utc: datetime | None
    flags: list[str] = field(default_factory=list)
    timing: dict[str, float] = field(default_factory=dict)  # stage → wall time [ms]
    diagnostics: dict[str, float] = field(default_factory=dict)  # PairResult.diagnostics
    geometry_tolerance_px: float = math.nan  # the geometry check's tolerance on its median distance [px]


@dataclass(frozen=True)
class Prepared:
    """A pair after :meth:`Pipeline.prepare`: what :meth:`Pipeline.finish` needs."""

    ctx: PairContext
    t_all: float  # perf_counter at the start (the pair's total time)
    first: bool  # the pipeline's first pair (it saves the table cache)
    work: tuple[np.ndarray, np.ndarray]  # working-size BGR images (photometrically matched)
    masks: "Masks"
    seg: "Segmentation"
    gray: tuple[np.ndarray, np.ndarray]  # working-size grey images
    received: tuple[np.ndarray, np.ndarray]  # the images as delivered, full size
    prepare_ms: float = 0.0  # wall time of the first half


@dataclass(frozen=True)
class MotionInput:
    """What the previous pair offers: its raw grey frames and the time since (None / NaN when
    motion cannot be computed across), and camera 2's clock-offset history [s]."""

    prev_gray: tuple[np.ndarray, np.ndarray] | None = None
    dt_s: float = math.nan
    offsets_s: tuple[float, ...] = ()
    profile: MotionProfile = field(default_factory=MotionProfile.empty)  # the previous pair's motion profile
    sky_check_in: int = 0  # pairs until the sky maps estimate the offset again (0: this one; .skyclock)


@dataclass(frozen=True)
class MotionEstimate:
    """Stereo features tracked back in time (working size; NaN rows = lost tracks)."""

    dt_s: float = math.nan
    px1: np.ndarray | None = None  # (N, 2) camera-1 pixels of the tracked stereo features
    w1: np.ndarray | None = None  # (N, 2) camera 1's plane-offset rate [1/s]
    w2: np.ndarray | None = None  # (N, 2) camera 2's plane-offset rate of the partner [1/s]
    pair_offset_s: float = math.nan  # this pair's clock-offset estimate [s]
    height_m: np.ndarray | None = None  # (N,) each feature's own stereo height [m] for the offset (NaN: rejected)
    profile: MotionProfile = field(default_factory=MotionProfile.empty)  # the tracks' motion over height


@dataclass(frozen=True)
class Masks:
    """Stage 2: usable sky per camera at working size."""

    usable: tuple[np.ndarray, np.ndarray]  # (H, W) bool each
    sun_angle: tuple[np.ndarray | None, np.ndarray | None]  # (H, W) float32 [deg] angle to the sun, None = unknown
    sun_dir_enu: np.ndarray | None  # (3,) unit vector to the sun in ENU, None = unknown or below the horizon
    obstacles: tuple = (None, None)  # (H, W) bool horizon obstacles found in the frame, None = the station's mask
    #: saturated cloud near the sun (masks.glare_and_sunlit), per camera or None: usable sky that
    #: segments as cloud, but not for matching (its contour is where each camera's exposure clips)
    sunlit: tuple = (None, None)
    clips: tuple = (None, None)  # each camera's working image's clip level (:func:`~.clip.clip_level`), None = not found yet
    #: per camera, the pixels within half an LK window of a clipped one (:func:`~.masks.near_clip`) where the
    #: cameras' responses differ (Pipeline._clip_contours), None = none or not asked
    near_clip: tuple = (None, None)

    def for_matching(self, seg: "Segmentation") -> tuple["Masks", "Segmentation"]:
        """These masks and ``seg`` without the sunlit saturated cloud (themselves when there is none)."""
        if all(s is None for s in self.sunlit):
            return self, seg
        keep = [None if s is None else ~s for s in self.sunlit]
        usable = tuple(u if k is None else u & k for u, k in zip(self.usable, keep))
        clouds = tuple(c if k is None else c & k for c, k in zip(seg.clouds, keep))
        return replace(self, usable=usable, sunlit=(None, None)), replace(seg, clouds=clouds)


@dataclass(frozen=True)
class Segmentation:
    """Stage 3: cloud masks (working size) and cloud fraction of each camera's usable sky."""

    clouds: tuple[np.ndarray, np.ndarray]  # (H, W) bool each
    fractions: dict[str, float]  # camera name → 0..1
    # Pipeline._smooth_pair of this pair, run only when first asked (two local-contrast maps: 6 ms at 960 px)
    smooth_test: Callable[[], bool] | None = field(default=None, repr=False, compare=False)

    @cached_property
    def smooth(self) -> bool:
        """Both cameras call their sky one cloud, and it is smooth (:meth:`Pipeline._smooth_pair`)."""
        return bool(self.smooth_test is not None and self.smooth_test())


@dataclass(frozen=True)
class Correspondences:
    """Stages 4–5: every method's matches, triangulated and checked."""

    triangulated: list[TriangulatedMatches]
    raw: list[Matches] = field(default_factory=list)  # every method's matches before rejection (the motion tracks LK's)


@dataclass(frozen=True)
class Points:
    """Kept correspondences as ENU points (dense ones thinned), full-size pixels."""

    xyz_m: np.ndarray  # (N, 3) ENU [m]
    miss_m: np.ndarray  # (N,) ray miss distance [m]
    px1: np.ndarray  # (N, 2) camera 1 pixels (full size)
    px2: np.ndarray  # (N, 2) camera 2 pixels (full size)
    noise_m: np.ndarray  # (N,) predicted height noise [m]
    per_method: list[tuple[str, int]]  # (method, count) in the order of the arrays
    resolved_m: tuple = ()  # heights of the layers the plane sweep resolved on its own [m]
    parallax_px: np.ndarray | None = None  # (N,) stereo parallax at working size [px] (None = unknown)


def _only_on_skylines(seg: "Segmentation", masks: "Masks") -> bool:
    """Whether all the cloud of a pair without a layer stands on the skylines found in its frames:
    every camera under ``CLEAR_PAIR_MAX_FRACTION``, and at least ``_SKYLINE_CLOUD_SHARE`` of each
    one's cloud pixels in components that touch an obstacle it found (a pale sunlit block, a wall
    or the hazy rim above a row, unmatched because it is no cloud at any height). Such a pair is a
    clear sky over a skyline. Cloud above the horizon stands free of the skyline somewhere; cloud
    only low over the skyline that gave no layer loses only its fraction."""
    fr = list(seg.fractions.values())
    if max(fr) >= CLEAR_PAIR_MAX_FRACTION or max(fr) < CLEAR_SKY_FRACTION:
        return False
    for cloud, obst in zip(seg.clouds, masks.obstacles):
        if not cloud.any():
            continue
        if obst is None or not obst.any():
            return False
        n, labels = cv2.connectedComponents(cloud.view(np.uint8), connectivity=8)
        near = cv2.dilate(obst.view(np.uint8), np.ones((5, 5), np.uint8)) > 0
        touching = np.zeros(n, bool)
        touching[labels[near & cloud]] = True
        touching[0] = False
        if np.count_nonzero(touching[labels]) < _SKYLINE_CLOUD_SHARE * np.count_nonzero(cloud):
            return False
    return True


@dataclass(frozen=True)
class SkyExposure:
    """How bright a camera's usable sky is (:func:`_sky_dn`), against its own white level."""

    bright_dn: float  # median brightest channel [DN] (NaN: no usable sky)
    two_clipped: float  # share of the usable sky with two or three channels at their clip level [1] (NaN: none)
    clip: object = None  # cbh.pipeline.clip.ClipLevel of the image


def _sky_dn(image: np.ndarray, usable: np.ndarray, clip, margin_dn: int) -> tuple[float, float]:
    """Median brightest channel [DN] of an image's usable sky, and the share of it with at least two
    channels within ``margin_dn`` of their clip level (``clip``, a :class:`~.clip.ClipLevel`: each
    channel's own on a tinted clip), on the sampling lattice (NaN: none)."""
    sl = sample_lattice(np.count_nonzero(usable))
    u = usable[sl]
    if not u.any():
        return math.nan, math.nan
    px = image[sl][u]
    at = (px >= np.asarray(clip.channel_levels(), np.int32) - int(margin_dn)).sum(axis=1)
    return float(np.median(px.max(axis=1))), float(np.mean(at >= 2))


@contextmanager
def _timed(ctx: PairContext, stage: str):
    t = time.perf_counter()
    try:
        yield
    finally:
        ctx.timing[stage] = ctx.timing.get(stage, 0.0) + _ms(t)


def _ms(t0: float) -> float:
    return (time.perf_counter() - t0) * 1000.0
