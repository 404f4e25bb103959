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


@pytest.mark.parametrize(
    "data, path",
    [
        # values OpenCV or the code reject only at the first pair (a cv2.error / ZeroDivisionError
        # traceback), or that silently drop every layer: refused at load, naming the key
        ({"matching": {"lk": {"quality": 0.0}}}, "pipeline.matching.lk.quality"),
        ({"matching": {"lk": {"quality": 1.5}}}, "pipeline.matching.lk.quality"),
        ({"matching": {"lk": {"min_distance_px": -1}}}, "pipeline.matching.lk.min_distance_px"),
        ({"segmentation": {"sun_scale_deg": 0.0}}, "pipeline.segmentation.sun_scale_deg"),
        ({"segmentation": {"horizon_start_deg": 95.0}}, "pipeline.segmentation.horizon_start_deg"),
        ({"matching": {"orb": {"max_parallax_deg": -1.0}}}, "pipeline.matching.orb.max_parallax_deg"),
        ({"matching": {"orb": {"max_hamming": -1}}}, "pipeline.matching.orb.max_hamming"),
        ({"matching": {"sweep": {"label_px": 0}}}, "pipeline.matching.sweep.label_px"),
        ({"matching": {"sweep": {"oblique_levels": 3}}}, "pipeline.matching.sweep.oblique_levels"),
        ({"layers": {"min_cover": 2.0}}, "pipeline.layers.min_cover"),
        ({"layers": {"min_fraction": -0.1}}, "pipeline.layers.min_fraction"),
        ({"masks": {"saturation_grow_px": -3}}, "pipeline.masks.saturation_grow_px"),
        ({"masks": {"saturation_min_area_px": -1}}, "pipeline.masks.saturation_min_area_px"),
    ],
)
def test_out_of_range_values_are_refused_at_load(data, path):
    with pytest.raises(ConfigError, match=path.replace(".", r"\.")):
        PipelineConfig.from_dict(data)
