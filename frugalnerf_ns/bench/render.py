"""Render time of a trained FrugalNeRF run, the training marcher beside the inference marcher, in one process.

  frugalnerf-bench render <run>/config.yml [--frames 4] [--views 3] [--out outputs/benchmark_render.json]

Rows (seconds per frame or per test view, same machine, same model, same image size, full scale):
- test view, training marcher (before issue 31): ``render_scale``, every sample slot of every ray
  (``--pipeline.model.fast-inference False``);
- test view, inference marcher (now): ``render_scale_inference``, blocks of slots, rays dropped once they
  leave the box or turn opaque; with the PSNR and largest pixel difference between the two renders;
- spiral frame, now: the scene's video path (``video.scene_video_cameras``), what ``ns-render spiral`` renders;
- ns-eval per test view, now: nerfstudio's ``get_average_eval_image_metrics`` calls for a subset of views;
- offline evaluator per test view: ``offline_tools.score_test_view``, what ``offline_tools eval`` runs per view.
Prints a Markdown table and writes JSON.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from frugalnerf_ns.bench.report import markdown_table, write_report


def timed(fn) -> float:
    start = time.perf_counter()
    fn()
    return time.perf_counter() - start


def main(argv=None) -> list:
    parser = argparse.ArgumentParser(prog="frugalnerf-bench render", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("config", type=Path, help="config.yml of a trained FrugalNeRF run")
    parser.add_argument("--frames", type=int, default=4, help="spiral frames timed per row")
    parser.add_argument("--views", type=int, default=3, help="test views timed per evaluation row (at most all)")
    parser.add_argument("--out", type=Path, default=Path("outputs/benchmark_render.json"))
    args = parser.parse_args(argv)
    if not args.config.is_file():
        sys.exit(f"benchmark_render: error: {args.config} is not a file (pass <run>/config.yml)")

    import torch
    from nerfstudio.utils.eval_utils import eval_setup
    from frugalnerf_ns.scoring.lpips_offline import OfflineLPIPS
    from frugalnerf_ns.tools.offline_tools import score_test_view
    from frugalnerf_ns.tools.video import scene_video_cameras

    _, pipeline, _, _ = eval_setup(args.config, test_mode="test")
    pipeline.eval()
    model, datamanager = pipeline.model, pipeline.datamanager
    start = datamanager.eval_dataset.cameras[0:1]
    size = f"{int(start.width)}x{int(start.height)}"
    dataset = datamanager.eval_dataset
    views = list(range(min(args.views, len(dataset))))

    def render_path(cameras):
        with torch.no_grad():
            for i in range(len(cameras)):
                model.get_outputs_for_camera(cameras[i : i + 1].to(model.device))

    def ns_eval():
        # get_average_eval_image_metrics scores the whole eval set; time a subset through the same calls.
        with torch.no_grad():
            for index in views:
                camera = dataset.cameras[index : index + 1].to(model.device)
                outputs = model.get_outputs_for_camera(camera)
                batch = dataset[index]
                model.get_image_metrics_and_images(outputs, batch)

    lpips = OfflineLPIPS().to(pipeline.device)

    def offline():
        for index in views:
            score_test_view(pipeline, dataset, index, lpips)

    renders = {}

    def test_views(fast: bool):
        model.config.fast_inference = fast
        with torch.no_grad():
            renders[fast] = [model.get_outputs_for_camera(dataset.cameras[i : i + 1].to(model.device))["rgb"]
                             for i in views]

    model.num_rendered_scales = None  # the default outside the viewer: the full scale only
    ours = scene_video_cameras(datamanager, start, args.frames)
    ns_eval()  # warm-up: LPIPS weights, first-call allocations
    rows = [
        ("test view, training marcher (before)", timed(lambda: test_views(False)) / len(views)),
        ("test view, inference marcher (now)", timed(lambda: test_views(True)) / len(views)),
        ("spiral frame, now (scene path)", timed(lambda: render_path(ours)) / args.frames),
        ("ns-eval per test view, now", timed(ns_eval) / len(views)),
        ("offline evaluator per test view", timed(offline) / len(views)),
    ]
    difference = torch.cat([(a - b).flatten() for a, b in zip(renders[True], renders[False])])
    agreement = {"psnr_inference_vs_training_marcher": float(-10 * torch.log10((difference**2).mean().clamp_min(1e-20))),
                 "max_pixel_difference": float(difference.abs().max())}
    model.num_rendered_scales = None
    records = [{"run": str(args.config.parent), "row": name, "seconds": seconds, "image": size,
                "threads": torch.get_num_threads(), "device": str(pipeline.device), **agreement}
               for name, seconds in rows]
    heading = f"{args.config.parent} ({size}, {torch.get_num_threads()} threads)"
    table = markdown_table(records, [(heading, lambda r: r["row"]), ("seconds", lambda r: f"{r['seconds']:.2f}")])
    table += (f"\n\ninference vs training marcher on {len(views)} test views: PSNR "
              f"{agreement['psnr_inference_vs_training_marcher']:.1f} dB, largest pixel difference "
              f"{agreement['max_pixel_difference']:.2e}")
    write_report("benchmark_render", table, records, args.out)
    return records
