"""Issue 10, cases 1, 7 and 9: recordings are never lost, exports never torn, folders recover."""
from __future__ import annotations

import csv
import errno
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from cbh.cli.main import main
from cbh.outputs.record import McapRecorder, open_session
from cbh.outputs.record.reader import check_mcap_file

from tests.faults.conftest import fill, frame, process_fn, t

SIZE = 160  # simulated image width [px]: a pair takes a fraction of a second


def _write_pairs(rec: McapRecorder, n: int, start_s: float = 0.0) -> None:
    proc = process_fn()
    for k in range(n):
        f1, f2 = frame("cam1", t(start_s + k), k), frame("cam2", t(start_s + k), k)
        rec.write((f1, f2), proc(f1, f2))


# --- 1. an existing --record path -----------------------------------------------------------

@pytest.mark.slow
def test_existing_record_path_is_refused_naming_overwrite(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert main(["run", "--size", str(SIZE), "--frames", "3", "-q", "--record", "x.mcap"]) == 0
    capsys.readouterr()
    rc = main(["run", "--size", str(SIZE), "--frames", "1", "-q", "--record", "x.mcap"])
    err = capsys.readouterr().err
    assert rc == 2 and "--overwrite" in err and err.count("cbh: error:") == 1
    assert open_session("x.mcap").pair_count == 3  # the first run's recording is intact
    assert main(["run", "--size", str(SIZE), "--frames", "1", "-q", "--record", "x.mcap", "--overwrite"]) == 0
    assert open_session("x.mcap").pair_count == 1


def test_default_record_name_is_never_reused(tmp_path, capsys, monkeypatch):
    """Two runs in the same second with the default name: the second gets a new name, printed."""
    from cbh.actions.run import build_run

    monkeypatch.chdir(tmp_path)
    a = build_run(record=True, frames=1, size_px=SIZE)
    b = build_run(record=True, frames=1, size_px=SIZE)
    try:
        assert a.recorder.path != b.recorder.path
        assert a.recorder.path.exists() and b.recorder.path.exists()
        if a.recorder.path.name[:-5] in b.recorder.path.name:  # same second: a note says so
            assert any(str(b.recorder.path) in n for n in b.notes)
    finally:
        for s in (a, b):
            for k in s.sinks:
                k.close()


def test_two_recorders_in_one_folder_at_the_same_second_never_share_a_file(tmp_path, unb_station):
    """Directory recordings are named by the first pair's time: two runs with the same time used
    to open the same file and corrupt each other. Files are created with O_EXCL now."""
    recs = [McapRecorder(tmp_path, unb_station, {}) for _ in range(2)]
    errors = []

    def go(r):
        try:
            _write_pairs(r, 10)
            r.close()
        except Exception as exc:  # pragma: no cover - reported below
            errors.append(exc)

    th = [threading.Thread(target=go, args=(r,)) for r in recs]
    for x in th:
        x.start()
    for x in th:
        x.join()
    assert not errors
    p1, p2 = recs[0].paths[0], recs[1].paths[0]
    assert p1 != p2
    for p in (p1, p2):
        assert open_session(p).pair_count == 10  # both complete, 20 of 20 pairs


def test_reprocess_never_writes_onto_its_input(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert main(["run", "--size", str(SIZE), "--frames", "2", "-q", "--record", "s.mcap"]) == 0
    # the new station carries its own [pipeline] table (the test is about the output path)
    (tmp_path / "new.toml").write_text(open_session("s.mcap").station_toml + "\n[pipeline]\n")
    before = (tmp_path / "s.mcap").read_bytes()
    capsys.readouterr()
    for extra in ([], ["--overwrite"]):
        rc = main(["replay", "s.mcap", "--reprocess", "--station", "new.toml", "--record", "s.mcap",
                   "--no-rerun", *extra])
        err = capsys.readouterr().err
        assert rc == 2 and ("being read" in err or "being reprocessed" in err), err
    assert (tmp_path / "s.mcap").read_bytes() == before
    # through another name for the same file too
    os.link(tmp_path / "s.mcap", tmp_path / "alias.mcap")
    rc = main(["replay", "s.mcap", "--reprocess", "--station", "new.toml", "--record", "alias.mcap",
               "--no-rerun", "--overwrite"])
    assert rc == 2 and (tmp_path / "s.mcap").read_bytes() == before


# --- 7. CSV on a full disk ------------------------------------------------------------------

def _read_csv_rows(path: Path) -> list[dict]:
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


def test_full_disk_never_leaves_a_torn_csv_row(tiny_tmpfs, unb_station):
    """A real 64 KiB tmpfs filled to a few hundred bytes: rows are written until the disk is
    full; the file then ends with the last complete row, which pandas reads as data."""
    import pandas as pd

    from cbh.outputs.export import COLUMNS, LayerExporter

    out = tiny_tmpfs / "layers.csv"
    exp = LayerExporter(out, unb_station)
    fill(tiny_tmpfs, 3000)
    proc = process_fn()
    written, err = 0, None
    for k in range(1000):
        f1, f2 = frame("cam1", t(k)), frame("cam2", t(k))
        try:
            exp.write((f1, f2), proc(f1, f2))
            written += 1
        except OSError as exc:
            err = exc
            break
    exp.close()
    assert err is not None and err.errno == errno.ENOSPC and written > 0
    data = out.read_bytes()
    assert data.endswith(b"\n")
    df = pd.read_csv(out)
    assert list(df.columns) == list(COLUMNS) and len(df) == written
    assert df["points"].notna().all() and df["cloud_base_height_m"].notna().all()


def test_torn_last_row_of_an_earlier_crash_is_repaired_on_open(tmp_path, unb_station, caplog):
    from cbh.outputs.export import LayerExporter

    out = tmp_path / "layers.csv"
    with LayerExporter(out, unb_station) as exp:
        proc = process_fn()
        for k in range(3):
            f1, f2 = frame("cam1", t(k)), frame("cam2", t(k))
            exp.write((f1, f2), proc(f1, f2))
    whole = out.read_bytes()
    out.write_bytes(whole + whole.splitlines(keepends=True)[-1][:17])  # a crash mid-row
    with caplog.at_level("WARNING"):
        with LayerExporter(out, unb_station) as exp:
            f1, f2 = frame("cam1", t(10)), frame("cam2", t(10))
            exp.write((f1, f2), process_fn()(f1, f2))
    assert "torn last row" in caplog.text
    rows = _read_csv_rows(out)
    assert len(rows) == 4 and all(None not in r.values() and "" not in (r["points"],) for r in rows)


def test_sink_error_on_a_full_disk_is_printed_once(tiny_tmpfs, capsys):
    fill(tiny_tmpfs, 400)
    rc = main(["run", "--size", str(SIZE), "--frames", "50", "-q", "--export", str(tiny_tmpfs / "l.csv")])
    err = capsys.readouterr().err
    assert rc == 2 and "disk full" in err
    assert len([ln for ln in err.splitlines() if "disk full" in ln]) == 1, err


# --- 9. recovery ----------------------------------------------------------------------------

def test_folder_with_a_truncated_file_is_read_around_it(tmp_path, unb_station, caplog, capsys):
    d = tmp_path / "rec"
    r = McapRecorder(d, unb_station, {}, rotate_s=5)
    _write_pairs(r, 15)  # 3 files of 5 pairs
    r.close()
    files = sorted(d.glob("*.mcap"))
    assert len(files) == 3
    with open(files[1], "r+b") as fh:  # the writer of the middle file was killed mid-pair
        fh.truncate(files[1].stat().st_size * 2 // 5)
    (d / "empty.mcap").write_bytes(b"")  # a run killed before its first byte
    with caplog.at_level("WARNING"):
        s = open_session(d)
        n = sum(1 for _ in s.pairs(layers_only=True))
    assert 10 <= n < 15  # both intact files and the complete pairs of the torn one
    assert "truncated" in caplog.text and "empty.mcap: skipped" in caplog.text
    capsys.readouterr()
    assert main(["export", str(d), "--out", str(tmp_path / "o.csv")]) == 0
    assert len(_read_csv_rows(tmp_path / "o.csv")) == n
    assert main(["inspect", str(d)]) == 0
    assert main(["replay", str(d), "--rerun", "save", str(tmp_path / "o.rrd")]) == 0


@pytest.mark.slow
def test_sighup_finalizes_the_recording(tmp_path):
    out = tmp_path / "hup.mcap"
    cmd = [str(Path(sys.executable).with_name("cbh")), "run", "--size", str(SIZE), "--realtime", "--cadence-s", "0.5",
           "--duration", "120", "-q", "--record", str(out)]
    p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=tmp_path)
    try:
        deadline = time.monotonic() + 90
        while time.monotonic() < deadline and (not out.exists() or out.stat().st_size < 20_000):
            time.sleep(0.2)
        assert out.exists() and out.stat().st_size >= 20_000, "no pair recorded"
        p.send_signal(signal.SIGHUP)
        so, se = p.communicate(timeout=60)
    finally:
        if p.poll() is None:
            p.kill()
    assert p.returncode == 0, se
    assert "stopped: SIGHUP" in so
    check_mcap_file(out)  # footer written: finalized
    assert open_session(out).pair_count >= 1


@pytest.mark.slow
def test_run_that_processes_no_pair_says_so_and_fails(camera, capsys):
    cam = camera("404")
    rc = main(["run", "--station", "unb-lea", "--source", f"cam1={cam.url}", "--source", f"cam2={cam.url}",
               "--duration", "1.5", "-q"])
    err = capsys.readouterr().err
    assert rc == 2
    lines = [ln for ln in err.splitlines() if ln.startswith("cbh: error:")]
    assert len(lines) == 1 and "no pair processed" in lines[0] and "HTTP 404" in lines[0], err
