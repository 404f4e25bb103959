"""Regenerate docs/ground-maps.png: cloud map per layer and shadow map of one simulated pair.

The real chain: `cbh run` on the simulated two-layer scene (640 px) records twelve pairs 10 s apart (the
last pair's "sun blocked now" needs earlier pairs whose view of the cloud on the sun ray was
outside the masked sun disk), and
`cbh.actions.export.ground_maps` projects camera 1's cloud mask onto the station's ground grid
(the same code as `cbh export --product cloudmap|shadow`).
Run from the repository root: python scripts/make_ground_figure.py
"""
from __future__ import annotations

import tempfile
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.colors import ListedColormap  # noqa: E402

from cbh.actions.export import ground_maps  # noqa: E402
from cbh.cli.main import main as cbh  # noqa: E402
from cbh.outputs.maps import to_float  # noqa: E402

REPO = Path(__file__).resolve().parents[1]


def main() -> None:
    out = REPO / "docs" / "ground-maps.png"
    with tempfile.TemporaryDirectory() as d:
        rec = Path(d) / "sim.mcap"
        if cbh(["run", "--station", "unb-lea", "--scene", "two-layers", "--size", "640", "--frames", "12",
                "--record", str(rec), "-q"]):
            raise SystemExit(1)
        m = ground_maps([rec])
    i = len(m.times) - 1
    km = m.grid.x_m / 1000.0
    ext = [km[0], km[-1], km[0], km[-1]]
    fig, axes = plt.subplots(1, 3, figsize=(15, 5.2), constrained_layout=True)
    grey = ListedColormap(["#cfe3f5", "#4a4a4a"])
    for k, ax in enumerate(axes[:2]):
        ax.imshow(to_float(m.layer_cloud[i, k]), origin="lower", extent=ext, cmap=grey, vmin=0, vmax=1,
                  interpolation="nearest")
        ax.set_title(f"layer {k + 1} at {m.layer_height_m[i, k]:.0f} m: cloud overhead\n"
                     "(dark cloud, light clear, white unknown)", fontsize=10)
    ax = axes[2]
    ax.imshow(to_float(m.shadow[i]), origin="lower", extent=ext, cmap=ListedColormap(["#f7e08a", "#5b5b73"]), vmin=0, vmax=1,
              interpolation="nearest")
    az = np.radians(m.sun_azimuth_deg[i])
    ax.annotate("", xy=(2.5 * np.sin(az), 2.5 * np.cos(az)), xytext=(0, 0),
                arrowprops=dict(arrowstyle="->", color="tab:red", lw=2))
    blocked = {1.0: "yes", 0.0: "no"}.get(float(m.sun_blocked[i, 0]), "unknown")
    ax.set_title(f"shadow on the ground (dark), sunlit (yellow); sun zenith {m.sun_zenith_deg[i]:.0f}°\n"
                 f"arrow: towards the sun; sun blocked at the station now: {blocked}", fontsize=10)
    for ax in axes:
        ax.plot(0, 0, marker="*", color="tab:red", ms=12)
        ax.set_xlabel("east of the station [km]")
    axes[0].set_ylabel("north of the station [km]")
    fig.suptitle(f"cbh export --product cloudmap|shadow — simulated two-layer sky, {m.times[i]:%Y-%m-%d %H:%M:%S} UTC, "
                 f"{m.grid.resolution_m:g} m cells", fontsize=11)
    fig.savefig(out, dpi=100)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
