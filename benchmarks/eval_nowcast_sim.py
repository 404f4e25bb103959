"""The irradiance nowcast's shade in simulation (issue 35): does the predicted shade at a site
arrive when the simulated cloud's shadow does?

    python benchmarks/eval_nowcast_sim.py [--scene two-layers] [--size 480] [--minutes 10] [--seed N] [--json OUT]

The simulator renders the scene every 10 s; the pipeline runs on the pairs as `cbh run` does
(motion from pair to pair); each pair issues the shade probability as `cbh export --product irradiance` does
(:func:`cbh.outputs.nowcast.lagged_shade`: the time-lagged ensemble of the last 10 min's pairs;
``--single`` for the issue pair's own :func:`~cbh.outputs.nowcast.shade_probability` alone) at nine sites within ±1 km of the station for leads 0–5 min. The truth at a site and time
(``--truth scene``, the default): the scene's own shadow on the ground (:func:`cbh.sim.ground.ground_shade`:
the sun ray from the site through every layer's full-resolution cloud field, an upper layer behind
a lower one included). ``--truth camera`` (the older one): the simulator's camera-1 truth (each
pixel's cloud-base height, at the camera's resolution) where the sun ray from the site crosses
each scene layer; shade when a layer has cloud there, sunlit when every layer is clear there,
unknown when a lower layer hides it. A shadow edge is a change of the true state
between two frames; the forecast's edge is the nearest change of (probability ≥ ½) in the same
direction; it counts when within 60 s. Printed per lead: edges, within 60 s, median |error|, and the
same over the edges where a forecast was issued on both sides (the nowcast says ``beyond_view``
rather than guess where the upwind cloud has left the map, and ``motion_unknown`` before the first
motion). ``--spinup S``: issue times before S seconds are not scored (a station that just started
has no motion and no lagged ensemble yet). ``--seed N``: another draw of the same scene (the scene's
seed N, layer k's texture seed 10·N + k, from 1 upwards; the heights, covers and winds as they are).
"""
from __future__ import annotations

import argparse
import json
import math
from datetime import timedelta

import numpy as np

CADENCE_S = 10.0
LEADS_S = (0.0, 60.0, 120.0, 180.0, 300.0)
SITES_M = [(x, y) for x in (-1000.0, 0.0, 1000.0) for y in (-1000.0, 0.0, 1000.0)]


def truth_shade(view, layers, sun_dir: np.ndarray, site: np.ndarray) -> float:
    """1 shade, 0 sunlit, NaN unknown (see the module docstring)."""
    cam = view.true_camera
    H, W = view.height_m.shape
    states = []
    for layer in layers:
        h = float(layer.height_m)
        t = (h - site[2]) / sun_dir[2]
        p = np.array([[site[0] + sun_dir[0] * t, site[1] + sun_dir[1] * t, h]])
        px = cam.world_to_pixel(p)[0]
        if not np.isfinite(px).all():
            return math.nan
        c, r = int(round(px[0])), int(round(px[1]))
        if not (0 <= c < W and 0 <= r < H):
            return math.nan
        seen = float(view.height_m[r, c])
        if math.isfinite(seen) and abs(seen - h) < 1.0:
            return 1.0
        if math.isfinite(seen) and seen < h:
            states.append(math.nan)  # a lower layer hides this one here
        else:
            states.append(0.0)
    return 0.0 if states and all(s == 0.0 for s in states) else math.nan


def _edges(times: list, states: list) -> list[tuple[float, int]]:
    """(time of the change [s], +1 into shade / −1 out of it) between consecutive known states."""
    out = []
    prev = None
    for t, s in zip(times, states):
        if not math.isfinite(s):
            prev = None
            continue
        if prev is not None and s != prev[1]:
            out.append((0.5 * (t + prev[0]), 1 if s > prev[1] else -1))
        prev = (t, s)
    return out


def reseeded(sc, seed: int | None):
    """The scene ``sc`` drawn anew (see the module docstring), or itself when ``seed`` is None."""
    from dataclasses import replace

    if seed is None:
        return sc
    return replace(sc, seed=int(seed), layers=tuple(replace(l, seed=10 * int(seed) + k + 1)
                                                    for k, l in enumerate(sc.layers)))


def evaluate(scene: str = "two-layers", size: int = 480, minutes: float = 10.0, truth_kind: str = "scene",
             single: bool = False, spinup_s: float = 0.0, seed: int | None = None) -> dict:
    from cbh.actions.pairground import pair_ground
    from cbh.geometry.station import load_station
    from cbh.geometry.sun import sun_position
    from cbh.actions.nowcast import _ensemble
    from cbh.outputs.nowcast import Site, lagged_shade, shade_probability
    from cbh.pipeline import Pipeline
    from cbh.pipeline.motion import PairState
    from cbh.presets import scene_path, station_path
    from cbh.sim import SkySimulator, load_scene
    from cbh.sim.ground import ground_shade

    sc = reseeded(load_scene(scene_path(scene)), seed)
    sim = SkySimulator(load_station(station_path()), sc, size_px=size)
    st = sim.station
    pipe, state = Pipeline(st), PairState.start()
    cam1 = st.pair()[0].name
    n = int(minutes * 60 / CADENCE_S) + 1
    z = float(st.cameras[cam1].position_m[2])
    sites = [np.array([x, y, z]) for x, y in SITES_M]
    truth: dict[float, list] = {}
    issued = []  # (issue time [s], PairGround, the ensemble's pairs up to it)
    history: list = []
    recent: list = []  # every valid pair's motions of the last 10 min (the motion errors)
    t0 = sc.time_utc
    for i in range(n):
        t = t0 + timedelta(seconds=CADENCE_S * i)
        shot = sim.render(t)
        sp = sun_position(st.latitude_deg, st.longitude_deg, st.altitude_m, t)
        if truth_kind == "scene":
            truth[CADENCE_S * i] = list(ground_shade(sim, t, np.array(sites))[0])
        else:
            truth[CADENCE_S * i] = [truth_shade(shot.views[cam1], shot.layers, sp.direction_enu, s) for s in sites]
        r = pipe.process(shot.views[cam1].image, shot.views[st.pair()[1].name].image, t, channels="bgr",
                         previous=state)
        state = r.state
        pg = pair_ground(st, pipe.config.masks, r)
        history = _ensemble(history, pg, recent) if pg.valid else history
        issued.append((CADENCE_S * i, pg, list(history) if pg.valid else [pg]))
    out = {"scene": scene, "seed": seed, "size_px": size, "sites": len(sites), "truth": truth_kind, "leads": {}}
    places = [Site(f"s{k}", math.nan, math.nan, float(p[2]), p) for k, p in enumerate(sites)]
    for lead in LEADS_S:
        hits, errs, edges_n, covered, covered_hits = 0, [], 0, 0, 0
        for k, site in enumerate(sites):
            tt = [ti + lead for ti, _, _ in issued if ti + lead in truth and ti >= spinup_s]
            true_s = [truth[t][k] for t in tt]
            fc = []
            for ti, pg, hist in issued:
                if ti + lead not in truth or ti < spinup_s:
                    continue
                tv = t0 + timedelta(seconds=ti + lead)
                sp = sun_position(st.latitude_deg, st.longitude_deg, st.altitude_m, tv)
                p, _ = (shade_probability(pg, site, sp.direction_enu, lead) if single
                        else lagged_shade(hist, places[k], sp.direction_enu, tv))
                fc.append(float(p >= 0.5) if math.isfinite(p) else math.nan)
            te, fe = _edges(tt, true_s), _edges(tt, fc)
            known = {t for t, f in zip(tt, fc) if math.isfinite(f)}
            for t_edge, sign in te:
                edges_n += 1
                cands = [abs(tf - t_edge) for tf, sf in fe if sf == sign]
                e = min(cands) if cands else math.inf
                errs.append(e)
                hits += e <= 60.0
                # the forecast was issued on both sides of the edge (not beyond_view / motion_unknown)
                if {t_edge - CADENCE_S / 2, t_edge + CADENCE_S / 2} <= known:
                    covered += 1
                    covered_hits += e <= 60.0
        out["leads"][int(lead)] = {"edges": edges_n, "within_60s": hits,
                                   "share": round(hits / edges_n, 3) if edges_n else None,
                                   "with_forecast": covered, "with_forecast_within_60s": covered_hits,
                                   "share_with_forecast": round(covered_hits / covered, 3) if covered else None,
                                   "median_abs_error_s": float(np.median(errs)) if errs else None}
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="two-layers")
    ap.add_argument("--size", type=int, default=480)
    ap.add_argument("--minutes", type=float, default=10.0)
    ap.add_argument("--truth", choices=("scene", "camera"), default="scene")
    ap.add_argument("--single", action="store_true", help="the issue pair's own forecast, no lagged ensemble")
    ap.add_argument("--spinup", type=float, default=0.0, help="issue times before this [s] are not scored (a station just started)")
    ap.add_argument("--seed", type=int, help="another draw of the scene: its seed N, layer k's seed 10 N + k")
    ap.add_argument("--json")
    a = ap.parse_args()
    res = evaluate(a.scene, a.size, a.minutes, a.truth, a.single, a.spinup, a.seed)
    for lead, v in res["leads"].items():
        print(f"lead {lead:4d} s: {v['edges']:3d} shadow edges, {v['within_60s']:3d} within 60 s ({v['share']}), "
              f"median |error| {v['median_abs_error_s']} s; with a forecast issued: {v['with_forecast_within_60s']}"
              f"/{v['with_forecast']} ({v['share_with_forecast']})")
    if a.json:
        with open(a.json, "w") as fh:
            json.dump(res, fh, indent=1)


if __name__ == "__main__":
    main()
