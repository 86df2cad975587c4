"""Where do a run's test-view errors lie: on what the training views saw, or on what none of them saw?

  python scripts/diagnostics/error_by_coverage.py <run>/config.yml [--tolerance 0.05] [--scale 0]

Every test pixel is lifted to 3D at the run's own rendered depth and projected into each training camera. It
counts as seen by that camera when it lands inside the image and the camera's own rendered depth there agrees
within ``--tolerance`` (relative), i.e. nothing the run put in front of it hides it. Printed per test view and
over all of them, for pixels seen by no / one / two or more training views: their share of the pixels, the
render's PSNR on them and their share of the squared error; then the PSNR the view would have were the unseen
pixels perfect (a target above it needs the seen pixels rendered better too), and, on the seen pixels, the PSNR of
the training photos' colours carried there with the run's depth (with the right depth on a matte surface they
match the photo; a wrong depth carries another pixel's colour). The visibility rests on the run's own depth, so a wrong depth can count
a pixel as seen or unseen wrongly; the frustum-only share (inside any training image, occlusion ignored) is
printed beside it; "all" pools the pixels of every test view, the last line averages PSNR over views as the
evaluator does. Writes ``<run>/error_by_coverage.json``.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("config", type=Path)
    parser.add_argument("--tolerance", type=float, default=0.05, help="relative depth agreement for 'seen'")
    parser.add_argument("--scale", type=int, default=0, help="which scale's colour and depth (0: the full scale)")
    args = parser.parse_args(argv)
    if not args.config.is_file():
        raise SystemExit(f"error_by_coverage: error: {args.config} is not a file (pass <run>/config.yml)")

    from nerfstudio.utils.eval_utils import eval_setup

    from frugalnerf_ns.geometry.reprojection import unproject_along_rays
    from frugalnerf_ns.geometry.visibility import training_view_coverage
    from frugalnerf_ns.scoring.coverage import GROUPS, summarise_coverage
    from frugalnerf_ns.tools import offline_tools

    offline_tools.patch_torchmetrics_lpips()
    _, pipeline, _, _ = eval_setup(args.config, test_mode="test")
    model = pipeline.model
    model.eval()
    if hasattr(model, "num_rendered_scales"):
        model.num_rendered_scales = max(args.scale + 1, 1)
    suffix = "" if args.scale == 0 else f"_scale{args.scale}"

    def render(dataset, index):
        camera, bundle, out, image = offline_tools.render_view(model, dataset, index)
        return camera, bundle, out[f"rgb{suffix}"].clamp(0, 1), out[f"depth{suffix}"][..., 0], image

    training = offline_tools.training_views_at_depth(model, pipeline.datamanager.train_dataset, f"depth{suffix}")

    report = {"tolerance": args.tolerance, "scale": args.scale, "views": []}
    pooled = {"seen_by": [], "in_frustum": [], "squared": [], "warp_squared": []}
    for index in range(len(pipeline.datamanager.eval_dataset)):
        _, bundle, rgb, depth, image = render(pipeline.datamanager.eval_dataset, index)
        points = unproject_along_rays(bundle.origins.cpu(), bundle.directions.cpu(), depth).reshape(-1, 3)
        coverage = training_view_coverage(points, *zip(*training), tolerance=args.tolerance)
        target = image.reshape(-1, 3)
        parts = {"seen_by": coverage.seen_by, "in_frustum": coverage.in_frustum,
                 "squared": (rgb.reshape(-1, 3) - target) ** 2, "warp_squared": (coverage.colors - target) ** 2}
        view = summarise_coverage(**parts)
        view["file"] = Path(pipeline.datamanager.eval_dataset.image_filenames[index]).name
        report["views"].append(view)
        for key, value in parts.items():
            pooled[key].append(value)
    report["all"] = summarise_coverage(**{key: torch.cat(value) for key, value in pooled.items()})
    header = "view | PSNR | in a frustum | unseen: share / PSNR / error share | seen by 1 | seen by 2+ | if unseen perfect | seen: render / warped photos"
    print(header)
    for view in report["views"] + [dict(report["all"], file="all")]:
        cells = [view["file"], f"{view['psnr']:.2f}", f"{view['in_any_frustum_fraction']:.2f}"]
        for name in GROUPS:
            group = view[name]
            cells.append(f"{group['fraction']:.2f} / {group['psnr']:.2f} / {group['error_share']:.2f}")
        cells += [f"{view['psnr_if_unseen_were_perfect']:.2f}",
                  f"{view['seen_psnr']:.2f} / {view['seen_psnr_of_warped_training_colour']:.2f}"]
        print(" | ".join(cells))
    # The evaluator averages PSNR over views; "all" above pools the squared error of every pixel.
    views = report["views"]
    report["mean_over_views"] = {key: sum(v[key] for v in views) / len(views)
                                 for key in ("psnr", "psnr_if_unseen_were_perfect")}
    print("mean over views (as the evaluator averages): PSNR {psnr:.2f}, if the unseen pixels were perfect "
          "{psnr_if_unseen_were_perfect:.2f}".format(**report["mean_over_views"]))
    (args.config.parent / "error_by_coverage.json").write_text(json.dumps(report, indent=2))


if __name__ == "__main__":
    main()
