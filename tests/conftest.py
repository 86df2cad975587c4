import os
from pathlib import Path

import pytest

from frugalnerf_ns.data.procedural_scene import write_procedural_scene

os.environ.setdefault("PYTHONWARNINGS", "ignore")


@pytest.fixture(scope="session")
def procedural_scene(tmp_path_factory) -> Path:
    """The demo's procedural scene, written once per test session."""
    return write_procedural_scene(tmp_path_factory.mktemp("data") / "procedural")


@pytest.fixture(scope="session")
def trained_run(procedural_scene, tmp_path_factory):
    """frugalnerf-tiny trained on the procedural scene with ns-train and scored with ns-eval, once per session:
    (ns-eval's results, run folder)."""
    from frugalnerf_ns.tools.demo import train_and_eval

    out = tmp_path_factory.mktemp("outputs")
    results = train_and_eval(procedural_scene, out)
    return results, Path(results["run_dir"])
