"""Check a DTU (IDR/NeuS) scene's camera conversion against the images themselves.

  python scripts/diagnostics/check_dtu_cameras.py [--data ../shared/data/dtu/scan65] [--views 22 25]

SIFT matches between two training views (pycolmap, no geometric verification) must lie on the epipolar
lines our converted cameras predict: a wrong axis convention, principal point or intrinsics scale moves
them by tens of pixels. Also prints where the triangulated points lie (inside the unit sphere for NeuS's
scale matrices) and the cameras' distances from the centre. Prints one table and writes nothing.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[2]


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, default=ROOT.parent / "shared" / "data" / "dtu" / "scan65")
    parser.add_argument("--views", type=int, nargs=2, default=[22, 25])
    args = parser.parse_args(argv)
    if not args.data.is_dir():
        raise SystemExit(f"check_dtu_cameras: error: {args.data} is not a folder")

    from PIL import Image

    from frugalnerf_ns.data.dataparsers.dtu import DTUDataParserConfig
    from frugalnerf_ns.data.sparse_points import (
        TriangulationOptions,
        build_tracks,
        extract_sift,
        match_pairs,
        opencv_projection_matrices,
        triangulate_tracks,
    )
    from frugalnerf_ns.geometry.epipolar import epipolar_distances, fundamental_from_projections

    outputs = DTUDataParserConfig(data=args.data, train_views=tuple(args.views)).setup().get_dataparser_outputs("train")
    cameras = outputs.cameras
    c2w = cameras.camera_to_worlds.double()
    intrinsics = torch.cat([cameras.fx, cameras.fy, cameras.cx, cameras.cy], -1).double()
    images = [np.asarray(Image.open(p).convert("RGB")) for p in outputs.image_filenames]
    keypoints, descriptors = extract_sift(images, 8192)
    matches = match_pairs(descriptors, [(0, 1)])[(0, 1)]
    projections = opencv_projection_matrices(c2w, intrinsics)
    f = fundamental_from_projections(projections[0], projections[1], c2w[0, :3, 3])
    distances = epipolar_distances(f, keypoints[0][matches[:, 0]], keypoints[1][matches[:, 1]])
    tracks = build_tracks({(0, 1): matches}, [len(k) for k in keypoints])
    sparse = triangulate_tracks(tracks, keypoints, c2w, intrinsics, TriangulationOptions())
    norms = sparse.points.norm(dim=-1)
    centers = c2w[:, :3, 3]
    angle = torch.rad2deg(torch.arccos(torch.nn.functional.cosine_similarity(centers[0], centers[1], dim=0)))
    print("| check | value |\n|---|---|")
    print(f"| views | {args.views[0]}, {args.views[1]} ({float(angle):.1f} deg apart seen from the centre) |")
    print(f"| camera distance from the centre | {', '.join(f'{float(d):.2f}' for d in centers.norm(dim=-1))} |")
    print(f"| SIFT features / matches | {', '.join(str(len(k)) for k in keypoints)} / {len(matches)} |")
    if len(matches):
        print(f"| epipolar distance of the matches (px): median, 90th pct | {float(distances.median()):.2f}, "
              f"{float(distances.quantile(0.9)):.2f} |")
        print(f"| matches within 2 px of their epipolar line | {float((distances < 2).double().mean()):.0%} |")
    print(f"| triangulated points kept | {sparse.points.shape[0]} |")
    if sparse.points.shape[0]:
        q = norms.quantile(torch.tensor([0.0, 0.5, 1.0], dtype=norms.dtype)).tolist()
        print(f"| their distance from the centre: min, median, max | {q[0]:.2f}, {q[1]:.2f}, {q[2]:.2f} |")


if __name__ == "__main__":
    main()
