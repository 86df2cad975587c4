"""The space beyond a scene box as a bounded volume: an L-infinity scene contraction and disparity sampling
(pure torch, no nerfstudio imports).

A capture that circles an object in a room has its object in a box and the room around it, out to tens of box
sizes. mip-NeRF 360's contraction maps all of space into a ball of radius 2, the box's inside unchanged; with
the L-infinity norm (nerfstudio's ``SceneContraction(order=inf)``) the ball is the cube [-2, 2]^3 and its
shells are cubes, so a VM grid's planes and lines stay aligned with it. In box units q = (p - centre) / half
(the box is [-1, 1]^3):

    contract(q) = q                              where |q|_inf <= 1
                  (2 - 1 / |q|_inf) q / |q|_inf   beyond it

A point n box-halves away lands at contracted norm 2 - 1/n: equal steps in disparity 1/n are equal steps in
the contracted space, which is why the samples beyond the box are spaced linearly in disparity
(``disparity_bins``).
"""

from __future__ import annotations

import torch
from jaxtyping import Float
from torch import Tensor


def contract(points: Float[Tensor, "*bs 3"], centre: Float[Tensor, "3"], half: Float[Tensor, "3"]) -> Float[Tensor, "*bs 3"]:
    """World points to contracted box units: the box [-1, 1]^3 as it is, all space beyond it into [-2, 2]^3."""
    q = (points - centre) / half
    norm = q.abs().amax(dim=-1, keepdim=True)
    outside = norm > 1.0
    safe = torch.where(outside, norm, torch.ones_like(norm))
    return torch.where(outside, (2.0 - 1.0 / safe) * q / safe, q)


def uncontract(contracted: Float[Tensor, "*bs 3"], centre: Float[Tensor, "3"], half: Float[Tensor, "3"]) -> Float[Tensor, "*bs 3"]:
    """``contract``'s inverse for contracted norms below 2: |y|_inf = m = 2 - 1/n gives n = 1 / (2 - m) and
    q = y n / m."""
    norm = contracted.abs().amax(dim=-1, keepdim=True)
    outside = norm > 1.0
    safe = torch.where(outside, norm, torch.ones_like(norm))
    q = torch.where(outside, contracted / (safe * (2.0 - safe)), contracted)
    return q * half + centre


def disparity_bins(
    t_start: Float[Tensor, " rays"], t_end: Float[Tensor, " rays"], num_samples: int, jitter: bool
) -> tuple[Float[Tensor, "rays edges"], Float[Tensor, "rays samples"]]:
    """``num_samples`` bins per ray from ``t_start`` to ``t_end``, equal in disparity 1/t, and a sample in each:
    at the bin's middle in disparity, or anywhere in it (uniform in disparity) when ``jitter``. Returns the
    bin edges (increasing t, ``num_samples + 1``) and the samples' distances."""
    u = torch.linspace(0.0, 1.0, num_samples + 1, device=t_start.device, dtype=t_start.dtype)
    near, far = 1.0 / t_start[:, None], 1.0 / t_end[:, None]
    # (1 - u) near + u far, not near + u (far - near): the last edge is exactly t_end (near - near cancels).
    edges = 1.0 / (near * (1.0 - u[None, :]) + far * u[None, :])
    if jitter:
        offset = torch.rand(t_start.shape[0], num_samples, device=u.device, dtype=u.dtype)
    else:
        offset = torch.full((t_start.shape[0], num_samples), 0.5, device=u.device, dtype=u.dtype)
    disparity = near + (far - near) * (u[None, :-1] + offset * (u[1] - u[0]))
    return edges, 1.0 / disparity


def interval_distortion(weights: Float[Tensor, "rays bins"]) -> Float[Tensor, " rays"]:
    """mip-NeRF 360's distortion loss (its Eq. 15) of weights on ``bins`` equal intervals of [0, 1] (the samples
    beyond the box are equal in disparity, those in front of it equal in distance: equal in their own normalised
    coordinate): sum_ij w_i w_j |m_i - m_j| + 1/3 sum_i w_i^2 / bins, with m_i the intervals' midpoints. Low where
    a ray's weight sits in one place (a surface), high where it is spread (fog, floaters in front of a far
    surface). The double sum in O(bins) through prefix sums: sum_ij = 2 sum_i w_i (m_i W_<i - (w m)_<i)."""
    bins = weights.shape[-1]
    mids = (torch.arange(bins, device=weights.device, dtype=weights.dtype) + 0.5) / bins
    wm = weights * mids
    before_w = torch.cumsum(weights, dim=-1) - weights
    before_wm = torch.cumsum(wm, dim=-1) - wm
    cross = 2.0 * (weights * (mids * before_w - before_wm)).sum(dim=-1)
    return cross + (weights * weights).sum(dim=-1) / (3.0 * bins)
