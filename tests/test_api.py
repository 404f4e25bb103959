"""The Python API a forecaster uses: ``import cbh`` (light), paths or arrays with a declared channel
order, greyscale refused, unknown time kept unknown, ``cbh.layer_table``, and the README example."""
from __future__ import annotations

import dataclasses
import math
import subprocess
import sys
from datetime import datetime, timezone

import cv2
import numpy as np
import pytest

import cbh
from cbh.errors import ImageError, InputError

T = datetime(2024, 6, 21, 14, 0, tzinfo=timezone.utc)


@pytest.fixture(scope="module")
def pair_files(tmp_path_factory, small_sky):
    """The shared simulated 320 px pair (one cumulus layer at 1500 m) as PNG files and its station."""
    sim, shot = small_sky
    d = tmp_path_factory.mktemp("api")
    (d / "station.toml").write_text(sim.station.to_toml())
    for cam in ("cam1", "cam2"):
        cv2.imwrite(str(d / f"{cam}.png"), shot.views[cam].image)
    return d


@pytest.fixture(scope="module")
def pipe(pair_files):
    return cbh.Pipeline(cbh.load_station(pair_files / "station.toml"))


@pytest.fixture(scope="module")
def from_paths(pipe, pair_files):
    return pipe.process(pair_files / "cam1.png", pair_files / "cam2.png", T)


def test_import_cbh_is_light_and_installs_no_top_level_cli(tmp_path):
    code = ("import sys, importlib.util, cbh; "
            "heavy = [m for m in ('numpy', 'cv2', 'torch', 'pandas', 'rerun', 'mcap') if m in sys.modules]; "
            "print(heavy, importlib.util.find_spec('cli') is None, callable(cbh.Pipeline), callable(cbh.layer_table))")
    r = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    assert r.stdout.split() == ["[]", "True", "True", "True"]


def test_paths_and_arrays_with_their_channel_order_give_the_same_result(pipe, pair_files, from_paths):
    from PIL import Image

    rgb = [np.asarray(Image.open(pair_files / f"{c}.png").convert("RGB")) for c in ("cam1", "cam2")]
    bgr = [cv2.imread(str(pair_files / f"{c}.png")) for c in ("cam1", "cam2")]
    r_rgb = pipe.process(*rgb, T, channels="rgb")
    r_bgr = pipe.process(*bgr, T, channels="BGR")
    assert from_paths.layers and abs(from_paths.layers[0].height_m - 1500.0) < 0.05 * 1500.0
    for r in (r_rgb, r_bgr):  # the same pixels in the same order: identical numbers
        assert r.cloud_fraction == from_paths.cloud_fraction
        assert [L.height_m for L in r.layers] == [L.height_m for L in from_paths.layers]
    # the reason a bare array is refused: RGB read as BGR swaps blue and red, and the blue/red
    # cloud test then calls much of the clear sky cloud (the hybrid default adapts to colour
    # casts, but a swap turns the sky orange: +0.20 here, +0.3 with the old fixed thresholds)
    swapped = pipe.process(*rgb, T, channels="bgr")
    assert swapped.cloud_fraction["cam1"] > from_paths.cloud_fraction["cam1"] + 0.1


def test_bare_arrays_greyscale_and_zoneless_times_are_refused(pipe, pair_files):
    bgr = [cv2.imread(str(pair_files / f"{c}.png")) for c in ("cam1", "cam2")]
    with pytest.raises(ImageError, match="channels='rgb'"):
        pipe.process(*bgr, T)
    with pytest.raises(ImageError, match="'rgb' or 'bgr'"):
        pipe.process(*bgr, T, channels="hsv")
    grey2d = cv2.cvtColor(bgr[0], cv2.COLOR_BGR2GRAY)
    with pytest.raises(ImageError, match="greyscale.*colour"):
        pipe.process(grey2d, bgr[1], T, channels="bgr")
    grey3 = np.repeat(grey2d[:, :, None], 3, axis=2)
    with pytest.raises(ImageError, match="greyscale.*colour"):
        pipe.process(bgr[0], grey3, T, channels="rgb")
    grey_file = pair_files / "grey.jpg"
    cv2.imwrite(str(grey_file), grey2d)  # a greyscale JPEG decodes to three equal channels
    with pytest.raises(ImageError, match="greyscale"):
        pipe.process(grey_file, pair_files / "cam2.png", T)
    # a camera that delivers no picture (saturated white, or dark) is said to be blank, not greyscale
    for value, why in ((255, "over-exposed"), (3, "dark")):
        blank = np.full_like(bgr[0], value)
        with pytest.raises(ImageError, match=f"blank frame.*{why}"):
            pipe.process(bgr[0], blank, T, channels="bgr")
    with pytest.raises(InputError, match="no zone"):
        pipe.process(*bgr, datetime(2024, 6, 21, 14, 0), channels="bgr")
    with pytest.raises(InputError, match="2024-06-21T14:00:00Z"):
        pipe.process(*bgr, "2024-06-21 14:00", channels="bgr")


def test_pipeline_given_a_path_instead_of_a_station_says_so(pair_files):
    # a path is the natural first try; it was an AttributeError traceback from inside __init__
    from cbh.errors import ConfigError

    with pytest.raises(ConfigError, match="load_station"):
        cbh.Pipeline(str(pair_files / "station.toml"))


def test_unknown_time_stays_unknown(pipe, pair_files):
    r = pipe.process(pair_files / "cam1.png", pair_files / "cam2.png", None)
    assert r.time_utc is None and "time_unknown" in r.flags
    assert r.summary()["time_utc"] is None
    df = cbh.layer_table([r])
    assert df["time_utc"].isna().all()


def test_layer_table_has_one_row_per_layer(from_paths):
    clear = dataclasses.replace(from_paths, layers=[])
    df = cbh.layer_table([from_paths, clear, from_paths])
    n = len(from_paths.layers)
    assert len(df) == 2 * n + 1  # the clear pair: one row, layer 0 (the time step is kept, as in the CSV)
    assert list(df["layer"]) == list(range(1, n + 1)) + [0] + list(range(1, n + 1))
    assert math.isnan(df["cloud_base_height_m"].iloc[n])
    assert str(df["time_utc"].dt.tz) == "UTC" and df["time_utc"].iloc[0] == T
    L = from_paths.layers[0]
    row = df.iloc[0]
    assert row["cloud_base_height_m"] == L.height_m and row["cover"] == L.cover and row["points"] == L.points
    # altitude above sea level = height above the ENU origin + station altitude (unb-lea: 1050 m)
    assert math.isclose(row["cloud_base_altitude_m"], L.height_m + 1050.0, abs_tol=1e-6)
    # the same table the CSV export writes: one set of columns for every consumer
    from cbh.outputs.export import COLUMNS

    assert tuple(df.columns[: len(COLUMNS)]) == COLUMNS

# The README's library example runs verbatim in tests/test_wahrsis.py (its result is the real pair's).


def test_outputs_refuse_a_result_without_a_time(tmp_path):
    """Recordings, the Rerun time line and layer tables place each pair at its time: a result
    whose time is unknown is refused with one clear error, never stamped with a made-up time."""
    from cbh.errors import RecordingError
    from cbh.outputs.export import LayerExporter
    from cbh.outputs.record import McapRecorder
    from cbh.outputs.rerun_view import RerunSink

    from .conftest import small_station, synthetic_pair

    st = small_station()
    frames, res = synthetic_pair(st, 0)
    res.time_utc = None
    with McapRecorder(tmp_path / "x.mcap", st, {}) as rec:
        with pytest.raises(RecordingError, match="capture time is unknown"):
            rec.write(frames, res)
    with LayerExporter(tmp_path / "x.csv", st) as exp:
        with pytest.raises(RecordingError, match="capture time is unknown"):
            exp.write(frames, res)
    with RerunSink(st, "save", str(tmp_path / "x.rrd")) as sink:
        with pytest.raises(RecordingError, match="capture time is unknown"):
            sink.write(frames, res)
