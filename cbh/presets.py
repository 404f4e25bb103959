"""Named presets shipped with cbh: stations (configs/*.toml) and scenes (configs/scenes/*.toml).

The files live in the repository's ``configs/`` folder; an installed wheel carries them as the
package data ``cbh/_configs`` (see pyproject.toml). ``configs/`` wins when both exist, so a
source checkout always uses what you edit.
"""
from __future__ import annotations

from pathlib import Path

from cbh.errors import ConfigError

__all__ = ["configs_dir", "station_path", "scene_path", "list_scenes", "DEFAULT_STATION", "DEFAULT_SCENE"]

DEFAULT_STATION = "unb-lea"
DEFAULT_SCENE = "two-layers"


def configs_dir() -> Path:
    here = Path(__file__).resolve().parent
    for cand in (here.parent / "configs", here / "_configs"):
        if (cand / f"{DEFAULT_STATION}.toml").is_file():
            return cand
    raise ConfigError("cbh's preset configs are missing from this installation (configs/ or cbh/_configs)")


def _resolve(name: str, folder: Path, what: str) -> Path:
    p = Path(name)
    if p.suffix == ".toml" and p.exists():
        return p
    cand = folder / f"{name}.toml"
    if cand.is_file():
        return cand
    names = sorted(f.stem for f in folder.glob("*.toml"))
    raise ConfigError(f"unknown {what} {name!r}: not a file, and not a preset ({', '.join(names)})")


def station_path(name: str = DEFAULT_STATION) -> Path:
    """Path of a station TOML: an existing file path, or a preset name like ``unb-lea``."""
    return _resolve(name, configs_dir(), "station")


def scene_path(name: str = DEFAULT_SCENE) -> Path:
    """Path of a scene TOML: an existing file path, or a preset name like ``two-layers``."""
    return _resolve(name, configs_dir() / "scenes", "scene")


def list_scenes() -> list[str]:
    return sorted(f.stem for f in (configs_dir() / "scenes").glob("*.toml"))
