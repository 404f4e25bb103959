"""``cbh calibrate-lens --report DIR``: residuals per image (CSV, PNG) and where the corners fell.

Files: ``images.csv`` (errors per image), ``residuals.csv`` (every corner: pixel, angle from the
axis, residual, held-out residual), ``residuals.png`` (per-image RMS, error against angle, the
residual vectors over the frame) and ``coverage.png`` (the corners over the frame with circles
every 30° from the axis, the angles no corner backs hatched, where the model is extrapolated,
and the coverage warnings below: is the periphery that matters for the sky covered?).
"""
from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

__all__ = ["write_lens_report"]


def _write_images_csv(path: Path, report: dict) -> None:
    keys = ["file", "board_found", "detector", "n_points", "rms_euclid_px", "rms_coord_px", "mean_euclid_px",
            "max_euclid_px", "held_out_rms_euclid_px", "held_out_rms_coord_px", "max_theta_deg"]
    with path.open("w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=keys, extrasaction="ignore")
        w.writeheader()
        for row in report["images"]:
            w.writerow(row)


def _write_residuals_csv(path: Path, model, corners, residuals, held, files, ids, rejected) -> None:
    with path.open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["file", "corner", "x_px", "y_px", "theta_deg", "dx_px", "dy_px", "err_px",
                    "held_out_dx_px", "held_out_dy_px", "outlier"])
        for k, (c, r) in enumerate(zip(corners, residuals)):
            th = model.theta_of_pixel(c)
            for j in range(len(c)):
                h = ("", "") if held is None else (f"{held[k][j, 0]:.5f}", f"{held[k][j, 1]:.5f}")
                w.writerow([Path(files[k]).name, int(ids[k][j]), f"{c[j, 0]:.4f}", f"{c[j, 1]:.4f}", f"{th[j]:.3f}",
                            f"{r[j, 0]:.5f}", f"{r[j, 1]:.5f}", f"{np.hypot(*r[j]):.5f}", *h, 0])
        for b in rejected:  # left out of the fit: residual through the final lens, no held-out value
            th = float(model.theta_of_pixel([[b["x_px"], b["y_px"]]])[0])
            w.writerow([Path(b["file"]).name, b["corner"], f"{b['x_px']:.4f}", f"{b['y_px']:.4f}", f"{th:.3f}",
                        f"{b['dx_px']:.5f}", f"{b['dy_px']:.5f}", f"{b['err_px']:.5f}", "", "", 1])


def _plot_residuals(path: Path, report: dict, model, corners, residuals) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    found = [e for e in report["images"] if e["board_found"]]
    fig, ax = plt.subplots(1, 3, figsize=(15, 4.6))
    x = np.arange(len(found))
    ax[0].bar(x - 0.2, [e["rms_euclid_px"] for e in found], 0.4, label="fit")
    if report["held_out"] is not None:
        ax[0].bar(x + 0.2, [e["held_out_rms_euclid_px"] for e in found], 0.4, label="held out")
    ax[0].set_xticks(x, [Path(e["file"]).stem for e in found], rotation=60, fontsize=7)
    ax[0].set_ylabel("per-point Euclidean RMS [px]")
    ax[0].legend()
    for c, r in zip(corners, residuals):
        ax[1].plot(model.theta_of_pixel(c), np.hypot(r[:, 0], r[:, 1]), ".", ms=3)
    ax[1].set_xlabel("angle from the optical axis [deg]")
    ax[1].set_ylabel("reprojection error [px]")
    allc, allr = np.concatenate(corners), np.concatenate(residuals)
    scale = 0.05 * model.width / max(float(np.max(np.hypot(allr[:, 0], allr[:, 1]))), 1e-9)
    ax[2].quiver(allc[:, 0], allc[:, 1], allr[:, 0] * scale, allr[:, 1] * scale, angles="xy", scale_units="xy",
                 scale=1, width=0.003)
    ax[2].set_xlim(0, model.width)
    ax[2].set_ylim(model.height, 0)
    ax[2].set_aspect("equal")
    ax[2].set_title(f"residuals × {scale:.0f}", fontsize=9)
    o = report["overall"]
    fig.suptitle(f"reprojection: {o['rms_euclid_px']:.3f} px per-point Euclidean RMS, "
                 f"{o['rms_coord_px']:.3f} px per coordinate")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _plot_coverage(path: Path, model, corners, files, cov: dict | None = None) -> None:
    """The corners over the frame, circles every 30° from the axis; with the report's ``coverage``,
    the angles no corner backs (where the model is extrapolated) hatched and the gaps written below."""
    import textwrap

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    notes = [] if cov is None else [f"warning: {w}" for w in cov["warnings"]]
    wrapped = [textwrap.fill(n, 110) for n in notes]
    n_lines = sum(w.count("\n") + 1 for w in wrapped)
    fig, ax = plt.subplots(figsize=(9.6, 8 * model.height / model.width + 0.6 + 0.16 * n_lines))
    th = model.theta_map()
    top = float(np.nanmax(th)) if cov is None else cov["frame_theta_deg"]
    levels = [a for a in range(30, 180, 30) if a < top]
    cs = ax.contour(th, levels=levels, colors=["0.3" if a != 90 else "k" for a in levels], linewidths=1)
    ax.clabel(cs, fmt="%d°", fontsize=8)
    if cov is not None:
        lo, hi = cov["extrapolation"]["data_theta_deg"]
        out = np.ma.masked_where((th >= lo) & (th <= hi), np.ones_like(th))
        ax.contourf(out, levels=[0.5, 1.5], colors="none", hatches=["////"], zorder=0)
        ax.contour(th, levels=sorted({lo, hi}), colors="tab:red", linestyles="--", linewidths=1)
        ax.plot([], [], color="tab:red", ls="--", label=f"corners {lo:.0f}°–{hi:.0f}°\nhatched: extrapolated")
    for c, f in zip(corners, files):
        ax.plot(c[:, 0], c[:, 1], ".", ms=4, label=Path(f).stem)
    ax.set_xlim(-0.5, model.width - 0.5)
    ax.set_ylim(model.height - 0.5, -0.5)
    ax.set_aspect("equal")
    ax.set_title("board corners over the field of view (circles: angle from the axis)")
    if len(files) <= 20:  # beside the frame, not over its corners
        ax.legend(fontsize=6, loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0.0)
    if wrapped:
        fig.text(0.01, 0.01, "\n".join(wrapped), fontsize=7, color="tab:red", va="bottom")
    fig.tight_layout(rect=(0, 0.03 * n_lines, 1, 1))
    fig.savefig(path, dpi=110)
    plt.close(fig)


def write_lens_report(folder: Path, report: dict, model, corners, residuals, held, files, ids=None) -> list[Path]:
    """Write the report files of a lens calibration into ``folder`` (created if needed).

    Parameters
    ----------
    folder : Path
    report : dict
        :func:`cbh.actions.calibrate_lens.calibrate_lens`'s report (per-image and overall errors).
    model : OCamModel
        The written lens.
    corners, residuals : sequence of ndarray, each shape (N_i, 2), float
        Detected corners [px] and their residuals [px], per image with a board.
    held : sequence of ndarray or None
        Held-out residuals [px], per image.
    files : sequence of Path
        The images with a board, in the same order.
    ids : sequence of ndarray, each shape (N_i,), int, optional
        Each corner's index on its board (default 0…N_i − 1); corners the fit left out as
        outliers (the report's ``rejected_corners``) are written after the others, flagged.

    Returns
    -------
    list of Path
        The files written.
    """
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    out = [folder / "images.csv", folder / "residuals.csv", folder / "residuals.png", folder / "coverage.png"]
    _write_images_csv(out[0], report)
    ids = [np.arange(len(c)) for c in corners] if ids is None else ids
    _write_residuals_csv(out[1], model, corners, residuals, held, files, ids, report.get("rejected_corners", []))
    _plot_residuals(out[2], report, model, corners, residuals)
    _plot_coverage(out[3], model, corners, files, report.get("coverage"))
    return out
