"""Run and score any nerfstudio method offline, the same way for FrugalNeRF and its baselines.

``python -m frugalnerf_ns.tools.offline_tools train <ns-train args>``: nerfstudio's ns-train, except that
torchmetrics' LPIPS (which tensorf and nerfacto build at start-up and which downloads AlexNet) is replaced
by the offline LPIPS of this package, so baselines train on a machine without network.

``python -m frugalnerf_ns.tools.offline_tools eval <run>/config.yml [--per-view] [--training-views]``: renders the
test views (or its training views) of a trained run and prints PSNR / SSIM / LPIPS as JSON (with ``--per-view``, each view's line first), computed by
one piece of code for every method, with the DTU object masks when the dataparser provides them (so baselines
are scored on the paper's protocol too).
"""

from __future__ import annotations

import contextlib
import json
import statistics
import sys
from pathlib import Path
from typing import Dict, List, Optional

import torch


def patch_torchmetrics_lpips() -> None:
    """Make ``torchmetrics.image.lpip.LearnedPerceptualImagePatchSimilarity`` the offline LPIPS."""
    import torchmetrics.image.lpip as lpip

    from frugalnerf_ns.scoring.lpips_offline import OfflineLPIPS

    class OfflineLearnedPerceptualImagePatchSimilarity(torch.nn.Module):
        def __init__(self, normalize: bool = False, **_: object) -> None:
            super().__init__()
            self.net = OfflineLPIPS()
            self.normalize = normalize

        def forward(self, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
            if not self.normalize:  # torchmetrics' default: inputs in [-1, 1]
                a, b = (a + 1) / 2, (b + 1) / 2
            return self.net(a, b).mean()

    lpip.LearnedPerceptualImagePatchSimilarity = OfflineLearnedPerceptualImagePatchSimilarity  # type: ignore


def render_view(model, dataset, index: int):
    """One view of ``dataset`` rendered whole, every output the model gives (on the CPU), with its camera, rays
    and image as the evaluator scores it (RGBA on white): what the diagnostics scripts compare."""
    from frugalnerf_ns.model.objective import target_rgb

    camera = dataset.cameras[index : index + 1].to(model.device)
    bundle = camera.generate_rays(camera_indices=0, keep_shape=True)
    with torch.no_grad():
        outputs = {key: value.cpu() for key, value in model.get_outputs_for_camera_ray_bundle(bundle).items()}
    return camera, bundle, outputs, target_rgb(dataset[index]["image"].float(), torch.ones(3))


def training_views_at_depth(model, dataset, depth_key: str = "depth") -> list:
    """(camera-to-world, [fx, fy, cx, cy], rendered depth, image) of every training view: where
    ``geometry.visibility.training_view_coverage`` looks for a test pixel."""
    views = []
    for index in range(len(dataset)):
        camera, _, outputs, image = render_view(model, dataset, index)
        intrinsics = torch.tensor([float(camera.fx), float(camera.fy), float(camera.cx), float(camera.cy)])
        views.append((camera.camera_to_worlds[0].cpu(), intrinsics, outputs[depth_key][..., 0], image))
    return views


def render_test_rgb(model, camera, mask: Optional[torch.Tensor]) -> torch.Tensor:
    """Rendered colour of one camera, [H, W, 3] in [0, 1].

    With a mask, only the rays inside it are rendered and the rest are black: the masked protocol
    (``masked_image_metrics``) sets both images' background to white, so this is exact and, on DTU where the
    object covers a fraction of the image, several times faster. FrugalNeRF renders its full scale only.
    """
    bundle = camera.generate_rays(camera_indices=0, keep_shape=True)
    height, width = bundle.shape
    only_full = model.full_scale_only() if hasattr(model, "full_scale_only") else contextlib.nullcontext()
    with torch.no_grad(), only_full:
        if mask is None:
            return model.get_outputs_for_camera_ray_bundle(bundle)["rgb"].clamp(0, 1)
        inside = mask.reshape(height, width).to(bundle.origins.device)
        rgb = torch.zeros(height, width, 3, device=bundle.origins.device)
        count = int(inside.sum())
        if count:
            rays = bundle[inside].reshape((count, 1))
            rgb[inside] = model.get_outputs_for_camera_ray_bundle(rays)["rgb"].reshape(count, 3).clamp(0, 1)
        return rgb


def score_test_view(pipeline, dataset, index: int, lpips) -> Dict[str, float]:
    """PSNR / SSIM / LPIPS of one test view, masked where the dataparser gives an eval mask."""
    from torchmetrics.functional import structural_similarity_index_measure as ssim

    from frugalnerf_ns.data.dataset import read_eval_mask
    from frugalnerf_ns.scoring.metrics import masked_image_metrics
    from frugalnerf_ns.model.objective import target_rgb

    camera = dataset.cameras[index : index + 1].to(pipeline.device)
    data = dataset[index]
    # RGBA (NeRF-synthetic) is scored on white, as the few-shot protocol composites it; RGB as it is.
    image = target_rgb(data["image"].to(pipeline.device), torch.ones(3, device=pipeline.device))
    # The eval mask where the dataparser lists one, also for nerfstudio's datasets (tensorf's), which
    # do not load it: every method is scored on the same pixels.
    mask = data["eval_mask"] if "eval_mask" in data else read_eval_mask(dataset, index)
    rgb = render_test_rgb(pipeline.model, camera, mask)
    if mask is None:
        mask = torch.ones(*image.shape[:2], 1, dtype=torch.bool)
    return masked_image_metrics(rgb, image, mask.to(rgb.device), ssim, lpips)


def evaluate_run(
    config_path: Path, step: Optional[int] = None, print_views: bool = False, training_views: bool = False
) -> Dict[str, float]:
    """Test-view PSNR / SSIM / LPIPS of a trained run (masked where the dataparser gives eval masks), at its
    latest checkpoint or at the checkpoint of ``step``; with ``print_views``, one ``VIEW {json}`` line per test
    view first (its image name and scores: which views a change helped); with ``training_views``, the same of
    the views it was trained on (how well the run fits its own photos)."""
    from nerfstudio.utils.eval_utils import eval_setup

    from frugalnerf_ns.scoring.lpips_offline import OfflineLPIPS

    patch_torchmetrics_lpips()
    def at_step(config):
        config.load_step = step
        return config

    _, pipeline, _, _ = eval_setup(config_path, test_mode="test", update_config_callback=at_step if step is not None else None)
    dataset = pipeline.datamanager.train_dataset if training_views else pipeline.datamanager.eval_dataset
    lpips = OfflineLPIPS().to(pipeline.device)
    per_view: List[Dict[str, float]] = []
    pipeline.eval()
    for index in range(len(dataset)):
        per_view.append(score_test_view(pipeline, dataset, index, lpips))
        if print_views:
            view = {"view": Path(dataset.image_filenames[index]).stem, **per_view[-1], "step": step}
            print("VIEW " + json.dumps(view), flush=True)
    result: Dict[str, float] = mean_scores(per_view) | {"num_test_views": len(dataset)}
    # Published shorter test lists (DTU: RegNeRF's 25 of the 40 views) scored beside the full list.
    for name, positions in (dataset.metadata.get("test_subsets") or {}).items():
        result |= {f"{name}_{key}": value for key, value in mean_scores([per_view[n] for n in positions]).items()}
        result[f"{name}_num_test_views"] = len(positions)
    return result


def mean_scores(per_view: List[Dict[str, float]]) -> Dict[str, float]:
    """Average of each metric over the views (a metric some views lack is averaged over those that have it)."""
    names = dict.fromkeys(name for view in per_view for name in view)
    return {name: statistics.fmean(view[name] for view in per_view if name in view) for name in names}


def main() -> None:
    if len(sys.argv) < 2 or sys.argv[1] not in ("train", "eval"):
        sys.exit("usage: python -m frugalnerf_ns.tools.offline_tools train <ns-train args> | eval <config.yml> [step ...]")
    command, rest = sys.argv[1], sys.argv[2:]
    if command == "train":
        patch_torchmetrics_lpips()
        from nerfstudio.scripts.train import entrypoint

        sys.argv = ["ns-train", *rest]
        entrypoint()
    else:
        usage = ("usage: python -m frugalnerf_ns.tools.offline_tools eval <run>/config.yml [step ...] [--per-view] "
                 "[--training-views]")
        print_views, training_views = "--per-view" in rest, "--training-views" in rest
        rest = [arg for arg in rest if arg not in ("--per-view", "--training-views")]
        if not rest or rest[0] in ("-h", "--help"):
            sys.exit(usage)
        if not Path(rest[0]).is_file():
            sys.exit(f"frugalnerf: error: {rest[0]} is not a run's config.yml ({usage})")
        if not all(s.isdigit() for s in rest[1:]):
            sys.exit(f"frugalnerf: error: steps must be whole numbers, got {' '.join(rest[1:])} ({usage})")
        # One line per checkpoint step asked for (the latest without steps), in one process: nerfstudio's
        # start-up costs more than scoring a few small test views.
        for step in [int(s) for s in rest[1:]] or [None]:
            scores = evaluate_run(Path(rest[0]), step, print_views, training_views)
            print("RESULT " + json.dumps(scores | {"step": step}), flush=True)


if __name__ == "__main__":
    main()
