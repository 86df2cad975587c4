"""Where the running code finds its files: the project's YAML tables (``configs/``), the source checkout (when there
is one), the folder that holds the package, and where outputs go.

The wheel ships ``configs/`` as the package ``frugalnerf_ns.configs``. A source checkout has no such folder
inside ``frugalnerf_ns``: an editable install maps the package to the checkout it was installed from, so a
second checkout put first on PYTHONPATH (a git worktree, the sweep's and the gate's children) would read the
installed checkout's presets and train them under its own name. Code that runs from a checkout therefore
reads that checkout's own ``configs/``.

Installed from a wheel, nothing lies beside the package: outputs go under the current folder (as ``ns-train``'s
do), and the commands that need a checkout's files or git history say so (:func:`require_checkout`).
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path

# The folder that holds ``frugalnerf_ns``: a source checkout's root, or site-packages (or a --target folder).
PACKAGE_PARENT = Path(__file__).resolve().parent.parent


class CheckoutRequired(RuntimeError):
    """A command that needs a source checkout ran from an installed package; the message is one line."""


def checkout_root() -> Path | None:
    """Root of the source checkout this package was imported from (None for an installed wheel)."""
    if (PACKAGE_PARENT / "pyproject.toml").is_file() and (PACKAGE_PARENT / "configs").is_dir():
        return PACKAGE_PARENT
    return None


def checkout_configs() -> Path | None:
    """``configs/`` of the source checkout this package was imported from (None for an installed wheel)."""
    root = checkout_root()
    return None if root is None else root / "configs"


def code_root() -> Path:
    """The folder a child process puts first on PYTHONPATH to import this same code (checkout or installed)."""
    return PACKAGE_PARENT


def config_path(name: str) -> Path:
    """Path of ``configs/<name>``: the running checkout's file, else the installed package's."""
    folder = checkout_configs()
    if folder is not None:
        return folder / name
    return Path(str(resources.files("frugalnerf_ns.configs").joinpath(name)))


def config_text(name: str) -> str:
    """Text of ``configs/<name>``: the running checkout's file, else the installed package's."""
    return config_path(name).read_text()


def shared_data() -> Path:
    """``../shared/data`` beside the checkout (beside the current folder for an installed package): where the
    project's real scenes are kept (its README); the default of the commands' data options."""
    return (checkout_root() or Path.cwd()).parent / "shared" / "data"


def outputs_dir(*parts: str) -> Path:
    """``outputs/<parts>``, relative: under the folder a command runs in, where the commands write by default (as
    ``ns-train`` does), whether they run from a checkout or an installed package."""
    return Path("outputs", *parts)


def require_checkout(command: str, needs: str) -> Path:
    """The checkout's root, or :class:`CheckoutRequired` naming ``command`` and what it ``needs`` from one."""
    root = checkout_root()
    if root is None:
        raise CheckoutRequired(f"{command} needs a source checkout ({needs}); this one runs from an installed package "
                               f"at {PACKAGE_PARENT}: run it from a clone of the repository")
    return root
