"""``frugalnerf-bench next-view <run>/config.yml``: seconds for ``frugalnerf-next-view`` and the start-up coverage line.

Times, on one trained run: loading it (nerfstudio's ``eval_setup``, what the command pays once), ranking the
candidates and writing the three files for ``--count`` suggestions, and the coverage line of the start-up summary
(cameras only). Repeats each ``--repeats`` times and reports the median; writes JSON.
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import sys
import time
from pathlib import Path

from frugalnerf_ns.config_files import outputs_dir


def main(argv=None) -> list:
    parser = argparse.ArgumentParser(prog="frugalnerf-bench next-view", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("config", type=Path, help="config.yml of a trained FrugalNeRF run")
    parser.add_argument("--count", type=int, default=3)
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--out", type=Path, default=outputs_dir("benchmark_next_view.json"))
    args = parser.parse_args(argv)
    if not args.config.is_file():
        sys.exit(f"frugalnerf-bench next-view: error: {args.config} is not a file (pass <run>/config.yml)")

    from frugalnerf_ns.run.pipeline import photo_coverage
    from frugalnerf_ns.tools.next_view import load_pipeline, suggest

    start = time.perf_counter()
    pipeline = load_pipeline(args.config)
    load_s = time.perf_counter() - start
    suggest_s, line_s = [], []
    for _ in range(args.repeats):
        start = time.perf_counter()
        record = suggest(args.config, args.count, viewer_copy=False, pipeline=pipeline, print_fn=lambda _: None)
        suggest_s.append(time.perf_counter() - start)
        start = time.perf_counter()
        line = photo_coverage(pipeline.datamanager)
        line_s.append(time.perf_counter() - start)
    cameras = pipeline.datamanager.train_dataset.cameras
    rows = [
        {"what": "load the run (eval_setup)", "seconds": load_s},
        {"what": f"rank {record['candidates']} candidates, write {args.count} suggestions", "seconds": statistics.median(suggest_s)},
        {"what": "start-up coverage line", "seconds": statistics.median(line_s)},
    ]
    result = {
        "config": str(args.config), "machine": platform.processor() or platform.machine(),
        "image_size": f"{int(cameras.width[0])}x{int(cameras.height[0])}", "photos": len(cameras),
        "scene_type": pipeline.datamanager.scene_type, "rows": rows, "coverage_line": line,
        "total_seconds": load_s + statistics.median(suggest_s),
    }
    print(f"{'what':<48} {'seconds':>8}")
    for row in rows:
        print(f"{row['what']:<48} {row['seconds']:>8.2f}")
    print(f"{'frugalnerf-next-view in all (load + rank)':<48} {result['total_seconds']:>8.2f}")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1))
    return rows
