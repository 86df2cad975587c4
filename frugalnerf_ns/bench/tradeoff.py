"""Speed vs accuracy on one scene and split: presets x iteration budgets, the number of scales, and tensorf.

  frugalnerf-bench tradeoff --scene fern [--presets frugalnerf-cpu] [--budgets 500 1500]
         [--scales 0 1 2 3] [--scales-budget 500] [--grid-sides auto 320] [--anytime-every 500]
         [--tensorf-iterations 1500] [--seed N] [--out outputs/tradeoff]
  frugalnerf-bench tradeoff --data <scene dir> --parser "frugal-nerfstudio --center-method focus" ...

Every FrugalNeRF run scales its preset's step schedule (upsampling, alpha mask, learning-rate decay) to its
budget and saves a checkpoint every ``--anytime-every`` steps; each checkpoint is scored on the test views
afterwards (``offline_tools eval``), and its wall time is the time from the start of ``ns-train`` (set-up,
triangulation and all) to that checkpoint's file. ``--scales`` runs the first preset with L = 0..3 lower
scales (the paper's ablation) at ``--scales-budget``, and ``--grid-sides`` runs it with each final grid
(``auto``: sized from the training pixels, ``--pipeline.model.auto-grid``; a number N: N^3 voxels);
tensorf (nerfstudio's) runs on the same views as the reference. Writes ``tradeoff.md`` (table),
``tradeoff.json``, ``pareto.png`` (final test PSNR and LPIPS vs wall time, Pareto front marked) and
``anytime.png`` (test PSNR vs wall time during training). The runs go through ``frugalnerf-sweep``'s runner
(one Ray task each, records in ``<out>/results.jsonl``): the same command again skips finished runs.
"""

from __future__ import annotations

import argparse
import shlex
import sys
from pathlib import Path
from typing import List, Optional, Sequence

import yaml

from frugalnerf_ns.bench.report import write_report
from frugalnerf_ns.tools.sweep.cli import run_sweep
from frugalnerf_ns.config_files import config_path, outputs_dir
from frugalnerf_ns.tools.sweep.grid import RunSpec, scene_data, scene_parser, seed_args
from frugalnerf_ns.tools.sweep.report import anytime_rows, anytime_table, pareto_front, plot  # noqa: F401 (pareto_front: tests)

markdown = anytime_table


def budget_args(preset: str, iterations: int) -> List[str]:
    """ns-train options that run ``preset`` for ``iterations`` steps. Its whole schedule (learning rates,
    loss weights, upsampling, alpha mask) follows: every schedule is a fraction of the run (FrugalTrainer)."""
    return ["--max-num-iterations", str(iterations)]


def spec(label: str, method: str, scene: str, views: int, data: Path, parser_args: Sequence[str], extra: Sequence[str],
         every: int, seed: Optional[int]) -> RunSpec:
    """One run scored every ``every`` steps; ``label`` names it in the table and plots."""
    train_args = [*extra, *seed_args(method, seed), "--steps-per-save", str(every), "--save-only-latest-checkpoint", "False"]
    return RunSpec(scene, views, method, label.replace("/", "-"), str(data), list(parser_args), train_args, seed, every,
                   extra={"run": label})


def plan_runs(args: argparse.Namespace, scene: str, views: int, data: Path, parser_args: Sequence[str],
              baseline_parser: Sequence[str], presets: Sequence[str]) -> List[RunSpec]:
    """The runs of one trade-off study: every preset at every budget, the first preset with each number of lower
    scales and each final grid side at ``--scales-budget``, and tensorf as the reference."""
    runs = []
    for preset in presets:
        for budget in args.budgets:
            runs.append(spec(f"{preset}/{budget}", preset, scene, views, data, parser_args, budget_args(preset, budget),
                             min(args.anytime_every, budget), args.seed))
    from frugalnerf_ns.run.presets import build_trainer_config

    own_lower = build_trainer_config(presets[0]).pipeline.model.num_lower_scales
    for lower in args.scales:
        if lower == own_lower and args.scales_budget in args.budgets:
            continue  # that run is the preset's own at this budget
        extra = budget_args(presets[0], args.scales_budget) + ["--pipeline.model.num-lower-scales", str(lower)]
        runs.append(spec(f"{presets[0]}/{args.scales_budget}/L={lower}", presets[0], scene, views, data, parser_args,
                         extra, args.scales_budget, args.seed))
    initial = build_trainer_config(presets[0]).pipeline.model.initial_voxels
    for side in args.grid_sides:
        # A final grid below the preset's starting grid starts at its final size (the grid never shrinks).
        grid = ["--pipeline.model.auto-grid", "True"] if side == "auto" else [
            "--pipeline.model.auto-grid", "False", "--pipeline.model.final-voxels", str(int(side) ** 3),
            "--pipeline.model.initial-voxels", str(min(initial, int(side) ** 3))]
        extra = budget_args(presets[0], args.scales_budget) + grid
        runs.append(spec(f"{presets[0]}/{args.scales_budget}/grid={side}", presets[0], scene, views, data, parser_args,
                         extra, args.scales_budget, args.seed))
    if args.tensorf_iterations > 0:
        extra = ["--max-num-iterations", str(args.tensorf_iterations), "--pipeline.datamanager.train-num-rays-per-batch",
                 str(args.tensorf_rays)]
        runs.append(spec(f"tensorf/{args.tensorf_iterations}", "tensorf", scene, views, data, baseline_parser, extra,
                         min(args.anytime_every, args.tensorf_iterations), args.seed))
    return runs


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="frugalnerf-bench tradeoff", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scene", help="scene name from --config (gives data, parser options and preset)")
    parser.add_argument("--config", type=Path, default=config_path("benchmark_scenes.yaml"))
    parser.add_argument("--views", type=int, default=2, help="training views of --scene (a count its config defines)")
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
    parser.add_argument("--out", type=Path, default=outputs_dir("tradeoff"))
    return parser


def main(argv=None) -> None:
    parser = build_parser()
    args = parser.parse_args(argv)

    if args.scene:
        table = yaml.safe_load(args.config.read_text())["scenes"]
        if args.scene not in table:
            parser.error(f"unknown scene {args.scene!r}; {args.config} has {sorted(table)}")
        entry = table[args.scene]
        scene, views = args.scene, args.views
        config = yaml.safe_load(args.config.read_text())
        _, parser_args = scene_parser(args.config, config, scene, views, baseline=False)
        _, baseline_parser = scene_parser(args.config, config, scene, views, baseline=True)
        data = scene_data(args.config, config, scene)
        presets = args.presets or [entry["preset"]]
    elif args.data:
        scene, views = args.data.name, 0
        data, parser_args = args.data.resolve(), shlex.split(args.parser)
        baseline_parser = shlex.split(args.baseline_parser) if args.baseline_parser is not None else parser_args
        presets = args.presets or ["frugalnerf-tiny"]
    else:
        parser.error("give --scene or --data")
    if not data.exists():
        parser.error(f"scene data {data} does not exist")
    args.out.mkdir(parents=True, exist_ok=True)
    runs = plan_runs(args, scene, views, data, parser_args, baseline_parser, presets)
    records = run_sweep(runs, args.out)
    failed = [r for r in records if r.get("status") != "ok"]
    if failed:
        sys.exit("tradeoff: " + "; ".join(f"{r['extra']['run']} failed ({r.get('error')}; log {r.get('log')})" for r in failed))
    rows = anytime_rows(records)
    write_report("tradeoff", markdown(rows), rows, args.out / "tradeoff.json", args.out / "tradeoff.md")
    plot(rows, args.out)
    print(f"tradeoff: drew {args.out / 'pareto.png'} and anytime.png")
