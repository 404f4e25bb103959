"""Every usage error and bad input ends as ONE line ``cbh: error: …`` on stderr, exit code 2,
printed once, never a traceback (issue 10, point 8)."""
from __future__ import annotations

import errno
import os
import subprocess
import sys

import pytest

from cbh.cli.main import main

from .conftest import REPO

STATION = str(REPO / "configs" / "unb-lea.toml")


def one_error_line(err: str) -> str:
    """The single ``cbh: error:`` line of a stderr text (asserts there is exactly one, and nothing else)."""
    lines = [l for l in err.splitlines() if l.strip()]
    assert len(lines) == 1, err
    assert lines[0].startswith("cbh: error: ") and "Traceback" not in err, err
    return lines[0]


@pytest.mark.parametrize("args, says", [
    (["run", "--frames", "abc"], "'--frames'"),
    (["pair"], "Missing argument"),
    (["nosuchcommand"], "No such command 'nosuchcommand'"),
    (["run", "--bogus"], "No such option: --bogus"),
    (["simulate", "--out", "x", "--frames", "1.5"], "'--frames'"),
])
def test_usage_errors_are_one_line_exit_2(args, says, capsys):
    assert main(args) == 2
    out, err = capsys.readouterr()
    assert says in one_error_line(err) and out == ""


def test_the_installed_console_script_prints_usage_errors_once(tmp_path):
    """The real entry point (typer may bundle its own click: its exceptions are caught too)."""
    exe = os.path.join(os.path.dirname(sys.executable), "cbh")
    if not os.path.exists(exe):
        pytest.skip("the cbh console script is not installed beside this Python")
    r = subprocess.run([exe, "run", "--frames", "abc"], capture_output=True, text=True, cwd=tmp_path, timeout=60)
    assert r.returncode == 2 and "'--frames'" in one_error_line(r.stderr)


def test_non_utf8_csv_to_triangulate(tmp_path, capsys):
    bad = tmp_path / "latin1.csv"
    bad.write_bytes("x1,y1,x2,y2\n960,960,960,960 # höhe\n".encode("latin-1"))
    assert main(["triangulate", "--station", STATION, "--pixels", str(bad)]) == 2
    assert "not a UTF-8 text CSV" in one_error_line(capsys.readouterr().err)


def test_triangulate_with_true_heights_but_no_valid_row(tmp_path, capsys):
    """Identical pixels in both cameras: the rays meet below the station (invalid); the table is
    printed, then one line says why there are no metrics."""
    px = tmp_path / "p.csv"
    px.write_text("x1,y1,x2,y2,true_height_m\n960,960,960,960,100\n960,960,960,960,150\n")
    assert main(["triangulate", "--station", STATION, "--pixels", str(px)]) == 2
    out, err = capsys.readouterr()
    assert out.count("false") == 2 and "MAE" not in out
    assert "no MAE/MAPE/RMSE" in one_error_line(err)


def test_mask_out_pointing_at_a_directory(tmp_path, capsys):
    (tmp_path / "frames").mkdir()
    assert main(["mask", str(tmp_path / "frames"), "--camera", "cam1", "--out", str(tmp_path)]) == 2
    assert "is a directory" in one_error_line(capsys.readouterr().err)


def test_unwritable_rerun_save_path_fails_before_the_run(tmp_path, capsys):
    # /sys is read-only even for root; elsewhere a missing directory is as unwritable
    target = "/sys/cbh-test.rrd" if os.path.isdir("/sys") else str(tmp_path / "no" / "x.rrd")
    assert main(["run", "--frames", "1", "--size", "96", "-q", "--rerun", f"save={target}"]) == 2
    out, err = capsys.readouterr()
    assert target in one_error_line(err) and "processed" not in out


@pytest.mark.parametrize("cmd", [["simulate", "--out", "{tmp}/o"], ["run", "--frames", "1", "-q"]])
def test_huge_image_size_is_refused_before_allocating(cmd, tmp_path, capsys):
    args = [a.replace("{tmp}", str(tmp_path)) for a in cmd] + ["--size", "100000"]
    assert main(args) == 2  # 100000² px would be a 149 GiB allocation: refused up front
    assert "maximum of 8192 px" in one_error_line(capsys.readouterr().err)


def test_log_file_on_a_full_disk_warns_once_and_the_run_goes_on(capsys):
    if not os.path.exists("/dev/full"):
        pytest.skip("no /dev/full on this system")
    assert main(["--log-file", "/dev/full", "run", "--frames", "2", "--size", "96", "-q"]) == 0
    out, err = capsys.readouterr()
    assert "processed 2 pairs" in out
    lines = [l for l in err.splitlines() if l.strip() and "clock_unknown" not in l]  # (96 px: a clock the check cannot see)
    assert lines == ["cbh: warning: cannot write log file /dev/full (disk full); logging to it stopped"], err


def test_log_file_that_cannot_be_opened_exits_2_at_start(tmp_path, capsys):
    assert main(["--log-file", str(tmp_path / "no" / "run.jsonl"), "run", "--frames", "1", "-q"]) == 2
    out, err = capsys.readouterr()
    assert "cannot open log file" in one_error_line(err) and out == ""


def test_a_failing_sink_is_reported_once(tmp_path, capsys, monkeypatch):
    """A disk that fills during a run: the service stops, and the error is printed once (not also
    logged to stderr by the service)."""
    from cbh.outputs.export import LayerExporter

    def full(self, frames, result):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(LayerExporter, "write", full)
    out_csv = tmp_path / "layers.csv"
    assert main(["run", "--frames", "2", "--size", "96", "-q", "--export", str(out_csv)]) == 2
    line = one_error_line(capsys.readouterr().err)
    assert "disk full" in line and str(out_csv) in line


def test_greyscale_images_to_pair_are_refused(tmp_path, capsys):
    """A greyscale image cannot be segmented (the cloud test is the blue/red ratio): one line,
    where it used to give cloud fraction 1.00 (issue 10, point 5)."""
    import cv2
    import numpy as np

    from cbh.presets import station_path
    from cbh.geometry.station import load_station

    st = load_station(station_path("unb-lea")).scaled(96)
    (tmp_path / "station.toml").write_text(st.to_toml())
    grey = (np.random.default_rng(0).random((96, 96)) * 255).astype(np.uint8)
    cv2.imwrite(str(tmp_path / "g1.png"), grey)
    cv2.imwrite(str(tmp_path / "g2.png"), grey)
    assert main(["pair", str(tmp_path / "g1.png"), str(tmp_path / "g2.png"), "--station", str(tmp_path / "station.toml"),
                 "--time", "2024-06-21T14:00:00Z"]) == 2
    assert "greyscale" in one_error_line(capsys.readouterr().err)


def test_corrupt_video_source_is_one_line_without_ffmpeg_noise(tmp_path):
    """A video file FFmpeg cannot open printed FFmpeg's ``moov atom not found`` and OpenCV's
    ``[ WARN:0@…] cap.cpp`` lines around our error; now only the one ``cbh: error:`` line
    (a subprocess: FFmpeg writes to file descriptor 2 directly)."""
    bad = tmp_path / "cam.mp4"
    bad.write_bytes(b"not a video at all")
    env = {k: v for k, v in os.environ.items() if not k.startswith("OPENCV_")}
    r = subprocess.run([sys.executable, "-m", "cbh.cli.main", "run", "--source", f"cam1={bad}",
                        "--source", f"cam2={bad}", "-q"], capture_output=True, text=True, cwd=tmp_path,
                       timeout=120, env=env)
    assert r.returncode == 2 and "cannot open" in one_error_line(r.stderr)


@pytest.fixture
def two_images(tmp_path):
    """Two small colour sky images a.png and b.png in tmp_path."""
    import cv2
    import numpy as np

    rng = np.random.default_rng(0)
    paths = []
    for name in ("a", "b"):
        img = np.clip(rng.normal(150, 40, (48, 48, 3)), 0, 255).astype(np.uint8)
        img[..., 0] = 220  # blue sky with grey-white patches
        cv2.imwrite(str(tmp_path / f"{name}.png"), img)
        paths.append(tmp_path / f"{name}.png")
    return paths


@pytest.mark.parametrize("case, says", [
    ("out_is_the_input", "would overwrite the input image"),
    ("jpg", "written as PNG"),
    ("png_for_two", "2 images need a folder"),
    ("folder_of_the_inputs", "would overwrite the input image"),
])
def test_segment_out_that_would_lose_data_or_mislead_is_one_line(case, says, two_images, tmp_path, capsys):
    a, b = two_images
    args = {"out_is_the_input": [str(a), "--out", str(a)],
            "jpg": [str(a), "--out", str(tmp_path / "x.jpg")],
            "png_for_two": [str(a), str(b), "--out", str(tmp_path / "x.png")],
            "folder_of_the_inputs": [str(a), str(b), "--out", str(tmp_path)]}[case]
    before = {p: p.read_bytes() for p in two_images}
    assert main(["segment", *args]) == 2
    assert says in one_error_line(capsys.readouterr().err)
    assert {p: p.read_bytes() for p in two_images} == before  # the inputs are untouched
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.png", "b.png"]  # and nothing else written


def test_segment_one_image_into_an_existing_folder_writes_stem_png(two_images, tmp_path, capsys):
    a, _ = two_images
    (tmp_path / "masks").mkdir()
    assert main(["segment", str(a), "--out", str(tmp_path / "masks")]) == 0
    assert [p.name for p in (tmp_path / "masks").iterdir()] == ["a.png"]
    assert str(tmp_path / "masks" / "a.png") in capsys.readouterr().out


SAMPLE = REPO / "recordings" / "sample-two-layers.mcap"
UNWRITABLE = "/sys"  # read-only even for root


def _cannot_create_in(folder: str) -> bool:
    try:
        with open(os.path.join(folder, ".cbh-probe"), "wb"):
            pass
    except OSError:
        return os.path.isdir(folder)
    os.unlink(os.path.join(folder, ".cbh-probe"))
    return False


needs_read_only_sys = pytest.mark.skipif(not _cannot_create_in(UNWRITABLE), reason="needs a read-only /sys")


@pytest.mark.parametrize("fmt", ["netcdf", "parquet", "csv"])
def test_export_out_that_is_a_directory_says_so(fmt, tmp_path, capsys):
    """netCDF said "Permission denied" for a directory; the others "Is a directory"."""
    assert main(["export", str(SAMPLE), "-o", str(tmp_path), "-f", fmt]) == 2
    assert f"--out {tmp_path}: is a directory" in one_error_line(capsys.readouterr().err)
    assert list(tmp_path.iterdir()) == []


@needs_read_only_sys
@pytest.mark.parametrize("args", [["-o", f"{UNWRITABLE}/x.parquet"], ["-o", f"{UNWRITABLE}/x.nc"],
                                  ["-o", UNWRITABLE, "--daily", "-f", "parquet"],
                                  ["-o", f"{UNWRITABLE}/kernel", "--daily", "-f", "netcdf"]])
def test_export_write_errors_name_the_out_file_not_a_temporary_one(args, capsys):
    assert main(["export", str(SAMPLE), *args]) == 2
    line = one_error_line(capsys.readouterr().err)
    assert line.startswith(f"cbh: error: cannot write {args[1]}") and ".tmp" not in line, line
    assert line.endswith(": Permission denied") or line.endswith(": Operation not permitted"), line


@needs_read_only_sys
def test_write_records_names_its_out_file(tmp_path):
    """`cbh reprocess` writes its day files through write_records (temporary file + rename)."""
    from cbh.errors import RecordingError
    from cbh.outputs.export import session_records, write_records

    records, info = session_records([SAMPLE])
    for fmt, name in (("netcdf", "d.nc"), ("parquet", "d.parquet")):
        with pytest.raises(RecordingError) as e:
            write_records(records, info, f"{UNWRITABLE}/{name}", fmt)
        assert str(e.value).startswith(f"cannot write {UNWRITABLE}/{name}: ") and ".tmp" not in str(e.value)
    assert write_records(records, info, tmp_path / "d.nc", "netcdf").is_file()
    assert [p.name for p in tmp_path.iterdir()] == ["d.nc"]  # no temporary file left beside it


def test_quicklook_out_directory_or_without_suffix(tmp_path, capsys):
    """`-o DIR` wrote DIR.png and said "to DIR"; a name without suffix gets .png, and says so."""
    assert main(["quicklook", str(SAMPLE), "-o", str(tmp_path)]) == 2
    assert "is a directory" in one_error_line(capsys.readouterr().err)
    assert not tmp_path.with_suffix(".png").exists()
    assert main(["quicklook", str(SAMPLE), "-o", str(tmp_path / "q")]) == 0
    assert capsys.readouterr().out.strip().endswith(f"to {tmp_path / 'q.png'}")
    assert [p.name for p in tmp_path.iterdir()] == ["q.png"]


_WARN_THEN = """
import sys, warnings
import numpy as np
import cbh.actions.inspect as action
from cbh.errors import RecordingError

def inspect_session(session, repair):
    np.mean(np.array([]))  # RuntimeWarning: Mean of empty slice
    np.mean(np.array([]))  # the same warning twice: reported once
    if sys.argv[-1] == "fail":
        raise RecordingError("no pairs in the recording")
    return {{}}, ["fine"]

action.inspect_session = inspect_session
import cbh.outputs.record.describe as describe
describe.format_description = lambda d: "described"
from cbh.cli.main import main
sys.argv = ["cbh", "inspect", "x.mcap", "{how}"]
main()
"""


@pytest.mark.parametrize("how", ["fail", "succeed"])
def test_a_numpy_warning_never_stands_beside_the_one_line_error(how, tmp_path):
    """Python warnings are held during a command: after an error only the log file gets them;
    after success each distinct one is one line on stderr."""
    log = tmp_path / "log.jsonl"
    code = _WARN_THEN.format(how=how).replace('"cbh", "inspect"', f'"cbh", "--log-file", "{log}", "inspect"')
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=tmp_path, timeout=120)
    if how == "fail":
        assert r.returncode == 2
        assert one_error_line(r.stderr) == "cbh: error: no pairs in the recording"
    else:
        assert r.returncode == 0, r.stderr
        lines = r.stderr.strip().splitlines()
        assert all(ln.startswith("cbh: WARNING: RuntimeWarning: ") for ln in lines), r.stderr
        assert r.stderr.count("Mean of empty slice") == 1, r.stderr
    assert "Mean of empty slice" in log.read_text()  # kept for whoever reads the log
