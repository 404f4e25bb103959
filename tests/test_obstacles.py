"""Static obstacle mask from a sequence (`cbh mask`), against the simulator's obstacle truth."""
from __future__ import annotations

from datetime import timedelta

import cv2
import numpy as np
import pytest

from cbh.errors import ImageError, InputError
from cbh.pipeline.obstacles import obstacle_mask_from_frames
from cbh.presets import station_path
from cbh.sim import SkySimulator, load_scene
from cbh.geometry.station import load_station
from cbh.cli.main import main


def sequence(scene, n=6, size=480, cam="cam1", step_s=30):
    sim = SkySimulator(load_station(station_path()), load_scene(scene), size_px=size)
    t0 = sim.scene.time_utc
    return sim, [sim.view(cam, t0 + timedelta(seconds=step_s * i)).image for i in range(n)]


@pytest.fixture(scope="module")
def cumulus():
    return sequence("single-cumulus")  # trees (200–260°) and buildings (70–110°) on the horizon


def test_finds_the_horizon_obstacles(cumulus):
    sim, images = cumulus
    model = sim.station.camera("cam1").model
    mask = obstacle_mask_from_frames(images, model)
    truth = sim.obstacle_mask("cam1")
    circle = model.image_circle_mask()
    found = (mask == 0) & circle
    assert truth.sum() > 1000  # the scene really has obstacles
    assert (found & truth).sum() / truth.sum() > 0.97
    # false alarms: only the 2 px safety margin along the silhouettes (their perimeter is
    # ~1000 px at 480 px, so ~2000 px ≈ 1.2 % of the sky), never sky or cloud elsewhere
    assert (found & ~truth).sum() / (circle & ~truth).sum() < 0.02
    far = cv2.dilate(truth.astype(np.uint8), np.ones((9, 9), np.uint8)) == 0
    assert not (found & far).any()


def test_open_sky_with_moving_clouds_is_all_usable():
    sim, images = sequence("two-layers")
    model = sim.station.camera("cam1").model
    mask = obstacle_mask_from_frames(images, model)
    circle = model.image_circle_mask()
    assert ((mask == 0) & circle).sum() == 0


def test_bad_sequences(cumulus):
    sim, images = cumulus
    model = sim.station.camera("cam1").model
    with pytest.raises(InputError, match="at least 3 frames"):
        obstacle_mask_from_frames(images[:2], model)
    with pytest.raises(ImageError, match="frame 1 is 240x240"):
        obstacle_mask_from_frames([images[0], cv2.resize(images[1], (240, 240)), images[2]], model)


def test_cli_writes_a_mask_the_station_and_pipeline_use(tmp_path, capsys):
    from cbh.pipeline.masks import load_obstacle_mask

    out = tmp_path / "sim"
    assert main(["simulate", "--scene", "single-cumulus", "--out", str(out), "--frames", "5",
                 "--cadence-s", "30", "--size", "480"]) == 0
    assert main(["mask", str(out / "cam1"), "--station", str(out / "station.toml"), "--camera", "cam1",
                 "--out", str(out / "cam1_mask.png")]) == 0
    assert "5 frames" in capsys.readouterr().out
    text = (out / "station.toml").read_text()
    text = text.replace('name = "cam1"\n', 'name = "cam1"\nmask = "cam1_mask.png"\n', 1)
    (out / "station.toml").write_text(text)
    cam = load_station(out / "station.toml").camera("cam1")
    usable = load_obstacle_mask(cam.mask, cam.model.width, cam.model.height)
    assert 0.02 < 1 - usable[cam.model.image_circle_mask()].mean() < 0.10


def test_cli_errors(tmp_path, capsys):
    assert main(["mask", str(tmp_path / "none"), "--camera", "cam1", "--out", str(tmp_path / "m.png")]) == 2
    assert capsys.readouterr().err.startswith("cbh: error:")
    assert main(["mask", str(tmp_path), "--camera", "camX", "--out", str(tmp_path / "m.png")]) == 2
    assert "camX" in capsys.readouterr().err
