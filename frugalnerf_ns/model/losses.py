"""FrugalNeRF's loss terms, one function each (pure torch): every term the model adds to its objective.

Eq. numbers are the paper's (Lin et al., FrugalNeRF, CVPR 2025, main text; docs/method.md maps each to its
function and test). What the geometric adaptation loss compares
(the reprojection error and the pseudo depth, Eq. 2-4 and 6-8) is geometry and lives in
``reprojection.py``; the loss itself (Eq. 5, 9) is here.
"""

from __future__ import annotations

from typing import Optional, Sequence, Tuple

import torch
from jaxtyping import Bool, Float, Int
from torch import Tensor

from frugalnerf_ns.field.tensorial import strided_view
from frugalnerf_ns.geometry.reprojection import PseudoDepth


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


class _StridedTotalVariation(torch.autograd.Function):
    """sum_s weight_s * ``total_variation`` of a tensor's stride-s view (edge-aware at each stride where an edge
    source is given), with its gradient written into one tensor of the full size.

    The same value as summing ``total_variation`` over ``strided_view``s; autograd would zero-fill and copy a
    full-size gradient for every slice of every view (a dozen passes over the appearance planes per step), where
    the gradient of a mean of squared differences d is 2 d / n added at one end of each difference and
    subtracted at the other."""

    @staticmethod
    def forward(ctx, tensor: Tensor, edge_source: Optional[Tensor], strides: Tuple[int, ...],
                weights: Tuple[float, ...]) -> Tensor:  # type: ignore[override]
        total = tensor.new_zeros(())
        edges = []
        for stride, weight in zip(strides, weights):
            view = strided_view(tensor, stride)
            edge = None if edge_source is None else edge_weights_from(strided_view(edge_source, stride))
            edges.append(edge)
            total = total + weight * total_variation(view, edge)
        ctx.save_for_backward(tensor)
        ctx.edges, ctx.strides, ctx.weights = edges, strides, weights
        return total

    @staticmethod
    def backward(ctx, grad: Tensor):  # type: ignore[override]
        (tensor,) = ctx.saved_tensors
        out = torch.zeros_like(tensor)
        for stride, weight, edge in zip(ctx.strides, ctx.weights, ctx.edges):
            view, target = strided_view(tensor, stride), strided_view(out, stride)
            for axis in (2, 3):
                length = view.shape[axis]
                if length < 2:  # total_variation's term is absent (a line's width) or empty
                    continue
                diff = view.narrow(axis, 1, length - 1) - view.narrow(axis, 0, length - 1)
                step = diff * (grad * (2.0 * weight / diff.numel()))
                if edge is not None:
                    step = step * edge[axis - 2]
                target.narrow(axis, 1, length - 1).add_(step)
                target.narrow(axis, 0, length - 1).sub_(step)
        return out, None, None, None


def strided_total_variation(
    tensor: Float[Tensor, "1 c h w"],
    strides: Sequence[int] = (1,),
    weights: Optional[Sequence[float]] = None,
    edge_source: Optional[Float[Tensor, "1 k h w"]] = None,
) -> Tensor:
    """sum over ``strides`` of weight * ``total_variation`` of the tensor's ``strided_view`` (weights default to 1),
    edge-aware with ``edge_weights_from(strided_view(edge_source))`` where ``edge_source`` is given (detached)."""
    weights = tuple(float(w) for w in (weights if weights is not None else [1.0] * len(strides)))
    if len(weights) != len(strides):
        raise ValueError(f"{len(strides)} strides but {len(weights)} weights")
    source = None if edge_source is None else edge_source.detach()
    return _StridedTotalVariation.apply(tensor, source, tuple(int(s) for s in strides), weights)


def grid_tv_loss(
    planes: Sequence[Tensor],
    lines: Sequence[Tensor],
    plane_weight: float,
    line_weight: float,
    edge_planes: Optional[Sequence[Tensor]] = None,
    strides: Sequence[int] = (1,),
    stride_weights: Optional[Sequence[float]] = None,
) -> Tensor:
    """L_tv on one VM grid: plane_weight * sum TV(planes) + line_weight * sum TV(lines), summed over the views
    at ``strides`` (the scales' views of the same tensors) with ``stride_weights`` (default 1 each).

    With ``edge_planes`` (the appearance planes, full size) the plane terms are edge-aware, each view's edges from
    the appearance plane's view at the same stride.
    """
    weights = list(stride_weights) if stride_weights is not None else [1.0] * len(strides)
    loss = planes[0].new_zeros(())
    for i, plane in enumerate(planes):
        edges = edge_planes[i] if edge_planes is not None else None
        loss = loss + strided_total_variation(plane, strides, [plane_weight * w for w in weights], edges)
    for line in lines:
        loss = loss + strided_total_variation(line, strides, [line_weight * w for w in weights])
    return loss


def density_l1_loss(planes: Sequence[Tensor], lines: Sequence[Tensor]) -> Tensor:
    """L_l1: mean absolute value of the density components, pushing empty space to zero density."""
    return sum(p.abs().mean() for p in planes) + sum(line.abs().mean() for line in lines)


def distortion_loss(
    weights: Float[Tensor, "rays samples"], t: Float[Tensor, "rays samples"], step: float
) -> Tensor:
    """L_dist of Mip-NeRF 360 for samples of equal length ``step`` centred at ``t``.

    sum_ij w_i w_j |t_i - t_j| + 1/3 sum_i w_i^2 step, computed in O(N) with prefix sums (t sorted per ray).
    nerfstudio's ``distortion_loss`` takes a RaySamples with per-sample bins and forms the N x N pairwise
    matrix; our samples are equal steps (TensoRF marching), so the prefix-sum form needs only (t, step).
    """
    w_t = weights * t
    prefix_w = torch.cumsum(weights, dim=-1) - weights
    prefix_wt = torch.cumsum(w_t, dim=-1) - w_t
    cross = 2.0 * (weights * (t * prefix_w - prefix_wt)).sum(dim=-1)
    self_term = (weights.square() * step).sum(dim=-1) / 3.0
    return (cross + self_term).mean()


def occlusion_loss(
    densities: Float[Tensor, "rays samples"],
    colors: Optional[Float[Tensor, "rays samples 3"]],
    num_near_samples: int,
    num_background_samples: int,
    shaded: Optional[Tensor] = None,
    background_tolerance: float = 0.01,
    num_slots: Optional[int] = None,
) -> Tensor:
    """Occlusion regulariser (FreeNeRF; reference code ``cal_occ_loss``): mean density of the first
    ``num_near_samples`` samples of every ray, where few-shot fields grow floaters hugging the cameras.

    With ``colors`` (the background prior for object scenes on black or white), samples among the first
    ``num_background_samples`` whose colour is black or white (mean within ``background_tolerance`` of 0 or
    1) are penalised too: there the background colour is explained by density in front of the object.
    ``shaded`` marks samples whose colour was evaluated; the others never count as background.
    ``num_slots`` (default: the tensors' sample count) is the slot count the mean is taken over, when the
    tensors hold only the first slots of each ray (the rest of zero density).
    """
    num_samples = densities.shape[-1]
    index = torch.arange(num_samples, device=densities.device)
    mask = (index < num_near_samples).expand_as(densities)
    if colors is not None:
        mean = colors.mean(dim=-1)
        background = (mean < background_tolerance) | (mean > 1.0 - background_tolerance)
        if shaded is not None:
            background = background & shaded
        mask = mask | (background & (index < num_background_samples))
    total = (densities * mask.to(densities.dtype)).sum()
    return total / (densities.shape[0] * (num_samples if num_slots is None else max(num_slots, num_samples)))


def loss_weight_schedule(step: int, total_steps: int, ratio: float) -> float:
    """Factor on the decaying loss weights at ``step``: ratio^(step / total_steps).

    The reference code multiplies the lower-scale colour, TV, depth-smoothness and sparse-depth weights by
    the learning-rate decay factor every iteration (and divides the distortion weight by it), so by the last
    step they have fallen (grown) by ``ratio``, as the learning rate has. Steps past the end keep the final
    factor; ``ratio`` 1 (or no steps) turns the schedule off.
    """
    if total_steps <= 0 or ratio == 1.0:
        return 1.0
    if ratio <= 0:
        raise ValueError(f"loss weight decay ratio must be positive, got {ratio}")
    return float(ratio ** (min(max(step, 0), total_steps) / total_steps))


def geometric_adaptation_loss(
    depths: Float[Tensor, "scales rays"], pseudo: PseudoDepth
) -> Float[Tensor, ""]:
    """Eq. 5 (train rays) / Eq. 9 (novel rays): sum over scales of the squared difference between each
    scale's depth and the pseudo depth, averaged over the reliable rays (the paper sums over rays; a mean
    keeps lambda_geo independent of the batch size). 0 when no ray is reliable."""
    weight = pseudo.reliable.to(depths.dtype)
    squared = (depths - pseudo.depth[None]) ** 2
    return (squared * weight[None]).sum() / weight.sum().clamp_min(1.0)


def photometric_consistency_loss(
    source: Float[Tensor, "patches pixels 3"],
    warped: Float[Tensor, "patches pixels 3"],
    kept: Bool[Tensor, " patches"],
) -> Float[Tensor, ""]:
    """Not a paper term: the L1 colour difference between training pixels and where their rendered depth
    carries them in the nearest other training view (the warp of Eq. 2, with gradient through the depth),
    averaged over the ``kept`` patches; 0 when none is kept. Self-supervised depth's photometric loss
    (Monodepth) on the views a few-shot NeRF has: L_geo picks among the scales' depths by this error, this
    term moves the full scale's depth down its gradient."""
    weight = kept.to(source.dtype)
    per_patch = (source - warped).abs().mean(dim=(-1, -2))
    return (per_patch * weight).sum() / weight.sum().clamp_min(1.0)


def depth_smoothness_loss(depth: Float[Tensor, "patches 2 2"]) -> Float[Tensor, ""]:
    """Patch-wise depth smoothness (supp. "Losses", RegNeRF): squared differences between horizontally and
    vertically adjacent depths of each 2x2 novel-view patch, averaged over patches."""
    horizontal = (depth[:, :, 1:] - depth[:, :, :-1]) ** 2
    vertical = (depth[:, 1:, :] - depth[:, :-1, :]) ** 2
    return horizontal.sum(dim=(1, 2)).mean() + vertical.sum(dim=(1, 2)).mean()


def inverse_depth_term(rendered: Tensor, target: Tensor, min_depth: float = 1e-3) -> Tensor:
    """L_sd's term per observation (paper Eq. 11), (1/rendered - 1/target)^2 with depths clamped at ``min_depth``;
    ``inverse_depth_loss`` is its mean, and the sparse-depth diagnostic (``bench/sparse_fit.py``) sums it by band."""
    return (1.0 / rendered.clamp_min(min_depth) - 1.0 / target.clamp_min(min_depth)) ** 2


def inverse_depth_loss(rendered: Float[Tensor, " rays"], target: Float[Tensor, " rays"], min_depth: float = 1e-3) -> Tensor:
    """L_sd (paper Eq. 11, DS-NeRF; reference code: MSE on inverse depth) between rendered and sparse metric
    depths. Rendered depth is clamped at ``min_depth`` so an empty ray (depth ~0) cannot blow the loss up."""
    if rendered.numel() == 0:
        return rendered.sum() * 0.0
    return torch.mean(inverse_depth_term(rendered, target, min_depth))


def relative_disparity_loss(
    rendered: Float[Tensor, " rays"], target: Float[Tensor, " rays"], min_depth: float = 1e-3, delta: float = 0.2
) -> Tensor:
    """L_sd's error relative to each point's own disparity (not a paper form): e = target / rendered - 1, the
    inverse-depth difference in units of the point's inverse depth, under a Huber penalty (quadratic within
    ``delta``, linear beyond: a badly wrong ray pulls with a bounded gradient). Eq. 11's absolute inverse-depth MSE
    weighs a point 10 units away 100 times less than one 1 unit away: in a metric box around a phone capture the
    room's points (10-140 units) pull by ~1e-3 and the room settles at a quarter of their depth."""
    if rendered.numel() == 0:
        return rendered.sum() * 0.0
    error = (target.clamp_min(min_depth) / rendered.clamp_min(min_depth) - 1.0).abs()
    return torch.mean(torch.where(error < delta, 0.5 * error**2 / delta, error - 0.5 * delta))


def pearson_depth_loss(rendered: Float[Tensor, " rays"], predicted: Float[Tensor, " rays"], eps: float = 1e-8) -> Tensor:
    """L_d = 1 - Pearson correlation between rendered and predicted depth (0 when perfectly correlated,
    up to 2 when anti-correlated). Fewer than two rays, or a constant input, give no signal (0)."""
    if rendered.numel() < 2:
        return rendered.sum() * 0.0
    x = rendered - rendered.mean()
    y = predicted - predicted.mean()
    denom = torch.sqrt((x * x).sum() * (y * y).sum())
    if float(denom.detach()) <= eps:
        return rendered.sum() * 0.0
    return 1.0 - (x * y).sum() / denom


def per_view_pearson_loss(
    rendered: Float[Tensor, " rays"], predicted: Float[Tensor, " rays"], view: Int[Tensor, " rays"]
) -> Tensor:
    """Mean of ``pearson_depth_loss`` over the training views present in the batch (each view's prediction
    has its own scale and shift)."""
    views = torch.unique(view)
    return sum(pearson_depth_loss(rendered[view == v], predicted[view == v]) for v in views) / max(1, len(views))
