"""`cbh export --product metar|cl61|eprofile`: METAR cloud groups and ceilometer-shaped files.

* ``metar``: one row per recorded pair, the METAR cloud groups of the window
  (:data:`cbh.outputs.aviation.WINDOW_S`) ending at it, from ampycloud on hits made of cbh's
  results (:mod:`cbh.outputs.aviation` says how and why).
* ``cl61`` / ``eprofile``: :mod:`cbh.outputs.ceilometer`.
"""
from __future__ import annotations

import logging
from collections import deque
from pathlib import Path

from cbh.errors import ConfigError, RecordingError

__all__ = ["PRODUCTS", "export_product", "metar_reports", "export_metar"]

log = logging.getLogger(__name__)

PRODUCTS = ("metar", "cl61", "eprofile")


def _pairs_hits(sessions, method: str, n: int, heights: str):
    """(time_utc, PairHits) of every complete pair of the sessions, in time order."""
    from cbh.actions.pairground import pair_ground
    from cbh.outputs.aviation import get_hit_method
    from cbh.outputs.record import open_session
    from cbh.pipeline.config import PipelineConfig

    sampler = get_hit_method(method)
    out = []
    seen = set()
    for path in sessions:
        s = open_session(path)
        st = s.station
        cfg = PipelineConfig.from_dict(s.config, where="recorded pipeline config")
        for pair in s.pairs():
            res = pair.result
            if res.time_utc in seen:
                log.warning("dropping a second pair at %s (same session given twice?)", res.time_utc.isoformat())
                continue
            seen.add(res.time_utc)
            pg = pair_ground(st, cfg.masks, res)
            if not pg.valid:
                continue  # an invalidating flag: its layers are not to be trusted
            import numpy as np

            hm = np.asarray(res.height_map, np.float32)
            out.append((res.time_utc, sampler(pg.camera, pg.labels, hm, pg.heights, n=n, heights=heights)))
    out.sort(key=lambda o: o[0])
    return out


def _thin(window: list, max_measurements: int) -> list:
    """Every k-th pair of the window, counted back from the latest, so that the measurements
    stay within ``max_measurements`` (ampycloud's clustering grows with the square of the hits)."""
    total = sum(ph.measurements for _, ph in window)
    if total <= max_measurements or not window:
        return window
    k = -(-total // max_measurements)
    return window[::-1][::k][::-1]


def metar_reports(sessions, *, method: str = "virtual", n: int = 128, heights: str = "layer",
                  window_s: float | None = None, msa_ft: float | None = None, every_s: float = 0.0):
    """METAR reports (:class:`cbh.outputs.aviation.MetarReport`) at every pair of the sessions
    (or, counted back from the last pair, at most one per ``every_s`` seconds), each from the hits of the window before it."""
    from cbh.outputs.aviation import MAX_HITS, WINDOW_S, metar_report

    if heights not in ("layer", "pixel"):
        raise ConfigError(f"METAR hit heights: unknown {heights!r} (valid: layer, pixel)")
    if n < 1:
        raise ConfigError(f"METAR virtual ceilometers: must be >= 1, got {n}")
    window_s = WINDOW_S if window_s is None else float(window_s)
    hits = _pairs_hits(sessions, method, n, heights)
    if not hits:
        raise RecordingError("no complete pairs in the recording(s): nothing to export")
    keep = set()  # report times: the last pair, then every pair at least every_s before the one kept after it
    nxt = None
    for t, _ in reversed(hits):
        if nxt is None or (nxt - t).total_seconds() >= every_s:
            keep.add(t)
            nxt = t
    reports = []
    win: deque = deque()
    for t, ph in hits:
        win.append((t, ph))
        while (t - win[0][0]).total_seconds() > window_s:
            win.popleft()
        if t in keep:
            reports.append(metar_report(t, _thin(list(win), MAX_HITS), msa_ft))
    return reports


def export_metar(sessions, out, **kw) -> str:
    from cbh.outputs.aviation import write_metar_csv

    reports = metar_reports(sessions, **kw)
    write_metar_csv(reports, out)
    return f"wrote {len(reports)} METAR cloud reports (last: {reports[-1].metar or '-'}) to {out}"


def export_product(sessions, out, product: str, fmt: str | None = None) -> str:
    """Write ``product`` (one of :data:`PRODUCTS`) of the sessions to ``out``; returns the
    summary line the CLI prints."""
    out = Path(out)
    if out.is_dir():
        raise RecordingError(f"--out {out}: is a directory; give a file name")
    if not out.parent.is_dir():
        raise RecordingError(f"output directory does not exist: {out.parent}")
    want = {"metar": "csv", "cl61": "netcdf", "eprofile": "netcdf"}[product]
    if fmt is not None and fmt.lower() != want:
        raise ConfigError(f"--product {product} is written as {want}, not {fmt!r}")
    if product == "metar":
        return export_metar(sessions, out)
    from cbh.outputs import ceilometer
    from cbh.outputs.export import session_records

    records, info = session_records(sessions)
    if not records:
        raise RecordingError("no complete pairs in the recording(s): nothing to export")
    ceilometer.write_product(records, info, out, product)
    return f"wrote {product} of {len(records)} time steps to {out}"
