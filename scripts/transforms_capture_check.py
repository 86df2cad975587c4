"""A real capture in NeRF-synthetic's file names trains as the same capture does in its own files: the bird's gate
split (training frames 0 23 46, the next-view study's 16 test frames) read as LLFF and, written as instant-ngp writes
a COLMAP capture (``tests/layout_fixtures.llff_capture_as_instant_ngp``), read by ``frugal-auto``; two seeds each.

    python scripts/transforms_capture_check.py [--iterations 750] [--seeds 42 43]

Trains one run at a time (reusing finished runs under outputs/transforms_capture_check/), scores each with the
project's evaluator, prints a Markdown table and writes docs/notes/transforms_capture.json.
"""

from __future__ import annotations

import argparse
import json
import platform
import subprocess
import sys
from pathlib import Path
from typing import Dict, List

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
BIRD = ROOT.parent / "shared" / "data" / "captures" / "bird"
RUNS = ROOT / "outputs" / "transforms_capture_check"
RECORD = ROOT / "docs" / "notes" / "transforms_capture.json"
TRAIN = [0, 23, 46]
TEST = [15, 27, 39, 51, 63, 75, 87, 90, 105, 116, 129, 141, 149, 163, 170, 181]


def run(name: str, data: Path, parser: List[str], seed: int, iterations: int) -> Dict:
    out = RUNS / f"i{iterations}" / name / f"seed{seed}"
    scores = out / "scores.json"
    if scores.is_file():
        return json.loads(scores.read_text())
    tools = [sys.executable, "-m", "frugalnerf_ns.tools.offline_tools"]
    out.mkdir(parents=True, exist_ok=True)
    if not list(out.rglob(f"step-{iterations - 1:09d}.ckpt")):
        with open(out / "train.log", "w") as log:
            subprocess.run(tools + ["train", "frugalnerf-cpu", "--data", str(data), "--output-dir", str(out), "--vis",
                                    "tensorboard", "--machine.seed", str(seed), "--pipeline.datamanager.seed", str(seed),
                                    "--max-num-iterations", str(iterations), *parser],
                           stdout=log, stderr=subprocess.STDOUT, check=True, cwd=ROOT)
    config = next(out.rglob("config.yml"))
    result = subprocess.run(tools + ["eval", str(config)], capture_output=True, text=True, check=True, cwd=ROOT)
    record = {"config": str(config.relative_to(ROOT)), **json.loads(result.stdout.split("RESULT ")[-1])}
    scores.write_text(json.dumps(record, indent=1))
    return record


def main() -> None:
    from tests.layout_fixtures import llff_capture_as_instant_ngp

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--iterations", type=int, default=750)
    parser.add_argument("--seeds", type=int, nargs="*", default=[42, 43])
    args = parser.parse_args()
    ngp = RUNS / "bird_instant_ngp"
    if not (ngp / "transforms_test.json").is_file():
        llff_capture_as_instant_ngp(BIRD, ngp, TRAIN, TEST)
    readings = {
        "LLFF files (frugal-auto)": (BIRD, ["frugal-auto", "--train-views", *map(str, TRAIN), "--test-views", *map(str, TEST)]),
        "instant-ngp files (frugal-auto)": (ngp, ["frugal-auto", "--train-views", "0", "1", "2", "--test-views",
                                                  *map(str, range(len(TEST)))]),
    }
    record = {"command": f"python scripts/transforms_capture_check.py --iterations {args.iterations}",
              "preset": "frugalnerf-cpu", "iterations": args.iterations, "train": TRAIN, "test": TEST,
              "machine": f"{platform.machine()} 2-core, CPU", "runs": {}}
    lines = ["| reading | seed | test PSNR / SSIM / LPIPS |", "|---|---|---|"]
    for name, (data, options) in readings.items():
        for seed in args.seeds:
            score = run(name.split()[0].lower().replace("-", "_"), data, options, seed, args.iterations)
            record["runs"][f"{name} seed {seed}"] = score
            lines.append(f"| {name} | {seed} | {score['psnr']:.2f} / {score['ssim']:.3f} / {score['lpips']:.3f} |")
            print(lines[-1], flush=True)
    RECORD.write_text(json.dumps(record, indent=1) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
