"""MCAP recorder → reader round trip, rotation, flush-per-pair and recovery of a killed writer."""
from __future__ import annotations

from dataclasses import replace

import os
import signal
import subprocess
import sys
from datetime import timedelta

import numpy as np
import pytest

from cbh.errors import RecordingError

from .conftest import REPO, small_station, synthetic_pair, write_session


@pytest.fixture(scope="module")
def station():
    return small_station()


@pytest.fixture(scope="module")
def session_file(tmp_path_factory, station):
    path = tmp_path_factory.mktemp("rec") / "s.mcap"
    rec, made = write_session(path, station, n=4)
    return path, made


def test_round_trip_gives_back_every_pair_exactly(session_file, station):
    from cbh.outputs.record import open_session

    path, made = session_file
    s = open_session(path)
    pairs = list(s.pairs())
    assert len(pairs) == len(made) == s.pair_count
    for p, (frames, res) in zip(pairs, made):
        r = p.result
        assert p.time_utc == res.time_utc and r.cameras == res.cameras
        # bit-exact doubles; a layer without altitude is recorded with height + station altitude
        want = [replace(l, altitude_m=l.height_m + station.altitude_m) for l in res.layers]
        assert [l.to_dict() for l in r.layers] == [l.to_dict() for l in want]
        assert p.altitude_m == [l.height_m + station.altitude_m for l in res.layers]
        np.testing.assert_array_equal(r.histogram.edges_m, res.histogram.edges_m)
        np.testing.assert_array_equal(r.histogram.counts, res.histogram.counts)
        np.testing.assert_array_equal(r.points.xyz_m, res.points.xyz_m)
        np.testing.assert_array_equal(r.points.miss_m, res.points.miss_m)
        np.testing.assert_array_equal(r.points.px1, res.points.px1)
        np.testing.assert_array_equal(r.points.px2, res.points.px2)
        np.testing.assert_array_equal(r.points.layer, res.points.layer)
        np.testing.assert_array_equal(r.height_map, res.height_map)  # NaN positions equal too
        for cam in res.cloud_masks:
            np.testing.assert_array_equal(r.cloud_masks[cam], res.cloud_masks[cam])
        assert r.cloud_fraction == res.cloud_fraction and r.timing_ms == res.timing_ms and r.flags == res.flags
        np.testing.assert_array_equal(r.matches["lk"], res.matches["lk"])
        for fr in frames:  # images are the bytes as received, not re-encoded
            img = p.images[fr.camera]
            assert img.data == fr.encoded and img.format == "jpeg" and img.time_utc == fr.time_utc
        f1, f2 = p.frames()
        assert f1.image.shape == frames[0].image.shape


def test_metadata_topics_and_status(session_file, station):
    from cbh.outputs.record import open_session
    from cbh.geometry.station import parse_station
    import tomllib

    path, made = session_file
    s = open_session(path)
    assert s.config == {"segment": {"method": "rbr", "threshold": 0.6}}
    assert s.station.name == station.name
    st2 = parse_station(tomllib.loads(s.station_toml))
    # parse_station re-orthonormalises rotations (SVD): equal to the last bit or two
    np.testing.assert_allclose(st2.cameras["cam2"].R_world_from_cam, station.cameras["cam2"].R_world_from_cam,
                               rtol=0, atol=1e-15)
    assert s.version and s.version != "unknown"
    topics = {t.topic: t for t in s.topics}
    for cam in ("cam1", "cam2"):
        assert topics[f"/{cam}/image/compressed"].schema == "foxglove.CompressedImage"
        assert topics[f"/{cam}/image/compressed"].count == 4
    assert topics["/pair/points"].schema == "foxglove.PointCloud"
    assert topics["/pair/height_map"].schema == "foxglove.RawImage"
    assert topics["/pair/layers"].schema == "cbh.PairLayers"
    assert topics["/service/status"].count == 1
    first, last = s.time_span
    assert first == made[0][1].time_utc and last == made[-1][1].time_utc + timedelta(seconds=10)
    (t, stats), = list(s.statuses())
    assert stats["pairs_dropped"] == 1 and stats["sources"]["cam2"] == "reconnecting"


def test_generic_protobuf_decoder_reads_every_message(session_file):
    """Foxglove-style generic decoding from the schemas in the file (no cbh code)."""
    from mcap.reader import make_reader
    from mcap_protobuf.decoder import DecoderFactory

    path, made = session_file
    with open(path, "rb") as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        seen = {}
        for schema, channel, message, decoded in reader.iter_decoded_messages():
            seen[channel.topic] = decoded
    assert len(seen) == 10  # 2 images, 2 masks, matches, points, height map, histogram, layers, status
    layers = seen["/pair/layers"]
    assert [l.height_m for l in layers.layers] == [l.height_m for l in made[-1][1].layers]
    assert seen["/pair/points"].point_stride == 36


def test_rotation_by_size_and_time(tmp_path, station):
    from cbh.outputs.record import open_session

    rec, made = write_session(tmp_path / "big.mcap", station, n=5, rotate_mb=0.001)
    assert len(rec.paths) >= 4 and rec.paths[0] == tmp_path / "big.mcap"
    assert rec.paths[1] == tmp_path / "big-001.mcap"
    s = open_session(rec.paths)
    assert [p.time_utc for p in s.pairs()] == [r.time_utc for _, r in made]
    d = tmp_path / "dir"
    rec2, made2 = write_session(d, station, n=5, rotate_s=25)  # pairs 10 s apart: 0,10,20 | 30,40
    names = [p.name for p in rec2.paths]
    assert names == ["unb-lea-20240301T120000Z.mcap", "unb-lea-20240301T120030Z.mcap"]
    assert open_session(d).pair_count == 5


def test_an_upsampled_height_map_is_recorded_at_its_own_size_and_read_back_exactly(tmp_path, station):
    """The pipeline's full-size height map is a 2× nearest upsample of its working-size map: it is
    recorded at the working size (a quarter of the bytes, 62 → 44 ms per 1920 px pair to write)
    and read back bit for bit; a map that is not an upsample is recorded as it is."""
    from dataclasses import replace

    from mcap.reader import make_reader

    from cbh.outputs.record import McapRecorder, open_session
    from cbh.outputs.record.writer import block_factor
    from cbh.result import Enlarged

    frames, res = synthetic_pair(station, 0)
    h, w = res.height_map.shape
    small = np.full((h // 2, w // 2), np.nan, np.float32)
    small[20:60, 25:75] = np.random.default_rng(1).normal(1500.0, 30.0, (40, 50))
    up = np.repeat(np.repeat(small, 2, axis=0), 2, axis=1)
    assert block_factor(up) == 2 and block_factor(res.height_map) == 1
    bumped = up.copy()
    bumped[41, 51] += 1.0  # one pixel off its block: not an upsample any more
    assert block_factor(bumped) == 1
    path = tmp_path / "hm.mcap"
    lazy = replace(res, height_map=Enlarged(small, w, h))  # as the pipeline hands it: enlarged only when read
    with McapRecorder(path, station, {}) as rec:
        for k, hm in enumerate((up, res.height_map, bumped)):
            rec.write(frames, replace(res, time_utc=res.time_utc + timedelta(seconds=10 * k), height_map=hm))
        lazy.time_utc = res.time_utc + timedelta(seconds=30)
        rec.write(frames, lazy)
    assert lazy.enlarged("height_map") is not None  # recorded from the small map: never enlarged
    with open(path, "rb") as fh:
        sizes = [len(m.data) for _, ch, m in make_reader(fh).iter_messages() if ch.topic == "/pair/height_map"]
    assert sizes[0] < 0.3 * sizes[1] and sizes[2] == sizes[1] and sizes[3] == sizes[0]
    pairs = list(open_session(path).pairs())
    assert pairs[0].result.enlarged("height_map").factor == 2  # read back small too, enlarged when read
    for p, want in zip(pairs, (up, res.height_map, bumped, up)):
        g = p.result.height_map
        assert g.shape == want.shape and g.dtype == np.float32
        np.testing.assert_array_equal(g.view(np.int32), want.view(np.int32))  # bit for bit, NaN included


def test_a_status_off_the_pairs_time_line_does_not_rotate_the_file(tmp_path, station):
    """Pairs carry the cameras' time; a status stamped years away (the wall clock of a machine
    whose cameras run on another clock) stays in the current file: it neither rotates it nor
    starts a file's time span (rotation stays on the pairs' 25 s)."""
    from datetime import timedelta

    from cbh.outputs.record import McapRecorder, open_session

    def session(path, status_first: bool):
        with McapRecorder(path, station, {}, rotate_s=25) as rec:
            off = synthetic_pair(station, 0)[1].time_utc + timedelta(days=900)
            if status_first:
                rec.write_status(off, {"event": {"event": "outage"}})
            for k in range(4):  # 0, 10, 20 s | 30 s
                frames, res = synthetic_pair(station, k)
                rec.write(frames, res)
                rec.write_status(off + timedelta(seconds=k), {"pairs_processed": k + 1})
        return rec

    for status_first in (False, True):
        path = tmp_path / f"s{int(status_first)}.mcap"
        rec = session(path, status_first)
        assert [p.name for p in rec.paths] == [path.name, f"{path.stem}-001.mcap"], status_first
        s = open_session(rec.paths)
        assert s.pair_count == 4 and len(list(s.statuses())) == 4 + status_first
        assert [len(list(open_session(p).pairs())) for p in rec.paths] == [3, 1]
    # a directory: the file is named after its first pair, not after a status written before it
    # (a camera down at start-up), and the status is kept
    rec = session(tmp_path / "dir", True)
    assert [p.name for p in rec.paths] == ["unb-lea-20240301T120000Z.mcap", "unb-lea-20240301T120030Z.mcap"]
    assert open_session(rec.paths[0]).metadata["session_start_utc"] == "2024-03-01T12:00:00Z"
    assert len(list(open_session(tmp_path / "dir").statuses())) == 5
    # statuses and no pair at all (the cameras never came up): still recorded
    with McapRecorder(tmp_path / "none", station, {}) as rec:
        rec.write_status(synthetic_pair(station, 0)[1].time_utc, {"event": {"event": "outage"}})
    assert len(rec.paths) == 1 and len(list(open_session(rec.paths[0]).statuses())) == 1


def test_frames_without_encoded_bytes_are_encoded_once(tmp_path, station):
    from cbh.outputs.record import McapRecorder, open_session

    frames, res = synthetic_pair(station, 0, encode=False)
    with McapRecorder(tmp_path / "x.mcap", station, {}) as rec:
        rec.write(frames, res)
    (p,) = list(open_session(tmp_path / "x.mcap").pairs())
    img = p.images["cam1"].decode()
    # JPEG q92 of a smooth image: mean error of a few grey levels at most
    assert np.abs(img.astype(int) - frames[0].image.astype(int)).mean() < 4


def test_foreign_and_truncated_files_give_one_line_errors(tmp_path, session_file):
    from cbh.outputs.record import open_session

    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"not an mcap at all" * 10)
    with pytest.raises(RecordingError, match="not an MCAP file"):
        open_session(junk)
    with pytest.raises(RecordingError, match="not found"):
        open_session(tmp_path / "missing.mcap")
    # A valid MCAP file that is not a cbh recording
    from mcap.writer import Writer

    other = tmp_path / "other.mcap"
    with open(other, "wb") as fh:
        w = Writer(fh)
        w.start()
        sid = w.register_schema("x", "jsonschema", b"{}")
        cid = w.register_channel("/x", "json", sid)
        w.add_message(cid, 1, b"{}", 1)
        w.finish()
    with pytest.raises(RecordingError, match="not a cbh recording"):
        open_session(other)
    path, _ = session_file
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    with pytest.raises(RecordingError, match="truncated.*--repair") as ei:
        open_session(cut)
    assert "\n" not in str(ei.value)


@pytest.mark.parametrize("fraction", [0.35, 0.8])
def test_recover_truncated_file_keeps_every_complete_pair(tmp_path, session_file, fraction):
    from cbh.outputs.record import open_session, recover

    path, made = session_file
    data = path.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: int(len(data) * fraction)])
    rep = recover(cut, tmp_path / "fixed.mcap")
    assert not rep.complete and 0 < rep.pairs < len(made)
    s = open_session(tmp_path / "fixed.mcap")
    got = list(s.pairs())
    assert len(got) == rep.pairs
    for p, (_, res) in zip(got, made):
        assert [l.height_m for l in p.result.layers] == [l.height_m for l in res.layers]
    # a complete file recovers to all pairs
    rep2 = recover(path, tmp_path / "same.mcap")
    assert rep2.complete and rep2.pairs == len(made)


KILL_SCRIPT = r"""
import sys, time
sys.path.insert(0, sys.argv[2])
from tests.conftest import small_station, synthetic_pair
from cbh.outputs.record import McapRecorder
st = small_station()
rec = McapRecorder(sys.argv[1], st, {"k": 1})
for k in range(1000):
    frames, res = synthetic_pair(st, k)
    rec.write(frames, res)
    print(k, flush=True)
    if k >= 2:
        time.sleep(0.2)
"""


@pytest.mark.slow
def test_sigkill_loses_at_most_the_pair_in_flight(tmp_path):
    from cbh.outputs.record import open_session, recover

    out = tmp_path / "killed.mcap"
    written = -1
    with subprocess.Popen([sys.executable, "-c", KILL_SCRIPT, str(out), str(REPO)], stdout=subprocess.PIPE,
                          text=True) as proc:
        for line in proc.stdout:
            written = int(line)
            if written >= 4:
                break
        os.kill(proc.pid, signal.SIGKILL)  # while it sleeps or writes pair 5
        proc.wait()
    assert written >= 4
    with pytest.raises(RecordingError, match="truncated"):
        open_session(out)
    rep = recover(out, tmp_path / "rec.mcap")
    # every pair whose write() returned is on disk; at most the one in flight is lost
    assert rep.pairs >= written + 1
    assert open_session(tmp_path / "rec.mcap").pair_count == rep.pairs


def test_bad_arguments(tmp_path, station):
    from cbh.errors import ConfigError
    from cbh.outputs.record import McapRecorder

    with pytest.raises(ConfigError, match="rotate_mb"):
        McapRecorder(tmp_path / "a.mcap", station, {}, rotate_mb=0)
    with pytest.raises(RecordingError, match="does not exist"):
        McapRecorder(tmp_path / "nodir" / "a.mcap", station, {})
    rec = McapRecorder(tmp_path / "empty.mcap", station, {})
    rec.close()
    from cbh.outputs.record import open_session

    s = open_session(tmp_path / "empty.mcap")
    assert s.pair_count == 0 and s.time_span is None
    with pytest.raises(RecordingError, match="closed"):
        rec.write(*synthetic_pair(station, 0))


def test_statuses_before_any_pair_reach_the_disk(tmp_path, station, monkeypatch):
    """A .mcap path writes a status at once (a crash before the first pair keeps the start-up
    outages); a directory holds them for its first pair's file name, at most 64; close()
    finishes the file even when writing the last statuses fails."""
    import cbh.outputs.record.writer as W
    from cbh.outputs.record import McapRecorder, open_session

    t = synthetic_pair(station, 0)[1].time_utc
    rec = McapRecorder(tmp_path / "a.mcap", station, {})
    size0 = (tmp_path / "a.mcap").stat().st_size
    rec.write_status(t, {"event": {"event": "outage"}})
    assert (tmp_path / "a.mcap").stat().st_size > size0  # flushed, not held
    rec.close()
    assert len(list(open_session(tmp_path / "a.mcap").statuses())) == 1

    d = McapRecorder(tmp_path / "dir", station, {})
    for k in range(63):
        d.write_status(t, {"n": k})
    assert not list((tmp_path / "dir").glob("*.mcap"))  # waiting for a pair to name the file
    d.write_status(t, {"n": 63})
    assert len(list((tmp_path / "dir").glob("*.mcap"))) == 1  # not without bound
    d.close()
    assert len(list(open_session(tmp_path / "dir").statuses())) == 64

    e = McapRecorder(tmp_path / "dir2", station, {})
    e.write_status(t, {"n": 0})
    monkeypatch.setattr(W.McapRecorder, "_flush", lambda self, f: (_ for _ in ()).throw(OSError(28, "No space left")))
    with pytest.raises(OSError):
        e.close()
    monkeypatch.undo()
    (f,) = list((tmp_path / "dir2").glob("*.mcap"))
    assert len(list(open_session(f).statuses())) == 1  # finished: summary and footer written


def test_a_height_map_edited_after_reading_is_recorded_as_edited(tmp_path, station):
    """Read once, the full-size map is the result's value: an edit to it (a user masking part of
    the sky) is what the recorder writes and what a copy or a pickle carries."""
    import copy
    import pickle
    from dataclasses import replace

    from cbh.outputs.record import McapRecorder, open_session
    from cbh.result import Enlarged

    frames, res = synthetic_pair(station, 0)
    h, w = res.height_map.shape
    small = np.full((h // 2, w // 2), 1500.0, np.float32)
    r = replace(res, height_map=Enlarged(small, w, h), cloud_masks={c: Enlarged(small > 0, w, h) for c in res.cameras})
    r.height_map[:10] = np.nan  # read (enlarged) and edited in place
    r.cloud_masks[res.cameras[0]][:4] = False
    assert r.enlarged("height_map") is None and r.enlarged("cloud_masks", res.cameras[0]) is None
    for other in (copy.copy(r), pickle.loads(pickle.dumps(r))):
        assert np.isnan(other.height_map[:10]).all() and not other.cloud_masks[res.cameras[0]][:4].any()
    with McapRecorder(tmp_path / "e.mcap", station, {}) as rec:
        rec.write(frames, r)
    got = next(open_session(tmp_path / "e.mcap").pairs()).result
    assert np.isnan(got.height_map[:10]).all() and (got.height_map[10:] == 1500.0).all()
    assert not got.cloud_masks[res.cameras[0]][:4].any() and got.cloud_masks[res.cameras[0]][4:].all()


def test_a_height_map_enlarged_by_four_is_recorded_small(tmp_path, station):
    """Any whole factor the pipeline hands over (4: a 3840 px camera at 960 px working size) is
    recorded at the working size and read back bit for bit; block_factor alone looks for 2 and 3."""
    from dataclasses import replace

    from mcap.reader import make_reader

    from cbh.outputs.record import McapRecorder, open_session
    from cbh.result import Enlarged

    frames, res = synthetic_pair(station, 0)
    h, w = res.height_map.shape
    small = np.random.default_rng(4).normal(2000.0, 50.0, (h // 4, w // 4)).astype(np.float32)
    small[:5] = np.nan
    with McapRecorder(tmp_path / "f4.mcap", station, {}) as rec:
        rec.write(frames, replace(res, height_map=Enlarged(small, w, h)))
    with open(tmp_path / "f4.mcap", "rb") as fh:
        size = [len(m.data) for _, ch, m in make_reader(fh).iter_messages() if ch.topic == "/pair/height_map"][0]
    assert size < small.nbytes + 1024  # the small map, not the full one
    got = next(open_session(tmp_path / "f4.mcap").pairs()).result.height_map
    np.testing.assert_array_equal(got, np.repeat(np.repeat(small, 4, axis=0), 4, axis=1))
