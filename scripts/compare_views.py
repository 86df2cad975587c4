"""One test view of several trained runs side by side (ground truth | each run's colour | the first run's depth), each
panel labelled with the run's name and its PSNR on that view: the pictures beside the results tables.

    python scripts/compare_views.py ours=<run>/config.yml nerfacto=<run>/config.yml [tensorf=...] --test 2 --out view.jpg

The runs must share their test split (the same scene, views and parser options); the ground truth is the first run's.
Works for FrugalNeRF and for nerfstudio's own methods (one scale, the same output names).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import List, Optional, Tuple

import numpy as np
import torch
from PIL import Image, ImageDraw


def render(config: Path, index: int) -> Tuple[np.ndarray, np.ndarray, Optional[np.ndarray]]:
    """(ground truth, colour, depth) of test view ``index`` of the run in ``config``, as float arrays in [0, 1]."""
    from nerfstudio.utils.eval_utils import eval_setup

    from frugalnerf_ns.model.objective import target_rgb
    from frugalnerf_ns.tools.offline_tools import patch_torchmetrics_lpips

    patch_torchmetrics_lpips()  # tensorf and nerfacto build torchmetrics' LPIPS, which would download AlexNet
    _, pipeline, _, _ = eval_setup(config, test_mode="test")
    dataset = pipeline.datamanager.eval_dataset
    if not 0 <= index < len(dataset):
        sys.exit(f"compare_views: --test {index}: {config} has {len(dataset)} test views")
    camera = dataset.cameras[index : index + 1].to(pipeline.model.device)
    with torch.no_grad():
        outputs = pipeline.model.get_outputs_for_camera_ray_bundle(camera.generate_rays(camera_indices=0, keep_shape=True))
    image = target_rgb(dataset[index]["image"].float(), torch.ones(3))  # RGBA on white, as the evaluator scores it
    depth = outputs.get("depth")
    return image.numpy(), outputs["rgb"].clamp(0, 1).cpu().numpy(), None if depth is None else depth[..., 0].cpu().numpy()


def depth_panel(depth: np.ndarray) -> np.ndarray:
    """Depth as grey levels linear in disparity between its 2nd and 98th percentiles (near: bright)."""
    disparity = 1.0 / np.clip(depth, 1e-6, None)
    lo, hi = np.percentile(disparity, [2, 98])
    return np.repeat(np.clip((disparity - lo) / max(hi - lo, 1e-9), 0, 1)[..., None], 3, axis=-1)


def main(argv: Optional[List[str]] = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("runs", nargs="+", help="label=<run>/config.yml, the first one's depth is shown")
    parser.add_argument("--test", type=int, default=0, help="index of the test view")
    parser.add_argument("--out", type=Path, required=True, help="the picture (.jpg or .png)")
    args = parser.parse_args(argv)
    from frugalnerf_ns.scoring.metrics import capped_psnr

    runs = []
    for item in args.runs:
        label, _, path = item.partition("=")
        if not path or not Path(path).is_file():
            sys.exit(f"compare_views: {item!r}: give label=<run>/config.yml of a trained run")
        runs.append((label, Path(path)))
    panels, labels, first_depth = [], [], None
    for number, (label, config) in enumerate(runs):
        truth, colour, depth = render(config, args.test)
        if number == 0:
            panels.append(truth)
            labels.append("ground truth")
            first_depth = depth
        if colour.shape != panels[0].shape:
            sys.exit(f"compare_views: {label}'s test view {args.test} is {colour.shape[:2]}, not {panels[0].shape[:2]}")
        panels.append(colour)
        labels.append(f"{label} {float(capped_psnr(torch.from_numpy(colour), torch.from_numpy(panels[0]))):.2f} dB")
    if first_depth is not None:
        panels.append(depth_panel(first_depth))
        labels.append(f"{runs[0][0]} depth")
    strip = Image.fromarray((np.concatenate(panels, axis=1) * 255).round().astype(np.uint8))
    draw = ImageDraw.Draw(strip)
    width = panels[0].shape[1]
    for number, text in enumerate(labels):
        draw.rectangle([number * width, 0, number * width + 7 * len(text) + 8, 16], fill=(0, 0, 0))
        draw.text((number * width + 4, 2), text, fill=(255, 255, 255))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    strip.save(args.out, quality=90)
    print(f"compare_views: wrote {args.out} ({', '.join(labels)})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
