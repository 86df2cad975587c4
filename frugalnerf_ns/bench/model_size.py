"""Model size on disk and peak memory of one training step, per preset, at each preset's final grid.

  frugalnerf-bench model-size --data ../shared/data/llff/fern --parser "frugal-llff --downscale-factor 8 --train-views 6 13"
         [--presets frugalnerf frugalnerf-fast frugalnerf-quality frugalnerf-cpu frugalnerf-tiny] [--auto-grid]
         [--out outputs/model_size.json]

Each preset (and with ``--auto-grid`` each preset again with ``--pipeline.model.auto-grid True``) runs in its
own process: the pipeline is set up on the data as ns-train does, the grid is upsampled to the final size
the run would reach, the checkpoint nerfstudio would write ({"pipeline": state dict}) is saved and measured,
and one training step (the preset's rays; the first, so it includes warm-up) is timed; the process's peak RSS is the step's peak memory. No
training happens, so the paper presets can be sized on a CPU.
"""

from __future__ import annotations

import argparse
import json
import resource
import shlex
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, Dict, List

from frugalnerf_ns.config_files import outputs_dir
from frugalnerf_ns.bench.cli import worker_command
from frugalnerf_ns.bench.report import markdown_table, write_report

COLUMNS = [
    ("preset", lambda r: r["preset"]),
    ("final grid", lambda r: r["grid"]),
    ("field parameters", lambda r: f"{r['parameters'] / 1e6:.1f} M"),
    ("field MB", lambda r: f"{r['field_mb']:.1f}"),
    ("checkpoint MB", lambda r: f"{r['checkpoint_mb']:.1f}"),
    ("first step (s)", lambda r: f"{r['step_seconds']:.2f}"),
    ("rays/step", lambda r: r["rays"]),
    ("peak RSS MiB", lambda r: f"{r['peak_rss_mib']:.0f}"),
]


def measure(preset: str, data: Path, parser_args: List[str], auto_grid: bool) -> Dict[str, Any]:
    import torch

    from frugalnerf_ns.bench.pipelines import preset_pipeline

    def grid(config) -> None:
        config.pipeline.model.auto_grid = auto_grid

    _, pipeline = preset_pipeline(preset, data, parser_args=parser_args, configure=grid)
    model = pipeline.model
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "step.ckpt"
        torch.save({"step": 0, "pipeline": pipeline.state_dict()}, path)
        megabytes = path.stat().st_size / 1e6
    # The field (grids, MLP, occupancy mask) is the scene; the checkpoint adds nerfstudio's bookkeeping (a
    # trained run's checkpoint also holds the optimisers' state: Adam keeps two numbers per parameter).
    field_mb = sum(t.numel() * t.element_size() for t in list(model.field.parameters()) + list(model.field.buffers())) / 1e6
    parameters = sum(p.numel() for p in model.field.parameters())
    optimizer = torch.optim.Adam(model.parameters(), lr=1e-3)
    model.train()
    bundle, batch = pipeline.datamanager.next_train(0)
    start = time.perf_counter()
    outputs = model(bundle)
    loss = sum(model.get_loss_dict(outputs, batch, model.get_metrics_dict(outputs, batch)).values())
    loss.backward()
    optimizer.step()
    seconds = time.perf_counter() - start
    return {
        "preset": preset + (" + auto-grid" if auto_grid else ""),
        "grid": "x".join(map(str, model.field.density_grid.resolution.tolist())),
        "parameters": parameters,
        "checkpoint_mb": megabytes,
        "field_mb": field_mb,
        "step_seconds": seconds,
        "rays": int(bundle.origins.shape[0]),
        "peak_rss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
    }


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(prog="frugalnerf-bench model-size", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, required=True)
    parser.add_argument("--parser", default="", help='dataparser subcommand and options, one string')
    parser.add_argument("--presets", nargs="+",
                        default=["frugalnerf", "frugalnerf-fast", "frugalnerf-quality", "frugalnerf-cpu", "frugalnerf-tiny"])
    parser.add_argument("--auto-grid", action="store_true", help="also measure every preset with its grid auto-sized")
    parser.add_argument("--out", type=Path, default=outputs_dir("model_size.json"))
    parser.add_argument("--worker", nargs=2, metavar=("PRESET", "AUTO"), help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.worker:
        result = measure(args.worker[0], args.data, shlex.split(args.parser), args.worker[1] == "1")
        print("RESULT " + json.dumps(result))
        return
    if not args.data.exists():
        parser.error(f"--data {args.data} does not exist")
    rows = []
    for preset in args.presets:
        for auto in ([False, True] if args.auto_grid else [False]):
            proc = subprocess.run(
                worker_command("model-size", "--data", str(args.data), "--parser", args.parser, "--worker", preset,
                               "1" if auto else "0"),
                capture_output=True, text=True,
            )
            lines = [line for line in proc.stdout.splitlines() if line.startswith("RESULT ")]
            if proc.returncode != 0 or not lines:
                sys.exit(f"model_size: {preset} failed:\n{proc.stderr[-3000:]}")
            rows.append(json.loads(lines[-1][len("RESULT "):]))
            print(f"model_size: {rows[-1]['preset']} measured", flush=True)
    write_report("model_size", markdown_table(rows, COLUMNS), rows, args.out)
