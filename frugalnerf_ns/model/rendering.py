"""Rendering the scales of the field along rays: what one scale renders, and what a training step keeps of
every scale for its losses (``StepRender``)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import List, NamedTuple, Optional

import torch
from jaxtyping import Bool, Float
from torch import Tensor

from frugalnerf_ns.field.radiance_field import FrugalNeRFField
from frugalnerf_ns.model.geometric_adaptation import AdaptationResult
from frugalnerf_ns.geometry.raymarch import RaySegments, composite_rgb, composite_weights, march_steps


def scale_suffix(scale: int) -> str:
    """Output name suffix: "" for the full scale, "_scale1", "_scale2", ... for the lower ones."""
    return "" if scale == 0 else f"_scale{scale}"


class ScaleRender(NamedTuple):
    rgb: Float[Tensor, "rays 3"]
    depth: Float[Tensor, "rays 1"]
    """Expected termination distance in the space the field is marched in (NDC t in NDC scenes)."""
    accumulation: Float[Tensor, "rays 1"]
    weights: Float[Tensor, "rays samples"]
    t: Float[Tensor, "rays samples"]
    densities: Float[Tensor, "rays samples"]
    colors: Float[Tensor, "rays samples 3"]
    shaded: Bool[Tensor, "rays samples"]
    """Samples whose colour was evaluated (compositing weight above the threshold)."""


def render_scale(
    field_: FrugalNeRFField,
    origins: Float[Tensor, "rays 3"],
    directions: Float[Tensor, "rays 3"],
    scale: int,
    background: Float[Tensor, "3"],
    segments: RaySegments,
    step_ratio: float,
    distance_scale: float,
    max_samples_per_ray: int,
    weight_threshold: float,
    jitter: bool,
) -> ScaleRender:
    """March one scale: fixed-step samples in the box, density where occupied, colour where it matters."""
    step = field_.sample_step(scale, step_ratio)
    diagonal = float((field_.aabb[1] - field_.aabb[0]).norm())
    limit = max(1, max_samples_per_ray // field_.stride(scale))
    num_samples = max(1, min(limit, int(diagonal / step) + 1))
    t, valid = march_steps(segments, step, num_samples, jitter=jitter)
    positions = origins[:, None, :] + directions[:, None, :] * t[..., None]
    valid = valid & field_.inside(positions)
    densities = torch.zeros_like(t)
    if valid.any():
        densities[valid] = field_.density(positions[valid], scale)
    comp = composite_weights(densities, t, step, distance_scale, segments.t_near, segments.t_far)
    colors = torch.zeros(*t.shape, 3, device=t.device, dtype=t.dtype)
    shade = comp.weights > weight_threshold
    if shade.any():
        dirs = directions[:, None, :].expand_as(positions)
        colors[shade] = field_.color(positions[shade], dirs[shade], scale)
    rgb = composite_rgb(comp.weights, colors, background)
    return ScaleRender(rgb, comp.depth, comp.accumulation, comp.weights, t, densities, colors, shade)


@dataclass
class StepRender:
    """What a training step rendered, for its losses: every scale's render of every ray of the batch."""

    background: Float[Tensor, "3"]
    """Background of this step (drawn per batch): the targets are composited on it too."""
    origins: Float[Tensor, "rays 3"]
    """World-space ray origins and unit directions (warping works in the world, also in NDC scenes)."""
    directions: Float[Tensor, "rays 3"]
    scales: List[ScaleRender]
    metric_depths: List[Float[Tensor, " rays"]]
    """Each scale's depth as metric distance along the world ray (what warping and L_sd use)."""
    adaptation: Optional[AdaptationResult] = field(default=None)
    """Cross-scale geometric adaptation of this step, computed once (metrics and losses share it)."""
