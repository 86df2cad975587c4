"""Render time of a trained FrugalNeRF run before and after issue 23, side by side in one process.

  frugalnerf-bench render <run>/config.yml [--frames 4] [--views 3] [--out outputs/benchmark_render.json]

Rows (seconds per frame or per test view, same machine, same model, same image size):
- spiral frame, before: nerfstudio's ``get_spiral_path`` from the first test camera, every scale rendered
  (what ``ns-render spiral`` did: outside the viewer the model rendered all scales);
- spiral frame, now: the scene's path (``video.scene_video_cameras``), full scale only (the default);
- ns-eval per view, before / now: nerfstudio's ``get_average_eval_image_metrics`` (what ``ns-eval`` runs) with
  every scale, then with the default (full scale only);
- offline evaluator per view: ``offline_tools.score_test_view``, what ``offline_tools eval`` runs per view.
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
    from nerfstudio.cameras.camera_paths import get_spiral_path
    from nerfstudio.utils.eval_utils import eval_setup
    from frugalnerf_ns.scoring.lpips_offline import OfflineLPIPS
    from frugalnerf_ns.tools.offline_tools import score_test_view
    from frugalnerf_ns.tools.video import scene_video_cameras

    _, pipeline, _, _ = eval_setup(args.config, test_mode="test")
    pipeline.eval()
    model, datamanager = pipeline.model, pipeline.datamanager
    every_scale = model.field.num_scales
    start = datamanager.eval_dataset.cameras[0:1]
    size = f"{int(start.width)}x{int(start.height)}"
    dataset = datamanager.eval_dataset
    views = list(range(min(args.views, len(dataset))))

    def render_path(cameras, scales):
        model.num_rendered_scales = scales
        with torch.no_grad():
            for i in range(len(cameras)):
                model.get_outputs_for_camera(cameras[i : i + 1].to(model.device))

    def ns_eval(scales):
        model.num_rendered_scales = scales
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

    theirs = get_spiral_path(start, steps=args.frames, radius=0.1)
    ours = scene_video_cameras(datamanager, start, args.frames)
    ns_eval(None)  # warm-up: LPIPS weights, first-call allocations
    rows = [
        ("spiral frame, before (nerfstudio path, every scale)", timed(lambda: render_path(theirs, every_scale)) / args.frames),
        ("spiral frame, now (scene path, full scale)", timed(lambda: render_path(ours, None)) / args.frames),
        ("ns-eval per test view, before (every scale)", timed(lambda: ns_eval(every_scale)) / len(views)),
        ("ns-eval per test view, now (full scale)", timed(lambda: ns_eval(None)) / len(views)),
        ("offline evaluator per test view", timed(offline) / len(views)),
    ]
    model.num_rendered_scales = None
    records = [{"run": str(args.config.parent), "row": name, "seconds": seconds, "image": size,
                "threads": torch.get_num_threads(), "device": str(pipeline.device)} for name, seconds in rows]
    heading = f"{args.config.parent} ({size}, {torch.get_num_threads()} threads)"
    table = markdown_table(records, [(heading, lambda r: r["row"]), ("seconds", lambda r: f"{r['seconds']:.2f}")])
    write_report("benchmark_render", table, records, args.out)
    return records
