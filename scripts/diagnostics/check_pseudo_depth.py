"""Are the pseudo depths of cross-scale geometric adaptation right? Checked against COLMAP's points.

  python scripts/diagnostics/check_pseudo_depth.py <run>/config.yml [--max-points 4000]

For an LLFF run (poses_bounds.npy and sparse/0/points3D.bin from the full capture, all views): every COLMAP
point seen in front of a camera gives an independent depth along that camera's ray. At those pixels of the
training and test cameras the trained model renders each scale's depth; the adaptation then picks a scale
per ray as it does for novel rays (rendered colour warped into the nearest other training view, Eq. 6-8).
Printed per camera group: each scale's median relative depth error, how often each scale is the closest to
COLMAP's depth, how often the adaptation picks it, how often the pick is the closest scale, and the pseudo
depth's error beside the full scale's. If the pick is no closer to the truth than the full scale, L_geo has
no better depth to teach and cannot pay. Writes ``<run>/pseudo_depth_check.json``.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("config", type=Path)
    parser.add_argument("--max-points", type=int, default=4000, help="COLMAP points per camera group")
    args = parser.parse_args(argv)
    if not args.config.is_file():
        raise SystemExit(f"check_pseudo_depth: error: {args.config} is not a file (pass <run>/config.yml)")

    from nerfstudio.cameras.rays import RayBundle
    from nerfstudio.utils.eval_utils import eval_setup

    from frugalnerf_ns.geometry.camera_conventions import llff_to_opengl
    from frugalnerf_ns.data.colmap_points import read_points3d_bin
    from frugalnerf_ns.data.dataparsers.llff import load_poses_bounds
    from frugalnerf_ns.model.geometric_adaptation import pseudo_ground_truth_scale
    from frugalnerf_ns.geometry.reprojection import project_to_camera
    from frugalnerf_ns.scoring.pseudo_depth import summarise

    _, pipeline, _, _ = eval_setup(args.config, test_mode="test")
    model = pipeline.model
    model.eval()
    data = Path(pipeline.datamanager.config.dataparser.data)
    points_file = data / "sparse" / "0" / "points3D.bin"
    if not points_file.is_file() or not (data / "poses_bounds.npy").is_file():
        raise SystemExit(f"check_pseudo_depth: error: needs an LLFF scene with {points_file}")
    points = torch.from_numpy(read_points3d_bin(points_file))
    poses, _ = load_poses_bounds(data / "poses_bounds.npy")
    raw_c2w = torch.from_numpy(llff_to_opengl(poses[:, :, :4]))  # COLMAP's world frame, like points3D
    scale = float(pipeline.datamanager.train_dataparser_outputs.dataparser_scale)
    all_images = sorted(p.name for p in Path(pipeline.datamanager.train_dataset.image_filenames[0]).parent.iterdir())
    generator = torch.Generator().manual_seed(0)
    report = {}
    for group, dataset in (("train", pipeline.datamanager.train_dataset), ("test", pipeline.datamanager.eval_dataset)):
        origins, directions, truth = [], [], []
        for index in range(len(dataset)):
            frame = all_images.index(Path(dataset.image_filenames[index]).name)
            camera = dataset.cameras[index : index + 1]
            intr = torch.tensor([float(camera.fx), float(camera.fy), float(camera.cx), float(camera.cy)], dtype=torch.float64)
            proj = project_to_camera(points, raw_c2w[frame].expand(len(points), 3, 4), intr.expand(len(points), 4))
            w, h = int(camera.width), int(camera.height)
            inside = proj.in_front & (proj.pixels[:, 0] >= 0) & (proj.pixels[:, 0] < w) & (proj.pixels[:, 1] >= 0) & (proj.pixels[:, 1] < h)
            chosen = torch.nonzero(inside)[:, 0]
            chosen = chosen[torch.randperm(len(chosen), generator=generator)[: args.max_points // len(dataset)]]
            distance = (points[chosen] - raw_c2w[frame, :3, 3]).norm(dim=-1) * scale  # along the ray, scene units
            bundle = camera.generate_rays(camera_indices=0, coords=proj.pixels[chosen].flip(-1).float())
            origins.append(bundle.origins)
            directions.append(bundle.directions)
            truth.append(distance.float())
        origins, directions, truth = torch.cat(origins), torch.cat(directions), torch.cat(truth)
        bundle = RayBundle(origins=origins.to(model.device), directions=directions.to(model.device),
                           pixel_area=torch.ones(len(origins), 1, device=model.device),
                           camera_indices=torch.zeros(len(origins), 1, dtype=torch.long, device=model.device))
        previous, model.num_rendered_scales = model.num_rendered_scales, model.field.num_scales
        with torch.no_grad():
            outputs = model.get_outputs(bundle)
        model.num_rendered_scales = previous
        scales = range(model.field.num_scales)
        depths = torch.stack([outputs["depth" + ("" if s == 0 else f"_scale{s}")].reshape(-1) for s in scales]).cpu()
        chosen_scale = pseudo_ground_truth_scale(
            bundle.origins, bundle.directions, depths.to(model.device), outputs["rgb"].reshape(-1, 3),
            model.reference_views, model.config.reprojection_threshold,
        ).cpu()
        report[group] = summarise(depths, truth, chosen_scale)
        r = report[group]
        print(f"{group} cameras, {r['rays']} COLMAP points:")
        print("  median relative depth error per scale: " + ", ".join(f"{e:.3f}" for e in r["median_relative_error_per_scale"]))
        print("  closest scale to COLMAP (fraction):    " + ", ".join(f"{e:.2f}" for e in r["closest_fraction_per_scale"]))
        print("  scale the adaptation picks (fraction): " + ", ".join(f"{e:.2f}" for e in r["picked_fraction_per_scale"])
              + f"  (left out {r['left_out_fraction']:.2f})")
        print(f"  pick is the closest scale: {r['pick_is_closest']:.2f} (by chance: {r['pick_is_closest_by_chance']:.2f})")
        print(f"  median relative error of the pseudo depth {r['median_relative_error_pseudo']:.3f} vs the full "
              f"scale's {r['median_relative_error_full_same_rays']:.3f}; pseudo closer on {r['pseudo_closer_than_full']:.2f} of rays")
    (args.config.parent / "pseudo_depth_check.json").write_text(json.dumps(report, indent=2))


if __name__ == "__main__":
    main()
