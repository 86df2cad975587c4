"""Keyed array caches next to the data (sparse points, monocular depth): written atomically, used only when
the key they were written for matches, rebuilt when stale or unreadable."""

from __future__ import annotations

import hashlib
import os
import tempfile
from pathlib import Path
from typing import BinaryIO, Callable, Dict, Optional, Sequence, Tuple

import numpy as np


def write_atomically(path: Path, write: Callable[[BinaryIO], None]) -> None:
    """Call ``write`` on a new file beside ``path``, then rename it to ``path``. A reader sees the old file or the
    whole new one, never a part; an interrupted write leaves no half file under the real name. The staging name
    is unique per writer (not ``path`` + a fixed suffix): two processes filling the same cache at once (two
    ns-train on one photo folder) would otherwise truncate each other's staging file, one renaming it while the
    other still writes, the other's rename then failing. The last complete write wins. Raises OSError where the
    folder is not writable."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, staging = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".partial")
    try:
        with os.fdopen(fd, "wb") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())  # the data before the name: a power cut never leaves an empty file named as whole
        os.replace(staging, path)
    except BaseException:
        Path(staging).unlink(missing_ok=True)
        raise


def save_keyed_arrays(path: Path, key: str, **arrays: np.ndarray) -> None:
    """Write ``arrays`` and ``key`` to ``path`` (npz) with ``write_atomically``. Raises OSError where the
    folder is not writable."""
    write_atomically(path, lambda f: np.savez(f, key=np.array(key), **arrays))


def load_keyed_arrays(path: Path, key: str) -> Tuple[Optional[Dict[str, np.ndarray]], str]:
    """(arrays, "") from a file written for ``key``; (None, why) when it is missing, stale or unreadable.
    The caller checks that the arrays are consistent with each other."""
    if not path.exists():
        return None, "missing"
    try:
        with np.load(path, allow_pickle=False) as data:
            if str(data["key"]) != key:
                return None, "stale (training images, cameras or options changed)"
            return {name: data[name] for name in data.files if name != "key"}, ""
    except Exception as err:  # noqa: BLE001 - any unreadable file is rebuilt, never used
        return None, f"corrupt ({type(err).__name__}: {err})"


def cache_file_name(view_names: Sequence[str], width: int, height: int, kind: str) -> str:
    """Cache file of one training split and image size, e.g. ``sparse_depth_6-13_504x378.npz`` (``kind``
    names what is cached: sparse points, or mono_depth predictions)."""
    views = "-".join(Path(name).stem for name in view_names)
    if len(views) > 80:  # many views: keep the name short, still unique
        views = hashlib.sha1(views.encode()).hexdigest()[:12]
    return f"{kind}_{views}_{width}x{height}.npz"


CACHE_FOLDER = "frugalnerf_cache"
"""The cache folder's name inside a scene's data folder."""

_chosen_cache_dirs: Dict[Path, Path] = {}


def user_cache_root() -> Path:
    """This user's cache folder for scenes whose data folder cannot be written: $XDG_CACHE_HOME/frugalnerf
    (default ~/.cache/frugalnerf)."""
    base = os.environ.get("XDG_CACHE_HOME")
    if not base:
        try:
            base = str(Path.home() / ".cache")
        except RuntimeError:  # no home folder (a bare service account): the system's temporary folder
            base = tempfile.gettempdir()
    return Path(base) / "frugalnerf"


def _writable(folder: Path) -> bool:
    """The folder can be made and written, and its permissions (or those of its nearest existing parent) allow
    writing: a dataset marked read-only is not written, also by root, whom the system would let."""
    existing = next(p for p in (folder, *folder.parents) if p.exists())
    if existing.is_dir() and not existing.stat().st_mode & 0o222:
        return False
    try:
        folder.mkdir(parents=True, exist_ok=True)
        probe = folder / f".write-test-{os.getpid()}"
        probe.touch()
        probe.unlink()
        return True
    except OSError:
        return False


def scene_cache_dir(data: Path, say: Callable[[str], None] = print) -> Path:
    """Where a scene's caches (downscaled images, sparse points, monocular depth) go: ``frugalnerf_cache`` in its
    data folder, or, where that cannot be written (a read-only dataset mount, CI's shared data), a folder of its
    own in ``user_cache_root()``, said once per scene and process. Never an error: the fallback is only made
    when first written to."""
    folder = data.resolve()
    folder = folder.parent if folder.is_file() else folder  # a transforms.json given as --data
    if folder not in _chosen_cache_dirs:
        local = folder / CACHE_FOLDER
        if _writable(local):
            _chosen_cache_dirs[folder] = local
        else:
            digest = hashlib.sha1(str(folder).encode()).hexdigest()[:12]
            _chosen_cache_dirs[folder] = user_cache_root() / f"{folder.name}-{digest}"
            say(f"frugalnerf: {folder} cannot be written: its caches go to {_chosen_cache_dirs[folder]}")
    return _chosen_cache_dirs[folder]
