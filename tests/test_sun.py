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


def test_same_as_pvlib_get_solarposition():
    """cbh loads pvlib's spa.py on its own (no pvlib package import): the result must be what
    ``pvlib.solarposition.get_solarposition(…, altitude=…)`` gives (same code, same defaults),
    to float rounding, day and night, both hemispheres, sea level to 4 km."""
    pd = pytest.importorskip("pandas")
    pvlib = pytest.importorskip("pvlib")
    cases = [(39.742476, -105.1786, 1830.14, datetime(2003, 10, 17, 19, 30, 30, tzinfo=timezone.utc)),
             (-15.76, -47.87, 1050.0, datetime(2024, 6, 21, 14, 0, 0, tzinfo=timezone.utc)),
             (1.30, 103.68, 20.0, datetime(2015, 10, 29, 4, 58, 1, tzinfo=timezone.utc)),
             (78.2, 15.6, 0.0, datetime(2026, 12, 1, 23, 59, 59, tzinfo=timezone.utc)),  # polar night
             (-33.9, 18.4, 4000.0, datetime(1999, 1, 1, 6, 0, 0, tzinfo=timezone.utc))]
    for lat, lon, alt, t in cases:
        ref = pvlib.solarposition.get_solarposition(pd.DatetimeIndex([t]), lat, lon, altitude=alt)
        s = sun_position(lat, lon, alt, t)
        assert s.zenith_deg == pytest.approx(float(ref["apparent_zenith"].iloc[0]), abs=1e-9)
        assert s.azimuth_deg == pytest.approx(float(ref["azimuth"].iloc[0]) % 360.0, abs=1e-9)


def test_sun_position_imports_neither_pvlib_nor_pandas():
    """A cold ``cbh pair`` pays every import: the sun position must not pull in the pvlib package
    (which imports scipy and pandas, 0.5–0.8 s)."""
    import subprocess
    import sys

    code = ("import sys; from datetime import datetime, timezone; from cbh.geometry.sun import sun_position; "
            "sun_position(1.3, 103.7, 20.0, datetime(2015, 10, 29, 4, 58, tzinfo=timezone.utc)); "
            "print(sorted(m for m in ('pvlib', 'pandas', 'scipy') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"


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
