"""The objects every stage hands on: a camera frame, and the result of one frame pair.

The pipeline (:mod:`cbh.pipeline`) produces one :class:`PairResult` per synchronized pair;
the service, the MCAP recorder, the Rerun viewer and the exporters all consume it.
Frames and units: docs/conventions.md.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from datetime import datetime, timezone

import numpy as np

__all__ = ["numeric_diagnostics", "Frame", "Layer", "Histogram", "PointSet", "PairResult", "Enlarged", "to_ns", "from_ns", "require_time"]


def require_time(result: "PairResult", what: str) -> datetime:
    """The result's capture time, or :class:`cbh.errors.RecordingError` naming ``what`` when it is
    unknown: recordings, the Rerun time line and the layer tables place every pair at its time,
    and cbh never invents one."""
    if result.time_utc is None:
        from cbh.errors import RecordingError

        raise RecordingError(f"{what}: the pair's capture time is unknown (flag time_unknown); it cannot be "
                             "placed on a time line: give the time (ISO 8601 with Z) when processing it")
    return result.time_utc


def to_ns(t: datetime) -> int:
    """UTC datetime → integer nanoseconds since the Unix epoch."""
    if t is None:
        raise ValueError("time unknown (None): cannot convert to nanoseconds since the epoch")
    if t.tzinfo is None:
        raise ValueError("naive datetime: cbh times must be timezone-aware UTC")
    delta = t - datetime(1970, 1, 1, tzinfo=timezone.utc)
    return (delta.days * 86_400 + delta.seconds) * 1_000_000_000 + delta.microseconds * 1_000


def from_ns(ns: int) -> datetime:
    """Integer nanoseconds since the Unix epoch → UTC datetime (microsecond precision)."""
    from datetime import timedelta

    return datetime(1970, 1, 1, tzinfo=timezone.utc) + timedelta(microseconds=int(ns) // 1_000)


@dataclass
class Frame:
    """One image from one camera.

    Attributes
    ----------
    camera : str
        Station camera name.
    time_utc : datetime
        Capture time, timezone-aware UTC.
    image : ndarray, shape (H, W, 3), uint8, or None
        Decoded BGR image; None while still encoded (sources may defer decoding).
    encoded : bytes or None
        The bytes as received (e.g. JPEG), recorded without re-encoding.
    format : str
        Format of ``encoded`` ("jpeg", "png").
    sequence : int
        Per-source frame counter.
    received_s : float or None
        ``time.monotonic()`` when the frame was received (for latency), None = unknown.
    """

    camera: str
    time_utc: datetime
    image: np.ndarray | None
    encoded: bytes | None = None
    format: str = "jpeg"
    sequence: int = 0
    received_s: float | None = None


@dataclass(frozen=True)
class Layer:
    """One cloud layer found in a frame pair (heights above the ENU origin)."""

    height_m: float  # cloud-base height: robust low statistic of the layer [m]
    median_height_m: float  # median height of the layer's points [m]
    spread_m: float  # robust spread (1.4826 · MAD) of the layer's heights [m]
    cover: float  # fraction of camera 1's usable sky covered by this layer, 0..1
    points: int  # number of triangulated points supporting it
    confidence: float  # 0..1
    altitude_m: float = math.nan  # cloud-base altitude above mean sea level [m] (height_m + station altitude)
    motion_east_ms: float = math.nan  # layer motion over the ground, east component [m/s], NaN = unknown
    motion_north_ms: float = math.nan  # layer motion over the ground, north component [m/s], NaN = unknown
    motion_spread_ms: float = math.nan  # robust spread (1.4826 · MAD) of the layer's track velocities [m/s], NaN = unknown
    motion_tracks: int = 0  # feature tracks (both cameras) behind the layer's motion [1]; 0 = no motion
    # a camera network's layer (cbh.pipeline.network): each pair's part, as (pair "a+b", points,
    # height_m, weight share 0..1); () for a pair's own layer
    support: tuple = ()
    # the heights this layer stands for [m]: its points' 10–90 % range widened to what the pair
    # cannot tell apart from it (cbh.pipeline.layers.layer_band): a second layer in this band is
    # reported as part of this one; NaN = unknown
    height_lo_m: float = math.nan
    height_hi_m: float = math.nan

    def to_dict(self) -> dict:
        """JSON-ready: floats, with None where a value is unknown (NaN)."""
        return {
            "height_m": _num(self.height_m),
            "altitude_m": _num(self.altitude_m),
            "median_height_m": _num(self.median_height_m),
            "spread_m": _num(self.spread_m),
            "height_lo_m": _num(self.height_lo_m),
            "height_hi_m": _num(self.height_hi_m),
            "cover": _num(self.cover),
            "points": int(self.points),
            "confidence": _num(self.confidence),
            "motion_east_ms": _num(self.motion_east_ms),
            "motion_north_ms": _num(self.motion_north_ms),
            "motion_spread_ms": _num(self.motion_spread_ms),
            "motion_tracks": int(self.motion_tracks),
            **({"support": {p: {"points": int(n), "height_m": _num(h), "weight": _num(w)}
                            for p, n, h, w in self.support}} if self.support else {}),
        }


def numeric_diagnostics(diagnostics: dict) -> dict[str, float]:
    """The scalar entries of ``PairResult.diagnostics`` (what every file format stores; a
    network's ``mismatched_cameras`` list is also stored as its ``geometry_mismatch_<camera>``
    scalars)."""
    return {str(k): float(v) for k, v in diagnostics.items() if not isinstance(v, (list, tuple, str))}


def _num(v: float) -> float | None:
    v = float(v)
    return v if math.isfinite(v) else None


@dataclass(frozen=True)
class Histogram:
    """Height histogram of the valid points: ``counts[i]`` in [edges_m[i], edges_m[i+1])."""

    edges_m: np.ndarray  # shape (B + 1,), float64 [m]
    counts: np.ndarray  # shape (B,), float64 (weights may be fractional)


@dataclass(frozen=True)
class PointSet:
    """Triangulated correspondences that passed every check (N points)."""

    xyz_m: np.ndarray  # shape (N, 3), float32, ENU [m]
    miss_m: np.ndarray  # shape (N,), float32 [m]
    px1: np.ndarray  # shape (N, 2), float32, pixels in camera 1
    px2: np.ndarray  # shape (N, 2), float32, pixels in camera 2
    layer: np.ndarray  # shape (N,), int16, index into PairResult.layers, -1 = none

    @property
    def height_m(self) -> np.ndarray:
        return self.xyz_m[:, 2]

    def __len__(self) -> int:
        return int(self.xyz_m.shape[0])

    @staticmethod
    def empty() -> "PointSet":
        z2 = np.zeros((0, 2), np.float32)
        return PointSet(np.zeros((0, 3), np.float32), np.zeros(0, np.float32), z2, z2.copy(), np.zeros(0, np.int16))


@dataclass(frozen=True)
class Enlarged:
    """A map kept at the resolution it was computed at, standing for its nearest-neighbour
    enlargement to ``(width, height)``: the pipeline's height map and cloud masks are made at
    working size (half the camera's, by default) and shown on the camera's full grid.

    :class:`PairResult` makes the full-size array on first access only; a consumer that can use
    the small map with its whole ``factor`` (the MCAP recorder stores the height map decimated)
    skips the enlargement (3–4 ms per 1920 px map) and the check that it is one (5 ms).
    """

    small: np.ndarray  # (h, w)
    width: int
    height: int

    @property
    def factor(self) -> int:
        """f when the full map is the small one's f × f blocks exactly (width = f·w, height = f·h), else 0."""
        if self.small.ndim < 2:
            return 0
        h, w = self.small.shape[:2]
        f = self.width // w if w else 0
        return f if f >= 1 and (w * f, h * f) == (self.width, self.height) else 0

    def full(self) -> np.ndarray:
        """The enlarged array (a new one: INTER_NEAREST, so whole factors repeat blocks exactly)."""
        import cv2

        a = self.small
        if a.shape[:2] == (self.height, self.width):
            return a.copy()
        if a.dtype == bool:
            return cv2.resize(a.view(np.uint8), (self.width, self.height), interpolation=cv2.INTER_NEAREST).view(bool)
        return cv2.resize(a, (self.width, self.height), interpolation=cv2.INTER_NEAREST)


@dataclass
class PairResult:
    """Everything cbh knows about one synchronized frame pair.

    Attributes
    ----------
    time_utc : datetime or None
        Capture time of camera 1's frame; None = unknown (flag ``time_unknown``).
    cameras : tuple of str
        (camera 1, camera 2) names; a camera network's result: every camera used, the
        reference (whose grid the height map is on) first.
    layers : list of Layer
        Ascending by ``height_m``; empty for a clear sky.
    histogram : Histogram
    points : PointSet
    height_map : ndarray, shape (H, W), float32
        Cloud-base height above the ENU origin on camera 1's pixel grid [m], NaN where unknown.
        May be given as an :class:`Enlarged` map: read, it is the full-size array (made on first
        access, and from then on the value); :meth:`enlarged` hands the small one, until then,
        to a consumer that can use it.
    cloud_masks : dict of str → ndarray (H, W) bool
        Each camera's cloud mask on its full pixel grid (values may be given as :class:`Enlarged`
        too).
    cloud_fraction : dict of str → float
        Cloud fraction of each camera's usable sky, 0..1.
    timing_ms : dict of str → float
        Wall time of each pipeline stage [ms].
    flags : list of str
        Quality flags: names of :class:`cbh.flags.Flag` (fixed bits in every file format).
    diagnostics : dict of str → float
        Named scalar quality measures of the pair (e.g. the geometry self-check's residual,
        the sun residual, the clock offset, the photometric difference); each key carries its
        unit in its name (``_deg``, ``_px``, ``_s``) and is documented where it is computed.
    state : object or None
        Temporal state to hand to the next pair's processing (the pipeline's
        :class:`cbh.pipeline.motion.PairState`: previous frames, running clock-offset estimate);
        not recorded or exported. None when the producer keeps no state.
    """

    time_utc: datetime | None
    cameras: tuple[str, str]
    layers: list[Layer]
    histogram: Histogram
    points: PointSet
    height_map: np.ndarray
    cloud_masks: dict[str, np.ndarray]
    cloud_fraction: dict[str, float]
    timing_ms: dict[str, float] = field(default_factory=dict)
    flags: list[str] = field(default_factory=list)
    matches: dict[str, np.ndarray] = field(default_factory=dict)  # method → (M, 4) x1,y1,x2,y2 kept matches (for display)
    diagnostics: dict[str, float] = field(default_factory=dict)
    state: object = field(default=None, repr=False, compare=False)
    # a camera network's result (cbh.pipeline.network): each processed pair's own result, by
    # "<a>+<b>"; not recorded (its numbers are in diagnostics)
    pairs: dict = field(default_factory=dict, repr=False, compare=False)

    def enlarged(self, name: str, camera: str | None = None) -> "Enlarged | None":
        """The :class:`Enlarged` map behind ``height_map`` (or camera ``camera``'s cloud mask,
        ``name="cloud_masks"``) while it has not been read at full size, else None (once read,
        the full array is the value, so that edits to it are what the recorder writes)."""
        if name == "height_map":
            v = self.__dict__.get("_height_map")
        else:
            v = self.__dict__.get("_cloud_masks", {}).get(camera)
        return v if isinstance(v, Enlarged) else None

    def summary(self) -> dict:
        """The JSON object ``cbh pair --json`` prints."""
        h = self.points.height_m.astype(np.float64)
        n = len(h)
        return {
            "time_utc": self.time_utc.isoformat().replace("+00:00", "Z") if self.time_utc is not None else None,
            "layers": [l.to_dict() for l in self.layers],
            "points": {
                "count": n,
                "mean_height_m": float(h.mean()) if n else None,
                "std_height_m": float(h.std()) if n else None,
                "p5_height_m": float(np.percentile(h, 5)) if n else None,
                "median_miss_m": float(np.median(self.points.miss_m)) if n else None,
            },
            "cloud_fraction": {k: float(v) for k, v in self.cloud_fraction.items()},
            "timing_ms": {k: round(float(v), 3) for k, v in self.timing_ms.items()},
            "flags": list(self.flags),
            "diagnostics": {k: (list(v) if isinstance(v, (list, tuple)) else _num(v))
                            for k, v in self.diagnostics.items()},
            **({"pairs": {name: {"cameras": list(r.cameras), "layers": [l.to_dict() for l in r.layers],
                                 "flags": list(r.flags)} for name, r in self.pairs.items()}} if self.pairs else {}),
        }


def _full_height_map(self) -> np.ndarray:
    v = self.__dict__["_height_map"]
    if isinstance(v, Enlarged):  # the full array becomes the value: edits to it are the result's
        v = self.__dict__["_height_map"] = v.full()
    return v


def _set_height_map(self, value) -> None:
    self.__dict__["_height_map"] = value


def _full_cloud_masks(self) -> dict:
    v = self.__dict__["_cloud_masks"]
    if any(isinstance(m, Enlarged) for m in v.values()):
        v = self.__dict__["_cloud_masks"] = {k: (m.full() if isinstance(m, Enlarged) else m) for k, m in v.items()}
    return v


def _set_cloud_masks(self, value) -> None:
    self.__dict__["_cloud_masks"] = value


# full-size on first access (see Enlarged); set after the dataclass made its __init__, whose
# assignments then go through the setters
PairResult.height_map = property(_full_height_map, _set_height_map, doc="Camera 1's full-size height map [m].")
PairResult.cloud_masks = property(_full_cloud_masks, _set_cloud_masks, doc="Each camera's full-size cloud mask.")
