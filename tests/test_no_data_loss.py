"""Issue 38: nothing lost, ever. Every command that writes a file, with its output pointed at each
of its own inputs, refuses in one line (exit 2) and leaves every input as it was; every writer
against a full disk fails in one line and leaves the older output whole.

The full disk is a real one where this machine lets a test mount a small tmpfs (root), and an
injected ENOSPC on every write into the output folder otherwise (Python-level writers only)."""
from __future__ import annotations

import builtins
import errno
import hashlib
import os
import shutil
import subprocess
from pathlib import Path

import pytest

from cbh.cli.main import main

from .conftest import REPO, SHARED

SAMPLE = REPO / "recordings" / "sample-two-layers.mcap"
BOARDS = SHARED / "data" / "chessboard-fisheye1"
CEIL = next((SHARED / "data" / "ceilometer-samples").glob("arm-*/*.nc"), None)
needs_shared = pytest.mark.skipif(not BOARDS.is_dir() or CEIL is None, reason="needs ../shared/data")


def _digest(p: Path) -> str:
    return hashlib.sha256(p.read_bytes()).hexdigest() if p.is_file() else "absent"


@pytest.fixture()
def inputs(tmp_path):
    """A folder of inputs: a recording, a ceilometer file, two chessboard images (links to the
    shared originals: an output over a link must not reach the original either), a station."""
    d = tmp_path / "in"
    d.mkdir()
    shutil.copy(SAMPLE, d / "rec.mcap")
    if CEIL is not None:
        (d / "ceil.nc").symlink_to(CEIL)
    for k in (1, 2):
        if (BOARDS / f"Fisheye1_{k}.jpg").is_file():
            (d / f"board{k}.jpg").symlink_to(BOARDS / f"Fisheye1_{k}.jpg")
    (d / "station.toml").write_text((REPO / "configs" / "unb-lea.toml").read_text())
    for k in (1, 2):  # a camera folder each, for `run`
        (d / f"c{k}").mkdir()
        if (BOARDS / "Fisheye1_1.jpg").is_file():
            (d / f"c{k}" / f"cam{k}_20240621T140000Z.jpg").symlink_to(BOARDS / "Fisheye1_1.jpg")
    (d / "c1" / "cam1_20240621T141000Z.png").write_bytes(b"\x89PNG an input mask-sized image")
    return d


def _commands(d: Path) -> list[tuple[str, list[str], list[Path]]]:
    """(name, argv with {OUT} for the output, the inputs it reads)."""
    rec, ceil, b1, b2, st = d / "rec.mcap", d / "ceil.nc", d / "board1.jpg", d / "board2.jpg", d / "station.toml"
    return [
        ("export layers", ["export", str(rec), "-o", "{OUT}"], [rec]),
        ("export metar", ["export", str(rec), "--product", "metar", "-o", "{OUT}"], [rec]),
        ("quicklook", ["quicklook", str(rec), "-o", "{OUT}"], [rec]),
        ("validate", ["validate", "--ceilometer", str(ceil), str(rec), "-o", "{OUT}"], [ceil, rec]),
        ("calibrate-lens", ["calibrate-lens", str(b1), str(b2), "--board", "6x8", "--square-mm", "30", "--out",
                            "{OUT}"], [b1, b2]),
        ("segment", ["segment", str(b1), "--out", "{OUT}"], [b1]),
        ("replay", ["replay", str(rec), "--rerun", "save", "{OUT}"], [rec]),
        ("mask", ["mask", str(d / "c1"), "--station", str(st), "--camera", "cam1", "--frames", "3",
                  "--out", "{OUT}"], [d / "c1" / "cam1_20240621T141000Z.png"]),
        ("reprocess", ["reprocess", "--station", str(st), "--source", f"cam1={d / 'c1'}", "--source",
                       f"cam2={d / 'c2'}", "--out", "{OUT}"], [d / "c1"]),
        ("run --export", ["run", "--station", str(st), "--source", f"cam1={d / 'c1'}", "--source",
                          f"cam2={d / 'c2'}", "--export", "{OUT}", "-q"], [d / "c1" / "cam1_20240621T140000Z.jpg"]),
    ]


@needs_shared
def test_no_command_writes_over_its_own_inputs(inputs, capsys):
    """Round 3: `calibrate-lens … --out IMG1.jpg` overwrote a chessboard image, `validate … -o REC.mcap`
    replaced the recording. Every output, pointed at every input (by another name: ./x, a link),
    is refused before anything is read, and no input changes."""
    every = sorted(p for p in inputs.rglob("*") if p.is_file())
    before = {p: _digest(p) for p in every}
    originals = {p: _digest(p.resolve()) for p in every}
    for name, argv, reads in _commands(inputs):
        for target in reads:
            for alias in (target, target.parent / "." / target.name):
                rc = main([a.replace("{OUT}", str(alias)) for a in argv])
                err = capsys.readouterr().err.strip().splitlines()
                assert rc == 2, (name, alias)
                assert len(err) == 1 and err[0].startswith("cbh: error:"), (name, err)
                # refused as an input, or (replay, segment) for a name no output of theirs can have
                assert any(m in err[0] for m in ("one of the command's own inputs", "must end in .rrd",
                                                 "is written as PNG", "would overwrite the input")), (name, err)
    assert {p: _digest(p) for p in every} == before
    assert {p: _digest(p.resolve()) for p in every} == originals


def _small_disk(tmp_path: Path, request):
    """A 256 kB tmpfs, unmounted after the test (None where mounting is not allowed)."""
    mnt = tmp_path / "small"
    mnt.mkdir()
    try:
        r = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=256k", "tmpfs", str(mnt)], capture_output=True)
    except OSError:
        return None
    if r.returncode != 0:
        return None
    request.addfinalizer(lambda: subprocess.run(["umount", str(mnt)], capture_output=True))
    return mnt


class _FullDisk:
    """Every write into ``folder`` through Python's open fails with ENOSPC after a few bytes."""

    def __init__(self, folder: Path, monkeypatch):
        real = builtins.open
        folder = str(folder.resolve())

        class Full:
            def __init__(self, f):
                self.f = f

            def write(self, data):
                self.f.write(data[:8])
                raise OSError(errno.ENOSPC, "No space left on device")

            def __getattr__(self, k):
                return getattr(self.f, k)

            def __enter__(self):
                return self

            def __exit__(self, *a):
                self.f.close()

        def fake(file, mode="r", *a, **k):
            f = real(file, mode, *a, **k)
            if any(c in mode for c in "wax") and str(Path(file).resolve()).startswith(folder):
                return Full(f)
            return f

        real_write = os.write

        def fake_write(fd, data):  # the unbuffered CSV writer's os.write on its own descriptor
            try:
                target = os.readlink(f"/proc/self/fd/{fd}")
            except OSError:
                target = ""
            if target.startswith(folder):
                raise OSError(errno.ENOSPC, "No space left on device")
            return real_write(fd, data)

        monkeypatch.setattr(builtins, "open", fake)
        monkeypatch.setattr(os, "write", fake_write)


@needs_shared
@pytest.mark.parametrize("name, argv, suffix", [
    ("export layers", ["export", "{REC}", "-o", "{OUT}"], ".csv"),
    pytest.param("export metar", ["export", "{REC}", "--product", "metar", "-o", "{OUT}"], ".csv",
                 marks=pytest.mark.slow),  # (ampycloud: 8 s)
    ("quicklook", ["quicklook", "{REC}", "-o", "{OUT}"], ".png"),
    ("export parquet", ["export", "{REC}", "-o", "{OUT}"], ".parquet"),
    ("export cl61", ["export", "{REC}", "--product", "cl61", "-o", "{OUT}"], ".nc"),
    ("validate", ["validate", "--ceilometer", "{CL61}", "{REC}", "-o", "{OUT}"], ".json"),
])
@pytest.mark.parametrize("mode", ["tmpfs", "injected"])
def test_a_full_disk_leaves_the_older_output_whole(inputs, tmp_path, monkeypatch, capsys, request, name, argv, suffix,
                                                   mode):
    """Round 3: `export … --out OLD.csv` on a full disk cut OLD.csv to a torn file. A writer that
    meets a full disk fails in one line (exit 2, naming the disk) and the file that was there is
    still the one that was there; the inputs too. (NetCDF said "Permission denied".)"""
    disk = _small_disk(tmp_path, request) if mode == "tmpfs" else None
    if mode == "tmpfs" and disk is None:
        pytest.skip("mounting a tmpfs is not allowed here (the injected mode runs)")
    if mode == "injected" and suffix in (".parquet", ".nc"):
        pytest.skip("pyarrow and the NetCDF library write below Python's open: a real full disk only")
    folder = disk if disk is not None else tmp_path / "out"
    folder.mkdir(exist_ok=True)
    old = folder / f"old{suffix}"
    old.write_bytes(b"the older output, whole\n")
    cl61 = inputs / "cl61.nc"  # a ceilometer file that overlaps the recording: its own CL61 export
    if "{CL61}" in argv:
        assert main(["export", str(inputs / "rec.mcap"), "--product", "cl61", "-o", str(cl61)]) == 0
        capsys.readouterr()
    if disk is not None:  # fill it
        for k, chunk in enumerate((4096, 1)):  # to the last byte
            try:
                with open(disk / f"fill{k}", "wb", buffering=0) as f:
                    while True:
                        f.write(b"\0" * chunk)
            except OSError:
                pass
    else:
        _FullDisk(folder, monkeypatch)
    before = {p: _digest(p) for p in inputs.iterdir()}
    rc = main([a.replace("{REC}", str(inputs / "rec.mcap")).replace("{CL61}", str(cl61))
               .replace("{OUT}", str(old)) for a in argv])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2, name
    assert err and "disk full" in err[-1].lower() and err[-1].startswith("cbh: error:"), err
    assert old.read_bytes() == b"the older output, whole\n"
    assert not [p for p in folder.iterdir() if p.name.startswith(".") and p.name.endswith(".tmp")]
    assert {p: _digest(p) for p in inputs.iterdir()} == before


@needs_shared
def test_validate_says_why_an_answer_is_empty(inputs, tmp_path, capsys):
    """Round 3: validate gave exit 0 and a report of nulls for times that do not overlap, read a
    NetCDF cut in half as profiles at 00:00 with base 0, and called a folder "not found". Each is
    one line and exit 2 now; an overlapping comparison counts hits, misses and false alarms."""
    half = tmp_path / "half.nc"
    data = (inputs / "ceil.nc").read_bytes()
    half.write_bytes(data[: len(data) // 2])
    rec = str(inputs / "rec.mcap")
    for ceil, says in ((inputs / "ceil.nc", "no overlap: the recording(s) span 2024-06-21T14:00:00Z"),
                       (half, "a truncated NetCDF file"), (tmp_path, "is a directory")):
        assert main(["validate", "--ceilometer", str(ceil), rec, "-o", str(tmp_path / "v.json")]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and says in err[0], err
    for bad in ("nan", "inf", "1e30", "0"):
        assert main(["validate", "--ceilometer", str(inputs / "ceil.nc"), rec, "-o", "v.json", "--match-s", bad]) == 2
        assert "--match-s" in capsys.readouterr().err
    cl61 = tmp_path / "cl61.nc"  # the recording's own CL61 export (the sky's lowest layer, every pair cloudy)
    assert main(["export", rec, "--product", "cl61", "-o", str(cl61)]) == 0
    assert main(["validate", "--ceilometer", str(cl61), rec, "-o", str(tmp_path / "v.json")]) == 0
    out = capsys.readouterr().out
    import json
    import re

    m = re.search(r"detection: (\d+) both cloudy, (\d+) missed .*?, (\d+) false alarms .*?, (\d+) both clear", out)
    assert m and sum(map(int, m.groups())) == 8, out  # every matched pair in one cell
    det = json.loads((tmp_path / "v.json").read_text())["detection"]
    assert det["hits"] + det["misses"] == 8 and det["false_alarms"] == det["both_clear"] == 0  # it is never clear


def test_run_names_a_silent_camera_and_refuses_a_borrowed_folder(tmp_path, capsys):
    """Round 3: a network camera with an empty folder, or cam2 pointed at cam1's folder, gave
    exit 0 and no word. The summary names the camera that delivered nothing; a folder holding
    only another camera's images is refused before the run."""
    from cbh.actions.simulate import simulate_to_folder

    out = tmp_path / "sim"
    for _ in simulate_to_folder(out, station="unb-lea-network", frames=3, size_px=160):
        pass
    (out / "empty").mkdir()
    st = str(out / "station.toml")
    assert main(["run", "--station", st, "--source", f"cam1={out / 'cam1'}", "--source", f"cam2={out / 'cam2'}",
                 "--source", f"cam3={out / 'empty'}", "-q"]) == 0
    assert "camera(s) cam3 delivered no frame" in capsys.readouterr().out
    assert main(["run", "--station", st, "--source", f"cam1={out / 'cam1'}", "--source", f"cam2={out / 'cam1'}",
                 "--source", f"cam3={out / 'cam3'}", "-q"]) == 2
    assert "holds cam1's images" in capsys.readouterr().err
    # one truncated cam3 frame: its time step goes on with cam1 and cam2 (it dropped all three)
    bad = sorted((out / "cam3").glob("*.jpg"))[1]
    bad.write_bytes(bad.read_bytes()[:2000])
    assert main(["run", "--station", st, "--source", f"cam1={out / 'cam1'}", "--source", f"cam2={out / 'cam2'}",
                 "--source", f"cam3={out / 'cam3'}", "-q"]) == 0
    text = capsys.readouterr().out
    assert "processed 3 pairs" in text and "unreadable frames skipped: cam3 1" in text, text
