"""Cloud segmentation on a labelled image set: every registered method next to the fixed baseline.

Run: python benchmarks/segmentation.py IMAGES_DIR MASKS_DIR [--station S.toml --camera CAM]
     python benchmarks/segmentation.py --simulate OUT_DIR [--size 480]   (make a labelled set first)

Images (JPEG/PNG) and masks (PNG, non-zero = cloud) are matched by file stem. Every image is
segmented as ``cbh segment`` does it (without a station: the whole image is sky; with
``--station``: that camera's masks and geometry; pixels outside the usable sky are predicted
clear), with each method of :data:`cbh.pipeline.segment.SEGMENTERS` and with the published
fixed baseline NRBR = (B − R)/(B + R) < 0.15 (``nbr@0.15``). Printed per method: mean pixel
accuracy over images, pooled precision, recall, F1 and IoU of the cloud class, and the worst
image (lowest accuracy). ``--per-image`` adds one line per image and method.

``--simulate OUT_DIR`` renders a labelled set with :class:`cbh.sim.SkySimulator` (which knows
the true cloud mask): every scene preset × four camera colour responses (neutral, a blue cast,
a dark low-gamma camera, a warm over-exposed one), written as OUT_DIR/images/*.png and
OUT_DIR/masks/*.png (cloud = 255), with the simulated station as OUT_DIR/station.toml; it is
scored with that station (``cam1``) and then, if ``--no-station`` is given, as plain images.

With a station, pixels outside the station's usable sky (image circle, zenith limit,
obstacles, sun) are not scored; without one, every pixel is.
"""
from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

import numpy as np

RESPONSES = {  # name: (gain, gamma, (wb_red, wb_blue))
    "neutral": (1.0, 1.0, (1.0, 1.0)),
    "bluecast": (1.0, 1.0, (0.85, 1.25)),
    "dark-gamma": (0.6, 0.7, (1.0, 1.0)),
    "warm-bright": (1.4, 1.2, (1.15, 0.9)),
}
IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png")


def simulate_set(out: Path, size: int) -> tuple[Path, Path, Path]:
    """Render the labelled set; returns (images_dir, masks_dir, station_toml)."""
    import cv2

    from cbh.geometry.station import load_station
    from cbh.presets import list_scenes, station_path
    from cbh.sim import Imperfection, SkySimulator, load_scene

    st = load_station(station_path())
    img_dir, mask_dir = out / "images", out / "masks"
    img_dir.mkdir(parents=True, exist_ok=True)
    mask_dir.mkdir(parents=True, exist_ok=True)
    for name in list_scenes():
        scene = load_scene(name)
        for rname, (gain, gamma, wb) in RESPONSES.items():
            imp = {"cam1": Imperfection(camera="cam1", gain=gain, gamma=gamma, white_balance=wb)}
            sim = SkySimulator(st, dataclasses.replace(scene, imperfections=imp), size_px=size)
            v = sim.view("cam1")
            cv2.imwrite(str(img_dir / f"{name}-{rname}.png"), v.image)
            cv2.imwrite(str(mask_dir / f"{name}-{rname}.png"), np.where(v.cloud_mask, 255, 0).astype(np.uint8))
    station = out / "station.toml"
    station.write_text(sim.station.to_toml())
    return img_dir, mask_dir, station


def pairs(images: Path, masks: Path) -> list[tuple[Path, Path]]:
    """(image, mask) paths matched by stem, sorted."""
    found = {p.stem: p for p in masks.iterdir() if p.suffix.lower() == ".png"}
    out = [(p, found[p.stem]) for p in sorted(images.iterdir())
           if p.suffix.lower() in IMAGE_SUFFIXES and p.stem in found]
    return out


def score(pred: np.ndarray, truth: np.ndarray) -> tuple[float, int, int, int]:
    """(accuracy, true positives, predicted positives, true cloud pixels)."""
    tp = int(np.count_nonzero(pred & truth))
    return float(np.mean(pred == truth)), tp, int(np.count_nonzero(pred)), int(np.count_nonzero(truth))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("images", nargs="?", type=Path)
    ap.add_argument("masks", nargs="?", type=Path)
    ap.add_argument("--simulate", type=Path, help="render a simulated labelled set into this folder and score it")
    ap.add_argument("--size", type=int, default=480, help="--simulate: image size [px]")
    ap.add_argument("--station", help="station TOML or preset (apply its masks and geometry)")
    ap.add_argument("--camera", help="the station's camera that took the images")
    ap.add_argument("--no-station", action="store_true", help="--simulate: score as plain images (no geometry)")
    ap.add_argument("--per-image", action="store_true")
    args = ap.parse_args(argv)
    import cv2

    from cbh.actions.segment import segment_image
    from cbh.errors import CbhError
    from cbh.geometry.station import load_station
    from cbh.pipeline.config import PipelineConfig
    from cbh.pipeline.segment import SEGMENTERS
    from cbh.presets import station_path

    if args.simulate:
        args.images, args.masks, sim_station = simulate_set(args.simulate, args.size)
        if args.station is None and not args.no_station:
            args.station, args.camera = str(sim_station), "cam1"
    if args.images is None or args.masks is None:
        ap.error("give IMAGES_DIR MASKS_DIR, or --simulate OUT_DIR")
    station = load_station(station_path(args.station)) if args.station else None
    items = pairs(args.images, args.masks)
    if not items:
        print(f"no image in {args.images} has a mask of the same stem in {args.masks}", file=sys.stderr)
        return 2
    methods = list(SEGMENTERS) + ["nbr@0.15"]
    base = PipelineConfig.from_dict(station.sections.get("pipeline", {})) if station else PipelineConfig()
    stats = {m: {"acc": [], "tp": 0, "pp": 0, "tt": 0} for m in methods}
    for img_path, mask_path in items:
        img = cv2.imread(str(img_path), cv2.IMREAD_COLOR)
        truth = cv2.imread(str(mask_path), cv2.IMREAD_GRAYSCALE)
        if img is None or truth is None or truth.shape != img.shape[:2]:
            print(f"skipped {img_path.name}: unreadable, or mask size differs", file=sys.stderr)
            continue
        truth = truth > 0
        for m in methods:
            try:
                if m == "nbr@0.15":
                    cfg = base.replace(segmentation=dataclasses.replace(base.segmentation, method="nbr", threshold=0.15))
                else:
                    cfg = base.replace(segmentation=dataclasses.replace(base.segmentation, method=m))
                seg = segment_image(img, station, args.camera, None, cfg, what=img_path.name)
            except CbhError as exc:
                print(f"skipped {img_path.name}: {exc}", file=sys.stderr)
                break
            scored = seg.usable if station is not None else np.ones(truth.shape, bool)
            acc, tp, pp, tt = score(seg.cloud[scored], truth[scored])
            s = stats[m]
            s["acc"].append((acc, img_path.name))
            s["tp"] += tp
            s["pp"] += pp
            s["tt"] += tt
            if args.per_image:
                print(f"  {img_path.name:40s} {m:14s} acc {100 * acc:6.2f} %")
    n = len(stats[methods[0]]["acc"])
    print(f"{n} labelled images ({args.images})")
    print(f"{'method':14s} {'accuracy_%':>10s} {'precision_%':>11s} {'recall_%':>9s} {'F1':>6s} {'IoU':>6s}  worst image")
    for m in methods:
        s = stats[m]
        if not s["acc"]:
            continue
        p = s["tp"] / s["pp"] if s["pp"] else float("nan")
        r = s["tp"] / s["tt"] if s["tt"] else float("nan")
        f1 = 2 * p * r / (p + r) if p + r > 0 else float("nan")
        iou = s["tp"] / (s["pp"] + s["tt"] - s["tp"]) if s["pp"] + s["tt"] - s["tp"] else float("nan")
        worst = min(s["acc"])
        mean = float(np.mean([a for a, _ in s["acc"]]))
        print(f"{m:14s} {100 * mean:10.2f} {100 * p:11.2f} {100 * r:9.2f} {100 * f1:6.1f} {100 * iou:6.1f}  "
              f"{worst[1]} ({100 * worst[0]:.1f} %)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
