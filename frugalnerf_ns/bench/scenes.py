"""Train and evaluate FrugalNeRF (and optionally nerfstudio baselines) on the scenes of a config file: a
front-end that builds a sweep grid from its options and runs it with ``frugalnerf-sweep``'s runner.

Every run goes through ``python -m frugalnerf_ns.tools.offline_tools`` (ns-train with offline LPIPS) and is scored
by the same evaluator (masked for DTU). Writes a Markdown table and JSON: per scene and the average, PSNR /
SSIM / LPIPS / training time / checkpoint size / peak memory, side by side. Finished runs are kept in
``<out>/results.jsonl``: the same command again skips them (and retries failed ones once).

Usage:
  frugalnerf-bench scenes [--config configs/benchmark_scenes.yaml] [--scenes fern dtu_scan65]
         [--views 2 3] [--baselines tensorf nerfacto] [--variants no-geo no-novel single-scale]
         [--preset frugalnerf-cpu] [--only-baselines] [--max-iterations N] [--seeds 42 43] [--out outputs/benchmark]
         [--data-root DIR] [--list]

``--variants`` adds FrugalNeRF runs with the named option sets of the config's ``variants`` section (the
paper's ablations), each labelled ``<preset>[<variant>]`` in the table. ``--seeds`` repeats every run with each
seed (nerfstudio's ``--machine.seed``; FrugalNeRF's batch sampler ``--pipeline.datamanager.seed`` too) and adds
a mean row with the spread (max - min) per scene and method.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import List, Optional

import yaml

from frugalnerf_ns.bench.report import write_report
from frugalnerf_ns.tools.sweep.cli import run_sweep
from frugalnerf_ns.config_files import config_path, outputs_dir
from frugalnerf_ns.tools.sweep.grid import SCENE_PRESET, GridError, expand, scene_data
from frugalnerf_ns.tools.sweep.report import scene_table

markdown = scene_table  # the table this script has always written


def scene_list(config_file: Path, config, names: List[str], data_root: Optional[Path]) -> str:
    """One line per scene: its view counts, preset and data folder, and whether that folder is here."""
    lines = [f"{config_file}: {len(names)} scenes"]
    for name in names:
        entry = config["scenes"][name]
        views = "/".join(str(v) for v in sorted(int(k) for k in entry.get("views") or {}))
        data = scene_data(config_file, config, name, data_root)
        lines.append(f"  {name}: {views or '-'} views, {entry.get('preset', '-')}, {data} "
                     f"({'here' if data.is_dir() else 'not found: --data-root'})")
    return "\n".join(lines)


def main(argv: Optional[List[str]] = None) -> None:
    parser = argparse.ArgumentParser(prog="frugalnerf-bench scenes", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--config", type=Path, default=config_path("benchmark_scenes.yaml"))
    parser.add_argument("--scenes", nargs="*", help="scene names from the config (default: all)")
    parser.add_argument("--views", type=int, nargs="*", default=[2], help="training view counts (default 2)")
    parser.add_argument("--baselines", nargs="*", default=[], help="nerfstudio methods to train too (tensorf, nerfacto)")
    parser.add_argument("--variants", nargs="*", default=[], help="FrugalNeRF ablations from the config's variants")
    parser.add_argument("--preset", help="FrugalNeRF method for every scene (default: each scene's preset)")
    parser.add_argument("--only-baselines", action="store_true", help="skip FrugalNeRF (e.g. to add baselines later)")
    parser.add_argument("--max-iterations", type=int, help="override every method's iteration budget")
    parser.add_argument("--seeds", type=int, nargs="*", default=[], help="repeat every run with each seed")
    parser.add_argument("--out", type=Path, default=outputs_dir("benchmark"))
    parser.add_argument("--data-root", type=Path, help="where the scenes' data paths start (default: the config's data_root)")
    parser.add_argument("--list", action="store_true", help="print the config's scenes, their splits and data, then exit")
    args = parser.parse_args(argv)

    config = yaml.safe_load(args.config.read_text())
    names = args.scenes or list(config["scenes"])
    unknown_scenes = sorted(set(names) - set(config["scenes"]))
    if unknown_scenes:
        sys.exit(f"benchmark: unknown scenes {unknown_scenes}; {args.config} has {sorted(config['scenes'])}")
    if args.list:
        print(scene_list(args.config, config, names, args.data_root))
        return
    present = [n for n in names if scene_data(args.config, config, n, args.data_root).is_dir()]
    for name in sorted(set(names) - set(present)):
        print(f"benchmark: skipping {name}: its data is not on this machine")
    if not args.scenes:  # all of them: a scene with its own splits only (a capture, lego) sits out other counts
        for name in [n for n in present if not set(args.views) <= {int(k) for k in config["scenes"][n].get("views") or {}}]:
            print(f"benchmark: skipping {name}: it defines no {'/'.join(map(str, args.views))}-view split")
            present.remove(name)
    unknown = sorted(set(args.variants) - set(config.get("variants") or {}))
    if unknown:
        sys.exit(f"benchmark: unknown variants {unknown}; {args.config} has {sorted(config.get('variants') or {})}")
    options = {} if args.only_baselines else {"full": []}
    options.update({v: [*map(str, config["variants"][v])] for v in args.variants})
    methods = ([] if args.only_baselines else [args.preset or SCENE_PRESET]) + list(args.baselines)
    try:
        specs = expand(args.config, present, args.views, methods, options, args.seeds or [None], args.max_iterations,
                       data_root=args.data_root)
    except GridError as err:
        sys.exit(f"benchmark: {err}")
    records = [r for r in run_sweep(specs, args.out) if r.get("status") == "ok"]

    write_report("benchmark", markdown(records), records, args.out / "benchmark_scenes.json",
                 args.out / "benchmark_scenes.md")
    if len(records) < len(specs):
        sys.exit(f"benchmark: {len(specs) - len(records)} runs failed (their logs are in {args.out / 'logs'})")
