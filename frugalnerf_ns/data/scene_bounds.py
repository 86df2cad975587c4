"""Near and far bounds of a scene whose poses carry no depth range (a capture in NeRF-synthetic's files, SLAM poses
of RealEstate-10K): from the points triangulated between its training views."""

from __future__ import annotations

from pathlib import Path
from typing import Callable, List, Optional, Sequence, Tuple

import numpy as np
import torch
from PIL import Image

from frugalnerf_ns.data.sparse_points import SparseDepth, TriangulationOptions
from frugalnerf_ns.data.training_points import all_training_sparse_depth

FAR_OVER_NEAR = 100.0
"""Captures: the far bound is at least this many times the near one (RealEstate's rooms take their own rule): a few points matched between 2-4 photos lie on the subject,
while the room around it reaches farther (COLMAP's bounds for the shared captures: the bird 125x, the juice box ~90x)."""
MIN_POINTS_FOR_BOUNDS = 10
"""Fewer triangulated points than this say nothing about the scene's depth range."""


def near_far_from_points(sparse: SparseDepth, c2w: np.ndarray) -> Optional[Tuple[float, float]]:
    """Near and far along the training cameras' axes (OpenGL: looking down -z) from their points: the 1st and 99th
    percentiles of the points' depths (LLFF's imgs2poses takes 0.1 and 99.9; a few points make those noisy), or None
    with fewer than ``MIN_POINTS_FOR_BOUNDS`` points in front of the cameras."""
    if sparse.num_points < MIN_POINTS_FOR_BOUNDS:
        return None
    points = sparse.points.double().numpy()[sparse.point.numpy()]
    pose = c2w[sparse.view.numpy()]
    depth = -np.einsum("nd,nd->n", points - pose[:, :3, 3], pose[:, :3, 2])
    depth = depth[depth > 0]
    if depth.size < MIN_POINTS_FOR_BOUNDS:
        return None
    return float(np.percentile(depth, 1.0)), float(np.percentile(depth, 99.0))


def training_points(
    files: Sequence[Path], c2w: np.ndarray, intrinsics: Sequence[Tuple[float, float, float, float]], cache_path: Path,
    say: Callable[[str], None],
) -> SparseDepth:
    """Every point triangulated between the training frames ``files`` (OpenGL camera-to-worlds ``c2w``, pinhole
    ``intrinsics`` fx fy cx cy per frame) with the default options, cached at ``cache_path``. For the bounds only:
    training triangulates again with its own options (--pipeline.datamanager.triangulation) in the model's frame."""
    images: List[np.ndarray] = []
    for file in files:
        with Image.open(file) as img:
            images.append(np.asarray(img.convert("RGB")))
    sparse, _ = all_training_sparse_depth(images, torch.from_numpy(np.asarray(c2w, dtype=np.float64)[:, :3, :4]),
                                          torch.tensor(list(intrinsics), dtype=torch.float64), TriangulationOptions(),
                                          None, cache_path, say)
    return sparse
