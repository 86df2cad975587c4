"""Speed vs accuracy on one scene and split: presets x iteration budgets, the number of scales, and tensorf.

  python scripts/tradeoff.py --scene fern [--presets frugalnerf-cpu] [--budgets 500 1500]
         [--scales 0 1 2 3] [--scales-budget 500] [--grid-sides auto 320] [--anytime-every 500]
         [--tensorf-iterations 1500] [--seed N] [--out outputs/tradeoff]
  python scripts/tradeoff.py --data <scene dir> --parser "frugal-nerfstudio --center-method focus" ...

Every FrugalNeRF run scales its preset's step schedule (upsampling, alpha mask, learning-rate decay) to its
budget and saves a checkpoint every ``--anytime-every`` steps; each checkpoint is scored on the test views
afterwards (``offline_tools eval``), and its wall time is the time from the start of ``ns-train`` (set-up,
triangulation and all) to that checkpoint's file. ``--scales`` runs the first preset with L = 0..3 lower
scales (the paper's ablation) at ``--scales-budget``, and ``--grid-sides`` runs it with each final grid
(``auto``: sized from the training pixels, ``--pipeline.model.auto-grid``; a number N: N^3 voxels);
tensorf (nerfstudio's) runs on the same views as the reference. Writes ``tradeoff.md`` (table),
``tradeoff.json``, ``pareto.png`` (final test PSNR and LPIPS vs wall time, Pareto front marked) and
``anytime.png`` (test PSNR vs wall time during training).
"""

from __future__ import annotations

import argparse
import json
import shlex
import subprocess
import sys
import time
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence

import yaml

sys.path.insert(0, str(Path(__file__).resolve().parent))
from benchmark_scenes import QUIET, ROOT, device_args  # noqa: E402  (a sibling script)

def budget_args(preset: str, iterations: int) -> List[str]:
    """ns-train options that run ``preset`` for ``iterations`` steps. Its whole schedule (learning rates,
    loss weights, upsampling, alpha mask) follows: every schedule is a fraction of the run (FrugalTrainer)."""
    return ["--max-num-iterations", str(iterations)]


def train(label: str, method: str, data: Path, parser_args: Sequence[str], extra: Sequence[str], every: int,
          out: Path, seed: Optional[int] = None) -> Dict[str, Any]:
    """Train one run with a checkpoint every ``every`` steps; return where it is and when each came."""
    if seed is not None:
        extra = [*extra, "--machine.seed", str(seed)]
    experiment = label.replace("/", "-")
    run_dir = out / "runs" / experiment / method / "run"
    command = [
        "/usr/bin/time", "-f", "PEAK_RSS_KB %M", sys.executable, "-m", "frugalnerf_ns.offline_tools", "train", method,
        "--data", str(data), "--output-dir", str(out / "runs"), "--experiment-name", experiment, "--timestamp", "run",
        *QUIET, *device_args(), "--steps-per-save", str(every), "--save-only-latest-checkpoint", "False", *extra,
        *parser_args,
    ]
    print(f"tradeoff: training {label} ...", flush=True)
    start = time.time()
    proc = subprocess.run(command, capture_output=True, text=True)
    if proc.returncode != 0:
        sys.exit(f"tradeoff: training {label} failed:\n{proc.stderr[-3000:]}")
    peak = [line for line in proc.stderr.splitlines() if line.startswith("PEAK_RSS_KB")]
    checkpoints = {
        int(path.stem.split("-")[1]): path for path in sorted((run_dir / "nerfstudio_models").glob("step-*.ckpt"))
    }
    return {
        "label": label, "method": method, "run_dir": run_dir, "seconds": time.time() - start,
        "peak_rss_mib": int(peak[-1].split()[1]) / 1024 if peak else None,
        "checkpoints": {step: (path.stat().st_mtime - start, path.stat().st_size / 1e6) for step, path in checkpoints.items()},
    }


def score(run: Dict[str, Any]) -> List[Dict[str, Any]]:
    """Test metrics at every checkpoint of a run (one evaluation process per run)."""
    steps = sorted(run["checkpoints"])
    proc = subprocess.run(
        [sys.executable, "-m", "frugalnerf_ns.offline_tools", "eval", str(run["run_dir"] / "config.yml"), *map(str, steps)],
        capture_output=True, text=True,
    )
    results = [json.loads(line[len("RESULT "):]) for line in proc.stdout.splitlines() if line.startswith("RESULT ")]
    if proc.returncode != 0 or len(results) != len(steps):
        sys.exit(f"tradeoff: scoring {run['label']} failed:\n{proc.stderr[-3000:]}")
    rows = []
    for result in results:
        step = result["step"]
        seconds, megabytes = run["checkpoints"][step]
        rows.append({
            "run": run["label"], "method": run["method"], "step": step + 1, "seconds": seconds,
            "psnr": result["psnr"], "ssim": result["ssim"], "lpips": result["lpips"], "checkpoint_mb": megabytes,
            "peak_rss_mib": run["peak_rss_mib"],
        })
    return rows


def pareto_front(points: List[Dict[str, Any]], key: str = "psnr", higher: bool = True) -> List[Dict[str, Any]]:
    """Runs no other run beats on both wall time and ``key``, sorted by time."""
    front, best = [], None
    for point in sorted(points, key=lambda p: (p["seconds"], -p[key] if higher else p[key])):
        value = point[key] if higher else -point[key]
        if best is None or value > best:
            front.append(point)
            best = value
    return front


def markdown(rows: List[Dict[str, Any]]) -> str:
    lines = ["| run | step | wall time | PSNR | SSIM | LPIPS | checkpoint MB | peak RSS MiB |", "|---" * 8 + "|"]
    for r in rows:
        lines.append(
            f"| {r['run']} | {r['step']} | {r['seconds'] / 60:.1f} min | {r['psnr']:.2f} | {r['ssim']:.3f} | "
            f"{r['lpips']:.3f} | {r['checkpoint_mb']:.1f} | {r['peak_rss_mib'] or 0:.0f} |"
        )
    return "\n".join(lines)


def plot(rows: List[Dict[str, Any]], out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    runs = list(dict.fromkeys(r["run"] for r in rows))
    finals = [max((r for r in rows if r["run"] == run), key=lambda r: r["step"]) for run in runs]
    figure, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    for axis, key, higher, label in ((axes[0], "psnr", True, "test PSNR (dB)"), (axes[1], "lpips", False, "test LPIPS")):
        for point in finals:
            axis.scatter(point["seconds"] / 60, point[key], s=30)
            axis.annotate(point["run"], (point["seconds"] / 60, point[key]), fontsize=7, xytext=(3, 3),
                          textcoords="offset points")
        front = pareto_front(finals, key, higher)
        axis.step([p["seconds"] / 60 for p in front], [p[key] for p in front], where="post", color="black",
                  linewidth=1, label="Pareto front")
        axis.set_xlabel("wall-clock training time (min)")
        axis.set_ylabel(label)
        axis.legend(fontsize="small")
    figure.suptitle("Quality vs training time (final checkpoints)")
    figure.tight_layout()
    figure.savefig(out / "pareto.png", dpi=110)
    plt.close(figure)

    figure, axis = plt.subplots(figsize=(7, 4.2))
    for run in runs:
        points = sorted((r for r in rows if r["run"] == run), key=lambda r: r["step"])
        axis.plot([p["seconds"] / 60 for p in points], [p["psnr"] for p in points], marker="o", markersize=3, label=run)
    axis.set_xlabel("wall-clock training time (min)")
    axis.set_ylabel("test PSNR (dB)")
    axis.set_title("Test PSNR during training (anytime curves)")
    axis.legend(fontsize="small")
    figure.tight_layout()
    figure.savefig(out / "anytime.png", dpi=110)
    plt.close(figure)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scene", help="scene name from --config (gives data, parser options and preset)")
    parser.add_argument("--config", type=Path, default=ROOT / "configs" / "benchmark_scenes.yaml")
    parser.add_argument("--data", type=Path, help="scene folder (instead of --scene)")
    parser.add_argument("--parser", default="", help='dataparser subcommand and options, one string (with --data), '
                        'e.g. "frugal-nerfstudio --center-method focus"')
    parser.add_argument("--baseline-parser", help="dataparser for tensorf, one string (default: --parser)")
    parser.add_argument("--presets", nargs="+", help="FrugalNeRF presets (default: the scene's)")
    parser.add_argument("--budgets", type=int, nargs="*", default=[500, 1500], help="iteration budgets")
    parser.add_argument("--scales", type=int, nargs="*", default=[0, 1, 2, 3], help="numbers of lower scales L")
    parser.add_argument("--scales-budget", type=int, default=500, help="iterations of the L sweep")
    parser.add_argument("--grid-sides", nargs="*", default=[],
                        help="final grid sides for the first preset at --scales-budget: 'auto' or N (N^3 voxels)")
    parser.add_argument("--anytime-every", type=int, default=500, help="steps between scored checkpoints")
    parser.add_argument("--tensorf-iterations", type=int, default=1500, help="0 skips the tensorf reference")
    parser.add_argument("--tensorf-rays", type=int, default=1024)
    parser.add_argument("--seed", type=int, help="nerfstudio's --machine.seed for every run (default: each method's)")
    parser.add_argument("--out", type=Path, default=ROOT / "outputs" / "tradeoff")
    args = parser.parse_args(argv)

    if args.scene:
        table = yaml.safe_load(args.config.read_text())["scenes"]
        if args.scene not in table:
            parser.error(f"unknown scene {args.scene!r}; {args.config} has {sorted(table)}")
        entry = table[args.scene]
        data = (ROOT / entry["data"]).resolve()
        parser_args, baseline_parser = entry["parser"], entry.get("baseline_parser", entry["parser"])
        presets = args.presets or [entry["preset"]]
    elif args.data:
        data, parser_args = args.data, shlex.split(args.parser)
        baseline_parser = shlex.split(args.baseline_parser) if args.baseline_parser is not None else parser_args
        presets = args.presets or ["frugalnerf-tiny"]
    else:
        parser.error("give --scene or --data")
    if not data.exists():
        parser.error(f"scene data {data} does not exist")
    args.out.mkdir(parents=True, exist_ok=True)

    runs = []
    for preset in presets:
        for budget in args.budgets:
            runs.append(train(f"{preset}/{budget}", preset, data, parser_args, budget_args(preset, budget),
                              min(args.anytime_every, budget), args.out, args.seed))
    from frugalnerf_ns.presets import build_trainer_config

    own_lower = build_trainer_config(presets[0]).pipeline.model.num_lower_scales
    for lower in args.scales:
        if lower == own_lower and args.scales_budget in args.budgets:
            continue  # that run is the preset's own at this budget
        extra = budget_args(presets[0], args.scales_budget) + ["--pipeline.model.num-lower-scales", str(lower)]
        runs.append(train(f"{presets[0]}/{args.scales_budget}/L={lower}", presets[0], data, parser_args, extra,
                          args.scales_budget, args.out, args.seed))
    initial = build_trainer_config(presets[0]).pipeline.model.initial_voxels
    for side in args.grid_sides:
        # A final grid below the preset's starting grid starts at its final size (the grid never shrinks).
        grid = ["--pipeline.model.auto-grid", "True"] if side == "auto" else [
            "--pipeline.model.auto-grid", "False", "--pipeline.model.final-voxels", str(int(side) ** 3),
            "--pipeline.model.initial-voxels", str(min(initial, int(side) ** 3))]
        extra = budget_args(presets[0], args.scales_budget) + grid
        runs.append(train(f"{presets[0]}/{args.scales_budget}/grid={side}", presets[0], data, parser_args, extra,
                          args.scales_budget, args.out, args.seed))
    if args.tensorf_iterations > 0:
        extra = ["--max-num-iterations", str(args.tensorf_iterations), "--pipeline.datamanager.train-num-rays-per-batch",
                 str(args.tensorf_rays)]
        runs.append(train(f"tensorf/{args.tensorf_iterations}", "tensorf", data, baseline_parser, extra,
                          min(args.anytime_every, args.tensorf_iterations), args.out, args.seed))
    rows = [row for run in runs for row in score(run)]
    table = markdown(rows)
    print(table)
    (args.out / "tradeoff.md").write_text(table + "\n")
    (args.out / "tradeoff.json").write_text(json.dumps(rows, indent=2))
    plot(rows, args.out)
    print(f"tradeoff: wrote {args.out / 'tradeoff.md'}, tradeoff.json, pareto.png and anytime.png")


if __name__ == "__main__":
    main()
