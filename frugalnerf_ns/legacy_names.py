"""Module names of the flat package that runs trained before the rooms still name.

A run's ``config.yml`` records the class path of every config and class it was built from, for example
``frugalnerf_ns.datamanager.FrugalDataManagerConfig``; ``ns-eval``, ``ns-render``, ``ns-viewer`` and a resumed
``ns-train`` import those paths. Each old module name below is served by the module that holds its code now
(the same module object, so classes compare equal); a name under an old package (``dataparsers.llff``) maps
the same way. ``model`` and ``data`` are rooms themselves and resolve their old class names in their
``__init__``.
"""

from __future__ import annotations

import importlib
import importlib.abc
import importlib.util
import sys
from types import ModuleType
from typing import Optional, Sequence

# old module (under frugalnerf_ns) -> its module now; only names that a saved config.yml can contain
MOVED = {
    "trainer": "run.trainer",
    "pipeline": "run.pipeline",
    "presets": "run.presets",
    "datamanager": "data.datamanager",
    "dataparsers": "data.dataparsers",
    "sparse_points": "data.sparse_points",
    "mono_depth": "data.mono_depth",
    "model_config": "model.frugalnerf",  # FrugalNeRFModelConfig: the settings of model/config.py bound to the model
}
PACKAGE = "frugalnerf_ns"


def current_name(fullname: str) -> Optional[str]:
    """Today's module name for an old one (``frugalnerf_ns.dataparsers.llff`` -> ``...data.dataparsers.llff``)."""
    if not fullname.startswith(PACKAGE + "."):
        return None
    head, _, rest = fullname[len(PACKAGE) + 1:].partition(".")
    if head not in MOVED:
        return None
    return f"{PACKAGE}.{MOVED[head]}" + (f".{rest}" if rest else "")


class _Alias(importlib.abc.Loader):
    def __init__(self, target: str) -> None:
        self.target = target

    def create_module(self, spec) -> ModuleType:
        return importlib.import_module(self.target)

    def exec_module(self, module: ModuleType) -> None:
        pass  # the module ran when it was imported under its own name


class OldModuleNames(importlib.abc.MetaPathFinder):
    """Serves ``frugalnerf_ns.<old name>`` with the module now at ``frugalnerf_ns.<room>.<name>``."""

    def find_spec(self, fullname: str, path: Optional[Sequence[str]] = None, target=None):
        new = current_name(fullname)
        if new is None:
            return None
        return importlib.util.spec_from_loader(fullname, _Alias(new))


def install() -> None:
    # First in the list: a path finder would otherwise load an old package's child (dataparsers.llff) a
    # second time from the new folder, as a different module with different classes.
    if not any(isinstance(finder, OldModuleNames) for finder in sys.meta_path):
        sys.meta_path.insert(0, OldModuleNames())
