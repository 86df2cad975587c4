"""scripts/record_runs.py: finished runs of the sweep runner into a committed result record."""

import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _run(key, scene, psnr, status="ok", commit="abc1234", seed=42):
    return {"key": key, "scene": scene, "views": 2, "method": "frugalnerf-cpu", "seed": seed, "status": status,
            "parser_args": ["frugal-llff"], "num_test_views": 6, "commit": commit, "machine": {"cpu": "x"},
            "psnr": psnr, "ssim": 0.61234, "lpips": 0.25, "train_seconds": 704.0, "run_dir": "/somewhere"}


def test_runs_are_added_replaced_by_a_rerun_and_failures_left_out(tmp_path):
    results = tmp_path / "results.jsonl"
    lines = [_run("a", "fortress", 22.56166), _run("b", "fern", 18.0, status="failed"), _run("c", "fern", 17.0),
             _run("a", "fortress", 22.60001)]  # the store appends: the later line of a key wins
    results.write_text("\n".join(json.dumps(line) for line in lines) + "\n")
    record = tmp_path / "rows.json"
    record.write_text(json.dumps({"what": "kept", "runs": [_run("z", "horns", 18.4) | {"commit": "old0000"}]}))
    done = subprocess.run([sys.executable, str(ROOT / "scripts" / "record_runs.py"), str(results), "--record", str(record),
                           "--scenes", "fortress", "--note", "alone"], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    saved = json.loads(record.read_text())
    assert saved["what"] == "kept" and [r["scene"] for r in saved["runs"]] == ["fortress", "horns"]
    fortress = saved["runs"][0]
    assert fortress["psnr"] == 22.60001 and fortress["ssim"] == 0.61234 and fortress["train_minutes"] == 11.7
    assert fortress["note"] == "alone" and "run_dir" not in fortress
    # The same run recorded again replaces its entry.
    assert subprocess.run([sys.executable, str(ROOT / "scripts" / "record_runs.py"), str(results), "--record",
                           str(record), "--scenes", "fortress"], capture_output=True).returncode == 0
    assert [r["scene"] for r in json.loads(record.read_text())["runs"]] == ["fortress", "horns"]
