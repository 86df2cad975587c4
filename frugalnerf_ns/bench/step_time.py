"""Seconds per training step of a trained run, this source tree beside an earlier one, from the same checkpoint.

  frugalnerf-bench step <run>/config.yml [--before DIR] [--torch-path] [--steps 10] [--rounds 3]
                                          [--out outputs/benchmark_step.json]

Each measurement is a child process that loads the run's checkpoint (its grid, alpha mask and weights: the
state at the end of training), seeds torch, runs two warm-up steps and then times ``--steps`` training steps:
the datamanager's batch, the model's forward, its metrics and losses, backward, and the run's own optimisers
(nerfstudio's ``Optimizers`` from the run's config). With ``--before DIR`` (a source tree of an earlier commit,
e.g. ``git worktree add /tmp/before <rev>``) the same child runs on that tree's package (``PYTHONPATH=DIR``),
alternating with this tree's, ``--rounds`` times; the table shows medians, the ratio and each tree's peak RSS.
Both trees draw the same batches and jitter (the same seeds), so they compute the same steps. With
``--torch-path`` this tree is also timed with ``--pipeline.model.kernels torch`` (the reference path the fused
kernels replace in training), in the same alternation. Run it alone on the machine: two processes on 2 cores slow
each other several-fold.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Dict, List, Optional

WORKER_FLAG = "--worker"
RESULT_PREFIX = "STEP_RESULT "


def worker(config: Path, steps: int, warmup: int, kernels: str = "") -> Dict[str, object]:
    """Time ``steps`` training steps of the run in ``config`` (runs in the child, on whichever package
    ``PYTHONPATH`` names: only nerfstudio's API and the model's nerfstudio methods are used), with the model's
    ``kernels`` set to ``kernels`` where given."""
    import torch
    from nerfstudio.engine.optimizers import Optimizers
    from nerfstudio.utils.eval_utils import eval_setup

    from frugalnerf_ns.config_files import code_root

    trainer_config, pipeline, _, loaded_step = eval_setup(config, test_mode="val")
    pipeline.train()
    model = pipeline.model
    if kernels:
        model.config.kernels = kernels
    optimizers = Optimizers(trainer_config.optimizers, model.get_param_groups())
    torch.manual_seed(0)

    def step(index: int) -> float:
        start = time.perf_counter()
        bundle, batch = pipeline.datamanager.next_train(index)
        outputs = model(bundle)
        metrics = model.get_metrics_dict(outputs, batch)
        loss = sum(model.get_loss_dict(outputs, batch, metrics).values())
        optimizers.zero_grad_all()
        loss.backward()
        optimizers.optimizer_step_all()
        return time.perf_counter() - start

    for index in range(warmup):
        step(index)
    seconds = [step(index) for index in range(warmup, warmup + steps)]
    return {
        "package": str(code_root()),  # the copy this child imported
        "loaded_step": loaded_step,
        "grid": [int(r) for r in model.field.density_grid.resolution.tolist()],
        "kernels": str(getattr(model.config, "kernels", "")),
        "seconds": seconds,
        "peak_rss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
    }


def run_child(tree: Path, config: Path, steps: int, warmup: int, kernels: str = "") -> Dict[str, object]:
    """One measurement in a child process on ``tree``'s package (``kernels``: the model's setting, "" for the run's)."""
    env = dict(os.environ, PYTHONPATH=str(tree))
    # This file is loaded by path (the other tree may not have it) under a private name: the package it then
    # imports is the one PYTHONPATH names.
    loader = ("import importlib.util, sys; spec = importlib.util.spec_from_file_location('frugalnerf_step_worker', "
              f"{str(Path(__file__).resolve())!r}); module = importlib.util.module_from_spec(spec); "
              "spec.loader.exec_module(module); module.main(sys.argv[1:])")
    command = [sys.executable, "-c", loader, WORKER_FLAG, str(config.resolve()), "--steps", str(steps), "--warmup", str(warmup),
               "--kernels", kernels]
    done = subprocess.run(command, cwd=tree, env=env, capture_output=True, text=True)
    lines = [line for line in done.stdout.splitlines() if line.startswith(RESULT_PREFIX)]
    if done.returncode != 0 or not lines:
        tail = (done.stderr or done.stdout).strip().splitlines()[-1:] or ["no output"]
        sys.exit(f"benchmark_step: error: the step timing on {tree} failed: {tail[0]}")
    result = json.loads(lines[-1][len(RESULT_PREFIX):])
    if Path(str(result["package"])).resolve() != tree.resolve():
        sys.exit(f"benchmark_step: error: the child imported frugalnerf_ns from {result['package']}, not {tree}")
    return result


def git_commit(tree: Path) -> str:
    done = subprocess.run(["git", "-C", str(tree), "rev-parse", "--short", "HEAD"], capture_output=True, text=True)
    dirty = subprocess.run(["git", "-C", str(tree), "status", "--porcelain", "--untracked-files=no"],
                           capture_output=True, text=True).stdout.strip()
    return (done.stdout.strip() or "?") + ("+changes" if dirty else "")


def main(argv: Optional[List[str]] = None) -> list:
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv[:1] == [WORKER_FLAG]:
        parser = argparse.ArgumentParser(prog="step_time worker")
        parser.add_argument("config", type=Path)
        parser.add_argument("--steps", type=int, required=True)
        parser.add_argument("--warmup", type=int, required=True)
        parser.add_argument("--kernels", default="")
        args = parser.parse_args(argv[1:])
        print(RESULT_PREFIX + json.dumps(worker(args.config, args.steps, args.warmup, args.kernels)), flush=True)
        return []

    from frugalnerf_ns.bench.report import markdown_table, write_report
    from frugalnerf_ns.config_files import code_root, outputs_dir

    parser = argparse.ArgumentParser(prog="frugalnerf-bench step", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("config", type=Path, help="config.yml of a trained FrugalNeRF run")
    parser.add_argument("--before", type=Path, help="source tree of an earlier commit, timed alternately with this one")
    parser.add_argument("--steps", type=int, default=10, help="timed steps per measurement")
    parser.add_argument("--warmup", type=int, default=2, help="untimed steps first")
    parser.add_argument("--rounds", type=int, default=3, help="measurements per tree (alternating with --before)")
    parser.add_argument("--torch-path", action="store_true",
                        help="also time this tree with --pipeline.model.kernels torch (the fused kernels' reference)")
    parser.add_argument("--out", type=Path, default=outputs_dir("benchmark_step.json"))
    args = parser.parse_args(argv)
    if not args.config.is_file():
        sys.exit(f"benchmark_step: error: {args.config} is not a file (pass <run>/config.yml)")
    if args.before is not None and not (args.before / "frugalnerf_ns" / "__init__.py").is_file():
        sys.exit(f"benchmark_step: error: --before {args.before}: no frugalnerf_ns package there (pass a source tree)")
    this_tree = code_root()
    trees = (([("before", args.before, "")] if args.before is not None else [])
             + ([("now, torch path", this_tree, "torch")] if args.torch_path else []) + [("now", this_tree, "")])
    results: Dict[str, List[Dict[str, object]]] = {name: [] for name, _, _ in trees}
    for _ in range(args.rounds):
        for name, tree, kernels in trees:
            results[name].append(run_child(tree, args.config, args.steps, args.warmup, kernels))
    rows = []
    for name, tree, _ in trees:
        medians = [statistics.median(r["seconds"]) for r in results[name]]  # type: ignore[arg-type]
        rows.append({
            "tree": name, "commit": git_commit(tree), "path": str(tree),
            "median_s_per_step": statistics.median(medians), "round_medians": medians,
            "peak_rss_mib": max(float(r["peak_rss_mib"]) for r in results[name]),  # type: ignore[arg-type]
            "grid": results[name][0]["grid"], "kernels": results[name][0].get("kernels", ""),
        })
    now = rows[-1]["median_s_per_step"]
    for row in rows:
        row["speedup_of_now"] = row["median_s_per_step"] / now
    title = (f"{args.config}: training steps from the checkpoint (grid {rows[-1]['grid']}), {args.steps} timed steps "
             f"after {args.warmup} warm-up, {args.rounds} rounds per tree, alternating")
    table = title + "\n\n" + markdown_table(rows, [
        ("tree", lambda r: f"{r['tree']} ({r['commit']})"),
        ("s/step (median)", lambda r: f"{r['median_s_per_step']:.3f}"),
        ("round medians", lambda r: " ".join(f"{m:.3f}" for m in r["round_medians"])),
        ("now is faster by", lambda r: f"{r['speedup_of_now']:.2f}x"),
        ("peak RSS", lambda r: f"{r['peak_rss_mib']:.0f} MiB"),
    ])
    write_report("step", table, {"config": str(args.config), "steps": args.steps, "warmup": args.warmup,
                                 "rounds": args.rounds, "rows": rows}, args.out)
    return rows


if __name__ == "__main__":
    main()
