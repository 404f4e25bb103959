"""Render what each camera of a station sees of a :class:`~cbh.sim.Scene`, with exact truth.

Every pixel's world ray (the camera's own model, no undistortion) meets each horizontal
cloud layer at ``t = (h − z_cam) / d_z``; the first cloudy hit in ascending height is what
the pixel sees. The texture is a function of world (east, north) only
(:mod:`cbh.sim.noise`), so both cameras see the same cloud at the same place: the image
pair is stereo-consistent and ``height_m`` is the exact cloud-base height along each
pixel's ray.

Per-camera imperfections (:class:`~cbh.sim.scene.Imperfection`): a clock offset makes the
camera capture ``dt`` later (clouds moved by ``wind · dt``; its frames are still stamped on
time) and a rotation error renders it with a rotation differing from the station file's by
(yaw, pitch, roll): ``R_true = Rz(−dyaw) · R_station · Rx(dpitch) · Ry(droll)``. The truth
(``height_m``, ``cloud_mask``) is for the true geometry the image was rendered with.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace
from datetime import datetime, timedelta, timezone
from typing import Iterator

import cv2
import numpy as np

from cbh.errors import ConfigError
from cbh.result import Frame, to_ns
from cbh.geometry.station import Camera, Station, rot_x, rot_y, rot_z
from cbh.sim.noise import FADE_ZERO_PX, FINEST_PX_PER_WAVELENGTH, TILE_PX, LayerTexture, fade_weight, sample_tile
from cbh.sim.scene import CloudLayer, Scene
from cbh.sim.sky import (GROUND_BGR, HAZE_BGR, RASTER_BINS_PER_DEG, SKYLINE_KINDS, SUN_BGR, SUN_RADIUS_DEG,
                         obstacle_profile, skyline_raster, sun_direction, sun_position)

__all__ = ["SkySimulator", "SimShot", "SimView"]

MIN_LEVEL_PX = 8  # coarsest pyramid level is at least this many px on a side
EDGE_WIDTH = 0.10  # soft cloud edge width in shape-field units (× layer.edge_softness)
DETAIL_CONTRAST = 0.17  # relative brightness change per unit of the detail field
NOISE_PAD = 64  # the sensor-noise bank is this much larger than the image


@dataclass
class SimView:
    """One camera's rendered image and its ground truth.

    Attributes
    ----------
    camera : str
    image : ndarray, shape (H, W, 3), uint8
        BGR image.
    height_m : ndarray, shape (H, W), float32
        Cloud-base height above the ENU origin seen by each pixel [m]; NaN for clear sky,
        obstacles, ground and outside the image circle.
    cloud_mask : ndarray, shape (H, W), bool
        Pixels that see a cloud (``isfinite(height_m)``).
    time_utc : datetime
        When this camera really captured the image (includes its clock offset).
    stamp_utc : datetime
        The time the camera stamps on the frame (the nominal capture time).
    true_camera : Camera
        The geometry the image was rendered with (includes the orientation error).
    """

    camera: str
    image: np.ndarray
    height_m: np.ndarray
    cloud_mask: np.ndarray
    time_utc: datetime
    stamp_utc: datetime
    true_camera: Camera


@dataclass
class SimShot:
    """All cameras' views at one nominal time.

    Attributes
    ----------
    time_utc : datetime
        Nominal capture time (every camera's stamp).
    views : dict of str → SimView
    layers : tuple of CloudLayer
        The layers with offsets advected to ``time_utc``.
    sun_zenith_deg, sun_azimuth_deg : float
        Sun position at ``time_utc`` [deg].
    """

    time_utc: datetime
    views: dict[str, SimView]
    layers: tuple[CloudLayer, ...]
    sun_zenith_deg: float
    sun_azimuth_deg: float

    def truth(self) -> dict:
        """JSON-ready ground truth summary (layers, sun, per-camera capture times and cloud fraction)."""
        iso = lambda t: t.isoformat().replace("+00:00", "Z")  # noqa: E731
        return {
            "time_utc": iso(self.time_utc),
            "time_ns": to_ns(self.time_utc),
            "layers": [l.to_dict() for l in self.layers],
            "sun": {"zenith_deg": self.sun_zenith_deg, "azimuth_deg": self.sun_azimuth_deg},
            "cameras": {
                name: {
                    "capture_time_utc": iso(v.time_utc),
                    "cloud_pixels": int(v.cloud_mask.sum()),
                    "layer_pixels": {
                        f"{l.height_m:g}": int(np.count_nonzero(v.height_m == np.float32(l.height_m)))
                        for l in self.layers
                    },
                }
                for name, v in self.views.items()
            },
        }


@dataclass
class _Level:
    shape: tuple[int, int]  # (rows, cols)
    tanx: np.ndarray  # (h, w) float32: d_east / d_up of each sample's ray
    tany: np.ndarray  # (h, w) float32: d_north / d_up
    inv_fp: np.ndarray  # (h, w) float32: 1 / (ground footprint per metre of height) [px]


def _axis_positions(n0: int, levels: int) -> list[tuple[int, float, float]]:
    """Per level (size, a, b): sample j sits at full-res coordinate a·j + b along this axis.

    Level m+1 is upsampled into level m by ``cv2.resize`` (INTER_LINEAR), which reads level
    m+1 at x_{m+1} = (x_m + 0.5)·n_{m+1}/n_m − 0.5; its samples therefore sit at
    x_m = (j + 0.5)·n_m/n_{m+1} − 0.5.
    """
    out = [(n0, 1.0, 0.0)]
    for _ in range(levels):
        n_prev, a, b = out[-1]
        n = (n_prev + 1) // 2
        r = n_prev / n
        out.append((n, a * r, a * (0.5 * r - 0.5) + b))
    return out


class _CameraState:
    """Everything about one camera that does not change from frame to frame."""

    def __init__(self, index: int, nominal: Camera, scene: Scene):
        imp = scene.imperfection(nominal.name)
        dyaw, dpitch, droll = (math.radians(v) for v in imp.rotation_error_deg)
        R_true = rot_z(-dyaw) @ nominal.R_world_from_cam @ rot_x(dpitch) @ rot_y(droll)
        self.index = index
        self.name = nominal.name
        self.nominal = nominal
        self.true = replace(nominal, R_world_from_cam=R_true)
        self.clock_offset_s = imp.clock_offset_s
        self.aureole = (float(scene.sky.aureole), float(scene.sky.aureole_width_deg))
        self.colour_lut = colour_response_lut(imp.gain, imp.gamma, imp.white_balance) if imp.has_colour_response else None
        model = nominal.model
        self.H, self.W = model.height, model.width
        R = R_true.astype(np.float64)

        # --- pyramid grids -------------------------------------------------------------
        n_levels = 0
        while min((self.H + (1 << (n_levels + 1)) - 1) >> (n_levels + 1),
                  (self.W + (1 << (n_levels + 1)) - 1) >> (n_levels + 1)) >= MIN_LEVEL_PX:
            n_levels += 1
        if n_levels == 0:
            raise ConfigError(f"camera {nominal.name!r}: image {self.W}x{self.H} is too small to simulate (min 16 px)")
        xs = _axis_positions(self.W, n_levels)
        ys = _axis_positions(self.H, n_levels)
        self.levels: list[_Level] = []
        for m in range(n_levels + 1):
            (nx, ax, bx), (ny, ay, by) = xs[m], ys[m]
            if m == 0:
                rays = model.ray_map() @ R.T  # (H, W, 3) ENU unit rays
            else:
                gx = ax * np.arange(nx) + bx
                gy = ay * np.arange(ny) + by
                px = np.stack(np.meshgrid(gx, gy), axis=-1).reshape(-1, 2)
                rays = (model.pixel_to_ray(px) @ R.T).reshape(ny, nx, 3)
            dz = rays[..., 2]
            up = dz > 1e-6
            with np.errstate(divide="ignore", invalid="ignore"):
                inv_dz = np.where(up, 1.0 / np.where(up, dz, 1.0), 0.0)
            lvl = _Level(
                shape=(ny, nx),
                tanx=(rays[..., 0] * inv_dz).astype(np.float32),
                tany=(rays[..., 1] * inv_dz).astype(np.float32),
                inv_fp=np.clip(dz, 0.0, 1.0).astype(np.float32) ** 1.5,  # ÷ angular size below
            )
            self.levels.append(lvl)
            if m == 0:
                self.dirs = np.ascontiguousarray(np.moveaxis(rays, -1, 0), dtype=np.float32)  # (3, H, W)
                self.inv_dz = inv_dz.astype(np.float32)
                del rays, dz, up, inv_dz
                continue
            # angular size of one sample of this level [rad]: geometric mean along x and y
            gxr = np.linalg.norm(np.gradient(rays, axis=1), axis=-1)
            gyr = np.linalg.norm(np.gradient(rays, axis=0), axis=-1)
            alpha = (np.sqrt(gxr * gyr) + 1e-12).astype(np.float32)
            lvl.inv_fp /= alpha
            if m == 1:
                # full resolution: half of level 1's, interpolated (exact for a smooth lens,
                # and 4x cheaper than differentiating the full-size ray map)

                alpha0 = cv2.resize(alpha, (self.W, self.H), interpolation=cv2.INTER_LINEAR) * np.float32(0.5)
                self.levels[0].inv_fp /= alpha0
                self.zenith_px_rad = float(alpha0[self.H // 2, self.W // 2])  # near the centre [rad]
                del alpha0

        # --- static masks and colours ------------------------------------------------------
        circle = model.image_circle_mask()
        dz = self.dirs[2]
        self.sky = circle & (dz > 1e-6)  # pixels that see the sky
        self.ground = circle & ~self.sky
        theta = model.theta_map()
        zen = np.degrees(np.arccos(np.clip(dz, -1.0, 1.0)))
        blend = np.clip(zen / 90.0, 0.0, 1.0) ** 2
        vig = (1.0 - scene.image.vignetting * np.clip(theta / 90.0, 0.0, 1.5) ** 2) * scene.image.exposure
        self.vig = np.where(circle, vig, 0.0).astype(np.float32)
        z_bgr, h_bgr = np.array(scene.sky.zenith_bgr), np.array(scene.sky.horizon_bgr)
        self.sky_bgr = [(z_bgr[c] + (h_bgr[c] - z_bgr[c]) * blend).astype(np.float32) for c in range(3)]
        if scene.sky.haze_band > 0.0:  # a hazy horizon: the sky whitens in a band above it
            band = scene.sky.haze_band * np.exp(-np.clip(90.0 - zen, 0.0, None) / scene.sky.haze_band_deg)
            self.sky_bgr = [(s + (HAZE_BGR[c] - s) * band).astype(np.float32) for c, s in enumerate(self.sky_bgr)]
        self._obstacles(scene, index, zen)
        self._haze: dict[int, np.ndarray] = {}
        self._boxes: dict[tuple, tuple | None] = {}
        self._sun_key = None
        self._sun_maps = None

    def _obstacles(self, scene: Scene, index: int, zen: np.ndarray) -> None:
        """Obstacle pixels and colours: silhouettes by azimuth ("buildings", "trees") and the
        skyline kinds on an (azimuth, elevation) raster, whose edges are blurred as by a lens
        (``obstacle_alpha``: coverage of each pixel, None without skyline kinds)."""
        self.obstacle_idx = np.zeros(0, np.int64)
        self.obstacle_bgr = np.zeros((0, 3), np.float32)
        self.obstacle_alpha = None
        if not scene.obstacles:
            return
        prof, shade = obstacle_profile(tuple(o for o in scene.obstacles if o.kind not in SKYLINE_KINDS))
        bins = prof.shape[0] / 360.0
        az = np.degrees(np.arctan2(self.dirs[0], self.dirs[1])) % 360.0
        b = np.minimum((az * bins).astype(np.int64), prof.shape[0] - 1)
        obst = self.sky & ((90.0 - zen) < prof[b])
        colour = shade[b]
        if any(o.kind in SKYLINE_KINDS for o in scene.obstacles):
            ids, pal = skyline_raster(scene.obstacles)
            n = RASTER_BINS_PER_DEG
            row = np.clip((90.0 - zen) * n, -1, ids.shape[0]).astype(np.int64)
            col = np.minimum((az * n).astype(np.int64), ids.shape[1] - 1)
            look = self.sky & (row >= 0) & (row < ids.shape[0])
            k = np.zeros(zen.shape, np.int32)
            k[look] = ids[row[look], col[look]]
            obst |= k > 0
            haze = pal[k, 3:]  # a distant row's colour tends to the sky's behind it
            sky_col = np.stack(self.sky_bgr, axis=-1)
            colour = np.where((k > 0)[..., None], pal[k, :3] * (1.0 - haze) + sky_col * haze, colour)
        self.obstacle_idx = np.flatnonzero(obst)
        rng = np.random.default_rng(np.random.SeedSequence([scene.seed, 0x0B5, index]))
        tex = rng.uniform(0.85, 1.15, size=(self.obstacle_idx.size, 1))
        self.obstacle_bgr = (colour.reshape(-1, 3)[self.obstacle_idx] * tex).astype(np.float32)
        if any(o.kind in SKYLINE_KINDS for o in scene.obstacles):
            hit = obst.astype(np.float32)
            self.obstacle_alpha = cv2.GaussianBlur(hit, (5, 5), 0.7)

    def octave_box(self, layer_index: int, octave: int, level: int, wavelength_over_dh: float):
        """(r0, r1, c0, c1) of the level-grid box where an octave has weight > 0, or None (cached)."""
        key = (layer_index, octave, level)
        if key not in self._boxes:
            act = self.levels[level].inv_fp > np.float32(FADE_ZERO_PX / wavelength_over_dh)
            rows = np.flatnonzero(act.any(axis=1))
            cols = np.flatnonzero(act.any(axis=0))
            self._boxes[key] = None if rows.size == 0 else (rows[0], rows[-1] + 1, cols[0], cols[-1] + 1)
        return self._boxes[key]

    def haze(self, layer_index: int, dh_m: float, visibility_m: float) -> np.ndarray:
        """Transmittance of the air to a layer, exp(−range / visibility), (H, W) float32 (cached)."""
        h = self._haze.get(layer_index)
        if h is None:
            h = np.multiply(self.inv_dz, np.float32(-dh_m / visibility_m))
            np.exp(h, out=h)
            self._haze[layer_index] = h
            self._haze[(layer_index, "1-")] = np.subtract(np.float32(1.0), h)
        return h

    def one_minus_haze(self, layer_index: int) -> np.ndarray:
        return self._haze[(layer_index, "1-")]

    def sun_maps(self, sun_dir: np.ndarray, zenith_sun_deg: float, show_disk: bool):
        """(sky glow [× SUN_BGR], cloud illumination factor, thin-cloud forward glow or None) maps."""
        key = (tuple(np.round(sun_dir, 12)), show_disk)
        if key != self._sun_key:
            cosg = self.dirs[0] * np.float32(sun_dir[0])
            cosg += self.dirs[1] * np.float32(sun_dir[1])
            cosg += self.dirs[2] * np.float32(sun_dir[2])
            np.clip(cosg, -1.0, 1.0, out=cosg)
            gam = np.degrees(np.arccos(cosg))  # angle to the sun [deg]
            if show_disk and zenith_sun_deg < 90.0 + SUN_RADIUS_DEG:
                a, w = self.aureole  # circumsolar aureole: strength and core width
                glow = 1.3 * np.exp(-gam / 1.5) + a * (0.35 * np.exp(-gam / w) + 0.10 * np.exp(-gam / 35.0))
                r_disk = max(SUN_RADIUS_DEG, 1.5 * math.degrees(self.zenith_px_rad))
                glow[gam <= r_disk] += 4.0  # the disk saturates
                forward = (1.2 * np.exp(-gam / 5.0)).astype(np.float32)
            else:
                glow = np.zeros_like(gam)
                forward = None
            illum = 1.0 + 0.45 * np.exp(-gam / 20.0)
            self._sun_maps = (glow.astype(np.float32), illum.astype(np.float32), forward)
            self._sun_key = key
        return self._sun_maps


class _LayerState:
    def __init__(self, index: int, layer: CloudLayer, tex: LayerTexture):
        self.index = index
        self.layer = layer
        self.tex = tex
        self.threshold = tex.threshold(layer.coverage)
        lo = max(self.threshold, tex.shape_min())
        self.thick_lo = lo
        self.thick_span = max(tex.shape_max() - lo, 1e-3)
        self.edge = EDGE_WIDTH * layer.edge_softness


#: Largest simulated image width [px]: 8192² BGR + float32 truth maps are ~0.5 GB per camera.
MAX_SIZE_PX = 8192


class SkySimulator:
    """Renders a :class:`Scene` through a :class:`~cbh.geometry.station.Station`'s cameras.

    Parameters
    ----------
    station : Station
    scene : Scene
    size_px : int or None
        Render at this width (the first camera's), scaling every calibration
        (:meth:`Station.scaled`); None: the calibrations' own size.

    Attributes
    ----------
    station : Station
        The (possibly scaled) station the images belong to: process them with this one.
    scene : Scene

    Examples
    --------
    >>> from cbh.geometry.station import load_station
    >>> from cbh.presets import station_path
    >>> sim = SkySimulator(load_station(station_path()), load_scene("single-cumulus"), size_px=96)  # doctest: +SKIP
    >>> shot = sim.render()  # doctest: +SKIP
    """

    def __init__(self, station: Station, scene: Scene, size_px: int | None = None):
        if size_px is not None:
            if isinstance(size_px, bool) or not isinstance(size_px, (int, np.integer)) or size_px < 16:
                raise ConfigError(f"image size must be an integer >= 16 px, got {size_px!r}")
            if size_px > MAX_SIZE_PX:  # refused before anything is allocated
                raise ConfigError(f"image size {size_px} px is above the simulator's maximum of {MAX_SIZE_PX} px")
            station = station.scaled(int(size_px))
        for cam in scene.imperfections:
            if cam not in station.cameras:
                raise ConfigError(
                    f"scene imperfections: camera {cam!r} is not in station {station.name!r} "
                    f"(cameras: {', '.join(station.cameras)})"
                )
        self.station = station
        self.scene = scene
        self._cams = {name: _CameraState(i, cam, scene) for i, (name, cam) in enumerate(station.cameras.items())}
        # one texture per layer, shared by every camera; its octave plan uses the finest camera
        px_rad = min(c.zenith_px_rad for c in self._cams.values())
        max_level = min(len(c.levels) for c in self._cams.values()) - 1
        cam_z = float(np.mean([c.position_m[2] for c in station.cameras.values()]))
        self._layers = []
        for layer in scene.layers:
            dh = max(layer.height_m - cam_z, 1.0)
            fp = dh * px_rad  # zenith footprint of a full-res pixel [m]
            tex = LayerTexture(layer.texture_scale_m, layer.seed, FINEST_PX_PER_WAVELENGTH * fp, fp, max_level)
            self._layers.append(_LayerState(len(self._layers), layer, tex))
        # sensor noise bank per image size (views into it at random offsets per frame)
        self._noise_banks: dict[tuple[int, int], np.ndarray] = {}
        self._sequence = {name: 0 for name in self._cams}

    # --- public API --------------------------------------------------------------------
    @property
    def cameras(self) -> tuple[str, ...]:
        return tuple(self._cams)

    def output_white(self, name: str) -> np.ndarray:
        """The brightest value (3,) BGR [DN] camera ``name`` outputs: full white through its colour
        response (gain, tone curve, white balance) and its white level. A clipped sky reads this."""
        cs = self._cams[name]
        px = np.full((1, 1, 3), 255, np.uint8)
        if cs.colour_lut is not None:
            px = cv2.LUT(px, cs.colour_lut)
        return output_levels(px, self.scene.image.white_level, self.scene.image.limited_range).reshape(3).astype(np.float32)

    def sun(self, time_utc: datetime) -> tuple[float, float]:
        """Sun (zenith_deg, azimuth_deg) at ``time_utc``."""
        st = self.station
        return sun_position(self.scene, st.latitude_deg, st.longitude_deg, st.altitude_m, _utc(time_utc))

    def render(self, time_utc: datetime | None = None, cameras=None) -> SimShot:
        """Render every camera (or those named) at nominal time ``time_utc`` (default: scene start).

        Returns
        -------
        SimShot
        """
        t = self.scene.time_utc if time_utc is None else _utc(time_utc)
        names = list(self._cams) if cameras is None else [cameras] if isinstance(cameras, str) else list(cameras)
        views = {n: self.view(n, t) for n in names}
        zs, az = self.sun(t)
        return SimShot(time_utc=t, views=views, layers=self.scene.layers_at(t), sun_zenith_deg=zs, sun_azimuth_deg=az)

    def view(self, camera: str, time_utc: datetime | None = None) -> SimView:
        """Render one camera at nominal time ``time_utc`` (its clock offset applied)."""
        if camera not in self._cams:
            raise ConfigError(f"camera {camera!r} is not in station {self.station.name!r} "
                              f"(cameras: {', '.join(self._cams)})")
        cs = self._cams[camera]
        stamp = self.scene.time_utc if time_utc is None else _utc(time_utc)
        t = stamp + timedelta(seconds=cs.clock_offset_s)
        image, height, mask = self._render_camera(cs, t)
        return SimView(camera=camera, image=image, height_m=height, cloud_mask=mask,
                       time_utc=t, stamp_utc=stamp, true_camera=cs.true)

    def obstacle_mask(self, camera: str) -> np.ndarray:
        """Ground truth: pixels of horizon obstacles in ``camera``'s image, shape (H, W), bool."""
        if camera not in self._cams:
            raise ConfigError(f"camera {camera!r} is not in station {self.station.name!r}")
        cs = self._cams[camera]
        m = np.zeros(cs.H * cs.W, bool)
        m[cs.obstacle_idx] = True
        return m.reshape(cs.H, cs.W)

    def frame(self, camera: str, time_utc: datetime | None = None) -> Frame:
        """One camera's frame as a real camera delivers it: JPEG bytes and the decoded image.

        The frame is stamped with the nominal time (a clock offset is the camera's error).
        """
        from cbh.imageio import decode_image, encode_jpeg

        v = self.view(camera, time_utc)
        data = encode_jpeg(v.image, self.scene.image.jpeg_quality)
        seq = self._sequence[camera]
        self._sequence[camera] = seq + 1
        return Frame(camera=camera, time_utc=v.stamp_utc, image=decode_image(data, f"simulated {camera}"),
                     encoded=data, format="jpeg", sequence=seq)

    def frames(self, start_utc: datetime | None = None, n: int = 1, cadence_s: float = 10.0) -> Iterator[SimShot]:
        """``n`` shots every ``cadence_s`` seconds from ``start_utc`` (default: scene start)."""
        t0 = self.scene.time_utc if start_utc is None else _utc(start_utc)
        for i in range(int(n)):
            yield self.render(t0 + timedelta(seconds=i * float(cadence_s)))

    # --- rendering -----------------------------------------------------------------------
    def _texture(self, cs: _CameraState, ls: _LayerState, offset_m: tuple[float, float]):
        """Shape and detail fields of a layer on camera ``cs``'s full-res grid, (H, W) float32 each."""
        tex = ls.tex
        dh = ls.layer.height_m - float(cs.true.position_m[2])
        # texture coordinate of a pixel: (cam_en + dh·tan − offset)·scale + tile offset
        base_e = float(cs.true.position_m[0]) - offset_m[0]
        base_n = float(cs.true.position_m[1]) - offset_m[1]
        by_level: dict[int, list] = {}
        for k, o in enumerate(tex.octaves):
            by_level.setdefault(o.level, []).append(k)
        top = max(by_level)
        shape = detail = None
        for m in range(top, -1, -1):
            lvl = cs.levels[m]
            h, w = lvl.shape
            if shape is None:
                shape = np.zeros((h, w), np.float32)
                detail = np.zeros((h, w), np.float32)
            else:
                shape = cv2.resize(shape, (w, h), interpolation=cv2.INTER_LINEAR)
                detail = cv2.resize(detail, (w, h), interpolation=cv2.INTER_LINEAR)
            for k in by_level.get(m, ()):
                o = tex.octaves[k]
                box = cs.octave_box(ls.index, k, m, o.wavelength_m / dh)
                if box is None:  # the octave is finer than this grid everywhere
                    continue
                r0, r1, c0, c1 = box
                a = np.float32(dh * o.scale)
                cu = np.float32((base_e * o.scale + o.offset_px[0]) % TILE_PX)
                cv_ = np.float32((base_n * o.scale + o.offset_px[1]) % TILE_PX)
                u = np.multiply(lvl.tanx[r0:r1, c0:c1], a)
                u += cu
                v = np.multiply(lvl.tany[r0:r1, c0:c1], a)
                v += cv_
                if o.transpose:
                    u, v = v, u
                t = sample_tile(tex.tiles_padded[o.tile], u, v)
                t *= fade_weight(lvl.inv_fp[r0:r1, c0:c1], o.wavelength_m / dh, u)
                if o.shape_amp:
                    shape[r0:r1, c0:c1] += np.float32(o.shape_amp) * t
                if o.detail_amp:
                    detail[r0:r1, c0:c1] += np.float32(o.detail_amp) * t
        return shape, detail

    def _render_camera(self, cs: _CameraState, t: datetime):
        scene = self.scene
        H, W = cs.H, cs.W
        zs, az = self.sun(t)
        sdir = sun_direction(zs, az)
        glow, illum, forward = cs.sun_maps(sdir, zs, scene.sun.disk)
        daylight = float(np.clip((98.0 - zs) / 10.0, 0.03, 1.0))
        dt_s = (t - scene.time_utc).total_seconds()

        trans = np.ones((H, W), np.float32)  # transmittance to the sky behind the clouds
        airlight = np.zeros((H, W), np.float32)  # weight of hazy air (sky-coloured) in front of clouds
        lum = np.zeros((H, W), np.float32)  # cloud radiance reaching the camera [DN/255]
        height = np.full((H, W), np.nan, np.float32)
        mask = np.zeros((H, W), bool)
        sky = cs.sky
        for ls in self._layers:
            layer = ls.layer.advected(dt_s)
            if layer.coverage <= 0.0:
                continue
            dh = layer.height_m - float(cs.true.position_m[2])
            if dh <= 0.0:  # at or below this camera: an upward camera cannot see its base
                continue
            shape, detail = self._texture(cs, ls, layer.offset_m)
            # thickness 0..1 from the shape field (before it is reused in place)
            thick = np.subtract(shape, np.float32(ls.thick_lo))
            thick *= np.float32(1.0 / ls.thick_span)
            np.clip(thick, 0.0, 1.0, out=thick)
            if ls.threshold == -math.inf:  # overcast: cloud everywhere
                m = sky.copy()
                alpha = np.ones((H, W), np.float32)
            else:
                x = shape
                x -= np.float32(ls.threshold)
                m = x > 0
                m &= sky
                # opacity: soft edge around the threshold (alpha = 0.5 on the mask's edge)
                alpha = np.multiply(x, np.float32(1.0 / ls.edge), out=x)
                alpha += np.float32(0.5)
                np.clip(alpha, 0.0, 1.0, out=alpha)
            new = m & ~mask
            np.copyto(height, np.float32(layer.height_m), where=new)
            mask |= m
            tau = cs.haze(ls.index, dh, scene.sky.visibility_m)  # air between camera and cloud
            # brightness: darker where thick, textured by the detail field, lit near the sun
            k = np.float32(layer.brightness)
            lcl = np.multiply(detail, np.float32(DETAIL_CONTRAST * layer.contrast), out=detail)
            lcl += np.float32(1.0)
            base = np.multiply(thick, np.float32(-0.42) * k)
            base += np.float32(0.96) * k
            lcl *= base
            lcl *= illum
            if forward is not None:  # thin cloud glows in front of the sun
                np.subtract(np.float32(1.0), thick, out=thick)
                thick *= forward
                if k != 1.0:
                    thick *= k
                lcl += thick
            # the opaque part (alpha) of this layer seen through what is in front of it;
            # the haze replaces the fraction 1 − tau of the cloud's light by airlight (sky colour).
            # (alpha off the sky does not matter: vignetting is 0 outside the image circle and
            # ground pixels are painted over.)
            vis = np.multiply(alpha, trans, out=base)
            lcl *= vis
            lcl *= tau
            lum += lcl
            vis *= cs.one_minus_haze(ls.index)
            airlight += vis
            np.subtract(np.float32(1.0), alpha, out=alpha)
            trans *= alpha

        image = self._compose(cs, t, glow, trans, airlight, lum, daylight)
        return self._camera_output(cs, image, height, mask, daylight), height, mask

    def _compose(self, cs: _CameraState, t: datetime, glow, trans, airlight, lum, daylight: float) -> np.ndarray:
        """Sky, sun glow, airlight and cloud radiance into one noisy BGR uint8 image."""
        cloud_bgr = (0.893, 0.911, 0.93)  # grey-white, slightly warm: blue/red ≈ 0.96
        noise = self._noise_views(cs, t)
        chans = []
        for c in range(3):
            sky_c = np.multiply(glow, np.float32(SUN_BGR[c]))
            sky_c += cs.sky_bgr[c]
            sky_c *= trans
            sky_c += airlight * cs.sky_bgr[c]
            cl = np.multiply(lum, np.float32(255.0 * cloud_bgr[c]))
            sky_c += cl
            sky_c *= np.float32(daylight)
            sky_c *= cs.vig
            if noise is not None:
                sky_c += noise[c]
            chans.append(sky_c)
        img = cv2.merge(chans)
        np.clip(img, 0.0, 255.0, out=img)
        img += np.float32(0.5)
        return img.astype(np.uint8)

    def _camera_output(self, cs: _CameraState, image: np.ndarray, height: np.ndarray, mask: np.ndarray,
                       daylight: float) -> np.ndarray:
        """Ground and obstacles painted in (their truth: no height, no cloud; ``height`` and
        ``mask`` edited in place), then the camera's colour response, output levels and JPEG."""
        scene = self.scene
        if cs.ground.any():
            image[cs.ground] = np.array(GROUND_BGR) * daylight
        if cs.obstacle_idx.size:
            flat = image.reshape(-1, 3)
            if cs.obstacle_alpha is None:
                flat[cs.obstacle_idx] = np.clip(cs.obstacle_bgr * daylight, 0, 255).astype(np.uint8)
            else:  # the lens blurs the skyline's edges into the sky (and the sky into thin masts)
                paint = np.zeros(flat.shape, np.float32)
                paint[cs.obstacle_idx] = cs.obstacle_bgr * daylight
                paint = cv2.GaussianBlur(paint.reshape(image.shape), (5, 5), 0.7)
                a = cs.obstacle_alpha[..., None]
                image = np.clip(image * (1.0 - a) + paint + 0.5, 0, 255).astype(np.uint8)
            height.reshape(-1)[cs.obstacle_idx] = np.nan
            mask.reshape(-1)[cs.obstacle_idx] = False
        if cs.colour_lut is not None:  # the camera's own gain, tone curve and white balance
            image = cv2.LUT(image, cs.colour_lut)
        image = output_levels(image, scene.image.white_level, scene.image.limited_range)
        if scene.image.jpeg_roundtrip:
            from cbh.imageio import decode_image, encode_jpeg

            image = decode_image(encode_jpeg(image, scene.image.jpeg_quality), "simulated image")
        if scene.image.reencode_quality > 0:
            image = reencode(image, scene.image.reencode_quality)
        return image

    def _noise_views(self, cs: _CameraState, t: datetime):
        sigma = self.scene.image.noise_dn
        if sigma <= 0:
            return None
        key = (cs.H, cs.W)
        bank = self._noise_banks.get(key)
        if bank is None:
            rng = np.random.default_rng(np.random.SeedSequence([self.scene.seed, 0x4015E, cs.H, cs.W]))
            bank = rng.standard_normal((cs.H + NOISE_PAD, cs.W + NOISE_PAD), dtype=np.float32)
            bank *= np.float32(sigma)
            self._noise_banks[key] = bank
        rng = np.random.default_rng(np.random.SeedSequence([self.scene.seed, cs.index, to_ns(t) & (2**63 - 1)]))
        offs = rng.integers(0, NOISE_PAD, size=(3, 2))
        return [bank[oy:oy + cs.H, ox:ox + cs.W] for oy, ox in offs]


def colour_response_lut(gain: float, gamma: float, white_balance: tuple[float, float]) -> np.ndarray:
    """Per-channel lookup table (256, 1, 3) uint8 of a camera colour response (BGR order).

    out_c = 255 · clip(gain · wb_c · in_c / 255, 0, 1)^gamma with wb = (blue, 1, red) gains:
    an exposure gain and white balance on the (display-referred) rendered values followed by a
    tone curve, which is what independently exposing cameras differ by.
    """
    wb_r, wb_b = white_balance
    x = np.arange(256, dtype=np.float64) / 255.0
    chans = [np.clip(gain * w * x, 0.0, 1.0) ** gamma for w in (wb_b, 1.0, wb_r)]
    return np.clip(np.round(255.0 * np.stack(chans, axis=-1)), 0, 255).astype(np.uint8).reshape(256, 1, 3)


def output_levels(image: np.ndarray, white_level: int = 255, limited_range: bool = False) -> np.ndarray:
    """A camera's output levels: values clipped at its ``white_level`` [DN], then optionally
    squeezed into video's limited range 16..235 (as IP cameras stream H.264 over RTSP)."""
    if white_level >= 255 and not limited_range:
        return image
    lut = np.minimum(np.arange(256), white_level).astype(np.float64)
    if limited_range:
        lut = 16.0 + lut * (219.0 / 255.0)
    return cv2.LUT(image, np.round(lut).astype(np.uint8))


def reencode(image: np.ndarray, quality: int) -> np.ndarray:
    """A frame saved again by a recorder: its decoded pixels re-encoded as JPEG of ``quality``
    with 4:2:0 chroma subsampling (a second quantisation; ringing round sharp edges such as a
    clipped sun disk lifts them above the clip level), and decoded."""
    ok, buf = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, int(quality),
                                           cv2.IMWRITE_JPEG_SAMPLING_FACTOR, cv2.IMWRITE_JPEG_SAMPLING_FACTOR_420])
    if not ok:  # pragma: no cover - OpenCV always encodes uint8 BGR
        raise ConfigError("JPEG re-encoding failed")
    return cv2.imdecode(buf, cv2.IMREAD_COLOR)


def _utc(t: datetime) -> datetime:
    if not isinstance(t, datetime):
        raise ConfigError(f"expected a datetime, got {t!r}")
    if t.tzinfo is None:
        raise ConfigError(f"naive datetime {t.isoformat()}: simulator times must be timezone-aware UTC")
    return t.astimezone(timezone.utc)
