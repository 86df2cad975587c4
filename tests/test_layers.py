"""The package's layering: every room (subpackage, or module of the package root) sits on a floor and imports
only from its own floor or the floors below. A new room must be given a floor here; an import that runs upwards
fails this test (lazy imports inside functions and typing-only imports count too: they are the same dependency,
only later). The package's ``__init__`` says what each room holds.

The floors, bottom to top:
0. the package root (its ``__init__`` too): one-line errors, progress lines, keyed caches, the config tables and
   where files are, old module names, the typed batches the datamanager hands the model, the start-up hooks
   (checkpoint loading, a private ffmpeg);
1. geometry (rays, NDC, reprojection, poses and paths, scene analysis, epipolar checks), field (grids, field,
   colour MLP), scoring (metrics, offline LPIPS, pseudo-depth summary, coverage and next-view scores);
2. model (config, rendering, objective, losses, geometric adaptation, training schedule, scoring) and, beside it,
   data (datamanager, patches, training views, dataset, dataparsers, sparse points, COLMAP points, monocular
   depth, splits, the procedural scene): neither imports the other, they meet in the batch types below them;
3. tools: the offline evaluator, the demo, video rendering, the sweep and the gate;
4. run: trainer, pipeline, checkpoints, presets, options;
5. bench: the measurements behind ``frugalnerf-bench`` (they build presets' pipelines, so they sit above run).
"""

from __future__ import annotations

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "frugalnerf_ns"

FLOORS = {
    0: "__init__ errors progress cache config_files legacy_names configs batch checkpoint_compat ffmpeg_path",
    1: "geometry field scoring",
    2: "model data",
    3: "tools",
    4: "run",
    5: "bench",
}
# Rooms on one floor that must not import each other either.
APART = [("model", "data")]
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
    return sorted(PACKAGE.rglob("*.py"))


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


def sideways_imports(sources):
    """Every import between two rooms of a pair in ``APART``, as ``file:line`` lines."""
    apart = {frozenset(pair) for pair in APART}
    found = []
    for path, text in sources:
        me = room(path)
        for line, other in imported_rooms(ast.parse(text)):
            if frozenset((me, other)) in apart:
                found.append(f"{path.relative_to(PACKAGE.parent)}:{line} ({me}) imports {other}")
    return found


def test_the_model_and_the_data_do_not_import_each_other():
    assert sideways_imports((p, p.read_text()) for p in modules()) == []
    # The check itself: the datamanager importing the model's batch module, as it once did.
    text = "from frugalnerf_ns.model.batch import TrainBatch\n"
    assert sideways_imports([(PACKAGE / "data" / "datamanager.py", text)]) == [
        "frugalnerf_ns/data/datamanager.py:1 (data) imports model"]


def test_an_upward_import_is_caught():
    # The check itself: a floor-1 module importing the model (floor 2) lazily, inside a function.
    text = "import torch\n\n\ndef f():\n    from frugalnerf_ns.model.frugalnerf import FrugalNeRFModel\n"
    assert upward_imports([(PACKAGE / "geometry" / "ndc.py", text)]) == [
        "frugalnerf_ns/geometry/ndc.py:5 (floor 1) imports model (floor 2)"]
    # Sideways (same floor) and downwards are fine; "from frugalnerf_ns import x" names the module x.
    text = "from frugalnerf_ns import errors\nfrom frugalnerf_ns.field import tensorial\nfrom frugalnerf_ns.model.rendering import x\n"
    assert upward_imports([(PACKAGE / "model" / "objective.py", text)]) == []
    assert upward_imports([(PACKAGE / "errors.py", "from frugalnerf_ns import scoring\n")]) == [
        "frugalnerf_ns/errors.py:1 (floor 0) imports scoring (floor 1)"]


def module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def import_graph(sources):
    """{module: package modules it imports anywhere in its text} of (path, text) pairs; a module's own parent
    packages are left out (importing a child runs them first anyway, and they import nothing of it)."""
    texts = {module_name(path): text for path, text in sources}
    graph = {}
    for me, text in texts.items():
        found = set()
        for node in ast.walk(ast.parse(text)):
            if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                found |= {node.module} | {f"{node.module}.{alias.name}" for alias in node.names}
            elif isinstance(node, ast.Import):
                found |= {alias.name for alias in node.names}
        graph[me] = {m for m in found & set(texts) if m != me and not me.startswith(m + ".")}
    return graph


def circles(graph):
    """Every module that can reach itself through imports, sorted."""
    def reach(start):
        seen, todo = set(), list(graph[start])
        while todo:
            module = todo.pop()
            if module not in seen:
                seen.add(module)
                todo.extend(graph[module])
        return seen

    return sorted(module for module in graph if module in reach(module))


def test_no_import_circles():
    sources = [(p, p.read_text()) for p in sorted(PACKAGE.rglob("*.py"))]
    assert circles(import_graph(sources)) == []


def test_an_import_circle_is_caught():
    # A lazy import back from the settings to the model: the circle the model's config once had.
    sources = [
        (PACKAGE / "model" / "config.py", "def f():\n    from frugalnerf_ns.model.frugalnerf import Model\n"),
        (PACKAGE / "model" / "frugalnerf.py", "from frugalnerf_ns.model.config import Settings\n"),
        (PACKAGE / "model" / "losses.py", "from frugalnerf_ns.model import config\n"),
    ]
    assert circles(import_graph(sources)) == ["frugalnerf_ns.model.config", "frugalnerf_ns.model.frugalnerf"]


def test_every_room_says_what_it_holds_and_its_floor():
    rooms = [p for p in sorted(PACKAGE.iterdir()) if (p / "__init__.py").is_file() and p.name in FLOOR]
    assert {p.name for p in rooms} == {"geometry", "field", "scoring", "model", "data", "tools", "run", "bench"}
    for room_dir in rooms:
        doc = ast.get_docstring(ast.parse((room_dir / "__init__.py").read_text())) or ""
        assert doc.startswith(f"Floor {FLOOR[room_dir.name]}, "), room_dir.name


def unnamed_modules(package: Path):
    """The modules and subpackages of ``package`` its ``__init__`` docstring does not name as ``name`` (modules)
    or ``name/`` (subpackages)."""
    doc = ast.get_docstring(ast.parse((package / "__init__.py").read_text())) or ""
    names = [p.stem for p in package.glob("*.py") if p.name != "__init__.py"]
    names += [f"{p.name}/" for p in package.iterdir() if (p / "__init__.py").is_file()]
    return sorted(name for name in names if f"``{name}``" not in doc)


def test_every_package_docstring_names_each_of_its_modules():
    packages = [PACKAGE, *sorted(p.parent for p in PACKAGE.rglob("*/__init__.py"))]
    assert {package.relative_to(PACKAGE.parent).as_posix(): unnamed_modules(package) for package in packages
            if unnamed_modules(package)} == {}


MAX_MODULE_LINES = 450
MAX_LINES = {"data/datamanager.py": 300}  # nerfstudio's datamanager is already long; ours only adds the batch


def oversized(paths, limits=None, default=MAX_MODULE_LINES):
    """(module, lines, limit) of every module longer than its limit (physical lines)."""
    limits = MAX_LINES if limits is None else limits
    found = []
    for path in paths:
        name = path.relative_to(PACKAGE).as_posix()
        lines = len(path.read_text().splitlines())
        limit = limits.get(name, default)
        if lines > limit:
            found.append((name, lines, limit))
    return found


def test_every_module_fits_on_a_few_screens():
    assert oversized(modules()) == []


def test_an_oversized_module_is_caught():
    fake = PACKAGE / "data" / "datamanager.py"
    assert oversized([fake], {"data/datamanager.py": 10}) == [("data/datamanager.py", len(fake.read_text().splitlines()), 10)]
    assert oversized([fake], {}, default=10**6) == []
