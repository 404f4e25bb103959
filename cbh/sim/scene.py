"""Synthetic sky scenes: cloud layers, sun, sky, obstacles, camera imperfections (TOML).

A scene says *what is in the sky*; the station (:mod:`cbh.geometry.station`) says *who looks at it*.
:class:`cbh.sim.SkySimulator` renders one through the other. Every table and key is optional
except ``[[layers]]`` entries' ``height_m`` and ``coverage``, ``[[obstacles]]`` entries'
``kind``, ``azimuth_deg`` and ``max_elevation_deg``, and ``[[imperfections]]`` entries'
``camera``; unknown keys are a :class:`~cbh.errors.ConfigError`
naming the key path (e.g. ``layers[1].coverage``). Heights are above the station's ENU origin.

The file format::

    name = "two-layers"                    # free text, defaults to the file stem
    description = "..."                    # free text
    time_utc = 2024-06-21T15:00:00Z        # start time (TOML datetime with offset, or ISO string
                                           # ending in Z); layer positions are given at this time
    seed = 7                               # sensor noise and obstacle shapes

    [sun]
    position = "true"                      # "true": pvlib solar position for the station's
                                           # latitude/longitude at the capture time; "fixed": below
    zenith_deg = 35.0                      # "fixed" only: sun zenith angle [deg]
    azimuth_deg = 120.0                    # "fixed" only: clockwise from north [deg]
    disk = true                            # draw the sun disk, glow and saturation

    [sky]
    zenith_bgr = [200, 125, 70]            # clear-sky colour at the zenith (B, G, R) [DN]
    horizon_bgr = [235, 215, 200]          # clear-sky colour at the horizon [DN]
    visibility_m = 40000.0                 # clouds fade into the haze over this range [m]
    aureole = 1.0                          # strength of the circumsolar aureole (whitish glow
                                           # around the sun, beyond the disk) relative to default
    aureole_width_deg = 8.0                # e-folding angle of the aureole's core [deg]
    haze_band = 0.0                        # hazy horizon: the clear sky whitens towards a pale
                                           # band at the horizon by this fraction, 0..1
    haze_band_deg = 4.0                    # e-folding elevation of that band [deg]

    [image]
    exposure = 1.0                         # brightness factor of the whole image
    vignetting = 0.25                      # brightness loss at 90 deg from the optical axis, 0..1
    noise_dn = 1.5                         # sensor noise standard deviation [DN]
    jpeg_quality = 92                      # JPEG quality of SkySimulator.frame() (1..100)
    jpeg_roundtrip = false                 # render() images also go through JPEG
    white_level = 255                      # sensor clip level [DN]: values above it read as it
    limited_range = false                  # video levels: 0..255 squeezed into 16..235 (RTSP/H.264)
    reencode_quality = 0                   # 1..100: the recorder saves the (decoded) frame again as
                                           # JPEG of this quality, chroma 4:2:0 (0: not re-encoded)

    [[layers]]                             # any number; listed in any order
    height_m = 1500.0                      # cloud base above the ENU origin [m], > 0
    coverage = 0.4                         # fraction of the layer's area that is cloud, 0..1
    texture_scale_m = 800.0                # size of the largest cloud features [m], > 0
    wind_ms = [6.0, -2.0]                  # drift (east, north) [m/s]
    seed = 11                              # texture seed
    offset_m = [0.0, 0.0]                  # texture shift (east, north) at time_utc [m]
    brightness = 1.0                       # cloud-base brightness factor (dark rain base < 1)
    contrast = 1.0                         # internal texture contrast factor
    edge_softness = 1.0                    # width of the soft cloud edge, relative

    [[obstacles]]                          # horizon silhouettes; their pixels have no height
    kind = "buildings"                     # "buildings", "trees", or a skyline: "skyline" (rows of
                                           # blocks with notches and antennas), "masts" (thin poles),
                                           # "treeline" (crowns with sky between the branches),
                                           # "walls" (sunlit façades brighter than the sky)
    azimuth_deg = [30.0, 95.0]             # azimuth range, clockwise from north [deg]
    max_elevation_deg = 14.0               # tallest silhouette [deg above the horizon]
    seed = 3

    [[imperfections]]                      # per camera, all off by default
    camera = "cam2"
    clock_offset_s = 2.0                   # the camera captures this late (its stamp is on time)
    rotation_error_deg = [0.5, 0.0, 0.0]   # true (yaw, pitch, roll) minus the station file's [deg]
    gain = 1.0                             # colour response: exposure gain on linear values [1]
    gamma = 1.0                            #   tone curve exponent: out = 255·(gain·wb·in/255)^gamma
    white_balance = [1.0, 1.0]             #   (red, blue) channel gains relative to green [1]
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from datetime import datetime, timezone
from pathlib import Path

from cbh.errors import ConfigError
from cbh import tomlio
from cbh.tomlio import read_toml
from cbh.timeutil import parse_utc

__all__ = [
    "Scene", "CloudLayer", "Sun", "Sky", "ImageSettings", "Obstacle", "Imperfection",
    "load_scene", "parse_scene", "with_clock_offsets", "DEFAULT_TIME_UTC",
]

#: Start time of a scene that gives none (a clear mid-morning in Brasília).
DEFAULT_TIME_UTC = datetime(2024, 6, 21, 14, 0, 0, tzinfo=timezone.utc)

SUN_POSITIONS = ("true", "fixed")
OBSTACLE_KINDS = ("buildings", "trees", "skyline", "masts", "treeline", "walls")


@dataclass(frozen=True)
class CloudLayer:
    """A horizontal cloud base with a fractal texture drifting with the wind.

    Attributes
    ----------
    height_m : float
        Cloud-base height above the ENU origin [m].
    coverage : float
        Fraction of the layer's area that is cloud, 0..1.
    texture_scale_m : float
        Size (wavelength) of the largest cloud features [m].
    wind_ms : tuple of float
        Drift (east, north) [m/s].
    seed : int
        Texture seed.
    offset_m : tuple of float
        Texture shift (east, north) [m]: the scene's value at ``time_utc``; in a rendered
        :class:`~cbh.sim.SimShot` the advected shift at that time.
    brightness, contrast, edge_softness : float
        Shading factors (1 = default look).
    """

    height_m: float
    coverage: float
    texture_scale_m: float = 800.0
    wind_ms: tuple[float, float] = (0.0, 0.0)
    seed: int = 0
    offset_m: tuple[float, float] = (0.0, 0.0)
    brightness: float = 1.0
    contrast: float = 1.0
    edge_softness: float = 1.0

    def advected(self, dt_s: float) -> "CloudLayer":
        """This layer ``dt_s`` seconds later (offset moved by wind · dt)."""
        return replace(
            self,
            offset_m=(self.offset_m[0] + self.wind_ms[0] * dt_s, self.offset_m[1] + self.wind_ms[1] * dt_s),
        )

    def to_dict(self) -> dict:
        return {
            "height_m": float(self.height_m),
            "coverage": float(self.coverage),
            "texture_scale_m": float(self.texture_scale_m),
            "wind_ms": [float(v) for v in self.wind_ms],
            "seed": int(self.seed),
            "offset_m": [float(v) for v in self.offset_m],
            "brightness": float(self.brightness),
            "contrast": float(self.contrast),
            "edge_softness": float(self.edge_softness),
        }


@dataclass(frozen=True)
class Sun:
    position: str = "true"  # "true" (pvlib) or "fixed"
    zenith_deg: float = 35.0  # "fixed": zenith angle [deg]
    azimuth_deg: float = 120.0  # "fixed": azimuth, clockwise from north [deg]
    disk: bool = True  # draw disk, glow and saturation


@dataclass(frozen=True)
class Sky:
    zenith_bgr: tuple[float, float, float] = (200.0, 125.0, 70.0)  # clear sky at the zenith [DN]
    horizon_bgr: tuple[float, float, float] = (235.0, 215.0, 200.0)  # clear sky at the horizon [DN]
    visibility_m: float = 40_000.0  # clouds fade into haze over this range [m]
    aureole: float = 1.0  # circumsolar aureole strength relative to the default [1]
    aureole_width_deg: float = 8.0  # e-folding angle of the aureole's core [deg]
    haze_band: float = 0.0  # hazy horizon: whitening of the clear sky at the horizon, 0..1 [1]
    haze_band_deg: float = 4.0  # e-folding elevation of the hazy band [deg]


@dataclass(frozen=True)
class ImageSettings:
    exposure: float = 1.0  # overall brightness factor
    vignetting: float = 0.25  # relative brightness loss at 90 deg off-axis, 0..1
    noise_dn: float = 1.5  # sensor noise std [DN]
    jpeg_quality: int = 92  # quality of encoded frames, 1..100
    jpeg_roundtrip: bool = False  # render() images go through JPEG too
    white_level: int = 255  # sensor clip level [DN]
    limited_range: bool = False  # video levels 16..235 instead of 0..255
    reencode_quality: int = 0  # the recorder's second JPEG (4:2:0) of the decoded frame, 1..100; 0 = none


@dataclass(frozen=True)
class Obstacle:
    kind: str  # "buildings" or "trees"
    azimuth_deg: tuple[float, float]  # azimuth range, clockwise from north [deg]
    max_elevation_deg: float  # tallest silhouette above the horizon [deg]
    seed: int = 0


@dataclass(frozen=True)
class Imperfection:
    camera: str
    clock_offset_s: float = 0.0  # the camera captures this many seconds late [s]
    rotation_error_deg: tuple[float, float, float] = (0.0, 0.0, 0.0)  # true minus nominal (yaw, pitch, roll) [deg]
    gain: float = 1.0  # colour response: exposure gain applied to the rendered values [1]
    gamma: float = 1.0  # tone-curve exponent: out = 255 · clip(gain · wb · in / 255)^gamma [1]
    white_balance: tuple[float, float] = (1.0, 1.0)  # (red, blue) gains relative to green [1]

    @property
    def has_colour_response(self) -> bool:
        """True when the camera's colour response differs from the identity."""
        return (self.gain, self.gamma, tuple(self.white_balance)) != (1.0, 1.0, (1.0, 1.0))


@dataclass(frozen=True)
class Scene:
    """A synthetic sky (see the module docstring for the TOML form).

    Attributes
    ----------
    layers : tuple of CloudLayer
        Ascending by height (sorted on construction).
    time_utc : datetime
        Start time (aware UTC); layer offsets are given at this time.
    sun, sky, image : Sun, Sky, ImageSettings
    obstacles : tuple of Obstacle
    imperfections : dict of str → Imperfection
        Per camera name.
    seed : int
    name : str
    path : Path or None
    """

    layers: tuple[CloudLayer, ...] = ()
    time_utc: datetime = DEFAULT_TIME_UTC
    sun: Sun = Sun()
    sky: Sky = Sky()
    image: ImageSettings = ImageSettings()
    obstacles: tuple[Obstacle, ...] = ()
    imperfections: dict[str, Imperfection] = field(default_factory=dict)
    seed: int = 0
    name: str = "scene"
    description: str = ""
    path: Path | None = None

    def __post_init__(self):
        # rendering relies on ascending heights (a lower layer hides a higher one)
        object.__setattr__(self, "layers", tuple(sorted(self.layers, key=lambda l: l.height_m)))

    def imperfection(self, camera: str) -> Imperfection:
        return self.imperfections.get(camera) or Imperfection(camera=camera)

    def layers_at(self, time_utc: datetime) -> tuple[CloudLayer, ...]:
        """The layers advected to ``time_utc``."""
        dt = (time_utc - self.time_utc).total_seconds()
        return tuple(l.advected(dt) for l in self.layers)


# --- parsing ------------------------------------------------------------------------------

def _unknown(where: str, table: dict, allowed) -> None:
    try:
        tomlio.check_keys(where, table, allowed)
    except ConfigError as exc:
        raise ConfigError(f"scene: {exc}") from None


def _table(where: str, value) -> dict:
    return tomlio.table(f"scene: {where}", value)


def _num(where: str, value, *, lo=None, hi=None, lo_open=False) -> float:
    return tomlio.number(f"scene: {where}", value, lo=lo, hi=hi, lo_open=lo_open)


def _int(where: str, value, *, lo=None, hi=None) -> int:
    return tomlio.integer(f"scene: {where}", value, lo=lo, hi=hi)


def _bool(where: str, value) -> bool:
    return tomlio.boolean(f"scene: {where}", value)


def _str(where: str, value) -> str:
    return tomlio.string(f"scene: {where}", value)


def _vec(where: str, value, n: int, **kw) -> tuple[float, ...]:
    return tomlio.vector(f"scene: {where}", value, n, **kw)


def _time(where: str, value) -> datetime:
    return parse_utc(value, f"scene: {where}", error=ConfigError)


def _choice(where: str, value, choices) -> str:
    return tomlio.choice(f"scene: {where}", value, choices)


def _parse_layer(where: str, d) -> CloudLayer:
    d = _table(where, d)
    _unknown(where, d, CloudLayer.__dataclass_fields__)
    if "height_m" not in d:
        raise ConfigError(f"scene: {where}.height_m: missing")
    if "coverage" not in d:
        raise ConfigError(f"scene: {where}.coverage: missing")
    return CloudLayer(
        height_m=_num(f"{where}.height_m", d["height_m"], lo=0.0, lo_open=True),
        coverage=_num(f"{where}.coverage", d["coverage"], lo=0.0, hi=1.0),
        texture_scale_m=_num(f"{where}.texture_scale_m", d.get("texture_scale_m", 800.0), lo=0.0, lo_open=True),
        wind_ms=_vec(f"{where}.wind_ms", d.get("wind_ms", [0.0, 0.0]), 2),
        seed=_int(f"{where}.seed", d.get("seed", 0), lo=0, hi=2**32 - 1),
        offset_m=_vec(f"{where}.offset_m", d.get("offset_m", [0.0, 0.0]), 2),
        brightness=_num(f"{where}.brightness", d.get("brightness", 1.0), lo=0.0, lo_open=True, hi=3.0),
        contrast=_num(f"{where}.contrast", d.get("contrast", 1.0), lo=0.0, hi=5.0),
        edge_softness=_num(f"{where}.edge_softness", d.get("edge_softness", 1.0), lo=0.0, lo_open=True, hi=20.0),
    )


def _parse_sun(d) -> Sun:
    sun_d = _table("sun", d)
    _unknown("sun", sun_d, Sun.__dataclass_fields__)
    return Sun(
        position=_choice("sun.position", sun_d.get("position", Sun.position), SUN_POSITIONS),
        zenith_deg=_num("sun.zenith_deg", sun_d.get("zenith_deg", Sun.zenith_deg), lo=0.0, hi=180.0),
        azimuth_deg=_num("sun.azimuth_deg", sun_d.get("azimuth_deg", Sun.azimuth_deg)) % 360.0,
        disk=_bool("sun.disk", sun_d.get("disk", True)),
    )


def _parse_sky(d) -> Sky:
    sky_d = _table("sky", d)
    _unknown("sky", sky_d, Sky.__dataclass_fields__)
    return Sky(
        zenith_bgr=_vec("sky.zenith_bgr", sky_d.get("zenith_bgr", list(Sky.zenith_bgr)), 3, lo=0.0, hi=255.0),
        horizon_bgr=_vec("sky.horizon_bgr", sky_d.get("horizon_bgr", list(Sky.horizon_bgr)), 3, lo=0.0, hi=255.0),
        visibility_m=_num("sky.visibility_m", sky_d.get("visibility_m", Sky.visibility_m), lo=0.0, lo_open=True),
        aureole=_num("sky.aureole", sky_d.get("aureole", Sky.aureole), lo=0.0, hi=20.0),
        aureole_width_deg=_num("sky.aureole_width_deg", sky_d.get("aureole_width_deg", Sky.aureole_width_deg),
                               lo=0.5, hi=60.0),
        haze_band=_num("sky.haze_band", sky_d.get("haze_band", Sky.haze_band), lo=0.0, hi=1.0),
        haze_band_deg=_num("sky.haze_band_deg", sky_d.get("haze_band_deg", Sky.haze_band_deg), lo=0.2, hi=30.0),
    )


def _parse_image(d) -> ImageSettings:
    im_d = _table("image", d)
    _unknown("image", im_d, ImageSettings.__dataclass_fields__)
    return ImageSettings(
        exposure=_num("image.exposure", im_d.get("exposure", 1.0), lo=0.0, lo_open=True, hi=10.0),
        vignetting=_num("image.vignetting", im_d.get("vignetting", ImageSettings.vignetting), lo=0.0, hi=1.0),
        noise_dn=_num("image.noise_dn", im_d.get("noise_dn", ImageSettings.noise_dn), lo=0.0, hi=100.0),
        jpeg_quality=_int("image.jpeg_quality", im_d.get("jpeg_quality", ImageSettings.jpeg_quality), lo=1, hi=100),
        jpeg_roundtrip=_bool("image.jpeg_roundtrip", im_d.get("jpeg_roundtrip", False)),
        white_level=_int("image.white_level", im_d.get("white_level", 255), lo=128, hi=255),
        limited_range=_bool("image.limited_range", im_d.get("limited_range", False)),
        reencode_quality=_int("image.reencode_quality", im_d.get("reencode_quality", 0), lo=0, hi=100),
    )


def _array(data: dict, key: str) -> list:
    raw = data.get(key, [])
    if not isinstance(raw, list):
        raise ConfigError(f"scene: {key}: expected an array of tables ([[{key}]])")
    return raw


def _parse_obstacle(i: int, d) -> Obstacle:
    w = f"obstacles[{i}]"
    d = _table(w, d)
    _unknown(w, d, Obstacle.__dataclass_fields__)
    for key in ("kind", "azimuth_deg", "max_elevation_deg"):
        if key not in d:
            raise ConfigError(f"scene: {w}.{key}: missing")
    return Obstacle(
        kind=_choice(f"{w}.kind", d["kind"], OBSTACLE_KINDS),
        azimuth_deg=_vec(f"{w}.azimuth_deg", d["azimuth_deg"], 2),
        max_elevation_deg=_num(f"{w}.max_elevation_deg", d["max_elevation_deg"], lo=0.0, lo_open=True, hi=60.0),
        seed=_int(f"{w}.seed", d.get("seed", i), lo=0, hi=2**32 - 1),
    )


def _parse_imperfections(raw: list) -> dict[str, Imperfection]:
    imperfections: dict[str, Imperfection] = {}
    for i, d in enumerate(raw):
        w = f"imperfections[{i}]"
        d = _table(w, d)
        _unknown(w, d, Imperfection.__dataclass_fields__)
        if "camera" not in d:
            raise ConfigError(f"scene: {w}.camera: missing")
        cam = _str(f"{w}.camera", d["camera"])
        if cam in imperfections:
            raise ConfigError(f"scene: {w}.camera: camera {cam!r} already has imperfections")
        imperfections[cam] = Imperfection(
            camera=cam,
            clock_offset_s=_num(f"{w}.clock_offset_s", d.get("clock_offset_s", 0.0), lo=-3600.0, hi=3600.0),
            rotation_error_deg=_vec(f"{w}.rotation_error_deg", d.get("rotation_error_deg", [0.0, 0.0, 0.0]), 3,
                                    lo=-45.0, hi=45.0),
            gain=_num(f"{w}.gain", d.get("gain", 1.0), lo=0.05, hi=20.0),
            gamma=_num(f"{w}.gamma", d.get("gamma", 1.0), lo=0.2, hi=5.0),
            white_balance=_vec(f"{w}.white_balance", d.get("white_balance", [1.0, 1.0]), 2, lo=0.2, hi=5.0),
        )
    return imperfections


def parse_scene(data: dict, *, name: str = "scene", path: Path | None = None) -> Scene:
    """Validate a scene dict (as read from TOML) into a :class:`Scene`.

    Raises
    ------
    ConfigError
        Unknown key, wrong type or out-of-range value; the message names the key path.
    """
    data = _table("top level", data)
    _unknown("", data, ("name", "description", "time_utc", "seed", "sun", "sky", "image",
                        "layers", "obstacles", "imperfections"))
    sun, sky, image = _parse_sun(data.get("sun", {})), _parse_sky(data.get("sky", {})), _parse_image(data.get("image", {}))
    layers = sorted((_parse_layer(f"layers[{i}]", d) for i, d in enumerate(_array(data, "layers"))),
                    key=lambda l: l.height_m)
    obstacles = [_parse_obstacle(i, d) for i, d in enumerate(_array(data, "obstacles"))]
    imperfections = _parse_imperfections(_array(data, "imperfections"))
    return Scene(
        layers=tuple(layers),
        time_utc=_time("time_utc", data["time_utc"]) if "time_utc" in data else DEFAULT_TIME_UTC,
        sun=sun,
        sky=sky,
        image=image,
        obstacles=tuple(obstacles),
        imperfections=imperfections,
        seed=_int("seed", data.get("seed", 0), lo=0, hi=2**32 - 1),
        name=_str("name", data.get("name", name)),
        description=_str("description", data.get("description", "")),
        path=path,
    )


def load_scene(path: str | Path) -> Scene:
    """Read a scene TOML file, or a preset name (``two-layers``) from ``configs/scenes``.

    Raises
    ------
    ConfigError
        Missing file, malformed TOML, or a bad key (the message names it).
    """
    p = Path(path)
    if not p.exists() and p.suffix != ".toml":
        from cbh.presets import scene_path

        p = scene_path(str(path))
    data = read_toml(p, "scene")
    try:
        return parse_scene(data, name=p.stem, path=p)
    except ConfigError as exc:
        msg = str(exc)
        raise ConfigError(f"scene {p.name}: {msg.removeprefix('scene: ')}") from None


def with_clock_offsets(scene: Scene, specs) -> Scene:
    """The scene with per-camera clock offsets set from ``CAMERA=SECONDS`` strings (e.g. the
    ``cbh simulate --clock-offset cam2=3`` option); other imperfections are kept.

    Raises
    ------
    ConfigError
        A spec that is not ``CAMERA=SECONDS`` with a finite number.
    """
    imps = dict(scene.imperfections)
    for spec in specs:
        cam, sep, val = str(spec).partition("=")
        try:
            sec = float(val)
        except ValueError:
            sec = math.nan
        if not sep or not cam.strip() or not math.isfinite(sec):
            raise ConfigError(f"--clock-offset {spec!r}: expected CAMERA=SECONDS, e.g. cam2=3")
        cam = cam.strip()
        imps[cam] = replace(imps.get(cam) or Imperfection(camera=cam), clock_offset_s=sec)
    return replace(scene, imperfections=imps)
