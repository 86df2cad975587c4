"""Keyed array caches next to the data (sparse points, monocular depth): written atomically, used only when
the key they were written for matches, rebuilt when stale or unreadable."""

from __future__ import annotations

import hashlib
from pathlib import Path
from typing import Dict, Optional, Sequence, Tuple

import numpy as np


def save_keyed_arrays(path: Path, key: str, **arrays: np.ndarray) -> None:
    """Write ``arrays`` and ``key`` to ``path`` (npz). Atomic: an interrupted write never leaves a half file
    under the real name. Raises OSError where the folder is not writable."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp.npz")
    np.savez(tmp, key=np.array(key), **arrays)
    tmp.replace(path)


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
