"""Look inside a trained run: per-scale colour, depth and accumulation of chosen test and training views,
scored, with side-by-side pictures (ground truth | ours per scale | depth | accumulation).

  python scripts/diagnostics/diagnose_views.py <run>/config.yml [--test 0 5] [--train 0 1] [--out docs/notes/diagnosis/<name>]

Prints one line per view and scale (PSNR over the image and, where the scene has eval masks, over the
object; mean accumulation inside and outside the mask; depth percentiles) and writes ``views.json`` and one
PNG per view. Training views are scored on the pixels they were trained on: the few-shot gap shows as a
training-view PSNR far above the test views'.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Dict, List, Optional

import numpy as np
import torch

from frugalnerf_ns.model.objective import target_rgb


def depth_picture(depth: torch.Tensor, lo: float, hi: float) -> np.ndarray:
    """Depth as grey levels between fixed bounds (near: bright), the same bounds for every scale; linear in
    disparity (1 / depth), so a scene whose rays run out to a far room or to infinity keeps its near range."""
    lo, hi = max(lo, 1e-6), max(hi, lo + 1e-6)
    value = ((1.0 / depth.clamp_min(1e-6) - 1.0 / hi) / (1.0 / lo - 1.0 / hi)).clamp(0, 1)
    return (value.expand(*depth.shape[:2], 3).numpy() * 255).astype(np.uint8)


def score_view(model, dataset, index: int, kind: str, mask: Optional[torch.Tensor], max_scales: int = 0) -> tuple:
    from frugalnerf_ns.scoring.metrics import capped_psnr, masked_psnr

    camera = dataset.cameras[index : index + 1].to(model.device)
    bundle = camera.generate_rays(camera_indices=0, keep_shape=True)
    # Every scale (outside the viewer the model renders only the full scale unless asked).
    num_scales = getattr(getattr(model, "field", None), "num_scales", 1)
    num_scales = min(num_scales, max_scales) if max_scales > 0 else num_scales
    if hasattr(model, "num_rendered_scales"):
        model.num_rendered_scales = num_scales
    with torch.no_grad():
        outputs = model.get_outputs_for_camera_ray_bundle(bundle)
    # RGBA (NeRF-synthetic) on white, as the evaluator scores it; RGB as it is.
    image = target_rgb(dataset[index]["image"].float(), torch.ones(3))
    rows: List[Dict[str, float]] = []
    pictures = [(image.numpy() * 255).astype(np.uint8)]
    depths = []
    # nerfstudio's own methods (tensorf) render one scale with the same output names.
    for scale in range(num_scales):
        suffix = "" if scale == 0 else f"_scale{scale}"
        rgb = outputs[f"rgb{suffix}"].clamp(0, 1).cpu()
        acc = outputs[f"accumulation{suffix}"].cpu()
        depth = outputs[f"depth{suffix}"].cpu()
        row = {"view": kind, "index": index, "scale": scale, "psnr": float(capped_psnr(rgb, image)),
               "acc_mean": float(acc.mean())}
        if mask is not None:
            m = mask.to(torch.bool)
            row |= {"psnr_object": masked_psnr(rgb, image, m[..., None]), "acc_object": float(acc[m].mean()),
                    "acc_background": float(acc[~m].mean()) if (~m).any() else float("nan")}
            inside = depth[m]
        else:
            inside = depth.flatten()
        q = torch.quantile(inside.flatten().float(), torch.tensor([0.05, 0.5, 0.95])).tolist()
        row |= {"depth_p5": q[0], "depth_p50": q[1], "depth_p95": q[2]}
        rows.append(row)
        pictures.append((rgb.numpy() * 255).astype(np.uint8))
        depths.append((depth, acc))
    lo = min(float(d.quantile(0.02)) for d, _ in depths)
    hi = max(float(d.quantile(0.98)) for d, _ in depths)
    strip = pictures + [depth_picture(d, lo, hi) for d, _ in depths]
    strip += [(a.expand(*a.shape[:2], 3).numpy() * 255).astype(np.uint8) for _, a in depths]
    return rows, np.concatenate(strip, axis=1)


def object_mask(folder: Optional[Path], image: Path) -> Optional[torch.Tensor]:
    """The mask in ``folder`` whose number matches the image's (DTU: image/000022.png -> mask/022.png)."""
    if folder is None:
        return None
    from PIL import Image

    for candidate in folder.iterdir():
        if candidate.stem.isdigit() and Path(image).stem.isdigit() and int(candidate.stem) == int(Path(image).stem):
            return torch.from_numpy(np.asarray(Image.open(candidate).convert("L")) > 127)
    return None


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("config", type=Path)
    parser.add_argument("--test", type=int, nargs="*", default=[0], help="positions in the test split")
    parser.add_argument("--train", type=int, nargs="*", default=[0], help="positions in the training split")
    parser.add_argument("--masks", type=Path, default=None,
                        help="object masks for views the dataparser gives none (DTU training views: <scene>/mask)")
    parser.add_argument("--out", type=Path, default=None, help="folder for the pictures (default: <run>/diagnosis)")
    parser.add_argument("--scales", type=int, default=0, help="render this many scales (1: the full scale only; 0: all)")
    args = parser.parse_args(argv)
    if not args.config.is_file():
        raise SystemExit(f"diagnose_views: error: {args.config} is not a file (pass <run>/config.yml)")

    from nerfstudio.utils.eval_utils import eval_setup
    from PIL import Image

    from frugalnerf_ns.tools.offline_tools import patch_torchmetrics_lpips

    patch_torchmetrics_lpips()  # nerfstudio's methods build torchmetrics' LPIPS, which would download weights
    _, pipeline, _, _ = eval_setup(args.config, test_mode="test")
    model = pipeline.model
    model.eval()
    out = args.out or args.config.parent / "diagnosis"
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    groups = [("test", pipeline.datamanager.eval_dataset, args.test), ("train", pipeline.datamanager.train_dataset, args.train)]
    for kind, dataset, positions in groups:
        for index in positions:
            mask = dataset[index].get("eval_mask")
            mask = mask[..., 0] if mask is not None else object_mask(args.masks, dataset.image_filenames[index])
            view_rows, picture = score_view(model, dataset, index, kind, mask, args.scales)
            rows += view_rows
            name = Path(dataset.image_filenames[index]).stem
            Image.fromarray(picture).save(out / f"{kind}-{name}.png")
            for r in view_rows:
                print(" ".join(f"{k}={v:.3f}" if isinstance(v, float) else f"{k}={v}" for k, v in r.items()) + f" file={name}")
    (out / "views.json").write_text(json.dumps(rows, indent=2))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
