"""A night drone flight over a station, rendered with its flight log (``cbh simulate --drone-flight``).

The paper's check (section 4): a drone with a light under it hovers at 20 positions (five
sectors, heights from 90 to 490 m) while the cameras take pictures. Rendered here:

- **the drone**: a light (a 1 px Gaussian spot, bright enough to clip) flying a
  :class:`FlightPlan` at constant speed between hovers, taking off and landing beside the
  cameras;
- **the night sky**: a dark background brightening toward the horizon (airglow, city
  light), read noise, stars (a power-law of brightness) turning about the celestial pole at
  the sidereal rate, and hot pixels that never move;
- **an aircraft** crossing the whole sky at cruise height with a steady red light and a white
  strobe that blinks (seen in some frames only);
- **the log**, as the drone writes it: a CSV (``time_utc, latitude, longitude, altitude_m``
  above the take-off, 10 Hz) and a DJI SRT with the same fixes, on a clock
  ``log_offset_s`` ahead of the cameras'.

Written: ``<camera>/<camera>_<time>.jpg`` (stamped on the cameras' clock), ``flight.csv``,
``flight.SRT``, ``station.toml`` (scaled), ``truth.json`` (the hover positions in ENU, the take-off
point, the log's offset, the aircraft's height).
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass
from datetime import datetime, timedelta, timezone
from pathlib import Path

import numpy as np

from cbh.errors import ConfigError

__all__ = ["FlightPlan", "paper_plan", "Flight", "render_flight", "write_flight_log_csv", "write_flight_log_srt"]

DEFAULT_START = datetime(2022, 7, 15, 1, 0, 0, tzinfo=timezone.utc)  # 22:00 in Brasília: night
SIDEREAL_RAD_S = 7.2921e-5


@dataclass(frozen=True)
class FlightPlan:
    """Hover positions and how the drone flies between them.

    Attributes
    ----------
    positions_m : ndarray, shape (K, 3)
        Hover positions in the station's ENU frame [m].
    takeoff_m : ndarray, shape (3,)
        The take-off point in ENU [m] (on the ground).
    hover_s : float
        Time at each position [s].
    speed_m_s, climb_m_s : float
        Horizontal and vertical speed between positions [m/s].
    """

    positions_m: np.ndarray
    takeoff_m: np.ndarray
    hover_s: float = 20.0
    speed_m_s: float = 8.0
    climb_m_s: float = 4.0

    def waypoints(self) -> tuple[np.ndarray, np.ndarray]:
        """(times [s] from the start (W,), positions ENU [m] (W, 3)): 10 s on the ground, each
        transit and hover, landing, 10 s on the ground."""
        pts = [self.takeoff_m, self.takeoff_m]
        times = [0.0, 10.0]
        stops = [(p, self.hover_s) for p in self.positions_m] + [(self.takeoff_m, 10.0)]
        for p, stay in stops:
            d = np.asarray(p, np.float64) - pts[-1]
            dt = max(math.hypot(d[0], d[1]) / self.speed_m_s, abs(d[2]) / self.climb_m_s, 1.0)
            times += [times[-1] + dt, times[-1] + dt + stay]
            pts += [np.asarray(p, np.float64)] * 2
        return np.array(times), np.array(pts)


def paper_plan(n_positions: int = 20, radius_m: float = 120.0, heights_m=(90.0, 223.0, 357.0, 490.0),
               centre_m=(25.0, 0.0), takeoff_m=(10.0, -40.0, -10.0), hover_s: float = 20.0) -> FlightPlan:
    """The paper's pattern: at each height, a position over the centre and one in each quadrant
    (N, E, S, W at ``radius_m``); the first ``n_positions`` of the heights in order."""
    if not 1 <= n_positions <= 5 * len(heights_m):
        raise ConfigError(f"--positions: 1 to {5 * len(heights_m)}, got {n_positions}")
    cx, cy = centre_m
    pos = []
    for h in heights_m:
        for dx, dy in ((0.0, 0.0), (0.0, 1.0), (1.0, 0.0), (0.0, -1.0), (-1.0, 0.0)):
            pos.append((cx + dx * radius_m, cy + dy * radius_m, h))
    return FlightPlan(np.array(pos[:n_positions]), np.asarray(takeoff_m, np.float64), hover_s)


@dataclass
class Flight:
    """A rendered flight: the truth of what was written."""

    plan: FlightPlan
    start_utc: datetime
    log_offset_s: float
    times_s: np.ndarray  # camera capture times after start [s]

    def position(self, t_s) -> np.ndarray:
        wt, wp = self.plan.waypoints()
        t = np.asarray(t_s, np.float64)
        return np.stack([np.interp(t, wt, wp[:, k]) for k in range(3)], axis=-1)

    @property
    def duration_s(self) -> float:
        return float(self.plan.waypoints()[0][-1])


def _add_spots(img: np.ndarray, xy: np.ndarray, amp: np.ndarray, sigma: float, radius: int = 3) -> None:
    """Add Gaussian spots (sub-pixel centres) to a float image, in place."""
    ok = np.all(np.isfinite(xy), axis=1)
    xy, amp = xy[ok], amp[ok]
    if not len(xy):
        return
    h, w = img.shape
    d = np.arange(-radius, radius + 1)
    cx, cy = np.round(xy[:, 0]).astype(int), np.round(xy[:, 1]).astype(int)
    xx = cx[:, None, None] + d[None, None, :]
    yy = cy[:, None, None] + d[None, :, None]
    g = np.exp(-(((xx - xy[:, 0, None, None]) ** 2) + (yy - xy[:, 1, None, None]) ** 2) / (2 * sigma**2))
    v = amp[:, None, None] * g
    xx, yy = np.broadcast_to(xx, v.shape), np.broadcast_to(yy, v.shape)
    inside = (xx >= 0) & (yy >= 0) & (xx < w) & (yy < h)
    np.add.at(img, (yy[inside], xx[inside]), v[inside])


class _Sky:
    """Stars, hot pixels and an aircraft, fixed by a seed."""

    def __init__(self, station, seed: int, n_stars: int, duration_s: float):
        rng = np.random.default_rng(seed)
        v = rng.normal(size=(n_stars, 3))
        self.stars = v / np.linalg.norm(v, axis=1, keepdims=True)  # directions at t = 0, ENU
        self.star_amp = np.clip(12.0 * rng.pareto(1.5, n_stars) + 8.0, 8.0, 400.0)  # peak [DN]
        lat = math.radians(station.latitude_deg)
        self.pole = np.array([0.0, math.cos(lat), math.sin(lat)])
        self.hot = {n: (rng.integers(0, c.model.width, 25), rng.integers(0, c.model.height, 25), rng.uniform(120, 255, 25))
                    for n, c in station.cameras.items()}
        ang = rng.uniform(0, 2 * math.pi)
        self.plane_dir = np.array([math.sin(ang), math.cos(ang), 0.0])
        self.plane_h = float(rng.uniform(5000.0, 10000.0))
        self.plane_t0 = float(rng.uniform(0.2, 0.6) * duration_s)  # when it passes overhead [s]
        self.plane_offset = float(rng.uniform(-3000.0, 3000.0))  # its track's distance from the station [m]

    def star_dirs(self, t_s: float) -> np.ndarray:
        a = -SIDEREAL_RAD_S * t_s  # the sky turns westward about the pole
        k = self.pole
        v = self.stars
        return v * math.cos(a) + np.cross(k, v) * math.sin(a) + np.outer(v @ k, k) * (1 - math.cos(a))

    def plane(self, t_s: float) -> np.ndarray:
        side = np.cross([0.0, 0.0, 1.0], self.plane_dir)
        return self.plane_dir * 230.0 * (t_s - self.plane_t0) + side * self.plane_offset + np.array([0, 0, self.plane_h])


def _frame(cam, sky: _Sky, t_s: float, drone_m: np.ndarray, rng, noise: float, drone_spot=(1.0, 400.0),
           day: bool = False) -> np.ndarray:
    """One camera's BGR uint8 frame at ``t_s``: the night sky, or by ``day`` a bright sky (no stars)
    on which the drone and the aircraft are dark specks."""
    m = cam.model
    zen = cam.zenith_map()
    inside = m.image_circle_mask()
    base = 150.0 + 60.0 * np.clip(zen / 90.0, 0, 1) ** 2 if day else 5.0 + 14.0 * np.clip(zen / 90.0, 0, 1) ** 3
    grey = np.where(inside, base, 0.0).astype(np.float32) + rng.normal(0, noise, zen.shape).astype(np.float32)
    red = np.zeros_like(grey)
    ppx = cam.world_to_pixel(sky.plane(t_s)[None])
    radius = max(3, int(3 * drone_spot[0]))
    if day:
        _add_spots(grey, ppx, np.array([-60.0]), 0.9)
        _add_spots(grey, cam.world_to_pixel(drone_m[None]), np.array([-abs(drone_spot[1])]), drone_spot[0], radius)
    else:
        d = sky.star_dirs(t_s)
        up = d[:, 2] > 0.02
        _add_spots(grey, cam.direction_to_pixel(d[up]), sky.star_amp[up] * np.clip(d[up, 2], 0, 1) ** 0.3, 0.8)
        _add_spots(red, ppx, np.array([60.0]), 0.9)
        if (t_s % 1.3) < 0.45:  # the strobe
            _add_spots(grey, ppx, np.array([250.0]), 0.9)
        _add_spots(grey, cam.world_to_pixel(drone_m[None]), np.array([drone_spot[1]]), drone_spot[0], radius)
    hx, hy, hv = sky.hot[cam.name]
    grey[hy, hx] = np.maximum(grey[hy, hx], hv)
    g = np.clip(grey, 0, 255)
    img = np.stack([np.clip(g * (1.15 if day else 1.0), 0, 255), g, np.clip(g * (0.8 if day else 1.0) + red, 0, 255)], axis=-1)
    img[~inside] = 0
    return img.round().astype(np.uint8)


def render_flight(station, out, plan: FlightPlan | None = None, *, start_utc: datetime = DEFAULT_START,
                  cadence_s: float = 1.0, log_offset_s: float = 3.0, seed: int = 0, n_stars: int = 400,
                  noise: float = 1.5, jpeg_quality: int = 92, hidden_from=(), drone_spot=(1.0, 400.0),
                  day: bool = False, gps_noise_m: float = 0.0):
    """Render every camera's frames of a flight and write its logs and truth into ``out``.

    A generator: yields (frame index, number of frames) as each time step is written; the
    :class:`Flight` is returned through StopIteration's value (``yield from``). The cameras
    named in ``hidden_from`` never see the drone (a covered or misdirected camera);
    ``drone_spot`` is its light's (sigma [px], peak [grey levels]; the default clips); by ``day``
    (give a ``start_utc`` with the sun up) the drone is a dark speck of that depth on a bright sky;
    ``gps_noise_m`` gives each logged fix a random error (that much horizontally [m], a third
    vertically; the frames show the drone where it is).
    """
    from cbh.imageio import encode_jpeg
    from cbh.sim.io import image_path

    if not (math.isfinite(cadence_s) and 0.05 <= cadence_s <= 60):
        raise ConfigError(f"--cadence-s: 0.05 to 60 s for a drone flight, got {cadence_s}")
    if not (math.isfinite(log_offset_s) and abs(log_offset_s) <= 600):
        raise ConfigError(f"--log-offset-s: at most 600 s either way, got {log_offset_s}")
    plan = plan or paper_plan()
    out = Path(out)
    flight = Flight(plan, start_utc, log_offset_s, np.arange(0.0, plan.waypoints()[0][-1], cadence_s))
    sky = _Sky(station, seed, n_stars, flight.duration_s)
    rng = np.random.default_rng(seed + 1)
    out.mkdir(parents=True, exist_ok=True)
    (out / "station.toml").write_text(station.to_toml())
    n = flight.times_s.size
    for i, t in enumerate(flight.times_s):
        stamp = start_utc + timedelta(seconds=float(t))
        p = flight.position(t)
        for name, cam in station.cameras.items():
            path = image_path(out, name, stamp)
            path.parent.mkdir(parents=True, exist_ok=True)
            drone = np.full(3, np.nan) if name in hidden_from else p
            path.write_bytes(encode_jpeg(_frame(cam, sky, float(t), drone, rng, noise, drone_spot, day), jpeg_quality))
        yield i, n
    _write_logs(station, flight, out, gps_noise_m, seed)
    _write_truth(station, flight, sky, out)
    return flight


def _log_fixes(station, flight: Flight, rate_hz: float = 10.0, gps_noise_m: float = 0.0, seed: int = 0):
    import pymap3d

    t = np.arange(0.0, flight.duration_s, 1.0 / rate_hz)
    p = flight.position(t)
    if gps_noise_m > 0:  # each fix's own error: gps_noise_m horizontally, a third of it vertically
        p = p + np.random.default_rng(seed + 2).normal(0.0, 1.0, p.shape) * np.array([1.0, 1.0, 1 / 3]) * gps_noise_m
    lat, lon, _ = pymap3d.enu2geodetic(p[:, 0], p[:, 1], p[:, 2], station.latitude_deg, station.longitude_deg,
                                       station.altitude_m)
    stamps = [flight.start_utc + timedelta(seconds=float(s) + flight.log_offset_s) for s in t]
    return stamps, np.asarray(lat), np.asarray(lon), p[:, 2] - flight.plan.takeoff_m[2]


def write_flight_log_csv(path, stamps, lat, lon, up) -> None:
    """The log as AirData/Litchi-style CSV: ``time_utc, latitude, longitude, altitude_m``."""
    lines = ["time_utc,latitude,longitude,altitude_m"]
    lines += [f"{s.strftime('%Y-%m-%dT%H:%M:%S.%f')[:-3]}Z,{a:.8f},{o:.8f},{u:.2f}" for s, a, o, u in zip(stamps, lat, lon, up)]
    Path(path).write_text("\n".join(lines) + "\n")


def write_flight_log_srt(path, stamps, lat, lon, up) -> None:
    """The log as DJI's SRT telemetry (Mavic Air 2 layout), one subtitle per fix."""
    import srt

    subs = []
    t0 = stamps[0]
    for i, (s, a, o, u) in enumerate(zip(stamps, lat, lon, up), start=1):
        start = s - t0
        text = (f'<font size="28">FrameCnt: {i}, DiffTime: 100ms\n{s.strftime("%Y-%m-%d %H:%M:%S.%f")[:-3]}\n'
                f"[iso: 3200] [shutter: 1/30.0] [fnum: 280] [ev: 0] [ct: 5500] [color_md : default] [focal_len: 240] "
                f"[latitude: {a:.6f}] [longitude: {o:.6f}] [rel_alt: {u:.3f} abs_alt: {u + 1040.0:.3f}] </font>")
        subs.append(srt.Subtitle(i, start, start + timedelta(milliseconds=100), text))
    Path(path).write_text(srt.compose(subs, reindex=False))


def _write_logs(station, flight: Flight, out: Path, gps_noise_m: float = 0.0, seed: int = 0) -> None:
    stamps, lat, lon, up = _log_fixes(station, flight, gps_noise_m=gps_noise_m, seed=seed)
    write_flight_log_csv(out / "flight.csv", stamps, lat, lon, up)
    write_flight_log_srt(out / "flight.SRT", stamps, lat, lon, up)


def _write_truth(station, flight: Flight, sky: _Sky, out: Path) -> None:
    import pymap3d

    to = flight.plan.takeoff_m
    lat, lon, _ = pymap3d.enu2geodetic(to[0], to[1], to[2], station.latitude_deg, station.longitude_deg, station.altitude_m)
    truth = {"log_offset_s": flight.log_offset_s, "takeoff": [float(lat), float(lon), float(to[2])],
             "takeoff_arg": f"{float(lat):.8f},{float(lon):.8f},{float(to[2]):g}",
             "hover_positions_m": np.round(flight.plan.positions_m, 3).tolist(), "hover_s": flight.plan.hover_s,
             "aircraft_height_m": sky.plane_h, "frames": int(flight.times_s.size),
             "start_utc": flight.start_utc.isoformat().replace("+00:00", "Z")}
    (out / "truth.json").write_text(json.dumps(truth, indent=1) + "\n")
