"""The nowcast's clear-sky-index levels alone, on the pyranometer's whole record (issue 35): how well
do they follow the cloud when the camera's shade is given?

    python benchmarks/eval_levels.py [--data DIR] [--half-lives 600 300 180] [--overcast-from 09:23]

The Fehmarn images cover 09:00–09:30 UTC; the pyranometer logs the whole day. This runs the
levels as `cbh export --product irradiance` learns them (:class:`cbh.outputs.nowcast.Levels`:
each minute's forecasts for leads 0–10 min verified once their time has passed, the prior's sunny
level from the record's last hour) with a stated shade instead of the camera's:

- ``oracle``: the shade the pyranometer itself shows (clear-sky index below ``--threshold``) at
  the valid time: the best the cloud map could do;
- ``overcast``: the same until ``--overcast-from``, then shade 1 at every issue and valid time:
  the camera reads a deck over the sun throughout (as it does from 09:23 at Fehmarn), so only the
  levels can follow the deck's thick and thin parts (the worst case for the second half hour).

Per half-life and window (09:00–09:30, 09:30–10:00): RMSE at 5 and 10 min [W/m²] and skill against
smart persistence (the index measured at the issue time, carried forward). A calculation on the
record, not the camera's nowcast: ``eval_irradiance.py`` scores that.
"""
from __future__ import annotations

import argparse
import math
from datetime import datetime, timedelta, timezone
from pathlib import Path

import numpy as np

DEFAULT = Path(__file__).resolve().parents[2] / "shared" / "data" / "fehmarn-2016-09-01"
WINDOWS = (("09:00", "09:30"), ("09:30", "10:00"))


def _utc(hhmm: str) -> datetime:
    h, m = map(int, hhmm.split(":"))
    return datetime(2016, 9, 1, h, m, tzinfo=timezone.utc)


def record(data: Path):
    """(times, clear-sky index, clear-sky GHI) of the pyranometer from 07:00 to 10:30 UTC."""
    from cbh.geometry.station import load_station
    from cbh.outputs import nowcast as nc

    st = load_station(data / "station.toml")
    site = nc.parse_site(f"pyranometer={st.latitude_deg},{st.longitude_deg}", st)
    times, ghi = nc.read_pyranometer(data / "radiation-20160901.csv")
    keep = [i for i, t in enumerate(times) if _utc("07:00") <= t <= _utc("10:30")]
    t = [times[i] for i in keep]
    cs = nc.clear_sky_ghi(site, t)
    return t, np.asarray(ghi)[keep] / cs, cs


def run(t, k, cs, shade, half_life_s: float, start: datetime, end: datetime) -> dict:
    """Skill of the levels with ``shade`` (per record minute) over the issue times ``start``–``end``."""
    from cbh.outputs import nowcast as nc

    at = {x: i for i, x in enumerate(t)}
    lv, pending = nc.Levels(half_life_s=half_life_s), []
    err = {5: [], 10: []}
    pers = {5: [], 10: []}
    now = _utc("08:00")
    while now <= end:
        i = at.get(now)
        if i is None:  # a minute missing from the record: no issue then
            now += timedelta(minutes=1)
            continue
        for tv, p in [x for x in pending if x[0] <= now]:
            lv.add(p, float(k[at[tv]]), tv)
        pending = [x for x in pending if x[0] > now]
        ks = nc.sunny_level(k[max(0, i - 60):i])
        if math.isfinite(ks):
            lv.set_prior(ks, nc.K_SHADE / nc.K_SUN * ks)
        a, b = lv.levels(now)
        pending += [(now + timedelta(minutes=m), float(shade[at[now + timedelta(minutes=m)]]))
                    for m in range(11) if now + timedelta(minutes=m) in at]
        for lead in (5, 10) if now >= start else ():
            j = at.get(now + timedelta(minutes=lead))
            if j is not None:
                err[lead].append((a + (b - a) * shade[j] - k[j]) * cs[j])
                pers[lead].append((k[i] - k[j]) * cs[j])
        now += timedelta(minutes=1)
    out = {}
    for lead in (5, 10):
        r, rp = (float(np.sqrt(np.mean(np.square(x[lead])))) for x in (err, pers))
        out[lead] = (r, rp, 1.0 - r / rp)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=DEFAULT)
    ap.add_argument("--half-lives", type=float, nargs="+", default=[600.0, 300.0, 180.0])
    ap.add_argument("--threshold", type=float, default=0.75, help="the oracle's shade: index below this")
    ap.add_argument("--overcast-from", default="09:23", help="the overcast case's deck over the sun from this UTC time")
    a = ap.parse_args()
    t, k, cs = record(a.data)
    oracle = (k < a.threshold).astype(float)
    overcast = np.where(np.array([x >= _utc(a.overcast_from) for x in t]), 1.0, oracle)
    for name, shade in (("oracle", oracle), ("overcast", overcast)):
        for hl in a.half_lives:
            for w0, w1 in WINDOWS:
                res = run(t, k, cs, shade, hl, _utc(w0), _utc(w1))
                print(f"{name:8s} half-life {hl:5.0f} s  {w0}-{w1}: " + "  ".join(
                    f"{lead} min RMSE {r:5.1f} (persistence {rp:5.1f}) skill {s:+.2f}" for lead, (r, rp, s) in res.items()))


if __name__ == "__main__":
    main()
