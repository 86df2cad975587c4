"""Grid sizes: per-axis resolutions for a voxel count over a box, and the voxel counts of an upsampling schedule."""

from __future__ import annotations

import math
from typing import List, Sequence, Tuple


def log_linear_voxel_counts(initial: int, final: int, num_upsamples: int) -> List[int]:
    """Voxel counts after each upsampling: from ``initial`` to ``final`` in equal ratios (TensoRF)."""
    if num_upsamples <= 0:
        return []
    log_a, log_b = math.log(initial), math.log(final)
    return [int(round(math.exp(log_a + (log_b - log_a) * (i + 1) / num_upsamples))) for i in range(num_upsamples)]


def spanning_stride(settings) -> int:
    """The stride of the coarsest scale, whose view must span the box (``scale_spanning_grid``, ``num_lower_scales``
    and ``downsample_ratio`` of the model's ``settings``), else 1."""
    if not settings.scale_spanning_grid:
        return 1
    return settings.downsample_ratio**settings.num_lower_scales


def resolution_for_voxels(
    num_voxels: int, box_size: Sequence[float], span_stride: int = 1
) -> Tuple[int, int, int]:
    """Per-axis resolution with cubic voxels filling a box of ``box_size`` with about ``num_voxels``.

    ``span_stride`` > 1 rounds each axis to the nearest ``span_stride * k + 1`` entries (k >= 1), so a view keeping
    every ``span_stride``-th entry (a lower scale) ends on the box's far face instead of stopping short of it
    (``coords_for_stride``: points beyond a view's last entry read that entry). A small grid may lose up to half a
    coarse interval per axis: 35x39x23 becomes 33x33x17 on LLFF's NDC box, 59 % of the voxels.
    """
    volume = math.prod(float(s) for s in box_size)
    voxel = (volume / num_voxels) ** (1.0 / 3.0)
    resolution = [max(2, int(float(s) / voxel)) for s in box_size]
    if span_stride > 1:
        resolution = [span_stride * max(1, round((r - 1) / span_stride)) + 1 for r in resolution]
    return tuple(resolution)  # type: ignore[return-value]
