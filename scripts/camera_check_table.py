"""The camera check on every shared scene as published and on deliberately broken copies of it.

    python scripts/camera_check_table.py [--out docs/notes/camera_check.json] [--scenes fern bird ...]

Each scene's training split is read by its parser (the images training reads, the cameras as read); the broken
copies change one thing each: the focal length x0.8 and x1.25, the principal point moved by 10 % of the width, the
poses' camera axes read in the other convention (OpenCV's as OpenGL's), the images turned by 90 degrees (the
cameras kept), the poses of another scene. Prints a Markdown table and writes the JSON record.
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path
from typing import Dict, List, Tuple

import numpy as np
import torch
from PIL import Image

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data"
SCENES: Dict[str, Tuple[str, Dict]] = {
    "fern": ("llff/fern", {}),
    "flower": ("llff/flower", {}),
    "horns": ("llff/horns", {}),
    "fortress": ("llff/fortress", {}),
    "dtu_scan65": ("dtu/scan65", {"train_views": (22, 25, 28)}),
    "juice_box_narrow": ("captures/juice_box", {"train_views": (13, 17, 21), "test_views": (14, 15, 16, 18, 19, 20)}),
    "juice_box_wide": ("captures/juice_box", {"train_views": (45, 13, 29, 46), "test_views": (14, 30)}),
    "bird": ("captures/bird", {"train_views": (0, 23, 46), "test_views": (12, 35)}),
}
OTHER = {"fern": "flower", "flower": "horns", "horns": "fern", "fortress": "fern", "dtu_scan65": "bird",
         "juice_box_narrow": "bird", "juice_box_wide": "dtu_scan65", "bird": "juice_box_narrow"}


def training_split(name: str):
    """(uint8 images, camera-to-worlds, intrinsics) of the scene's training split as its parser reads it."""
    from frugalnerf_ns.data.dataparsers.auto import AutoDataParserConfig

    folder, options = SCENES[name]
    outputs = AutoDataParserConfig(data=DATA / folder, **options).setup().get_dataparser_outputs("train")
    cams = outputs.cameras
    images = [np.asarray(Image.open(p).convert("RGB")) for p in outputs.image_filenames]
    intrinsics = torch.cat([cams.fx, cams.fy, cams.cx, cams.cy], dim=1).double()
    return images, cams.camera_to_worlds.double(), intrinsics


def broken_copies(name: str, images, c2w, intrinsics, other_c2w) -> List[Tuple[str, list, torch.Tensor, torch.Tensor]]:
    width = images[0].shape[1]
    rows = [("as published", images, c2w, intrinsics)]
    for factor in (0.8, 1.25):
        k = intrinsics.clone()
        k[:, :2] *= factor
        rows.append((f"focal x{factor:g}", images, c2w, k))
    k = intrinsics.clone()
    k[:, 2] += 0.1 * width
    rows.append(("principal point +10% of the width", images, c2w, k))
    flipped = c2w.clone()
    flipped[:, :3, 1:3] *= -1
    rows.append(("OpenCV axes read as OpenGL", images, flipped, intrinsics))
    rows.append(("images turned 90 degrees", [np.ascontiguousarray(np.rot90(i)) for i in images], c2w, intrinsics))
    count = c2w.shape[0]
    others = other_c2w[:count] if other_c2w.shape[0] >= count else torch.cat([other_c2w] * count)[:count]
    rows.append(("poses of another scene", images, others, intrinsics))
    return rows


COPIES = ("as published", "focal x0.8", "focal x1.25", "principal point +10% of the width", "OpenCV axes read as OpenGL",
          "images turned 90 degrees", "poses of another scene")


def page_table(record: Dict) -> str:
    """The user page's rows (docs/data.md): each scene's copies, the verdict and the median error."""
    rows = []
    for name, scene in record["scenes"].items():
        views = " ".join(map(str, scene["options"].get("train_views", []))) or "paper split"
        cells = []
        for copy in COPIES:
            check = scene["copies"][copy]
            verdict = "flagged" if check["flagged"] else ("passes" if check["judged"] else "no verdict")
            cells.append(f"{verdict} ({check['median_error']:.2f} px)")
        rows.append(f"| {name} ({views}) | " + " | ".join(cells) + " |")
    return "\n".join(rows)


def main() -> None:
    from frugalnerf_ns.data.camera_check import check_cameras
    from frugalnerf_ns.data.sparse_points import TriangulationOptions

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenes", nargs="*", default=list(SCENES))
    parser.add_argument("--out", type=Path, default=ROOT / "docs" / "notes" / "camera_check.json")
    parser.add_argument("--sift-upsample", type=int, default=1,
                        help="SIFT on the images enlarged this many times (the options' default 1; frugalnerf-cpu: 2)")
    parser.add_argument("--page-table", action="store_true", help="print docs/data.md's rows from the record, check nothing")
    args = parser.parse_args()
    if args.page_table:
        print(page_table(json.loads(args.out.read_text())))
        return
    record = {"command": f"python scripts/camera_check_table.py --sift-upsample {args.sift_upsample}",
              "sift_upsample": args.sift_upsample, "machine": f"{platform.machine()}, torch {torch.__version__}",
              "scenes": {}}
    lines = ["| scene | copy | matches | points | median error (px) | in front | best focal (error) | best centre shift (error) | flagged |",
             "|---|---|---|---|---|---|---|---|---|"]
    splits = {}
    for name in args.scenes:
        splits[name] = training_split(name)
        splits.setdefault(OTHER[name], training_split(OTHER[name]))
    for name in args.scenes:
        images, c2w, intrinsics = splits[name]
        record["scenes"][name] = {"data": SCENES[name][0], "options": {k: list(v) for k, v in SCENES[name][1].items()},
                                  "size": list(images[0].shape[1::-1]), "copies": {}}
        for label, imgs, cams, k in broken_copies(name, images, c2w, intrinsics, splits[OTHER[name]][1]):
            start = time.perf_counter()
            check = check_cameras(imgs, cams, k, TriangulationOptions(sift_upsample=args.sift_upsample))
            row = {**check.to_dict(), "seconds": time.perf_counter() - start}
            record["scenes"][name]["copies"][label] = row
            lines.append(f"| {name} | {label} | {check.matches} | {check.points} | {check.median_error:.2f} | "
                         f"{100 * check.in_front:.0f}% | x{check.focal_scale:.2f} ({check.focal_error:.2f}) | "
                         f"{check.centre_shift[0]:+.2f}, {check.centre_shift[1]:+.2f} ({check.centre_error:.2f}) | {'**yes**' if check.flagged else ('no' if check.judged else 'no verdict')} |")
            print(lines[-1], flush=True)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(record, indent=1) + "\n")
    print("\n".join(lines))
    print(page_table(record))


if __name__ == "__main__":
    main()
