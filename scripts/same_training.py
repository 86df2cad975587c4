"""Does training compute the same thing before and after a change? Short seeded runs of the gate's scenes in two trees
(the older one a git worktree), every tensor of their final checkpoints compared.

    python scripts/same_training.py --before 6679381 [--after HEAD] [--scenes fern dtu_scan65] [--steps 150]

Each tree trains with its own source (PYTHONPATH), the same interpreter and its own empty cache folder (so neither
reuses the other's downscaled copies or triangulated points). A shortened run compresses every schedule (upsampling,
alpha mask and shrink, loss-weight decay) into its steps, so each of them runs. Prints a Markdown table and writes
``--record`` (JSON). Exits 1 when any tensor differs.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Dict, List

import torch
import yaml

ROOT = Path(__file__).resolve().parents[1]
SCENES_FILE = ROOT / "configs" / "benchmark_scenes.yaml"
# The gate's scenes and the split each is gated on (configs/gate.yaml): NDC (fern), masks and DTU cameras (DTU), a
# photo capture in a box with the space beyond it (the juice box's wide split, the bird).
DEFAULT_RUNS = {"fern": 2, "dtu_scan65": 2, "juice_box": 4, "bird": 3}


def tree_at(commit: str, where: Path) -> Path:
    """The source tree of ``commit``: this checkout for HEAD, else a detached git worktree under ``where``."""
    if commit == "HEAD":
        return ROOT
    tree = where / commit
    if not tree.is_dir():
        subprocess.run(["git", "worktree", "add", "--detach", str(tree), commit], cwd=ROOT, check=True,
                       capture_output=True)
    return tree


def train(tree: Path, scene: str, views: int, steps: int, out: Path, cache: Path) -> Path:
    """One seeded run of ``scene``'s preset with the view count's options; returns its last checkpoint."""
    config = yaml.safe_load(SCENES_FILE.read_text())
    entry = config["scenes"][scene]
    data = (SCENES_FILE.parent / config["data_root"] / entry["data"]).resolve()
    command = [sys.executable, "-m", "frugalnerf_ns.tools.offline_tools", "train", entry["preset"], "--data", str(data),
               "--output-dir", str(out), "--timestamp", "run", "--vis", "tensorboard", "--machine.device-type", "cpu",
               "--machine.seed", "42", "--pipeline.datamanager.seed", "42", "--max-num-iterations", str(steps),
               "--steps-per-save", "100000", *entry["parser"], *entry["views"][views]]
    env = {**os.environ, "PYTHONPATH": str(tree), "XDG_CACHE_HOME": str(cache)}
    out.parent.mkdir(parents=True, exist_ok=True)
    with open(out.parent / f"{out.name}.log", "w") as log:
        subprocess.run(command, cwd=tree, env=env, stdout=log, stderr=subprocess.STDOUT, check=True)
    return next(out.rglob(f"step-{steps - 1:09d}.ckpt"))


def compare(before: Path, after: Path) -> Dict:
    a = torch.load(before, map_location="cpu", weights_only=False)["pipeline"]
    b = torch.load(after, map_location="cpu", weights_only=False)["pipeline"]
    differing = sorted(k for k in set(a) | set(b) if k not in a or k not in b or not torch.equal(a[k], b[k]))
    return {"tensors": len(set(a) | set(b)), "differing": differing}


def main(argv: List[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--before", required=True, help="the commit before the change")
    parser.add_argument("--after", default="HEAD")
    parser.add_argument("--scenes", nargs="*", default=list(DEFAULT_RUNS), help=f"of {list(DEFAULT_RUNS)}")
    parser.add_argument("--steps", type=int, default=150)
    parser.add_argument("--work", type=Path, default=Path(tempfile.gettempdir()) / "same_training")
    parser.add_argument("--record", type=Path, help="JSON record to write (default: none)")
    args = parser.parse_args(argv)
    unknown = sorted(set(args.scenes) - set(DEFAULT_RUNS))
    if unknown:
        sys.exit(f"same_training: unknown scenes {unknown} (known: {list(DEFAULT_RUNS)})")
    args.work.mkdir(parents=True, exist_ok=True)
    trees = {tag: tree_at(commit, args.work) for tag, commit in (("before", args.before), ("after", args.after))}
    commits = {tag: subprocess.run(["git", "rev-parse", "--short", commit], cwd=ROOT, capture_output=True, text=True,
                                   check=True).stdout.strip() for tag, commit in (("before", args.before), ("after", args.after))}
    rows = []
    for scene in args.scenes:
        started = time.time()
        checkpoints = {}
        for tag, tree in trees.items():
            run = args.work / "runs" / commits[tag] / scene
            cache = args.work / "cache" / commits[tag]
            checkpoints[tag] = train(tree, scene, DEFAULT_RUNS[scene], args.steps, run, cache)
        result = compare(checkpoints["before"], checkpoints["after"])
        rows.append({"scene": scene, "views": DEFAULT_RUNS[scene], "steps": args.steps, **result,
                     "minutes": round((time.time() - started) / 60, 1)})
        print(f"{scene}: {len(result['differing'])} of {result['tensors']} tensors differ", flush=True)
    print(f"\n| run ({commits['before']} -> {commits['after']}, seed 42) | views | steps | tensors | differing |")
    print("|---|---|---|---|---|")
    for row in rows:
        print(f"| {row['scene']} | {row['views']} | {row['steps']} | {row['tensors']} | {len(row['differing'])} |")
    if args.record:
        args.record.write_text(json.dumps({"before": commits["before"], "after": commits["after"], "runs": rows},
                                          indent=1) + "\n")
    sys.exit(1 if any(row["differing"] for row in rows) else 0)


if __name__ == "__main__":
    main()
