"""Ray marching and alpha compositing as pure torch functions (no nerfstudio imports).

FrugalNeRF inherits TensoRF's renderer: samples at a fixed step along each ray inside the scene box, a
density activation, distances scaled by a constant before compositing, and colour evaluated only where
the compositing weight matters. Keeping these as plain functions lets the tests drive them at extremes
without building a model. nerfstudio's samplers and renderers are not used: its UniformSampler bins each
ray between its own near and far (not a fixed world step shared by the voxel grid and the alpha mask), and
the compositing here carries the stability fixes the numerical-stability suite needs (exclusive cumsum
without cancellation, an optical-depth cap, float32 compositing of half inputs).
"""

from __future__ import annotations

from typing import NamedTuple, Optional

import torch
from jaxtyping import Bool, Float
from torch import Tensor


class RaySegments(NamedTuple):
    """Where a batch of rays meets the scene box."""

    t_near: Float[Tensor, " rays"]
    t_far: Float[Tensor, " rays"]
    hit: Bool[Tensor, " rays"]


def intersect_aabb(
    origins: Float[Tensor, "rays 3"],
    directions: Float[Tensor, "rays 3"],
    aabb: Float[Tensor, "2 3"],
    near_plane: float = 0.0,
) -> RaySegments:
    """Slab test against an axis-aligned box. Rays that miss get t_near == t_far (an empty segment)."""
    # A direction component of exactly 0 gives +-inf slab distances, which is the right limit; only the
    # 0 * inf = nan case (origin on a slab plane) needs guarding, hence the tiny signed floor.
    safe_dir = torch.where(directions.abs() < 1e-12, torch.full_like(directions, 1e-12), directions)
    inv_dir = 1.0 / safe_dir
    t0 = (aabb[0] - origins) * inv_dir
    t1 = (aabb[1] - origins) * inv_dir
    t_near = torch.minimum(t0, t1).amax(dim=-1).clamp_min(near_plane)
    t_far = torch.maximum(t0, t1).amin(dim=-1)
    hit = t_far > t_near
    t_far = torch.where(hit, t_far, t_near)
    return RaySegments(t_near, t_far, hit)


def march_steps(
    segments: RaySegments, step: float, num_samples: int, jitter: bool
) -> tuple[Float[Tensor, "rays samples"], Bool[Tensor, "rays samples"]]:
    """Sample positions t_i = t_near + (i + u) * step, u ~ U[0, 1) per ray when jittering (training), else 0.5.

    Returns the sample distances and which of them lie before the far end of the ray's segment.
    """
    rays = segments.t_near.shape[0]
    index = torch.arange(num_samples, device=segments.t_near.device, dtype=segments.t_near.dtype)
    if jitter:
        offset = torch.rand(rays, 1, device=index.device, dtype=index.dtype)
    else:
        offset = torch.full((rays, 1), 0.5, device=index.device, dtype=index.dtype)
    t = segments.t_near[:, None] + (index[None, :] + offset) * step
    inside = t < segments.t_far[:, None]
    return t, inside


MAX_OPTICAL_DEPTH = 1e3
"""Largest optical depth sigma * delta of one sample: its alpha is 1 to every dtype's precision."""


class Composited(NamedTuple):
    weights: Float[Tensor, "rays samples"]
    accumulation: Float[Tensor, "rays 1"]
    depth: Float[Tensor, "rays 1"]


def transmittance_weights(
    optical: Float[Tensor, "rays samples"], optical_before: Optional[Float[Tensor, " rays"]] = None
) -> tuple[Float[Tensor, "rays samples"], Float[Tensor, " rays"]]:
    """Compositing weights from per-sample optical depths tau_i (NeRF's quadrature):
    w_i = (1 - exp(-tau_i)) * exp(-(tau_before + sum_{j<i} tau_j)), and the ray's total optical depth after
    the last sample (what a march continued block by block carries as ``optical_before``).

    The exclusive transmittance is a sum of optical depths, not a product of (1 - alpha) factors (which
    underflows in float16), and the inclusive sum is shifted rather than each sample's own term subtracted
    from it: after a large optical depth, sum - own loses the small remainder in float32 and the weights add
    up to more than 1.
    """
    before = torch.cumsum(torch.cat([torch.zeros_like(optical[..., :1]), optical[..., :-1]], dim=-1), dim=-1)
    if optical_before is not None:
        before = optical_before[..., None] + before
    weights = (1.0 - torch.exp(-optical)) * torch.exp(-before)
    return weights, before[..., -1] + optical[..., -1]


def composite_weights(
    densities: Float[Tensor, "rays samples"],
    t: Float[Tensor, "rays samples"],
    step: float,
    distance_scale: float,
    t_near: Optional[Float[Tensor, " rays"]] = None,
    t_far: Optional[Float[Tensor, " rays"]] = None,
) -> Composited:
    """Alpha compositing with TensoRF's distance scale: alpha_i = 1 - exp(-sigma_i * delta_i * scale).

    Depth is the expected termination distance normalised by the accumulated weight, clamped into the ray's
    segment so that a ray that hits nothing still reports a finite depth inside the box.
    """
    # Half-precision inputs (autocast) are composited in float32, as autocast itself does for exp and
    # cumsum: a near-empty ray's depth gradient ~ t / eps overflows float16, and bfloat16's 8-bit mantissa
    # makes the transmittance sum drift. Outputs come back in float32 then; float64 stays float64.
    compute = torch.promote_types(densities.dtype, torch.float32)
    densities, t = densities.to(compute), t.to(compute)
    if t_near is not None and t_far is not None:
        t_near, t_far = t_near.to(compute), t_far.to(compute)
    deltas = torch.full_like(densities, step * distance_scale)
    # The cap maps an overflowed (+inf) optical depth, e.g. a density of 1e6 in float16, to a finite one;
    # exp(-MAX_OPTICAL_DEPTH) is exactly 0 in every dtype, so results below the cap are unchanged.
    optical = (densities * deltas).clamp(0.0, MAX_OPTICAL_DEPTH)
    weights, _ = transmittance_weights(optical)
    accumulation = weights.sum(dim=-1, keepdim=True)
    eps = torch.finfo(weights.dtype).eps
    depth = (weights * t).sum(dim=-1, keepdim=True) / (accumulation + eps)
    if t_near is not None and t_far is not None:
        depth = torch.maximum(torch.minimum(depth, t_far[:, None]), t_near[:, None])
    return Composited(weights, accumulation, depth)


def composite_rgb(
    weights: Float[Tensor, "rays samples"],
    rgb: Float[Tensor, "rays samples 3"],
    background: Float[Tensor, "rays 3"] | Float[Tensor, "3"],
) -> Float[Tensor, "rays 3"]:
    """Colour = sum_i w_i c_i + (1 - sum_i w_i) * background."""
    accumulation = weights.sum(dim=-1, keepdim=True)
    return (weights[..., None] * rgb).sum(dim=-2) + (1.0 - accumulation) * background
