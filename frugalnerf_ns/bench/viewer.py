"""How fast the viewer renders a trained run on this machine, per render mode (table + JSON).

  frugalnerf-bench viewer <run>/config.yml [<run2>/config.yml ...] [--out outputs/viewer.json]

For every run: the full-resolution frame the viewer shows when the camera rests (``--max-res``, nerfstudio's
default 512) and the preview it renders while the camera moves, in three modes: every scale plus the
pseudo-GT scale map (the default), every scale without the map, and the full scale only (the "Render lower
scales" checkbox off). nerfstudio sizes the moving preview from the measured rays per second so it takes
1/30 s, but never below 30 px high; the table gives that preview size and how long it really takes here.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Dict, List

import torch
from nerfstudio.utils.eval_utils import eval_setup

from frugalnerf_ns.config_files import outputs_dir
from frugalnerf_ns.bench.report import markdown_table, write_report

MODES = {
    "all scales + scale map": (True, True),
    "all scales": (True, False),
    "full scale only": (False, False),
}
VIEWER_FPS, MIN_PREVIEW_HEIGHT = 30, 30  # nerfstudio 1.1.5 render_state_machine


def frame_seconds(model, camera, repeats: int) -> float:
    times = []
    with torch.no_grad():
        for _ in range(repeats):
            start = time.perf_counter()
            model.get_outputs_for_camera(camera)
            times.append(time.perf_counter() - start)
    return min(times)  # the least disturbed repeat


def benchmark_run(config: Path, max_res: int, repeats: int) -> List[Dict]:
    _, pipeline, _, _ = eval_setup(config, test_mode="test")  # what ns-viewer loads
    model = pipeline.model
    manager = pipeline.datamanager
    if model.reference_views is None and getattr(manager, "warp_images", None) is not None:
        # Runs trained before the FrugalPipeline have no map in the viewer; measure it anyway.
        model.set_reference_views(manager.warp_images, manager.warp_camera_to_worlds, manager.warp_intrinsics)
    cameras = manager.eval_dataset.cameras
    aspect = float(cameras.width[0]) / float(cameras.height[0])

    def camera_of_height(height: int):
        camera = cameras[0:1]  # a new object: rescaling it leaves the dataset's cameras alone
        camera.rescale_output_resolution(height / float(camera.height), scale_rounding_mode="round")
        return camera

    rows = []
    for mode, (lower_scales, scale_map) in MODES.items():
        model.viewer_lower_scales.value, model.render_scale_map = lower_scales, scale_map
        # What the viewer's checkbox gives (no viewer is attached here, so say it outright).
        model.num_rendered_scales = model.field.num_scales if lower_scales else 1
        still = camera_of_height(int(min(max_res, max_res / aspect)))
        seconds = frame_seconds(model, still, repeats)
        rays_per_second = int(still.height) * int(still.width) / seconds
        preview_height = int(round((rays_per_second / VIEWER_FPS / aspect) ** 0.5, -1))
        preview = camera_of_height(max(MIN_PREVIEW_HEIGHT, min(int(still.height), preview_height)))
        rows.append({
            "run": str(config.parent), "mode": mode, "frame": f"{int(still.width)}x{int(still.height)}",
            "frame_seconds": seconds, "rays_per_second": rays_per_second,
            "preview": f"{int(preview.width)}x{int(preview.height)}",
            "preview_seconds": frame_seconds(model, preview, repeats),
        })
    return rows


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(prog="frugalnerf-bench viewer", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("configs", type=Path, nargs="+", help="config.yml of trained runs")
    parser.add_argument("--max-res", type=int, default=512, help="the viewer's Max res (nerfstudio default 512)")
    parser.add_argument("--repeats", type=int, default=2, help="renders per measurement; the fastest counts")
    parser.add_argument("--out", type=Path, default=outputs_dir("viewer_benchmark.json"))
    args = parser.parse_args(argv)
    for config in args.configs:
        if not config.is_file():
            parser.error(f"no config at {config} (pass a run's config.yml)")
    rows = [row for config in args.configs for row in benchmark_run(config, args.max_res, args.repeats)]
    table = markdown_table(rows, [
        ("run", lambda r: Path(r["run"]).parent.parent.name), ("mode", lambda r: r["mode"]),
        ("still frame", lambda r: r["frame"]), ("s/frame", lambda r: f"{r['frame_seconds']:.2f}"),
        ("rays/s", lambda r: f"{r['rays_per_second']:,.0f}"), ("moving preview", lambda r: r["preview"]),
        ("s/preview", lambda r: f"{r['preview_seconds']:.3f}"),
    ])
    write_report("benchmark_viewer", table, rows, args.out)
