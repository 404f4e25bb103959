"""`cbh quicklook`: a ceilometer-style picture of recorded sessions (matplotlib, Agg backend).

Panels, sharing the UTC time axis:

1. **Cloud bases**: every layer's base height above ground against time, coloured by the
   layer's cover in okta (0–8; the colour bar), marker per layer number (1 = lowest); the
   ceiling (:func:`cbh.outputs.export.ceiling_index`) as a black line; layers of a pair with
   an invalidating flag drawn as red crosses (exported, not trusted).
2. **Cloud fraction** of the reference camera (0–1), with the total okta on the right axis.
3. **Layer speed** over the ground [m/s] per layer.
4. **Layer direction**: where each layer moves *towards*, degrees clockwise from north.

Panels 3–4 say "motion unknown" when no pair carries motion (recordings made without motion
estimation).
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from cbh.errors import ConfigError, RecordingError
from cbh.flags import INVALIDATING
from cbh.outputs.export import ceiling_index, okta, session_records
from cbh.outputs.figures import save_figure

__all__ = ["quicklook", "draw_quicklook", "MARKERS"]

MARKERS = ("o", "s", "^", "D", "v", "P")  # layer 1, 2, 3 …


def draw_quicklook(records, info: dict, out, *, title: str | None = None, dpi: int = 120, ghi: dict | None = None) -> None:
    """Draw the quicklook of pair records (:func:`cbh.outputs.export.session_records`) to ``out``
    (PNG); with ``ghi`` (:func:`_ghi_series`) a fifth panel: the pyranometer's GHI, the clear sky and
    the nowcast issued 5 and 10 min before."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if not records:
        raise RecordingError("no complete pairs in the recording(s): nothing to draw")
    t = _Series(records)
    rows = 5 if ghi else 4
    fig, axes = plt.subplots(rows, 1, figsize=(11, 9.5 + 2.0 * (rows - 4)), sharex=True,
                             gridspec_kw={"height_ratios": [3.2, 1.2, 1.2, 1.2, 1.8][:rows], "hspace": 0.12})
    fig.subplots_adjust(left=0.09, right=0.86, top=0.95, bottom=0.07)
    try:
        _draw_heights(fig, axes[0], t, title or f"cbh quicklook — station {info['station']} "
                      f"({info['latitude_deg']:.4f}°, {info['longitude_deg']:.4f}°, {info['altitude_m']:.0f} m)")
        _draw_fraction(axes[1], t)
        _draw_motion(axes[2], axes[3], t)
        if ghi:
            _draw_ghi(axes[4], ghi)
            axes[3].set_xlabel("")
            axes[4].set_xlabel("time (UTC)")
        save_figure(fig, out, dpi)
    finally:
        plt.close(fig)


class _Series:
    """The quicklook's time series, gaps broken (:func:`_break_gaps`): ``times`` (T,)
    datetime64[us]; per layer (T, L): ``H`` height [m], ``C`` cover, ``VE``/``VN`` motion
    [m/s]; per time (T,): ``ceil`` [m], ``cf`` cloud fraction, ``bad`` (an invalidating flag)."""

    def __init__(self, records):
        times = np.array([np.datetime64(r.time_utc.replace(tzinfo=None), "us") for r in records])
        self.n_l = n_l = max([len(r.height_m) for r in records] + [1])
        H, C, VE, VN = (np.full((len(records), n_l), np.nan) for _ in range(4))
        bad = np.zeros(len(records), bool)
        ceil = np.full(len(records), np.nan)
        for i, r in enumerate(records):
            k = len(r.height_m)
            H[i, :k], C[i, :k] = r.height_m, r.cover
            VE[i, :k] = r.motion_east_ms or [math.nan] * k
            VN[i, :k] = r.motion_north_ms or [math.nan] * k
            bad[i] = bool(set(r.flags) & INVALIDATING)
            c = ceiling_index(r.cover)
            if c is not None:
                ceil[i] = r.height_m[c]
        cf = np.array([r.cloud_fraction for r in records])
        self.times, arrays, self.bad = _break_gaps(times, (H, C, VE, VN, ceil, cf), bad)
        self.H, self.C, self.VE, self.VN, self.ceil, self.cf = arrays


def _draw_heights(fig, ax, t: _Series, title: str) -> None:
    """Panel 1: each layer's base [km] coloured by its cover (okta), flagged pairs as red
    crosses, the ceiling as a black line; the okta colour bar to the right."""
    import matplotlib.pyplot as plt
    from matplotlib.colors import BoundaryNorm, ListedColormap

    okta_cmap = ListedColormap(plt.get_cmap("viridis_r")(np.linspace(0.05, 0.95, 9)))
    norm = BoundaryNorm(np.arange(-0.5, 9.5, 1.0), 9)
    sc = None
    for k in range(t.n_l):
        good = np.isfinite(t.H[:, k]) & ~t.bad
        okt = np.array([okta(c) for c in t.C[:, k]], float)
        sc = ax.scatter(t.times[good], t.H[good, k] / 1000.0, c=okt[good], cmap=okta_cmap, norm=norm, s=26,
                        marker=MARKERS[k % len(MARKERS)], edgecolors="k", linewidths=0.3, label=f"layer {k + 1}",
                        zorder=3)
        flagged = np.isfinite(t.H[:, k]) & t.bad
        if flagged.any():
            ax.scatter(t.times[flagged], t.H[flagged, k] / 1000.0, marker="x", c="tab:red", s=30, zorder=4,
                       label="invalid (flagged)" if k == 0 else None)
    if np.isfinite(t.ceil).any():
        ax.plot(t.times, t.ceil / 1000.0, color="k", lw=1.0, label="ceiling (≥ 5 okta)", zorder=2)
    top = np.nanmax(t.H) if np.isfinite(t.H).any() else 1000.0
    ax.set_ylim(0, max(1.0, top * 1.2 / 1000.0))
    ax.set_ylabel("cloud base above ground [km]")
    ax.grid(alpha=0.3)
    ax.legend(loc="upper left", fontsize=8, ncol=4, framealpha=0.8)
    pos = ax.get_position()
    cax = fig.add_axes([0.915, pos.y0, 0.015, pos.height])  # right of the okta axis of panel 2
    cb = fig.colorbar(sc, cax=cax, ticks=range(9))
    cb.set_label("layer cover [okta]")
    ax.set_title(title, fontsize=11)


def _draw_fraction(ax, t: _Series) -> None:
    """Panel 2: total cloud fraction (0..1, with an okta axis on the right)."""
    ax.fill_between(t.times, 0, t.cf, where=np.isfinite(t.cf), color="0.75")
    ax.plot(t.times, t.cf, color="0.3", lw=1)
    ax.set_ylim(0, 1)
    ax.set_ylabel("cloud\nfraction")
    ax.grid(alpha=0.3)
    ax2 = ax.twinx()
    ax2.set_ylim(0, 8)
    ax2.set_yticks([0, 2, 4, 6, 8])
    ax2.set_ylabel("okta")


def _draw_motion(ax_speed, ax_dir, t: _Series) -> None:
    """Panels 3 and 4: each layer's speed [m/s] and the direction it moves towards (no lines
    across 0/360), "motion unknown" where no pair has motion; the time axis (UTC)."""
    import matplotlib.dates as mdates

    speed = np.hypot(t.VE, t.VN)
    direction = np.degrees(np.arctan2(t.VE, t.VN)) % 360.0
    known = np.isfinite(speed).any()
    for ax, data, label, lw in ((ax_speed, speed, "speed\n[m/s]", 0.8),
                                (ax_dir, direction, "moves towards\n[deg from N]", 0.0)):
        for k in range(t.n_l):
            ax.plot(t.times, data[:, k], marker=MARKERS[k % len(MARKERS)], ms=3.5, lw=lw, label=f"layer {k + 1}")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
        if not known:
            ax.text(0.5, 0.5, "motion unknown (not estimated in these recordings)", transform=ax.transAxes,
                    ha="center", va="center", color="0.4")
    if known:
        ax_speed.set_ylim(0, max(1.0, np.nanmax(speed) * 1.25))
        ax_speed.legend(loc="upper left", fontsize=8, ncol=t.n_l)
    else:
        ax_speed.set_ylim(0, 10)
    ax_dir.set_ylim(0, 360)
    ax_dir.set_yticks([0, 90, 180, 270, 360], ["N", "E", "S", "W", "N"])
    loc = mdates.AutoDateLocator(minticks=4, maxticks=10)
    ax_dir.xaxis.set_major_locator(loc)
    ax_dir.xaxis.set_major_formatter(mdates.ConciseDateFormatter(loc))
    ax_dir.set_xlabel("time (UTC)")


def _ghi_series(sessions, pyranometer) -> dict:
    """The GHI panel's series at the station (camera 1's site): measured, clear sky, and the
    nowcast at 5 and 10 min, each at its valid time (:func:`cbh.actions.nowcast.ghi_series`)."""
    from cbh.actions.nowcast import ghi_series
    from cbh.outputs.record import open_session

    st = open_session(list(sessions)[0]).station
    return ghi_series(sessions, [f"{st.name}={st.latitude_deg},{st.longitude_deg}"], pyranometer)[st.name]


def _draw_ghi(ax, ghi: dict) -> None:
    styles = {"measured": dict(color="k", lw=1.4), "clear": dict(color="0.6", lw=1.0, ls="--"),
              "nowcast 5 min ahead": dict(color="tab:orange", lw=1.0, marker=".", ms=4),
              "nowcast 10 min ahead": dict(color="tab:red", lw=1.0, marker=".", ms=4)}
    for name, (t, v) in ghi.items():
        ax.plot(t, v, label="clear sky (pvlib Ineichen)" if name == "clear" else name, **styles.get(name, {}))
    ax.set_ylabel("GHI at the station\n[W/m²]")
    ax.set_ylim(bottom=0)
    ax.legend(loc="upper left", fontsize=8, ncol=4)
    ax.grid(alpha=0.3)


def _break_gaps(times: np.ndarray, arrays: tuple, bad: np.ndarray):
    """Insert an all-NaN step in every gap longer than 3 median cadences (at least 60 s), so
    that lines and fills do not bridge the time between sessions."""
    if len(times) < 3:
        return times, arrays, bad
    dt = np.diff(times).astype("timedelta64[us]").astype(np.float64) / 1e6
    limit = max(3.0 * float(np.median(dt)), 60.0)
    gaps = np.flatnonzero(dt > limit)
    if not gaps.size:
        return times, arrays, bad
    mids = times[gaps] + (times[gaps + 1] - times[gaps]) / 2
    times = np.insert(times, gaps + 1, mids)
    arrays = tuple(np.insert(a, gaps + 1, np.nan, axis=0) for a in arrays)
    return times, arrays, np.insert(bad, gaps + 1, False)


def _check_image_suffix(out: Path) -> None:
    """:class:`ConfigError` unless matplotlib can write ``out``'s suffix (none: PNG), checked
    before the recordings are read (an unknown suffix, e.g. ``-o x.mcap``, was a traceback)."""
    from matplotlib.backend_bases import FigureCanvasBase

    kinds = FigureCanvasBase.get_supported_filetypes()
    suffix = out.suffix[1:].lower()
    if suffix and suffix not in kinds:
        raise ConfigError(f"--out {out}: cannot draw a {suffix!r} file (use .png, or one of "
                          f"{', '.join(sorted(kinds))})")


def quicklook(sessions, out, *, title: str | None = None, pyranometer=None) -> str:
    """Draw the quicklook of recorded sessions to ``out`` (PNG); returns the CLI's summary line.
    With a pyranometer (``pyranometer``, or the recorded station's ``[station] pyranometer``) it
    gains the GHI panel: measured, clear sky, and cbh's nowcast 5 and 10 min ahead."""
    from cbh.fileio import refuse_inputs

    out = Path(out)
    sessions = list(sessions) if isinstance(sessions, (list, tuple)) else [sessions]
    refuse_inputs([out], [*sessions, pyranometer], "--out")
    if out.is_dir():
        raise RecordingError(f"--out {out}: is a directory; give the image's file name (e.g. {out / 'quicklook.png'})")
    if not out.parent.is_dir():
        raise RecordingError(f"output directory does not exist: {out.parent}")
    _check_image_suffix(out)
    if not out.suffix:
        out = out.with_suffix(".png")  # what matplotlib would write; the summary names the real file
    records, info = session_records(sessions)
    if pyranometer is None:
        from cbh.outputs.record import open_session

        rec_pyr = open_session(sessions[0]).station.pyranometer
        pyranometer = rec_pyr if rec_pyr is not None and Path(rec_pyr).is_file() else None
    ghi = _ghi_series(sessions, pyranometer) if pyranometer is not None else None
    draw_quicklook(records, info, out, title=title, ghi=ghi)
    return f"drew {len(records)} time steps to {out}" + (" with the GHI panel" if ghi else "")
