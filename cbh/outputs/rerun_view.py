"""Rerun visualisation: the default blueprint, a live :class:`RerunSink`, and ``log_pair``.

Entities (time line ``capture_time``, UTC):

- ``/<cam>/image`` (EncodedImage, bytes as received), ``/<cam>/cloud_mask`` (SegmentationImage:
  0 sky, 1 cloud, drawn over the image), ``/<cam>/matches`` (Points2D of the triangulated
  correspondences, coloured by height), ``/<cam1>/flow`` (LineStrips2D x1,y1 → x2,y2 of the
  kept matches);
- ``/world/points`` (Points3D, ENU [m], coloured by height), ``/world/cameras`` (positions and
  optical axes, static);
- ``/height_map`` (DepthImage [m above ground] on camera 1's grid, decimated to ≤ 960 px);
- ``/histogram`` (BarChart of point heights), ``/layers/<i>`` (Scalars: layer i's cloud-base
  height [m above ground]), ``/cloud_fraction/<cam>`` (Scalars 0..1).

Modes: ``spawn`` (start a viewer), ``serve`` (gRPC server; viewers connect to the printed URL),
``connect`` (to a running viewer, ``target`` = URL, default the local one), ``save``
(``target`` = PATH.rrd). Every sink uses its own ``rr.RecordingStream``: several coexist.
"""
from __future__ import annotations

import logging
import uuid
from pathlib import Path

import numpy as np

from cbh.errors import ConfigError, RecordingError
from cbh.interfaces import ResultSink
from cbh.result import Frame, PairResult, to_ns

__all__ = ["RerunSink", "default_blueprint", "log_pair", "log_station", "parse_rerun_spec", "height_colors",
           "MODES", "TIMELINE"]

log = logging.getLogger(__name__)

MODES = ("spawn", "serve", "connect", "save")
TIMELINE = "capture_time"
HEIGHT_RANGE_M = (0.0, 10_000.0)  # colour scale of heights [m above ground]
MAX_FLOW_LINES = 2000
MAX_HEIGHT_MAP_PX = 960  # the height map is shown decimated to at most this size [px]


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


def height_colors(height_m: np.ndarray, height_range_m=HEIGHT_RANGE_M) -> np.ndarray:
    """Turbo colours for heights: (N,) [m] → (N, 3) uint8 RGB; NaN → grey."""
    import cv2

    h = np.asarray(height_m, np.float64).ravel()
    lo, hi = height_range_m
    u = np.clip((np.nan_to_num(h, nan=lo) - lo) / max(hi - lo, 1e-9), 0, 1)
    lut = cv2.applyColorMap(np.arange(256, dtype=np.uint8).reshape(-1, 1), cv2.COLORMAP_TURBO)[:, 0, ::-1]
    rgb = lut[np.round(u * 255).astype(int)]
    rgb[~np.isfinite(h)] = (128, 128, 128)
    return rgb.astype(np.uint8)


def default_blueprint(cam1: str, cam2: str):
    """Both fisheye images (cloud masks, matches), the 3D cloud-base points, the height map,
    the height histogram, layer heights and cloud fraction over time."""
    import rerun.blueprint as rrb

    return rrb.Blueprint(
        rrb.Vertical(
            rrb.Horizontal(
                rrb.Spatial2DView(origin=f"/{cam1}", name=f"{cam1}: image, clouds, matches"),
                rrb.Spatial2DView(origin=f"/{cam2}", name=f"{cam2}: image, clouds, matches"),
                rrb.Tabs(
                    rrb.Spatial3DView(origin="/world", name="cloud base (ENU)"),
                    rrb.Spatial2DView(origin="/height_map", name="height map"),
                ),
            ),
            rrb.Horizontal(
                rrb.BarChartView(origin="/histogram", name="height histogram"),
                rrb.TimeSeriesView(origin="/layers", name="layer heights [m above ground]"),
                rrb.TimeSeriesView(origin="/cloud_fraction", name="cloud fraction"),
            ),
            row_shares=[3, 2],
        ),
        collapse_panels=True,
    )


def log_station(rec, station, cameras: tuple[str, str]) -> None:
    """Static entities: ENU axes, camera positions and optical axes, mask annotation, series styles."""
    import rerun as rr

    rec.log("/world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
    cams = [station.cameras[c] for c in cameras if c in station.cameras] or list(station.cameras.values())
    pos = np.array([c.position_m for c in cams], np.float64)
    rec.log("/world/cameras", rr.Points3D(pos, labels=[c.name for c in cams], radii=-6.0,
                                         colors=[(255, 255, 255)] * len(cams)), static=True)
    axes = np.array([c.R_world_from_cam[:, 2] for c in cams]) * 500.0  # optical axes, 500 m long
    rec.log("/world/cameras/axes", rr.Arrows3D(vectors=axes, origins=pos, colors=[(255, 255, 0)] * len(cams)),
            static=True)
    for c in cameras:
        rec.log(f"/{c}", rr.AnnotationContext([(0, "sky", (0, 0, 0, 0)), (1, "cloud", (255, 60, 200, 255))]),
                static=True)
    for name in station.cameras:
        rec.log(f"/cloud_fraction/{name}", rr.SeriesLines(names=f"{name}"), static=True)


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

    rec.set_time(TIMELINE, timestamp=np.datetime64(to_ns(result.time_utc), "ns"))
    cam1, cam2 = result.cameras
    for cam, (data, fmt) in images.items():
        media = {"jpeg": "image/jpeg", "jpg": "image/jpeg", "png": "image/png"}.get(fmt.lower())
        if media is None:
            raise RecordingError(f"{cam}: cannot show image format {fmt!r} in Rerun (jpeg or png)")
        rec.log(f"/{cam}/image", rr.EncodedImage(contents=bytes(data), media_type=media, draw_order=0.0))
    for cam, mask in result.cloud_masks.items():
        rec.log(f"/{cam}/cloud_mask", rr.SegmentationImage(np.asarray(mask, bool).astype(np.uint8), opacity=0.35,
                                                           draw_order=1.0))
    pts = result.points
    h = pts.height_m
    cols = height_colors(h, height_range_m)
    rec.log("/world/points", rr.Points3D(np.asarray(pts.xyz_m, np.float32), colors=cols, radii=-2.0))
    rec.log(f"/{cam1}/matches", rr.Points2D(np.asarray(pts.px1, np.float32), colors=cols, radii=-2.5, draw_order=2.0))
    rec.log(f"/{cam2}/matches", rr.Points2D(np.asarray(pts.px2, np.float32), colors=cols, radii=-2.5, draw_order=2.0))
    if result.matches:
        flow = np.concatenate([np.asarray(a, np.float32).reshape(-1, 4) for a in result.matches.values()])[:MAX_FLOW_LINES]
        rec.log(f"/{cam1}/flow", rr.LineStrips2D(flow.reshape(-1, 2, 2), colors=[(0, 255, 255)], radii=-0.75,
                                                  draw_order=1.5))
    hm = np.asarray(result.height_map, np.float32)
    if hm.ndim == 2 and hm.size:
        step = max(1, -(-max(hm.shape) // MAX_HEIGHT_MAP_PX))
        hm = hm[::step, ::step]  # a display copy; the recording keeps the full map
        rec.log("/height_map", rr.DepthImage(np.nan_to_num(hm, nan=0.0), meter=1.0, colormap="turbo",
                                             depth_range=tuple(float(v) for v in height_range_m)))
    edges = np.asarray(result.histogram.edges_m, np.float64)
    counts = np.asarray(result.histogram.counts, np.float64)
    if counts.size:
        rec.log("/histogram", rr.BarChart(counts, abscissa=0.5 * (edges[:-1] + edges[1:])))
    styled = max_layers_styled if max_layers_styled is not None else []
    for i, layer in enumerate(result.layers):
        if i not in styled:
            rec.log(f"/layers/{i}", rr.SeriesPoints(names=f"layer {i + 1}", marker_sizes=4.0), static=True)
            styled.append(i)
        rec.log(f"/layers/{i}", rr.Scalars(float(layer.height_m)))
    for cam, frac in result.cloud_fraction.items():
        rec.log(f"/cloud_fraction/{cam}", rr.Scalars(float(frac)))


class RerunSink(ResultSink):
    """Live Rerun view of the service (a :class:`cbh.interfaces.ResultSink`).

    Parameters
    ----------
    station : cbh.geometry.station.Station
    mode : {"spawn", "serve", "connect", "save"}
    target : str, optional
        URL for ``connect`` (default: the local viewer), PATH.rrd for ``save``.
    cameras : (str, str), optional
        The pair shown (default: the station's first two cameras).
    grpc_port : int, optional
        Port of the ``serve`` mode (default: Rerun's, 9876). The URL is in :attr:`url`.
    bind : str, optional
        Address the ``serve`` mode listens on (default ``127.0.0.1``: this machine only; give
        ``0.0.0.0`` to let other machines connect). A port in use is a :class:`ConfigError`.
    """

    kind = "viewer"

    def output_paths(self) -> list[Path]:
        return [Path(self.target)] if self.mode == "save" else []


    def __init__(self, station, mode: str = "spawn", target: str | None = None, *,
                 cameras: tuple[str, str] | None = None, recording_name: str | None = None,
                 height_range_m=HEIGHT_RANGE_M, grpc_port: int | None = None, bind: str | None = None):
        import rerun as rr

        self.mode, self.target = parse_rerun_spec(mode, target)
        self.station = station
        c1, c2 = station.pair(cameras)
        self.cameras = (c1.name, c2.name)
        self.height_range_m = tuple(height_range_m)
        self.url: str | None = None
        self._styled: list[int] = []
        self._closed = False
        self.rec = rr.RecordingStream("cbh", recording_id=uuid.uuid4())
        if recording_name:
            self.rec.send_recording_name(recording_name)
        bp = default_blueprint(*self.cameras)
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
        log_station(self.rec, station, self.cameras)

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
        self.rec.flush()
        self.rec.disconnect()

    def __enter__(self) -> "RerunSink":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
