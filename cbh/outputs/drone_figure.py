"""The drone check's figure: the drone's track over each camera's sky, and the errors by height and sector."""
from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["drone_figure"]

SECTOR_COLOURS = {"centre": "tab:green", "N": "tab:blue", "E": "tab:orange", "S": "tab:red", "W": "tab:purple"}


def _sky_panel(ax, name: str, stack: np.ndarray, track, log_t, enu, offset_s: float) -> None:
    from cbh.pipeline.dronetrack import interp_log, nearest_to_log

    ax.imshow(np.clip(stack.astype(np.float32) * 2.5, 0, 255), cmap="gray", vmin=0, vmax=255)
    t = np.arange(log_t[0], log_t[-1], 0.5)
    px = track.camera.world_to_pixel(interp_log(log_t, enu, t))
    ax.plot(px[:, 0], px[:, 1], "-", color="tab:cyan", lw=0.6, label="flight log")
    _, idx, _ = nearest_to_log(track, log_t, enu, offset_s)
    seen = track.pixels[idx[idx >= 0]]
    ax.plot(seen[:, 0], seen[:, 1], ".", color="tab:orange", ms=2.0, label="drone found")
    ax.set_title(f"{name}: the drone's track over the night's frames", fontsize=9)
    ax.legend(loc="lower right", fontsize=7)
    ax.set_axis_off()


def drone_figure(path: Path, rep: dict, stacks: dict, tracks, log_t, enu, offset_s: float) -> None:
    """Write the figure (PNG, whole or not at all): each camera's frames stacked (brightest
    at night) with the log's track and the drone's detections, the height error against the
    logged height by sector, and MAPE by sector."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from cbh.outputs.figures import save_figure

    by_name = {tr.camera.name: tr for tr in tracks}
    names = list(stacks)[:2]
    fig, axes = plt.subplots(2, 2, figsize=(10, 9.5))
    for ax, n in zip(axes[0], names):
        _sky_panel(ax, n, stacks[n], by_name[n], log_t, enu, offset_s)
    rows = rep["rows"]
    ax = axes[1, 0]
    for sec, col in SECTOR_COLOURS.items():
        r = [x for x in rows if x["sector"] == sec and np.isfinite(x["error_m"])]
        if r:
            ax.plot([x["logged_height_m"] for x in r], [x["error_m"] for x in r], "o", color=col, label=sec)
    ax.axhline(0, color="k", lw=0.6)
    ax.set_xlabel("logged height above camera 1 [m]"), ax.set_ylabel("measured − logged height [m]")
    ax.legend(fontsize=8, title="sector")
    ax = axes[1, 1]
    secs = list(rep["summary"]["by_sector"])
    vals = [rep["summary"]["by_sector"][s]["mape_pct"] or 0.0 for s in secs]
    ax.bar(secs, vals, color=[SECTOR_COLOURS[s] for s in secs])
    ax.set_ylabel("MAPE [%]"), ax.set_title(f"clock offset of the log {offset_s:+.2f} s", fontsize=9)
    fig.tight_layout()
    try:
        save_figure(fig, Path(path))
    finally:
        plt.close(fig)
