"""What a sweep costs over running the same trainings one after another, and what the one-training-per-2-cores
rule buys: one table and a JSON file.

  python scripts/diagnostics/sweep_overhead.py [--runs 4] [--iterations 150] [--out outputs/sweep_overhead]

Modes, each on the same runs (frugalnerf-tiny on the procedural scene, one seed per run, train + score):
  direct        the runs one after another in this process, no Ray (the baseline)
  sweep         frugalnerf-sweep's scheduler on a local Ray it starts and stops (2 cores per run)
  sweep-1core   the same with 1 core per run: on a 2-core machine two trainings at once
Wall time includes everything each mode does (Ray's start and stop for the sweeps). Run it alone on the
machine: anything else running skews every number.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, Dict, List


def specs_for(scene: Path, runs: int, iterations: int):
    from frugalnerf_ns.tools.sweep.grid import RunSpec, seed_args

    return [RunSpec("procedural", 3, "frugalnerf-tiny", "full", str(scene), [],
                    ["--max-num-iterations", str(iterations), *seed_args("frugalnerf-tiny", seed)], seed)
            for seed in range(1, runs + 1)]


def mode_row(name: str, wall: float, records: List[Dict[str, Any]], baseline: float | None) -> Dict[str, Any]:
    ok = [r for r in records if r.get("status") == "ok"]
    return {
        "mode": name, "wall_seconds": wall, "runs_ok": len(ok), "runs": len(records),
        "overhead_percent": None if baseline is None else 100.0 * (wall - baseline) / baseline,
        "mean_train_seconds": statistics.fmean(r["train_seconds"] for r in ok) if ok else None,
        "mean_psnr": statistics.fmean(r["psnr"] for r in ok) if ok else None,
    }


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--runs", type=int, default=4)
    parser.add_argument("--iterations", type=int, default=150)
    parser.add_argument("--modes", nargs="+", default=["direct", "sweep", "sweep-1core"],
                        choices=["direct", "sweep", "sweep-1core"])
    parser.add_argument("--out", type=Path, default=Path("outputs/sweep_overhead"))
    args = parser.parse_args(argv)

    from frugalnerf_ns.data.procedural_scene import write_procedural_scene
    from frugalnerf_ns.tools.sweep.cli import run_sweep
    from frugalnerf_ns.tools.sweep.runner import execute

    args.out.mkdir(parents=True, exist_ok=True)
    rows: List[Dict[str, Any]] = []
    with tempfile.TemporaryDirectory() as tmp:
        scene = write_procedural_scene(Path(tmp) / "procedural")
        specs = specs_for(scene, args.runs, args.iterations)
        baseline = None
        for mode in args.modes:
            out = Path(tmp) / mode
            print(f"sweep_overhead: {mode}: {len(specs)} runs of {args.iterations} steps ...", flush=True)
            start = time.perf_counter()
            if mode == "direct":
                records = [execute(spec, out, threads=os.cpu_count()) for spec in specs]
            else:
                records = run_sweep(specs, out, cpus_per_run=2 if mode == "sweep" else 1, say=lambda line: None)
            wall = time.perf_counter() - start
            if mode == "direct":
                baseline = wall
            rows.append(mode_row(mode, wall, records, baseline))

    lines = ["| mode | runs ok | wall time | overhead vs direct | mean train time per run | mean PSNR |",
             "|---|---|---|---|---|---|"]
    for r in rows:
        overhead = "" if r["overhead_percent"] is None else f"{r['overhead_percent']:+.1f} %"
        lines.append(f"| {r['mode']} | {r['runs_ok']}/{r['runs']} | {r['wall_seconds']:.1f} s | {overhead} | "
                     f"{r['mean_train_seconds'] or 0:.1f} s | {r['mean_psnr'] or 0:.2f} |")
    print("\n" + "\n".join(lines))
    summary = {"cpus": os.cpu_count(), "runs": args.runs, "iterations": args.iterations, "rows": rows}
    (args.out / "sweep_overhead.json").write_text(json.dumps(summary, indent=2))
    print(f"\nwrote {args.out / 'sweep_overhead.json'}")
    return 0 if all(r["runs_ok"] == r["runs"] for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
