"""Rerun visualisation: the default blueprint, a live :class:`RerunSink`, and ``log_pair``.

What a meteorologist sees first (the default blueprint): both raw sky images with the cloud
mask drawn as a thin outline, the 3D cloud-base points, the height histogram and the layer
heights over time. One height colour map (turbo over ``HEIGHT_RANGE_M``, with a legend) is
used for the matches in the images, the 3D points, the height map and the layer time series,
so a colour means the same height everywhere.

Entities (time line ``capture_time``, UTC):

- ``/<cam>/image`` (EncodedImage, bytes as received), ``/<cam>/cloud_outline`` (LineStrips2D:
  the cloud mask's contours), ``/<cam>/cloud_mask`` (SegmentationImage, light fill; hidden by
  default), ``/<cam>/matches`` (Points2D: a subsample of at most ``MAX_SHOWN_MATCHES`` kept
  correspondences coloured by height; hidden by default), ``/<cam1>/flow`` (LineStrips2D
  x1,y1 → x2,y2; hidden by default);
- ``/world/points`` (Points3D, ENU [m], coloured by height), ``/world/cameras`` (positions and
  optical axes, static, one label for the pair), ``/world/motion`` (Arrows3D: each layer's
  displacement over ``MOTION_ARROW_S`` seconds at its height);
- ``/height_map`` (DepthImage [m above ground] on camera 1's grid, decimated to ≤ 960 px);
- ``/histogram`` (BarChart of point heights in linear bins, ~60 bars up to the highest
  point), ``/layers/<i>`` (Scalars: layer i+1's cloud-base height [m above ground], each
  sample coloured by its height), ``/cloud_fraction/<cam>`` (Scalars 0..1);
- ``/legend`` (Image: the height colour scale, static);
- ``/flags`` (TextDocument, markdown: valid or not and why, each flag with its meaning, the
  cameras' clock offset; :func:`flag_text`). A pair whose flags invalidate its layers
  (:data:`cbh.flags.INVALIDATING`) has its points, layer samples and motion drawn grey
  (``FLAGGED_RGB``), the layer samples as crosses: a flagged layer never looks like a valid one.

Modes: ``spawn`` (start a viewer), ``serve`` (gRPC server; viewers connect to the printed URL),
``connect`` (to a running viewer, ``target`` = URL, default the local one), ``save``
(``target`` = PATH.rrd). Every sink uses its own ``rr.RecordingStream``: several coexist.
"""
from __future__ import annotations

import logging
import math
import uuid
from pathlib import Path

import cv2
import numpy as np

from cbh.errors import ConfigError, RecordingError
from cbh.flags import INVALIDATING, flag_meaning
from cbh.interfaces import ResultSink
from cbh.result import Frame, PairResult, require_time, to_ns

__all__ = ["RerunSink", "default_blueprint", "log_pair", "flag_text", "log_station", "parse_rerun_spec", "height_colors",
           "legend_image", "display_histogram", "cloud_outline",
           "MODES", "TIMELINE"]

log = logging.getLogger(__name__)

MODES = ("spawn", "serve", "connect", "save")
TIMELINE = "capture_time"
HEIGHT_RANGE_M = (0.0, 10_000.0)  # colour scale of heights [m above ground]
MAX_SHOWN_MATCHES = 300  # matches shown per camera (a subsample: the cloud must stay visible)
MAX_HEIGHT_MAP_PX = 960  # the height map is shown decimated to at most this size [px]
MAX_OUTLINE_PX = 480  # the cloud outline is traced on the mask decimated to at most this size [px]
HIST_BARS = 60  # about this many histogram bars, whatever the height range
MOTION_ARROW_S = 300.0  # motion arrows show the displacement over this time [s]
FLUSH_TIMEOUT_S = 15.0  # ``connect``: the viewer must have taken everything within this at the end [s]


def parse_rerun_spec(mode: str, target: str | None = None) -> tuple[str, str | None]:
    """Validate a ``--rerun`` value: ``spawn``, ``serve``, ``connect [URL]``, ``save PATH.rrd``.

    ``MODE=TARGET`` in one value works too (``save=out.rrd``, ``connect=URL``).

    Shorthands: a value ending in ``.rrd`` means ``save`` to it; a ``rerun+http(s)://`` URL
    means ``connect`` to it.
    """
    m = (mode or "").strip()
    if target is None:  # MODE=TARGET / MODE:TARGET in one value (e.g. save=out.rrd, connect=URL)
        for name in ("connect", "save"):
            for sep in ("=", ":"):
                if m.lower().startswith(name + sep):
                    m, target = name, (m[len(name) + 1:] or None)
    if m.endswith(".rrd") and target is None:
        return "save", m
    if m.startswith(("rerun://", "rerun+http://", "rerun+https://")) and target is None:
        return "connect", m
    m = m.lower()
    if m not in MODES:
        raise ConfigError(f"--rerun: unknown mode {mode!r} (valid: {', '.join(MODES)}, PATH.rrd or a rerun+http:// URL)")
    if m == "save":
        if not target:
            raise ConfigError("--rerun save needs an output PATH.rrd")
        if not str(target).endswith(".rrd"):
            raise ConfigError(f"--rerun save: output must end in .rrd, got {target!r}")
    elif m in ("spawn", "serve") and target:
        raise ConfigError(f"--rerun {m} takes no target (got {target!r})")
    return m, (str(target) if target else None)


def _turbo_lut() -> np.ndarray:
    """(256, 3) uint8 RGB: OpenCV's turbo, the same map Rerun uses for the DepthImage."""
    return cv2.applyColorMap(np.arange(256, dtype=np.uint8).reshape(-1, 1), cv2.COLORMAP_TURBO)[:, 0, ::-1].copy()


def height_colors(height_m: np.ndarray, height_range_m=HEIGHT_RANGE_M) -> np.ndarray:
    """The one height colour map: (N,) heights [m] → (N, 3) uint8 RGB (turbo); NaN → grey."""
    h = np.asarray(height_m, np.float64).ravel()
    lo, hi = height_range_m
    u = np.clip((np.nan_to_num(h, nan=lo) - lo) / max(hi - lo, 1e-9), 0, 1)
    rgb = _turbo_lut()[np.round(u * 255).astype(int)]
    rgb[~np.isfinite(h)] = (128, 128, 128)
    return rgb.astype(np.uint8)


def legend_image(height_range_m=HEIGHT_RANGE_M, width_px: int = 600) -> np.ndarray:
    """The height colour scale as an RGB image (≈ 70 × ``width_px``) with km ticks."""
    lo, hi = height_range_m
    bar_h, pad = 26, 12
    img = np.full((bar_h + 44, width_px + 2 * pad, 3), 255, np.uint8)
    x = np.linspace(lo, hi, width_px)
    img[6:6 + bar_h, pad:pad + width_px] = height_colors(x, height_range_m)[None, :, :]
    step_km = max(1, int(round((hi - lo) / 1000.0 / 10)))
    for km in range(int(np.ceil(lo / 1000)), int(hi // 1000) + 1, step_km):
        xp = pad + int(round((km * 1000.0 - lo) / (hi - lo) * (width_px - 1)))
        cv2.line(img, (xp, 6 + bar_h), (xp, 12 + bar_h), (0, 0, 0), 1)
        label = f"{km}"
        (tw, _), _ = cv2.getTextSize(label, cv2.FONT_HERSHEY_SIMPLEX, 0.45, 1)
        cv2.putText(img, label, (xp - tw // 2, 28 + bar_h), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    cv2.putText(img, "cloud-base height above ground [km]", (pad, bar_h + 42), cv2.FONT_HERSHEY_SIMPLEX, 0.45,
                (0, 0, 0), 1, cv2.LINE_AA)
    return img


def display_histogram(edges_m: np.ndarray, counts: np.ndarray, bars: int = HIST_BARS):
    """Re-bin the pipeline's log-height histogram into ~``bars`` linear bins for display.

    Returns (centres_m, counts, width_m); the range runs from 0 to the highest occupied bin,
    rounded up to a whole km, so the bars are wide enough to see at default zoom.
    """
    edges_m = np.asarray(edges_m, np.float64)
    counts = np.asarray(counts, np.float64)
    occupied = np.flatnonzero(counts > 0)
    if not occupied.size:
        return np.zeros(0), np.zeros(0), 1.0
    top = max(1000.0, np.ceil(edges_m[occupied[-1] + 1] / 1000.0) * 1000.0)
    width = next(w for w in (25, 50, 100, 200, 250, 500, 1000, 2000) if top / w <= bars)
    lin = np.arange(0.0, top + width, width)
    centres = 0.5 * (edges_m[:-1] + edges_m[1:])
    out, _ = np.histogram(centres, bins=lin, weights=counts)
    return 0.5 * (lin[:-1] + lin[1:]), out, float(width)


def cloud_outline(mask: np.ndarray, max_px: int = MAX_OUTLINE_PX) -> list[np.ndarray]:
    """Contours of a cloud mask as polylines in full-size pixel coordinates.

    The mask is traced decimated to at most ``max_px`` (an outline, not a measurement);
    coordinates follow docs/conventions.md (pixel centres at integers; x' = (x + 0.5) s - 0.5).
    """
    m = np.asarray(mask, bool)
    if not m.any():
        return []
    step = max(1, -(-max(m.shape) // max_px))
    small = m[::step, ::step].astype(np.uint8)
    contours, _ = cv2.findContours(small, cv2.RETR_LIST, cv2.CHAIN_APPROX_SIMPLE)
    out = []
    for c in contours:
        if len(c) < 4:
            continue
        pts = c[:, 0, :].astype(np.float32) * step + (step - 1) / 2.0
        out.append(np.vstack([pts, pts[:1]]))
    return out


def default_blueprint(cam1: str, cam2: str, *more: str, height_range_m=HEIGHT_RANGE_M, nowcast: bool = False):
    """The raw sky first: every camera's fisheye image with the cloud outline (matches, flow and
    the mask fill are there but hidden, one click away; a camera network's further cameras
    beside them), the 3D cloud base with motion arrows, the height map, the histogram, layer
    heights and cloud fraction over time, the legend."""
    import rerun.blueprint as rrb

    hidden = rrb.EntityBehavior(visible=False)

    def sky(cam: str, extra: tuple[str, ...] = ()):
        return rrb.Spatial2DView(origin=f"/{cam}", name=cam,
                                 overrides={f"/{cam}/{e}": hidden for e in ("matches", "cloud_mask") + extra})

    return rrb.Blueprint(
        rrb.Vertical(
            rrb.Horizontal(
                sky(cam1, ("flow",)),
                sky(cam2),
                *(sky(c) for c in more),
                rrb.Tabs(
                    *([rrb.Spatial2DView(origin="/shadow_map", name="cloud shadow on the ground (north up)")]
                      if nowcast else []),
                    rrb.Spatial3DView(origin="/world", name="cloud base (ENU, m)"),
                    rrb.Spatial2DView(origin="/height_map", name=f"height map ({cam1})"),
                ),
            ),
            rrb.Horizontal(
                rrb.BarChartView(origin="/histogram", name="points per height [m]"),
                rrb.TimeSeriesView(origin="/layers", name="layer base [m above ground]",
                                   axis_y=rrb.ScalarAxis(range=tuple(float(v) for v in height_range_m))),
                *([rrb.TimeSeriesView(origin="/nowcast", name="GHI at the sites [W/m²]: measured, clear sky, "
                                      "nowcast", axis_x=rrb.TimeAxis(view_range=rrb.TimeRange(
                                          start=rrb.TimeRangeBoundary.infinite(),
                                          end=rrb.TimeRangeBoundary.infinite())))] if nowcast else []),
                rrb.Vertical(
                    rrb.TextDocumentView(origin="/flags", name="flags of this pair"),
                    rrb.TimeSeriesView(origin="/cloud_fraction", name="cloud fraction",
                                       axis_y=rrb.ScalarAxis(range=(0.0, 1.0))),
                    rrb.Spatial2DView(origin="/legend", name="height colour scale"),
                    row_shares=[2, 2, 1],
                ),
                column_shares=[2, 3, 3, 2] if nowcast else [2, 3, 2],
            ),
            row_shares=[3, 2],
        ),
        collapse_panels=True,
    )


def log_station(rec, station, cameras: tuple[str, str], height_range_m=HEIGHT_RANGE_M) -> None:
    """Static entities: ENU axes, camera positions and optical axes, mask annotation, series styles."""
    import rerun as rr

    rec.log("/world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
    cams = [station.cameras[c] for c in cameras if c in station.cameras] or list(station.cameras.values())
    pos = np.array([c.position_m for c in cams], np.float64)
    rec.log("/world/cameras", rr.Points3D(pos, radii=-6.0, colors=[(255, 255, 255)] * len(cams)), static=True)
    # one label for the pair: per-camera labels 50 m apart overlap at a 10 km scale ("cam12")
    base = float(np.linalg.norm(pos[-1] - pos[0])) if len(pos) > 1 else 0.0
    rec.log("/world/cameras/label", rr.Points3D(pos.mean(axis=0, keepdims=True), radii=0.0,
                                                labels=[f"{' + '.join(c.name for c in cams)} ({base:.0f} m apart)"]),
            static=True)
    axes = np.array([c.R_world_from_cam[:, 2] for c in cams]) * 500.0  # optical axes, 500 m long
    rec.log("/world/cameras/axes", rr.Arrows3D(vectors=axes, origins=pos, colors=[(255, 255, 0)] * len(cams)),
            static=True)
    for c in cameras:
        rec.log(f"/{c}", rr.AnnotationContext([(0, "sky", (0, 0, 0, 0)), (1, "cloud", (255, 255, 255, 255))]),
                static=True)
    palette = ((235, 235, 235), (140, 180, 255), (255, 170, 90), (150, 230, 150), (230, 140, 230))
    for k, name in enumerate(cameras):
        colour = palette[k % len(palette)]
        rec.log(f"/cloud_fraction/{name}", rr.SeriesLines(names=name, colors=[colour]), static=True)
    rec.log("/legend", rr.Image(legend_image(height_range_m)), static=True)


def log_pair(rec, images: dict[str, tuple[bytes, str]], result: PairResult, *, max_layers_styled: list | None = None,
             height_range_m=HEIGHT_RANGE_M) -> None:
    """Log one pair on the ``capture_time`` time line (the pair's capture time).

    Parameters
    ----------
    rec : rerun.RecordingStream
    images : dict of camera → (encoded bytes, format)
        The images as received ("jpeg" or "png").
    result : PairResult
    """
    import rerun as rr

    rec.set_time(TIMELINE, timestamp=np.datetime64(to_ns(require_time(result, "Rerun view")), "ns"))
    cam1, cam2 = result.cameras[:2]  # (a network: the reference and its first pair's partner)
    for cam, (data, fmt) in images.items():
        media = {"jpeg": "image/jpeg", "jpg": "image/jpeg", "png": "image/png"}.get(fmt.lower())
        if media is None:
            raise RecordingError(f"{cam}: cannot show image format {fmt!r} in Rerun (jpeg or png)")
        rec.log(f"/{cam}/image", rr.EncodedImage(contents=bytes(data), media_type=media, draw_order=0.0))
    for cam, mask in result.cloud_masks.items():
        rec.log(f"/{cam}/cloud_outline", rr.LineStrips2D(cloud_outline(mask), colors=[(255, 255, 255)], radii=-1.0,
                                                         draw_order=1.5))
        rec.log(f"/{cam}/cloud_mask", rr.SegmentationImage(np.asarray(mask, bool).astype(np.uint8), opacity=0.2,
                                                           draw_order=1.0))
    rec.log("/flags", rr.TextDocument(flag_text(result), media_type=rr.MediaType.MARKDOWN))
    valid = not (INVALIDATING & set(result.flags))
    pts = result.points
    h = pts.height_m
    cols = height_colors(h, height_range_m) if valid else _flagged(len(h))
    rec.log("/world/points", rr.Points3D(np.asarray(pts.xyz_m, np.float32), colors=cols, radii=-2.0))
    shown = np.arange(len(h))[:: max(1, -(-len(h) // MAX_SHOWN_MATCHES))]
    rec.log(f"/{cam1}/matches", rr.Points2D(np.asarray(pts.px1, np.float32)[shown], colors=cols[shown], radii=-2.5,
                                            draw_order=2.0))
    rec.log(f"/{cam2}/matches", rr.Points2D(np.asarray(pts.px2, np.float32)[shown], colors=cols[shown], radii=-2.5,
                                            draw_order=2.0))
    if result.matches:
        flow = np.concatenate([np.asarray(a, np.float32).reshape(-1, 4) for a in result.matches.values()])
        flow = flow[:: max(1, -(-len(flow) // MAX_SHOWN_MATCHES))]
        rec.log(f"/{cam1}/flow", rr.LineStrips2D(flow.reshape(-1, 2, 2), colors=[(0, 255, 255)], radii=-0.75,
                                                  draw_order=1.8))
    hm = np.asarray(result.height_map, np.float32)
    if hm.ndim == 2 and hm.size:
        step = max(1, -(-max(hm.shape) // MAX_HEIGHT_MAP_PX))
        hm = hm[::step, ::step]  # a display copy; the recording keeps the full map
        rec.log("/height_map", rr.DepthImage(np.nan_to_num(hm, nan=0.0), meter=1.0, colormap="turbo",
                                             depth_range=tuple(float(v) for v in height_range_m)))
    centres, counts, width = display_histogram(result.histogram.edges_m, result.histogram.counts)
    if counts.size:
        rec.log("/histogram", rr.BarChart(counts, abscissa=centres, widths=[width] * len(counts), color=(90, 90, 90)))
    styled = max_layers_styled if max_layers_styled is not None else []
    arrows, origins, arrow_cols, arrow_labels = [], [], [], []
    for i, layer in enumerate(result.layers):
        if i not in styled:
            rec.log(f"/layers/{i}", rr.SeriesPoints(names=f"layer {i + 1}", marker_sizes=5.0), static=True)
            styled.append(i)
        colour = height_colors(np.array([layer.height_m]), height_range_m)[0] if valid else _flagged(1)[0]
        rec.log(f"/layers/{i}", rr.Scalars(float(layer.height_m)),
                rr.SeriesPoints.from_fields(colors=[colour], markers=["circle" if valid else "cross"]))
        ve, vn = float(layer.motion_east_ms), float(layer.motion_north_ms)
        if np.isfinite(ve) and np.isfinite(vn):
            sel = np.asarray(pts.layer) == i
            centre = np.asarray(pts.xyz_m, np.float64)[sel].mean(axis=0) if sel.any() else np.array([0, 0, layer.height_m])
            origins.append(centre)
            arrows.append([ve * MOTION_ARROW_S, vn * MOTION_ARROW_S, 0.0])
            arrow_cols.append(colour)
            speed, bearing = float(np.hypot(ve, vn)), float(np.degrees(np.arctan2(ve, vn)) % 360.0)
            arrow_labels.append(f"layer {i + 1}: {speed:.1f} m/s towards {bearing:.0f}°"
                                + ("" if valid else " (flagged: not valid)"))
    if arrows:
        rec.log("/world/motion", rr.Arrows3D(vectors=np.array(arrows), origins=np.array(origins), colors=arrow_cols,
                                             labels=arrow_labels, radii=-3.0))
    else:
        rec.log("/world/motion", rr.Clear(recursive=False))
    for cam, frac in result.cloud_fraction.items():
        rec.log(f"/cloud_fraction/{cam}", rr.Scalars(float(frac)))


FLAGGED_RGB = (150, 150, 150)  # a flagged pair's points and layers: grey, its layers as crosses


GHI_COLOURS = {"measured": (235, 235, 235), "clear": (120, 120, 120), "nowcast 5 min ahead": (255, 140, 0),
               "nowcast 10 min ahead": (214, 39, 40)}


def _entity(name: str) -> str:
    return "".join(c if c.isalnum() or c in "-_" else "_" for c in name.strip()) or "_"


def log_ghi_series(rec, series: dict) -> None:
    """Per site, its GHI series ({site: {name: (times datetime64 (T,), W/m² (T,))}}, as
    :func:`cbh.actions.nowcast.ghi_series` gives them) as Scalars under
    ``/nowcast/<site>/<name>`` on the ``capture_time`` line, each at its valid time."""
    import rerun as rr

    for site, named in series.items():
        for name, (times, values) in named.items():
            path = f"/nowcast/{_entity(site)}/{_entity(name)}"
            rec.log(path, rr.SeriesLines(colors=[GHI_COLOURS.get(name, (31, 119, 180))], names=[f"{site}: {name}"]),
                    static=True)
            for t, v in zip(np.asarray(times), np.asarray(values, np.float64)):
                if np.isfinite(v):
                    rec.set_time(TIMELINE, timestamp=np.datetime64(t, "ns"))
                    rec.log(path, rr.Scalars(float(v)))


def log_shadow_map(rec, time_utc, shade: np.ndarray, sites: dict) -> None:
    """The cloud shadow on the ground grid (1 shaded: dark, 0 sunlit: light, NaN unknown: mid
    grey), north up, with each site ({name: (row, column)} of its cell) marked and named."""
    import rerun as rr

    rec.set_time(TIMELINE, timestamp=np.datetime64(to_ns(time_utc), "ns"))
    sh = np.asarray(shade, np.float32)
    img = np.where(np.isfinite(sh), 235.0 - 200.0 * np.clip(sh, 0, 1), 128.0).astype(np.uint8)[::-1]  # rows: north up
    rec.log("/shadow_map/image", rr.Image(img, color_model="L", draw_order=0.0))
    if sites:
        n = sh.shape[0]
        xy = [(c + 0.5, n - 1 - r + 0.5) for r, c in sites.values()]
        rec.log("/shadow_map/sites", rr.Points2D(xy, labels=list(sites), radii=-4.0, colors=[(30, 144, 255)],
                                                 show_labels=True, draw_order=2.0))


def _flagged(n: int) -> np.ndarray:
    return np.tile(np.array(FLAGGED_RGB, np.uint8), (n, 1))


def flag_text(result: PairResult) -> str:
    """The flag panel of a pair (markdown): valid or not and why, each flag with its meaning, the
    cameras' clock offset. An invalid pair's layers are drawn grey, as crosses."""
    bad = sorted(INVALIDATING & set(result.flags))
    head = ("**Valid.**" if not bad else
            f"**Not valid** ({', '.join(bad)}): the layers are drawn grey, as crosses, and are not reported as valid.")
    lines = [head, ""]
    lines += [f"- `{f}`: {flag_meaning(f)}" for f in result.flags] or ["- no flag"]
    d = result.diagnostics
    off = d.get("clock_offset_s")
    if isinstance(off, (int, float)) and math.isfinite(off):
        own = d.get("clock_offset_pair_s")
        lines += ["", f"clock offset {result.cameras[1]} − {result.cameras[0]}: {off:+.1f} s"
                  + (f" (this pair's own estimate {own:+.1f} s)" if isinstance(own, (int, float)) and math.isfinite(own)
                     else "")]
    layers = ", ".join(f"{L.height_m:.0f} m" for L in result.layers)
    lines += ["", f"layers: {layers or 'none'}"]
    return "\n".join(lines)


class RerunSink(ResultSink):
    """Live Rerun view of the service (a :class:`cbh.interfaces.ResultSink`).

    Parameters
    ----------
    station : cbh.geometry.station.Station
    mode : {"spawn", "serve", "connect", "save"}
    target : str, optional
        URL for ``connect`` (default: the local viewer), PATH.rrd for ``save``.
    cameras : tuple of str, optional
        The cameras shown (default: every camera of the station).
    grpc_port : int, optional
        Port of the ``serve`` mode (default: Rerun's, 9876). The URL is in :attr:`url`.
    bind : str, optional
        Address the ``serve`` mode listens on (default ``127.0.0.1``: this machine only; give
        ``0.0.0.0`` to let other machines connect). A port in use is a :class:`ConfigError`.
    """

    kind = "viewer"

    def __init__(self, station, mode: str = "spawn", target: str | None = None, *,
                 cameras: tuple[str, str] | None = None, recording_name: str | None = None,
                 height_range_m=HEIGHT_RANGE_M, grpc_port: int | None = None, bind: str | None = None,
                 nowcast: bool = False):
        import rerun as rr

        self.mode, self.target = parse_rerun_spec(mode, target)
        self.station = station
        from cbh.pipeline.network import station_cameras

        self.cameras = tuple(station_cameras(station, cameras))
        self.height_range_m = tuple(height_range_m)
        self.url: str | None = None
        self._styled: list[int] = []
        self._closed = False
        if self.mode == "connect":  # before any stream exists: nothing listening is one line, at once
            from cbh.outputs.rerun_serve import check_viewer

            self.target = check_viewer(self.target)
        self.rec = rr.RecordingStream("cbh", recording_id=uuid.uuid4())
        if recording_name:
            self.rec.send_recording_name(recording_name)
        bp = default_blueprint(*self.cameras, height_range_m=self.height_range_m, nowcast=nowcast)
        if self.mode == "save":
            out = Path(self.target)
            if not out.parent.is_dir():
                raise RecordingError(f"--rerun save: directory does not exist: {out.parent}")
            self.rec.save(out, default_blueprint=bp)
        elif self.mode == "spawn":
            self.rec.spawn(default_blueprint=bp)
        elif self.mode == "serve":
            from cbh.outputs.rerun_serve import serve_grpc

            self.url = serve_grpc(self.rec, bp, bind or "127.0.0.1", 9876 if grpc_port is None else grpc_port)
            log.info("Rerun server: connect a viewer with `rerun --connect %s`", self.url)
        else:
            self.rec.connect_grpc(self.target, default_blueprint=bp)
        log_station(self.rec, station, self.cameras, self.height_range_m)

    def output_paths(self) -> list[Path]:
        return [Path(self.target)] if self.mode == "save" else []

    def write(self, frames: tuple[Frame, Frame], result: PairResult) -> None:
        """Log one pair (images as received; a frame without bytes is JPEG-encoded once)."""
        from cbh.imageio import encode_jpeg

        images = {}
        for fr in frames:
            images[fr.camera] = (fr.encoded, fr.format) if fr.encoded is not None else (encode_jpeg(fr.image), "jpeg")
        log_pair(self.rec, images, result, max_layers_styled=self._styled, height_range_m=self.height_range_m)

    def write_images(self, images: dict[str, tuple[bytes, str]], result: PairResult) -> None:
        """Log one recorded pair: ``images`` maps camera → (encoded bytes, format)."""
        log_pair(self.rec, images, result, max_layers_styled=self._styled, height_range_m=self.height_range_m)

    def log_ghi(self, series: dict) -> None:
        """Each site's GHI series (:func:`log_ghi_series`)."""
        log_ghi_series(self.rec, series)

    def log_shadow(self, time_utc, shade: np.ndarray, sites: dict) -> None:
        """The pair's cloud shadow on the ground grid with the sites on it (:func:`log_shadow_map`)."""
        log_shadow_map(self.rec, time_utc, shade, sites)

    def log_status(self, time_utc, stats: dict) -> None:
        """Service counters as time series under ``/service/<name>``."""
        import rerun as rr

        self.rec.set_time(TIMELINE, timestamp=np.datetime64(to_ns(time_utc), "ns"))
        for k in ("pairs_processed", "pairs_dropped", "unpaired", "latency_s"):
            v = stats.get(k) if isinstance(stats, dict) else None
            if isinstance(v, (int, float)) and not isinstance(v, bool):
                self.rec.log(f"/service/{k}", rr.Scalars(float(v)))

    write_status = log_status  # the service calls write_status(time_utc, stats) on every sink that has it

    def close(self) -> None:
        """Flush and close the stream (completes the .rrd of ``save``). Idempotent."""
        if self._closed:
            return
        self._closed = True
        try:  # a viewer that went away mid-run must not hold the exit for ever
            self.rec.flush(timeout_sec=FLUSH_TIMEOUT_S if self.mode == "connect" else 1e38)
        except RuntimeError as exc:
            raise RecordingError(f"--rerun connect: the viewer at {self.target} did not take the data: "
                                 f"{' '.join(str(exc).split())}") from None
        finally:
            self.rec.disconnect()

    def __enter__(self) -> "RerunSink":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
