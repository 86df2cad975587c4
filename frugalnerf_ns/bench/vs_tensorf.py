"""FrugalNeRF (three weight-sharing scales) vs nerfstudio's tensorf: time per iteration, peak memory, test PSNR.

Both methods train on the same scene, split, rays per batch, iteration count and full-resolution grid
(fixed: no upsampling, no alpha mask, so the grids stay equal all run). FrugalNeRF uses the paper's
per-plane component counts (16/4/4 density, 48/12/12 appearance); tensorf uses nerfstudio's (16 and 48 on
every plane). A FrugalNeRF row with one scale (L = 0) shows what the two lower scales cost.

Each method runs in its own subprocess so that peak memory is its own. Prints a table and writes JSON.

Usage: frugalnerf-bench vs-tensorf [--iterations 300] [--resolution 64] [--rays 1024]
       [--scene DIR] [--output outputs/benchmark/benchmark_vs_tensorf.json]
The target (issue 2): FrugalNeRF's s/iter at most 1.5x tensorf's.
"""

from __future__ import annotations

import argparse
import json
import resource
import statistics
import subprocess
import sys
from pathlib import Path
from typing import Any, Dict, List, Optional

from frugalnerf_ns.config_files import outputs_dir
from frugalnerf_ns.bench.cli import worker_command
from frugalnerf_ns.bench.report import markdown_table, write_report

METHODS = ("frugalnerf", "frugalnerf-L0", "tensorf")
TARGET_RATIO = 1.5


# ---- worker (one method, own process) ----------------------------------------------------------------------
def _trainer_config(method: str, args: argparse.Namespace):
    from nerfstudio.configs.method_configs import method_configs
    from nerfstudio.data.datamanagers.base_datamanager import VanillaDataManagerConfig

    from frugalnerf_ns.data.input_checks import FrugalNerfstudioDataParserConfig
    from frugalnerf_ns.run.presets import build_trainer_config

    dataparser = FrugalNerfstudioDataParserConfig(data=args.scene, center_method="focus")
    if method.startswith("frugalnerf"):
        config = build_trainer_config("frugalnerf-tiny")
        model = config.pipeline.model
        model.initial_voxels = model.final_voxels = args.resolution**3
        model.upsample_at = ()
        model.alpha_mask_at = ()
        model.density_components = (16, 4, 4)
        model.appearance_components = (48, 12, 12)
        model.mlp_hidden_dim = 128
        model.num_lower_scales = 0 if method.endswith("L0") else 2
    else:
        config = method_configs["tensorf"]
        model = config.pipeline.model
        model.init_resolution = model.final_resolution = args.resolution
        model.upsampling_iters = ()
        # The ParallelDataManager of the stock config spawns workers; both methods use the vanilla one.
        config.pipeline.datamanager = VanillaDataManagerConfig()
    config.pipeline.datamanager.dataparser = dataparser
    config.pipeline.datamanager.train_num_rays_per_batch = args.rays
    config.pipeline.datamanager.eval_num_rays_per_batch = args.rays
    model.eval_num_rays_per_chunk = 4096
    for group in config.optimizers.values():
        if group.get("scheduler") is not None:
            group["scheduler"].max_steps = args.iterations
    return config


def _peak_rss_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # Linux: KiB


def run_worker(method: str, args: argparse.Namespace) -> Dict[str, Any]:
    import torch
    from torchmetrics.functional import structural_similarity_index_measure

    from frugalnerf_ns.scoring.lpips_offline import OfflineLPIPS
    from frugalnerf_ns.tools.offline_tools import patch_torchmetrics_lpips
    from frugalnerf_ns.run.stepping import optimizers_and_callbacks, run_steps

    patch_torchmetrics_lpips()
    torch.manual_seed(0)
    device = "cuda" if torch.cuda.is_available() else "cpu"
    config = _trainer_config(method, args)
    pipeline = config.pipeline.setup(device=device, test_mode="val", world_size=1, local_rank=0)
    pipeline.train()
    optimizers, callbacks = optimizers_and_callbacks(config, pipeline)
    num_parameters = sum(p.numel() for p in pipeline.model.parameters())
    rss_before = _peak_rss_mib()
    if device == "cuda":
        torch.cuda.reset_peak_memory_stats()
    times, _, _ = run_steps(pipeline, optimizers, callbacks, args.iterations)

    # Test views, scored by the same code for both methods.
    pipeline.eval()
    lpips = OfflineLPIPS().to(device)
    psnrs, ssims, lpipss = [], [], []
    for camera, batch in pipeline.datamanager.fixed_indices_eval_dataloader:
        with torch.no_grad():
            rgb = pipeline.model.get_outputs_for_camera(camera.to(device))["rgb"].clamp(0, 1)
        image = batch["image"].to(device)[..., :3]
        psnrs.append(float(-10 * torch.log10(torch.mean((rgb - image) ** 2))))
        nchw = lambda x: x.permute(2, 0, 1)[None]  # noqa: E731
        ssims.append(float(structural_similarity_index_measure(nchw(rgb), nchw(image))))
        lpipss.append(float(lpips(nchw(rgb), nchw(image))))

    warm = times[min(10, len(times) // 5):]  # skip warm-up iterations (allocator, first-call overheads)
    result = {
        "method": method,
        "device": device,
        "iterations": args.iterations,
        "rays_per_batch": args.rays,
        "grid_resolution": args.resolution,
        "parameters": num_parameters,
        "s_per_iter_median": statistics.median(warm),
        "s_per_iter_mean": statistics.fmean(warm),
        "train_seconds": sum(times),
        "psnr": statistics.fmean(psnrs),
        "ssim": statistics.fmean(ssims),
        "lpips": statistics.fmean(lpipss),
        "peak_rss_mib": _peak_rss_mib(),
        "rss_growth_mib": _peak_rss_mib() - rss_before,
    }
    if device == "cuda":
        result["peak_cuda_mib"] = torch.cuda.max_memory_allocated() / 2**20
    return result


# ---- driver -------------------------------------------------------------------------------------------------
def table(results: List[Dict[str, Any]]) -> str:
    cuda = any("peak_cuda_mib" in r for r in results)

    def memory(r: Dict[str, Any]) -> str:
        return f"{r['peak_cuda_mib']:.0f}" if cuda else f"{r['peak_rss_mib']:.0f} ({r['rss_growth_mib']:+.0f})"

    return markdown_table(results, [
        ("method", lambda r: r["method"]), ("params", lambda r: f"{r['parameters'] / 1e6:.2f}M"),
        ("s/iter (median)", lambda r: f"{r['s_per_iter_median']:.4f}"), ("train s", lambda r: f"{r['train_seconds']:.1f}"),
        ("peak CUDA MiB" if cuda else "peak RSS MiB (growth)", memory), ("PSNR", lambda r: f"{r['psnr']:.2f}"),
        ("SSIM", lambda r: f"{r['ssim']:.3f}"), ("LPIPS", lambda r: f"{r['lpips']:.3f}"),
    ])


def main(argv: Optional[List[str]] = None) -> None:
    parser = argparse.ArgumentParser(prog="frugalnerf-bench vs-tensorf", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scene", type=Path, default=outputs_dir("benchmark", "scene"), help="nerfstudio scene (written if missing)")
    parser.add_argument("--iterations", type=int, default=300)
    parser.add_argument("--resolution", type=int, default=64, help="full-resolution grid per axis, both methods")
    parser.add_argument("--rays", type=int, default=1024, help="rays per batch, both methods")
    parser.add_argument("--methods", nargs="+", default=list(METHODS), choices=METHODS)
    parser.add_argument("--output", type=Path, default=outputs_dir("benchmark", "benchmark_vs_tensorf.json"))
    parser.add_argument("--worker", choices=METHODS, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)

    if args.worker:
        print("RESULT " + json.dumps(run_worker(args.worker, args)))
        return

    if not (args.scene / "transforms.json").exists():
        from frugalnerf_ns.data.procedural_scene import write_procedural_scene

        write_procedural_scene(args.scene)
    results = []
    for method in args.methods:
        print(f"benchmark: training {method} ({args.iterations} iterations, {args.resolution}^3 grid, {args.rays} rays)")
        cmd = worker_command("vs-tensorf", "--worker", method, "--scene", str(args.scene), "--iterations",
                             str(args.iterations), "--resolution", str(args.resolution), "--rays", str(args.rays))
        proc = subprocess.run(cmd, capture_output=True, text=True)
        lines = [line for line in proc.stdout.splitlines() if line.startswith("RESULT ")]
        if proc.returncode != 0 or not lines:
            sys.exit(f"benchmark: {method} failed:\n{proc.stderr[-3000:]}")
        results.append(json.loads(lines[-1][len("RESULT "):]))

    by_name = {r["method"]: r for r in results}
    summary: Dict[str, Any] = {"results": results}
    text = table(results)
    if "frugalnerf" in by_name and "tensorf" in by_name:
        ratio = by_name["frugalnerf"]["s_per_iter_median"] / by_name["tensorf"]["s_per_iter_median"]
        summary["frugalnerf_over_tensorf_time_ratio"] = ratio
        verdict = "meets" if ratio <= TARGET_RATIO else "MISSES"
        text += f"\n\nfrugalnerf / tensorf time per iteration: {ratio:.2f}x ({verdict} the <= {TARGET_RATIO}x target)"
    write_report("vs_tensorf", text, summary, args.output)
