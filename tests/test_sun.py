"""One sun position (cbh/geometry/sun.py) for the pipeline's sun mask and the simulator."""
from __future__ import annotations

from datetime import datetime, timezone

import numpy as np
import pytest

from cbh.geometry.sun import direction_enu, sun_position


def test_spa_paper_example():
    """NREL SPA (Reda & Andreas 2004, Table A5.1): Golden CO, 2003-10-17 12:30:30 MST, 1830.14 m:
    topocentric zenith 50.11162°, azimuth 194.34024°. The paper's refraction uses 820 mbar and
    11 °C; pvlib derives the pressure from the altitude (≈ 813 mbar) at 12 °C, which moves the
    refraction by ≈ 0.0002° at this zenith: 0.001° bar on the zenith, 1e-4° on the azimuth."""
    t = datetime(2003, 10, 17, 19, 30, 30, tzinfo=timezone.utc)
    s = sun_position(39.742476, -105.1786, 1830.14, t)
    assert s.zenith_deg == pytest.approx(50.11162, abs=1e-3)
    assert s.azimuth_deg == pytest.approx(194.34024, abs=1e-4)
    np.testing.assert_allclose(np.linalg.norm(s.direction_enu), 1.0, rtol=1e-12)
    np.testing.assert_allclose(s.direction_enu, direction_enu(s.zenith_deg, s.azimuth_deg))
    # the altitude enters (through the refraction): 1830 m vs sea level differ by ≈ 0.004°
    assert sun_position(39.742476, -105.1786, 0.0, t).zenith_deg < s.zenith_deg - 0.002


def test_pipeline_and_simulator_see_the_same_sun():
    """The pipeline's sun mask and the simulator's sun come from the same function with the
    station's latitude, longitude and altitude (unb-lea: 1050 m)."""
    from cbh.geometry.station import load_station
    from cbh.pipeline import Pipeline
    from cbh.pipeline.run import PairContext
    from cbh.presets import station_path
    from cbh.sim import SkySimulator, parse_scene

    sim = SkySimulator(load_station(station_path("unb-lea")),
                       parse_scene({"name": "sun", "time_utc": "2024-06-21T13:00:00Z", "layers": []}), size_px=96)
    shot = sim.render()
    st = sim.station
    ref = sun_position(st.latitude_deg, st.longitude_deg, st.altitude_m, shot.time_utc)
    assert (shot.sun_zenith_deg, shot.sun_azimuth_deg) == (ref.zenith_deg, ref.azimuth_deg)
    pipe = Pipeline(st)
    work = (shot.views["cam1"].image, shot.views["cam2"].image)
    masks = pipe.stage_masks(work, PairContext(time_utc=shot.time_utc))
    np.testing.assert_array_equal(masks.sun_dir_enu, ref.direction_enu)
