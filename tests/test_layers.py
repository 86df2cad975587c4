"""The package's layering: every module sits on a floor and imports only from its own floor or the floors
below. A new module must be given a floor here; an import that runs upwards fails this test (lazy imports
inside functions and typing-only imports count too: they are the same dependency, only later).

The floors, bottom to top (the rooms that issue 30's subpackages will make folders of):
0. the package root: one-line errors, progress lines, keyed caches, the config tables;
1. geometry and fields: NDC, ray marching, reprojection, camera conventions, poses and paths, what the cameras
   say about the scene, the VM grids, the field and its colour MLP; the metrics and offline LPIPS;
2. the model: config, rendering, objective, losses, geometric adaptation, batches, training schedule, scoring;
3. data: datamanager, dataset, dataparsers, sparse points, monocular depth, splits, the procedural scene;
4. tools: the offline evaluator, the demo, video rendering, ffmpeg, the sweep and the gate;
5. running: trainer, pipeline, checkpoints, presets, options.
"""

from __future__ import annotations

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "frugalnerf_ns"

FLOORS = {
    0: "errors progress cache config_files",
    1: "ndc raymarch reprojection camera_conventions novel_views video_path scene_analysis tensorial field color_mlp "
       "metrics lpips_offline",
    2: "model model_config rendering objective losses geometric_adaptation batch training_schedule image_scoring",
    3: "datamanager dataset dataparsers sparse_points mono_depth splits procedural_scene data novel_cameras",
    4: "offline_tools demo video ffmpeg_path sweep",
    5: "trainer pipeline checkpoints checkpoint_compat presets options stepping",
}
FLOOR = {name: floor for floor, names in FLOORS.items() for name in names.split()}


def room(path: Path) -> str:
    """The top-level module or subpackage of the package that ``path`` belongs to."""
    return path.relative_to(PACKAGE).with_suffix("").parts[0]


def imported_rooms(tree: ast.AST):
    """(line, room) of every import of a package module, wherever it stands in the file."""
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names = [node.module] + [f"{node.module}.{alias.name}" for alias in node.names]
        elif isinstance(node, ast.Import):
            names = [alias.name for alias in node.names]
        else:
            continue
        rooms = {name.split(".")[1] for name in names if name.startswith("frugalnerf_ns.")}
        for other in sorted(rooms & set(FLOOR)):
            yield node.lineno, other


def modules():
    return [p for p in sorted(PACKAGE.rglob("*.py")) if p.name != "__init__.py" or p.parent != PACKAGE]


def upward_imports(sources):
    """Every import that runs upwards in ``sources`` ((path, text) pairs), as ``file:line`` lines."""
    found = []
    for path, text in sources:
        me = room(path)
        for line, other in imported_rooms(ast.parse(text)):
            if other != me and FLOOR[other] > FLOOR[me]:
                found.append(f"{path.relative_to(PACKAGE.parent)}:{line} (floor {FLOOR[me]}) imports {other} (floor {FLOOR[other]})")
    return found


def test_every_module_has_a_floor():
    assert sorted({room(p) for p in modules()} - set(FLOOR)) == []


def test_no_module_imports_from_a_floor_above_its_own():
    assert upward_imports((p, p.read_text()) for p in modules()) == []


def test_an_upward_import_is_caught():
    # The check itself: a floor-1 module importing the model (floor 2) lazily, inside a function.
    text = "import torch\n\n\ndef f():\n    from frugalnerf_ns.model import FrugalNeRFModel\n"
    assert upward_imports([(PACKAGE / "ndc.py", text)]) == ["frugalnerf_ns/ndc.py:5 (floor 1) imports model (floor 2)"]
    # Sideways (same floor) and downwards are fine; "from frugalnerf_ns import x" names the module x.
    text = "from frugalnerf_ns import losses, errors\nfrom frugalnerf_ns.rendering import StepRender\n"
    assert upward_imports([(PACKAGE / "model.py", text)]) == []
    assert upward_imports([(PACKAGE / "errors.py", "from frugalnerf_ns import metrics\n")]) == [
        "frugalnerf_ns/errors.py:1 (floor 0) imports metrics (floor 1)"]
