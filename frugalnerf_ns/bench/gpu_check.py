"""Check a CUDA machine end to end for FrugalNeRF: one command, one table, one JSON file.

  frugalnerf-bench gpu-check [--fern ../shared/data/llff/fern] [--out outputs/gpu_check] [--parts ...]
  frugalnerf-bench gpu-check --dry-run      # no GPU needed: a few CPU steps of every part (tests the script)

Parts (``--parts``, all by default):
  presets     every registered preset for a few steps on the procedural scene and on fern, with the grid at the
              preset's final size (the steady state): losses finite, every parameter, buffer and output on the
              GPU, the CPU-only grid-sample backward never called, the tinycudann colour MLP used where it can
              run; time per step and peak GPU memory per preset.
  paper       the paper preset ``frugalnerf`` trained to completion on fern 2-view (views 6, 13) at 1008x756
              (images_4) and scored by the offline evaluator; targets 17.4 / 0.47 / 0.41 in <= 5 minutes.
  speed       time per training step of FrugalNeRF vs nerfstudio's tensorf at equal grid and rays per batch,
              same GPU, same run (``frugalnerf-bench vs-tensorf``: synchronised, median after warm-up);
              target <= 1.3x.
  grid_sample the bilinear plane read: torch's grid_sample backward vs the index_add backward written for the
              CPU, on this device, at the paper's plane size: decides whether the CPU path should run here.
  memory      peak GPU memory of the paper preset at growing grid sizes, and the largest grid that fits a
              24 GB card (fitted a + b R^2 on max_memory_reserved, 1 GiB kept for the CUDA context).
  tcnn        if tinycudann imports: its colour MLP against the torch MLP given the same weights (outputs within
              fp16 tolerance) and their speed.
  kernels     the fused kernels (NVIDIA Warp, compiled by NVRTC) on this device against the torch path there: the
              inference march and feature reads, a training step's reads with their backward, the space beyond a
              box (``bench/kernel_check.py``): equal within 1/255 (pixels) or 1e-4 (gradients), and their times.

Without CUDA (and without --dry-run) it says so in one line and exits 0.
"""

from __future__ import annotations

import argparse
import json
import math
import platform
import statistics
import subprocess
import tempfile
import time
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence

import torch

from frugalnerf_ns.bench.cli import worker_command
from frugalnerf_ns.bench.device_probes import (
    count_cpu_path_calls,
    misplaced,
    peak_mib,
    reset_peak,
    timed,
    walk,
)
from frugalnerf_ns.bench.kernel_check import part_kernels
from frugalnerf_ns.bench.report import write_report
from frugalnerf_ns.run.stepping import run_steps
from frugalnerf_ns.config_files import outputs_dir, shared_data


PARTS = ("presets", "paper", "speed", "grid_sample", "memory", "tcnn", "kernels")
PAPER_TARGET = {"psnr": 17.4, "ssim": 0.47, "lpips": 0.41, "train_seconds": 300.0}
SPEED_TARGET = 1.3
CONSUMER_CARD_GIB = 24.0
CONTEXT_RESERVE_GIB = 1.0


# ---- part: presets ---------------------------------------------------------------------------------------
def build_pipeline(preset: str, data: Path, device: torch.device, dry_run: bool, train_views=None,
                   final_grid: Optional[int] = None):
    """The preset's pipeline on ``data`` (training split), grid upsampled to its final size, plus optimisers."""
    from frugalnerf_ns.bench.pipelines import preset_pipeline
    from frugalnerf_ns.run.stepping import optimizers_and_callbacks

    def configure(config) -> None:
        if dry_run:  # a CPU can afford a few small steps of each preset, not 4096 + 4096 rays on a 640^3 grid
            config.pipeline.datamanager.train_num_rays_per_batch = 100
            config.pipeline.datamanager.num_novel_rays_per_batch = 50
            config.pipeline.model.final_voxels = min(config.pipeline.model.final_voxels, 32**3)
        if final_grid is not None:
            config.pipeline.model.final_voxels = final_grid**3

    config, pipeline = preset_pipeline(preset, data, device=str(device), train_views=train_views, configure=configure)
    pipeline.train()
    optimizers, callbacks = optimizers_and_callbacks(config, pipeline)
    return config, pipeline, optimizers, callbacks


def check_preset(preset: str, scene: str, data: Path, device: torch.device, steps: int, dry_run: bool,
                 train_views=None) -> Dict[str, Any]:
    from frugalnerf_ns.field.color_mlp import tcnn_available

    reset_peak(device)
    row: Dict[str, Any] = {"part": "presets", "preset": preset, "scene": scene}
    try:
        with count_cpu_path_calls() as cpu_path:
            _, pipeline, optimizers, callbacks = build_pipeline(preset, data, device, dry_run, train_views)
            times, losses, outputs = run_steps(pipeline, optimizers, callbacks, steps)
        model = pipeline.model
        tensors = [*model.named_parameters(), *model.named_buffers(), *walk("outputs", outputs), *walk("losses", losses)]
        wrong = misplaced(iter(tensors), device)
        mlp = model.field.color_mlp.implementation
        expected_mlp = "tcnn" if tcnn_available() else "torch"
        finite = all(math.isfinite(float(v.detach())) for v in losses.values())
        cpu_path_on_gpu = cpu_path.get("cuda", 0)
        row.update({
            "steps": steps,
            "grid": list(model.field.density_grid.resolution.tolist()),
            "s_per_step": statistics.median(times[1:] if len(times) > 1 else times),
            "peak_mib": peak_mib(device),
            "losses_finite": finite,
            "checked_tensors": len(tensors),
            "misplaced_tensors": wrong[:5],
            "cpu_path_calls_on_gpu": cpu_path_on_gpu,
            "color_mlp": mlp,
            "ok": finite and not wrong and cpu_path_on_gpu == 0 and mlp == expected_mlp,
        })
        if mlp != expected_mlp:
            row["error"] = f"colour MLP is {mlp}, expected {expected_mlp}"
        del pipeline, optimizers, callbacks, model, outputs, losses
    except Exception as err:  # one preset's failure is a row of the table, not the end of the check
        row.update({"ok": False, "error": f"{type(err).__name__}: {str(err).splitlines()[0][:200] if str(err) else ''}"})
    reset_peak(device)
    return row


def part_presets(args, device: torch.device, scenes: Dict[str, Dict[str, Any]]) -> List[Dict[str, Any]]:
    from frugalnerf_ns.run.presets import load_preset_table

    presets = args.presets or list(load_preset_table())
    rows = []
    for scene, spec in scenes.items():
        if scene not in args.scenes:
            continue
        for preset in presets:
            print(f"gpu_check: presets: {preset} on {scene} ...", flush=True)
            rows.append(check_preset(preset, scene, spec["data"], device, args.steps, args.dry_run, spec.get("train_views")))
    return rows


# ---- part: paper preset trained on fern ------------------------------------------------------------------
def part_paper(args, device: torch.device, scenes: Dict[str, Dict[str, Any]]) -> List[Dict[str, Any]]:
    from frugalnerf_ns.tools.sweep.grid import RunSpec
    from frugalnerf_ns.tools.sweep.runner import execute

    if args.dry_run:
        spec = RunSpec("procedural", 0, "frugalnerf-tiny", "full", str(scenes["procedural"]["data"]), [],
                       ["--max-num-iterations", "4"])
    else:
        if "fern" not in scenes:
            return [{"part": "paper", "ok": False, "error": f"no LLFF fern at {args.fern} (--fern)"}]
        spec = RunSpec("fern_images4", 2, "frugalnerf", "full", str(scenes["fern"]["data"]),
                       ["frugal-llff", "--downscale-factor", "4", "--train-views", "6", "13"], [])
    print(f"gpu_check: paper: training {spec.method} on {spec.scene} to completion ...", flush=True)
    record = execute(spec, args.out / "paper")
    row: Dict[str, Any] = {"part": "paper", "preset": spec.method, "scene": spec.scene}
    if record["status"] != "ok":
        return [{**row, "ok": False, "error": f"{record.get('error')} (log {record.get('log')})"}]
    row.update({k: record[k] for k in ("psnr", "ssim", "lpips", "train_seconds")})
    row["meets_target"] = (row["psnr"] >= PAPER_TARGET["psnr"] and row["ssim"] >= PAPER_TARGET["ssim"]
                           and row["lpips"] <= PAPER_TARGET["lpips"] and row["train_seconds"] <= PAPER_TARGET["train_seconds"])
    row["ok"] = all(math.isfinite(row[k]) for k in ("psnr", "ssim", "lpips"))
    return [row]


# ---- part: speed against tensorf -------------------------------------------------------------------------
def part_speed(args, device: torch.device, scenes: Dict[str, Dict[str, Any]]) -> List[Dict[str, Any]]:
    resolution, rays, iterations = (16, 64, 4) if args.dry_run else (300, 4096, 300)
    output = args.out / "speed.json"
    cmd = worker_command("vs-tensorf", "--scene", str(scenes["procedural"]["data"]), "--iterations", str(iterations),
                         "--resolution", str(resolution), "--rays", str(rays), "--methods", "frugalnerf", "tensorf",
                         "--output", str(output))
    print(f"gpu_check: speed: frugalnerf vs tensorf, {resolution}^3 grid, {rays} rays, {iterations} steps ...", flush=True)
    proc = subprocess.run(cmd, capture_output=True, text=True)
    if proc.returncode != 0 or not output.exists():
        tail = (proc.stderr or proc.stdout).strip().splitlines()
        return [{"part": "speed", "ok": False, "error": tail[-1][:200] if tail else f"exit {proc.returncode}"}]
    summary = json.loads(output.read_text())
    rows = []
    for result in summary["results"]:
        rows.append({"part": "speed", "preset": result["method"], "grid": [resolution] * 3, "rays": rays,
                     "s_per_step": result["s_per_iter_median"], "peak_mib": result.get("peak_cuda_mib", result["peak_rss_mib"]),
                     "ok": True})
    ratio = summary.get("frugalnerf_over_tensorf_time_ratio")
    rows.append({"part": "speed", "preset": "ratio", "ratio": ratio, "meets_target": ratio is not None and ratio <= SPEED_TARGET,
                 "ok": ratio is not None})
    return rows


# ---- part: grid_sample backward on this device -----------------------------------------------------------
def part_grid_sample(args, device: torch.device, scenes) -> List[Dict[str, Any]]:
    import torch.nn.functional as F

    from frugalnerf_ns.field.tensorial import _BilinearSampleCPU

    # The paper preset's largest plane: 48 appearance components on 640 x 640; 4096 + 4096 rays x ~100 samples.
    channels, size, points = (12, 64, 20_000) if args.dry_run else (48, 640, 800_000)
    generator = torch.Generator(device="cpu").manual_seed(0)
    plane = torch.randn(1, channels, size, size, generator=generator).to(device).requires_grad_(True)
    x = (torch.rand(points, generator=generator) * 2 - 1).to(device)
    y = (torch.rand(points, generator=generator) * 2 - 1).to(device)
    upstream = torch.randn(channels, points, generator=generator).to(device)

    def torch_path():
        plane.grad = None
        grid = torch.stack([x, y], dim=-1).view(1, -1, 1, 2)
        out = F.grid_sample(plane, grid, mode="bilinear", padding_mode="border", align_corners=True).view(channels, -1)
        out.backward(upstream)

    def index_add_path():
        plane.grad = None
        _BilinearSampleCPU.apply(plane, x, y, 1).backward(upstream)

    torch_path()
    reference = plane.grad.clone()
    index_add_path()
    difference = float((plane.grad - reference).abs().max())
    repeats, warmup = (3, 1) if args.dry_run else (20, 3)
    t_torch = timed(torch_path, device, repeats, warmup)
    t_index = timed(index_add_path, device, repeats, warmup)
    faster = "index_add" if t_index < t_torch else "grid_sample"
    # sample_plane uses grid_sample on CUDA; the row says whether a measurement contradicts that choice.
    used_here = "grid_sample" if device.type == "cuda" else "index_add"
    return [{"part": "grid_sample", "preset": f"plane {channels}x{size}^2, {points} points", "s_grid_sample": t_torch,
             "s_index_add": t_index, "max_grad_difference": difference, "faster": faster, "used": used_here,
             "ok": difference < 1e-3, "meets_target": faster == used_here}]


# ---- part: memory against grid size ----------------------------------------------------------------------
def part_memory(args, device: torch.device, scenes) -> List[Dict[str, Any]]:
    spec = scenes.get("fern") or scenes["procedural"]
    sizes = (16, 24, 32) if args.dry_run else (320, 640, 960, 1280)
    rows, fitted = [], []
    for size in sizes:
        print(f"gpu_check: memory: frugalnerf at {size}^3 ...", flush=True)
        reset_peak(device)
        row: Dict[str, Any] = {"part": "memory", "preset": "frugalnerf", "grid": [size] * 3}
        try:
            _, pipeline, optimizers, callbacks = build_pipeline("frugalnerf", spec["data"], device, args.dry_run,
                                                                spec.get("train_views"), final_grid=size)
            run_steps(pipeline, optimizers, callbacks, 3)
            row["peak_mib"] = peak_mib(device)
            reserved = torch.cuda.max_memory_reserved(device) / 2**20 if device.type == "cuda" else row["peak_mib"]
            row["reserved_mib"] = reserved
            fitted.append((size, reserved))
            row["ok"] = True
            del pipeline, optimizers, callbacks
        except torch.cuda.OutOfMemoryError:
            row.update({"ok": True, "error": "out of memory"})
        reset_peak(device)
        rows.append(row)
    if len(fitted) >= 2:
        a, b = fit_quadratic(fitted)
        budget = (CONSUMER_CARD_GIB - CONTEXT_RESERVE_GIB) * 1024
        largest = int(math.sqrt(max(budget - a, 0) / b)) if b > 0 else None
        row = {"part": "memory", "preset": f"largest grid in {CONSUMER_CARD_GIB:.0f} GB", "fit_mib": [a, b],
               "largest_grid": largest, "ok": largest is not None}
        if device.type != "cuda":  # a process's peak RSS cannot be reset: the points are not per grid size
            row.update({"ok": True, "note": "CPU dry run: peak RSS is cumulative, the fit means nothing"})
        rows.append(row)
    return rows


def fit_quadratic(points: Sequence[tuple]) -> tuple:
    """Least-squares a, b of memory = a + b * R^2 (the VM planes grow with R^2; lines and rays do not)."""
    xs = [float(r) ** 2 for r, _ in points]
    ys = [float(m) for _, m in points]
    mean_x, mean_y = statistics.fmean(xs), statistics.fmean(ys)
    var = sum((x - mean_x) ** 2 for x in xs)
    b = sum((x - mean_x) * (y - mean_y) for x, y in zip(xs, ys)) / var if var else 0.0
    return mean_y - b * mean_x, b


# ---- part: tinycudann colour MLP -------------------------------------------------------------------------
def torch_mlp_from_tcnn(params: torch.Tensor, in_dim: int, hidden: int, row_major: bool, pad_value: float):
    """The bias-free torch MLP that tinycudann's FullyFusedMLP computes, read from its flat parameter vector
    (inputs padded to a multiple of 16 with ``pad_value``, output padded to 16)."""
    in_pad, out_pad = -(-in_dim // 16) * 16, 16
    shapes = [(hidden, in_pad), (hidden, hidden), (out_pad, hidden)]
    weights, offset = [], 0
    for rows, cols in shapes:
        block = params[offset: offset + rows * cols].float()
        weights.append(block.view(rows, cols) if row_major else block.view(cols, rows).t())
        offset += rows * cols

    def forward(x: torch.Tensor) -> torch.Tensor:
        padded = torch.cat([x, x.new_full((x.shape[0], in_pad - in_dim), pad_value)], dim=-1)
        h = torch.relu(padded @ weights[0].t())
        h = torch.relu(h @ weights[1].t())
        return torch.sigmoid(h @ weights[2].t())[:, :3]

    return forward, offset


def part_tcnn(args, device: torch.device, scenes) -> List[Dict[str, Any]]:
    from frugalnerf_ns.field.color_mlp import ColorMLP, tcnn_available

    if not tcnn_available():
        why = "no CUDA device" if device.type != "cuda" else "tinycudann does not import"
        return [{"part": "tcnn", "preset": "colour MLP", "ok": True, "skipped": why}]
    features, hidden, batch = 27, 128, 4096 * 64
    tcnn_mlp = ColorMLP(features, hidden_dim=hidden, implementation="tcnn").to(device)
    torch_mlp = ColorMLP(features, hidden_dim=hidden, implementation="torch").to(device)
    x = torch.rand(batch, features, device=device)
    with torch.no_grad():
        reference = tcnn_mlp(x)
        params = next(tcnn_mlp.net.parameters()).detach()
        best = None
        for row_major in (True, False):
            for pad_value in (1.0, 0.0):
                forward, used = torch_mlp_from_tcnn(params, tcnn_mlp.in_dim, hidden, row_major, pad_value)
                if used > params.numel():
                    continue
                difference = float((forward(x) - reference).abs().max())
                if best is None or difference < best[0]:
                    best = (difference, row_major, pad_value)

    def step(mlp):
        def run():
            mlp.zero_grad(set_to_none=True)
            mlp(x).sum().backward()
        return run

    t_tcnn = timed(step(tcnn_mlp), device, 20, 3)
    t_torch = timed(step(torch_mlp), device, 20, 3)
    difference = best[0] if best else float("nan")
    return [{"part": "tcnn", "preset": f"colour MLP, {batch} inputs", "s_tcnn": t_tcnn, "s_torch": t_torch,
             "max_output_difference": difference, "layout": None if best is None else
             {"row_major": best[1], "input_pad_value": best[2]}, "ok": difference <= 2e-3}]


# ---- driver ----------------------------------------------------------------------------------------------
def machine_description(device: torch.device) -> Dict[str, Any]:
    from frugalnerf_ns.tools.sweep.runner import cpu_model, git_commit

    info: Dict[str, Any] = {"torch": torch.__version__, "python": platform.python_version(), "device": device.type}
    if device.type == "cuda":
        props = torch.cuda.get_device_properties(device)
        info.update({"gpu": props.name, "gpu_memory_gib": props.total_memory / 2**30, "cuda": torch.version.cuda})
    else:
        info["cpu"] = cpu_model() or platform.machine()
    info["commit"] = git_commit()
    return info


def fmt(value: Any) -> str:
    if value is None:
        return ""
    if isinstance(value, float):
        return f"{value:.4g}"
    if isinstance(value, list):
        return "x".join(str(v) for v in value) if all(isinstance(v, int) for v in value) else str(value)
    return str(value)


def table(rows: List[Dict[str, Any]]) -> str:
    """One Markdown table: part, what, the numbers of that part, ok, target."""
    lines = ["| part | what | scene | numbers | ok | target |", "|---|---|---|---|---|---|"]
    skip = {"part", "preset", "scene", "ok", "meets_target"}
    for row in rows:
        numbers = ", ".join(f"{key}={fmt(value)}" for key, value in row.items() if key not in skip and value not in (None, []))
        target = "" if "meets_target" not in row else ("met" if row["meets_target"] else "MISSED")
        lines.append(f"| {row['part']} | {row.get('preset', '')} | {row.get('scene', '')} | {numbers} | "
                     f"{'yes' if row.get('ok') else 'NO'} | {target} |")
    return "\n".join(lines)


def main(argv: Optional[List[str]] = None) -> int:
    parser = argparse.ArgumentParser(prog="frugalnerf-bench gpu-check", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--dry-run", action="store_true", help="run every part for a few CPU steps (no GPU needed)")
    parser.add_argument("--parts", nargs="+", choices=PARTS, default=list(PARTS))
    parser.add_argument("--presets", nargs="+", help="presets for the presets part (default: all registered)")
    parser.add_argument("--steps", type=int, default=None, help="steps per preset (default 20; dry run 2)")
    parser.add_argument("--fern", type=Path, default=shared_data() / "llff" / "fern")
    parser.add_argument("--scenes", nargs="+", choices=("procedural", "fern"), default=["procedural", "fern"],
                        help="scenes of the presets part (fern only where --fern exists)")
    parser.add_argument("--out", type=Path, default=outputs_dir("gpu_check"))
    args = parser.parse_args(argv)

    if not torch.cuda.is_available() and not args.dry_run:
        print(f"gpu_check: no CUDA device (torch {torch.__version__}, built for CUDA {torch.version.cuda}): nothing to "
              "check here; --dry-run exercises the script on the CPU.")
        return 0
    if "fern" in args.scenes and not (args.fern / "poses_bounds.npy").exists():
        print(f"gpu_check: --fern {args.fern}: no LLFF scene there (poses_bounds.npy); fern rows are left out")
    device = torch.device("cuda" if torch.cuda.is_available() and not args.dry_run else "cpu")
    args.steps = args.steps or (2 if args.dry_run else 20)
    args.out.mkdir(parents=True, exist_ok=True)

    with tempfile.TemporaryDirectory() as tmp:
        from frugalnerf_ns.data.procedural_scene import write_procedural_scene

        scenes: Dict[str, Dict[str, Any]] = {"procedural": {"data": write_procedural_scene(Path(tmp) / "procedural")}}
        if "fern" in args.scenes and (args.fern / "poses_bounds.npy").exists():
            scenes["fern"] = {"data": args.fern, "train_views": (6, 13)}
        parts = {"presets": part_presets, "paper": part_paper, "speed": part_speed, "grid_sample": part_grid_sample,
                 "memory": part_memory, "tcnn": part_tcnn, "kernels": part_kernels}
        rows: List[Dict[str, Any]] = []
        started = time.time()
        for name in args.parts:
            rows.extend(parts[name](args, device, scenes))

    summary = {"machine": machine_description(device), "dry_run": args.dry_run, "seconds": time.time() - started,
               "rows": rows}
    output = args.out / "gpu_check.json"
    write_report("gpu_check", table(rows), summary, output)
    failed = [row for row in rows if not row.get("ok")]
    print(f"gpu_check: {len(rows) - len(failed)}/{len(rows)} rows ok on {summary['machine'].get('gpu', device.type)}")
    return 1 if failed else 0
