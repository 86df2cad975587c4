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
    """The stride of the coarsest scale whose view must span the box (``scale_spanning_grid``, ``num_lower_scales``,
    ``scale_spanning_scales`` and ``downsample_ratio`` of the model's ``settings``), else 1."""
    if not settings.scale_spanning_grid:
        return 1
    spanning = settings.num_lower_scales
    if settings.scale_spanning_scales is not None:
        spanning = min(spanning, settings.scale_spanning_scales)
    return settings.downsample_ratio**spanning


def resolution_for_voxels(
    num_voxels: int, box_size: Sequence[float], span_stride: int = 1, span_rounding: str = "nearest"
) -> Tuple[int, int, int]:
    """Per-axis resolution with cubic voxels filling a box of ``box_size`` with about ``num_voxels``.

    ``span_stride`` > 1 rounds each axis to a ``span_stride * k + 1`` entries (k >= 1), so a view keeping every
    ``span_stride``-th entry (a lower scale) ends on the box's far face instead of stopping short of it
    (``coords_for_stride``: points beyond a view's last entry read that entry). ``span_rounding`` "nearest"
    takes the nearest such size (a small grid may lose up to half a coarse interval per axis: 35x39x23 becomes
    33x33x17 on LLFF's NDC box, 59 % of the voxels), "up" the next one at or above the axis' size (never fewer
    entries: 49x49x33), "kept" the nearest unless the grid keeps less than ``KEPT_VOXEL_SHARE`` of the voxels,
    then the axes that lost most round up instead (33x33x33).
    """
    volume = math.prod(float(s) for s in box_size)
    voxel = (volume / num_voxels) ** (1.0 / 3.0)
    resolution = [max(2, int(float(s) / voxel)) for s in box_size]
    if span_rounding not in ("nearest", "up", "kept"):
        raise ValueError(f"span_rounding must be 'nearest', 'up' or 'kept', not {span_rounding!r}")
    if span_stride > 1:
        asked = resolution
        to_int = math.ceil if span_rounding == "up" else round
        resolution = [span_stride * max(1, to_int((r - 1) / span_stride)) + 1 for r in asked]
        if span_rounding == "kept":
            # Nearest, then the axis that lost the largest share of its entries rounds up instead, until the
            # grid keeps at least KEPT_VOXEL_SHARE of the voxels asked for.
            while math.prod(resolution) < KEPT_VOXEL_SHARE * math.prod(asked):
                axis = min(range(3), key=lambda i: resolution[i] / asked[i])
                resolution[axis] += span_stride
    return tuple(resolution)  # type: ignore[return-value]


KEPT_VOXEL_SHARE = 0.75
"""Least share of the asked voxels a grid rounded with ``span_rounding="kept"`` keeps."""
