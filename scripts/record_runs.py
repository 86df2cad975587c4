"""Add finished runs of the sweep runner (``frugalnerf-bench scenes``, ``frugalnerf-gate``) to a committed result record.

    python scripts/record_runs.py <runs folder>/results.jsonl [...] --record docs/notes/paper_datasets/rows.json \
        [--scenes fortress re10k_5aca] [--note "what these runs were"]

Each run's scene, views, method, seed, split, test-view count, PSNR / SSIM / LPIPS, training minutes, commit and machine
are kept (the run folders and logs stay out of the repository). A run already in the record (same scene, views, method,
seed and commit) is replaced; the others are kept. Only runs with status "ok" are added.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any, Dict, List, Optional

KEEP = ("scene", "views", "method", "seed", "parser_args", "num_test_views", "commit", "machine")


def record_entry(run: Dict[str, Any], note: Optional[str]) -> Dict[str, Any]:
    entry = {key: run.get(key) for key in KEEP}
    entry.update({metric: round(float(run[metric]), 6) for metric in ("psnr", "ssim", "lpips")})  # the pages round it once
    entry["train_minutes"] = round(float(run["train_seconds"]) / 60, 1) if run.get("train_seconds") else None
    if note:
        entry["note"] = note
    return entry


def same_run(a: Dict[str, Any], b: Dict[str, Any]) -> bool:
    return all(a.get(k) == b.get(k) for k in ("scene", "views", "method", "seed", "commit"))


def main(argv: Optional[List[str]] = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("results", type=Path, nargs="+", help="results.jsonl of a runs folder")
    parser.add_argument("--record", type=Path, required=True, help="the record (JSON) to add the runs to")
    parser.add_argument("--scenes", nargs="*", help="only these scenes")
    parser.add_argument("--note", help="said of every run added (machine load, what differed)")
    args = parser.parse_args(argv)
    record = json.loads(args.record.read_text()) if args.record.exists() else {"runs": []}
    added = 0
    for path in args.results:
        if not path.is_file():
            print(f"record_runs: {path} is not a file", file=sys.stderr)
            return 2
        latest: Dict[str, Dict[str, Any]] = {}
        for line in path.read_text().splitlines():
            if line.strip():
                run = json.loads(line)
                latest[run["key"]] = run  # the store appends: the last line of a key is its state
        for run in latest.values():
            if run.get("status") != "ok" or (args.scenes and run["scene"] not in args.scenes):
                continue
            entry = record_entry(run, args.note)
            record["runs"] = [r for r in record["runs"] if not same_run(r, entry)] + [entry]
            added += 1
    record["runs"].sort(key=lambda r: (r["scene"], r["views"], r["method"], str(r["seed"]), str(r["commit"])))
    args.record.parent.mkdir(parents=True, exist_ok=True)
    args.record.write_text(json.dumps(record, indent=1) + "\n")
    print(f"record_runs: {added} runs into {args.record} ({len(record['runs'])} in all)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
