"""What ``cbh inspect`` reports about a session (a plain dict, JSON-ready)."""
from __future__ import annotations

import numpy as np

from cbh.outputs.record.reader import Session

__all__ = ["describe_session", "format_description"]


def _iso(t) -> str:
    return t.isoformat().replace("+00:00", "Z")


def describe_session(s: Session) -> dict:
    """Time span, frames per camera, pairs, drops, topics, per-layer height statistics."""
    span = s.time_span
    cams = [c for c in s.metadata.get("cameras", "").split(",") if c]
    frames = {t.topic.split("/")[1]: t.count for t in s.topics if t.topic.endswith("/image/compressed")}
    heights: dict[int, list[float]] = {}
    n_clear = 0
    indices, cf, flags = [], [], {}
    for p in s.pairs(layers_only=True):
        indices.append(p.index)
        r = p.result
        if not r.layers:
            n_clear += 1
        for i, l in enumerate(r.layers):
            heights.setdefault(i, []).append(float(l.height_m))
        if r.cameras[0] in r.cloud_fraction:
            cf.append(float(r.cloud_fraction[r.cameras[0]]))
        for f in r.flags:
            flags[f] = flags.get(f, 0) + 1
    last_status = None
    for _t, stats in s.statuses():
        last_status = stats
    missing = 0
    if indices:  # pair indices the recorder assigned but whose pair is not in the file
        missing = int(indices[-1] - indices[0] + 1 - len(set(indices)))
    drops = {"missing_pair_indices": missing}
    if isinstance(last_status, dict):
        for k in ("pairs_processed", "pairs_dropped", "unpaired", "frames_dropped"):
            if isinstance(last_status.get(k), (int, float)):
                drops[k] = last_status[k]
    layers = []
    for i in sorted(heights):
        h = np.asarray(heights[i])
        layers.append({"layer": i, "pairs": int(h.size), "min_m": float(h.min()), "median_m": float(np.median(h)),
                       "max_m": float(h.max()), "mean_m": float(h.mean())})
    return {
        "files": [str(p) for p in s.paths],
        "station": s.station_name,
        "cameras": cams,
        "cbh_version": s.version,
        "start_utc": _iso(span[0]) if span else None,
        "end_utc": _iso(span[1]) if span else None,
        "duration_s": (span[1] - span[0]).total_seconds() if span else 0.0,
        "pairs": s.pair_count,
        "frames": frames,
        "status_messages": s.count("/service/status"),
        "drops": drops,
        "last_status": last_status,
        "topics": [{"topic": t.topic, "schema": t.schema, "encoding": t.encoding, "messages": t.count} for t in s.topics],
        "layers": layers,
        "pairs_without_layer": n_clear,
        "cloud_fraction_mean": float(np.mean(cf)) if cf else None,
        "flags": flags,
    }


def format_description(d: dict) -> str:
    """Human-readable text of :func:`describe_session`."""
    lines = [
        f"files:       {', '.join(d['files'])}",
        f"station:     {d['station']} (cameras {', '.join(d['cameras'])}), recorded by cbh {d['cbh_version']}",
    ]
    if d["start_utc"]:
        lines.append(f"time span:   {d['start_utc']} .. {d['end_utc']} ({d['duration_s']:.1f} s)")
    else:
        lines.append("time span:   (empty session)")
    fr = ", ".join(f"{k} {v}" for k, v in d["frames"].items()) or "none"
    lines.append(f"pairs:       {d['pairs']}   frames: {fr}   status messages: {d['status_messages']}")
    lines.append("drops:       " + ", ".join(f"{k} {v:g}" for k, v in d["drops"].items()))
    lines.append("topics:")
    w = max([len(t["topic"]) for t in d["topics"]] + [5])
    for t in d["topics"]:
        lines.append(f"  {t['topic']:<{w}}  {t['schema']:<26} {t['messages']:>6}")
    lines.append("layers (cloud-base height above ground, m):")
    for l in d["layers"]:
        lines.append(f"  layer {l['layer'] + 1}: {l['pairs']:>5} pairs  min {l['min_m']:8.1f}  median {l['median_m']:8.1f}"
                     f"  max {l['max_m']:8.1f}")
    lines.append(f"  no layer: {d['pairs_without_layer']} pairs")
    if d["cloud_fraction_mean"] is not None:
        lines.append(f"cloud fraction (reference camera): mean {d['cloud_fraction_mean']:.3f}")
    if d["flags"]:
        lines.append("flags:       " + ", ".join(f"{k} {v}" for k, v in sorted(d["flags"].items())))
    return "\n".join(lines)
