"""Cloud-base heights from one synchronized frame pair, on the raw fisheye images.

>>> from cbh.pipeline import Pipeline, PipelineConfig            # doctest: +SKIP
>>> cfg = PipelineConfig.from_dict(station.sections.get("pipeline", {}))   # doctest: +SKIP
>>> result = Pipeline(station, "cam1,cam2", cfg).process(img1, img2, time_utc)   # doctest: +SKIP

Stages: :mod:`.masks`, :mod:`.segment`, :mod:`.match`, :mod:`.heightmap`, :mod:`.layers`,
orchestrated by :class:`Pipeline` (:mod:`.run`); configuration in :mod:`.config`.
"""
from .config import (
    DISConfig,
    FilteringConfig,
    HeightMapConfig,
    LayersConfig,
    LKConfig,
    MasksConfig,
    MatchingConfig,
    ORBConfig,
    PipelineConfig,
    SegmentationConfig,
    SweepConfig,
)
from .layers import LAYER_METHODS
from .match import MATCHERS, PairGeometry
from .run import Pipeline, working_factor
from .segment import SEGMENTERS

__all__ = [
    "Pipeline",
    "PipelineConfig",
    "MasksConfig",
    "SegmentationConfig",
    "LKConfig",
    "ORBConfig",
    "DISConfig",
    "SweepConfig",
    "MatchingConfig",
    "FilteringConfig",
    "HeightMapConfig",
    "LayersConfig",
    "PairGeometry",
    "SEGMENTERS",
    "MATCHERS",
    "LAYER_METHODS",
    "working_factor",
]
