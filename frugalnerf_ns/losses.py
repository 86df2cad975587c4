"""FrugalNeRF's loss terms, one function each (pure torch).

Eq. numbers refer to ``../shared/paper/frugalnerf-paper.tex``. The geometric adaptation terms (Eq. 2-10)
live with their geometry in ``reprojection.py``.
"""

from __future__ import annotations

from typing import Optional, Sequence, Tuple

import torch
from jaxtyping import Float
from torch import Tensor


def multiscale_color_loss(
    predictions: Sequence[Float[Tensor, "rays 3"]],
    target: Float[Tensor, "rays 3"],
    scale_weights: Sequence[float],
) -> Tensor:
    """Eq. 1, the multi-scale voxel colour loss: sum over scales l of w_l * MSE(C^l, C).

    The paper writes an unweighted sum and then says a weighted average is used; the weights are the
    reference code's per-scale colour weights (LLFF: 1 for the full scale, 10 for the lower ones).
    """
    if len(predictions) != len(scale_weights):
        raise ValueError(f"{len(predictions)} scale predictions but {len(scale_weights)} scale weights")
    return sum(w * torch.mean((pred - target) ** 2) for pred, w in zip(predictions, scale_weights))


def total_variation(
    tensor: Float[Tensor, "1 c h w"], edge_weights: Optional[Tuple[Tensor, Tensor]] = None
) -> Tensor:
    """TensoRF's TV of a plane or line: mean squared difference between neighbouring entries.

    ``edge_weights`` (one map per difference direction) make it edge-aware. A line (w == 1) has only the
    vertical term.
    """
    terms = []
    dh = (tensor[:, :, 1:, :] - tensor[:, :, :-1, :]).square()
    terms.append(dh if edge_weights is None else dh * edge_weights[0])
    if tensor.shape[-1] > 1:
        dw = (tensor[:, :, :, 1:] - tensor[:, :, :, :-1]).square()
        terms.append(dw if edge_weights is None else dw * edge_weights[1])
    return sum((t.mean() for t in terms if t.numel() > 0), tensor.new_zeros(()))


def edge_weights_from(appearance_plane: Float[Tensor, "1 c h w"]) -> Tuple[Tensor, Tensor]:
    """exp(-|grad appearance|), averaged over channels and detached: density may change across colour edges."""
    app = appearance_plane.detach()
    dh = (app[:, :, 1:, :] - app[:, :, :-1, :]).abs().mean(dim=1, keepdim=True)
    dw = (app[:, :, :, 1:] - app[:, :, :, :-1]).abs().mean(dim=1, keepdim=True)
    return torch.exp(-dh), torch.exp(-dw)


def grid_tv_loss(
    planes: Sequence[Tensor],
    lines: Sequence[Tensor],
    plane_weight: float,
    line_weight: float,
    edge_planes: Optional[Sequence[Tensor]] = None,
) -> Tensor:
    """L_tv on one VM grid: plane_weight * sum TV(planes) + line_weight * sum TV(lines).

    With ``edge_planes`` (the appearance planes of the same scale) the plane terms are edge-aware.
    """
    loss = planes[0].new_zeros(())
    for i, plane in enumerate(planes):
        weights = edge_weights_from(edge_planes[i]) if edge_planes is not None else None
        loss = loss + plane_weight * total_variation(plane, weights)
    for line in lines:
        loss = loss + line_weight * total_variation(line)
    return loss


def density_l1_loss(planes: Sequence[Tensor], lines: Sequence[Tensor]) -> Tensor:
    """L_l1: mean absolute value of the density components, pushing empty space to zero density."""
    return sum(p.abs().mean() for p in planes) + sum(line.abs().mean() for line in lines)


def distortion_loss(
    weights: Float[Tensor, "rays samples"], t: Float[Tensor, "rays samples"], step: float
) -> Tensor:
    """L_dist of Mip-NeRF 360 for samples of equal length ``step`` centred at ``t``.

    sum_ij w_i w_j |t_i - t_j| + 1/3 sum_i w_i^2 step, computed in O(N) with prefix sums (t sorted per ray).
    """
    w_t = weights * t
    prefix_w = torch.cumsum(weights, dim=-1) - weights
    prefix_wt = torch.cumsum(w_t, dim=-1) - w_t
    cross = 2.0 * (weights * (t * prefix_w - prefix_wt)).sum(dim=-1)
    self_term = (weights.square() * step).sum(dim=-1) / 3.0
    return (cross + self_term).mean()
