"""``frugalnerf-bench <subcommand> [options]``: every development measurement behind one command.

Each subcommand is a module of this package with ``main(argv)``; it prints a table and writes JSON. The
modules are imported only when their subcommand runs (most of them import nerfstudio, which takes seconds).
"""

from __future__ import annotations

import importlib
import sys
from typing import List, Optional

# subcommand -> (module, what it measures); the order is the help's.
SUBCOMMANDS = {
    "scenes": ("scenes", "train and score the benchmark scenes (and baselines, ablations, seeds) with the sweep runner"),
    "tradeoff": ("tradeoff", "speed vs accuracy on one scene: budgets, lower scales, grid sizes, tensorf; anytime curves"),
    "vs-tensorf": ("vs_tensorf", "time per step, memory and test PSNR against nerfstudio's tensorf at equal grid and rays"),
    "render": ("render", "seconds per spiral frame and per test view of a trained run, before and after full-scale-only"),
    "viewer": ("viewer", "seconds per viewer frame and moving preview of trained runs, per render mode"),
    "next-view": ("next_view", "seconds for frugalnerf-next-view on a trained run, and for the start-up coverage line"),
    "startup": ("startup", "start-up time against the number of training views: parsing, images, SIFT, matching, triangulation"),
    "cameras": ("photo_cameras", "cameras estimated from LLFF photos alone against the published poses (photos without cameras)"),
    "model-size": ("model_size", "checkpoint size, parameters and first-step memory per preset at its final grid"),
    "step": ("step_time", "seconds per training step of a trained run, this source tree beside an earlier one"),
    "profile": ("profile_step", "where a training step's time goes (torch.profiler stages and operators)"),
    "gpu-check": ("gpu_check", "a CUDA machine end to end: presets, the paper run, speed, grid sample, memory, tcnn"),
}


def usage() -> str:
    width = max(map(len, SUBCOMMANDS))
    lines = ["usage: frugalnerf-bench <subcommand> [options]   (frugalnerf-bench <subcommand> --help for its options)", "",
             "subcommands:"]
    lines += [f"  {name:<{width}}  {what}" for name, (_, what) in SUBCOMMANDS.items()]
    return "\n".join(lines)


def main(argv: Optional[List[str]] = None) -> int:
    args = sys.argv[1:] if argv is None else list(argv)
    if not args or args[0] in ("-h", "--help"):
        print(usage())
        return 0
    name, rest = args[0], args[1:]
    if name not in SUBCOMMANDS:
        print(f"frugalnerf-bench: unknown subcommand {name!r}; choose one of {', '.join(SUBCOMMANDS)}", file=sys.stderr)
        return 2
    module = importlib.import_module(f"frugalnerf_ns.bench.{SUBCOMMANDS[name][0]}")
    code = module.main(rest)
    return code if isinstance(code, int) else 0


def worker_command(subcommand: str, *args: str) -> List[str]:
    """The command line that runs ``subcommand`` in a child process (for a measurement that needs its own
    process, so that its peak memory is its own)."""
    return [sys.executable, "-m", "frugalnerf_ns.bench.cli", subcommand, *args]


if __name__ == "__main__":
    sys.exit(main())
