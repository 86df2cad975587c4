"""Profile FrugalNeRF training steps with torch.profiler: where a step's time goes (table + JSON).

  frugalnerf-bench profile --data ../shared/data/llff/fern [--preset frugalnerf-cpu] [--steps 5]
         [--at-final-grid] [--out outputs/profile_step.json]
  frugalnerf-bench profile --load-config <run>/config.yml     # a trained run: its grid and alpha mask

Builds the preset's pipeline on the data (training split, as ns-train does), optionally upsamples the grid
to the preset's final size first (the steady state of most of training), runs two warm-up steps, then
profiles ``--steps`` steps. Prints the named stages (data, each scale's rendering, geometric adaptation,
regularisers, backward, optimiser) and the operators with the most self CPU time.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import torch
from torch.profiler import ProfilerActivity, profile, record_function

from frugalnerf_ns.config_files import outputs_dir
from frugalnerf_ns.bench.report import markdown_table, write_report

STAGES = ("data", "forward", "render_scale0", "render_scale1", "render_scale2", "geometric_adaptation", "losses",
          "regularizers", "backward", "optimizer")


def build_pipeline(args):
    if args.load_config:
        from nerfstudio.utils.eval_utils import eval_setup

        # "val" sets the datamanager up for training (patches, novel and sparse-depth rays).
        _, pipeline, _, _ = eval_setup(args.load_config, test_mode="val")
        return pipeline
    from frugalnerf_ns.bench.pipelines import preset_pipeline

    _, pipeline = preset_pipeline(args.preset, args.data, train_views=args.train_views or None,
                                  final_grid=args.at_final_grid)
    return pipeline


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(prog="frugalnerf-bench profile", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, help="scene folder (a fresh model of --preset)")
    parser.add_argument("--load-config", type=Path, help="config.yml of a trained run (instead of --data)")
    parser.add_argument("--preset", default="frugalnerf-cpu")
    parser.add_argument("--train-views", type=int, nargs="*", help="training view indices (default: the scene's split)")
    parser.add_argument("--steps", type=int, default=5)
    parser.add_argument("--at-final-grid", action="store_true", help="profile at the preset's final grid size")
    parser.add_argument("--rows", type=int, default=15, help="operators listed")
    parser.add_argument("--out", type=Path, default=outputs_dir("profile_step.json"))
    args = parser.parse_args(argv)
    source = args.load_config or args.data
    if source is None or not source.exists():
        parser.error(f"give an existing --data or --load-config (got {source})")

    pipeline = build_pipeline(args)
    model = pipeline.model
    model.train()
    optimizer = torch.optim.Adam(model.parameters(), lr=1e-3)

    def step(index: int) -> None:
        with record_function("data"):
            bundle, batch = pipeline.datamanager.next_train(index)
        with record_function("forward"):
            outputs = model(bundle)
        with record_function("losses"):
            metrics = model.get_metrics_dict(outputs, batch)
            loss = sum(model.get_loss_dict(outputs, batch, metrics).values())
        optimizer.zero_grad(set_to_none=True)
        with record_function("backward"):
            loss.backward()
        with record_function("optimizer"):
            optimizer.step()

    for index in range(2):
        step(index)
    start = time.perf_counter()
    with profile(activities=[ProfilerActivity.CPU]) as prof:
        for index in range(2, 2 + args.steps):
            step(index)
    seconds = (time.perf_counter() - start) / args.steps
    averages = prof.key_averages()
    stages = {e.key: e.cpu_time_total / 1e6 / args.steps for e in averages if e.key in STAGES}
    operators = sorted((e for e in averages if e.key not in STAGES and not e.key.startswith("ProfilerStep")),
                       key=lambda e: e.self_cpu_time_total, reverse=True)[: args.rows]
    resolution = tuple(model.field.density_grid.resolution.tolist())
    title = f"{args.load_config or args.preset + ' on ' + args.data.name}: grid {resolution}, {seconds:.3f} s/step under the profiler"
    stage_rows = [{"stage": name, "seconds": stages[name]} for name in STAGES if name in stages]
    rows = [{"operator": e.key, "self_seconds": e.self_cpu_time_total / 1e6 / args.steps, "calls": e.count / args.steps}
            for e in operators]
    table = "\n\n".join([
        title,
        markdown_table(stage_rows, [("stage", lambda r: r["stage"]), ("s/step", lambda r: f"{r['seconds']:.3f}"),
                                    ("share", lambda r: f"{r['seconds'] / seconds:.0%}")]),
        markdown_table(rows, [("operator", lambda r: r["operator"]), ("self s/step", lambda r: f"{r['self_seconds']:.3f}"),
                              ("share", lambda r: f"{r['self_seconds'] / seconds:.0%}"),
                              ("calls/step", lambda r: f"{r['calls']:.0f}")]),
    ])
    write_report("profile", table, {"preset": args.preset, "source": str(source), "grid": resolution,
                                    "seconds_per_step": seconds, "stages": stages, "operators": rows}, args.out)
