"""Regenerate docs/wahrsis-height-map.jpg: the real WAHRSIS pair's dense height map over camera 1.

Run from the repository root: python scripts/make_docs_figures.py (reads ../shared/data).
"""
from __future__ import annotations

from datetime import datetime, timezone
from pathlib import Path

import cv2
import numpy as np

from cbh.imageio import read_image
from cbh.pipeline import Pipeline, PipelineConfig
from cbh.geometry.station import load_station

REPO = Path(__file__).resolve().parents[1]
DATA = REPO.parent / "shared" / "data" / "wahrsis-2015-10-29"
LO_M, HI_M = 300.0, 1500.0


def main():
    st = load_station(REPO / "configs" / "wahrsis-2015-10-29.toml")
    im1, _ = read_image(DATA / "2015-10-29-12-58-01-wahrsis3-med.jpg")
    im2, _ = read_image(DATA / "2015-10-29-12-58-01-wahrsis4-med.jpg")
    pipe = Pipeline(st, None, PipelineConfig.from_dict(st.sections.get("pipeline", {})))
    r = pipe.process(im1, im2, datetime(2015, 10, 29, 4, 58, 1, tzinfo=timezone.utc), channels="bgr")
    h = r.height_map
    known = np.isfinite(h)
    v = np.clip((np.nan_to_num(h, nan=LO_M) - LO_M) / (HI_M - LO_M), 0, 1)
    col = cv2.applyColorMap((v * 255).astype(np.uint8), cv2.COLORMAP_TURBO)
    over = np.where(known[..., None], (0.65 * col + 0.35 * im1).astype(np.uint8), im1)
    # crop to the image circle and shrink
    cx, cy = st.camera("wahrsis3").model.center_xy
    R = int(st.camera("wahrsis3").model.radius_px * 1.02)
    x0, y0 = int(cx) - R, max(int(cy) - R, 0)
    crop = lambda a: cv2.resize(a[y0 : int(cy) + R, x0 : int(cx) + R], (560, 560), interpolation=cv2.INTER_AREA)
    fig = cv2.hconcat([crop(im1), crop(over)])
    bar = cv2.applyColorMap(np.tile(np.linspace(0, 255, 400).astype(np.uint8), (14, 1)), cv2.COLORMAP_TURBO)
    legend = np.full((40, fig.shape[1], 3), 255, np.uint8)
    legend[13:27, 640:1040] = bar
    for x, txt in ((585, f"{LO_M:.0f} m"), (1048, f"{HI_M:.0f} m")):
        cv2.putText(legend, txt, (x, 26), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
    cv2.putText(legend, f"WAHRSIS3 + WAHRSIS4, 2015-10-29 04:58:01Z: {len(r.points)} points, "
                f"mean {r.points.height_m.mean():.0f} m", (10, 26), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
    out = REPO / "docs" / "wahrsis-height-map.jpg"
    cv2.imwrite(str(out), cv2.vconcat([fig, legend]), [cv2.IMWRITE_JPEG_QUALITY, 85])
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
