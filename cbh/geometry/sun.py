"""Where the sun is: the one sun-position function of cbh (pvlib's SPA).

Used by the pipeline's sun mask and by the simulator, so the two can never disagree.

pvlib's SPA lives in ``pvlib/spa.py``, a plain-numpy module; importing it through the pvlib
package would import all of pvlib (scipy, pandas: 0.5–0.8 s on this machine, at every cold start
of ``cbh pair``, for one function). :func:`_spa` loads that one file as its own module and
:func:`sun_position` calls it exactly as ``pvlib.solarposition.get_solarposition(…,
altitude=…)`` does (method ``nrel_numpy``: pressure from the altitude by pvlib's ``alt2pres``,
12 °C, ΔT = 67 s, refraction 0.5667°); ``tests/test_sun.py`` checks that both agree.
"""
from __future__ import annotations

import importlib.util
import math
import threading
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path

import numpy as np

__all__ = ["SunPosition", "sun_position", "direction_enu"]


@dataclass(frozen=True)
class SunPosition:
    """Apparent (refraction-corrected) position of the sun seen from the station.

    Attributes
    ----------
    zenith_deg : float
        Apparent zenith angle [deg] (0 = overhead, > 90 below the horizon).
    azimuth_deg : float
        Azimuth, clockwise from north, in [0, 360) [deg].
    direction_enu : ndarray, shape (3,), float64
        Unit vector towards the sun in the station's East-North-Up frame.
    """

    zenith_deg: float
    azimuth_deg: float
    direction_enu: np.ndarray


def direction_enu(zenith_deg: float, azimuth_deg: float) -> np.ndarray:
    """Unit ENU vector towards (zenith [deg], azimuth [deg] clockwise from north), shape (3,)."""
    z, a = math.radians(zenith_deg), math.radians(azimuth_deg)
    return np.array([math.sin(z) * math.sin(a), math.sin(z) * math.cos(a), math.cos(z)])


def sun_position(latitude_deg: float, longitude_deg: float, altitude_m: float, time_utc: datetime) -> SunPosition:
    """The sun's apparent position for a station and a UTC time (pvlib SPA).

    Parameters
    ----------
    latitude_deg, longitude_deg : float
        Station position [deg] (north, east positive).
    altitude_m : float
        Station altitude above mean sea level [m] (enters the refraction correction).
    time_utc : datetime
        Timezone-aware UTC time.

    Returns
    -------
    SunPosition
        Apparent zenith (refraction-corrected), azimuth and the ENU unit vector.
    """
    if time_utc.tzinfo is None:
        raise ValueError("sun_position: time_utc must be timezone-aware (UTC)")
    pressure_mbar = ((44331.514 - altitude_m) / 11880.516) ** (1 / 0.1902632)  # pvlib.atmosphere.alt2pres / 100
    app_zenith, _, _, _, azimuth, _ = _spa().solar_position(
        np.array([time_utc.timestamp()]), latitude_deg, longitude_deg, altitude_m, pressure_mbar, _TEMPERATURE_C,
        _DELTA_T_S, _REFRACTION_DEG)
    zen = float(app_zenith[0])
    az = float(azimuth[0]) % 360.0
    return SunPosition(zen, az, direction_enu(zen, az))


_TEMPERATURE_C = 12.0  # get_solarposition's default
_DELTA_T_S = 67.0  # spa_python's default (TT − UT1)
_REFRACTION_DEG = 0.5667  # spa_python's default atmospheric refraction at sunrise/sunset
_spa_lock = threading.Lock()
_spa_module: list = []


def _spa():
    """pvlib's ``spa.py`` as a module of its own (see the module doc), loaded once."""
    with _spa_lock:
        if not _spa_module:
            spec = importlib.util.find_spec("pvlib")  # finds the package without importing it
            path = Path(list(spec.submodule_search_locations)[0]) / "spa.py"
            s = importlib.util.spec_from_file_location("cbh._pvlib_spa", path)
            mod = importlib.util.module_from_spec(s)
            s.loader.exec_module(mod)
            _spa_module.append(mod)
        return _spa_module[0]
