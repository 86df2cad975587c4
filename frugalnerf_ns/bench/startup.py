"""Start-up time against the number of training views: parsing, image loading, SIFT, matching and
triangulation (the sparse points of L_sd), each timed on its own, in one process, for each view count.

Matching joins each view with its nearest cameras (``TriangulationOptions.match_neighbors``), so the pairs
grow linearly with the views; ``--all-pairs-up-to N`` also times the matching start-up had before (pycolmap's
matcher on every pair) for view counts up to N, side by side.

Usage:
  frugalnerf-bench startup --data <nerf_synthetic/lego> [--views 2 8 30 100]
         [--all-pairs-up-to 30] [--out outputs/startup_benchmark.json]

Any layout frugal-auto reads works (the views are its --num-train-views); the issue's target is a Blender
scene at 400x400: at most linear growth and under 60 s for 100 views on 2 cores.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Dict, List, Optional

import numpy as np
import torch
from PIL import Image

from frugalnerf_ns.bench.report import markdown_table, write_report
from frugalnerf_ns.scoring.metrics import composite
from frugalnerf_ns.config_files import outputs_dir


def load_training_images(paths) -> List[np.ndarray]:
    """uint8 RGB as the datamanager hands them to SIFT (alpha composited on white)."""
    images = []
    for path in paths:
        with Image.open(path) as img:
            pixels = torch.from_numpy(np.asarray(img.convert("RGBA"), dtype=np.float32) / 255.0)
        rgb = composite(pixels[..., :3], pixels[..., 3:]).numpy()
        images.append(np.round(rgb * 255.0).astype(np.uint8))
    return images


def all_pairs_pycolmap(images: List[np.ndarray], max_features: int) -> int:
    """The matching start-up did before: pycolmap's extractor and matcher on every pair (timed by the caller)."""
    import pycolmap

    options = pycolmap.FeatureExtractionOptions()
    options.sift.max_num_features = max_features
    extractor = pycolmap.FeatureExtractor.create(options, pycolmap.Device.cpu)
    features = []
    for image in images:
        grey = np.asarray(image.astype(np.float32) @ [0.299, 0.587, 0.114])
        features.append(extractor.extract_from_uint8_array(np.ascontiguousarray(np.clip(grey, 0, 255).astype(np.uint8))))
    matcher = pycolmap.FeatureMatcher.create(pycolmap.FeatureMatchingOptions(), pycolmap.Device.cpu)
    pairs = 0
    for i in range(len(features)):
        for j in range(i + 1, len(features)):
            matcher.match(features[i][0], features[i][1], features[j][0], features[j][1])
            pairs += 1
    return pairs


def time_views(data: Path, views: int, all_pairs: bool) -> Dict[str, float]:
    from frugalnerf_ns.data.dataparsers.auto import AutoDataParserConfig
    from frugalnerf_ns.data.sparse_points import (
        TriangulationOptions,
        build_tracks,
        extract_sift,
        match_pairs,
        neighbour_pairs,
        triangulate_tracks,
    )

    row: Dict[str, float] = {"views": views}
    start = time.perf_counter()
    outputs = AutoDataParserConfig(data=data, num_train_views=views).setup().get_dataparser_outputs("train")
    row["parse_s"] = time.perf_counter() - start

    start = time.perf_counter()
    images = load_training_images(outputs.image_filenames)
    row["load_s"] = time.perf_counter() - start
    row["width"], row["height"] = images[0].shape[1], images[0].shape[0]

    options = TriangulationOptions()
    cameras = outputs.cameras
    c2w = cameras.camera_to_worlds.double()
    intrinsics = torch.cat([cameras.fx, cameras.fy, cameras.cx, cameras.cy], dim=-1).double()
    start = time.perf_counter()
    keypoints, descriptors = extract_sift(images, options.max_features)
    row["sift_s"] = time.perf_counter() - start
    row["features_per_view"] = float(np.mean([len(k) for k in keypoints]))

    start = time.perf_counter()
    pairs = neighbour_pairs(c2w, options.match_neighbors)
    matches = match_pairs(descriptors, pairs)
    row["match_s"] = time.perf_counter() - start
    row["pairs"] = len(pairs)

    start = time.perf_counter()
    tracks = build_tracks(matches, [len(k) for k in keypoints])
    near_far = (outputs.metadata or {}).get("near_far")
    sparse = triangulate_tracks(tracks, keypoints, c2w, intrinsics, options, None if near_far is None else tuple(near_far))
    row["triangulate_s"] = time.perf_counter() - start
    row["points"] = sparse.num_points
    row["total_s"] = sum(row[k] for k in ("parse_s", "load_s", "sift_s", "match_s", "triangulate_s"))
    row["total_per_view_s"] = row["total_s"] / views
    if all_pairs:
        start = time.perf_counter()
        row["before_pairs"] = all_pairs_pycolmap(images, options.max_features)
        row["before_sift_and_match_s"] = time.perf_counter() - start
    return row


def table(rows: List[Dict[str, float]]) -> str:
    def before(r: Dict[str, float]) -> str:
        return f"{r['before_sift_and_match_s']:.1f} ({r['before_pairs']} pairs)" if "before_pairs" in r else "-"

    return markdown_table(rows, [
        ("views", lambda r: r["views"]), ("size", lambda r: f"{r['width']}x{r['height']}"),
        ("parse s", lambda r: f"{r['parse_s']:.2f}"), ("load s", lambda r: f"{r['load_s']:.2f}"),
        ("SIFT s", lambda r: f"{r['sift_s']:.2f}"), ("pairs", lambda r: r["pairs"]),
        ("match s", lambda r: f"{r['match_s']:.2f}"), ("triangulate s", lambda r: f"{r['triangulate_s']:.2f}"),
        ("total s", lambda r: f"{r['total_s']:.1f}"), ("s/view", lambda r: f"{r['total_per_view_s']:.2f}"),
        ("points", lambda r: r["points"]), ("before: all pairs, SIFT + match s", before),
    ])


def main(argv: Optional[List[str]] = None) -> None:
    parser = argparse.ArgumentParser(prog="frugalnerf-bench startup", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, required=True, help="scene folder (any layout frugal-auto reads)")
    parser.add_argument("--views", type=int, nargs="+", default=[2, 8, 30, 100])
    parser.add_argument("--all-pairs-up-to", type=int, default=0, help="also time the old all-pairs matching up to N views")
    parser.add_argument("--out", type=Path, default=outputs_dir("startup_benchmark.json"))
    args = parser.parse_args(argv)

    from frugalnerf_ns.data.input_checks import DataError

    rows = []
    for views in args.views:
        try:
            rows.append(time_views(args.data, views, views <= args.all_pairs_up_to))
        except DataError as err:
            sys.exit(f"benchmark_startup: {err}")
        print(f"startup: {views} views: {rows[-1]['total_s']:.1f} s", flush=True)
    write_report("benchmark_startup", table(rows),
                 {"data": str(args.data), "threads": torch.get_num_threads(), "rows": rows}, args.out)
