"""Which training cameras see a set of 3D points, given each camera's rendered depth (pure torch).

Used to split a run's test-view error into what the training views saw and what none of them saw
(``scoring/coverage.py``, ``scripts/diagnostics/error_by_coverage.py``). Cameras follow
``geometry/reprojection.py``: nerfstudio's camera-to-world [3, 4] with OpenGL axes, intrinsics (fx, fy, cx, cy),
pixel centres at i + 0.5, depths as distances along the unit ray.
"""

from __future__ import annotations

from typing import NamedTuple, Sequence

import torch
from jaxtyping import Bool, Float, Int
from torch import Tensor

from frugalnerf_ns.geometry.reprojection import project_to_camera


class Coverage(NamedTuple):
    seen_by: Int[Tensor, " points"]
    """How many cameras see the point: inside their image, and their own depth there agrees with its distance."""
    in_frustum: Bool[Tensor, " points"]
    """The point lands inside at least one camera's image, occlusion ignored."""
    colors: Float[Tensor, "points 3"]
    """The first seeing camera's image colour at the point's pixel (nearest pixel); 0 where unseen."""


def training_view_coverage(
    points: Float[Tensor, "points 3"],
    camera_to_worlds: Sequence[Float[Tensor, "3 4"]],
    intrinsics: Sequence[Float[Tensor, "4"]],
    depths: Sequence[Float[Tensor, "height width"]],
    images: Sequence[Float[Tensor, "height width 3"]],
    tolerance: float = 0.05,
    occlusion_only: bool = False,
) -> Coverage:
    """A point counts as seen by a camera when it projects inside the image and the camera's depth at that
    (nearest) pixel is its distance from the camera within ``tolerance`` (relative): nothing in front hides it.
    With ``occlusion_only``, a point nearer than that depth counts as seen too (only what lies behind the camera's
    surface is hidden): for depths from two renders of an unsure model, which rarely agree to a few per cent.

    The distance compared is the Euclidean one from the camera centre, as rendered depths are distances along
    unit rays."""
    count = points.shape[0]
    seen_by = torch.zeros(count, dtype=torch.long, device=points.device)
    in_frustum = torch.zeros(count, dtype=torch.bool, device=points.device)
    colors = torch.zeros(count, 3, dtype=points.dtype, device=points.device)
    colored = torch.zeros(count, dtype=torch.bool, device=points.device)
    for c2w, intr, depth, image in zip(camera_to_worlds, intrinsics, depths, images):
        height, width = depth.shape
        proj = project_to_camera(points, c2w.expand(count, 3, 4), intr.expand(count, 4))
        u, v = proj.pixels.unbind(-1)
        inside = proj.in_front & (u >= 0) & (u < width) & (v >= 0) & (v < height)
        col = u.clamp(0, width - 1).long()
        row = v.clamp(0, height - 1).long()
        distance = (points - c2w[:3, 3]).norm(dim=-1)
        behind = distance - depth[row, col]
        visible = inside & ((behind <= tolerance * distance) if occlusion_only else (behind.abs() <= tolerance * distance))
        in_frustum |= inside
        seen_by += visible.long()
        first = visible & ~colored
        colors[first] = image[row[first], col[first]].to(colors.dtype)
        colored |= visible
    return Coverage(seen_by, in_frustum, colors)
