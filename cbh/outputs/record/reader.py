"""Reading cbh recordings back: metadata, time span, topics, and pairs as PairResult objects."""
from __future__ import annotations

import json
import tomllib
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path
from typing import Iterator

import cv2
import numpy as np

from cbh.errors import CbhError, RecordingError
from cbh.result import Enlarged, Frame, Histogram, Layer, PairResult, PointSet, from_ns
from cbh.outputs.record.schemas import cbh_types, foxglove_types
from cbh.outputs.record.writer import METADATA_NAME, POINT_DTYPE

__all__ = ["open_session", "Session", "RecordedPair", "RecordedImage", "TopicInfo", "check_mcap_file"]

MAGIC = bytes([137, 77, 67, 65, 80, 48, 13, 10])
PAIR_TOPIC = "/pair/layers"
STATUS_TOPIC = "/service/status"


def check_mcap_file(path: Path) -> None:
    """:class:`RecordingError` unless ``path`` is a complete MCAP file (magic at both ends)."""
    if not path.exists():
        raise RecordingError(f"recording not found: {path}")
    if path.is_dir():
        raise RecordingError(f"not a recording file (a directory): {path}")
    try:
        with open(path, "rb") as fh:
            head = fh.read(8)
            size = fh.seek(0, 2)
            tail = b""
            if size >= 16:
                fh.seek(size - 8)
                tail = fh.read(8)
    except OSError as exc:
        raise RecordingError(f"cannot read recording {path}: {exc.strerror}") from None
    if head != MAGIC:
        raise RecordingError(f"{path}: not an MCAP file (bad magic bytes)")
    if tail != MAGIC:
        raise RecordingError(
            f"{path}: truncated MCAP file (was its writer killed?); recover it with "
            f"`cbh inspect {path} --repair OUT.mcap`")


@dataclass(frozen=True)
class RecordedImage:
    """One camera image as recorded (the bytes as received)."""

    camera: str
    time_utc: datetime
    data: bytes
    format: str

    def decode(self) -> np.ndarray:
        """BGR uint8 (H, W, 3)."""
        from cbh.imageio import decode_image

        return decode_image(self.data, what=f"recorded {self.camera} image at {self.time_utc.isoformat()}")

    def frame(self, sequence: int = 0) -> Frame:
        return Frame(self.camera, self.time_utc, self.decode(), encoded=self.data, format=self.format, sequence=sequence)


@dataclass
class RecordedPair:
    """One recorded pair: its index in the session, images and the decoded result."""

    index: int
    time_utc: datetime
    images: dict[str, RecordedImage]
    result: PairResult
    altitude_m: list[float] = field(default_factory=list)  # per layer, as recorded [m above sea level]

    def frames(self) -> tuple[Frame, ...]:
        """The frames (camera 1, camera 2, and a network's further cameras) with decoded images."""
        try:
            return tuple(self.images[c].frame(self.index) for c in self.result.cameras)
        except KeyError as exc:
            raise RecordingError(f"pair {self.index}: no recorded image for camera {exc.args[0]!r}") from None


@dataclass(frozen=True)
class TopicInfo:
    topic: str
    schema: str
    encoding: str
    count: int


def _decode_masks(data: bytes, what: str) -> np.ndarray:
    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_GRAYSCALE)
    if img is None:
        raise RecordingError(f"{what}: corrupt PNG")
    return img > 127


def _points(pc, what: str) -> PointSet:
    names = [(f.name, f.offset) for f in pc.fields]
    expected = [(n, POINT_DTYPE.fields[n][1]) for n in POINT_DTYPE.names]
    if names != expected or pc.point_stride != POINT_DTYPE.itemsize:
        raise RecordingError(f"{what}: point cloud layout {names} is not cbh's")
    if len(pc.data) % POINT_DTYPE.itemsize:
        raise RecordingError(f"{what}: point data length {len(pc.data)} is not a multiple of {POINT_DTYPE.itemsize}")
    rec = np.frombuffer(pc.data, POINT_DTYPE)
    xyz = np.stack([rec["x"], rec["y"], rec["z"]], axis=1).astype(np.float32)
    return PointSet(
        xyz_m=xyz, miss_m=rec["miss"].astype(np.float32),
        px1=np.stack([rec["x1"], rec["y1"]], axis=1).astype(np.float32),
        px2=np.stack([rec["x2"], rec["y2"]], axis=1).astype(np.float32),
        layer=rec["layer"].astype(np.int16),
    )


def _height_map(ri, what: str) -> np.ndarray:
    if ri.encoding != "32FC1":
        raise RecordingError(f"{what}: height map encoding {ri.encoding!r}, expected 32FC1")
    w, h, step = ri.width, ri.height, ri.step
    if step < 4 * w or len(ri.data) < step * h:
        raise RecordingError(f"{what}: height map data too short for {w}x{h}")
    rows = np.frombuffer(ri.data, np.uint8)[: step * h].reshape(h, step)[:, : 4 * w]
    return np.ascontiguousarray(rows).view("<f4").reshape(h, w).astype(np.float32)


def _ts_ns(ts) -> int:
    return int(ts.seconds) * 1_000_000_000 + int(ts.nanos)


def build_pair(index: int, msgs: dict[str, object], what: str) -> RecordedPair:
    """Decode one pair's protobuf messages (topic → message) into a :class:`RecordedPair`."""
    pl = msgs[PAIR_TOPIC]
    t = from_ns(_ts_ns(pl.timestamp))
    cams = (pl.camera1, pl.camera2)  # a network's further cameras: in its cloud fractions, in order
    cams += tuple(c.camera for c in pl.cloud_fraction if c.camera not in cams)
    images, masks = {}, {}
    for topic, m in msgs.items():
        parts = topic.strip("/").split("/")
        if len(parts) == 3 and parts[1:] == ["image", "compressed"]:
            images[parts[0]] = RecordedImage(parts[0], from_ns(_ts_ns(m.timestamp)), bytes(m.data), m.format)
        elif len(parts) == 2 and parts[1] == "cloud_mask":
            masks[parts[0]] = _decode_masks(m.data, f"{what} {topic}")
    nan = float("nan")
    has_quality = "motion_tracks" in Layer.__dataclass_fields__  # Layer carries the motion's quality
    layers = [Layer(l.height_m, l.median_height_m, l.spread_m, l.cover, int(l.points), l.confidence,
                    altitude_m=l.altitude_m,
                    motion_east_ms=l.motion_east_ms if l.HasField("motion_east_ms") else nan,
                    motion_north_ms=l.motion_north_ms if l.HasField("motion_north_ms") else nan,
                    height_lo_m=l.height_lo_m if l.HasField("height_lo_m") else nan,
                    height_hi_m=l.height_hi_m if l.HasField("height_hi_m") else nan,
                    **({"motion_spread_ms": l.motion_spread_ms if l.HasField("motion_spread_ms") else nan,
                        "motion_tracks": int(l.motion_tracks)} if has_quality else {}))
              for l in pl.layers]
    hist_msg = msgs.get("/pair/histogram")
    hist = (Histogram(np.asarray(hist_msg.edges_m, np.float64), np.asarray(hist_msg.counts, np.float64))
            if hist_msg is not None else Histogram(np.zeros(1), np.zeros(0)))
    pts = _points(msgs["/pair/points"], what) if "/pair/points" in msgs else PointSet.empty()
    hm = _height_map(msgs["/pair/height_map"], what) if "/pair/height_map" in msgs else np.zeros((0, 0), np.float32)
    if pl.height_map_scale > 1 and hm.size:  # recorded decimated (lossless, see the writer): camera 1's grid when read
        f = int(pl.height_map_scale)
        hm = Enlarged(hm, hm.shape[1] * f, hm.shape[0] * f)
    matches = {}
    if "/pair/matches" in msgs:
        for s in msgs["/pair/matches"].sets:
            matches[s.method] = np.stack([np.asarray(s.x1), np.asarray(s.y1), np.asarray(s.x2), np.asarray(s.y2)],
                                         axis=1).reshape(-1, 4)
    result = PairResult(
        time_utc=t, cameras=cams, layers=layers, histogram=hist, points=pts, height_map=hm,
        cloud_masks=masks, cloud_fraction={c.camera: c.fraction for c in pl.cloud_fraction},
        timing_ms={x.stage: x.ms for x in pl.timing}, flags=list(pl.flags), matches=matches,
        diagnostics=_diagnostics(pl.diagnostics),
    )
    return RecordedPair(index=index, time_utc=t, images=images, result=result,
                        altitude_m=[l.altitude_m for l in pl.layers])


_DECODERS = {
    "foxglove.CompressedImage": lambda: foxglove_types()["CompressedImage"],
    "foxglove.RawImage": lambda: foxglove_types()["RawImage"],
    "foxglove.PointCloud": lambda: foxglove_types()["PointCloud"],
    "cbh.PairLayers": lambda: cbh_types()["PairLayers"],
    "cbh.Histogram": lambda: cbh_types()["Histogram"],
    "cbh.Matches": lambda: cbh_types()["Matches"],
    "cbh.ServiceStatus": lambda: cbh_types()["ServiceStatus"],
}


class Session:
    """A recorded session: one MCAP file or several rotated ones (in time order).

    Attributes
    ----------
    paths : list of Path
    metadata : dict of str → str
        The first file's ``cbh`` metadata record (station_toml, config_json, cbh_version, …).
    """

    def __init__(self, paths: list[Path]):
        from mcap.reader import make_reader

        self.paths = paths
        self.metadata: dict[str, str] = {}
        self._topics: dict[str, list] = {}
        starts, ends = [], []
        for p in paths:
            check_mcap_file(p)
            try:
                with open(p, "rb") as fh:
                    reader = make_reader(fh)
                    meta = [m for m in reader.iter_metadata() if m.name == METADATA_NAME]
                    summary = reader.get_summary()
            except CbhError:
                raise
            except Exception as exc:  # mcap raises many kinds (struct.error, McapError, …)
                raise RecordingError(f"{p}: unreadable MCAP ({type(exc).__name__}: {exc})") from None
            if not meta:
                raise RecordingError(f"{p}: an MCAP file but not a cbh recording (no '{METADATA_NAME}' metadata record)")
            md = dict(meta[0].metadata)
            if not self.metadata:
                self.metadata = md
            elif md.get("station_name") != self.metadata.get("station_name"):
                raise RecordingError(
                    f"{p}: station {md.get('station_name')!r} differs from {self.metadata.get('station_name')!r} of {paths[0]}")
            if summary is None or summary.statistics is None:
                raise RecordingError(f"{p}: MCAP file without a summary section; rewrite it with `cbh inspect {p} --repair OUT.mcap`")
            st = summary.statistics
            if st.message_count:
                starts.append(st.message_start_time)
                ends.append(st.message_end_time)
            for cid, ch in summary.channels.items():
                sc = summary.schemas.get(ch.schema_id)
                info = self._topics.setdefault(ch.topic, [sc.name if sc else "", ch.message_encoding, 0])
                info[2] += st.channel_message_counts.get(cid, 0)
        if "station_toml" not in self.metadata:
            raise RecordingError(f"{paths[0]}: cbh metadata record lacks the station (not a cbh recording?)")
        self.start_ns = min(starts) if starts else None
        self.end_ns = max(ends) if ends else None
        self._station = None
        self._tmp = None  # repaired copies of truncated files (open_session)

    # --- metadata ---------------------------------------------------------------------
    @property
    def station_toml(self) -> str:
        return self.metadata["station_toml"]

    @property
    def station(self):
        """The recorded station (:class:`cbh.geometry.station.Station`); masks whose file is gone are dropped."""
        if self._station is None:
            from cbh.geometry.station import parse_station

            try:
                data = tomllib.loads(self.station_toml)
            except tomllib.TOMLDecodeError as exc:
                raise RecordingError(f"{self.paths[0]}: recorded station TOML is malformed: {exc}") from None
            for cam in data.get("cameras", []):
                if isinstance(cam, dict) and "mask" in cam and not Path(str(cam["mask"])).is_file():
                    cam.pop("mask")
            self._station = parse_station(data, check_masks=False)
        return self._station

    @property
    def config(self) -> dict:
        try:
            return json.loads(self.metadata.get("config_json", "{}"))
        except json.JSONDecodeError as exc:
            raise RecordingError(f"{self.paths[0]}: recorded pipeline config is not JSON: {exc}") from None

    @property
    def version(self) -> str:
        return self.metadata.get("cbh_version", "unknown")

    @property
    def station_name(self) -> str:
        return self.metadata.get("station_name", "")

    @property
    def time_span(self) -> tuple[datetime, datetime] | None:
        """(first, last) message log time (capture time), or None for an empty session."""
        if self.start_ns is None:
            return None
        return from_ns(self.start_ns), from_ns(self.end_ns)

    @property
    def topics(self) -> list[TopicInfo]:
        return [TopicInfo(t, s, e, c) for t, (s, e, c) in sorted(self._topics.items())]

    def count(self, topic: str) -> int:
        return self._topics.get(topic, ["", "", 0])[2]

    @property
    def pair_count(self) -> int:
        return self.count(PAIR_TOPIC)

    # --- messages ---------------------------------------------------------------------
    def _messages(self, topics: set[str] | None = None) -> Iterator[tuple[str, int, int, object]]:
        """(topic, log_time_ns, sequence, decoded protobuf) in file order."""
        from mcap.reader import make_reader

        for p in self.paths:
            try:
                with open(p, "rb") as fh:
                    reader = make_reader(fh)
                    for schema, channel, message in reader.iter_messages(topics=topics, log_time_order=False):
                        if schema is None or schema.name not in _DECODERS:
                            continue
                        msg = _DECODERS[schema.name]().FromString(message.data)
                        yield channel.topic, message.log_time, message.sequence, msg
            except CbhError:
                raise
            except Exception as exc:
                raise RecordingError(f"{p}: corrupt recording ({type(exc).__name__}: {exc})") from None

    def pairs(self, layers_only: bool = False) -> Iterator[RecordedPair]:
        """Every complete pair (one whose ``/pair/layers`` message was written), in file order.

        ``layers_only`` reads only ``/pair/layers`` (fast): the results then have no images,
        masks, points, height map or histogram.
        """
        pending: dict[int, dict[str, object]] = {}
        for topic, _t, seq, msg in self._messages({PAIR_TOPIC} if layers_only else None):
            if topic == STATUS_TOPIC:
                continue
            pending.setdefault(seq, {})[topic] = msg
            if topic == PAIR_TOPIC:
                msgs = pending.pop(seq)
                yield build_pair(seq, msgs, f"{self.paths[0].name} pair {seq}")

    def images(self, cameras, start_ns: int | None = None, end_ns: int | None = None
               ) -> Iterator[tuple[int, RecordedImage]]:
        """(pair index, image) of the recorded images of ``cameras``, in file order; with
        ``start_ns``/``end_ns`` only those whose capture time (log time) lies in
        [``start_ns``, ``end_ns``), read through the file's index (fast for a time slice).

        Parameters
        ----------
        cameras : str or iterable of str
            Camera name(s) (topics ``/<camera>/image/compressed``; only these are read).
        start_ns, end_ns : int or None
            Capture-time bounds [ns since the Unix epoch]; None = open.
        """
        from mcap.reader import make_reader

        topics = [f"/{c}/image/compressed" for c in ([cameras] if isinstance(cameras, str) else cameras)]
        T = foxglove_types()["CompressedImage"]
        for p in self.paths:
            try:
                with open(p, "rb") as fh:
                    reader = make_reader(fh)
                    for _schema, channel, message in reader.iter_messages(
                            topics=topics, start_time=start_ns, end_time=end_ns, log_time_order=False):
                        m = T.FromString(message.data)
                        cam = channel.topic.strip("/").split("/")[0]
                        yield message.sequence, RecordedImage(cam, from_ns(_ts_ns(m.timestamp)), bytes(m.data), m.format)
            except CbhError:
                raise
            except Exception as exc:
                raise RecordingError(f"{p}: corrupt recording ({type(exc).__name__}: {exc})") from None

    def statuses(self) -> Iterator[tuple[datetime, dict]]:
        """(time, stats dict) of every ``/service/status`` message."""
        for _topic, t, _seq, msg in self._messages({STATUS_TOPIC}):
            try:
                stats = json.loads(msg.json) if msg.json else {}
            except json.JSONDecodeError:
                stats = {c.name: c.value for c in msg.counters}
            yield from_ns(t), stats

def open_session(path) -> Session:
    """Open a recording: a ``.mcap`` file, a directory of rotated files, or a list of files.

    Raises :class:`RecordingError` (one line) for a missing, foreign, truncated or corrupt file
    given on its own. In a directory (or a list of several files) a damaged file does not stop
    the rest: a truncated one (its writer was killed) is read through a repaired temporary copy
    (:func:`cbh.outputs.record.recover`; every complete pair is kept), an empty or foreign one
    is skipped; each with one warning.
    """
    if isinstance(path, (list, tuple)):
        paths = [Path(p) for p in path]
        several = len(paths) > 1
    else:
        p = Path(path)
        if p.is_dir():
            paths = sorted(p.glob("*.mcap"))
            if not paths:
                raise RecordingError(f"no .mcap files in directory {p}")
            several = True
        else:
            paths, several = [p], False
    if not paths:
        raise RecordingError("no recording given")
    tmp = None
    if several:
        paths, tmp = _usable(paths)
    s = Session(paths)
    if len(paths) > 1:  # rotated files: order by their first message
        order = sorted(paths, key=lambda q: (Session([q]).start_ns or 0))
        if order != paths:
            s = Session(order)
    if tmp is not None:  # the repaired copies live as long as the session
        import shutil
        import weakref

        weakref.finalize(s, shutil.rmtree, tmp, True)
    return s


def _mcap_state(path: Path) -> str:
    """``complete`` (magic at both ends), ``truncated`` (magic at the start only) or ``foreign``."""
    try:
        with open(path, "rb") as fh:
            if fh.read(8) != MAGIC:
                return "foreign"
            size = fh.seek(0, 2)
            if size < 16:
                return "truncated"
            fh.seek(size - 8)
            return "complete" if fh.read(8) == MAGIC else "truncated"
    except OSError:
        return "foreign"


def _usable(paths: list[Path]):
    """(paths to read, temporary directory or None): truncated files replaced by repaired
    copies, unreadable ones left out (warned)."""
    import logging
    import tempfile

    from cbh.outputs.record.recover import recover

    log = logging.getLogger(__name__)
    out, tmp = [], None
    for p in paths:
        state = _mcap_state(p)
        if state == "complete":
            out.append(p)
            continue
        if state == "foreign":
            log.warning(f"{p}: skipped (empty, unreadable or not an MCAP file)")
            continue
        if tmp is None:
            tmp = tempfile.mkdtemp(prefix="cbh-recover-")
        fixed = Path(tmp) / f"{len(out):04d}-{p.name}"
        try:
            rep = recover(p, fixed, overwrite=True)
            Session([fixed])  # readable as a cbh recording?
        except RecordingError as exc:
            log.warning(f"{p}: truncated and not recoverable, skipped ({exc})")
            continue
        log.warning(f"{p}: truncated (its writer was killed?); read its {rep.pairs} complete pairs "
                    f"(repair it for good with `cbh inspect {p} --repair OUT.mcap`)")
        out.append(fixed)
    if not out:
        if tmp is not None:
            import shutil

            shutil.rmtree(tmp, ignore_errors=True)
        raise RecordingError(f"no readable recording among {len(paths)} files ({paths[0].parent})")
    return out, tmp


def _diagnostics(recorded) -> dict:
    """The recorded scalars, and a network's ``mismatched_cameras`` list rebuilt from its
    ``geometry_mismatch_<camera>`` scalars (:mod:`cbh.pipeline.network`)."""
    d = {x.name: x.value for x in recorded}
    if any(k.startswith("geometry_mismatch_") for k in d):
        d["mismatched_cameras"] = [k[len("geometry_mismatch_"):] for k, v in d.items()
                                   if k.startswith("geometry_mismatch_") and v == 1.0]
    return d
