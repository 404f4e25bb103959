"""`cbh simulate`: render a synthetic stereo sky sequence with exact ground truth to a folder."""
from __future__ import annotations

from pathlib import Path

import typer


def register(app: typer.Typer) -> None:
    app.command("simulate")(simulate_cmd)


def simulate_cmd(
    station: str = typer.Option(None, "--station", help="Station TOML or preset name (default: unb-lea)."),
    scene: str = typer.Option("two-layers", "--scene", help="Scene TOML or preset name (configs/scenes)."),
    out: Path = typer.Option(..., "--out", help="Output folder (created)."),
    frames: int = typer.Option(1, "--frames", help="Number of frames."),
    cadence_s: float = typer.Option(10.0, "--cadence-s", help="Seconds between frames."),
    start: str = typer.Option(None, "--start", help="Start time, ISO 8601 UTC (default: the scene's time_utc)."),
    size: int = typer.Option(None, "--size", help="Render this many pixels wide (calibration scaled)."),
    clock_offset: list[str] = typer.Option([], "--clock-offset", help="CAMERA=SECONDS: the camera captures this late (stamps stay nominal); overrides the scene's."),
) -> None:
    """Render N frames of every camera of a station looking at a scene; write images, truth, station.

    Writes OUT/<camera>/<camera>_<YYYYmmddTHHMMSS.fffZ>.jpg, OUT/truth/<time>.npz (per camera
    height_m, cloud_mask) and .json (layers, sun), OUT/station.toml (the scaled station: OUT can
    be processed as it is) and OUT/scene.toml.
    """
    import math
    import time
    from datetime import datetime, timezone

    from cbh.errors import ConfigError
    from cbh.presets import scene_path, station_path
    from cbh.sim import SkySimulator, load_scene
    from cbh.sim.scene import with_clock_offsets
    from cbh.sim.io import time_tag, write_shot
    from cbh.geometry.station import load_station

    if frames < 1:
        raise ConfigError(f"--frames must be >= 1, got {frames}")
    if not (math.isfinite(cadence_s) and cadence_s > 0):
        raise ConfigError(f"--cadence-s must be > 0, got {cadence_s}")
    if size is not None and size < 16:
        raise ConfigError(f"--size must be >= 16 pixels, got {size}")
    t0 = None
    if start is not None:
        try:
            t0 = datetime.fromisoformat(start.strip().replace("Z", "+00:00"))
        except ValueError:
            raise ConfigError(f"--start: not an ISO 8601 time: {start!r} (e.g. 2024-06-21T14:00:00Z)") from None
        if t0.tzinfo is None:
            raise ConfigError(f"--start: needs a UTC offset (end it with Z): {start!r}")
        t0 = t0.astimezone(timezone.utc)

    st = load_station(station_path(station) if station else station_path())
    scene_file = scene_path(scene)
    sc = load_scene(scene_file)
    if clock_offset:
        sc = with_clock_offsets(sc, clock_offset)
    sim = SkySimulator(st, sc, size_px=size)
    if out.exists() and not out.is_dir():
        raise ConfigError(f"--out: not a directory: {out}")
    out.mkdir(parents=True, exist_ok=True)
    (out / "station.toml").write_text(sim.station.to_toml())
    (out / "scene.toml").write_bytes(Path(scene_file).read_bytes())

    from datetime import timedelta

    t0 = sc.time_utc if t0 is None else t0
    for i in range(frames):
        tic = time.perf_counter()
        shot = sim.render(t0 + timedelta(seconds=i * cadence_s))
        write_shot(shot, out, sc.image.jpeg_quality)
        clouds = "  ".join(
            f"{name}: cloud {100.0 * v.cloud_mask.mean():.1f} %" for name, v in shot.views.items()
        )
        layers = ", ".join(f"{l.height_m:g} m" for l in shot.layers) or "none"
        print(
            f"{time_tag(shot.time_utc)}  {clouds}  layers {layers}  "
            f"sun z={shot.sun_zenith_deg:.1f} az={shot.sun_azimuth_deg:.1f} deg  "
            f"({time.perf_counter() - tic:.2f} s)",
            flush=True,
        )
