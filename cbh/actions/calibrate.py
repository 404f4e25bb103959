"""``cbh calibrate`` in library terms: each camera's orientation from the sun track and the clouds.

Steps (numerics in :mod:`cbh.geometry.calibrate` and :mod:`cbh.pipeline.sundetect`):

1. Frames of every station camera are read from its source (image folder with UTC-stamped
   names, video, stream for ``duration_s``, or a ``.mcap`` recording of ``cbh run --record``),
   kept when inside ``[from_utc, to_utc]``, and resized to the pipeline's working size. Two
   cameras whose frames are the same images (one folder or stream given for both) are refused.
2. **Sun**: in each frame, the sun is looked for within ``search_deg`` of where the station
   file's orientation and pvlib put it; occluded, ambiguous and absent suns are rejected
   (:func:`~cbh.pipeline.sundetect.detect_sun`). A camera's sun track is used when it has at
   least ``min_sun_frames`` detections spanning at least ``min_sun_azimuth_span_deg`` of
   azimuth (otherwise the report says what is missing).
3. **Clouds**: frames are paired by time (:class:`~cbh.live.pairing.Pairer`) and matched with
   the pipeline's ``orb`` matcher on the raw images (rotation-invariant, so a few degrees of
   misorientation do not matter; its gate around the infinity prediction is widened to
   ``max_misorientation_deg``). A RANSAC rotation fit over distant points (parallax below
   ``baseline / 500 m``) rejects mismatches and gives the starting relative rotation.
4. One robust joint fit of every camera's rotation to the sun tracks and the epipolar
   constraints (:func:`~cbh.geometry.calibrate.fit_orientations`). Without a usable sun
   track, ``relative_only`` keeps the reference camera (the first station camera) as the
   station file has it and fits the others relative to it; otherwise that is an error.
   Rotations under which the cloud matches meet behind both cameras (below the station) are
   refused, before the joint fit (cameras fixed by their sun) and after it: the two cameras'
   frames are swapped.
5. The station file is rewritten with the fitted angles (the rest of the text, comments
   included, is kept) and a comment giving the date, data span and residuals. Warnings (the
   clouds far off their epipolar curves, scattered sun detections) are in the report and logged.
"""
from __future__ import annotations

import hashlib
import logging
import math
import re
import time
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path

import cv2
import numpy as np

from cbh.errors import CalibrationError, CbhError, ConfigError, ImageError, SourceError
from cbh.result import Frame
from cbh.fileio import atomic_write

__all__ = ["CalibrateOptions", "calibrate", "rewrite_station_angles", "parse_sources"]

_log = logging.getLogger(__name__)

_IMAGE_GAP_S = 0.5
_SAME_IMAGE_PAIRS = 3  # refuse as soon as this many pairs all held the same image twice
_MIN_SIGN_ANGLE_DEG = 0.05  # rays closer than this to parallel do not vote in the front/behind count [deg]


@dataclass
class CalibrateOptions:
    """Knobs of :func:`calibrate` (defaults are the CLI's)."""

    from_utc: datetime | None = None
    to_utc: datetime | None = None
    duration_s: float | None = None  # live sources: stop after this long
    relative_only: bool = False  # no sun: keep the reference camera, fit the others relative to it
    search_deg: float = 20.0  # sun search radius around the station file's prediction [deg]
    max_misorientation_deg: float = 15.0  # ORB gate around the infinity prediction [deg]
    min_sun_frames: int = 5
    min_sun_azimuth_span_deg: float = 20.0
    max_matches_per_pair: int = 400  # RANSAC inliers kept per pair for the fit (even subsample)
    sun_sigma_deg: float = 0.05  # expected sun detection noise [deg]
    sun_outlier_deg: float = 1.0  # a detection this far off after the fit is an outlier (not in the RMS) [deg]
    match_sigma_px: float = 0.7  # expected ORB keypoint noise, working size [px]
    lk_sigma_px: float = 0.15  # expected LK (refinement) noise, working size [px]
    refine_pairs: int = 40  # pairs re-matched with LK on the first fit's geometry (0 = no refinement)


@dataclass
class _CamData:
    name: str
    frames: int = 0
    times: list = field(default_factory=list)
    rays: list = field(default_factory=list)
    sun_enu: list = field(default_factory=list)
    reasons: dict = field(default_factory=dict)
    t_first: datetime | None = None
    t_last: datetime | None = None


def parse_sources(specs: list[str]) -> dict[str, str]:
    """``["cam1=SPEC", …]`` → {camera: spec} (ConfigError naming a malformed or repeated one)."""
    out: dict[str, str] = {}
    for s in specs:
        cam, sep, spec = s.partition("=")
        if not sep or not cam.strip() or not spec.strip():
            raise ConfigError(f"--source {s!r}: expected CAM=SPEC (e.g. cam1=images/cam1)")
        if cam.strip() in out:
            raise ConfigError(f"--source: camera {cam.strip()!r} given twice")
        out[cam.strip()] = spec.strip()
    return out


def _check_sources(station, sources: dict[str, str]) -> dict[str, str]:
    unknown = [c for c in sources if c not in station.cameras]
    if unknown:
        raise ConfigError(f"--source {unknown[0]}=…: no camera {unknown[0]!r} in station {station.name!r} "
                          f"(cameras: {', '.join(station.cameras)})")
    missing = [c for c in station.cameras if c not in sources]
    if missing:
        raise ConfigError(f"station camera(s) {', '.join(missing)} have no --source (give --source {missing[0]}=SPEC)")
    return sources


def _recording_frames(camera: str, path: Path):
    from cbh.outputs.record import open_session

    for pair in open_session(path).pairs():
        img = pair.images.get(camera)
        if img is not None:
            yield Frame(camera, img.time_utc, None, encoded=img.data, format=img.format)


def _source_frames(cam, spec: str, base_dir: Path, duration_s: float | None):
    """Frames of one camera (images not yet decoded), until the source ends or ``duration_s``."""
    from cbh.interfaces import EndOfStream
    from cbh.live.sources import open_source

    if spec.lower().endswith(".mcap") or (Path(spec).is_dir() and any(Path(spec).glob("*.mcap"))):
        p = Path(spec) if Path(spec).is_absolute() or Path(spec).exists() else base_dir / spec
        yield from _recording_frames(cam.name, p)
        return
    src = open_source(cam, spec, decode=False, base_dir=base_dir)
    if src.live and not duration_s:
        raise ConfigError(f"{cam.name}: {spec} is a live stream: give --duration SECONDS to calibrate over it")
    src.open()
    t_end = time.monotonic() + duration_s if duration_s else None
    try:
        while True:
            if t_end is not None and time.monotonic() >= t_end:
                return
            try:
                f = src.read(timeout_s=1.0)
            except EndOfStream:
                return
            if f is None:
                if not src.live and t_end is None:  # a finite source with nothing more
                    return
                continue
            yield f
    finally:
        src.close()


def calibrate(station_path: str | Path, sources: dict[str, str], out: str | Path,
              options: CalibrateOptions | None = None) -> dict:
    """Fit the orientation of every station camera and write the calibrated station to ``out``.

    Returns
    -------
    dict
        The JSON report (``cbh calibrate --json``): per camera the angles before/after [deg],
        their standard deviations, sun frames/detections and residuals (RMS in deg and px, per
        frame), per pair the correspondences used and the epipolar residual; the data span.

    Raises
    ------
    CalibrationError
        No frames, no sun ever found (without ``relative_only``), no correspondences, an angle
        the data cannot determine; the same images for two cameras (one source given twice),
        or cloud matches that triangulate behind both cameras (two cameras' sources swapped).
    ConfigError, ImageError, SourceError
        Bad station, missing/unknown cameras in ``sources``, unreadable images.
    """
    from cbh.actions.station import load_station

    opt = options or CalibrateOptions()
    t_start = time.perf_counter()
    station_path, out = Path(station_path), Path(out)
    if out.suffix.lower() != ".toml":  # a calibration written over `--out SESSION.mcap` lost the recording
        raise ConfigError(f"--out {out}: the calibrated station is TOML; use a .toml file name")
    from cbh.fileio import refuse_inputs

    refuse_inputs([out], list(sources.values()), "--out")  # (over the station file itself: as the help says)
    station = load_station(station_path)
    _check_sources(station, sources)
    s = _Session(station, station_path.parent, opt)
    s.read(sources)
    s.check_frames(sources)
    sun_obs, sun_notes = s.sun_tracks()
    if not sun_obs and not opt.relative_only:
        raise CalibrationError("no usable sun track: " + "; ".join(f"{n}: {sun_notes[n]}" for n in s.names)
                               + " (with no sun, --relative-only calibrates the other cameras relative to "
                               f"{s.ref})")
    clocks = s.use_clocks()
    start, start_station, pairs = s.starting_rotations(sun_obs, clocks)
    s.check_cloud_in_front({n: start_station[n] for n in sun_obs}, pairs)  # cameras each fixed by its sun
    sun_pairs = s.sun_pairs(sun_obs, start)
    fit = _best_fit([start, start_station], sun_obs, pairs, s.ref, loss="cauchy", scale=3.0, sun_pairs=sun_pairs)
    if opt.refine_pairs > 0 and pairs:  # LK matches (sub-pixel) on the fitted geometry, then the fit again
        pairs = s.refined_pairs(fit, pairs)
        fit = _best_fit([{n: fit.cameras[n].R_world_from_cam for n in s.names}], sun_obs, pairs, s.ref,
                        sun_pairs=sun_pairs)
    s.check_cloud_in_front({n: c.R_world_from_cam for n, c in fit.cameras.items()}, pairs, fit.epipolar_rad)
    report = s.report(fit, pairs, sun_obs, sun_notes, station_path, out, t_start)
    _write_station(station_path, out, {n: fit.cameras[n] for n in s.names}, _comment(report),
                   {n: c["clock_offset_s"] for n, c in report["cameras"].items() if c["clock_offset_s"] is not None})
    for w in report["warnings"]:  # on stderr through the CLI's log handler, beside the report on stdout
        _log.warning("%s", w)
    return report


class _Session:
    """One calibration's data, as the frames are read: per camera its sun detections, per pair
    of cameras (every pair: a camera network's relative rotations come from all of them, made
    consistent by the one joint fit) the cloud correspondences and the images kept for the
    refinement."""

    def __init__(self, station, base_dir: Path, opt: CalibrateOptions):
        from cbh.pipeline import Pipeline

        self.station, self.base, self.opt = station, base_dir, opt
        self.names = list(station.cameras)
        self.ref = self.names[0]
        self.pairs = [(a, b) for j, b in enumerate(self.names) for a in self.names[:j]]
        # one pipeline per pair: working-size models, masks, segmentation
        self.pipes = {pq: Pipeline(station, f"{pq[0]},{pq[1]}") for pq in self.pairs}
        first = self.pipes[self.pairs[0]]
        self.cfg0 = first.config
        m = self.cfg0.matching
        self.orb_cfg = m.__class__(methods=("orb",), orb=m.orb.__class__(
            max_features=m.orb.max_features, max_hamming=m.orb.max_hamming,
            max_parallax_deg=opt.max_misorientation_deg))
        self.work_cam = {}
        for (a, b), pipe in self.pipes.items():
            self.work_cam.setdefault(a, pipe.cam1)
            self.work_cam.setdefault(b, pipe.cam2)
        self.data = {n: _CamData(n) for n in self.names}
        self.pair_obs: dict[tuple[str, str], list] = {pq: [] for pq in self.pairs}
        self.pair_counts = {pq: 0 for pq in self.pairs}
        self.stash: dict[tuple[str, str], list] = {pq: [] for pq in self.pairs}
        self.stash_stride = {pq: 1 for pq in self.pairs}
        self.digests: dict[tuple[str, datetime], bytes] = {}  # each frame's pixels, hashed (same-image check)
        self.compared = {pq: 0 for pq in self.pairs}
        self.identical = {pq: 0 for pq in self.pairs}
        self._sun_cache: dict[int, np.ndarray | None] = {}
        # the clocks: per pair its frames before, each pair's sky-map offset and carried matches
        self.prev: dict[tuple[str, str], tuple] = {}
        self.clock: dict[tuple[str, str], list[float]] = {pq: [] for pq in self.pairs}
        self.carried: dict[tuple[str, str], list] = {pq: [] for pq in self.pairs}

    # --- reading -------------------------------------------------------------------------------
    def read(self, sources: dict[str, str]) -> None:
        """Every camera's frames, taken in turns; each pair matched as soon as it is complete."""
        from cbh.live.pairing import Pairer

        pairers = {pq: Pairer(pq, tolerance_s=_IMAGE_GAP_S) for pq in self.pairs}
        live = {n: _source_frames(self.station.cameras[n], sources[n], self.base, self.opt.duration_s)
                for n in self.names}
        while live:
            for n in list(live):
                try:
                    f = next(live[n])
                except StopIteration:
                    del live[n]
                    continue
                except CbhError:
                    raise
                except OSError as exc:
                    raise SourceError(f"{n}: {exc.strerror or exc}") from None
                kept = self.take(f)
                if kept is None:
                    continue
                for k, p in pairers.items():
                    if n in k:
                        p.push(kept)
                        for fa, fb in p.pop_pairs():
                            self.match(k, fa, fb)
        for k, p in pairers.items():
            for fa, fb in p.flush():
                self.match(k, fa, fb)

    def sun_at(self, t: datetime) -> np.ndarray | None:
        """Apparent ENU sun direction at ``t`` (None at night)."""
        from cbh.geometry.sun import sun_position

        key = int(t.timestamp())  # one pvlib call per second of data (the sun moves 0.004 deg/s)
        if key not in self._sun_cache:
            st = self.station
            sp = sun_position(st.latitude_deg, st.longitude_deg, st.altitude_m, t)
            self._sun_cache[key] = sp.direction_enu if sp.zenith_deg < 90.0 else None
        return self._sun_cache[key]

    def to_working(self, name: str, img: np.ndarray) -> np.ndarray:
        pq = next(pq for pq in self.pairs if name in pq)
        return self.pipes[pq].to_working(pq.index(name), img)

    def take(self, frame: Frame) -> Frame | None:
        """One frame: in the time span? decoded, checked, at working size, its sun looked for."""
        from cbh.imageio import decode_image
        from cbh.pipeline.sundetect import detect_sun

        t, opt = frame.time_utc, self.opt
        if (opt.from_utc and t < opt.from_utc) or (opt.to_utc and t > opt.to_utc):
            return None
        cam = self.station.cameras[frame.camera]
        img = frame.image if frame.image is not None else decode_image(
            frame.encoded or b"", what=f"{frame.camera} frame at {t.isoformat()}")
        if img.ndim != 3 or img.shape[:2] != (cam.model.height, cam.model.width):
            raise ImageError(f"{frame.camera}: image at {t.isoformat()} is {img.shape[1]}x{img.shape[0]} px, "
                             f"its calibration is {cam.model.width}x{cam.model.height}")
        self.digests[(frame.camera, t)] = hashlib.blake2b(np.ascontiguousarray(img).data, digest_size=16).digest()
        w = self.to_working(frame.camera, img)
        d = self.data[frame.camera]
        d.frames += 1
        d.t_first = t if d.t_first is None else min(d.t_first, t)
        d.t_last = t if d.t_last is None else max(d.t_last, t)
        s = self.sun_at(t)
        if s is None:
            d.reasons["night"] = d.reasons.get("night", 0) + 1
        else:
            wc = self.work_cam[frame.camera]
            det = detect_sun(w, wc, s @ wc.R_world_from_cam, opt.search_deg)
            d.reasons[det.reason] = d.reasons.get(det.reason, 0) + 1
            if det.ok:
                d.times.append(t)
                d.rays.append(det.ray_cam)
                d.sun_enu.append(s)
        return Frame(frame.camera, t, w)

    def match(self, other: tuple[str, str], fa: Frame, fb: Frame) -> None:
        """ORB correspondences of one pair (``other``: its two cameras); its images kept for the
        refinement when it falls on the even subset."""
        from cbh.pipeline.match import MatchInput, get_matcher
        from cbh.pipeline.run import PairContext

        self._compare_images(other, fa, fb)
        pipe = self.pipes[other]
        work = (fa.image, fb.image)
        masks = pipe.stage_masks(work, PairContext(time_utc=fa.time_utc))
        masks, seg = masks.for_matching(pipe.stage_segment(work, masks))  # (no saturated contours)
        if not seg.clouds[0].any():
            return
        inp = MatchInput(geometry=pipe.geometry, gray1=cv2.cvtColor(work[0], cv2.COLOR_BGR2GRAY),
                         gray2=cv2.cvtColor(work[1], cv2.COLOR_BGR2GRAY), cloud1=seg.clouds[0],
                         usable1=masks.usable[0], usable2=masks.usable[1], cloud2=seg.clouds[1])
        self._sky(other, fa.time_utc, (inp.gray1, inp.gray2), masks.usable, seg.clouds[0])
        m = get_matcher("orb")(inp, self.orb_cfg)
        if not len(m):
            return
        self.pair_obs[other].append((pipe.cam1.model.pixel_to_ray(m.px1), pipe.cam2.model.pixel_to_ray(m.px2)))
        self.pair_counts[other] += 1
        # keep grey images and masks of an even subset of the pairs for the LK refinement
        kept = self.stash[other]
        stride = self.stash_stride[other]
        if self.pair_counts[other] % stride == 0:
            kept.append((inp.gray1, inp.gray2, np.packbits(seg.clouds[0]), np.packbits(masks.usable[0]),
                         np.packbits(masks.usable[1]), np.packbits(seg.clouds[1])))
            if len(kept) > self.opt.refine_pairs:
                del kept[1::2]
                self.stash_stride[other] = stride * 2

    def _sky(self, other: tuple[str, str], t: datetime, gray, usable, cloud1) -> None:
        """The pair's clock offset on the sky maps against the pair before (within the motion's
        ``max_gap_s``) and its carried matches on camera a's cloud (:meth:`Pipeline.sky_offset`):
        the cloud correspondences of a pair whose clocks differ (:meth:`use_clocks`)."""
        from cbh.pipeline.run import _on_mask

        pipe = self.pipes[other]
        before = self.prev.get(other)
        self.prev[other] = (t, gray)
        if before is None:
            return
        dt = (t - before[0]).total_seconds()
        if not 0.0 < dt <= pipe.config.motion.max_gap_s:
            return
        sky = pipe.sky_offset(gray, usable, before[1], dt)
        if not math.isfinite(sky.offset_s):
            return
        self.clock[other].append(float(sky.offset_s))
        rays = np.concatenate([sky.a1, np.ones((len(sky.a1), 1))], axis=1) @ pipe.cam1.R_world_from_cam
        on = _on_mask(cloud1, pipe.cam1.model.ray_to_pixel(rays))
        if on.any():
            self.carried[other].append((sky.a1[on], sky.flow[on], sky.rate[on]))

    def clock_offset(self, pq: tuple[str, str]) -> tuple[float, float, int]:
        """Camera b's clock offset against camera a from the sky maps: (median [s], robust spread
        [s], pairs); NaN with none."""
        v = np.asarray(self.clock[pq], np.float64)
        if not v.size:
            return math.nan, math.nan, 0
        med = float(np.median(v))
        return med, float(1.4826 * np.median(np.abs(v - med))), int(v.size)

    def use_clocks(self) -> dict[tuple[str, str], float]:
        """Pairs whose clocks differ by more than the pairing tolerance take their cloud
        correspondences from the sky maps, camera b carried to camera a's capture time by each
        pixel's own motion and the median offset, in place of ORB at the same stamp (with a 30 s
        offset the real Fehmarn station's ORB matches missed their epipolar curves by 2° and,
        triangulated, met behind both cameras: the fit was refused as "swapped cameras"); their
        images are not re-matched by LK at the same stamp either. Returns {pair: offset used}."""
        used = {}
        for pq in self.pairs:
            off, _, n = self.clock_offset(pq)
            if not (n and abs(off) > self.pipes[pq].config.motion.offset_tolerance_s and self.carried[pq]):
                continue
            pipe = self.pipes[pq]
            obs = []
            for a1, flow, rate in self.carried[pq]:
                r1 = np.concatenate([a1, np.ones((len(a1), 1))], axis=1)
                r2 = np.concatenate([a1 + flow - rate * off, np.ones((len(a1), 1))], axis=1)
                r1 = (r1 / np.linalg.norm(r1, axis=1, keepdims=True)) @ pipe.cam1.R_world_from_cam
                r2 = (r2 / np.linalg.norm(r2, axis=1, keepdims=True)) @ pipe.cam2.R_world_from_cam
                obs.append((r1, r2))
            self.pair_obs[pq] = obs
            self.stash[pq] = []
            used[pq] = off
        return used

    def _compare_images(self, other: tuple[str, str], fa: Frame, fb: Frame) -> None:
        """Count the pairs whose two images are the same; refuse at once when the first
        ``_SAME_IMAGE_PAIRS`` all are (one folder or stream given for both cameras)."""
        self.compared[other] += 1
        if self.digests.get((fa.camera, fa.time_utc)) == self.digests.get((fb.camera, fb.time_utc)):
            self.identical[other] += 1
        if self.compared[other] == _SAME_IMAGE_PAIRS and self.identical[other] == _SAME_IMAGE_PAIRS:
            self._refuse_identical(other)

    def _refuse_identical(self, other: tuple[str, str]) -> None:
        raise CalibrationError(
            f"{other[0]} and {other[1]} delivered the same images ({self.identical[other]} of "
            f"{self.compared[other]} pairs identical): the same folder or stream is given for both cameras? "
            f"give each --source its own camera's frames")

    def check_frames(self, sources: dict[str, str]) -> None:
        """Every camera delivered frames; no two cameras delivered the same images."""
        empty = [n for n in self.names if self.data[n].frames == 0]
        if empty:
            span = ""
            if self.opt.from_utc or self.opt.to_utc:
                span = f" between {_iso(self.opt.from_utc) or '…'} and {_iso(self.opt.to_utc) or '…'}"
            raise CalibrationError(f"no frames{span} from camera(s) {', '.join(empty)} ({sources[empty[0]]})")
        for other in self.pairs:
            if self.compared[other] and 2 * self.identical[other] > self.compared[other]:
                self._refuse_identical(other)

    # --- the fit ---------------------------------------------------------------------------------
    def sun_tracks(self) -> tuple[dict, dict]:
        """Each camera's usable sun track ({camera: SunObservations}) and, for the others, why not."""
        from cbh.geometry.calibrate import SunObservations

        sun_obs, sun_notes = {}, {}
        for n in self.names:
            d = self.data[n]
            k = len(d.rays)
            if k == 0:
                sun_notes[n] = f"no sun found in {d.frames} frames ({_reasons(d.reasons)})"
                continue
            az = np.degrees(np.arctan2([v[0] for v in d.sun_enu], [v[1] for v in d.sun_enu]))
            span = _azimuth_span_deg(az)
            if k < self.opt.min_sun_frames or span < self.opt.min_sun_azimuth_span_deg:
                sun_notes[n] = (f"sun track too short: {k} detections over {span:.1f} deg of azimuth "
                                f"(need {self.opt.min_sun_frames} over {self.opt.min_sun_azimuth_span_deg:g} deg; "
                                f"give frames from more of the day)")
                continue
            sun_obs[n] = SunObservations(np.array(d.rays), np.array(d.sun_enu), self.opt.sun_sigma_deg)
        return sun_obs, sun_notes

    def starting_rotations(self, sun_obs: dict, clocks: dict | None = None) -> tuple[dict, dict, list]:
        """Two starts for the fit (the RANSAC rotation of distant points; the station file's
        relative rotations), each sun-tracked camera first fitted to its own sun, and the ORB
        correspondences of every pair as PairObservations."""
        from cbh.geometry.calibrate import PairObservations, fit_orientations, rotation_from_far_matches

        R0 = {n: self.station.cameras[n].R_world_from_cam.copy() for n in self.names}
        start = dict(R0)
        for n, o in sun_obs.items():  # each sun-tracked camera on its own first
            start[n] = fit_orientations({n: R0[n]}, {n: o}, [], reference=n).cameras[n].R_world_from_cam
        started = {self.ref, *sun_obs}
        start_station = dict(start)  # the alternative start: the station file's relative rotations
        pairs = []
        for a, b in self._start_order(sun_obs):  # each camera started from a pair with one started before it
            obs = self.pair_obs[(a, b)]
            ra = np.concatenate([o[0] for o in obs])
            rb = np.concatenate([o[1] for o in obs])
            t = self.station.cameras[b].position_m - self.station.cameras[a].position_m
            thr = max(1.0, math.degrees(math.atan(float(np.linalg.norm(t)) / 500.0)))
            R_rel, inl = rotation_from_far_matches(ra, rb, thr)
            if inl.sum() < 20:
                raise CalibrationError(f"only {int(inl.sum())} consistent cloud correspondences between "
                                       f"{a} and {b}")
            if b not in sun_obs and b not in started:
                start[b] = start[a] @ R_rel
                started.add(b)
            elif a not in sun_obs and a not in started:
                start[a] = start[b] @ R_rel.T
                started.add(a)
            # every correspondence (even subsample per pair, so no single pair dominates); the
            # robust fit sorts out mismatches
            cap = self.opt.max_matches_per_pair * max(len(obs), 1)
            keep = np.arange(len(ra))
            if len(keep) > cap:
                keep = keep[:: len(keep) // cap + 1]
            ppr = _px_per_rad(self.work_cam[b])
            carried = (a, b) in (clocks or {})
            pairs.append(PairObservations(a, b, ra[keep], rb[keep], t, self.opt.match_sigma_px / ppr,
                                          "skyflow" if carried else "orb"))
        return start, start_station, pairs

    def _start_order(self, sun_obs: dict) -> list[tuple[str, str]]:
        """The pairs with cloud correspondences, ordered so that each camera without a sun track
        is reached from one already started (the reference first, then through the others).

        Raises CalibrationError for a camera that no such pair reaches."""
        have = [pq for pq in self.pairs if self.pair_obs[pq]]
        started, order = {self.ref, *sun_obs}, []
        while True:
            nxt = [pq for pq in have if pq not in order and (pq[0] in started or pq[1] in started)]
            if not nxt:
                break
            order.extend(nxt)
            started.update(c for pq in nxt for c in pq)
        for n in self.names:
            if n not in started:
                counts = ", ".join(f"{a}-{b} {self.pair_counts[(a, b)]}" for a, b in self.pairs if n in (a, b))
                raise CalibrationError(f"no cloud correspondences between {n} and a camera of known orientation "
                                       f"(pairs read: {counts}), and no sun track for {n}: its orientation "
                                       "cannot be determined")
        return order

    def sun_pairs(self, sun_obs: dict, start: dict) -> list:
        """The sun seen by both cameras of a pair at once: a relative constraint at infinity, for
        cameras without a usable sun track of their own (detections that disagree with the
        rest by more than 1 deg dropped)."""
        from cbh.geometry.calibrate import SunPairObservations

        out = []
        for ref, other in self.pairs:
            if ref in sun_obs and other in sun_obs:
                continue
            ta = {t: r for t, r in zip(self.data[ref].times, self.data[ref].rays)}
            both = [(ta[t], r) for t, r in zip(self.data[other].times, self.data[other].rays) if t in ta]
            if len(both) > 2:
                A0, B0 = start[ref], start[other]
                dis = np.array([math.degrees(math.acos(min(1.0, float((A0 @ a) @ (B0 @ b))))) for a, b in both])
                both = [x for x, d in zip(both, dis) if abs(d - np.median(dis)) <= 1.0]
            if both:
                out.append(SunPairObservations(ref, other, np.array([b[0] for b in both]),
                                               np.array([b[1] for b in both]), self.opt.sun_sigma_deg * math.sqrt(2.0)))
        return out

    def refined_pairs(self, fit, pairs: list) -> list:
        """``pairs``, each followed by the LK correspondences (sub-pixel) of its kept images,
        matched on the fitted geometry (the ORB ones stay: LK alone can be few on real skies)."""
        from dataclasses import replace

        from cbh.geometry.calibrate import PairObservations
        from cbh.pipeline import Pipeline
        from cbh.pipeline.match import MatchInput, get_matcher

        fitted = replace(self.station, cameras={n: replace(c, R_world_from_cam=fit.cameras[n].R_world_from_cam)
                                                for n, c in self.station.cameras.items()})
        lk_cfg = self.cfg0.matching.__class__(methods=("lk",), lk=self.cfg0.matching.lk)
        new = []
        for p in pairs:
            pipe = Pipeline(fitted, f"{p.cam_a},{p.cam_b}", config=self.pipes[(p.cam_a, p.cam_b)].config)
            shape1 = (pipe.cam1.model.height, pipe.cam1.model.width)
            shape2 = (pipe.cam2.model.height, pipe.cam2.model.width)
            ra_l, rb_l = [], []
            new.append(p)
            for g1, g2, c1, u1, u2, c2 in self.stash[(p.cam_a, p.cam_b)]:
                inp = MatchInput(geometry=pipe.geometry, gray1=g1, gray2=g2, cloud1=_unpack(c1, shape1),
                                 usable1=_unpack(u1, shape1), usable2=_unpack(u2, shape2), cloud2=_unpack(c2, shape2))
                m = get_matcher("lk")(inp, lk_cfg)
                if len(m):
                    ra_l.append(pipe.cam1.model.pixel_to_ray(m.px1))
                    rb_l.append(pipe.cam2.model.pixel_to_ray(m.px2))
            if ra_l:
                ppr = _px_per_rad(self.work_cam[p.cam_b])
                new.append(PairObservations(p.cam_a, p.cam_b, np.concatenate(ra_l), np.concatenate(rb_l),
                                            p.baseline_m, self.opt.lk_sigma_px / ppr, "lk"))
        return new

    def check_cloud_in_front(self, R: dict, pairs: list, epipolar_rad: list | None = None) -> None:
        """Refuse rotations ``R`` ({camera: R_world_from_cam}) under which the cloud matches
        triangulate behind both cameras.

        A cloud seen from two cameras lies in front of both; with the two cameras' frames
        swapped, every ray pair meets at the cloud's mirror image through the baseline, below
        the station and behind both cameras (the epipolar constraint cannot tell: it is the
        same for baseline ``t`` and ``−t``). Counted over the matches whose rays are not
        near-parallel (distant points, whose sign noise decides) and, with ``epipolar_rad``
        (a fit's residuals per pair), over that fit's inliers only.
        """
        from cbh.geometry.triangulate import triangulate

        for i, p in enumerate(pairs):
            if p.cam_a not in R or p.cam_b not in R:
                continue
            sel = np.ones(len(p.rays_a), bool) if epipolar_rad is None \
                else np.abs(epipolar_rad[i]) <= 3.0 * p.sigma_rad * 2.0
            n = int(sel.sum())
            if n < 20:
                continue
            d1 = p.rays_a[sel] @ R[p.cam_a].T
            d2 = p.rays_b[sel] @ R[p.cam_b].T
            o1 = np.broadcast_to(self.station.cameras[p.cam_a].position_m, (n, 3))
            o2 = np.broadcast_to(self.station.cameras[p.cam_b].position_m, (n, 3))
            tri = triangulate(o1, d1, o2, d2)
            clear = tri.angle_deg >= _MIN_SIGN_ANGLE_DEG
            front = int(np.sum(clear & (tri.range1_m > 0) & (tri.range2_m > 0)))
            behind = int(np.sum(clear & (tri.range1_m < 0) & (tri.range2_m < 0)))
            if behind > front and behind >= 20:
                raise CalibrationError(
                    f"{p.cam_a}-{p.cam_b}: {behind} of {front + behind} cloud matches meet behind both cameras, "
                    f"below the station: the two cameras' frames are probably swapped (--source {p.cam_a}=… "
                    f"holding {p.cam_b}'s images); give each --source its own camera's frames")

    # --- the report --------------------------------------------------------------------------
    def report(self, fit, pairs: list, sun_obs: dict, sun_notes: dict, station_path: Path, out: Path,
               t_start: float) -> dict:
        """The JSON report of :func:`calibrate` (its ``summary`` lines included)."""
        cams = {n: {**self._camera_report(n, fit.cameras[n], sun_obs, sun_notes), **self._clock_report(n)}
                for n in self.names}
        pair_rep = [self._pair_report(p, e) for p, e in zip(pairs, fit.epipolar_rad)]
        relative = {}
        for n in self.names[1:]:
            Rr = fit.cameras[self.ref].R_world_from_cam.T @ fit.cameras[n].R_world_from_cam
            R0 = self.station.cameras[self.ref].R_world_from_cam.T @ self.station.cameras[n].R_world_from_cam
            relative[n] = {"relative_change_deg": math.degrees(math.acos(min(1.0, (np.trace(R0.T @ Rr) - 1.0) / 2.0)))}
        warnings = self._warnings(pairs, pair_rep, cams)
        if not fit.absolute:
            warnings += self._relative_warnings(relative)
        report = {
            "station": str(station_path),
            "warnings": warnings,
            "out": str(out),
            "calibrated_utc": _iso(datetime.now(timezone.utc)),
            "data_from_utc": _iso(min(self.data[n].t_first for n in self.names)),
            "data_to_utc": _iso(max(self.data[n].t_last for n in self.names)),
            "absolute": fit.absolute,
            "reference": self.ref,
            "cameras": cams,
            "pairs": pair_rep,
            "relative": relative,
            "elapsed_s": round(time.perf_counter() - t_start, 3),
        }
        report["summary"] = _summary(report)
        return report

    def _camera_report(self, n: str, cf, sun_obs: dict, sun_notes: dict) -> dict:
        from cbh.geometry.station import angles_from_rotation

        d, opt, used = self.data[n], self.opt, n in sun_obs
        before = angles_from_rotation(self.station.cameras[n].R_world_from_cam)
        full_ppd = _px_per_rad(self.station.cameras[n]) * math.pi / 180.0
        good = cf.sun_residual_deg[cf.sun_residual_deg <= opt.sun_outlier_deg]
        sun_rms = float(np.sqrt(np.mean(good ** 2))) if len(good) else math.nan
        sres = [{"time_utc": _iso(t), "residual_deg": float(r)} for t, r in zip(d.times, cf.sun_residual_deg)] if used else []
        return {
            "angles_before_deg": _angles(before),
            "angles_deg": _angles(cf.angles_deg),
            "change_deg": _angles([(a - b + 180.0) % 360.0 - 180.0 for a, b in zip(cf.angles_deg, before)]),
            "sigma_deg": _angles(cf.sigma_deg),
            "frames": d.frames,
            "sun_detections": len(d.rays),
            "sun_rejected": {k: v for k, v in d.reasons.items() if k != "ok"},
            "sun_used": used,
            "sun_note": sun_notes.get(n),
            "sun_rms_deg": _num(sun_rms) if used else None,
            "sun_rms_px": _num(sun_rms * full_ppd) if used else None,
            "sun_outliers": int(np.sum(cf.sun_residual_deg > opt.sun_outlier_deg)) if used else 0,
            "sun_residuals": sres,
        }

    def _relative_warnings(self, relative: dict) -> list[str]:
        """Without the sun, a relative turn well beyond what the station says its calibration
        leaves (``expected_miss_ratio``, or 0.15°): the clouds alone barely constrain camera b's
        tilt along the baseline (it moves a deck's parallax, not its epipolar curves, near the
        zenith), and a lens model's error can pull it. On the real Fehmarn hour they asked for
        0.7° (mostly pitch) and put its 8.5 km deck at 5.5–6.5 km."""
        gc = self.cfg0.geometry_check
        limit = max(3.0 * math.degrees(gc.expected_miss_ratio), 0.15)
        return [f"{n}: the clouds alone turn it by {r['relative_change_deg']:.2f} deg against {self.ref} (more than "
                f"{limit:.2f} deg): without the sun, a camera's tilt along the baseline trades against the layers' "
                "heights; check the new station on a known height (a kite, a drone: `cbh triangulate`; a ceilometer: "
                "`cbh validate`) before using it"
                for n, r in relative.items() if r["relative_change_deg"] > limit]

    def _clock_report(self, n: str) -> dict:
        """Camera ``n``'s clock offset against the reference (as a station file states it:
        how many seconds late it captures against its stamps, the reference's own stated value
        added): None when not measured; the reference keeps its stated value."""
        stated = self.station.cameras[self.ref].clock_offset_s
        if n == self.ref:
            return {"clock_offset_s": stated, "clock_offset_spread_s": None, "clock_offset_pairs": 0}
        off, spread, k = self.clock_offset((self.ref, n))
        if not k:
            return {"clock_offset_s": None, "clock_offset_spread_s": None, "clock_offset_pairs": 0}
        return {"clock_offset_s": round(off + float(stated or 0.0), 2), "clock_offset_spread_s": round(spread, 2),
                "clock_offset_pairs": k}

    def _pair_report(self, p, e: np.ndarray) -> dict:
        ppr_full = _px_per_rad(self.station.cameras[p.cam_b])
        inl = np.abs(e) <= 3.0 * p.sigma_rad * 2.0
        return {
            "cameras": [p.cam_a, p.cam_b],
            "method": p.method,
            "pairs_matched": self.pair_counts[(p.cam_a, p.cam_b)],
            "refined_pairs": len(self.stash[(p.cam_a, p.cam_b)]) if p.method == "lk" else 0,
            "matches_used": int(len(e)),
            "matches_inlier": int(inl.sum()),
            "epipolar_rms_deg": _num(math.degrees(float(np.sqrt(np.mean(e[inl] ** 2))))) if inl.any() else None,
            "epipolar_median_px": _num(float(np.median(np.abs(e))) * ppr_full),
        }

    def _warnings(self, pairs: list, pair_rep: list, cams: dict) -> list[str]:
        warnings = []
        for p, pr in zip(pairs, pair_rep):
            expect_px = p.sigma_rad * _px_per_rad(self.station.cameras[p.cam_b])
            if pr["epipolar_median_px"] is not None and pr["epipolar_median_px"] > 3.0 * expect_px:
                warnings.append(
                    f"{p.cam_a}-{p.cam_b} {p.method}: the cloud matches stay {pr['epipolar_median_px']:.1f} px off "
                    f"their epipolar curves (expected ~{expect_px:.1f} px): the lens calibrations or the data do not "
                    "support one rotation; check the new station with `cbh pair` before using it")
        for n, c in cams.items():
            if c["sun_used"] and c["sun_rms_deg"] is not None and c["sun_rms_deg"] > 5 * self.opt.sun_sigma_deg:
                warnings.append(f"{n}: the sun detections scatter by {c['sun_rms_deg']:.2f} deg RMS around the fit")
        return warnings


def _unpack(bits: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """A mask kept by ``np.packbits``, back as (H, W) bool."""
    return np.unpackbits(bits, count=shape[0] * shape[1]).reshape(shape).astype(bool)


def _write_station(station_path: Path, out: Path, fitted: dict, comment: list[str], clocks: dict | None = None) -> None:
    """The station file rewritten with the fitted angles and measured clock offsets (comments and
    other keys kept), checked to read back to the fitted rotations, written atomically to ``out``."""
    import tomllib

    from cbh.geometry.station import parse_station

    text = station_path.read_text(encoding="utf-8")
    new_text = rewrite_station_angles(text, {n: cf.angles_deg for n, cf in fitted.items()}, comment, clocks)
    try:
        back = parse_station(tomllib.loads(new_text), base_dir=station_path.parent, path=out)
    except (tomllib.TOMLDecodeError, ConfigError) as exc:  # pragma: no cover - a bug here, said in one line
        raise CalibrationError(f"internal: the rewritten station does not read back ({exc})") from None
    for n, cf in fitted.items():
        err = np.abs(back.cameras[n].R_world_from_cam - cf.R_world_from_cam).max()
        if err > 1e-6:  # pragma: no cover - a bug in rewrite_station_angles
            raise CalibrationError(f"internal: rewritten station disagrees for {n} ({err:.2g})")
    _write_atomic(out, new_text)


def _best_fit(starts: list[dict], sun_obs, pairs, ref, loss: str = "huber", scale: float = 2.0, sun_pairs=()):
    """The fit with the lowest robust cost over several starting rotations.

    Two starts: the RANSAC rotation of distant points (right when the station file is off by
    degrees, biased by parallax when the clouds are close) and the station file's own
    rotations (right when it is nearly calibrated). A start whose fit fails counts as worst.
    """
    from cbh.geometry.calibrate import fit_orientations

    best, err, best_n = None, None, -1
    for st in starts:
        try:
            f = fit_orientations(st, sun_obs, pairs, reference=ref, loss=loss, huber=scale, sun_pairs=sun_pairs)
        except CalibrationError as exc:
            err = err or exc
            continue
        n_in = sum(int(np.sum(np.abs(e) <= 3.0 * p.sigma_rad)) for e, p in zip(f.epipolar_rad, pairs))
        if n_in > best_n:
            best, best_n = f, n_in
    if best is None:
        raise err
    return best


def _summary(rep: dict) -> list[str]:
    """Human-readable lines for the CLI."""
    out = [f"data {rep['data_from_utc']} .. {rep['data_to_utc']}; "
           f"{'absolute (sun) + relative (clouds)' if rep['absolute'] else 'relative only: ' + rep['reference'] + ' kept'}"]
    for n, c in rep["cameras"].items():
        a, b, s = c["angles_before_deg"], c["angles_deg"], c["sigma_deg"]
        line = (f"{n}: yaw {a['yaw']:.3f} -> {b['yaw']:.3f}  pitch {a['pitch']:.3f} -> {b['pitch']:.3f}  "
                f"roll {a['roll']:.3f} -> {b['roll']:.3f} deg (sigma {max(s.values()):.3f} deg); "
                f"{c['frames']} frames, sun in {c['sun_detections']}")
        if c["sun_used"]:
            line += f", sun RMS {c['sun_rms_deg']:.3f} deg ({c['sun_rms_px']:.2f} px), {c['sun_outliers']} outliers"
        elif c["sun_note"]:
            line += f" ({c['sun_note']})"
        if n != rep["reference"]:
            line += (f"; clock offset {c['clock_offset_s']:+.2f} s (spread {c['clock_offset_spread_s']:.2f} s over "
                     f"{c['clock_offset_pairs']} pairs)" if c.get("clock_offset_s") is not None
                     else "; clock offset not measured (no cloud motion across the baseline)")
        out.append(line)
    for p in rep["pairs"]:
        out.append(f"{p['cameras'][0]}-{p['cameras'][1]} {p['method']}: {p['matches_used']} cloud matches from "
                   f"{p['refined_pairs'] or p['pairs_matched']} "
                   f"pairs, median epipolar residual {p['epipolar_median_px']:.2f} px")
    out.append(f"wrote {rep['out']} ({rep['elapsed_s']:.1f} s)")
    return out


def _write_atomic(path: Path, text: str) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_write(path) as tmp:
        tmp.write_text(text, encoding="utf-8")


def _px_per_rad(cam) -> float:
    return cam.model.px_per_rad(math.radians(45.0))


def _azimuth_span_deg(az_deg: np.ndarray) -> float:
    """Smallest arc of azimuth containing every value [deg]."""
    a = np.sort(np.asarray(az_deg) % 360.0)
    if len(a) < 2:
        return 0.0
    gaps = np.diff(np.concatenate([a, [a[0] + 360.0]]))
    return float(360.0 - gaps.max())


def _reasons(r: dict) -> str:
    return ", ".join(f"{k}: {v}" for k, v in sorted(r.items())) or "no frames"


def _angles(a) -> dict:
    return {k: _num(v) for k, v in zip(("yaw", "pitch", "roll"), a)}


def _num(v):
    v = float(v)
    return v if math.isfinite(v) else None


def _iso(t: datetime | None) -> str | None:
    """ISO 8601 UTC text (:func:`cbh.timeutil.format_utc`), None for None (JSON null)."""
    from cbh.timeutil import format_utc

    return None if t is None else format_utc(t)


def _comment(rep: dict) -> list[str]:
    lines = [f"Calibrated by `cbh calibrate` on {rep['calibrated_utc']} from frames "
             f"{rep['data_from_utc']} .. {rep['data_to_utc']} "
             f"({'sun track + clouds' if rep['absolute'] else 'clouds only, ' + rep['reference'] + ' kept'})."]
    for n, c in rep["cameras"].items():
        a, b = c["angles_before_deg"], c["angles_deg"]
        s = f"  {n}: was yaw/pitch/roll {a['yaw']:.3f}/{a['pitch']:.3f}/{a['roll']:.3f} deg"
        if c["sun_used"]:
            s += f"; sun {c['sun_detections']} frames, RMS {c['sun_rms_deg']:.3f} deg ({c['sun_rms_px']:.2f} px)"
        lines.append(s)
        del b
    for p in rep["pairs"]:
        lines.append(f"  {p['cameras'][0]}-{p['cameras'][1]} {p['method']}: {p['matches_used']} cloud matches from "
                     f"{p['refined_pairs'] or p['pairs_matched']} pairs, median epipolar residual {p['epipolar_median_px']:.2f} px")
    return lines


_CAMERA_HEADER = re.compile(r"^\s*\[\[\s*cameras\s*\]\]\s*(#.*)?$")
_TABLE_HEADER = re.compile(r"""^\s*\[\[?\s*[A-Za-z_"']""")
_ANGLE_KEY = re.compile(r"^\s*(yaw_deg|pitch_deg|roll_deg)\s*=")
_ROTATION_KEY = re.compile(r"^\s*rotation\s*=")
_CLOCK_KEY = re.compile(r"^\s*clock_offset_s\s*=")
_NAME_KEY = re.compile(r"""^\s*name\s*=\s*["']([^"']*)["']""")


def rewrite_station_angles(text: str, angles: dict[str, tuple[float, float, float]], comment: list[str],
                           clocks: dict[str, float] | None = None) -> str:
    """The station TOML ``text`` with each named camera's orientation replaced by ``angles``
    (yaw, pitch, roll [deg]); a ``rotation`` matrix is replaced too, and ``clock_offset_s`` by
    ``clocks`` where given. Everything else (comments, other keys, tables) is kept; ``comment``
    lines go above the first ``[[cameras]]``, replacing an earlier calibration comment."""
    clocks = clocks or {}
    lines = text.splitlines()
    # drop an earlier `cbh calibrate` comment block
    out_lines, skip = [], False
    for ln in lines:
        if ln.startswith("# Calibrated by `cbh calibrate`"):
            skip = True
            continue
        if skip and ln.startswith("#   "):
            continue
        skip = False
        out_lines.append(ln)
    lines = out_lines
    result: list[str] = []
    i = 0
    inserted_comment = False
    while i < len(lines):
        ln = lines[i]
        if _CAMERA_HEADER.match(ln):
            if not inserted_comment:
                result.extend("# " + c if not c.startswith("  ") else "#   " + c.strip() for c in comment)
                inserted_comment = True
            # the camera's own keys: up to the next table header
            j, depth = i + 1, 0
            while j < len(lines) and not (depth == 0 and _TABLE_HEADER.match(lines[j])):
                code = lines[j].split("#", 1)[0]
                depth += code.count("[") - code.count("]")
                j += 1
            block = lines[i + 1:j]
            name = next((m.group(1) for m in map(_NAME_KEY.match, block) if m), None)
            if name in angles:
                kept, k, anchor = [], 0, None
                while k < len(block):
                    b = block[k]
                    if _ANGLE_KEY.match(b) or (name in clocks and _CLOCK_KEY.match(b)):
                        anchor = anchor if anchor is not None else len(kept)
                        k += 1
                        continue
                    if _ROTATION_KEY.match(b):
                        anchor = anchor if anchor is not None else len(kept)
                        depth = b.count("[") - b.count("]")
                        k += 1
                        while depth > 0 and k < len(block):
                            depth += block[k].count("[") - block[k].count("]")
                            k += 1
                        continue
                    kept.append(b)
                    k += 1
                if anchor is None:  # after the last key line
                    anchor = max((idx + 1 for idx, b in enumerate(kept) if b.strip() and not b.strip().startswith("#")),
                                 default=len(kept))
                y, p, r = angles[name]
                new = [f"yaw_deg = {y:.5f}", f"pitch_deg = {p:.5f}", f"roll_deg = {r:.5f}"]
                if name in clocks:
                    new.append(f"clock_offset_s = {clocks[name]:.2f}  # measured by `cbh calibrate` (sky maps)")
                block = kept[:anchor] + new + kept[anchor:]
            result.append(ln)
            result.extend(block)
            i = j
            continue
        result.append(ln)
        i += 1
    return "\n".join(result) + "\n"
