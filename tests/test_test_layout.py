"""The suite's own layout: shared builders live in helper modules, and no test module imports another (a test
module's import would run its fixtures' module-level code twice and hide where a helper lives)."""

import ast
from pathlib import Path

TESTS = Path(__file__).resolve().parent


def imported_modules(path: Path):
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module:
            yield node.module
            yield from (f"{node.module}.{alias.name}" for alias in node.names)  # from tests import test_x
        elif isinstance(node, ast.Import):
            yield from (alias.name for alias in node.names)


def test_no_test_module_imports_another():
    offenders = {
        path.name: sorted(m for m in imported_modules(path) if m.split(".")[-1].startswith("test_") and m.startswith("tests"))
        for path in TESTS.glob("*.py")
    }
    assert {name: mods for name, mods in offenders.items() if mods} == {}
    assert len(list(TESTS.glob("test_*.py"))) > 40  # the glob found the suite
