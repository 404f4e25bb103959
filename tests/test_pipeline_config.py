"""PipelineConfig: strict keys with key paths, registries by name, round trip."""
import pytest

from cbh.errors import ConfigError
from cbh.pipeline import PipelineConfig


def test_defaults_round_trip():
    cfg = PipelineConfig.from_dict({})
    d = cfg.to_dict()
    assert d["matching"]["methods"] == ["lk", "sweep"]
    assert PipelineConfig.from_dict(d) == cfg


def test_override_nested_value():
    cfg = PipelineConfig.from_dict({"matching": {"methods": ["orb"], "lk": {"window_px": 31}}, "masks": {"max_zenith_deg": 70}})
    assert cfg.matching.methods == ("orb",)
    assert cfg.matching.lk.window_px == 31
    assert cfg.masks.max_zenith_deg == 70.0


@pytest.mark.parametrize(
    "data, path",
    [
        ({"matching": {"lk": {"window": 21}}}, "pipeline.matching.lk.window"),
        ({"bogus": 1}, "pipeline.bogus"),
        ({"layers": {"min_points": "many"}}, "pipeline.layers.min_points"),
        ({"matching": {"lk": {"window_px": 20}}}, "pipeline.matching.lk.window_px"),
        ({"filtering": {"min_height_m": 5000.0, "max_height_m": 1000.0}}, "pipeline.filtering.min_height_m"),
        ({"masks": "yes"}, "pipeline.masks"),
    ],
)
def test_bad_keys_name_the_path(data, path):
    with pytest.raises(ConfigError) as exc:
        PipelineConfig.from_dict(data)
    assert path in str(exc.value)


def test_unknown_methods_list_valid_names():
    with pytest.raises(ConfigError) as exc:
        PipelineConfig.from_dict({"segmentation": {"method": "cnn"}})
    assert "nbr_adaptive" in str(exc.value) and "otsu" in str(exc.value)
    with pytest.raises(ConfigError) as exc:
        PipelineConfig.from_dict({"matching": {"methods": ["lk", "sift"]}})
    assert "pipeline.matching.methods[1]" in str(exc.value) and "dis" in str(exc.value)
