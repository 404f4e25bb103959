"""The irradiance nowcast (issue 35) against the real Fehmarn pyranometer.

    python benchmarks/eval_irradiance.py [--recording REC.mcap] [--data DIR] [--json OUT]

Without ``--recording`` it first records the shared half hour as a station runs it (``cbh run
--record``, about 15 s). The nowcast is issued at every recorded pair for the pyranometer's site
(about 25 m from camera FE3: taken at FE3) with the levels learned online from the same
pyranometer (only measurements up to each issue time). Per lead time: RMSE and bias [W/m²] of
the nowcast, of smart persistence (the clear-sky index measured at the issue time, carried
forward) and of the clear-sky guess (k = 1), on the issue times where the nowcast has a value;
skill = 1 − RMSE(nowcast) / RMSE(smart persistence).
"""
from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

DEFAULT = Path(__file__).resolve().parents[2] / "shared" / "data" / "fehmarn-2016-09-01"
LEADS = "0,1,2,3,5,10,15,20"


def record(data: Path, out: Path) -> Path:
    subprocess.run([sys.executable, "-m", "cbh.cli.main", "run", "--station", str(data / "station.toml"),
                    "--source", f"fe3={data / 'fe3'}", "--source", f"fe4={data / 'fe4'}", "--record", str(out), "-q"],
                   check=True, capture_output=True)
    return out


def evaluate(rec: Path, data: Path = DEFAULT, leads: str = LEADS) -> dict:
    from cbh.actions.nowcast import nowcast_rows
    from cbh.geometry.station import load_station
    from cbh.outputs import nowcast as nc

    st = load_station(data / "station.toml")
    pyr_file = data / "radiation-20160901.csv"
    site = f"pyranometer={st.latitude_deg},{st.longitude_deg}"
    rows, summary = nowcast_rows([rec], [site], nc.parse_leads(leads), pyr_file)
    times, ghi = nc.read_pyranometer(pyr_file)
    place = rows[0]["_site"]
    out = {"levels": summary["levels"], "leads": {}}
    issue = sorted({r["time_utc"] for r in rows})
    k_now = {t: nc.measured_at(times, ghi, t) / float(nc.clear_sky_ghi(place, [t])[0]) for t in issue}
    for lead in nc.parse_leads(leads):
        sel = [r for r in rows if r["lead_s"] == lead and math.isfinite(r["ghi_wm2"])]
        meas = np.array([nc.measured_at(times, ghi, r["valid_time_utc"]) for r in sel])
        fc = np.array([r["ghi_wm2"] for r in sel])
        cs = np.array([r["clear_sky_ghi_wm2"] for r in sel])
        sp = np.array([k_now[r["time_utc"]] for r in sel]) * cs
        ok = np.isfinite(meas) & np.isfinite(sp)
        if not ok.any():
            continue
        rmse = lambda a: float(np.sqrt(np.mean((a[ok] - meas[ok]) ** 2)))  # noqa: E731
        r_fc, r_sp, r_cs = rmse(fc), rmse(sp), rmse(cs)
        out["leads"][int(lead // 60)] = {
            "n": int(ok.sum()), "rmse_wm2": round(r_fc, 1), "bias_wm2": round(float(np.mean(fc[ok] - meas[ok])), 1),
            "rmse_smart_persistence_wm2": round(r_sp, 1), "rmse_clear_sky_wm2": round(r_cs, 1),
            "skill_vs_persistence": round(1.0 - r_fc / r_sp, 3) if lead > 0 and r_sp > 0 else None,
            "rmse_over_clear_sky": round(r_fc / r_cs, 3) if r_cs > 0 else None}
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--recording", type=Path)
    ap.add_argument("--data", type=Path, default=DEFAULT)
    ap.add_argument("--leads", default=LEADS)
    ap.add_argument("--json", type=Path)
    a = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        rec = a.recording or record(a.data, Path(tmp) / "fehmarn.mcap")
        res = evaluate(rec, a.data, a.leads)
    print(f"levels learned: {res['levels']}")
    print("lead  n   RMSE  bias  RMSE(smart pers.)  RMSE(clear sky)  skill  RMSE/clear-sky  [W/m2]")
    for lead, v in res["leads"].items():
        skill = "      —" if v["skill_vs_persistence"] is None else f"{v['skill_vs_persistence']:+7.3f}"
        print(f"{lead:3d} min {v['n']:3d} {v['rmse_wm2']:6.1f} {v['bias_wm2']:+6.1f} {v['rmse_smart_persistence_wm2']:10.1f} "
              f"{v['rmse_clear_sky_wm2']:14.1f} {skill} {v['rmse_over_clear_sky']:9.3f}")
    if a.json:
        a.json.write_text(json.dumps(res, indent=1))


if __name__ == "__main__":
    main()
