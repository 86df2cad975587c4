"""The project's YAML tables (``configs/``) as the running code sees them.

The wheel ships ``configs/`` as the package ``frugalnerf_ns.configs``. A source checkout has no such folder
inside ``frugalnerf_ns``: an editable install maps the package to the checkout it was installed from, so a
second checkout put first on PYTHONPATH (a git worktree, the sweep's and the gate's children) would read the
installed checkout's presets and train them under its own name. Code that runs from a checkout therefore
reads that checkout's own ``configs/``.
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path


def checkout_configs() -> Path | None:
    """``configs/`` of the source checkout this package was imported from (None for an installed wheel)."""
    root = Path(__file__).resolve().parent.parent
    if (root / "pyproject.toml").is_file() and (root / "configs").is_dir():
        return root / "configs"
    return None


def config_text(name: str) -> str:
    """Text of ``configs/<name>``: the running checkout's file, else the installed package's."""
    folder = checkout_configs()
    if folder is not None:
        return (folder / name).read_text()
    return resources.files("frugalnerf_ns.configs").joinpath(name).read_text()
