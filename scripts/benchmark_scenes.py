"""Train and evaluate FrugalNeRF (and optionally nerfstudio baselines) on the scenes of a config file.

Every run goes through ``python -m frugalnerf_ns.offline_tools`` (ns-train with offline LPIPS) and is scored
by the same evaluator (masked for DTU). Writes a Markdown table and JSON: per scene and the average, PSNR /
SSIM / LPIPS / training time / checkpoint size / peak memory, side by side.

Usage:
  python scripts/benchmark_scenes.py [--config configs/benchmark_scenes.yaml] [--scenes fern dtu_scan65]
         [--baselines tensorf nerfacto] [--variants no-geo no-novel single-scale] [--preset frugalnerf-cpu]
         [--max-iterations N] [--seeds 42 43] [--out outputs/benchmark]

``--variants`` adds FrugalNeRF runs with the named option sets of the config's ``variants`` section (the
paper's ablations), each labelled ``<preset>[<variant>]`` in the table. ``--seeds`` repeats every run with each
seed (nerfstudio's ``--machine.seed``; FrugalNeRF's batch sampler ``--pipeline.datamanager.seed`` too) and adds
a mean row with the spread (max - min) per scene and method.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Any, Dict, List, Optional

import yaml

ROOT = Path(__file__).resolve().parents[1]
QUIET = ["--vis", "tensorboard", "--steps-per-eval-image", "1000000", "--steps-per-eval-batch", "1000000",
         "--steps-per-eval-all-images", "1000000"]


def device_args() -> List[str]:
    """nerfstudio's methods default to CUDA; use the CPU where there is no GPU."""
    import torch

    return [] if torch.cuda.is_available() else ["--machine.device-type", "cpu"]


def run_location(out: Path, scene: str, method: str, label: str, timestamp: str = "bench"):
    """(experiment name, run folder) of one run. Variants keep the registered method name, which ns-eval and
    eval_setup look up, and get their own experiment folder instead."""
    experiment = scene if label == method else f"{scene}-{label.replace(method, '').strip('[]')}"
    return experiment, out / "runs" / experiment / method / timestamp


def seed_args(method: str, seed: Optional[int]) -> List[str]:
    """Options that seed one run: torch/numpy/random for every method, our batch sampler for ours."""
    if seed is None:
        return []
    ours = ["--pipeline.datamanager.seed", str(seed)] if method.startswith("frugalnerf") else []
    return ["--machine.seed", str(seed), *ours]


def run_method(
    method: str, scene: str, data: Path, parser_args: List[str], extra: List[str], out: Path, label: Optional[str] = None,
    seed: Optional[int] = None,
) -> Dict[str, Any]:
    """Train ``method`` (shown as ``label``) on one scene with ``seed`` (None: the method's default), score its
    test views, return one table row."""
    label = label or method
    timestamp = "bench" if seed is None else f"seed{seed}"
    extra = [*extra, *seed_args(method, seed)]
    experiment, run_dir = run_location(out, scene, method, label, timestamp)
    train = [
        "/usr/bin/time", "-f", "PEAK_RSS_KB %M",
        sys.executable, "-m", "frugalnerf_ns.offline_tools", "train", method, "--data", str(data),
        "--output-dir", str(out / "runs"), "--experiment-name", experiment, "--timestamp", timestamp,
        *QUIET, *device_args(), *extra, *parser_args,
    ]
    start = time.time()
    proc = subprocess.run(train, capture_output=True, text=True)
    seconds = time.time() - start
    if proc.returncode != 0:
        sys.exit(f"benchmark: training {method} on {scene} failed:\n{proc.stderr[-3000:]}")
    peak = [line for line in proc.stderr.splitlines() if line.startswith("PEAK_RSS_KB")]
    evaluation = subprocess.run(
        [sys.executable, "-m", "frugalnerf_ns.offline_tools", "eval", str(run_dir / "config.yml")],
        capture_output=True, text=True,
    )
    lines = [line for line in evaluation.stdout.splitlines() if line.startswith("RESULT ")]
    if evaluation.returncode != 0 or not lines:
        sys.exit(f"benchmark: evaluating {method} on {scene} failed:\n{evaluation.stderr[-3000:]}")
    ckpt = sorted((run_dir / "nerfstudio_models").glob("step-*.ckpt"))[-1]
    return {
        "scene": scene,
        "method": label,
        **json.loads(lines[-1][len("RESULT "):]),
        "train_seconds": seconds,
        "checkpoint_mb": ckpt.stat().st_size / 1e6,
        "peak_rss_mib": int(peak[-1].split()[1]) / 1024 if peak else None,
        "run_dir": str(run_dir),
        "seed": seed,
    }


def markdown(results: List[Dict[str, Any]]) -> str:
    """One row per run; runs scored on a published shorter test list too (DTU: RegNeRF's 25 views beside
    pixelNeRF's 40) get those three metrics in extra columns."""
    subsets = list(dict.fromkeys(k[: -len("_psnr")] for r in results for k in r if k.endswith("_psnr")))
    head = "| scene | method | PSNR | SSIM | LPIPS |" + "".join(f" PSNR / SSIM / LPIPS ({s}) |" for s in subsets)
    seeded = any(r.get("seed") is not None for r in results)
    head = head.replace("| method |", "| method | seed |") if seeded else head
    rows = [head + " train time | checkpoint MB | peak RSS MiB |", "|---" * (8 + len(subsets) + seeded) + "|"]

    def cells(r: Dict[str, Any]) -> str:
        text = f"{r['psnr']:.2f} | {r['ssim']:.3f} | {r.get('lpips', float('nan')):.3f} |"
        for subset in subsets:
            values = [r.get(f"{subset}_{k}") for k in ("psnr", "ssim", "lpips")]
            text += " " + (" / ".join(f"{v:.3f}" if v is not None else "-" for v in values)) + " |"
        return text

    methods = list(dict.fromkeys(r["method"] for r in results))
    scenes = list(dict.fromkeys(r["scene"] for r in results))
    for r in results:
        seed = f" {r.get('seed')} |" if seeded else ""
        rows.append(
            f"| {r['scene']} | {r['method']} |{seed} {cells(r)} "
            f"{r['train_seconds'] / 60:.1f} min | {r['checkpoint_mb']:.1f} | {r['peak_rss_mib'] or 0:.0f} |"
        )
    for scene in scenes:
        for m in methods:
            rs = [r for r in results if r["scene"] == scene and r["method"] == m]
            if seeded and len(rs) > 1:
                spread = {k: max(r[k] for r in rs) - min(r[k] for r in rs) for k in ("psnr", "ssim", "lpips")}
                mean = {k: statistics.fmean(r[k] for r in rs) for k in ("psnr", "ssim", "lpips", "train_seconds")}
                rows.append(
                    f"| {scene} | {m} | mean of {len(rs)} (spread) | {mean['psnr']:.2f} ({spread['psnr']:.2f}) | "
                    f"{mean['ssim']:.3f} ({spread['ssim']:.3f}) | {mean['lpips']:.3f} ({spread['lpips']:.3f}) |"
                    + " |" * len(subsets) + f" {mean['train_seconds'] / 60:.1f} min | | |"
                )
    if len(scenes) > 1:
        for m in methods:
            rs = [r for r in results if r["method"] == m]
            if len({r["scene"] for r in rs}) == len(scenes):
                avg = {k: statistics.fmean(r[k] for r in rs) for k in ("psnr", "ssim", "lpips", "train_seconds", "checkpoint_mb")}
                rows.append(
                    f"| average | {m} |" + (" all |" if seeded else "") + f" {avg['psnr']:.2f} | {avg['ssim']:.3f} | {avg['lpips']:.3f} |"
                    + " |" * len(subsets) + f" {avg['train_seconds'] / 60:.1f} min | {avg['checkpoint_mb']:.1f} | |"
                )
    return "\n".join(rows)


def main(argv: Optional[List[str]] = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--config", type=Path, default=ROOT / "configs" / "benchmark_scenes.yaml")
    parser.add_argument("--scenes", nargs="*", help="scene names from the config (default: all)")
    parser.add_argument("--baselines", nargs="*", default=[], help="nerfstudio methods to train too (tensorf, nerfacto)")
    parser.add_argument("--variants", nargs="*", default=[], help="FrugalNeRF ablations from the config's variants")
    parser.add_argument("--preset", help="FrugalNeRF method for every scene (default: each scene's preset)")
    parser.add_argument("--only-baselines", action="store_true", help="skip FrugalNeRF (e.g. to add baselines later)")
    parser.add_argument("--max-iterations", type=int, help="override every method's iteration budget")
    parser.add_argument("--seeds", type=int, nargs="*", default=[], help="repeat every run with each seed")
    parser.add_argument("--out", type=Path, default=ROOT / "outputs" / "benchmark")
    args = parser.parse_args(argv)

    config = yaml.safe_load(args.config.read_text())
    names = args.scenes or list(config["scenes"])
    results = []
    for name in names:
        scene = config["scenes"][name]
        data = (ROOT / scene["data"]).resolve()
        if not data.is_dir():
            print(f"benchmark: skipping {name}: {data} not found")
            continue
        budget = ["--max-num-iterations", str(args.max_iterations)] if args.max_iterations else []
        preset = args.preset or scene["preset"]
        runs = [] if args.only_baselines else [(preset, preset, scene["parser"], budget)]
        for variant in args.variants:
            runs.append((preset, f"{preset}[{variant}]", scene["parser"], list(config["variants"][variant]) + budget))
        for baseline in args.baselines:
            extra = list(config["baselines"][baseline]["args"]) + budget
            runs.append((baseline, baseline, scene["baseline_parser"], extra))
        for (method, label, parser_args, extra), seed in [(run, seed) for run in runs for seed in args.seeds or [None]]:
            print(f"benchmark: {name}: training {label}" + (f" (seed {seed})" if seed is not None else "") + " ...", flush=True)
            results.append(run_method(method, name, data, parser_args, extra, args.out, label, seed))
            r = results[-1]
            args.out.mkdir(parents=True, exist_ok=True)
            (args.out / "benchmark_scenes.json").write_text(json.dumps(results, indent=2))  # partial results survive
            print(f"  PSNR {r['psnr']:.2f}  SSIM {r['ssim']:.3f}  LPIPS {r['lpips']:.3f}  {r['train_seconds'] / 60:.1f} min")

    table = markdown(results)
    print()
    print(table)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "benchmark_scenes.json").write_text(json.dumps(results, indent=2))
    (args.out / "benchmark_scenes.md").write_text(table + "\n")
    print(f"\nwrote {args.out / 'benchmark_scenes.md'} and {args.out / 'benchmark_scenes.json'}")


if __name__ == "__main__":
    main()
