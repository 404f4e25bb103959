"""Archives as work: image folders, ``cbh run --record`` recordings and video files → frame
pairs of one station, partitioned by UTC day (for ``cbh reprocess``).

The work list holds references (:class:`FrameRef`), not images: whoever processes a pair
(a Ray actor, possibly on another machine that sees the same file system) loads the images
itself with :func:`load_images`.

Inputs, per camera (``--source CAM=SPEC`` or the station's ``source`` key):

===================  ==================================================================================
image folder         every ``.jpg/.jpeg/.png`` below the folder, recursively: flat
                     (``cam1/cam1_20240621T140000Z.jpg``), one folder per day
                     (``cam1/2024-06-21/…``) or both cameras in one tree (files named
                     ``<camera>_…``: as soon as one file of the tree is, only those are taken, the
                     rule of ``cbh run``'s directory source). Time: the UTC stamp in the file name
                     (:func:`cbh.timeutil.time_from_name`); a name with only a time of day takes
                     the date from its folder (``2024-06-21/14-00-00.jpg``). A file without a stamp
                     is skipped and counted: an archive's modification times are not capture times.
recording            a ``.mcap`` file of ``cbh run --record`` or a folder of them: its recorded pairs
                     (both cameras' images as received), so give it for either camera (or both).
                     A truncated recording (writer killed) is repaired into a copy
                     (:func:`cbh.outputs.record.recover`) and its complete pairs are used.
video file           frames at ``start + position`` (start: the UTC stamp in the file name, else
                     modification time minus duration: the rule of :class:`cbh.live.sources.VideoSource`).
===================  ==================================================================================

Frames of the two cameras are paired by nearest time within the pairing tolerance by
:class:`cbh.live.pairing.Pairer` (the rule of the live service); unpaired frames are counted.
"""
from __future__ import annotations

import logging
from collections import defaultdict
from dataclasses import dataclass, field
from datetime import date, datetime, timedelta
from pathlib import Path

import cv2
import numpy as np

from cbh.errors import CbhError, ConfigError, ImageError, RecordingError
from cbh.live.pairing import Pairer
from cbh.live.sources import IMAGE_SUFFIXES, VIDEO_SUFFIXES, camera_prefixed, is_sim_spec, quiet_video_logs
from cbh.result import Frame, to_ns
from cbh.timeutil import time_from_name

__all__ = ["FrameRef", "PairRef", "Inventory", "scan_station", "pair_frames", "by_day", "load_images",
           "source_kind"]

log = logging.getLogger(__name__)

_RECORDING_MARGIN_S = 120.0  # camera images of a recorded pair lie within the pairing tolerance of it


@dataclass(frozen=True, slots=True)
class FrameRef:
    """Where one camera frame is: an image file, a video frame or a recorded image.

    Attributes
    ----------
    camera : str
    time_utc : datetime
        Capture time (UTC).
    kind : {"image", "video", "recording"}
    path : str
        Image file, video file or ``.mcap`` file (absolute).
    index : int
        Video: frame number from 0; recording: the pair's sequence number; image: -1.
    """

    camera: str
    time_utc: datetime
    kind: str
    path: str
    index: int = -1

    def describe(self) -> str:
        return self.path if self.kind == "image" else f"{self.path}#{self.index}"


@dataclass(frozen=True, slots=True)
class PairRef:
    """A frame pair to process; ``time_utc`` is camera 1's capture time (the pair's time).

    A camera network's frame set: ``more`` holds cameras 3…N, and any frame but the first
    present may be None (a camera without a frame within the tolerance)."""

    time_utc: datetime
    frame1: FrameRef | None
    frame2: FrameRef | None
    more: tuple = ()

    @property
    def frames(self) -> tuple:
        """Every camera's frame, in the station's camera order (None: missing)."""
        return (self.frame1, self.frame2, *self.more)

    @property
    def present(self) -> list:
        return [f for f in self.frames if f is not None]


@dataclass
class Inventory:
    """What the inputs of one station hold."""

    pairs: list[PairRef] = field(default_factory=list)  # time order
    frames: dict[str, int] = field(default_factory=dict)  # camera → frames found
    unpaired: dict[str, int] = field(default_factory=dict)  # camera → frames without a partner
    skipped: list[dict] = field(default_factory=list)  # {"path", "reason"}: inputs not usable
    repaired: list[dict] = field(default_factory=list)  # {"path", "copy", "pairs"}: truncated recordings


def source_kind(spec: str) -> str:
    """``image folder`` | ``recording`` | ``video``, from a path; :class:`ConfigError` otherwise."""
    p = Path(spec)
    low = spec.lower()
    if "://" in low or is_sim_spec(spec):
        raise ConfigError(f"source {spec!r}: reprocess reads archives (image folders, recordings, video "
                          "files), not live streams or the simulator")
    if p.is_file():
        if p.suffix.lower() == ".mcap":
            return "recording"
        if p.suffix.lower() in VIDEO_SUFFIXES:
            return "video"
        raise ConfigError(f"source {spec!r}: a file that is neither a recording (.mcap) nor a video "
                          f"({', '.join(VIDEO_SUFFIXES)}); give an image folder instead of one image")
    if p.is_dir():
        has_images = any(q.suffix.lower() in IMAGE_SUFFIXES for q in p.rglob("*"))
        if not has_images and any(p.glob("*.mcap")):
            return "recording"
        return "image folder"
    raise ConfigError(f"source {spec!r}: no such file or directory")


# --- scanning ---------------------------------------------------------------------------------

def _image_time(path: Path):
    t = time_from_name(path.name)
    if t is None:
        t = time_from_name(f"{path.parent.name}T{path.name}")  # date in the folder, time in the name
    return t


def scan_images(camera: str, root: Path) -> tuple[list[FrameRef], list[dict]]:
    """Frames of ``camera`` in an image folder tree (time order) and the files skipped."""
    files = sorted(q for q in root.rglob("*") if q.suffix.lower() in IMAGE_SUFFIXES and q.is_file())
    if any(camera_prefixed(q.name, camera) for q in files):
        files = [q for q in files if camera_prefixed(q.name, camera)]
    refs, skipped = [], []
    for q in files:
        t = _image_time(q)
        if t is None:
            skipped.append({"path": str(q), "reason": "no UTC time stamp in the file or folder name"})
            continue
        refs.append(FrameRef(camera, t, "image", str(q.resolve())))
    refs.sort(key=lambda r: (r.time_utc, r.path))
    return refs, skipped


def scan_video(camera: str, path: Path) -> list[FrameRef]:
    """Frames of a video file with their capture times (:class:`cbh.errors.SourceError` if unreadable)."""
    from cbh.live.sources import VideoSource

    src = VideoSource(camera, str(path))
    src.open()  # start time: the live rule (name stamp, else mtime − duration)
    start = src.start_utc
    src.close()
    cap = cv2.VideoCapture(str(path), cv2.CAP_FFMPEG)
    refs = []
    try:
        i = 0
        while cap.grab():  # demux and decode, no colour conversion: the frame's position is all we need
            t = start + timedelta(milliseconds=float(cap.get(cv2.CAP_PROP_POS_MSEC)))
            refs.append(FrameRef(camera, t, "video", str(path.resolve()), i))
            i += 1
    finally:
        cap.release()
    return refs


def _open_recording(path: Path, workdir: Path, inv: Inventory):
    """Open a recording; a truncated one is repaired into ``workdir`` (counted in ``inv``)."""
    from cbh.outputs.record import open_session

    try:
        return open_session(path), path
    except RecordingError as exc:
        if "truncated" not in str(exc) and "summary" not in str(exc):
            inv.skipped.append({"path": str(path), "reason": str(exc)})
            log.warning("recording skipped: %s", exc, extra={"cbh_file": str(path)})
            return None, path
    from cbh.outputs.record.recover import recover

    workdir.mkdir(parents=True, exist_ok=True)
    import hashlib

    tag = hashlib.sha1(str(path.resolve()).encode()).hexdigest()[:8]
    copy = workdir / f"{path.stem}-{tag}-repaired.mcap"
    try:
        rep = recover(path, copy, overwrite=True)  # our own work file (a rerun finds it)
        sess = open_session(copy)
    except RecordingError as exc:
        inv.skipped.append({"path": str(path), "reason": f"truncated and not repairable: {exc}"})
        log.warning("recording skipped: truncated and not repairable: %s", exc, extra={"cbh_file": str(path)})
        return None, path
    inv.repaired.append({"path": str(path), "copy": str(copy), "pairs": rep.pairs})
    log.warning("truncated recording %s: %d complete pairs recovered into %s", path, rep.pairs, copy,
                extra={"cbh_file": str(path)})
    return sess, copy


def scan_recordings(cameras: tuple[str, ...], spec: Path, workdir: Path, inv: Inventory) -> list[PairRef]:
    """Recorded pairs of ``cameras`` in a ``.mcap`` file or a folder of them."""
    files = [spec] if spec.is_file() else sorted(spec.glob("*.mcap"))
    pairs = []
    for f in files:
        sess, used = _open_recording(f, workdir, inv)
        if sess is None:
            continue
        try:
            recs = list(sess.pairs(layers_only=True))
        except RecordingError as exc:
            inv.skipped.append({"path": str(f), "reason": str(exc)})
            log.warning("recording skipped: %s", exc, extra={"cbh_file": str(f)})
            continue
        for rp in recs:
            if set(cameras) - set(rp.result.cameras):
                inv.skipped.append({"path": f"{f}#{rp.index}",
                                    "reason": f"recorded pair of {','.join(rp.result.cameras)}, not {','.join(cameras)}"})
                continue
            p = str(Path(used).resolve())
            refs = [FrameRef(c, rp.time_utc, "recording", p, rp.index) for c in cameras]
            pairs.append(PairRef(rp.time_utc, refs[0], refs[1], tuple(refs[2:])))
        for c in cameras:
            inv.frames[c] = inv.frames.get(c, 0) + len(recs)
    return pairs


def pair_frames(frames1: list[FrameRef], frames2: list[FrameRef], tolerance_s: float) -> tuple[list[PairRef], dict]:
    """Pair two cameras' frames by nearest time within ``tolerance_s`` (the live service's
    :class:`~cbh.live.pairing.Pairer`, fed in time order). Returns (pairs, unpaired per camera)."""
    if not frames1 or not frames2:
        c1 = frames1[0].camera if frames1 else "camera 1"
        c2 = frames2[0].camera if frames2 else "camera 2"
        return [], {c1: len(frames1), c2: len(frames2)}
    cams = (frames1[0].camera, frames2[0].camera)
    pairer = Pairer(cams, tolerance_s=tolerance_s, max_waiting=max(16, len(frames1) + len(frames2) + 2))
    lists = {cams[0]: frames1, cams[1]: frames2}
    merged = sorted([(f.time_utc, k, i) for k, c in enumerate(cams) for i, f in enumerate(lists[c])])
    pairs = []

    def take(ready):
        for a, b in ready:
            r1, r2 = frames1[a.sequence], frames2[b.sequence]
            pairs.append(PairRef(r1.time_utc, r1, r2))

    for t, k, i in merged:
        pairer.push(Frame(cams[k], t, None, sequence=i))
        take(pairer.pop_pairs())
    take(pairer.flush())
    return pairs, dict(pairer.stats.unpaired)


def group_frames(lists: dict[str, list[FrameRef]], tolerance_s: float) -> tuple[list[PairRef], dict]:
    """A camera network's frame sets: every camera's frames grouped by nearest time within
    ``tolerance_s`` (the live service's :class:`~cbh.live.pairing.Grouper`, fed in time order;
    a camera without a frame in a set is None there). Returns (sets, unpaired per camera)."""
    from cbh.live.pairing import Grouper

    cams = tuple(lists)
    g = Grouper(cams, tolerance_s=tolerance_s, max_waiting=max(16, sum(len(v) for v in lists.values()) + 2))
    merged = sorted([(f.time_utc, k, i) for k, c in enumerate(cams) for i, f in enumerate(lists[c])])
    sets = []

    def take(ready):
        for group in ready:
            refs = [None if f is None else lists[f.camera][f.sequence] for f in group]
            t = next(r.time_utc for r in refs if r is not None)
            sets.append(PairRef(t, refs[0], refs[1], tuple(refs[2:])))

    for t, k, i in merged:
        g.push(Frame(cams[k], t, None, sequence=i))
        take(g.pop_pairs())
    take(g.flush())
    return sets, dict(g.stats.unpaired)


def scan_station(cameras: tuple[str, ...], specs: dict[str, str], tolerance_s: float, workdir: Path,
                 t_from: datetime | None = None, t_to: datetime | None = None) -> Inventory:
    """The pairs of one station's inputs within [``t_from``, ``t_to``).

    Parameters
    ----------
    cameras : (str, str)
        Camera 1 and camera 2.
    specs : dict of str → str
        Camera → input path (absolute). For a recording one camera's entry is enough.
    tolerance_s : float
        Pairing tolerance [s].
    workdir : Path
        Where repaired copies of truncated recordings go.
    """
    inv = Inventory()
    kinds = {c: source_kind(s) for c, s in specs.items()}
    rec = [c for c in cameras if kinds.get(c) == "recording"]
    if rec:
        paths = {Path(specs[c]).resolve() for c in rec}
        others = [c for c in cameras if c in specs and kinds[c] != "recording"]
        if len(paths) > 1 or others:
            raise ConfigError(f"cameras {','.join(cameras)}: a recording holds both cameras' images; give the same "
                              "recording for both cameras (or for one), not a mix of inputs")
        pairs = scan_recordings(cameras, paths.pop(), workdir, inv)
        inv.unpaired = {c: 0 for c in cameras}
    else:
        frames = {}
        for c in cameras:
            if c not in specs:
                raise ConfigError(f"camera {c}: no input (give --source {c}=PATH or a `source` key in the station)")
            if kinds[c] == "video":
                frames[c] = scan_video(c, Path(specs[c]))
            else:
                frames[c], skipped = scan_images(c, Path(specs[c]))
                inv.skipped.extend(skipped)
            inv.frames[c] = len(frames[c])
        if len(cameras) == 2:
            pairs, inv.unpaired = pair_frames(frames[cameras[0]], frames[cameras[1]], tolerance_s)
        else:
            pairs, inv.unpaired = group_frames({c: frames[c] for c in cameras}, tolerance_s)
    for s in inv.skipped:
        log.warning("input skipped: %s: %s", s["path"], s["reason"], extra={"cbh_file": s["path"]})
    pairs = [p for p in pairs if (t_from is None or p.time_utc >= t_from) and (t_to is None or p.time_utc < t_to)]
    pairs.sort(key=lambda p: p.time_utc)
    inv.pairs = pairs
    return inv


def by_day(pairs: list[PairRef]) -> dict[date, list[PairRef]]:
    """Pairs grouped by the UTC day of their time (days ascending, pairs in time order)."""
    out: dict[date, list[PairRef]] = defaultdict(list)
    for p in pairs:
        out[p.time_utc.date()].append(p)
    return dict(sorted(out.items()))


# --- loading (on the worker) ------------------------------------------------------------------

def load_images(refs: list[FrameRef]) -> dict[FrameRef, np.ndarray | CbhError]:
    """Decoded BGR images of the frames, or the :class:`cbh.errors.CbhError` that makes one unusable.

    Video frames are read sequentially from the smallest needed frame number (one seek per
    file); recorded images are read through the recording's index for the time slice only.
    """
    from cbh.imageio import decode_image, read_image

    out: dict[FrameRef, np.ndarray | CbhError] = {}
    groups: dict[tuple[str, str], list[FrameRef]] = defaultdict(list)
    for r in refs:
        if r.kind == "image":
            try:
                out[r] = read_image(r.path)[0]
            except CbhError as exc:
                out[r] = exc
        else:
            groups[(r.kind, r.path)].append(r)
    for (kind, path), rs in groups.items():
        try:
            if kind == "video":
                out.update(_video_frames(path, rs))
            else:
                from cbh.outputs.record import open_session

                sess = open_session(path)
                t0 = min(to_ns(r.time_utc) for r in rs) - int(_RECORDING_MARGIN_S * 1e9)
                t1 = max(to_ns(r.time_utc) for r in rs) + int(_RECORDING_MARGIN_S * 1e9)
                want = {(r.index, r.camera): r for r in rs}
                for seq, img in sess.images(sorted({r.camera for r in rs}), t0, t1):
                    r = want.get((seq, img.camera))
                    if r is not None:
                        try:
                            out[r] = decode_image(img.data, what=f"{path} pair {seq} {img.camera}")
                        except CbhError as exc:
                            out[r] = exc
        except CbhError as exc:
            for r in rs:
                out.setdefault(r, exc)
        for r in rs:
            out.setdefault(r, ImageError(f"{r.describe()}: frame not found (file changed since it was scanned?)"))
    return out


def _video_frames(path: str, refs: list[FrameRef]) -> dict[FrameRef, np.ndarray | CbhError]:
    want = {r.index: r for r in refs}
    first, last = min(want), max(want)
    quiet_video_logs()  # a Ray worker's process: its own FFmpeg log level
    cap = cv2.VideoCapture(path, cv2.CAP_FFMPEG)
    out: dict[FrameRef, np.ndarray | CbhError] = {}
    try:
        if not cap.isOpened():
            raise ImageError(f"{path}: cannot open the video")
        if first:
            cap.set(cv2.CAP_PROP_POS_FRAMES, first)
        for i in range(first, last + 1):
            ok, img = cap.read()
            if not ok or img is None:
                break  # a truncated file: the missing frames are reported by the caller
            if i in want:
                out[want[i]] = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR) if img.ndim == 2 else img
    finally:
        cap.release()
    for r in refs:
        out.setdefault(r, ImageError(f"{path}: frame {r.index} unreadable (truncated video?)"))
    return out
