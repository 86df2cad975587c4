"""How far each run's depth lies from the sparse points L_sd pulls it to, at the training pixels the points
project to.

  python scripts/diagnostics/sparse_depth_fit.py --points <run>/config.yml <run>/config.yml [<run>/config.yml ...]

``--points`` names the run whose training set-up gives the points (its triangulation options, from the scene's
cache as training loads them); every other config is a trained run rendered at those points' pixels in their
training views. The depth compared is the one L_sd compares (``objective.depth_through_box``: the field's metric
depth, and where the scene has a far background sphere, that sphere's distance in the share the field lets
through). Printed per run and training view: observations, the relative depth difference |rendered - point| /
point (median, p90, share above 10 %), and the mean of L_sd's own term (1/rendered - 1/point)^2; then the same per
quarter of the points' depth with that quarter's share of the term (``bench/sparse_fit.py``), and per track
length (the number of training views a point is seen in). A run that scores
well on the test views yet lies far from many points says those points are wrong; a run that fits them closely
and scores worse says fitting them costs it.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch


def depth_at_points(pipeline, sparse) -> torch.Tensor:
    """The run's depth, as L_sd sees it, on the rays through every observation's pixel."""
    model = pipeline.model
    model.eval()
    cameras = pipeline.datamanager.train_dataset.cameras.to(model.device)
    coords = sparse.pixels.flip(-1).to(model.device)  # nerfstudio's coords are (row, column)
    bundle = cameras.generate_rays(camera_indices=sparse.view[:, None].to(model.device), coords=coords)
    bundle = bundle.reshape((-1, 1))
    with torch.no_grad():
        out = model.get_outputs_for_camera_ray_bundle(bundle)
    depth = out["depth"].reshape(-1).cpu()
    far = getattr(model, "far_background", None)
    outer = getattr(model, "outer_space", None)
    # With the outer space the model's depth already runs through the box and beyond (outer_space.depth_through_outer_space).
    if far is not None and far.has_shell and (outer is None or not outer.is_active):
        flat = bundle.reshape((-1,))
        far_depth = far.distance(flat.origins, flat.directions).reshape(-1).cpu()
        accumulation = out["accumulation"].reshape(-1).cpu()
        depth = accumulation * depth + (1.0 - accumulation) * far_depth
    return depth


def draw_agreement(images, sparse, rendered: torch.Tensor, path: Path) -> None:
    """The training views one above the other, each observation circled green / yellow / red as the run's depth
    lies within 5 %, within 10 % or beyond from the point's; the nearest quarter of the points drawn larger."""
    from PIL import Image, ImageDraw

    relative = ((rendered - sparse.depth).abs() / sparse.depth).tolist()
    near = (sparse.depth <= sparse.depth.quantile(0.25)).tolist()
    tiles = []
    for index, image in enumerate(images):
        tile = Image.fromarray((image[..., :3].clamp(0, 1).numpy() * 255).round().astype("uint8"))
        pen = ImageDraw.Draw(tile)
        for obs in (sparse.view == index).nonzero()[:, 0].tolist():
            u, v = sparse.pixels[obs].tolist()
            colour = (0, 255, 0) if relative[obs] < 0.05 else (255, 255, 0) if relative[obs] < 0.1 else (255, 0, 0)
            radius = 4 if near[obs] else 2
            pen.ellipse([u - radius, v - radius, u + radius, v + radius], outline=colour, width=2 if near[obs] else 1)
        tiles.append(tile)
    canvas = Image.new("RGB", (max(t.width for t in tiles), sum(t.height for t in tiles)))
    top = 0
    for tile in tiles:
        canvas.paste(tile, (0, top))
        top += tile.height
    path.parent.mkdir(parents=True, exist_ok=True)
    canvas.save(path)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--points", type=Path, required=True, help="config.yml of the run whose set-up gives the points")
    parser.add_argument("runs", type=Path, nargs="+", help="config.yml of each run to compare with the points")
    parser.add_argument("--out", type=Path, help="JSON report (default: print only)")
    parser.add_argument("--draw", type=Path, help="PNG: the training views stacked, each observation circled by how "
                        "far the first run's depth lies from it (green < 5 %%, yellow < 10 %%, red beyond; thick: the "
                        "nearest quarter of the points)")
    args = parser.parse_args(argv)
    for path in [args.points, *args.runs]:
        if not path.is_file():
            raise SystemExit(f"sparse_depth_fit: error: {path} is not a file (pass <run>/config.yml)")

    from nerfstudio.utils.eval_utils import eval_setup

    from frugalnerf_ns.bench.sparse_fit import agreement_by_depth, depth_agreement
    from frugalnerf_ns.tools.offline_tools import patch_torchmetrics_lpips

    patch_torchmetrics_lpips()
    _, source, _, _ = eval_setup(args.points, test_mode="val")  # training's set-up: the sparse points
    sparse = source.datamanager.sparse
    if sparse is None:
        raise SystemExit(f"sparse_depth_fit: error: {args.points} trains without sparse points")
    sparse = type(sparse)(*(t.cpu() for t in sparse))
    dataset = source.datamanager.train_dataset
    images = [dataset.get_image_float32(i) for i in range(len(dataset))] if args.draw else []
    del source
    print(f"{sparse.num_points} points, {sparse.view.numel()} observations (from {args.points})")
    report = {"points": str(args.points), "num_points": sparse.num_points, "runs": []}
    print("run | view | observations | relative depth difference median / p90 | above 10 % | mean (1/d - 1/d_sd)^2")
    for path in args.runs:
        _, pipeline, _, _ = eval_setup(path, test_mode="test")
        rendered = depth_at_points(pipeline, sparse)
        entry = {"run": str(path), "all": depth_agreement(rendered, sparse.depth), "views": {},
                 "depth_bands": agreement_by_depth(rendered, sparse.depth)}
        for view in sorted(set(sparse.view.tolist())):
            mine = sparse.view == view
            entry["views"][view] = depth_agreement(rendered[mine], sparse.depth[mine])
        report["runs"].append(entry)
        rows = [(f"view {view}", row) for view, row in entry["views"].items()] + [("all", entry["all"])]
        # Points seen in every training view are held by more rays than those of one pair: split by track length.
        track = torch.bincount(sparse.point, minlength=sparse.num_points)[sparse.point]
        entry["by_track_length"] = {int(k): depth_agreement(rendered[track == k], sparse.depth[track == k])
                                    for k in sorted(set(track.tolist()))}
        rows += [(f"seen in {k} views", row) for k, row in entry["by_track_length"].items()]
        rows += [(f"depth {band['depth_from']:.3g}-{band['depth_to']:.3g} (term share {band['share_of_term']:.2f})", band)
                 for band in entry["depth_bands"]]
        for name, row in rows:
            print(f"{path.parent.name} | {name} | {row['observations']} | {row['median_relative']:.3f} / "
                  f"{row['p90_relative']:.3f} | {row['above_10_percent']:.3f} | {row['mean_inverse_depth_term']:.4g}")
        del pipeline
        if args.draw and path == args.runs[0]:
            draw_agreement(images, sparse, rendered, args.draw)
            print(f"wrote {args.draw}")
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(report, indent=2))
        print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
