"""Epipolar geometry of two views as pure torch functions: the fundamental matrix of two projection matrices
and each match's distance from its epipolar line (how ``scripts/diagnostics/check_dtu_cameras.py`` checks a
dataparser's converted cameras against SIFT matches: a wrong axis convention, principal point or intrinsics
scale moves true matches tens of pixels off their lines).

Conventions: projections are 3x4 OpenCV-style matrices, pixel = (P X)_{0,1} / (P X)_2, such as
``data.sparse_points.opencv_projection_matrices`` builds from nerfstudio cameras; pixels are (u, v) in the
same units. Works in the matrices' dtype (float64 for checks in pixels).
"""

from __future__ import annotations

import torch
from jaxtyping import Float
from torch import Tensor


def fundamental_from_projections(
    p1: Float[Tensor, "3 4"], p2: Float[Tensor, "3 4"], center1: Float[Tensor, "3"]
) -> Float[Tensor, "3 3"]:
    """F = [e2]_x P2 P1^+ (Hartley & Zisserman, eq. 9.1), e2 = P2 C1: x2^T F x1 = 0 for matching pixels."""
    e2 = p2 @ torch.cat([center1, torch.ones(1, dtype=p2.dtype)])
    cross = torch.tensor([[0, -e2[2], e2[1]], [e2[2], 0, -e2[0]], [-e2[1], e2[0], 0]], dtype=p2.dtype)
    return cross @ p2 @ torch.linalg.pinv(p1)


def epipolar_distances(
    f: Float[Tensor, "3 3"], x1: Float[Tensor, "matches 2"], x2: Float[Tensor, "matches 2"]
) -> Float[Tensor, " matches"]:
    """Distance in pixels of each x2 from the epipolar line F x1."""
    h1 = torch.cat([x1, torch.ones(len(x1), 1, dtype=x1.dtype)], 1)
    h2 = torch.cat([x2, torch.ones(len(x2), 1, dtype=x2.dtype)], 1)
    lines = h1 @ f.T
    return (h2 * lines).sum(-1).abs() / lines[:, :2].norm(dim=-1)
