"""Which scale renders the test views best, split by how many training views see each pixel.

  python scripts/diagnostics/scales_by_coverage.py <run>/config.yml [--tolerance 0.05] [--scores]

The paper's premise is that the coarser scales' geometry is the better one where the few views leave the full
scale unconstrained. This renders every test view at every scale and pools the squared error per coverage group
(unseen, seen by one training view, by two or more: scale 0's depth carried into each training view, as
``error_by_coverage.py`` counts it). Beside each scale: the mean colour of the first two and of all scales, and
the per-pixel best scale (an upper bound no renderer can reach without the ground truth, and biased up: the
minimum of several noisy estimates beats each of them even when none is better). With ``--scores``, the
evaluator's own PSNR / SSIM / LPIPS (``offline_tools.score_test_view``) of the full scale and of each mean: the
blend's PSNR against what averaging costs in sharpness. Writes ``<run>/scales_by_coverage.json``.
"""

from __future__ import annotations

import argparse
import contextlib
import json
from pathlib import Path
from typing import Dict, List

import torch


def scale_colours(outputs: Dict[str, torch.Tensor], num_scales: int) -> List[torch.Tensor]:
    """The colour each scale renders (the model names the full scale ``rgb``, the others ``rgb_scale{s}``)."""
    return [outputs["rgb" if s == 0 else f"rgb_scale{s}"] for s in range(num_scales)]


def candidates(colours: List[torch.Tensor]) -> Dict[str, torch.Tensor]:
    """Each scale's colour and the means of the first two and of all scales."""
    named = {f"scale{s}": c for s, c in enumerate(colours)}
    named["mean of 0-1"] = (colours[0] + colours[1]) / 2
    named[f"mean of 0-{len(colours) - 1}"] = sum(colours) / len(colours)
    return named


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("config", type=Path)
    parser.add_argument("--tolerance", type=float, default=0.05, help="relative depth agreement for 'seen'")
    parser.add_argument("--scores", action="store_true", help="also the evaluator's PSNR / SSIM / LPIPS of each mean")
    args = parser.parse_args(argv)
    if not args.config.is_file():
        raise SystemExit(f"scales_by_coverage: error: {args.config} is not a file (pass <run>/config.yml)")

    from nerfstudio.utils.eval_utils import eval_setup

    from frugalnerf_ns.geometry.reprojection import unproject_along_rays
    from frugalnerf_ns.geometry.visibility import training_view_coverage
    from frugalnerf_ns.scoring.coverage import GROUPS, group_masks, psnr_of
    from frugalnerf_ns.scoring.lpips_offline import OfflineLPIPS
    from frugalnerf_ns.tools import offline_tools

    offline_tools.patch_torchmetrics_lpips()
    _, pipeline, _, _ = eval_setup(args.config, test_mode="test")
    model = pipeline.model
    model.eval()
    num_scales = getattr(getattr(model, "field", None), "num_scales", 1)
    if num_scales < 2:
        raise SystemExit(f"scales_by_coverage: error: {args.config} is a run with one scale: nothing to compare")
    model.num_rendered_scales = num_scales

    def render(dataset, index):
        camera, bundle, outputs, image = offline_tools.render_view(model, dataset, index)
        colours = [c.clamp(0, 1) for c in scale_colours(outputs, num_scales)]
        return camera, bundle, colours, outputs["depth"][..., 0], image

    training = offline_tools.training_views_at_depth(model, pipeline.datamanager.train_dataset)

    groups = (*GROUPS, "all")
    pooled: Dict[str, Dict[str, float]] = {group: {} for group in groups}
    counts = dict.fromkeys(groups, 0)
    per_view: Dict[str, List[float]] = {}
    test = pipeline.datamanager.eval_dataset
    for index in range(len(test)):
        _, bundle, colours, depth, image = render(test, index)
        points = unproject_along_rays(bundle.origins.cpu(), bundle.directions.cpu(), depth).reshape(-1, 3)
        seen_by = training_view_coverage(points, *zip(*training), tolerance=args.tolerance).seen_by
        target = image.reshape(-1, 3)
        errors = {name: ((c.reshape(-1, 3) - target) ** 2).mean(-1) for name, c in candidates(colours).items()}
        errors["best scale per pixel"] = torch.stack([errors[f"scale{s}"] for s in range(num_scales)]).min(0).values
        for name, error in errors.items():
            per_view.setdefault(name, []).append(psnr_of(float(error.sum()), error.numel()))
        for group, inside in (group_masks(seen_by) | {"all": torch.ones_like(seen_by, dtype=torch.bool)}).items():
            counts[group] += int(inside.sum())
            for name, error in errors.items():
                pooled[group][name] = pooled[group].get(name, 0.0) + float(error[inside].sum())

    names = list(per_view)
    report = {"tolerance": args.tolerance, "mean_psnr_over_views": {n: sum(v) / len(v) for n, v in per_view.items()},
              "groups": {}}
    print("group | pixel share | " + " | ".join(names))
    for group in groups:
        psnrs = {name: psnr_of(pooled[group][name], counts[group]) for name in names}
        report["groups"][group] = {"share": counts[group] / counts["all"], "psnr": psnrs}
        print(f"{group} | {counts[group] / counts['all']:.2f} | " + " | ".join(f"{psnrs[n]:.2f}" for n in names))
    print("mean over views (as the evaluator averages) | | "
          + " | ".join(f"{report['mean_psnr_over_views'][n]:.2f}" for n in names))

    if args.scores:
        # The evaluator's own path, its renderer handed the mean of the first k scales (k = 1: the full scale,
        # the number `offline_tools eval` reports). Each view is rendered once; the means reuse its colours.
        real = model.get_outputs_for_camera_ray_bundle
        state: Dict[str, object] = {"k": 1, "colours": None}

        def mean_of_first_k(bundle):
            if state["colours"] is None:
                state["colours"] = scale_colours(real(bundle), num_scales)
            colours = state["colours"][: state["k"]]
            return {"rgb": sum(colours) / len(colours)}

        model.get_outputs_for_camera_ray_bundle = mean_of_first_k
        model.full_scale_only = contextlib.nullcontext  # the evaluator would otherwise render scale 0 alone
        lpips = OfflineLPIPS().to(pipeline.device)
        scores: Dict[int, list] = {k: [] for k in range(1, num_scales + 1)}
        for index in range(len(test)):
            state["colours"] = None
            for k in scores:
                state["k"] = k
                scores[k].append(offline_tools.score_test_view(pipeline, test, index, lpips))
        report["evaluator_scores"] = {}
        for k, views in scores.items():
            mean = offline_tools.mean_scores(views)
            report["evaluator_scores"][f"mean of first {k}"] = mean
            print(f"evaluator, mean of the first {k} scale(s): " + " / ".join(f"{m} {v:.4f}" for m, v in mean.items()))
    (args.config.parent / "scales_by_coverage.json").write_text(json.dumps(report, indent=2))


if __name__ == "__main__":
    main()
