"""Writing simulated shots to a folder (what ``cbh simulate`` produces).

Layout under ``out_dir``::

    <camera>/<camera>_<YYYYmmddTHHMMSS.fffZ>.jpg   each camera's frame, named by its time stamp
    truth/<YYYYmmddTHHMMSS.fffZ>.npz               <camera>_height_m (H, W) float32 [m above the
                                                   ENU origin, NaN = no cloud], <camera>_cloud_mask
                                                   (H, W) bool, for every camera; ground_shade
                                                   (n, n) float32 (1 shade, 0 sun, NaN night) and
                                                   ground_thickness on the station's ground grid
                                                   (ground_x_m, ground_y_m: cell centres, rows = y)
    truth/<YYYYmmddTHHMMSS.fffZ>.json              layers (advected), sun, per-camera capture times
"""
from __future__ import annotations

import json
from datetime import datetime
from pathlib import Path

import numpy as np

from cbh.sim.render import SimShot

__all__ = ["time_tag", "image_path", "write_shot"]


def time_tag(t: datetime) -> str:
    """``YYYYmmddTHHMMSS.fffZ`` of an aware UTC time (milliseconds)."""
    return t.strftime("%Y%m%dT%H%M%S") + f".{t.microsecond // 1000:03d}Z"


def image_path(out_dir: str | Path, camera: str, t: datetime) -> Path:
    return Path(out_dir) / camera / f"{camera}_{time_tag(t)}.jpg"


def write_shot(shot: SimShot, out_dir: str | Path, jpeg_quality: int = 92, ground: dict | None = None) -> dict[str, Path]:
    """Write a shot's JPEG images and its ground truth; returns the written paths by role.

    Images are stamped (named) with the nominal time: a camera with a clock offset captured
    later than its name says, as a real one would (the truth JSON has the real times).
    ``ground``: arrays of the scene's own shadow on the ground (``ground_shade``,
    ``ground_thickness`` on the station's ground grid, :func:`cbh.sim.ground.ground_shade`) and
    the grid's ``ground_x_m``/``ground_y_m``, added to the truth NPZ.
    """
    from cbh.imageio import encode_jpeg

    out = Path(out_dir)
    tag = time_tag(shot.time_utc)
    written: dict[str, Path] = {}
    for name, view in shot.views.items():
        p = image_path(out, name, view.stamp_utc)
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_bytes(encode_jpeg(view.image, jpeg_quality))
        written[name] = p
    truth_dir = out / "truth"
    truth_dir.mkdir(parents=True, exist_ok=True)
    arrays = {}
    for name, view in shot.views.items():
        arrays[f"{name}_height_m"] = view.height_m.astype(np.float32)
        arrays[f"{name}_cloud_mask"] = view.cloud_mask.astype(bool)
    arrays.update(ground or {})
    npz = truth_dir / f"{tag}.npz"
    np.savez_compressed(npz, **arrays)
    js = truth_dir / f"{tag}.json"
    js.write_text(json.dumps(shot.truth(), indent=1) + "\n")
    written["truth_npz"] = npz
    written["truth_json"] = js
    return written
