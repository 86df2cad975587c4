"""How well the cameras of photos without poses (issue 33) agree with a posed scene's cameras: the training
views' pixels alone (the files and size the scene's parser trains on) go through
``photo_poses.estimate_cameras`` with the photos layout's defaults (no EXIF: the assumed field of view), the
test views are registered into that reconstruction, and everything is compared with the parser's cameras after
the similarity that best aligns the training cameras (``align_cameras``: two cameras suffice). Then the
start-up of a photos-only folder, first and cached.

Usage:
  frugalnerf-bench cameras [--data-root ../shared/data] [--cases fern-2v fern-3v ...]
         [--focal-factors 0.9 1.0 1.1] [--startup-photos <photos>] [--out outputs/photo_cameras.json]

Columns: seconds to estimate (SIFT, matching, verification, poses, bundle adjustment, registration); the focal
length against the parser's; the worst training pair's relative rotation and direction of travel (free of the
gauge); training and test cameras' rotation and centre errors after alignment, centres as a percentage of the
training cameras' spread (their mean distance to their centroid). The posed scenes' cameras come from COLMAP
on all of a scene's photos (LLFF: 20-62) or a calibration rig (DTU): the better estimate, not an exact truth.
"""

from __future__ import annotations

import argparse
import math
import shutil
import tempfile
import time
from pathlib import Path
from typing import Dict, List, Optional

import numpy as np
from PIL import Image

from frugalnerf_ns.bench.report import markdown_table, write_report
from frugalnerf_ns.bench.startup import load_training_images
from frugalnerf_ns.data.dataparsers.auto import AutoDataParserConfig
from frugalnerf_ns.data.input_checks import DataError
from frugalnerf_ns.data.photo_poses import PoseEstimationOptions, estimate_cameras
from frugalnerf_ns.geometry.camera_conventions import align_cameras, apply_similarity
from frugalnerf_ns.config_files import outputs_dir, shared_data


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


def aligned_errors(train_est, train_ref, est, ref, prefix: str) -> Dict[str, float]:
    """Rotation (deg) and centre errors (as a fraction of the training cameras' spread: their mean distance to
    their centroid) of cameras ``est`` against ``ref`` after the similarity that aligns the training cameras."""
    rotation, scale, translation = align_cameras(train_est, train_ref)
    moved = apply_similarity(est, rotation, scale, translation)
    spread = float(np.linalg.norm(train_ref[:, :3, 3] - train_ref[:, :3, 3].mean(0), axis=1).mean())
    rot = [rotation_degrees(m[:3, :3], r[:3, :3]) for m, r in zip(moved, ref)]
    centre = [float(np.linalg.norm(m[:3, 3] - r[:3, 3])) / spread for m, r in zip(moved, ref)]
    return {f"{prefix}_rotation_deg_median": float(np.median(rot)), f"{prefix}_rotation_deg_max": float(np.max(rot)),
            f"{prefix}_centre_median": float(np.median(centre)), f"{prefix}_centre_max": float(np.max(centre))}


CASES = {
    # name: (data folder under --data-root, parser options: training views by count or list, test views)
    **{f"{scene}-{n}v": (f"llff/{scene}", {"num_train_views": n}) for scene in ("fern", "flower", "horns") for n in (2, 3, 4)},
    "fern-3v-6-10-13": ("llff/fern", {"train_views": (6, 10, 13)}),
    "flower-3v-3-12-21": ("llff/flower", {"train_views": (3, 12, 21)}),
    "juice_box-3v": ("captures/juice_box", {"train_views": (13, 17, 21), "test_views": (14, 15, 16, 18, 19, 20)}),
    "juice_box-4v-wide": ("captures/juice_box", {"train_views": (45, 13, 29, 46)}),
    "bird-3v": ("captures/bird", {"train_views": (0, 23, 46), "test_views": (8, 15, 31, 38)}),
    "bird-4v": ("captures/bird", {"train_views": (0, 30, 60, 90), "test_views": (15, 45, 75)}),
    "dtu_scan65-3v": ("dtu/scan65", {"train_views": (22, 25, 28)}),
    "lego-8v": ("nerf_synthetic/lego", {"num_train_views": 8}),
}


def measure(data: Path, parser_options: Dict, options: PoseEstimationOptions, focal_factor: Optional[float] = None) -> Dict:
    """Cameras estimated from the pixels of a posed scene's training views (the files and size its parser
    trains on), test views registered, against the parser's cameras. ``focal_factor``: the focal length given
    (as EXIF would) at that multiple of the parser's and kept, instead of found from the photos."""
    parser = AutoDataParserConfig(data=data, **parser_options).setup()
    train, test = parser.get_dataparser_outputs("train"), parser.get_dataparser_outputs("test")
    # uint8 RGB as the datamanager hands them to SIFT (alpha composited on white).
    train_images, test_images = load_training_images(train.image_filenames), load_training_images(test.image_filenames)
    start = time.perf_counter()
    row: Dict = {"data": str(data), "train": [Path(f).stem for f in train.image_filenames],
                 "size": f"{train_images[0].shape[1]}x{train_images[0].shape[0]}"}
    published_focal = float(train.cameras.fx[0])
    given = None if focal_factor is None else focal_factor * published_focal
    try:
        cameras = estimate_cameras(train_images, [Path(f).name for f in train.image_filenames], given, options,
                                   test_images, [Path(f).name for f in test.image_filenames], unregistered_as_nan=True)
    except DataError as err:
        row.update({"seconds": time.perf_counter() - start, "error": str(err)})
        return row
    row["seconds"] = time.perf_counter() - start
    reference = train.cameras.camera_to_worlds.double().numpy()
    reference_test = test.cameras.camera_to_worlds.double().numpy()
    train_est = cameras.camera_to_worlds.numpy()
    test_est = cameras.test_camera_to_worlds.numpy()
    registered = np.isfinite(test_est).all(axis=(1, 2))
    row.update({
        "focal": cameras.focal, "published_focal": published_focal, "points": cameras.points.num_points,
        "reprojection_error_px": cameras.reprojection_error,
        "focal_error_pct": 100.0 * (cameras.focal / published_focal - 1.0),
        "test_registered": int(registered.sum()), "test_count": int(len(test_est)),
    })
    row.update(pair_errors(train_est, reference))
    row.update(aligned_errors(train_est, reference, train_est, reference, "train"))
    if registered.any():
        row.update(aligned_errors(train_est, reference, test_est[registered], reference_test[registered], "test"))
    return row


def startup_times(photos: List[Path], work: Path) -> Dict:
    """Seconds from a photos-only folder to the training cameras, first (estimating) and again (cached)."""
    folder = work / "photos"
    if folder.exists():
        shutil.rmtree(folder)
    folder.mkdir(parents=True)
    for photo in photos:
        shutil.copy(photo, folder / photo.name)
    times = []
    for _ in range(2):
        start = time.perf_counter()
        AutoDataParserConfig(data=folder).setup().get_dataparser_outputs("train")
        times.append(time.perf_counter() - start)
    with Image.open(photos[0]) as img:
        size = f"{img.size[0]}x{img.size[1]}"
    return {"photos": len(photos), "size": size, "first_s": times[0], "cached_s": times[1]}


def fmt(row: Dict, key: str, digits: int = 2, scale: float = 1.0) -> str:
    return "-" if key not in row else f"{scale * row[key]:.{digits}f}"


def main(argv: Optional[List[str]] = None) -> int:
    parser = argparse.ArgumentParser(prog="frugalnerf-bench cameras", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data-root", type=Path, default=shared_data())
    parser.add_argument("--cases", nargs="+", default=list(CASES), choices=list(CASES))
    parser.add_argument("--startup-photos", type=Path, nargs="*", default=None,
                        help="photos to time the start-up with (default: fern's images_4 views 1 6 13 19, 1008x756)")
    parser.add_argument("--focal-factors", type=float, nargs="*", default=None,
                        help="also measure each case with the focal length fixed at these multiples of the parser's")
    parser.add_argument("--out", type=Path, default=outputs_dir("photo_cameras.json"))
    args = parser.parse_args(argv)
    rows = []
    for name in args.cases:
        folder, parser_options = CASES[name]
        data = args.data_root / folder
        if not data.exists():
            print(f"frugalnerf-bench cameras: {data} is absent; {name} skipped")
            continue
        for factor in [None, *(args.focal_factors or [])]:
            label = name if factor is None else f"{name}, focal {factor:g}x"
            rows.append({"case": label, **measure(data, parser_options, PoseEstimationOptions(), factor)})
            print(f"  {label}: {rows[-1]['seconds']:.1f} s" + (f" ({rows[-1]['error']})" if "error" in rows[-1] else ""))
    columns = [
        ("case", lambda r: r["case"]), ("train views", lambda r: " ".join(r["train"])), ("size", lambda r: r["size"]),
        ("s", lambda r: f"{r['seconds']:.1f}"), ("points", lambda r: r.get("points", "-")),
        ("focal (parser's)", lambda r: "-" if "focal" not in r else
         f"{r['focal']:.0f} ({r['published_focal']:.0f}, {r['focal_error_pct']:+.1f}%)"),
        ("reproj. (px)", lambda r: fmt(r, "reprojection_error_px", 3)),
        ("pair rot / dir (deg)", lambda r: f"{fmt(r, 'pair_rotation_deg')} / {fmt(r, 'pair_direction_deg')}"),
        ("train rot median (deg)", lambda r: fmt(r, "train_rotation_deg_median")),
        ("train centre median / max (% spread)",
         lambda r: f"{fmt(r, 'train_centre_median', 1, 100)} / {fmt(r, 'train_centre_max', 1, 100)}"),
        ("test registered", lambda r: "-" if "test_count" not in r else f"{r['test_registered']}/{r['test_count']}"),
        ("test rot median / max (deg)", lambda r: f"{fmt(r, 'test_rotation_deg_median')} / {fmt(r, 'test_rotation_deg_max')}"),
        ("test centre median / max (% spread)",
         lambda r: f"{fmt(r, 'test_centre_median', 1, 100)} / {fmt(r, 'test_centre_max', 1, 100)}"),
        ("error", lambda r: r.get("error", "")),
    ]
    table = markdown_table(rows, columns)
    payload: Dict = {"cases": rows}
    photos = args.startup_photos
    if photos is None:
        fern = args.data_root / "llff" / "fern" / "images_4"
        photos = [sorted(fern.iterdir())[i] for i in (1, 6, 13, 19)] if fern.is_dir() else []
    if photos:
        with tempfile.TemporaryDirectory() as work:
            payload["startup"] = startup_times(list(photos), Path(work))
        st = payload["startup"]
        table += (f"\n\nStart-up, {st['photos']} photos at {st['size']} (folder to training cameras): "
                  f"{st['first_s']:.1f} s estimating, {st['cached_s']:.2f} s cached")
    write_report("benchmark_photo_cameras", table, payload, args.out)
    return 0
