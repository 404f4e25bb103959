"""Screenshot of cbh's default Rerun view (docs/rerun-default-view.jpg) from the sample recording.

    python scripts/make_rerun_screenshot.py [--recording recordings/sample-two-layers.mcap] [--out docs/rerun-default-view.jpg]
        [--site NAME=LAT,LON …] [--pyranometer FILE]

What it does, so that the README shows what a user sees:
1. replays the recording into an .rrd with the default blueprint (``cbh replay … --rerun save=…``);
2. opens the native Rerun viewer on it under a virtual X display (Xvfb, started here unless
   ``DISPLAY`` is set) with Vulkan on the CPU (Mesa lavapipe: ``WGPU_BACKEND=vulkan``; the GL
   fallback lacks the R32Float render target Rerun needs), with the pointer parked in a corner
   (python-xlib), so no hover tooltip covers the sky, and lets the viewer write its own screenshot
   (``rerun --screenshot-to``);
3. downsizes it to 1600 px wide as a JPEG.

Needs (Debian): xvfb, mesa-vulkan-drivers; (PyPI) python-xlib, optional. Exits 2 with one line if a
piece is missing.
"""
from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def _fail(msg: str) -> None:
    print(f"make_rerun_screenshot: error: {msg}", file=sys.stderr)
    sys.exit(2)


def _park_pointer(display: str, corner: tuple[int, int], stop: threading.Event) -> None:
    """Keep the pointer in a corner of the screen while the viewer runs (no hover tooltips).

    winit centres the window on the screen, where Xvfb also starts the pointer, so the pointer
    must be moved: python-xlib's XTEST motion does it (xdotool's move has no effect on this
    Xvfb); without python-xlib the screenshot may show one hover tooltip.
    """
    try:
        from Xlib import X, display as xdisplay
        from Xlib.ext import xtest
    except ImportError:
        print("make_rerun_screenshot: note: pip install python-xlib to park the pointer", file=sys.stderr)
        return
    d = xdisplay.Display(display)
    k = 0
    while not stop.is_set():  # real device motion (XTEST), so the viewer sees the pointer leave
        xtest.fake_input(d, X.MotionNotify, x=corner[0] - (k % 2), y=corner[1])
        d.sync()
        k += 1
        stop.wait(0.3)
    d.close()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--recording", default=str(REPO / "recordings" / "sample-two-layers.mcap"))
    ap.add_argument("--out", default=str(REPO / "docs" / "rerun-default-view.jpg"))
    ap.add_argument("--size", default="1600x1000", help="viewer window size (logical pixels)")
    ap.add_argument("--site", action="append", default=[], help="passed to `cbh replay --site` (the nowcast panels)")
    ap.add_argument("--pyranometer", default=None, help="passed to `cbh replay --pyranometer`")
    args = ap.parse_args()
    for tool in ("rerun", "cbh"):
        if not shutil.which(tool):
            _fail(f"`{tool}` is not on PATH (pip install -e . installs both)")
    with tempfile.TemporaryDirectory() as tmp:
        rrd = Path(tmp) / "view.rrd"
        shot = Path(tmp) / "shot.png"
        extra = [a for site in args.site for a in ("--site", site)]
        extra += ["--pyranometer", args.pyranometer] if args.pyranometer else []
        r = subprocess.run(["cbh", "replay", args.recording, "--rerun", f"save={rrd}", *extra], capture_output=True,
                           text=True)
        if r.returncode != 0:
            _fail(f"cbh replay failed: {r.stderr.strip()}")
        xvfb = None
        display = os.environ.get("DISPLAY")
        if not display:
            if not shutil.which("Xvfb"):
                _fail("no DISPLAY and no Xvfb (apt-get install xvfb mesa-vulkan-drivers)")
            display = ":97"
            w, h = (int(v) for v in args.size.split("x"))
            xvfb = subprocess.Popen(["Xvfb", display, "-screen", "0", f"{w}x{h}x24"],
                                    stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            time.sleep(1.5)
        stop = threading.Event()
        w, h = (int(v) for v in args.size.split("x"))
        parker = threading.Thread(target=_park_pointer, args=(display, (w - 1, h - 1), stop), daemon=True)
        parker.start()
        try:
            # scale factor 1: the window is exactly --size pixels, so the parked pointer is off the views
            env = dict(os.environ, DISPLAY=display, WGPU_BACKEND=os.environ.get("WGPU_BACKEND", "vulkan"),
                       WINIT_X11_SCALE_FACTOR="1")
            r = subprocess.run(["rerun", str(rrd), "--window-size", args.size, "--screenshot-to", str(shot)],
                               env=env, capture_output=True, text=True, timeout=300)
        finally:
            stop.set()
            if xvfb is not None:
                xvfb.terminate()
        if r.returncode != 0 or not shot.is_file():
            last = (r.stderr.strip().splitlines() or ["(no output)"])[-1]
            _fail(f"the viewer did not write a screenshot: {last}")
        import cv2

        img = cv2.imread(str(shot), cv2.IMREAD_COLOR)
        scale = 1600.0 / img.shape[1]
        if scale < 1.0:
            img = cv2.resize(img, (1600, round(img.shape[0] * scale)), interpolation=cv2.INTER_AREA)
        out = Path(args.out)
        out.parent.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(out), img, [cv2.IMWRITE_JPEG_QUALITY, 88])
        print(f"wrote {out} ({img.shape[1]}x{img.shape[0]})")


if __name__ == "__main__":
    main()
