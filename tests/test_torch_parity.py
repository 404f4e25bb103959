"""The torch backend (cbh/pipeline/torch_ops.py) against the numpy/OpenCV path, stage by stage.

Tolerances, and why:
- remap: the same pixel-centre convention to 1e-3 px. cv2.remap quantises its bilinear weights
  to 1/32 px (INTER_BITS = 5), so the convention is checked on positions of that grid, where
  both are exact up to float32 rounding of the coordinates (≈ 6e-5 px at 300 px).
- box filters and 2 × 2 pooling: float32 sums in a different order: ≤ 1e-3 grey levels.
- ZNCC: off the 1/32 grid, cv2.remap's quantised weights move a warped grey level by up to
  |∇I| / 64 (measured ≤ 0.01 grey levels), which moves the ZNCC of a textured 8 × 8 window
  (σ ≥ 1 grey level) by ≲ 0.01: asserted ≤ 0.02 on textured cloud blocks.
- passes: the decisions taken on those scores (coarse hypotheses, layer cuts, accepted pixels,
  labels) agree except where a score sits within that noise of a threshold or a tie: ≥ 99.9 %
  of pixels; refined s within 0.01 plane step (≈ 0.01 px of parallax) for 99 % of pixels.
- whole pipeline: layer heights within 0.2 % of each other (the aggregated layers average
  thousands of such pixels), 99 % of the height map within 0.1 %.

Torch runs on one thread here: on this oversubscribed 2-core machine its OpenMP threads
spin-wait (a 1 ms op took 1 s with 2 threads under load 16).
"""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

torch = pytest.importorskip("torch")

from cbh.errors import ConfigError  # noqa: E402
from cbh.geometry.station import load_station  # noqa: E402
from cbh.pipeline import Pipeline  # noqa: E402
from cbh.pipeline import sweep as S  # noqa: E402
from cbh.pipeline import torch_ops as T  # noqa: E402
from cbh.presets import station_path  # noqa: E402

S_MIN, S_MAX = 1.0 / 15000.0, 1.0 / 300.0


@pytest.fixture(scope="module", autouse=True)
def one_thread():
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


@pytest.fixture(scope="module")
def scene():
    from cbh.sim import SkySimulator, load_scene

    sim = SkySimulator(load_station(station_path("unb-lea")), load_scene("two-layers"), size_px=480)
    shot = sim.render()
    pipe = Pipeline(sim.station)
    im1, im2 = shot.views["cam1"].image, shot.views["cam2"].image
    r = pipe.process(im1, im2, shot.time_utc, channels="bgr")
    g1, g2 = (cv2.cvtColor(pipe.to_working(i, im), cv2.COLOR_BGR2GRAY).astype(np.float32) for i, im in ((0, im1), (1, im2)))
    prep = pipe.prepare(im1, im2, shot.time_utc, channels="bgr")
    cloud = prep.masks.for_matching(prep.seg)[1].clouds[0]  # what the sweep gets: no saturated cloud
    tm = T.TorchPlaneMaps(pipe.geometry.planes, (g2.shape[1], g2.shape[0]), torch.device("cpu"))
    return dict(sim=sim, shot=shot, pipe=pipe, result=r, g1=g1, g2=g2, cloud=cloud, tm=tm,
                cfg=pipe.config.matching.sweep, maps=pipe.geometry.planes)


def test_remap_uses_opencv_pixel_centres():
    rng = np.random.default_rng(0)
    mx = (np.round(rng.uniform(-2, 81, (40, 50)) * 32) / 32).astype(np.float32)  # also a little outside
    my = (np.round(rng.uniform(-2, 65, (40, 50)) * 32) / 32).astype(np.float32)
    ramp_x = np.tile(np.arange(80, dtype=np.float32), (64, 1))
    ramp_y = np.tile(np.arange(64, dtype=np.float32)[:, None], (1, 80))
    for ramp, m in ((ramp_x, mx), (ramp_y, my)):
        ref = cv2.remap(ramp, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        out = T.remap(torch.from_numpy(ramp)[None, None], torch.from_numpy(mx)[None], torch.from_numpy(my)[None])
        out = out[0, 0].numpy()
        assert np.abs(out - ref).max() <= 1e-3 * 80  # a value difference of 1e-3 px on a 1 px/px ramp … at most 80 px
        inside = (mx >= 0) & (mx <= 79) & (my >= 0) & (my <= 63)
        assert np.abs(out[inside] - m[inside]).max() <= 1e-3  # sampled where asked: the pixel-centre convention


@pytest.mark.parametrize("k", [3, 4, 9, 15])
def test_box_and_pool_match_opencv(k):
    rng = np.random.default_rng(1)
    x = (rng.random((60, 70)) * 255).astype(np.float32)
    t = torch.from_numpy(x)[None, None]
    assert np.abs(T.box(t, k)[0, 0].numpy() - S._box(x, k)).max() <= 1e-3
    assert np.abs(T.pool2(t)[0, 0].numpy() - S._pool2(x)).max() <= 1e-3


def test_zncc_matches_opencv_on_textured_blocks(scene):
    sl = S._bbox(scene["cloud"], 9, even=True)
    i1 = np.ascontiguousarray(scene["g1"][sl])
    s = np.array([0.0, 2e-4, 6e-4, 1e-3])
    it = S._zncc_half_iter(i1, scene["g2"], scene["maps"], s, 4, sl)
    std_n, _ = next(it)
    ref = np.stack([x for _, x in it])
    std_t, out = T.zncc_half(torch.from_numpy(i1), torch.from_numpy(scene["g2"]), scene["tm"], s, 4, sl)
    assert np.abs(std_t.numpy() - std_n).max() <= 1e-2
    # textured in image 1, and a proper correlation: where the warped image 2 is flat (outside
    # camera 2, the sun disk) var2 ≈ 0 and the score is float noise over the 1e-3 regulariser
    both = (std_n >= 1.0)[None] & (np.abs(ref) <= 1.0)
    assert both.sum() > 1000
    d = np.abs(out.numpy() - ref)[both]
    assert np.median(d) <= 1e-4  # float32 rounding where the interpolation agrees
    # a handful of blocks (3 of 173 000 here) whose warped window is nearly flat: σ2 → 0 divides
    # the 1/32 px weight difference up; no pass accepts such a block (it is not textured in both)
    assert (d > 0.02).mean() <= 1e-4


def test_every_sweep_pass_agrees(scene):
    from dataclasses import replace

    g1, g2, cloud, cfg, maps, tm = (scene[k] for k in ("g1", "g2", "cloud", "cfg", "maps", "tm"))
    cfg = replace(cfg, oblique_levels=0)  # (the levels' part below turns them on: a difference to see)
    t1, t2 = torch.from_numpy(g1), torch.from_numpy(g2)
    c_n = S.coarse_pass(g1, g2, cloud, maps, S_MIN, S_MAX, 0.0, cfg)
    c_t = T.coarse_pass_torch(t1, t2, cloud, tm, S_MIN, S_MAX, 0.0, cfg)
    assert c_n.ranges == c_t.ranges and len(c_n.ranges) >= 1
    s, ds = S.fine_planes(c_n, maps.scale_px, S_MIN, S_MAX, cfg)
    f_n = S.fine_pass(g1, g2, cloud, maps, s, ds, cfg)
    f_t = T.fine_pass_torch(t1, t2, cloud, tm, s, ds, cfg)
    assert (f_n.ok == f_t.ok.numpy()).mean() >= 0.999
    assert np.abs(f_n.cost - f_t.cost.numpy()).max() <= 0.02
    l_n, l_t = S.label_pass(f_n, cfg), T.label_pass_torch(f_t, cfg)
    assert len(l_n.cuts_s) == len(l_t.cuts_s) == 1  # two layers
    assert np.allclose(l_n.cuts_s, l_t.cuts_s)
    assert (l_n.label == l_t.label.numpy()).mean() >= 0.999
    r_n = S.refine_pass(f_n, l_n, maps.scale_px, cfg)
    r_t = T.refine_pass_torch(f_t, l_t, maps.scale_px, cfg).numpy()
    ok = f_n.ok & f_t.ok.numpy()
    assert np.percentile(np.abs(r_n[ok] - r_t[ok]) / ds, 99) <= 0.01
    _oblique_levels_agree(f_n, f_t, l_n, l_t, r_n, maps, cfg, ok, ds)


def _oblique_levels_agree(f_n, f_t, l_n, l_t, r_0, maps, cfg0, ok, ds) -> None:
    """``oblique_levels`` (the refinement's boxes grown 2× and 4× where a plane step moves a pixel
    less): the same heights on both backends, and they differ from the layer box's alone where
    the pixels are oblique (else the levels did nothing)."""
    from dataclasses import replace

    cfg = replace(cfg0, oblique_levels=2)
    assert f_n.reach is None and f_t.reach is None  # (off: not computed)
    reach = S.parallax_reach(maps, f_n.region)  # what the fine pass keeps with the levels on
    assert 0.9 <= reach.max() <= 1.0 + 1e-6
    f_n, f_t = replace(f_n, reach=reach), replace(f_t, reach=torch.from_numpy(reach))
    r_n = S.refine_pass(f_n, l_n, maps.scale_px, cfg)
    r_t = T.refine_pass_torch(f_t, l_t, maps.scale_px, cfg).numpy()
    assert np.percentile(np.abs(r_n[ok] - r_t[ok]) / ds, 99) <= 0.01
    oblique = ok & (cv2.resize(f_n.reach, ok.shape[::-1], interpolation=cv2.INTER_NEAREST) < 0.5)
    assert oblique.sum() > 1000
    assert np.median(np.abs(r_n[oblique] - r_0[oblique]) / ds) > 0.01


def test_coarse_pass_with_near_planes_agrees(scene):
    """Down to 100 m the coarse pass runs its near planes at half the coarse size (two tiers,
    :func:`cbh.pipeline.sweep.coarse_planes`): the same votes on both backends."""
    g1, g2, cloud, cfg, maps, tm = (scene[k] for k in ("g1", "g2", "cloud", "cfg", "maps", "tm"))
    s_max = 1.0 / 100.0
    plan = S.coarse_planes(S_MIN, s_max, maps.scale_px, cfg)
    assert len(plan.near) > 0 and len(plan.far) > 0
    c_n = S.coarse_pass(g1, g2, cloud, maps, S_MIN, s_max, 0.0, cfg)
    c_t = T.coarse_pass_torch(torch.from_numpy(g1), torch.from_numpy(g2), cloud, tm, S_MIN, s_max, 0.0, cfg)
    assert c_n.ranges == c_t.ranges and len(c_n.ranges) >= 1


def _rel_diff(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    both = np.isfinite(a) & np.isfinite(b)
    assert both.sum() >= 0.999 * np.isfinite(a).sum()
    return np.abs(a[both] - b[both]) / a[both]


@pytest.mark.slow
def test_pipeline_on_torch_matches_opencv(scene):
    """Layers within 0.2 %; the height map's measured pixels: 99 % within 0.1 % (as the sweep's
    passes agree). With the fill, a filled pixel (≤ 3 px from a measured one) copies its nearest
    measured height, and OpenCV's chamfer distances (≤ 2 % long) can rank another seed first than
    the exact jump flooding does: at a layer edge that is the other layer's height (measured:
    1.27 % of pixels off by more than 0.1 %, against 0.91 % with OpenCV's fill on both sides).
    A strict expected failure in stop 59 (2.6 % of the unfilled pixels off by more than 0.1 %, at
    50–80° from the zenith); it passes again since stop 60 (edge windows weighed down, oblique
    levels on), the cause of the gap not isolated."""
    from dataclasses import replace

    shot, r_n = scene["shot"], scene["result"]
    images = (shot.views["cam1"].image, shot.views["cam2"].image, shot.time_utc)
    r_t = Pipeline(scene["sim"].station, device="cpu", backend="torch").process(*images, channels="bgr")
    h_n, h_t = [L.height_m for L in r_n.layers], [L.height_m for L in r_t.layers]
    assert len(h_n) == len(h_t) == 2
    assert np.allclose(h_n, h_t, rtol=2e-3)
    assert np.mean(_rel_diff(r_n.height_map, r_t.height_map) > 1e-3) <= 0.02
    cfg = scene["pipe"].config
    unfilled = replace(cfg, height_map=replace(cfg.height_map, fill="none"))
    m_n, m_t = (Pipeline(scene["sim"].station, config=unfilled, backend=b).process(*images, channels="bgr").height_map
                for b in ("opencv", "torch"))
    assert np.percentile(_rel_diff(m_n, m_t), 99) <= 1e-3


def _segment_both(pipe, image, usable, sun_angle, sky_clear=False):
    from cbh.pipeline.segment import segment
    from cbh.pipeline.torch_segment import segment_torch

    cfg = pipe.config.segmentation
    return (segment(image, usable, pipe.zenith(0), sun_angle, cfg, sky_clear=sky_clear),
            segment_torch(image, usable, T.upload(pipe.zenith(0), "cpu"), sun_angle, cfg, sky_clear=sky_clear))


@pytest.mark.parametrize("preset", ["two-layers", "clear-sky", pytest.param("overcast", marks=pytest.mark.slow),
                                    pytest.param("sun-behind-clouds", marks=pytest.mark.slow)])
def test_segmentation_on_torch_matches_opencv(preset):
    """Both backends take their decisions from the same samples (shared host code), so the masks
    differ only where a pixel's score is within the references' float32/remap-weight noise
    (≤ 1e-3 in NBR) of the threshold: ≥ 99.98 % of pixels (measured: all of them), the cloud
    fraction within 0.05 %. (A chroma weight of 0.2 instead of 0.3 changes 0.05 % of pixels.)
    Covers the bimodal sky with the brightness cue, a clear and an overcast one-class sky (the
    local-contrast test), and the sun behind cloud."""
    from cbh.sim import SkySimulator, load_scene

    sim = SkySimulator(load_station(station_path("unb-lea")), load_scene(preset), size_px=480)
    shot = sim.render()
    pipe = Pipeline(sim.station)
    prep = pipe.prepare(shot.views["cam1"].image, shot.views["cam2"].image, shot.time_utc, channels="bgr")
    for sun in (prep.masks.sun_angle[0], None):  # with the sun's position, and without (time unknown)
        (c_n, f_n), (c_t, f_t) = _segment_both(pipe, prep.work[0], prep.masks.usable[0], sun)
        assert c_t.dtype == bool and c_t.shape == c_n.shape
        assert np.mean(c_n == c_t) >= 0.9998, preset
        assert abs(f_n - f_t) <= 0.0005
    # … and a segmentation: against the simulator's true cloud mask (the hybrid's 97.5 % on such skies)
    (_, _), (c_t, _) = _segment_both(pipe, prep.work[0], prep.masks.usable[0], prep.masks.sun_angle[0])
    truth = cv2.resize(shot.views["cam1"].cloud_mask.view(np.uint8), c_t.shape[::-1], interpolation=cv2.INTER_NEAREST) > 0
    u = prep.masks.usable[0]
    assert np.mean(truth[u] == c_t[u]) >= 0.93, preset


def test_segmentation_on_torch_reads_texture_on_a_one_class_sky():
    """A blue sky with strong brightness texture (blue-red ratio unchanged: one class only) is a
    textured overcast for both backends (their local contrast, not its colour, decides)."""
    from cbh.sim import SkySimulator, load_scene

    sim = SkySimulator(load_station(station_path("unb-lea")), load_scene("clear-sky"), size_px=480)
    shot = sim.render()
    pipe = Pipeline(sim.station)
    prep = pipe.prepare(shot.views["cam1"].image, shot.views["cam2"].image, shot.time_utc, channels="bgr")
    rng = np.random.default_rng(3)
    texture = cv2.GaussianBlur(rng.normal(size=prep.work[0].shape[:2]).astype(np.float32), (0, 0), 1.5)
    img = np.clip(prep.work[0] * (1.0 + 0.15 * texture / texture.std())[..., None], 0, 255).astype(np.uint8)  # ±15 %
    (c_n, f_n), (c_t, f_t) = _segment_both(pipe, img, prep.masks.usable[0], prep.masks.sun_angle[0])
    smooth_n, _ = _segment_both(pipe, prep.work[0], prep.masks.usable[0], prep.masks.sun_angle[0])[0]
    assert f_n > 0.95 and np.mean(smooth_n) < 0.05  # the texture, not the colour, made it cloud
    assert np.array_equal(c_n, c_t) and f_t == f_n


def test_segmentation_on_torch_calls_a_clear_class_of_cloud_cloud(tmp_path):
    """Randomized sky 9570 (480 px): a textured overcast under a warm cast, whose two-class split
    called its bluer shade clear (5 % cloud) until a clear class with no part bluer than red and
    a cloud's texture counted as cloud (:func:`cbh.pipeline.segment.clear_class_is_sky`): both
    backends now read it all cloud."""
    from cbh.sim import SkySimulator
    from cbh.sim.randomize import RandomOptions, random_case, station_with_masks

    case = random_case(9570, load_station(station_path()), RandomOptions(skylines=True, unmasked=True,
                                                                          twice_encoded=True))
    sim = SkySimulator(case.station, case.scene, size_px=480)
    shot = sim.render()
    cams = list(sim.station.cameras)[:2]
    pipe = Pipeline(station_with_masks(case, sim, tmp_path))
    prep = pipe.prepare(shot.views[cams[0]].image, shot.views[cams[1]].image, shot.time_utc, channels="bgr")
    (c_n, f_n), (c_t, f_t) = _segment_both(pipe, prep.work[0], prep.masks.usable[0], prep.masks.sun_angle[0])
    assert f_n >= 0.9 and f_t >= 0.9 and np.mean(c_n == c_t) >= 0.9998, (f_n, f_t)


def test_segmentation_on_torch_takes_a_pale_sky_as_clear_when_told(tmp_path):
    """``sky_clear`` (the other camera sees the sky clear, :meth:`Pipeline._pale_camera`): randomized
    clear sky 13016, whose camera 1 reads its pale sky as one cloud, is clear but for what stands
    out from it on both backends, and the whole pipeline on torch makes no layer of its pale sky."""
    from dataclasses import replace

    from cbh.sim import SkySimulator
    from cbh.sim.contrail import Contrail
    from cbh.sim.randomize import RandomOptions, draw_contrails, random_case, station_with_masks

    case = random_case(13016, load_station(station_path()), RandomOptions(kind="clear"))
    case = replace(case, contrails=(Contrail(height_m=8334.0, point_m=(2836.0, 2104.0), azimuth_deg=349.6,
                                             width_m=90.0, brightness_dn=90.0),))
    sim = SkySimulator(case.station, case.scene, size_px=480)
    shot = draw_contrails(case, sim, sim.render())
    cams = list(sim.station.cameras)[:2]
    st = station_with_masks(case, sim, tmp_path)
    pipe = Pipeline(st)
    prep = pipe.prepare(shot.views[cams[0]].image, shot.views[cams[1]].image, shot.time_utc, channels="bgr")
    (c_n, f_n), (c_t, f_t) = _segment_both(pipe, prep.work[0], prep.masks.usable[0], prep.masks.sun_angle[0])
    assert f_n >= 0.9 and f_t >= 0.9  # alone: one cloud
    (c_n, f_n), (c_t, f_t) = _segment_both(pipe, prep.work[0], prep.masks.usable[0], prep.masks.sun_angle[0], True)
    assert f_n <= 0.05 and np.mean(c_n == c_t) >= 0.9998, (f_n, f_t)
    r = Pipeline(st, backend="torch").process(shot.views[cams[0]].image, shot.views[cams[1]].image, shot.time_utc,
                                              channels="bgr")
    assert all(abs(L.height_m / 8334.0 - 1) <= 0.15 for L in r.layers) and max(r.cloud_fraction.values()) <= 0.05, \
        (r.layers, r.cloud_fraction)


@pytest.mark.parametrize("size", [600, 3])
def test_segmentation_on_torch_edge_cases_as_opencv(size):
    """No usable pixel on the sampling lattice (usable sky on even rows only: the 2-px lattice
    starts on row 1), and a thumbnail: both backends give the same answer."""
    from cbh.pipeline.config import SegmentationConfig
    from cbh.pipeline.segment import segment
    from cbh.pipeline.torch_segment import segment_torch

    rng = np.random.default_rng(5)
    img = np.clip(np.array([200, 150, 120]) * rng.uniform(0.8, 1.2, (size, size, 1)), 0, 255).astype(np.uint8)
    yy, xx = np.mgrid[0:size, 0:size].astype(np.float32)
    zen = np.hypot(yy - size / 2, xx - size / 2) * (80.0 / size)
    usable = np.zeros((size, size), bool)
    usable[0::2] = True
    cfg = SegmentationConfig()
    (c_n, f_n), (c_t, f_t) = (segment(img, usable, zen, zen, cfg), segment_torch(img, usable, zen, zen, cfg))
    assert np.array_equal(c_n, c_t) and f_n == f_t


@pytest.mark.parametrize("exp", ["low", pytest.param("med", marks=pytest.mark.slow),
                                 pytest.param("high", marks=pytest.mark.slow)])
@pytest.mark.slow
def test_segmentation_on_torch_matches_opencv_on_the_real_pair(shared, exp):
    """The real WAHRSIS photographs (haze, JPEG noise, vignetting) at each exposure (the low one,
    noisiest, by default)."""
    from datetime import datetime, timezone

    from cbh.imageio import read_image

    st = load_station(Path(__file__).resolve().parents[1] / "configs" / "wahrsis-2015-10-29.toml")
    pipe = Pipeline(st)
    t = datetime(2015, 10, 29, 4, 58, 1, tzinfo=timezone.utc)
    d = shared / "data" / "wahrsis-2015-10-29"
    im1, _ = read_image(d / f"2015-10-29-12-58-01-wahrsis3-{exp}.jpg")
    im2, _ = read_image(d / f"2015-10-29-12-58-01-wahrsis4-{exp}.jpg")
    prep = pipe.prepare(im1, im2, t, channels="bgr")
    (c_n, f_n), (c_t, f_t) = _segment_both(pipe, prep.work[0], prep.masks.usable[0], prep.masks.sun_angle[0])
    assert np.mean(c_n == c_t) >= 0.9998
    assert abs(f_n - f_t) <= 0.0005 and 0.05 < f_t < 0.95, f_t


def _exact_distance(known: np.ndarray) -> np.ndarray:
    """Exact Euclidean distance to the nearest known pixel, by brute force over the seeds."""
    ky, kx = np.nonzero(known)
    yy, xx = np.mgrid[0: known.shape[0], 0: known.shape[1]]
    d2 = np.full(known.shape, np.inf)
    for y, x in zip(ky, kx):
        np.minimum(d2, (yy - y) ** 2 + (xx - x) ** 2, out=d2)
    return np.sqrt(d2)


@pytest.mark.parametrize("shape,density", [((90, 120), 0.002), ((90, 120), 0.05), ((60, 150), 0.0003), ((1, 40), 0.05)])
def test_nearest_fill_on_torch_finds_the_nearest_measured_pixel(shape, density):
    """Jump flooding (1 + JFA + 2) against brute force, on several random maps: every pixel gets
    the exact nearest distance and the height of a seed at that distance. OpenCV's 5 × 5 chamfer
    distances are ≤ 2 % long; the fill rule (distance ≤ 3 px) then selects the same pixels."""
    from cbh.pipeline.heightmap import nearest_fill
    from cbh.pipeline.torch_heightmap import nearest_fill_torch

    rng = np.random.default_rng(7)
    for _ in range(5):
        known = rng.random(shape) < density
        known.flat[rng.integers(known.size)] = True
        hmap = np.where(known, rng.uniform(300, 9000, known.shape), np.nan).astype(np.float32)
        exact = _exact_distance(known)
        near_t, d_t = nearest_fill_torch(hmap)
        near_n, d_n = nearest_fill(hmap)
        assert np.abs(d_t - exact).max() <= 1e-3
        yy, xx = np.mgrid[0: shape[0], 0: shape[1]]
        seed = {float(v): (y, x) for v, y, x in zip(hmap[known], *np.nonzero(known))}
        sy, sx = np.array([seed[float(v)] for v in near_t.ravel()]).T.reshape(2, *shape)
        assert np.abs(np.hypot(yy - sy, xx - sx) - exact).max() <= 1e-3  # its height is a nearest seed's
        assert np.array_equal(near_t[known], hmap[known]) and np.all(d_t[known] == 0)
        assert np.all(np.abs(d_n - exact) <= 0.02 * exact + 1e-3)
        assert np.array_equal(d_t <= 3.0, d_n <= 3.0)


def test_nearest_fill_on_torch_without_any_measurement():
    from cbh.pipeline.torch_heightmap import nearest_fill_torch

    near, d = nearest_fill_torch(np.full((5, 6), np.nan, np.float32))
    assert np.isnan(near).all() and np.isinf(d).all()


def test_sun_angle_map_matches_opencv(scene):
    pipe = scene["pipe"]
    from cbh.pipeline.masks import angle_map_deg

    d = np.array([0.3, -0.2, 0.93])
    d /= np.linalg.norm(d)
    ref = angle_map_deg(pipe.cam1, d, pipe.rays_cam(0))
    out = T.angle_map_deg_torch(torch.from_numpy(pipe.rays_cam(0)), d @ pipe.cam1.R_world_from_cam).numpy()
    assert np.abs(out - ref).max() <= 0.02  # cv2.phase is good to ≈ 0.01°


def test_device_choices_are_checked(unb_station):
    with pytest.raises(ConfigError):
        Pipeline(unb_station, backend="gpu")
    with pytest.raises(ConfigError):
        Pipeline(unb_station, device="nonsense")
    if not torch.cuda.is_available():
        with pytest.raises(ConfigError, match="CUDA is not available"):
            Pipeline(unb_station, device="cuda")
    assert Pipeline(unb_station).backend == "opencv"
    assert Pipeline(unb_station, backend="torch").backend == "torch"


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_pipeline_on_cuda_matches_cpu(scene):
    shot, r_n = scene["shot"], scene["result"]
    r_c = Pipeline(scene["sim"].station, device="cuda").process(
        shot.views["cam1"].image, shot.views["cam2"].image, shot.time_utc, channels="bgr")
    assert np.allclose([L.height_m for L in r_n.layers], [L.height_m for L in r_c.layers], rtol=2e-3)


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_segmentation_and_fill_on_cuda_match_the_host(scene):
    from cbh.pipeline.segment import segment
    from cbh.pipeline.torch_heightmap import nearest_fill_torch
    from cbh.pipeline.torch_segment import segment_torch

    pipe, shot = scene["pipe"], scene["shot"]
    prep = pipe.prepare(shot.views["cam1"].image, shot.views["cam2"].image, shot.time_utc, channels="bgr")
    args = (prep.work[0], prep.masks.usable[0], pipe.zenith(0), prep.masks.sun_angle[0], pipe.config.segmentation)
    (c_n, f_n), (c_c, f_c) = segment(*args), segment_torch(*args, device="cuda")
    assert np.mean(c_n == c_c) >= 0.9998 and abs(f_n - f_c) <= 0.0005
    rng = np.random.default_rng(2)
    known = rng.random((90, 120)) < 0.01
    hmap = np.where(known, rng.uniform(300, 9000, known.shape), np.nan).astype(np.float32)
    _, d_c = nearest_fill_torch(hmap, "cuda")
    assert np.abs(d_c - _exact_distance(known)).max() <= 1e-3


def test_cli_device_errors_are_one_line(repo, tmp_path, capsys):
    from cbh.cli.main import main

    rc = main(["pair", str(tmp_path / "a.jpg"), str(tmp_path / "b.jpg"), "--station",
               str(repo / "configs" / "unb-lea.toml"), "--device", "tpu9"])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and err.startswith("cbh: error:") and "tpu9" in err and len(err.splitlines()) == 1
