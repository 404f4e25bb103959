"""Soak test of ``cbh run``: full speed for a long time, resident memory (RSS) printed over time.

Runs the real command line in a subprocess (``cbh run --cadence-s 0 --record DIR --export
CSV``) and samples its RSS from ``/proc/PID/status``; the pairs processed so far are the rows
of the CSV export. It must stay flat: every queue and list in the service is bounded.

    python benchmarks/bench_soak.py                          # 3600 s, simulator at full speed
    python benchmarks/bench_soak.py --duration 600 --size 240
    python benchmarks/bench_soak.py --via mjpeg --fps 20     # live: loopback MJPEG cameras
    python benchmarks/bench_soak.py --rotate-s 600           # record with rotation

``--via sim``: the simulator source as fast as the pipeline takes frames (lossless; the case
that grew without bound before). ``--via mjpeg``: two simulated cameras served over loopback
HTTP (``python -m cbh.sim.camera_server``), frames dropped when processing falls behind.

Prints one line per sample (elapsed s, pairs, RSS MB) and at the end the RSS growth between
the end of the warm-up (first 20 % of the run) and the end, per hour and per pair.
"""
from __future__ import annotations

import argparse
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def rss_mb(pid: int) -> float | None:
    """Resident set size of a process [MB = 1e6 bytes], None once it has exited."""
    try:
        with open(f"/proc/{pid}/status") as fh:
            for line in fh:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) * 1024 / 1e6
    except OSError:
        return None
    return None


def count_rows(path: Path) -> int:
    """Pairs processed = data rows of the layer export with distinct times (a pair may have
    several layer rows)."""
    try:
        with open(path, "rb") as fh:
            fh.readline()
            times = {line.split(b",", 1)[0] for line in fh if line.endswith(b"\n")}
        return len(times)
    except OSError:
        return 0


def cbh_cmd() -> list[str]:
    exe = Path(sys.executable).with_name("cbh")
    return [str(exe)] if exe.exists() else [sys.executable, "-m", "cbh.cli.main"]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--duration", type=float, default=3600.0, help="run length [s] (default 3600)")
    ap.add_argument("--interval", type=float, default=None, help="seconds between RSS samples (default duration/30)")
    ap.add_argument("--size", type=int, default=240, help="image width [px] (small: many pairs per second)")
    ap.add_argument("--via", choices=("sim", "mjpeg"), default="sim", help="frame source")
    ap.add_argument("--fps", type=float, default=10.0, help="--via mjpeg: frames per second per camera")
    ap.add_argument("--rotate-s", type=float, default=None, help="rotate the MCAP recording every S seconds")
    ap.add_argument("--no-record", action="store_true", help="no MCAP recording (export only)")
    ap.add_argument("--keep", action="store_true", help="keep the output directory")
    a = ap.parse_args()
    interval = a.interval or max(5.0, a.duration / 30)

    work = Path(tempfile.mkdtemp(prefix="cbh-soak-"))
    server = None
    try:
        export = work / "layers.csv"
        cmd = cbh_cmd() + ["run", "--cadence-s", "0", "--duration", f"{a.duration:g}", "--export", str(export), "-q"]
        if not a.no_record:
            cmd += ["--record", str(work / "rec")]
            if a.rotate_s:
                cmd += ["--rotate-s", f"{a.rotate_s:g}"]
        if a.via == "sim":
            cmd += ["--size", str(a.size)]
        else:
            station = work / "station.toml"
            server = subprocess.Popen(
                [sys.executable, "-m", "cbh.sim.camera_server", "--size", str(a.size), "--fps", f"{a.fps:g}",
                 "--port", "0", "--write-station", str(station)],
                stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=work)
            urls = {}
            while len(urls) < 2:
                line = server.stdout.readline()
                if not line:
                    raise SystemExit("camera server did not start")
                m = re.match(r"(cam\d): (\S+)", line)
                if m:
                    urls[m.group(1)] = m.group(2)
            while not station.exists():
                time.sleep(0.1)
            cmd += ["--station", str(station)] + [f"--source={c}={u}" for c, u in urls.items()]
        print("running:", " ".join(cmd), flush=True)
        print(f"{'elapsed_s':>9} {'pairs':>7} {'rss_mb':>8}", flush=True)
        t0 = time.monotonic()
        proc = subprocess.Popen(cmd, cwd=work, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        samples = []
        next_t = t0 + min(interval, 5.0)
        while proc.poll() is None:
            time.sleep(max(0.0, min(1.0, next_t - time.monotonic())))
            if time.monotonic() < next_t:
                continue
            next_t += interval
            r = rss_mb(proc.pid)
            if r is None:
                break
            el = time.monotonic() - t0
            n = count_rows(export)
            samples.append((el, n, r))
            print(f"{el:9.0f} {n:7d} {r:8.1f}", flush=True)
        out, err = proc.communicate()
        print(out.strip())
        if proc.returncode != 0:
            print(err.strip()[-2000:], file=sys.stderr)
            return proc.returncode
        warm = [s for s in samples if s[0] >= 0.2 * a.duration] or samples
        if len(warm) >= 2:
            (t1, n1, r1), (t2, n2, r2) = warm[0], warm[-1]
            per_h = (r2 - r1) / max(t2 - t1, 1e-9) * 3600
            per_pair = (r2 - r1) * 1e6 / max(n2 - n1, 1) / 1e3
            print(f"RSS after warm-up {r1:.1f} MB at {t1:.0f} s ({n1} pairs) -> {r2:.1f} MB at {t2:.0f} s ({n2} pairs): "
                  f"{r2 - r1:+.1f} MB ({per_h:+.1f} MB/h, {per_pair:+.2f} KB/pair); "
                  f"max {max(s[2] for s in samples):.1f} MB; {n2 / t2:.2f} pairs/s")
        return 0
    finally:
        if server is not None:
            server.terminate()
            server.wait(timeout=10)
        if a.keep:
            print(f"outputs kept in {work}")
        else:
            shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    raise SystemExit(main())
