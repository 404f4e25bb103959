"""Cloud-base heights from one synchronized frame pair, on the raw fisheye images.

>>> from cbh.pipeline import Pipeline, PipelineConfig            # doctest: +SKIP
>>> cfg = PipelineConfig.from_dict(station.sections.get("pipeline", {}))   # doctest: +SKIP
>>> result = Pipeline(station, "cam1,cam2", cfg).process(img1, img2, time_utc, channels="bgr")   # doctest: +SKIP

Stages: :mod:`.masks`, :mod:`.segment`, :mod:`.match`, :mod:`.heightmap`, :mod:`.layers`,
orchestrated by :class:`Pipeline` (:mod:`.run`); configuration in :mod:`.config`.
"""
from cbh.pipeline import config as _config
from cbh.pipeline.config import *  # noqa: F401,F403 - every stage config, listed once in config.__all__
from cbh.pipeline.layers import LAYER_METHODS
from cbh.pipeline.match import MATCHERS, PairGeometry
from cbh.pipeline.run import Pipeline, working_factor
from cbh.pipeline.segment import SEGMENTERS

__all__ = ["Pipeline", *_config.__all__, "PairGeometry", "SEGMENTERS", "MATCHERS", "LAYER_METHODS", "working_factor"]
