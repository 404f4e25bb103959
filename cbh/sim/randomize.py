"""Randomized skies (domain randomization) for robustness benchmarks and regression seeds.

:func:`random_case` draws one station + scene from wide physical distributions instead of a
few presets, so that the pipeline is judged on the class of inputs and not on one sample:

- sky type: clear (20 %), broken (60 %: 1–3 layers), overcast (20 %: a full lowest layer);
- layers 300 m – 10 km (log-uniform, ≥ 35 % apart), coverage 0.15–0.7, texture 300–3000 m,
  winds 0–30 m/s in any direction, dark to bright bases, soft to sharp edges;
- baselines 20–200 m in any direction, each camera yawed anywhere;
- the sun from 10° to 85° zenith at any azimuth; the circumsolar aureole 0.3–4 × the default
  strength and 4–15° wide; clear-sky colours from deep to pale blue; haze;
- horizon obstacles (buildings, trees) in half of the skies, the station's mask given for
  half of those;
- per camera: colour response (gain, gamma, white balance), sensor noise, JPEG quality,
  vignetting, white level 235–255, and limited-range video (16–235) in 15 % of the skies.

:class:`RandomOptions` widens the distribution (issue 33) without changing what a seed drew
before (its own draws come from a separate stream of the seed):

- ``skylines``: the obstacles of a sky that has them are skylines instead (rows of blocks of
  different heights with notches and antennas, thin masts and poles, tree lines with sky between
  the branches, sunlit walls brighter than the sky; 1–4 of them, up to 35° high), and half of
  all skies have a hazy horizon (a pale band 2–8° high);
- ``unmasked``: every sky has obstacles, and the station never has a mask;
- ``kind``: only skies of this kind (its other draws then differ from the seed's unforced sky);
- ``twice_encoded``: the frames are saved twice: the camera's output (limited-range video, or
  full range) as JPEG, then the recorder's second JPEG (4:2:0), the final clip level anywhere
  from 230 to 255 DN;
- ``contrails``: aircraft contrails (:mod:`cbh.sim.contrail`) drawn into 70 % of the skies;
- ``mounts``: the cameras as real stations mount them (the station file states it all, as a
  calibration would): each tilted 0–3° towards any azimuth, camera 2 up to 15 m above or below
  camera 1, and each camera its own lens: the base camera's own, an equidistant or an equisolid
  one (90° radius 82–98 % of half the width), centred up to 2 % of the width off the image's
  centre (the real Fehmarn station: tilts of 2.0° and 2.6°, camera 2 9 m lower);
- ``optics``: what each camera's optics add (:mod:`cbh.sim.optics`), drawn independently per
  camera: lens-flare ghosts of the sun (in 80 % of the frames that see the sun: 1–3 soft tinted
  disks of 1–6 % of the image circle's radius, 8–50 DN, on the line through the sun and the
  centre) and dust or dried drops on the dome (in half of the frames: 1–4 blurred, dimmed
  patches of 1–5 % of the radius);
- ``overlays``: each camera stamps its clock (and, in half of the stations, its name) on its
  frames (:mod:`cbh.sim.overlay`), as IP cameras do: one style and place per station (white or
  yellow text with a one-pixel outline, a drop shadow or a black banner; cap height 1.5–4 % of
  the frame; a line or two near the top or the bottom edge, mostly on the sky, sometimes in a
  corner outside the image circle), camera 2's clock 0–40 s off camera 1's;
- ``dense``: broken skies of two or three layers (15 % of them closer than the historical 35 %:
  18–35 % apart), the lowest covering 0.55–0.85 of the sky and the upper ones 0.3–0.7, so that an
  upper deck is seen mostly through the gaps of the lower ones.

A case is a pure function of its seed and options.
"""
from __future__ import annotations

import math
from datetime import datetime, timedelta, timezone
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from cbh.geometry.station import Station, rotation_from_angles
from cbh.sim.scene import CloudLayer, Imperfection, ImageSettings, Obstacle, Scene, Sky, Sun

__all__ = ["RandomCase", "RandomOptions", "random_case", "random_network_case", "station_with_masks", "run_random_case",
           "draw_contrails", "draw_optics", "draw_overlays", "finish_frames", "SKY_KINDS"]

SKY_KINDS = ("clear", "broken", "overcast")


@dataclass(frozen=True)
class RandomOptions:
    """Widenings of :func:`random_case`'s distribution (the module docstring); all off = the
    historical distribution, seed for seed."""

    skylines: bool = False  # skyline obstacles and hazy horizons
    unmasked: bool = False  # every sky has obstacles, and no mask is given
    kind: str | None = None  # "clear", "broken" or "overcast": only skies of this kind
    twice_encoded: bool = False  # camera JPEG then the recorder's JPEG, clip level 230–255 DN
    dense: bool = False  # broken skies of 2–3 layers, the lowest covering 0.55–0.85 (upper decks seen through gaps)
    contrails: bool = False  # 1–3 aircraft contrails at 7–11.5 km in 70 % of skies (:mod:`cbh.sim.contrail`)
    mounts: bool = False  # cameras as real stations mount them: tilted, at different heights, each its own lens
    optics: bool = False  # lens-flare ghosts of the sun and dust on the dome, each camera its own (:mod:`cbh.sim.optics`)
    overlays: bool = False  # each camera stamps its clock and name on the frame (:mod:`cbh.sim.overlay`)

    def __post_init__(self):
        if self.kind is not None and self.kind not in SKY_KINDS:
            raise ValueError(f"kind must be one of {', '.join(SKY_KINDS)}, got {self.kind!r}")


@dataclass(frozen=True)
class RandomCase:
    """One randomized sky: what is rendered, who looks at it, and what the pipeline is told.

    Attributes
    ----------
    seed : int
    kind : str
        "clear", "broken" or "overcast".
    scene : Scene
    station : Station
        The true station (cameras at their true positions and orientations).
    mask_given : bool
        Whether the station file the pipeline gets carries the obstacle masks.
    baseline_m : float
    """

    seed: int
    kind: str
    scene: Scene
    station: Station
    mask_given: bool
    baseline_m: float
    contrails: tuple = ()  # Contrail, drawn into the rendered frames (RandomOptions.contrails)
    optics: tuple = ()  # per camera (its Ghosts, its DomeSpots), drawn into its frames (RandomOptions.optics)
    overlays: tuple = ()  # per camera, its Overlay lines (RandomOptions.overlays)

    def describe(self) -> str:
        """One line: the sky's main parameters."""
        ls = ", ".join(f"{l.height_m:.0f} m/{l.coverage:.2f}/{math.hypot(*l.wind_ms):.0f} m/s"
                       for l in self.scene.layers) or "none"
        im = self.scene.image
        return (f"seed {self.seed} {self.kind}: layers {ls}; B {self.baseline_m:.0f} m; sun z "
                f"{self.scene.sun.zenith_deg:.0f}°; aureole {self.scene.sky.aureole:.1f}; obstacles "
                f"{len(self.scene.obstacles)}{' (masked)' if self.mask_given else ''}; white "
                f"{im.white_level}{' limited' if im.limited_range else ''}; jpeg {im.jpeg_quality}"
                f"{f' then {im.reencode_quality}' if im.reencode_quality else ''}"
                f"{f'; haze band {self.scene.sky.haze_band:.1f}' if self.scene.sky.haze_band else ''}"
                f"{'; ' + '/'.join(o.kind for o in self.scene.obstacles) if self.scene.obstacles else ''}"
                + "".join(f"; contrail {c.height_m:.0f} m az {c.azimuth_deg:.0f}°" for c in self.contrails)
                + self._mounts() + self._optics()
                + (f"; overlay {self.overlays[0][0].style} {len(self.overlays[0])} line(s)" if self.overlays else ""))

    def _optics(self) -> str:
        """Each camera's ghosts and dome spots (:class:`RandomOptions` ``optics``); else nothing."""
        if not any(g or d for g, d in self.optics):
            return ""
        return "; optics " + ", ".join(f"{len(g)} ghost{'s' * (len(g) != 1)}/{len(d)} spot{'s' * (len(d) != 1)}"
                                       for g, d in self.optics)

    def _mounts(self) -> str:
        """Each camera's lens and tilt, and camera 2's height above camera 1, where a camera is
        tilted or off the other's height (:class:`RandomOptions` ``mounts``); else nothing."""
        cams = list(self.station.cameras.values())[:2]
        tilts = [math.degrees(math.acos(min(1.0, float(np.asarray(c.R_world_from_cam)[2, 2])))) for c in cams]
        dz = float(cams[1].position_m[2] - cams[0].position_m[2])
        if max(tilts) < 1e-6 and dz == 0.0:
            return ""
        lenses = ", ".join(f"{c.model.kind} tilt {t:.1f}°" for c, t in zip(cams, tilts))
        return f"; mounts {lenses}, dz {dz:+.1f} m"


def _layers(rng: np.random.Generator, kind: str) -> tuple[CloudLayer, ...]:
    if kind == "clear":
        return ()
    n = 1 if kind == "overcast" and rng.random() < 0.6 else int(rng.integers(1, 4))
    return _layer_stack(rng, n, math.log(1.35),
                        lambda i: 1.0 if (kind == "overcast" and i == 0) else float(rng.uniform(0.15, 0.7)))


def _dense_layers(rng: np.random.Generator) -> tuple[CloudLayer, ...]:
    """2–3 layers 300 m – 10 km, 18–35 % apart in 15 % of the skies (else ≥ 35 %), the lowest
    covering 0.55–0.85 of the sky and the upper ones 0.3–0.7."""
    n = int(rng.integers(2, 4))
    sep = math.log(1.18) if rng.random() < 0.15 else math.log(1.35)
    return _layer_stack(rng, n, sep, lambda i: float(rng.uniform(0.55, 0.85)) if i == 0 else float(rng.uniform(0.3, 0.7)))


def _layer_stack(rng: np.random.Generator, n: int, sep: float, cover) -> tuple[CloudLayer, ...]:
    """``n`` layers 300 m – 10 km (log-uniform, at least ``sep`` apart in log height), each with
    its wind, texture and look drawn, its coverage ``cover(i)`` (i from the lowest)."""
    heights: list[float] = []
    while len(heights) < n:
        h = float(math.exp(rng.uniform(math.log(300.0), math.log(10_000.0))))
        if all(abs(math.log(h / o)) > sep for o in heights):
            heights.append(h)
    heights.sort()
    layers = []
    for i, h in enumerate(heights):
        speed, wdir = rng.uniform(0.0, 30.0), rng.uniform(0.0, 2 * math.pi)
        layers.append(CloudLayer(
            height_m=round(h, 1), coverage=cover(i), texture_scale_m=float(rng.uniform(300.0, 3000.0)),
            wind_ms=(speed * math.sin(wdir), speed * math.cos(wdir)), seed=int(rng.integers(0, 2**31)),
            offset_m=(float(rng.uniform(-5e3, 5e3)), float(rng.uniform(-5e3, 5e3))),
            brightness=float(rng.uniform(0.6, 1.1)), contrast=float(rng.uniform(0.6, 1.4)),
            edge_softness=float(rng.uniform(0.5, 2.0))))
    return tuple(layers)


def _sky(rng: np.random.Generator) -> Sky:
    pale = rng.uniform(0.0, 0.6)  # 0 = deep blue, 1 = white
    zen = np.array([200.0, 125.0, 70.0]) * (1 - pale) + np.array([225.0, 200.0, 185.0]) * pale
    zen *= rng.uniform(0.85, 1.1)
    hor = np.minimum(255.0, zen + rng.uniform(0.3, 0.8) * (np.array([245.0, 230.0, 220.0]) - zen).clip(0))
    return Sky(zenith_bgr=tuple(float(v) for v in zen.clip(0, 255)), horizon_bgr=tuple(float(v) for v in hor),
               visibility_m=float(rng.uniform(15e3, 80e3)), aureole=float(math.exp(rng.uniform(math.log(0.3), math.log(4.0)))),
               aureole_width_deg=float(rng.uniform(4.0, 15.0)))


def _obstacles(rng: np.random.Generator) -> tuple[Obstacle, ...]:
    if rng.random() < 0.5:
        return ()
    out = []
    for _ in range(int(rng.integers(1, 4))):
        a0 = float(rng.uniform(0.0, 360.0))
        out.append(Obstacle(kind=str(rng.choice(["buildings", "trees"])),
                            azimuth_deg=(a0, (a0 + rng.uniform(20.0, 120.0)) % 360.0),
                            max_elevation_deg=float(rng.uniform(5.0, 25.0)), seed=int(rng.integers(0, 2**31))))
    return tuple(out)


def _skylines(rng: np.random.Generator) -> tuple[Obstacle, ...]:
    """1–4 skyline obstacles (:data:`cbh.sim.sky.SKYLINE_KINDS`), each 10–120° of azimuth."""
    out = []
    for _ in range(int(rng.integers(1, 5))):
        a0 = float(rng.uniform(0.0, 360.0))
        kind = str(rng.choice(["skyline", "masts", "treeline", "walls"], p=[0.35, 0.2, 0.3, 0.15]))
        top = float(rng.uniform(4.0, 35.0)) if kind != "walls" else float(rng.uniform(3.0, 15.0))
        out.append(Obstacle(kind=kind, azimuth_deg=(a0, (a0 + rng.uniform(10.0, 120.0)) % 360.0),
                            max_elevation_deg=top, seed=int(rng.integers(0, 2**31))))
    return tuple(out)


def _twice_encoded(rng: np.random.Generator, image: ImageSettings) -> ImageSettings:
    """The image settings of a twice-saved frame whose clip level is 230–255 DN: limited-range
    video (white ≤ 235) or full range, the camera's JPEG then the recorder's."""
    clip = int(rng.integers(230, 256))
    limited = clip <= 235 and rng.random() < 0.8
    white = int(round((clip - 16) * 255.0 / 219.0)) if limited else clip
    return replace(image, white_level=min(white, 255), limited_range=limited, jpeg_roundtrip=True,
                   jpeg_quality=int(rng.integers(70, 96)), reencode_quality=int(rng.integers(70, 96)))


def _imperfection(rng: np.random.Generator, camera: str) -> Imperfection:
    return Imperfection(camera=camera, gain=float(rng.uniform(0.75, 1.3)), gamma=float(rng.uniform(0.8, 1.25)),
                        white_balance=(float(rng.uniform(0.9, 1.1)), float(rng.uniform(0.9, 1.1))))


def _station(rng: np.random.Generator, base: Station) -> tuple[Station, float]:
    b = float(math.exp(rng.uniform(math.log(20.0), math.log(200.0))))
    d = rng.uniform(0.0, 2 * math.pi)
    names = list(base.cameras)
    cams = dict(base.cameras)
    cams[names[0]] = replace(cams[names[0]], position_m=np.zeros(3), mask=None,
                             R_world_from_cam=rotation_from_angles(float(rng.uniform(-180, 180))))
    cams[names[1]] = replace(cams[names[1]], position_m=np.array([b * math.sin(d), b * math.cos(d), 0.0]), mask=None,
                             R_world_from_cam=rotation_from_angles(float(rng.uniform(-180, 180))))
    return replace(base, cameras=cams), b


def _mounts(rng: np.random.Generator, station: Station) -> Station:
    """``station``'s first two cameras as real stations mount them (:class:`RandomOptions` ``mounts``):
    each tilted 0–3° towards any azimuth (its yaw kept), camera 2 moved 0–15 m up or down, and
    each camera's own lens (the base's own, equidistant or equisolid, off-centre)."""
    from cbh.geometry.camera import EquidistantModel, EquisolidModel
    from cbh.geometry.station import angles_from_rotation

    cams = dict(station.cameras)
    for i, name in enumerate(list(cams)[:2]):
        c = cams[name]
        yaw = angles_from_rotation(c.R_world_from_cam)[0]
        tilt, towards = float(rng.uniform(0.0, 3.0)), float(rng.uniform(0.0, 2 * math.pi))
        R = rotation_from_angles(yaw, tilt * math.cos(towards), tilt * math.sin(towards))
        m = c.model
        kind = str(rng.choice(["own", "equidistant", "equisolid"], p=[0.4, 0.3, 0.3]))
        off = rng.uniform(-0.02, 0.02, 2) * m.width
        centre = (float((m.width - 1) / 2 + off[0]), float((m.height - 1) / 2 + off[1]))
        radius = float(rng.uniform(0.82, 0.98)) * 0.5 * m.width
        if kind == "equidistant":
            m = EquidistantModel(width=m.width, height=m.height, center_xy=centre, radius_px=radius)
        elif kind == "equisolid":
            m = EquisolidModel(width=m.width, height=m.height, center_xy=centre, radius_px=radius)
        else:
            m = replace(m, center_xy=centre)
        pos = np.array(c.position_m, float)
        if i == 1:
            pos[2] += float(rng.uniform(-15.0, 15.0))
        cams[name] = replace(c, R_world_from_cam=R, model=m, position_m=pos)
    return replace(station, cameras=cams)


def _place_and_time(rng: np.random.Generator, base: Station):
    """A station place (latitude ±60°, any longitude) and a UTC time whose sun is 10–85° from the zenith."""
    from cbh.geometry.sun import sun_position

    while True:
        lat, lon = float(rng.uniform(-60.0, 60.0)), float(rng.uniform(-180.0, 180.0))
        t = datetime(2025, 1, 1, tzinfo=timezone.utc) + timedelta(seconds=int(rng.integers(0, 365 * 86400)))
        sp = sun_position(lat, lon, base.altitude_m, t)
        if 10.0 <= sp.zenith_deg <= 85.0:
            return replace(base, latitude_deg=lat, longitude_deg=lon), t, float(sp.zenith_deg), float(sp.azimuth_deg)


def random_case(seed: int, base: Station, options: RandomOptions = RandomOptions()) -> RandomCase:
    """The randomized sky of ``seed``, seen by ``base``'s first two cameras (intrinsics kept),
    drawn as ``options`` say."""
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0x5C1E5]))
    wide = np.random.default_rng(np.random.SeedSequence([int(seed), 0x5C1E5, 33]))  # the options' own draws
    kind = str(rng.choice(SKY_KINDS, p=[0.2, 0.6, 0.2]))
    if options.kind is not None:
        kind = options.kind
    layers = _layers(rng, kind)
    if options.dense:  # after the historical draws, so the rest of the sky is the seed's own
        kind, layers = "broken", _dense_layers(np.random.default_rng(np.random.SeedSequence([int(seed), 0x5C1E5, 34])))
    sky = _sky(rng)
    if options.skylines and wide.random() < 0.5:
        sky = replace(sky, haze_band=float(wide.uniform(0.3, 0.9)), haze_band_deg=float(wide.uniform(2.0, 8.0)))
    base, time_utc, zen, azi = _place_and_time(rng, base)
    # the sun at its true position for the station's place and time (the pipeline predicts it
    # from the same place and time); zenith/azimuth kept for the description
    sun = Sun(position="true", zenith_deg=zen, azimuth_deg=azi)
    obstacles = _obstacles(rng)
    if options.unmasked and not obstacles:
        obstacles = _obstacles(wide) or _obstacles(wide) or _obstacles(wide) or (
            Obstacle(kind="buildings", azimuth_deg=(0.0, 90.0), max_elevation_deg=15.0, seed=int(seed)),)
    if options.skylines and obstacles:
        obstacles = _skylines(wide)
    white = 255 if rng.random() < 0.5 else int(rng.integers(235, 256))
    image = ImageSettings(exposure=float(rng.uniform(0.8, 1.15)), vignetting=float(rng.uniform(0.0, 0.4)),
                          noise_dn=float(rng.uniform(0.5, 3.0)), jpeg_quality=int(rng.integers(60, 96)),
                          jpeg_roundtrip=True, white_level=white, limited_range=bool(rng.random() < 0.15))
    if options.twice_encoded:
        image = _twice_encoded(wide, image)
    station, b = _station(rng, base)
    if options.mounts:
        station = _mounts(np.random.default_rng(np.random.SeedSequence([int(seed), 0x5C1E5, 36])), station)
    names = list(station.cameras)[:2]
    imps = {n: _imperfection(rng, n) for n in names}
    mask_given = bool(obstacles) and rng.random() < 0.5 and not options.unmasked
    scene = Scene(layers=layers, time_utc=time_utc, sun=sun, sky=sky, image=image, obstacles=obstacles, imperfections=imps,
                  seed=int(rng.integers(0, 2**31)), name=f"random-{seed}")
    trails = _contrails(np.random.default_rng(np.random.SeedSequence([int(seed), 0x5C1E5, 35]))) if options.contrails else ()
    optics = _optics(np.random.default_rng(np.random.SeedSequence([int(seed), 0x5C1E5, 37]))) if options.optics else ()
    overlays = _overlays(np.random.default_rng(np.random.SeedSequence([int(seed), 0x5C1E5, 38]))) if options.overlays else ()
    return RandomCase(seed=int(seed), kind=kind, scene=scene, station=station, mask_given=mask_given, baseline_m=b,
                      contrails=trails, optics=optics, overlays=overlays)


def _overlays(rng: np.random.Generator) -> tuple:
    """Per camera of the pair, its OSD lines (:mod:`cbh.sim.overlay`): one vendor's style and place
    for both, each camera its own name and clock."""
    from cbh.sim.overlay import OVERLAY_FORMATS, OVERLAY_STYLES, Overlay

    style, fmt = str(rng.choice(OVERLAY_STYLES)), str(rng.choice(OVERLAY_FORMATS))
    h = float(rng.uniform(0.015, 0.04))
    named, two_lines, yellow = rng.random() < 0.5, rng.random() < 0.3, rng.random() < 0.2
    if rng.random() < 0.15:  # in a corner, outside the image circle (as at Fehmarn)
        x, y = float(rng.uniform(0.005, 0.02)), float(rng.uniform(0.03, 0.05))
    else:  # near the top or the bottom edge, across the circle
        x, y = float(rng.uniform(0.12, 0.45)), float(rng.uniform(0.06, 0.22))
        if rng.random() < 0.5:
            y = 1.0 - y
    offset2 = float(rng.uniform(0.0, 40.0)) if rng.random() < 0.7 else 0.0
    out = []
    for k, off in enumerate((0.0, offset2)):
        name = f"CAM{k + 1}" if named else ""
        if two_lines and name:
            lines = (Overlay(name, "", style, h, x, y, yellow, off), Overlay("", fmt, style, h, x, y + 1.8 * h, yellow, off))
        else:
            lines = (Overlay(name, fmt, style, h, x, y, yellow, off),)
        out.append(lines)
    return tuple(out)


def _optics(rng: np.random.Generator) -> tuple:
    """Per camera of the pair (:mod:`cbh.sim.optics`): 1–3 ghosts in 80 % of the frames, 1–4 dome spots in half."""
    from cbh.sim.optics import GHOST_TINTS_BGR, DomeSpot, Ghost

    out = []
    for _ in range(2):
        ghosts = tuple(Ghost(ratio=float(rng.uniform(0.2, 1.2)), radius_frac=float(rng.uniform(0.01, 0.06)),
                             brightness_dn=float(rng.uniform(8.0, 50.0)), tint=str(rng.choice(list(GHOST_TINTS_BGR))))
                       for _ in range(int(rng.integers(1, 4)) if rng.random() < 0.8 else 0))
        spots = []
        for _ in range(int(rng.integers(1, 5)) if rng.random() < 0.5 else 0):
            rho, phi = 0.85 * math.sqrt(float(rng.random())), float(rng.uniform(0.0, 2.0 * math.pi))
            spots.append(DomeSpot(centre_frac=(rho * math.cos(phi), rho * math.sin(phi)),
                                  radius_frac=float(rng.uniform(0.01, 0.05)), blur_frac=float(rng.uniform(0.005, 0.02)),
                                  transmission=float(rng.uniform(0.75, 1.0))))
        out.append((ghosts, tuple(spots)))
    return tuple(out)


def _contrails(rng: np.random.Generator) -> tuple:
    """0 (30 %) or 1–3 contrails: cruise level 7–11.5 km, any direction, axis within 5 km of
    the zenith point, σ 20–150 m (young to spread), 25–110 DN at the axis."""
    from cbh.sim.contrail import Contrail

    if rng.random() < 0.3:
        return ()
    return tuple(Contrail(height_m=float(rng.uniform(7000.0, 11500.0)), point_m=tuple(float(v) for v in rng.uniform(-5000, 5000, 2)),
                          azimuth_deg=float(rng.uniform(0.0, 180.0)), width_m=float(rng.uniform(20.0, 150.0)),
                          brightness_dn=float(rng.uniform(25.0, 110.0)))
                 for _ in range(int(rng.integers(1, 4))))


def draw_contrails(case: RandomCase, sim, shot):
    """``shot``'s frames and true height maps with ``case.contrails`` drawn in (:func:`~cbh.sim.contrail.draw_contrail`),
    as new views; ``shot`` itself when the case has none."""
    if not case.contrails:
        return shot
    from cbh.sim.contrail import draw_contrail

    views = dict(shot.views)
    for name in list(sim.station.cameras)[:2]:
        im, hm = views[name].image, views[name].height_m
        for c in case.contrails:
            im, hm = draw_contrail(im, hm, sim.station.cameras[name], c, sim.output_white(name))
        views[name] = replace(views[name], image=im, height_m=hm)
    return replace(shot, views=views)


def draw_optics(case: RandomCase, sim, shot):
    """``shot``'s frames with each camera's ``case.optics`` drawn in (:mod:`cbh.sim.optics`), as
    new views (the truth unchanged: a ghost is no cloud, and cloud behind a dome spot is still
    cloud); ``shot`` itself when the case has none."""
    if not any(g or d for g, d in case.optics):
        return shot
    from cbh.sim.optics import draw_dome_spot, draw_ghost
    from cbh.sim.sky import sun_direction

    views = dict(shot.views)
    sun = sun_direction(*sim.sun(shot.time_utc))
    for name, (ghosts, spots) in zip(list(sim.station.cameras)[:2], case.optics):
        cam, im = sim.station.cameras[name], views[name].image
        for d in spots:
            im = draw_dome_spot(im, cam, d)
        for g in ghosts:
            im = draw_ghost(im, cam, sun, g, sim.output_white(name))
        views[name] = replace(views[name], image=im)
    return replace(shot, views=views)


def draw_overlays(case: RandomCase, sim, shot):
    """``shot``'s frames with each camera's ``case.overlays`` stamped on (:mod:`cbh.sim.overlay`),
    as new views (the truth unchanged: text is no cloud); ``shot`` itself when it has none."""
    if not case.overlays:
        return shot
    from cbh.sim.overlay import draw_overlay

    views = dict(shot.views)
    for name, lines in zip(list(sim.station.cameras)[:2], case.overlays):
        im = views[name].image
        for line in lines:
            im = draw_overlay(im, line, shot.time_utc, case.scene.image.jpeg_quality)
        views[name] = replace(views[name], image=im)
    return replace(shot, views=views)


def finish_frames(case: RandomCase, sim, shot):
    """``shot`` as the case's cameras deliver it: its contrails (:func:`draw_contrails`), each
    camera's optics (:func:`draw_optics`), then each camera's on-screen text (:func:`draw_overlays`)."""
    return draw_overlays(case, sim, draw_optics(case, sim, draw_contrails(case, sim, shot)))


def station_with_masks(case: RandomCase, sim, folder: Path) -> Station:
    """The station the pipeline is told about (``sim.station``: the case's at the rendered size):
    with the simulator's obstacle masks written to ``folder`` when ``case.mask_given`` (255 =
    sky), else without masks."""
    if not case.mask_given:
        return sim.station
    import cv2

    cams = dict(sim.station.cameras)
    for name in list(cams)[:2]:
        p = Path(folder) / f"mask-{case.seed}-{name}.png"
        cv2.imwrite(str(p), np.where(sim.obstacle_mask(name), 0, 255).astype(np.uint8))
        cams[name] = replace(cams[name], mask=p)
    return replace(sim.station, cameras=cams)


def run_random_case(seed: int, base: Station, size_px: int, folder: Path, config=None,
                    options: RandomOptions = RandomOptions()):
    """Render the randomized sky ``seed`` (drawn as ``options`` say) at ``size_px`` and run the
    pipeline on its pair.

    Returns
    -------
    (case, result, score, seconds) : RandomCase, PairResult, LayerScore, float
        ``score``: :func:`cbh.sim.evaluate.score_layers` against camera 1's truth over its
        analysed field less the true obstacles; ``seconds``: the pipeline's wall time.
    """
    import time

    from cbh.pipeline import Pipeline
    from cbh.sim import SkySimulator
    from cbh.sim.evaluate import score_layers

    case = random_case(seed, base, options)
    sim = SkySimulator(case.station, case.scene, size_px=size_px)
    shot = finish_frames(case, sim, sim.render())
    pipe = Pipeline(station_with_masks(case, sim, folder), config=config)
    cams = list(sim.station.cameras)[:2]
    t0 = time.perf_counter()
    r = pipe.process(shot.views[cams[0]].image, shot.views[cams[1]].image, shot.time_utc, channels="bgr")
    dt = time.perf_counter() - t0
    cam1 = sim.station.cameras[cams[0]]
    fov = (cam1.zenith_map() <= pipe.config.masks.max_zenith_deg) & ~sim.obstacle_mask(cams[0])
    score = score_layers(r, shot.views[cams[0]].height_m, fov, case.baseline_m, 1.0 / cam1.model.px_per_rad())
    return case, r, score, dt


def random_network_case(seed: int, size: int, tilt: bool = False):
    """The randomized sky of ``seed`` (:func:`random_case`) seen by a three-camera network:
    cam1 at the origin and cam2 as the case has them (20–200 m), cam3 (camera 1's lens of
    ``unb-lea-network``) 300–1000 m away in a random direction, yawed anywhere. ``tilt``: one
    camera, drawn, 2° off level about a random horizontal axis (the station says level).

    Returns (case, simulator at ``size_px``, the tilted camera or None, cam3's baseline [m])."""
    from cbh.geometry.station import load_station
    from cbh.presets import station_path
    from cbh.sim import SkySimulator

    base = load_station(station_path("unb-lea-network"))
    case = random_case(seed, base)
    rng = np.random.default_rng(seed + 7_000_000)
    cams = dict(case.station.cameras)
    d3, b3 = rng.uniform(0, 2 * math.pi), float(rng.uniform(300.0, 1000.0))
    cams["cam3"] = replace(base.cameras["cam3"], position_m=np.array([b3 * math.sin(d3), b3 * math.cos(d3), 0.0]),
                           R_world_from_cam=rotation_from_angles(float(rng.uniform(-180, 180))))
    station = replace(case.station, cameras=cams)
    imps = dict(case.scene.imperfections)
    bad = None
    if tilt:
        bad = str(rng.choice(["cam1", "cam2", "cam3"]))
        a = rng.uniform(0, 2 * math.pi)
        old = imps.get(bad, Imperfection(camera=bad))
        imps[bad] = replace(old, rotation_error_deg=(0.0, 2.0 * math.cos(a), 2.0 * math.sin(a)))
    scene = replace(case.scene, imperfections=imps)
    return case, SkySimulator(station, scene, size_px=size), bad, b3
