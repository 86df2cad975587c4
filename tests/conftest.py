import os
from pathlib import Path

import pytest

from frugalnerf_ns.procedural_scene import write_procedural_scene

os.environ.setdefault("PYTHONWARNINGS", "ignore")


@pytest.fixture(scope="session")
def procedural_scene(tmp_path_factory) -> Path:
    """The demo's procedural scene, written once per test session."""
    return write_procedural_scene(tmp_path_factory.mktemp("data") / "procedural")
