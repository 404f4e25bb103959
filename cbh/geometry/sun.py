"""Where the sun is: the one sun-position function of cbh (pvlib's SPA).

Used by the pipeline's sun mask and by the simulator, so the two can never disagree.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from datetime import datetime

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
    import pandas as pd
    import pvlib

    if time_utc.tzinfo is None:
        raise ValueError("sun_position: time_utc must be timezone-aware (UTC)")
    sp = pvlib.solarposition.get_solarposition(
        pd.DatetimeIndex([time_utc]), latitude_deg, longitude_deg, altitude=altitude_m
    )
    zen = float(sp["apparent_zenith"].iloc[0])
    az = float(sp["azimuth"].iloc[0]) % 360.0
    return SunPosition(zen, az, direction_enu(zen, az))
