"""One strict config reader (cbh/tomlio.py) behind station, [pipeline], scene and [service]:
the same rules everywhere: unknown keys and non-finite numbers name the key path."""
from __future__ import annotations

import math
import re

import pytest

from cbh.errors import ConfigError
from cbh.geometry.station import parse_station
from cbh.live.service import ServiceConfig
from cbh.pipeline import PipelineConfig
from cbh.sim import parse_scene

from .conftest import REPO


def _station(**station):
    base = {"name": "s", "latitude_deg": 1.0, "longitude_deg": 2.0, "altitude_m": 3.0}
    cams = [{"name": f"c{i}", "position_m": [50.0 * i, 0.0, 0.0],
             "intrinsics": {"model": "equidistant", "width": 480, "height": 480, "center_xy": [239.5, 239.5],
                            "radius_px": 230.0}} for i in (0, 1)]
    return {"station": {**base, **station}, "cameras": cams}


READERS = {
    "station": lambda d: parse_station(_station(**d), base_dir=REPO),
    "pipeline": lambda d: PipelineConfig.from_dict({"masks": d}),
    "scene": lambda d: parse_scene({"layers": [{"coverage": 0.5, "height_m": 1000.0, **d}]}),
    "service": lambda d: ServiceConfig.from_dict(d),
}
FINITE = {
    "station": ("altitude_m", "station.altitude_m"),
    "pipeline": ("max_zenith_deg", "pipeline.masks.max_zenith_deg"),
    "scene": ("height_m", "layers[0].height_m"),
    "service": ("cadence_s", "service.cadence_s"),
}


@pytest.mark.parametrize("reader", list(READERS))
@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_non_finite_numbers_are_refused_naming_the_key(reader, bad):
    key, path = FINITE[reader]
    with pytest.raises(ConfigError, match=re.escape(path) + ": must be finite"):
        READERS[reader]({key: bad})


@pytest.mark.parametrize("reader, path", [("station", "station.altitdue_m"), ("pipeline", "pipeline.masks.altitdue_m"),
                                          ("scene", "layers[0].altitdue_m"), ("service", "service.altitdue_m")])
def test_unknown_keys_name_the_key_path(reader, path):
    with pytest.raises(ConfigError, match=re.escape(path) + ": unknown key"):
        READERS[reader]({"altitdue_m": 1.0})


@pytest.mark.parametrize("reader, key, path", [("pipeline", "max_zenith_deg", "pipeline.masks.max_zenith_deg"),
                                               ("service", "cadence_s", "service.cadence_s"),
                                               ("scene", "height_m", "layers[0].height_m")])
def test_booleans_are_not_numbers(reader, key, path):
    with pytest.raises(ConfigError, match=re.escape(path) + ": expected a number"):
        READERS[reader]({key: True})
