"""Pipeline configuration: one frozen dataclass per stage, units in the field comments.

A station file may carry a ``[pipeline]`` table (and sub-tables ``[pipeline.masks]``,
``[pipeline.segmentation]``, ``[pipeline.matching]``, ``[pipeline.matching.lk]`` …) whose keys
are exactly the field names below. Unknown keys and wrongly typed values raise
:class:`~cbh.errors.ConfigError` naming the key path, e.g. ``pipeline.matching.lk.window_px``.
Methods are chosen by name; unknown names raise a ConfigError listing the valid ones.

>>> cfg = PipelineConfig.from_dict({"matching": {"methods": ["lk"]}})
>>> cfg.matching.methods
('lk',)
>>> PipelineConfig.from_dict(cfg.to_dict()) == cfg
True
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

from cbh.errors import ConfigError
from cbh.tomlio import dataclass_from_table, dataclass_to_dict

__all__ = [
    "MasksConfig",
    "PhotometricConfig",
    "SegmentationConfig",
    "LKConfig",
    "ORBConfig",
    "DISConfig",
    "SweepConfig",
    "MatchingConfig",
    "FilteringConfig",
    "HeightMapConfig",
    "LayersConfig",
    "MotionConfig",
    "GeometryCheckConfig",
    "SunCheckConfig",
    "PipelineConfig",
]

FILL_METHODS = ("none", "nearest")
# Method names are not listed here: validation asks the registries (SEGMENTERS in .segment,
# MATCHERS in .match, LAYER_METHODS in .layers), so a registered method is a valid name.


def _registries() -> tuple[dict, dict, dict]:
    """(segmenters, matchers, layer methods): the name → function registries of the stages."""
    from cbh.pipeline.layers import LAYER_METHODS  # here: those modules import this one
    from cbh.pipeline.match import MATCHERS
    from cbh.pipeline.segment import SEGMENTERS

    return SEGMENTERS, MATCHERS, LAYER_METHODS


@dataclass(frozen=True)
class MasksConfig:
    """Which pixels of each camera are usable sky."""

    max_zenith_deg: float = 80.0  # largest zenith angle of usable sky [deg]
    static_mask: bool = True  # apply the camera's obstacle mask image (station `mask`), if any
    auto_obstacles: bool = True  # a camera without a mask: find dark horizon objects in each frame (and learn them over a run)
    overlay_text: bool = True  # find the camera's on-screen text (its clock, its name) in each frame and mask it (cbh.pipeline.overlay)
    sun: bool = True  # mask a disk around the sun (pvlib position from lat/lon + time)
    sun_radius_deg: float = 8.0  # radius of the masked sun disk [deg]
    saturation: bool = True  # also mask saturated blobs (sun, glare, specular reflections)
    saturation_level: int = 250  # full-range threshold: a pixel is saturated when all channels reach this, lowered by each image's own clip level (cbh.pipeline.clip) [0..255]
    saturation_min_area_px: int = 20  # smallest saturated blob kept, at working size [px]
    saturation_grow_px: int = 6  # dilation of saturated blobs, at working size [px]
    glare_radius_deg: float = 30.0  # with a known sun, only saturation within this angle of it is glare; beyond: over-exposed cloud (180 = all glare) [deg]


@dataclass(frozen=True)
class SegmentationConfig:
    """Cloud / clear-sky classification on the normalized blue-red ratio NBR = (B−R)/(B+R)."""

    method: str = "hybrid"  # one of: hybrid, nbr, nbr_adaptive, otsu
    clear_percentile: float = 85.0  # hybrid: a region's clear-sky reference = this percentile of its NBR / chroma [%]
    min_gap: float = 0.06  # hybrid: smallest blue deficit (reference − NBR) of cloud; below it one class only [1]
    chroma_gap: float = 0.06  # hybrid: … or half of it when the cloud class is this much greyer (chroma) and half as saturated [1]
    fixed_threshold: float = 0.15  # hybrid: one-class images are cloud when their median NBR is below this [1]
    clear_chroma: float = 0.2  # hybrid: … or their median chroma is below this (a pale or warm-cast clear sky keeps ≥ 0.25) [1]
    texture_cv: float = 0.03  # hybrid: a one-class sky whose median local contrast (std/mean, 7 px) exceeds this is cloud [1]
    chroma_weight: float = 0.3  # hybrid: weight of the desaturation cue against the blue deficit, 0..1 [1]
    brightness_weight: float = 0.25  # hybrid: score added per ln(1.5) of brightness difference from the clear sky nearby [1]
    score_threshold: float = 0.45  # hybrid: cloud where the combined cloudiness score exceeds this [1]
    threshold: float = 0.10  # NBR below this is cloud (nbr; base of nbr_adaptive) [1]
    sun_threshold: float = -0.05  # nbr_adaptive: threshold right at the sun [1]
    sun_scale_deg: float = 25.0  # nbr_adaptive: e-folding angle of the sun term [deg]
    horizon_threshold: float = 0.03  # nbr_adaptive: threshold at zenith 90 deg [1]
    horizon_start_deg: float = 55.0  # nbr_adaptive: zenith angle where the horizon ramp starts [deg]
    grey_chroma: float = 0.10  # nbr_adaptive: pixels with (max−min)/max below this get no sun term [1]
    otsu_min: float = -0.05  # otsu: clamp of the Otsu threshold, lower end [1]
    otsu_max: float = 0.20  # otsu: clamp of the Otsu threshold, upper end [1]
    min_brightness: int = 8  # pixels darker than this (max channel) are not classified [0..255]
    min_sky_dn: float = 32.0  # flag underexposed when a camera's usable sky has a median brightest channel below this [0..255]
    max_side_px: int = 1600  # larger images are classified area-averaged to this long side; 0 = never [px]


@dataclass(frozen=True)
class PhotometricConfig:
    """Camera 2's colour response relative to camera 1 (see :mod:`cbh.pipeline.photometric`)."""

    correct: bool = True  # estimate, report and remove camera 2's gain / gamma / white balance [-]
    max_gain: float = 1.5  # flag exposure_mismatch beyond ×/÷ this gain (half a stop = 1.41) [1]
    max_gamma: float = 1.25  # … or beyond ×/÷ this tone-curve exponent [1]
    max_wb: float = 1.15  # … or beyond ×/÷ this red or blue white-balance gain [1]


@dataclass(frozen=True)
class LKConfig:
    """Pyramidal Lucas-Kanade on cloud pixels, started at the point-at-infinity prediction."""

    space: str = "warped"  # warped (track into image 2 warped onto camera 1's grid) or raw [-]
    max_points: int = 600  # corner features tracked (600 vs 1500: layers within 0.05 %, same dense map, half the time) [1]
    quality: float = 0.005  # goodFeaturesToTrack quality level [1]
    min_distance_px: int = 5  # spacing of features, at working size [px]
    window_px: int = 21  # LK window side [px]
    levels: int = 4  # pyramid levels above the base [1]
    fb_max_px: float = 0.5  # forward-backward disagreement allowed [px]


@dataclass(frozen=True)
class ORBConfig:
    """ORB features matched with Hamming distance, cross-checked."""

    max_features: int = 4000  # features per image [1]
    max_hamming: int = 60  # largest descriptor distance accepted [bits]
    max_parallax_deg: float = 25.0  # largest angle between the ray and its infinity prediction [deg]


@dataclass(frozen=True)
class DISConfig:
    """Dense DIS optical flow between image 1 and image 2 warped into camera 1's grid."""

    preset: str = "fast"  # ultrafast, fast or medium
    point_stride_px: int = 3  # keep every n-th dense correspondence in the point set [px]
    fb_max_px: float = 0.5  # forward-backward disagreement allowed [px]; 0 = no check


@dataclass(frozen=True)
class SweepConfig:
    """Dense plane sweep over horizontal planes (see :mod:`cbh.pipeline.sweep`)."""

    window_px: int = 9  # ZNCC window side, fine pass, at working size [px]
    coarse_factor: int = 2  # the coarse pass runs at working size / this [1]
    coarse_window_px: int = 7  # ZNCC window side, coarse pass, at coarse size [px]
    coarse_step_px: float = 1.0  # largest image shift between coarse planes, at coarse size [px]
    coarse_near_px: float = 32.0  # coarse planes with more parallax than this (working size) run at half the coarse size; 0 = off [px]
    coarse_near_rel: float = 0.03  # … and lie at most this share of their parallax apart (≥ one pixel at that size); 0 = one pixel [1]
    step_px: float = 1.0  # largest image shift between fine planes, at working size [px]
    step_rel: float = 0.05  # … or this share of their parallax, where that is more (a log lattice beyond step_px / step_rel); 0 = off [1]
    far_px: float = 6.0  # the fine pass sweeps every plane up to this parallax from infinity [px]
    min_height_m: float = 100.0  # lowest plane, above the ENU origin [m]; filtering's floor: lower clouds pinned to the
    #                             lowest plane were reported there with confidence 1 (a 200 m layer as 302 m)
    max_height_m: float = 15000.0  # highest plane, above the ENU origin [m]
    min_zncc: float = 0.6  # a pixel's best plane must correlate at least this well [1]
    min_texture: float = 1.0  # grey-level standard deviation in the window, at least [0..255]
    min_vote_fraction: float = 0.01  # a layer hypothesis needs this fraction of the cloud pixels' votes [1]
    extent_ratio: float = 0.1  # a hypothesis spans the planes whose votes stay above this × its peak [1]
    valley_ratio: float = 0.5  # two vote peaks are separate only if the valley is below this × the lower [1]
    aggregate_px: int = 31  # refine each pixel on its layer's cost summed over this box (1 = off) [px]
    label_px: int = 15  # box over which a pixel's cost decides its layer [px]
    far_aggregate_px: float = 8.0  # layers with less parallax than this get a box grown by this/parallax (≤ 4×); 0 = off [px]
    oblique_levels: int = 2  # pixels a plane step moves less (near the horizon) refined on their layer's box grown 2× per level:
    #                          below 1/√2 of the zenith's shift, 4× below 1/(2√2), … (≤ 4× in all); 0 = off [1]
    vote_percentile: float = 70.0  # fine layer votes: only pixels whose wide-box ZNCC is above this percentile [%]
    region_px: int = 64  # layers are also proposed per region of this side (a deck seen only through gaps); 0 = off [px]
    region_share: float = 0.1  # a region's layer needs this share of the region's votes [1]
    max_planes: int = 48  # fine planes at most (the step grows beyond) [1]
    regional_planes: int = 16  # fine planes the regions' own hypotheses may add beyond max_planes (the step kept) [1]
    map_cache_mb: float = 512.0  # remap tables of the planes used, kept for the next pairs (≈ 7 MB per fine plane at 960 px; per process); 0 = off [MB]
    point_stride_px: int = 3  # keep every n-th dense correspondence in the point set [px]


@dataclass(frozen=True)
class MatchingConfig:
    """Correspondences camera 1 → camera 2."""

    methods: tuple[str, ...] = ("lk", "sweep")  # any of: lk, orb, dis, sweep
    lk: LKConfig = field(default_factory=LKConfig)
    orb: ORBConfig = field(default_factory=ORBConfig)
    dis: DISConfig = field(default_factory=DISConfig)
    sweep: SweepConfig = field(default_factory=SweepConfig)


@dataclass(frozen=True)
class FilteringConfig:
    """Geometric rejection of correspondences (this replaces epipolar lines)."""

    max_miss_ratio: float = 0.01  # ray-miss distance / range from camera 1, at most [1]
    min_angle_deg: float = 0.1  # triangulation angle, at least [deg]
    min_height_m: float = 100.0  # height above the ENU origin, at least [m]
    max_height_m: float = 15000.0  # height above the ENU origin, at most [m]


@dataclass(frozen=True)
class HeightMapConfig:
    """Dense height map on camera 1's grid."""

    fill: str = "nearest"  # none or nearest (copy the nearest measured height, inside the cloud mask only)
    fill_max_px: float = 3.0  # fill only holes within this distance of a measurement, at working size [px]


@dataclass(frozen=True)
class LayersConfig:
    """Multi-layer histogram of log-height."""

    method: str = "histogram"  # histogram
    bin_log: float = 0.01  # histogram bin width in ln(height) (≈1 %) [1]
    smooth_log: float = 0.04  # Gaussian smoothing of the histogram in ln(height) [1]
    min_separation_log: float = 0.18  # peaks closer than this in ln(height) are one layer [1]
    resolve_px: float = 2.0  # layers closer than this in parallax (working size) are one to the sweep: a layer's band [px]
    valley_ratio: float = 0.5  # two peaks are separate only if the valley is below this × the lower peak [1]
    base_percentile: float = 10.0  # a layer's cloud-base height = this percentile of its points [%]
    noise_margin: float = 1.2  # the spread is "explained by noise" up to this × the predicted noise [1]
    min_points: int = 50  # a layer needs at least this many points [1]
    min_fraction: float = 0.04  # … and this fraction of all points [1]
    min_fraction_resolved: float = 0.005  # … or this, where the plane sweep resolved a layer of its own above its lowest [1]
    min_cover: float = 0.005  # … and this fraction of camera 1's usable sky [1]
    reject_aliases: bool = True  # drop a layer whose pixels correlate as well at a bigger layer's height (see cbh.pipeline.support) [1]


@dataclass(frozen=True)
class MotionConfig:
    """Cloud motion per layer and camera 2's clock offset, from the previous pair (see
    :mod:`cbh.pipeline.motion`; the previous pair itself is state, not configuration)."""

    enabled: bool = True  # track clouds between consecutive pairs (needs ``previous`` and capture times)
    max_gap_s: float = 200.0  # no motion across a longer time between consecutive pairs [s] (a 3-minute cadence and its jitter: docs/fehmarn.md)
    max_points: int = 500  # features tracked per camera (of the LK stereo matches) [1]
    window_px: int = 15  # LK window side, at working size [px]
    levels: int = 5  # pyramid levels above the base (cloud displacements up to ~2^levels windows) [1]
    fb_max_px: float = 0.3  # forward-backward disagreement allowed, at working size [px]
    min_tracks: int = 10  # a layer needs this many tracks for a motion [1]
    layer_tolerance_log: float = 0.1  # a track belongs to a layer within this |ln(h / h_layer)| (or 3 spreads) [1]
    clock_offset: bool = True  # estimate camera 2's clock offset and compensate it in the matching
    offset_history: int = 60  # pairs in the running (median) clock-offset estimate [1] (15 drifted 3 s at -90 s)
    offset_tolerance_s: float = 0.5  # flag ``clock_offset`` above this |offset| (cbh run: the pairing tolerance) [s]
    compensate_min_s: float = 0.2  # compensate camera 2 only above this |offset|: the estimate's systematic error reaches ≈ 0.15 s [s]
    rematch_s: float = 0.2  # match again in the same pair when the offset estimate moved by more [s]
    max_offset_s: float = 300.0  # a pair's offset estimate beyond this is not believed (real IP cameras: ±120 s; the real Fehmarn sky was matched at 150 s, a third of its pairs at 210 s) [s]
    offset_jump_s: float = 3.0  # two pairs in a row this far from the running offset (and agreeing): the clock jumped, start again [s]
    sky_check_pairs: int = 10  # with a known offset followed by the stereo tracks, the sky maps check it every this many pairs [1]
    sky_matching: bool = True  # with a long carry, match on the sky maps, each pixel carried by its own motion (.skyclock)
    sky_matching_min_px: float = 8.0  # … when |offset| × the fastest layer's rate exceeds this, at working size near the zenith [px]
    plane_compensation: bool = True  # the sweep compensates each plane with the motion of its own height (False, and on a torch device: every plane on one per-pixel compensated image)


@dataclass(frozen=True)
class GeometryCheckConfig:
    """Per-pair check of the correspondences against the station geometry (:mod:`.geocheck`)."""

    enabled: bool = True  # run the check (flag geometry_mismatch / identical_images)
    max_residual_px: float = 1.0  # median epipolar distance allowed at least, camera 2 working size [px]
    max_rotation_px: float = 0.25  # camera 2's fitted rotation against camera 1, as a shift at 45° off axis, at most [px]
    expected_miss_ratio: float = 0.0  # median epipolar angle the lens calibration is known to leave [rad]; 0 = none
    min_inlier_fraction: float = 0.5  # share of 2-D matches consistent with the geometry, at least [1]
    min_matches: int = 30  # fewer 2-D matches: no verdict [1]
    max_matches: int = 3000  # at most this many matches are judged (even subsample) [1]
    # a 2-D match is judged only where its windows in image 1 and in image 2 (warped onto camera 1's grid at
    # infinity) correlate at least this much (ZNCC, the matcher's window): LK locked onto a neighbouring blob of
    # fine texture passes its forward-backward check, not this (randomized 17849: 0.18–0.37 for those, 0.67–0.80
    # for the true ones); 0 = every match [1]
    min_zncc: float = 0.4
    # … and only where its window in image 1 is a corner: λ_min / λ_max of its structure tensor at least this
    # (:func:`~cbh.pipeline.match.corner_ratio`): along a line (a contrail) a window matches itself anywhere, and
    # LK slid 0.5–3° off the curves on a clear sky's contrails (randomized 17945, hard options: 0.02–0.09 for
    # those; cloud texture's true matches: 5th percentile 0.34–0.37); 0 = every match [1]
    min_corner_ratio: float = 0.1
    identical_max_dn: float = 0.5  # images closer than this mean grey difference are the same image [DN]


@dataclass(frozen=True)
class SunCheckConfig:
    """Detected vs predicted sun in each camera (:mod:`.sundetect`), when the time is known."""

    enabled: bool = True  # detect the sun and report sun_residual_deg
    search_deg: float = 15.0  # look for the sun this far from its predicted direction [deg]
    max_residual_deg: float = 1.0  # flag sun_misaligned beyond this [deg]


@dataclass(frozen=True)
class PipelineConfig:
    """The whole pipeline. ``working_radius_px``: images are downsampled (models scaled exactly)
    so that the 90° radius of each lens is at most this many pixels; 0 = full size."""

    working_radius_px: float = 480.0  # lens radius at 90 deg after downsampling [px]; 0 = no downsampling
    masks: MasksConfig = field(default_factory=MasksConfig)
    photometric: PhotometricConfig = field(default_factory=PhotometricConfig)
    segmentation: SegmentationConfig = field(default_factory=SegmentationConfig)
    matching: MatchingConfig = field(default_factory=MatchingConfig)
    filtering: FilteringConfig = field(default_factory=FilteringConfig)
    height_map: HeightMapConfig = field(default_factory=HeightMapConfig)
    layers: LayersConfig = field(default_factory=LayersConfig)
    motion: MotionConfig = field(default_factory=MotionConfig)
    geometry_check: GeometryCheckConfig = field(default_factory=GeometryCheckConfig)
    sun_check: SunCheckConfig = field(default_factory=SunCheckConfig)

    @classmethod
    def from_dict(cls, data: dict | None, where: str = "pipeline") -> "PipelineConfig":
        """Validate a ``[pipeline]`` table (missing keys take defaults)."""
        cfg = dataclass_from_table(cls, data or {}, where)
        _validate(cfg, where)
        return cfg

    def to_dict(self) -> dict:
        """Plain dict (TOML/JSON-ready) that :meth:`from_dict` reads back to an equal config."""
        return dataclass_to_dict(self)

    def replace(self, **changes) -> "PipelineConfig":
        """A copy with top-level fields replaced (validated)."""
        cfg = dataclasses.replace(self, **changes)
        _validate(cfg, "pipeline")
        return cfg


def _choice(where, value, valid):
    if value not in valid:
        raise ConfigError(f"{where}: unknown method {value!r} (valid: {', '.join(valid)})")


def _positive(where, value, strict=True):
    if (strict and not value > 0) or (not strict and not value >= 0):
        raise ConfigError(f"{where}: must be {'>' if strict else '>='} 0, got {value!r}")


def _validate(cfg: PipelineConfig, where: str) -> None:
    """Ranges and choices of every section (types and unknown keys: :func:`dataclass_from_table`);
    the first violation is a :class:`ConfigError` naming its key path under ``where``."""
    _positive(f"{where}.working_radius_px", cfg.working_radius_px, strict=False)
    segmenters, matchers, layer_methods = _registries()
    _check_masks(cfg.masks, f"{where}.masks")
    _check_photometric(cfg.photometric, f"{where}.photometric")
    _check_segmentation(cfg.segmentation, f"{where}.segmentation", segmenters)
    _check_matching(cfg.matching, f"{where}.matching", matchers)
    _check_sweep(cfg.matching.sweep, f"{where}.matching.sweep")
    _check_filtering(cfg.filtering, f"{where}.filtering")
    _choice(f"{where}.height_map.fill", cfg.height_map.fill, FILL_METHODS)
    _positive(f"{where}.height_map.fill_max_px", cfg.height_map.fill_max_px, strict=False)
    _check_geometry(cfg.geometry_check, f"{where}.geometry_check")
    _positive(f"{where}.sun_check.search_deg", cfg.sun_check.search_deg)
    _positive(f"{where}.sun_check.max_residual_deg", cfg.sun_check.max_residual_deg)
    _check_layers(cfg.layers, f"{where}.layers", layer_methods)
    _check_motion(cfg.motion, f"{where}.motion")


def _in_range(where: str, value, lo, hi, text: str) -> None:
    """``ConfigError`` "``where``: must be in ``text``" unless ``lo <= value <= hi`` (``text``
    states the bounds, e.g. "(0, 1]": the open ends are checked by the caller's ``lo``/``hi``)."""
    if not lo <= value <= hi:
        raise ConfigError(f"{where}: must be in {text}, got {value}")


def _odd(where: str, value, least: int) -> None:
    if value < least or value % 2 == 0:
        raise ConfigError(f"{where}: must be an odd number >= {least}, got {value}")


def _check_masks(m, where: str) -> None:
    if not 0 < m.max_zenith_deg <= 90:
        raise ConfigError(f"{where}.max_zenith_deg: must be in (0, 90], got {m.max_zenith_deg}")
    _positive(f"{where}.sun_radius_deg", m.sun_radius_deg, strict=False)
    if not 0 < m.glare_radius_deg <= 180:
        raise ConfigError(f"{where}.glare_radius_deg: must be in (0, 180], got {m.glare_radius_deg}")
    _in_range(f"{where}.saturation_level", m.saturation_level, 0, 255, "0..255")
    _positive(f"{where}.saturation_min_area_px", m.saturation_min_area_px, strict=False)
    _positive(f"{where}.saturation_grow_px", m.saturation_grow_px, strict=False)


def _check_photometric(ph, where: str) -> None:
    for k in ("max_gain", "max_gamma", "max_wb"):
        if not getattr(ph, k) >= 1.0:
            raise ConfigError(f"{where}.{k}: must be >= 1, got {getattr(ph, k)}")


def _check_segmentation(sg, where: str, segmenters) -> None:
    _choice(f"{where}.method", sg.method, tuple(segmenters))
    if not 50.0 <= sg.clear_percentile < 100.0:
        raise ConfigError(f"{where}.clear_percentile: must be in [50, 100), got {sg.clear_percentile}")
    _positive(f"{where}.min_gap", sg.min_gap)
    _positive(f"{where}.chroma_gap", sg.chroma_gap)
    _positive(f"{where}.texture_cv", sg.texture_cv, strict=False)
    _in_range(f"{where}.chroma_weight", sg.chroma_weight, 0, 1, "0..1")
    _positive(f"{where}.brightness_weight", sg.brightness_weight, strict=False)
    if not 0 < sg.score_threshold < 1:
        raise ConfigError(f"{where}.score_threshold: must be in (0, 1), got {sg.score_threshold}")
    _positive(f"{where}.max_side_px", sg.max_side_px, strict=False)
    _in_range(f"{where}.grey_chroma", sg.grey_chroma, 0, 1, "0..1")
    _positive(f"{where}.sun_scale_deg", sg.sun_scale_deg)
    if not 0 <= sg.horizon_start_deg < 90:
        raise ConfigError(f"{where}.horizon_start_deg: must be in [0, 90), got {sg.horizon_start_deg}")
    if sg.otsu_min > sg.otsu_max:
        raise ConfigError(f"{where}.otsu_min: must be <= otsu_max")
    _positive(f"{where}.min_sky_dn", sg.min_sky_dn, strict=False)


def _check_matching(mt, where: str, matchers) -> None:
    """The method list and the LK, ORB and DIS settings (the sweep: :func:`_check_sweep`)."""
    if not mt.methods:
        raise ConfigError(f"{where}.methods: give at least one method (valid: {', '.join(matchers)})")
    for i, name in enumerate(mt.methods):
        _choice(f"{where}.methods[{i}]", name, tuple(matchers))
    if len(set(mt.methods)) != len(mt.methods):
        raise ConfigError(f"{where}.methods: duplicate method in {list(mt.methods)}")
    lk, orb, dis = mt.lk, mt.orb, mt.dis
    _odd(f"{where}.lk.window_px", lk.window_px, 5)
    _positive(f"{where}.lk.max_points", lk.max_points)
    if not 0 < lk.quality <= 1:
        raise ConfigError(f"{where}.lk.quality: must be in (0, 1], got {lk.quality}")
    _positive(f"{where}.lk.min_distance_px", lk.min_distance_px, strict=False)
    _positive(f"{where}.orb.max_hamming", orb.max_hamming, strict=False)
    _positive(f"{where}.orb.max_parallax_deg", orb.max_parallax_deg)
    _positive(f"{where}.sweep.label_px", mt.sweep.label_px)
    _positive(f"{where}.lk.fb_max_px", lk.fb_max_px)
    _in_range(f"{where}.lk.levels", lk.levels, 0, 8, "0..8")
    _positive(f"{where}.orb.max_features", orb.max_features)
    _choice(f"{where}.dis.preset", dis.preset, ("ultrafast", "fast", "medium"))
    _positive(f"{where}.dis.point_stride_px", dis.point_stride_px)
    _positive(f"{where}.dis.fb_max_px", dis.fb_max_px, strict=False)
    _choice(f"{where}.lk.space", lk.space, ("warped", "raw"))


def _check_sweep(sw, where: str) -> None:
    for k in ("window_px", "coarse_window_px"):
        _odd(f"{where}.{k}", getattr(sw, k), 3)
    _in_range(f"{where}.coarse_factor", sw.coarse_factor, 1, 8, "1..8")
    _positive(f"{where}.far_px", sw.far_px, strict=False)
    _positive(f"{where}.coarse_near_px", sw.coarse_near_px, strict=False)
    _in_range(f"{where}.coarse_near_rel", sw.coarse_near_rel, 0.0, 0.25, "0..0.25")
    _in_range(f"{where}.step_rel", sw.step_rel, 0.0, 0.25, "0..0.25")
    for k in ("coarse_step_px", "step_px", "min_height_m", "max_planes", "point_stride_px"):
        _positive(f"{where}.{k}", getattr(sw, k))
    if not sw.min_height_m < sw.max_height_m:
        raise ConfigError(f"{where}.min_height_m: must be < max_height_m")
    if not -1.0 <= sw.min_zncc < 1.0:
        raise ConfigError(f"{where}.min_zncc: must be in [-1, 1), got {sw.min_zncc}")
    _positive(f"{where}.region_px", sw.region_px, strict=False)
    for k in ("min_vote_fraction", "extent_ratio", "valley_ratio", "region_share"):
        if not 0 < getattr(sw, k) <= 1:
            raise ConfigError(f"{where}.{k}: must be in (0, 1], got {getattr(sw, k)}")
    _positive(f"{where}.min_texture", sw.min_texture, strict=False)
    _positive(f"{where}.far_aggregate_px", sw.far_aggregate_px, strict=False)
    if not 0 <= sw.oblique_levels <= 2:
        raise ConfigError(f"{where}.oblique_levels: must be 0, 1 or 2, got {sw.oblique_levels}")
    if not 0 <= sw.vote_percentile < 100:
        raise ConfigError(f"{where}.vote_percentile: must be in [0, 100), got {sw.vote_percentile}")
    _positive(f"{where}.map_cache_mb", sw.map_cache_mb, strict=False)
    _positive(f"{where}.regional_planes", sw.regional_planes, strict=False)


def _check_filtering(fl, where: str) -> None:
    _positive(f"{where}.max_miss_ratio", fl.max_miss_ratio)
    _positive(f"{where}.min_angle_deg", fl.min_angle_deg, strict=False)
    if not fl.min_height_m < fl.max_height_m:
        raise ConfigError(f"{where}.min_height_m: must be < max_height_m")
    _positive(f"{where}.min_height_m", fl.min_height_m)


def _check_geometry(gc, where: str) -> None:
    _positive(f"{where}.max_residual_px", gc.max_residual_px)
    _positive(f"{where}.max_rotation_px", gc.max_rotation_px)
    _in_range(f"{where}.min_inlier_fraction", gc.min_inlier_fraction, 0, 1, "0..1")
    _positive(f"{where}.expected_miss_ratio", gc.expected_miss_ratio, strict=False)
    _positive(f"{where}.min_matches", gc.min_matches)
    _positive(f"{where}.max_matches", gc.max_matches)
    _positive(f"{where}.identical_max_dn", gc.identical_max_dn, strict=False)
    _in_range(f"{where}.min_zncc", gc.min_zncc, 0, 1, "0..1")
    _in_range(f"{where}.min_corner_ratio", gc.min_corner_ratio, 0, 1, "0..1")


def _check_layers(ly, where: str, layer_methods) -> None:
    _choice(f"{where}.method", ly.method, tuple(layer_methods))
    for k in ("bin_log", "smooth_log", "min_separation_log"):
        _positive(f"{where}.{k}", getattr(ly, k))
    for k in ("min_fraction", "min_fraction_resolved", "min_cover"):
        if not 0 <= getattr(ly, k) < 1:
            raise ConfigError(f"{where}.{k}: must be in [0, 1), got {getattr(ly, k)}")
    if not ly.noise_margin >= 1.0:
        raise ConfigError(f"{where}.noise_margin: must be >= 1, got {ly.noise_margin}")
    _in_range(f"{where}.base_percentile", ly.base_percentile, 0, 50, "0..50")
    if not 0 < ly.valley_ratio <= 1:
        raise ConfigError(f"{where}.valley_ratio: must be in (0, 1], got {ly.valley_ratio}")


def _check_motion(mo, where: str) -> None:
    for k in ("max_gap_s", "max_points", "fb_max_px", "min_tracks", "layer_tolerance_log", "offset_history",
              "offset_tolerance_s", "rematch_s", "max_offset_s", "offset_jump_s", "sky_matching_min_px", "sky_check_pairs"):
        _positive(f"{where}.{k}", getattr(mo, k))
    _positive(f"{where}.compensate_min_s", mo.compensate_min_s, strict=False)
    _odd(f"{where}.window_px", mo.window_px, 5)
    _in_range(f"{where}.levels", mo.levels, 0, 8, "0..8")
