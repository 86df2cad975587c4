"""The package installed as a wheel, away from any checkout: its console commands find their tables inside the
package, write under the folder they run in, and the gate (which needs a checkout's git history) says so in one line.

The wheel is built from this checkout (``pip install --no-deps --target``) and imported through PYTHONPATH from an
unrelated folder; every check first confirms that the wheel's copy, not the checkout's, is the one imported.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from frugalnerf_ns.bench.cli import SUBCOMMANDS

ROOT = Path(__file__).resolve().parents[1]
COMMANDS = ("frugalnerf-demo", "frugalnerf-sweep", "frugalnerf-gate", "frugalnerf-next-view", "frugalnerf-bench")

pytestmark = pytest.mark.e2e


@pytest.fixture(scope="module")
def installed(tmp_path_factory):
    """(site folder, an unrelated working folder, the environment that imports the wheel's copy)."""
    base = tmp_path_factory.mktemp("wheel")
    source, site, elsewhere = base / "source", base / "site", base / "elsewhere"
    elsewhere.mkdir()
    # Built from a copy of what the wheel is made of: setuptools builds in the source folder (build/, egg-info).
    for name in ("frugalnerf_ns", "configs"):
        shutil.copytree(ROOT / name, source / name, ignore=shutil.ignore_patterns("__pycache__"))
    for name in ("pyproject.toml", "README.md"):
        shutil.copy2(ROOT / name, source / name)
    built = subprocess.run([sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--no-build-isolation",
                            "--disable-pip-version-check", "--target", str(site), str(source)],
                           capture_output=True, text=True, cwd=elsewhere, timeout=600)
    assert built.returncode == 0, built.stderr[-2000:]
    env = {**os.environ, "PYTHONPATH": str(site)}
    where = subprocess.run([sys.executable, "-c", "import frugalnerf_ns; print(frugalnerf_ns.__file__)"],
                           capture_output=True, text=True, cwd=elsewhere, env=env, check=True).stdout.strip()
    assert Path(where).is_relative_to(site), f"the checkout's copy was imported: {where}"
    return site, elsewhere, env


def run(installed, *args, timeout=300):
    site, elsewhere, env = installed
    return subprocess.run([str(site / "bin" / args[0]), *args[1:]], capture_output=True, text=True, cwd=elsewhere,
                          env=env, timeout=timeout)


def test_every_console_command_and_bench_subcommand_prints_its_help(installed):
    for command in COMMANDS:
        done = run(installed, command, "--help")
        assert done.returncode == 0 and "usage" in done.stdout.lower(), (command, done.stderr[-1500:])
    for sub in SUBCOMMANDS:
        done = run(installed, "frugalnerf-bench", sub, "--help")
        assert done.returncode == 0 and "usage" in done.stdout.lower(), (sub, done.stderr[-1500:])


def test_the_scene_list_is_read_from_the_package(installed):
    site, elsewhere, _ = installed
    done = run(installed, "frugalnerf-bench", "scenes", "--list", "--data-root", str(elsewhere))
    assert done.returncode == 0, done.stderr[-1500:]
    first, *scenes = done.stdout.splitlines()
    assert first.startswith(str(site / "frugalnerf_ns" / "configs" / "benchmark_scenes.yaml"))
    assert any(line.strip().startswith("fern: 2/3/4 views, frugalnerf-cpu") for line in scenes)
    assert all(line.endswith("(not found: --data-root)") for line in scenes)  # nothing lies in the empty folder


def test_outputs_go_under_the_folder_the_command_runs_in(installed):
    site, elsewhere, _ = installed
    done = run(installed, "frugalnerf-bench", "scenes", "--scenes", "fern", "--data-root", str(elsewhere))
    assert done.returncode == 0, done.stderr[-1500:]
    assert "skipping fern: its data is not on this machine" in done.stdout
    assert json.loads((elsewhere / "outputs" / "benchmark" / "benchmark_scenes.json").read_text()) == []  # no runs
    assert not (site / "outputs").exists()


def test_the_gate_says_in_one_line_that_it_needs_a_checkout(installed):
    done = run(installed, "frugalnerf-gate", "--list")
    assert done.returncode == 2
    assert done.stderr.strip().count("\n") == 0, done.stderr
    assert "frugalnerf-gate needs a source checkout" in done.stderr and "clone of the repository" in done.stderr
