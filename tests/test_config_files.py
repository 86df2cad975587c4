"""Where the code finds its files: one module (``config_files``) knows the checkout, the packaged tables and the outputs
folder; every other module asks it. The installed wheel itself is exercised end to end in tests/test_wheel.py."""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

from frugalnerf_ns import config_files
from frugalnerf_ns.tools.sweep import gate
from frugalnerf_ns.tools.sweep.runner import git_commit

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "frugalnerf_ns"


def test_in_a_checkout_the_tables_and_the_code_are_the_checkouts():
    assert config_files.checkout_root() == ROOT and config_files.code_root() == ROOT
    assert config_files.config_path("gate.yaml") == ROOT / "configs" / "gate.yaml"
    assert config_files.config_text("splits.yaml") == (ROOT / "configs" / "splits.yaml").read_text()
    assert config_files.outputs_dir("benchmark", "x.json") == Path("outputs/benchmark/x.json")  # under the cwd
    assert config_files.shared_data() == ROOT.parent / "shared" / "data"


def test_without_a_checkout_the_gate_stops_in_one_line(monkeypatch, tmp_path, capsys):
    monkeypatch.setattr(config_files, "PACKAGE_PARENT", tmp_path)  # as site-packages: no pyproject.toml, no configs/
    assert config_files.checkout_root() is None and config_files.shared_data() == Path.cwd().parent / "shared" / "data"
    assert gate.main(["--list"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("frugalnerf-gate: frugalnerf-gate needs a source checkout"), err


def test_a_run_records_a_commit_only_for_a_checkouts_root(tmp_path):
    head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, cwd=ROOT).stdout.strip()
    assert git_commit(ROOT) == head
    # A folder inside a repository that is not its root (site-packages in a venv inside a clone) names no commit.
    assert git_commit(ROOT / "frugalnerf_ns") is None and git_commit(tmp_path) is None


def test_no_module_but_config_files_builds_paths_from_its_own_location_or_names_the_outputs_folder():
    found = []
    for path in sorted(PACKAGE.rglob("*.py")):
        if path.name == "config_files.py":
            continue
        for number, line in enumerate(path.read_text().splitlines(), 1):
            code = line.split("#")[0]
            if re.search(r"__file__\)?\.(resolve\(\)\.)?parents?\b", code) or re.search(r"(Path\(|/ )[\"']outputs\b", code):
                found.append(f"{path.relative_to(ROOT)}:{number}: {line.strip()}")
    # The gate keeps its --against worktrees inside the checkout it needs anyway.
    assert found == ["frugalnerf_ns/tools/sweep/gate.py:263: dest = Path(root) / \"outputs\" / \"gate\" / \"worktrees\" / commit"]
