"""Scoring a pair result against simulator ground truth (the issue-4 accuracy bars).

Used by the tests and by ``benchmarks/eval_scenes.py``. Dense-map numbers are over the pixels
that are cloud in truth *inside the analysed field of view* (zenith ≤ the pipeline's
``masks.max_zenith_deg``): the pipeline masks everything beyond it by design.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from cbh.result import PairResult
from cbh.geometry.station import Station, rotation_from_angles

__all__ = ["SceneScore", "score_pair", "station_variant", "LayerScore", "layer_tolerance", "score_layers"]


@dataclass(frozen=True)
class SceneScore:
    truth_m: list[float]  # true layer heights, ascending [m]
    found_m: list[float]  # reported cloud-base heights, ascending [m]
    layer_error: list[float]  # |found − truth| / truth per layer (when the counts agree)
    dense_mdape: float  # median |h − h_true| / h_true over covered true-cloud pixels
    dense_coverage: float  # covered / true-cloud pixels in the analysed field

    @property
    def layers_match(self) -> bool:
        return len(self.truth_m) == len(self.found_m)


def station_variant(station: Station, baseline_m: float, yaw2_deg: float, camera: str = "cam2") -> Station:
    """``station`` with ``camera`` moved to ``baseline_m`` east of the origin and yawed ``yaw2_deg``."""
    cams = dict(station.cameras)
    cams[camera] = replace(cams[camera], position_m=np.array([baseline_m, 0.0, 0.0]),
                           R_world_from_cam=rotation_from_angles(yaw2_deg))
    return replace(station, cameras=cams)


def score_pair(result: PairResult, truth_height_m: np.ndarray, truth_layers_m, fov: np.ndarray,
               dense_layers_m=None) -> SceneScore:
    """Score ``result`` against camera 1's true height map (H, W) and true layer heights.

    ``fov``: camera 1's analysed field of view (H, W) bool. ``dense_layers_m``: count only
    the pixels of these true layers in the dense-map numbers (None = all).
    """
    truth = sorted(float(h) for h in truth_layers_m)
    found = [float(l.height_m) for l in result.layers]
    err = [abs(f - t) / t for f, t in zip(found, truth)] if len(found) == len(truth) else []
    cloud = np.isfinite(truth_height_m) & fov
    if dense_layers_m is not None:
        cloud &= np.isin(truth_height_m, np.asarray(dense_layers_m, np.float32))
    have = cloud & np.isfinite(result.height_map)
    ape = np.abs(result.height_map[have] - truth_height_m[have]) / truth_height_m[have]
    return SceneScore(
        truth_m=truth, found_m=found, layer_error=err,
        dense_mdape=float(np.median(ape)) if ape.size else float("nan"),
        dense_coverage=float(have.sum() / cloud.sum()) if cloud.any() else float("nan"),
    )


@dataclass(frozen=True)
class LayerScore:
    """Reported layers against the visible true layers of one randomized sky.

    A true layer is *expected* when it is the visible cloud on at least ``expect_share`` of
    camera 1's analysed field, *optional* when on ``optional_share`` … ``expect_share`` (a
    sliver: found or not, it is no error). A reported layer matches a true one when within
    ``tolerance(h)`` of it; an unmatched reported layer is *spurious*.

    *Reported as one* (``merged``): where two or more true layers (expected or optional) lie in
    one reported layer's band (``Layer.height_lo_m`` … ``height_hi_m``: the heights the pair
    cannot tell apart from it; each true layer within its ``tolerance(h)`` of the band), those
    of them that no other reported layer is within tolerance of are found as that one layer,
    which is then not spurious. A single true layer in a band is scored by the rule above alone.
    """

    expected_m: list[float]
    found_m: list[float]
    matched: dict[float, float]  # expected height → reported height
    spurious_m: list[float]
    tolerance: dict[float, float]  # expected height → relative tolerance
    merged: dict[float, float] = field(default_factory=dict)  # expected height → the layer it was reported as one with
    cloud_fraction: float = 0.0  # share of the analysed field that is cloud in truth

    @property
    def missed_m(self) -> list[float]:
        return [h for h in self.expected_m if h not in self.matched and h not in self.merged]


def layer_tolerance(height_m: float, baseline_m: float, pixel_rad: float, floor: float = 0.05,
                    pixel_error: float = 0.5) -> float:
    """Relative height tolerance max(floor, H·δθ/B) with δθ = ``pixel_error`` pixels of
    ``pixel_rad`` [rad/px]: the parallax error a stereo pair cannot resolve (δH ≈ H² δθ / B)."""
    return max(floor, height_m * pixel_error * pixel_rad / baseline_m)


def score_layers(result: PairResult, truth_height_m: np.ndarray, fov: np.ndarray, baseline_m: float,
                 pixel_rad: float, expect_share: float = 0.03, optional_share: float = 0.003) -> LayerScore:
    """Score ``result``'s layers against camera 1's true height map inside ``fov`` (see :class:`LayerScore`)."""
    vals, counts = np.unique(truth_height_m[fov & np.isfinite(truth_height_m)], return_counts=True)
    n = max(int(fov.sum()), 1)
    expected = [float(v) for v, c in zip(vals, counts) if c / n >= expect_share]
    optional = [float(v) for v, c in zip(vals, counts) if optional_share <= c / n < expect_share]
    tol = {h: layer_tolerance(h, baseline_m, pixel_rad) for h in expected + optional}
    found = sorted(float(l.height_m) for l in result.layers)
    matched: dict[float, float] = {}
    spurious = []
    for f in found:
        near = [h for h in expected + optional if abs(f - h) / h <= tol[h]]
        h = min(near, key=lambda h: abs(f - h) / h) if near else None
        if h is None:
            spurious.append(f)
        elif h in matched:  # a second report of one layer (split): the farther one is spurious
            spurious.append(max(f, matched[h], key=lambda x: abs(x - h)))
            matched[h] = min(f, matched[h], key=lambda x: abs(x - h))
        elif h in expected:
            matched[h] = f
    merged: dict[float, float] = {}
    for L in result.layers:  # true layers closer than the pair resolves, reported as one (see LayerScore)
        lo, hi, f = float(L.height_lo_m), float(L.height_hi_m), float(L.height_m)
        if not (math.isfinite(lo) and lo <= f <= hi):
            continue
        inside = [h for h in expected + optional if lo * (1 - tol[h]) <= h <= hi * (1 + tol[h])]
        # the true layers in the band that no other reported layer accounts for
        free = [h for h in inside if not any(abs(g - h) / h <= tol[h] for g in found if g != f)]
        if len(inside) < 2 or not free:
            continue
        merged.update({h: f for h in free if h in expected and h not in matched and h not in merged})
        if f in spurious:
            spurious.remove(f)
    return LayerScore(expected_m=expected, found_m=found, matched=matched, spurious_m=spurious,
                      tolerance={h: tol[h] for h in expected}, merged=merged, cloud_fraction=float(counts.sum()) / n)
