"""Reading a station file the one way every command reads it.

:func:`cbh.geometry.station.load_station` validates what the geometry layer owns (``[station]``,
the cameras, ``[ground]``) and keeps the other tables raw. The tables of the layers above it
are validated here, each by the layer that owns it: ``[pipeline]`` by
:meth:`cbh.pipeline.config.PipelineConfig.from_dict`, ``[service]`` by
:meth:`cbh.live.service.ServiceConfig.from_dict`, so that a station one command refuses is
refused by all, with the same line, before any other input is touched (issue 26).
Stations read back from recordings are not checked here: they stay readable whatever later
versions accept.
"""
from __future__ import annotations

from pathlib import Path

from cbh.geometry.station import Station
from cbh.geometry.station import load_station as load_station_geometry

__all__ = ["load_station", "check_sections"]


def _owners() -> dict:
    """Section name → the owning layer's validator (raises :class:`~cbh.errors.ConfigError`)."""
    from cbh.live.service import ServiceConfig
    from cbh.pipeline.config import PipelineConfig

    return {"pipeline": PipelineConfig.from_dict, "service": ServiceConfig.from_dict}


def check_sections(station: Station) -> None:
    """Validate a station's ``[pipeline]`` and ``[service]`` tables as the commands that use them
    do: unknown keys, types and ranges are a :class:`~cbh.errors.ConfigError` naming the key."""
    for name, validate in _owners().items():
        if name in station.sections:
            validate(station.sections[name])


def load_station(path: str | Path) -> Station:
    """Read and validate a station TOML file, every table of it (``cbh.load_station``).

    Raises :class:`~cbh.errors.ConfigError` naming the key.
    """
    station = load_station_geometry(path)
    check_sections(station)
    return station
