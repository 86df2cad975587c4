"""How well the cameras of photos without poses (issue 33) agree with a scene's published poses: LLFF scenes'
training views estimated from their pixels alone (``photo_poses.estimate_cameras``, the photos layout's
defaults: no EXIF, the assumed field of view), the test views registered into that reconstruction, then the
estimate moved onto the published cameras by the similarity that best aligns the training cameras
(``align_cameras``: two cameras suffice) and compared.

Usage:
  frugalnerf-bench cameras [--data-root ../shared/data] [--scenes fern flower horns] [--views 2 3 4]
         [--out outputs/photo_cameras.json]

Columns: seconds to estimate (SIFT, matching, verification, poses, bundle adjustment, registration); the focal
length against the published one; the worst training pair's relative rotation and direction of travel (no
alignment needed); the test views' rotation and centre errors after alignment, the centre error in units of
the training cameras' mean distance to their centroid. The published poses are COLMAP's from all of a scene's
photos (20-62), so they are the better estimate, not an exact truth.
"""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path
from typing import Dict, List, Optional

import numpy as np
from PIL import Image

from frugalnerf_ns.bench.report import markdown_table, write_report
from frugalnerf_ns.data.photo_poses import PoseEstimationOptions, estimate_cameras
from frugalnerf_ns.data.splits import every_nth, load_split_table, select_views
from frugalnerf_ns.geometry.camera_conventions import align_cameras, apply_similarity, llff_to_opengl
from frugalnerf_ns.tools.sweep.grid import ROOT


def rotation_degrees(a: np.ndarray, b: np.ndarray) -> float:
    return math.degrees(math.acos(float(np.clip((np.trace(a.T @ b) - 1.0) / 2.0, -1.0, 1.0))))


def direction_degrees(a: np.ndarray, b: np.ndarray) -> float:
    cos = float(a @ b) / max(float(np.linalg.norm(a) * np.linalg.norm(b)), 1e-300)
    return math.degrees(math.acos(float(np.clip(cos, -1.0, 1.0))))


def pair_errors(estimate: np.ndarray, reference: np.ndarray) -> Dict[str, float]:
    """Worst relative rotation error and worst error of the direction from one camera to the other (in the
    first camera's frame) over the pairs of training cameras: both free of the gauge."""
    rotation, direction = 0.0, 0.0
    for a in range(len(estimate)):
        for b in range(a + 1, len(estimate)):
            rel_est = estimate[a, :3, :3].T @ estimate[b, :3, :3]
            rel_ref = reference[a, :3, :3].T @ reference[b, :3, :3]
            rotation = max(rotation, rotation_degrees(rel_est, rel_ref))
            dir_est = estimate[a, :3, :3].T @ (estimate[b, :3, 3] - estimate[a, :3, 3])
            dir_ref = reference[a, :3, :3].T @ (reference[b, :3, 3] - reference[a, :3, 3])
            direction = max(direction, direction_degrees(dir_est, dir_ref))
    return {"pair_rotation_deg": rotation, "pair_direction_deg": direction}


def held_out_errors(train_est, train_ref, test_est, test_ref) -> Dict[str, float]:
    """Test cameras' rotation (deg) and centre errors (in units of the training cameras' spread) after the
    similarity that aligns the training cameras."""
    rotation, scale, translation = align_cameras(train_est, train_ref)
    moved = apply_similarity(test_est, rotation, scale, translation)
    spread = float(np.linalg.norm(train_ref[:, :3, 3] - train_ref[:, :3, 3].mean(0), axis=1).mean())
    rot = [rotation_degrees(m[:3, :3], r[:3, :3]) for m, r in zip(moved, test_ref)]
    centre = [float(np.linalg.norm(m[:3, 3] - r[:3, 3])) / spread for m, r in zip(moved, test_ref)]
    return {"test_rotation_deg_median": float(np.median(rot)), "test_rotation_deg_max": float(np.max(rot)),
            "test_centre_median": float(np.median(centre)), "test_centre_max": float(np.max(centre))}


def measure(scene: Path, num_views: int, options: PoseEstimationOptions) -> Dict:
    files = sorted(p for p in (scene / "images_8").iterdir() if p.suffix.lower() in (".png", ".jpg"))
    table = load_split_table()["llff"]
    split = select_views(len(files), every_nth(len(files), table["test_every"]), num_train_views=num_views,
                         scene_train_views=table["scenes"].get(scene.name), what=str(scene))
    load = lambda i: np.asarray(Image.open(files[i]).convert("RGB"))  # noqa: E731
    train_images, test_images = [load(i) for i in split.train], [load(i) for i in split.test]
    start = time.perf_counter()
    cameras = estimate_cameras(train_images, [files[i].name for i in split.train], None, options,
                               test_images, [files[i].name for i in split.test])
    seconds = time.perf_counter() - start
    poses = np.load(scene / "poses_bounds.npy")[:, :15].reshape(-1, 3, 5)
    reference = llff_to_opengl(poses[:, :, :4])
    published_focal = float(poses[0, 2, 4]) * train_images[0].shape[1] / float(poses[0, 1, 4])
    train_est = cameras.camera_to_worlds.numpy()
    row = {
        "scene": scene.name, "train": split.train, "test": split.test, "seconds": seconds,
        "focal": cameras.focal, "published_focal": published_focal, "points": cameras.points.num_points,
        "focal_error_pct": 100.0 * (cameras.focal / published_focal - 1.0),
    }
    row.update(pair_errors(train_est, reference[split.train]))
    row.update(held_out_errors(train_est, reference[split.train], cameras.test_camera_to_worlds.numpy(), reference[split.test]))
    return row


def main(argv: Optional[List[str]] = None) -> int:
    parser = argparse.ArgumentParser(prog="frugalnerf-bench cameras", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data-root", type=Path, default=ROOT.parent / "shared" / "data")
    parser.add_argument("--scenes", nargs="+", default=["fern", "flower", "horns"])
    parser.add_argument("--views", nargs="+", type=int, default=[2, 3, 4])
    parser.add_argument("--out", type=Path, default=ROOT / "outputs" / "photo_cameras.json")
    args = parser.parse_args(argv)
    rows = []
    for name in args.scenes:
        scene = args.data_root / "llff" / name
        if not (scene / "poses_bounds.npy").is_file():
            print(f"frugalnerf-bench cameras: {scene} has no poses_bounds.npy; skipped")
            continue
        for views in args.views:
            rows.append(measure(scene, views, PoseEstimationOptions()))
            print(f"  {name} {views} views: {rows[-1]['seconds']:.1f} s")
    columns = [
        ("scene", lambda r: r["scene"]), ("train views", lambda r: " ".join(map(str, r["train"]))),
        ("s", lambda r: f"{r['seconds']:.1f}"), ("points", lambda r: r["points"]),
        ("focal (published)", lambda r: f"{r['focal']:.0f} ({r['published_focal']:.0f}, {r['focal_error_pct']:+.1f}%)"),
        ("pair rot / dir (deg)", lambda r: f"{r['pair_rotation_deg']:.2f} / {r['pair_direction_deg']:.2f}"),
        ("test rot median / max (deg)", lambda r: f"{r['test_rotation_deg_median']:.2f} / {r['test_rotation_deg_max']:.2f}"),
        ("test centre median / max (spreads)", lambda r: f"{r['test_centre_median']:.2f} / {r['test_centre_max']:.2f}"),
    ]
    write_report("benchmark_photo_cameras", markdown_table(rows, columns), rows, args.out)
    return 0
