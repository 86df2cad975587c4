"""Profile FrugalNeRF training steps with torch.profiler: where a step's time goes (table + JSON).

  python scripts/profile_step.py --data ../shared/data/llff/fern [--preset frugalnerf-cpu] [--steps 5]
         [--at-final-grid] [--out outputs/profile_step.json]
  python scripts/profile_step.py --load-config <run>/config.yml     # a trained run: its grid and alpha mask

Builds the preset's pipeline on the data (training split, as ns-train does), optionally upsamples the grid
to the preset's final size first (the steady state of most of training), runs two warm-up steps, then
profiles ``--steps`` steps. Prints the named stages (data, each scale's rendering, geometric adaptation,
regularisers, backward, optimiser) and the operators with the most self CPU time.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import torch
from torch.profiler import ProfilerActivity, profile, record_function

STAGES = ("data", "forward", "render_scale0", "render_scale1", "render_scale2", "geometric_adaptation", "losses",
          "regularizers", "backward", "optimizer")


def build_pipeline(args):
    if args.load_config:
        from nerfstudio.utils.eval_utils import eval_setup

        # "val" sets the datamanager up for training (patches, novel and sparse-depth rays).
        _, pipeline, _, _ = eval_setup(args.load_config, test_mode="val")
        return pipeline
    from frugalnerf_ns.field.radiance_field import resolution_for_voxels
    from frugalnerf_ns.run.presets import build_trainer_config

    config = build_trainer_config(args.preset)
    config.pipeline.datamanager.data = args.data
    config.pipeline.datamanager.dataparser.data = args.data
    if args.train_views:
        config.pipeline.datamanager.dataparser.train_views = tuple(args.train_views)
    pipeline = config.pipeline.setup(device="cpu", test_mode="val")
    model = pipeline.model
    if args.at_final_grid:
        box = (model.field.aabb[1] - model.field.aabb[0]).tolist()
        model.field.upsample(resolution_for_voxels(model.final_voxels, box))
    return pipeline


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, help="scene folder (a fresh model of --preset)")
    parser.add_argument("--load-config", type=Path, help="config.yml of a trained run (instead of --data)")
    parser.add_argument("--preset", default="frugalnerf-cpu")
    parser.add_argument("--train-views", type=int, nargs="*", help="training view indices (default: the scene's split)")
    parser.add_argument("--steps", type=int, default=5)
    parser.add_argument("--at-final-grid", action="store_true", help="profile at the preset's final grid size")
    parser.add_argument("--rows", type=int, default=15, help="operators listed")
    parser.add_argument("--out", type=Path, default=Path("outputs/profile_step.json"))
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
    print(f"{args.load_config or args.preset + ' on ' + args.data.name}: grid {resolution}, {seconds:.3f} s/step under the profiler")
    print("| stage | s/step | share |\n|---|---|---|")
    for name in STAGES:
        if name in stages:
            print(f"| {name} | {stages[name]:.3f} | {stages[name] / seconds:.0%} |")
    print("| operator | self s/step | share | calls/step |\n|---|---|---|---|")
    rows = []
    for e in operators:
        self_seconds = e.self_cpu_time_total / 1e6 / args.steps
        rows.append({"operator": e.key, "self_seconds": self_seconds, "calls": e.count / args.steps})
        print(f"| {e.key} | {self_seconds:.3f} | {self_seconds / seconds:.0%} | {e.count / args.steps:.0f} |")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"preset": args.preset, "source": str(source), "grid": resolution,
                                    "seconds_per_step": seconds, "stages": stages, "operators": rows}, indent=2))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
