"""Let nerfstudio 1.1.5 load its own checkpoints under torch >= 2.6.

torch 2.6 made ``torch.load(weights_only=True)`` the default; nerfstudio's checkpoints hold numpy scalars
(e.g. in scheduler state), so ns-eval, ns-render, ns-viewer and ``--load-dir`` resuming fail with
"Unsupported global: numpy...scalar". We allow exactly the numpy globals those checkpoints need, rather
than turning weights_only off (which would allow arbitrary code in a checkpoint to run).
"""

from __future__ import annotations

from typing import List

import numpy as np
import torch


def numpy_checkpoint_globals() -> List[object]:
    """The numpy reconstruction helpers a pickled numpy scalar refers to, and nothing else."""
    try:  # numpy >= 1.25 keeps the real module under numpy.core.multiarray / numpy._core.multiarray
        from numpy.core.multiarray import scalar  # type: ignore[attr-defined]
    except ImportError:  # pragma: no cover - numpy 2
        from numpy._core.multiarray import scalar  # type: ignore[no-redef]
    return [scalar, np.dtype, type(np.dtype(np.float64)), type(np.dtype(np.float32)), type(np.dtype(np.int64))]


def allow_nerfstudio_checkpoints() -> bool:
    """Register the globals once; returns False where torch has no safe-globals list (torch < 2.4)."""
    add = getattr(torch.serialization, "add_safe_globals", None)
    if add is None:
        return False
    add(numpy_checkpoint_globals())
    return True
