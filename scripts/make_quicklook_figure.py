"""Regenerate docs/quicklook.png: the quicklook of a simulated two-layer sequence.

Runs the real chain: the simulator renders the two-layer scene (cumulus at 1200 m moving
(6, 2) m/s, altocumulus at 3500 m moving (-3, 8) m/s) every 20 s (40 pairs) at 640 px,
`cbh run` processes and records every pair, and `cbh quicklook` draws the recording.
Run from the repository root: python scripts/make_quicklook_figure.py [--pairs N]
(about 4 s per pair on a busy 2-core machine).
"""
from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

from cbh.cli.main import main as cbh

REPO = Path(__file__).resolve().parents[1]


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--pairs", type=int, default=40)
    ap.add_argument("--cadence-s", type=float, default=20.0)
    ap.add_argument("--out", type=Path, default=REPO / "docs" / "quicklook.png")
    a = ap.parse_args()
    with tempfile.TemporaryDirectory() as d:
        rec = Path(d) / "sim.mcap"
        rc = cbh(["run", "--station", "unb-lea", "--scene", "two-layers", "--size", "640",
                  "--cadence-s", f"{a.cadence_s:g}", "--frames", str(a.pairs), "--record", str(rec), "-q"])
        if rc:
            raise SystemExit(rc)
        rc = cbh(["quicklook", str(rec), "--out", str(a.out),
                  "--title", f"cbh quicklook — simulated two-layer sky (1200 m, 3500 m), {a.pairs} pairs "
                  f"{a.cadence_s:g} s apart"])
        raise SystemExit(rc)


if __name__ == "__main__":
    main()
