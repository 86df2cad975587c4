"""Sparse points of the benchmark scenes' training views: count and time per scene (table + JSON).

  python scripts/diagnostics/triangulate_scenes.py [--out outputs/triangulation.json]

Runs exactly what training does (``sparse_points.triangulate_training_views`` with the default options, the
LLFF near/far bounds, and for metric scenes the scene box), without the cache.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from frugalnerf_ns.data.dataparsers.dtu import DTUDataParserConfig
from frugalnerf_ns.data.dataparsers.llff import LLFFDataParserConfig
from frugalnerf_ns.data.sparse_points import points_inside_box, triangulate_training_views

ROOT = Path(__file__).resolve().parents[2]
SCENES = {
    "fern": LLFFDataParserConfig(data=ROOT / "../shared/data/llff/fern", downscale_factor=8, train_views=(6, 13)),
    "dtu_scan65": DTUDataParserConfig(data=ROOT / "../shared/data/dtu/scan65", train_views=(22, 25)),
}


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, default=Path("outputs/triangulation.json"))
    args = parser.parse_args(argv)
    rows = []
    for name, config in SCENES.items():
        outputs = config.setup().get_dataparser_outputs("train")
        cameras = outputs.cameras
        images = [np.asarray(Image.open(f).convert("RGB")) for f in outputs.image_filenames]
        intrinsics = torch.stack([cameras.fx[:, 0], cameras.fy[:, 0], cameras.cx[:, 0], cameras.cy[:, 0]], -1).double()
        metadata = outputs.metadata or {}
        near_far = metadata.get("near_far")
        bounds = None if near_far is None else (float(near_far[0]), float(near_far[1]))
        start = time.time()
        sparse = triangulate_training_views(images, cameras.camera_to_worlds.double(), intrinsics, depth_bounds=bounds)
        seconds = time.time() - start
        triangulated = sparse.num_points
        if metadata.get("ndc") is None:
            sparse = points_inside_box(sparse, outputs.scene_box.aabb)
        height, width = images[0].shape[:2]
        rows.append({"scene": name, "size": f"{width}x{height}", "triangulated": triangulated, "kept": sparse.num_points, "seconds": seconds})
    print("| scene | image size | triangulated | kept | seconds |\n|---|---|---|---|---|")
    for row in rows:
        print(f"| {row['scene']} | {row['size']} | {row['triangulated']} | {row['kept']} | {row['seconds']:.2f} |")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(rows, indent=2))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
