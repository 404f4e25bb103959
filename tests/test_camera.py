"""Camera models: OCamCalib reference vectors, round trips, ideal fisheyes, scaling."""
from __future__ import annotations

import math

import numpy as np
import pytest

from cbh.geometry.camera import EquidistantModel, EquisolidModel, OCamModel, format_ocamcalib, read_ocamcalib
from cbh.errors import CalibrationError

from .conftest import OCAM_FILE

# Paper Table 1 (a0 > 0 form, already in the cbh frame)
TABLE1 = {
    "cam1": dict(poly=(630.939, 0.0, -683.907e-6, 490.328e-9, -509.5e-12), center_xy=(960.09, 960.31)),
    "cam2": dict(poly=(627.381, 0.0, -514.267e-6, 996.681e-10, -240.4e-12), center_xy=(960.27, 960.07)),
}


def tb_to_cbh(v):
    """OCamCalib toolbox ray (x along rows, y along columns, z; scene at z < 0) → cbh frame."""
    return np.array([v[1], v[0], -v[2]])


@pytest.fixture(scope="module")
def skysol():
    return read_ocamcalib(OCAM_FILE)


# Reference vectors from ../shared/data/ocamcalib/README.md (toolbox frame)
CAM2WORLD = [
    ((948, 964), (0, 0, -1)),
    ((1048, 964), (+0.146625319, +0.000024047, -0.989192102)),
    ((948, 1264), (-0.000122089, +0.430513157, -0.902584293)),
    ((748, 714), (-0.285328900, -0.357352295, -0.889318141)),
]
WORLD2CAM = [
    ((0.5, 0, -1), (1260.866671, 963.948764)),
    ((0.3, -0.4, -0.5), (1263.969206, 543.107243)),
    ((1, 1, -0.2), (1601.391621, 1616.152979)),
]


def test_reads_toolbox_file(skysol):
    assert (skysol.width, skysol.height) == (1920, 1920)
    assert skysol.center_xy == (964.0, 948.0)  # file gives "row column"
    assert skysol.poly[0] == pytest.approx(679.7272)  # ss[0] = -679.7272, negated into the cbh frame
    assert skysol.affine == (1.001451, 0.000284, -0.000164)
    assert len(skysol.invpol) == 11


@pytest.mark.parametrize("rowcol, ray", CAM2WORLD)
def test_cam2world_reference(skysol, rowcol, ray):
    got = skysol.pixel_to_ray([[rowcol[1], rowcol[0]]])[0]
    np.testing.assert_allclose(got, tb_to_cbh(ray), atol=2e-9)  # reference printed to 9 decimals


@pytest.mark.parametrize("ray, rowcol", WORLD2CAM)
def test_world2cam_reference(skysol, ray, rowcol):
    got = skysol.ray_to_pixel(tb_to_cbh(ray)[None])[0]
    # the toolbox inverts with its fitted invpol (≈0.005 px, README); cbh inverts exactly
    np.testing.assert_allclose(got, [rowcol[1], rowcol[0]], atol=0.006)


def hemisphere_rays(max_deg=89.0, n=120):
    th = np.radians(np.linspace(0.0, max_deg, n))
    ph = np.linspace(0.0, 2 * np.pi, n, endpoint=False)
    T, P = np.meshgrid(th, ph)
    return np.stack([np.sin(T) * np.cos(P), np.sin(T) * np.sin(P), np.cos(T)], -1).reshape(-1, 3)


def table1_model(name):
    return OCamModel(width=1920, height=1920, **TABLE1[name])


@pytest.mark.parametrize("model", [
    pytest.param(lambda: read_ocamcalib(OCAM_FILE), id="skysol"),
    pytest.param(lambda: table1_model("cam1"), id="table1-cam1"),
    pytest.param(lambda: table1_model("cam2"), id="table1-cam2"),
    pytest.param(lambda: EquidistantModel(width=1000, height=800, center_xy=(501.2, 398.7), radius_px=390.0), id="equidistant"),
    pytest.param(lambda: EquisolidModel(width=5184, height=3456, center_xy=(2592, 1724), radius_px=1470), id="equisolid"),
])
def test_round_trip_up_to_89_deg(model):
    m = model()
    rays = hemisphere_rays()
    px = m.ray_to_pixel(rays)
    assert np.isfinite(px).all()
    back = m.pixel_to_ray(px)
    np.testing.assert_allclose(back, rays, atol=1e-9)
    np.testing.assert_allclose(m.ray_to_pixel(back), px, atol=0.01)  # the 0.01 px bar


def test_without_invpol_ray_to_pixel_is_exact(skysol):
    from dataclasses import replace

    bare = replace(skysol, invpol=None)
    rays = hemisphere_rays(89.0, 50)
    np.testing.assert_allclose(bare.ray_to_pixel(rays), skysol.ray_to_pixel(rays), atol=0.01)


def test_table1_cameras_see_the_horizon_near_the_image_edge():
    # f(r) = 0 (θ = 90°) should fall near the 960 px image radius for a 180° lens on a 1920 px sensor
    for name in TABLE1:
        m = table1_model(name)
        r90 = np.hypot(*(m.ray_to_pixel([[1.0, 0.0, 0.0]])[0] - m.center_xy))
        assert 900 < r90 < 1000, (name, r90)
        assert m.max_theta_deg == 90.0


def test_equidistant_and_equisolid_profiles():
    ed = EquidistantModel(width=100, height=100, center_xy=(49.5, 49.5), radius_px=40.0)
    es = EquisolidModel(width=100, height=100, center_xy=(49.5, 49.5), radius_px=40.0)
    for theta in (0.0, 30.0, 60.0, 90.0):
        ray = [[math.sin(math.radians(theta)), 0.0, math.cos(math.radians(theta))]]
        assert ed.ray_to_pixel(ray)[0, 0] - 49.5 == pytest.approx(40.0 * theta / 90.0)
        assert es.ray_to_pixel(ray)[0, 0] - 49.5 == pytest.approx(40.0 / math.sin(math.pi / 4) * math.sin(math.radians(theta) / 2))


def test_pixel_axes_follow_conventions():
    m = table1_model("cam1")
    c = np.array(m.center_xy)
    right = m.pixel_to_ray([c + [100, 0]])[0]
    down = m.pixel_to_ray([c + [0, 100]])[0]
    assert right[0] > 0 and abs(right[1]) < 1e-12  # +x column → +x camera
    assert down[1] > 0 and abs(down[0]) < 1e-12  # +y row → +y camera
    assert m.pixel_to_ray([c])[0] == pytest.approx([0, 0, 1])


@pytest.mark.parametrize("factor", [0.25, 0.5, 2.0])
def test_scaled_model_maps_resized_pixels(factor):
    m = table1_model("cam2")
    s = m.scaled(factor)
    px = m.ray_to_pixel(hemisphere_rays(85.0, 20))
    px_s = (px + 0.5) * factor - 0.5
    np.testing.assert_allclose(s.pixel_to_ray(px_s), m.pixel_to_ray(px), atol=1e-9)
    assert s.width == round(1920 * factor)


def test_format_ocamcalib_round_trip(skysol, tmp_path):
    p = tmp_path / "calib_results.txt"
    p.write_text(format_ocamcalib(skysol))
    again = read_ocamcalib(p)
    rays = hemisphere_rays(88.0, 30)
    np.testing.assert_allclose(again.ray_to_pixel(rays), skysol.ray_to_pixel(rays), atol=1e-3)


@pytest.mark.parametrize("text, match", [
    ("", "expected 5 data lines"),
    ("5 1 2 3\n2 1 2\n1 1\n1 0 0\n10 10\n", "coefficient count"),
    ("garbage here\n", "not an OCamCalib"),
])
def test_bad_calibration_files(tmp_path, text, match):
    p = tmp_path / "bad.txt"
    p.write_text(text)
    with pytest.raises(CalibrationError, match=match):
        read_ocamcalib(p)


def test_missing_calibration_file(tmp_path):
    with pytest.raises(CalibrationError, match="not found"):
        read_ocamcalib(tmp_path / "nope.txt")


def test_contains_rejects_outside_circle():
    m = table1_model("cam1")
    ok = m.contains([[960, 960], [5, 5], [-3, 960], [960, 1925]])
    assert ok.tolist() == [True, False, False, False]


def test_a_lens_scale_is_dr_dtheta():
    """``CameraModel.px_per_rad``: an equidistant lens's R90 / 90° everywhere; an OCam lens's a0
    at the axis (r = f⁻¹: dr/dθ = a0 there); an equisolid lens's scale falls off axis as cos(θ/2)."""
    import math

    from cbh.geometry.camera import EquidistantModel, EquisolidModel
    from cbh.geometry.station import load_station
    from cbh.presets import station_path

    eq = EquidistantModel(width=960, height=960, center_xy=(479.5, 479.5), radius_px=450.0)
    for th in (0.0, 0.5, 1.2):
        assert eq.px_per_rad(th) == pytest.approx(450.0 / (math.pi / 2), rel=1e-9)
    ocam = load_station(station_path()).camera("cam1").model
    assert ocam.px_per_rad() == pytest.approx(ocam.poly[0], rel=1e-4)
    es = EquisolidModel(width=960, height=960, center_xy=(479.5, 479.5), radius_px=450.0)
    k = 450.0 / math.sin(math.pi / 4) / 2
    assert es.px_per_rad(math.radians(60.0)) == pytest.approx(k * math.cos(math.radians(30.0)), rel=1e-4)
