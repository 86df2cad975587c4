"""`make demo`: write the procedural scene, train `frugalnerf-tiny` on it, evaluate, print test-view PSNR.

Runs the real nerfstudio commands (ns-train, ns-eval) exactly as a user would, on the CPU in a few minutes.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Dict, List, Optional, Sequence

from frugalnerf_ns.config_files import outputs_dir
from frugalnerf_ns.data.procedural_scene import constant_color_psnr, write_procedural_scene


def _tool(name: str) -> str:
    """The nerfstudio console script installed next to this interpreter (falls back to PATH)."""
    candidate = Path(sys.executable).parent / name
    return str(candidate) if candidate.exists() else name


def train_and_eval(
    scene: Path, output_dir: Path, method: str = "frugalnerf-tiny", extra_args: Sequence[str] = ()
) -> Dict[str, float]:
    """ns-train (viewer off, so it exits) then ns-eval; returns ns-eval's results and the run folder."""
    timestamp = time.strftime("%Y-%m-%d_%H%M%S")
    train_cmd: List[str] = [
        _tool("ns-train"), method, "--data", str(scene), "--output-dir", str(output_dir),
        "--experiment-name", scene.name, "--timestamp", timestamp, "--vis", "tensorboard", *extra_args,
    ]
    env = {**os.environ, "PYTHONWARNINGS": "ignore"}
    subprocess.run(train_cmd, check=True, env=env)
    run_dir = output_dir / scene.name / method / timestamp
    eval_json = run_dir / "eval.json"
    subprocess.run(
        [_tool("ns-eval"), "--load-config", str(run_dir / "config.yml"), "--output-path", str(eval_json)],
        check=True,
        env=env,
    )
    results = json.loads(eval_json.read_text())["results"]
    results["run_dir"] = str(run_dir)
    return results


def main(argv: Optional[Sequence[str]] = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--scene", type=Path, default=outputs_dir("demo-scene"), help="where the scene is written")
    parser.add_argument("--output-dir", type=Path, default=outputs_dir(), help="nerfstudio output folder")
    parser.add_argument("--iterations", type=int, default=None, help="override the preset's iteration count")
    args = parser.parse_args(argv)

    if not (args.scene / "transforms.json").exists():
        print(f"frugalnerf demo: writing the procedural scene to {args.scene}")
        write_procedural_scene(args.scene)
    extra = ["--max-num-iterations", str(args.iterations)] if args.iterations else []
    start = time.time()
    results = train_and_eval(args.scene, args.output_dir, extra_args=extra)
    baseline = constant_color_psnr(args.scene)
    print()
    print(f"frugalnerf demo: trained and evaluated in {time.time() - start:.0f} s ({results['run_dir']})")
    lpips = f"{results['lpips']:.3f}" if "lpips" in results else "unavailable"
    print(
        f"test-view PSNR {results['psnr']:.2f} dB, SSIM {results['ssim']:.3f}, LPIPS {lpips} "
        f"(constant-colour baseline: PSNR {baseline:.2f} dB)"
    )


if __name__ == "__main__":
    main()
