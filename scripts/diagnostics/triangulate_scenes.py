"""Sparse points of the gate scenes' training views: count, time and (where the full capture's COLMAP points
exist) depth agreement, per SIFT upsampling (table + JSON).

  python scripts/diagnostics/triangulate_scenes.py [--sift-upsample 1 2] [--out outputs/triangulation.json]

Runs exactly what training does (``sparse_points.triangulate_training_views`` with the default options but
``sift_upsample``, the LLFF near/far bounds, and for metric scenes the scene box), without the cache. For fern and
flower, whose folders hold COLMAP's points from all their photos, each observation is compared with the full
capture's point that projects within 1 px of it in the same view: the relative difference of their depths
(COLMAP's points are the better estimate, not an exact truth; a 1 px association also pairs neighbours at depth
edges).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from frugalnerf_ns.data.colmap_points import read_points3d_bin
from frugalnerf_ns.data.dataparsers.dtu import DTUDataParserConfig
from frugalnerf_ns.data.dataparsers.llff import LLFFDataParserConfig, load_poses_bounds
from frugalnerf_ns.data.sparse_points import TriangulationOptions, points_inside_box, triangulate_training_views
from frugalnerf_ns.geometry.camera_conventions import llff_to_opengl
from frugalnerf_ns.geometry.reprojection import project_to_camera

ROOT = Path(__file__).resolve().parents[2]
DATA = ROOT / ".." / "shared" / "data"
SCENES = {  # the quality gate's 2-view splits
    "fern": LLFFDataParserConfig(data=DATA / "llff/fern", downscale_factor=8, train_views=(6, 13)),
    "flower": LLFFDataParserConfig(data=DATA / "llff/flower", downscale_factor=8, train_views=(11, 22)),
    "horns": LLFFDataParserConfig(data=DATA / "llff/horns", downscale_factor=8, train_views=(20, 42)),
    "dtu_scan65": DTUDataParserConfig(data=DATA / "dtu/scan65", train_views=(22, 25)),
}


def depth_agreement(sparse, outputs, intrinsics, config) -> dict:
    """Relative depth difference of each observation from the full capture's COLMAP point within 1 px of it."""
    folder = Path(config.data)
    points_file = folder / "sparse" / "0" / "points3D.bin"
    if not points_file.is_file():
        return {}
    colmap = torch.from_numpy(read_points3d_bin(points_file)).double()
    poses, _ = load_poses_bounds(folder / "poses_bounds.npy")
    raw = torch.from_numpy(llff_to_opengl(poses[:, :, :4])).double()  # COLMAP's frame, like points3D
    scale = float(outputs.dataparser_scale)
    names = sorted(p.name for p in Path(outputs.image_filenames[0]).parent.iterdir())
    errors = []
    for view, filename in enumerate(outputs.image_filenames):
        frame = names.index(Path(filename).name)
        proj = project_to_camera(colmap, raw[frame].expand(len(colmap), 3, 4), intrinsics[view].expand(len(colmap), 4))
        pixels = torch.where(proj.in_front[:, None], proj.pixels, torch.full_like(proj.pixels, 1e9))
        truth = (colmap - raw[frame, :3, 3]).norm(dim=-1) * scale
        mine = sparse.view == view
        distance, nearest = torch.cdist(sparse.pixels[mine], pixels).min(dim=1)
        close = distance <= 1.0
        errors.append((sparse.depth[mine][close] - truth[nearest[close]]).abs() / truth[nearest[close]])
    error = torch.cat(errors)
    if error.numel() == 0:
        return {"compared": 0}
    return {"compared": int(error.numel()), "median_relative_depth_difference": float(error.median()),
            "p90_relative_depth_difference": float(error.quantile(0.9)),
            "fraction_above_10_percent": float((error > 0.1).double().mean())}


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sift-upsample", type=int, nargs="+", default=[1, 2])
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
        for upsample in args.sift_upsample:
            start = time.time()
            sparse = triangulate_training_views(images, cameras.camera_to_worlds.double(), intrinsics,
                                                TriangulationOptions(sift_upsample=upsample), bounds, progress=False)
            seconds = time.time() - start
            triangulated = sparse.num_points
            if metadata.get("ndc") is None:
                sparse = points_inside_box(sparse, outputs.scene_box.aabb)
            height, width = images[0].shape[:2]
            rows.append({"scene": name, "size": f"{width}x{height}", "sift_upsample": upsample, "triangulated": triangulated,
                         "kept": sparse.num_points, "seconds": seconds, **depth_agreement(sparse, outputs, intrinsics, config)})
    print("| scene | image size | SIFT upsample | triangulated | kept | seconds | compared with the full capture | "
          "median / p90 relative depth difference | above 10 % |\n|---|---|---|---|---|---|---|---|---|")
    for row in rows:
        agreement = "| | |"
        if row.get("compared"):
            agreement = (f"{row['median_relative_depth_difference']:.3f} / {row['p90_relative_depth_difference']:.3f} | "
                         f"{row['fraction_above_10_percent']:.3f} |")
        print(f"| {row['scene']} | {row['size']} | {row['sift_upsample']} | {row['triangulated']} | {row['kept']} | "
              f"{row['seconds']:.2f} | {row.get('compared', '')} | {agreement}")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(rows, indent=2))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
