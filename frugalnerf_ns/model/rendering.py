"""Rendering the scales of the field along rays: what one scale renders, and what a training step keeps of
every scale for its losses (``StepRender``).

Two marchers share one sampling rule (``march_steps``: fixed steps from the ray's entry into the box):
``render_scale`` keeps every sample slot of every ray (training: the losses read weights, depths and colours
per sample, and gradients flow); ``render_scale_inference`` (no gradients: ns-eval, ns-render, the viewer)
walks the slots in blocks, drops a ray once it has left the box or once its transmittance is below
``TERMINATION_TRANSMITTANCE`` (what is left of it can change a pixel by less than 1/255), and returns only
the pixel values. ``render_scale`` is its test oracle (tests/test_inference_render.py)."""

from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass
import math
from typing import Dict, List, NamedTuple, Optional

import torch
from jaxtyping import Bool, Float
from torch import Tensor

from frugalnerf_ns.field.radiance_field import FrugalNeRFField
from frugalnerf_ns.field import fused_kernels
from frugalnerf_ns.geometry.raymarch import (
    MAX_OPTICAL_DEPTH,
    RaySegments,
    composite_rgb,
    composite_weights,
    march_steps,
    transmittance_weights,
)


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
    slots: int
    """Sample slots per ray of the scale's rule (``samples_per_ray``); the tensors keep only the first ones
    that some ray of the batch can reach (``reachable_slots``): the rest hold zero weight for every ray."""


def samples_per_ray(field_: FrugalNeRFField, scale: int, step: float, max_samples_per_ray: int) -> int:
    """Sample slots per ray at a scale: enough to cross the box's diagonal, at most the cap (divided by the
    scale's stride: the lower scales march with larger steps)."""
    diagonal = float((field_.aabb[1] - field_.aabb[0]).norm())
    limit = max(1, max_samples_per_ray // field_.stride(scale))
    return max(1, min(limit, int(diagonal / step) + 1))


def reachable_slots(segments: RaySegments, step: float, num_samples: int) -> int:
    """How many of ``num_samples`` slots some ray's segment can reach: slot i starts at t_near + i * step
    (``march_steps``), so past floor(longest segment / step) every slot of every ray lies beyond its far end
    (one slot more than that is kept against rounding). Dropping those changes no weight, depth or colour."""
    if segments.t_near.numel() == 0:
        return min(num_samples, 1)
    longest = float((segments.t_far - segments.t_near).max())
    return max(1, min(num_samples, int(longest / step) + 2))


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
    shade_rays: Optional[Bool[Tensor, " rays"]] = None,
    detached_rays: Optional[Bool[Tensor, " rays"]] = None,
) -> ScaleRender:
    """March one scale: fixed-step samples in the box, density where occupied, colour where it matters.

    ``shade_rays`` (None: all) limits the colour to the rays whose colour is read; the others' ``rgb`` is the
    background's share alone and their ``colors`` are zero. ``detached_rays`` (None: none) are shaded without
    gradient (their colour is read, but only detached): no backward pass through the colour MLP for them."""
    step = field_.sample_step(scale, step_ratio)
    num_samples = samples_per_ray(field_, scale, step, max_samples_per_ray)
    # Slots past every ray's exit would hold zero weight (about half of them in NDC scenes, where the box's
    # diagonal is much longer than a ray's path through it): they are not marched.
    t, valid = march_steps(segments, step, reachable_slots(segments, step, num_samples), jitter=jitter)
    positions = origins[:, None, :] + directions[:, None, :] * t[..., None]
    valid = valid & field_.inside(positions)
    # Each mask's slots found once, as flat indices (row-major: the order boolean indexing gives), and read and
    # written through them: boolean indexing finds them again at every read and write, forward and backward.
    flat_positions = positions.reshape(-1, 3)
    slots = valid.reshape(-1).nonzero().squeeze(1)
    densities = torch.zeros_like(t)
    if slots.numel():
        values = field_.density(flat_positions.index_select(0, slots), scale)
        densities = densities.reshape(-1).index_put((slots,), values.to(t.dtype)).view_as(t)
    comp = composite_weights(densities, t, step, distance_scale, segments.t_near, segments.t_far)
    shade = comp.weights > weight_threshold
    if shade_rays is not None:
        shade = shade & shade_rays[:, None]
    colors = torch.zeros(t.numel(), 3, device=t.device, dtype=t.dtype)
    read = [(shade, False)] if detached_rays is None else [
        (shade & ~detached_rays[:, None], False), (shade & detached_rays[:, None], True)]
    for mask, detached in read:
        slots = mask.reshape(-1).nonzero().squeeze(1)
        if slots.numel():
            with torch.set_grad_enabled(torch.is_grad_enabled() and not detached):
                values = field_.color(flat_positions.index_select(0, slots),
                                      directions.index_select(0, slots // t.shape[1]), scale)
            colors = colors.index_put((slots,), values.to(t.dtype))
    colors = colors.view(*t.shape, 3)
    rgb = composite_rgb(comp.weights, colors, background)
    return ScaleRender(rgb, comp.depth, comp.accumulation, comp.weights, t, densities, colors, shade, num_samples)


SKIP_GROUP = 8
"""Slots per group in the inference marcher's empty-space test (``BakedDensity.occupied_groups``): finer
groups are dilated less (more is skipped) but cost more lookups; 8 left ~30 % fewer slots than 16 on fern."""

TERMINATION_TRANSMITTANCE = 1e-4
"""A ray whose transmittance fell below this is finished: its remaining samples can add at most this much
to any colour channel (below 1/255) and take it from the background's share."""

FAINT_WEIGHT = 2e-3
"""Samples below this compositing weight are the ones a ray may leave unshaded (``FAINT_BUDGET``)."""

FAINT_BUDGET = 1.0 / 255.0 - TERMINATION_TRANSMITTANCE - 1e-4
"""Weight per ray whose colour the inference marcher may leave out (its faintest samples, first come first
left): with the termination's 1e-4 a pixel moves by less than 1/255 in every channel. On a trained fern
model about a fifth of the shaded samples carry ~1e-3 of a ray's weight between them; the colour MLP is
half of a frame."""


FUSED_CHUNK_RAYS = 1 << 18
"""Rays per chunk at least, outside training, where the fused kernels render on the CPU
(``FrugalNeRFModel.get_outputs_for_camera_ray_bundle``): a chunk marches its rays on every core
(``fused_kernels.density_march_blocks``) and a frame of up to 512x512 is one chunk, so the colour MLP's
spinning OpenMP threads meet the march once a frame, not once per 4096 rays. Memory stays bounded by the march's
blocks and ``SHADE_ROWS``."""

SHADE_ROWS = 1 << 15
"""Shaded samples whose colour one call of ``inference_color`` computes in the fused path (features, MLP inputs and
hidden layers of this many rows at once: ~30 MB at the CPU presets' sizes; parts of 128 k rows ran the colour MLP
~1.9x slower, their intermediate tensors no longer in the cache)."""

SHADE_ROW_STEP = 1 << 12
"""The row counts a frame's colour parts come in (``SHADE_ROWS``, or its last part padded to a multiple of this)."""


def render_in_chunks(model, bundle, rays_per_chunk: int) -> Dict[str, Tensor]:
    """What nerfstudio's ``Model.get_outputs_for_camera_ray_bundle`` does, with the caller's chunk size (not the
    config's: another thread may render at the same time): ``model.forward`` on each chunk of the image's rays
    (row-major), its tensor outputs joined in the image's shape on the bundle's device."""
    height, width = bundle.origins.shape[:2]
    joined = defaultdict(list)
    for start in range(0, len(bundle), rays_per_chunk):
        chunk = bundle.get_row_major_sliced_ray_bundle(start, start + rays_per_chunk).to(model.device)
        for name, value in model.forward(ray_bundle=chunk).items():
            if isinstance(value, Tensor):
                joined[name].append(value.to(bundle.directions.device))
    return {name: torch.cat(values).view(height, width, -1) for name, values in joined.items()}


class PixelRender(NamedTuple):
    """What a render outside training keeps of a scale: the pixel values."""

    rgb: Float[Tensor, "rays 3"]
    depth: Float[Tensor, "rays 1"]
    accumulation: Float[Tensor, "rays 1"]


def faint_samples_left_out(
    weights: Float[Tensor, "rays slots"], shaded: Bool[Tensor, "rays slots"], left_so_far: Float[Tensor, " rays"],
    budget: float,
) -> Bool[Tensor, "rays slots"]:
    """The shaded samples below ``FAINT_WEIGHT`` whose colour a ray leaves out: its faint samples in slot order
    while the weight left out (``left_so_far`` before these slots) stays within ``budget``. The running sum
    only grows, so the samples left out are a prefix of the ray's faint ones and their weights sum to at most
    ``budget``: the pixel loses at most that much of any channel."""
    faint = shaded & (weights < FAINT_WEIGHT)
    running = left_so_far[:, None] + torch.where(faint, weights, 0.0).cumsum(dim=-1)
    return faint & (running <= budget)


@torch.no_grad()
def render_scale_inference(
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
    block: int = 32,
    termination: float = TERMINATION_TRANSMITTANCE,
    faint_budget: float = FAINT_BUDGET,
    kernels=None,
) -> PixelRender:
    """``render_scale`` without jitter or gradients, marched ``block`` slots at a time over the rays still
    alive: the same samples (``march_steps``' rule), the same compositing (``composite_weights``: optical
    depth capped, exclusive transmittance from summed optical depths), the same colour threshold. A ray leaves
    the march when it has no slots left in its segment or its transmittance drops below ``termination`` (0
    keeps every ray to its end: the dense result up to float rounding). A ray leaves the colour of its faint
    samples (weight below ``FAINT_WEIGHT``) out, in order, while their weights sum to at most ``faint_budget``
    (``faint_samples_left_out``; 0 shades every sample above the threshold, as the oracle does): with the
    termination a pixel moves by less than 1/255.

    The slots come in groups of ``SKIP_GROUP``; a ray marches only the groups that can hold density
    (``BakedDensity.occupied_groups``: every skipped slot's density is exactly 0, so it would add nothing to
    any sum), ``block // SKIP_GROUP`` of them per iteration, in order. Density comes from
    ``field.occupied_density`` at every slot of a marched group (the baked grid: one dense read, no selection
    of the occupied slots); colour only at the slots whose weight passes the threshold, added per ray. The
    state of the rays still marching is kept packed, and a ray's sums are written out when it leaves.

    ``kernels`` (``fused_kernels.warp_kernels``; None: torch): the density pass as one fused
    kernel (``fused_kernels.density_march``, the same samples, weights and samples to shade) and the colour of
    every sample to shade in one batch, where the density is baked (on the rays' device: the model hands them over
    on the CPU only)."""
    step = field_.sample_step(scale, step_ratio)
    num_samples = samples_per_ray(field_, scale, step, max_samples_per_ray)
    rays, device = origins.shape[0], origins.device
    compute = torch.promote_types(origins.dtype, torch.float32)
    stop_optical = float("inf") if termination <= 0 else -math.log(termination)
    delta = step * distance_scale
    baked = field_.baked_density(scale)
    group = min(SKIP_GROUP, block)
    per_block = max(1, block // group)  # groups marched per iteration
    # Per ray: accumulated weight, weighted t (depth), colour. Rays that miss the box keep zeros.
    sums = torch.zeros(rays, 6, device=device, dtype=compute)
    ids = torch.nonzero(segments.hit, as_tuple=True)[0]
    o, d = origins[ids].to(compute), directions[ids].to(compute)
    t_near, t_far = segments.t_near[ids].to(compute), segments.t_far[ids].to(compute)
    if kernels is not None and baked is not None:
        fused = fused_kernels.density_march_blocks(
            kernels, baked, field_.aabb, field_.mask_lookup(), o, d, t_near, t_far,
            baked.group_bounds(d, step, group), step, num_samples, group, per_block, delta, weight_threshold,
            FAINT_WEIGHT, faint_budget, stop_optical, MAX_OPTICAL_DEPTH)
        sums[ids, 0], sums[ids, 1] = fused.accumulation.to(compute), fused.weighted_t.to(compute)
        rgb = torch.zeros(ids.numel(), 3, device=device, dtype=compute)
        # The shaded samples' colours in parts: a large chunk's features and MLP layers would not fit otherwise.
        for first in range(0, fused.rays.numel(), SHADE_ROWS):
            rows, t = fused.rays[first : first + SHADE_ROWS], fused.t[first : first + SHADE_ROWS].to(compute)
            count = rows.numel()
            # The last part padded (its last sample repeated) to a multiple of SHADE_ROW_STEP rows: oneDNN keeps
            # a compiled matrix product per row count, and a frame's last part had a count of its own (a video's
            # resident memory grew ~4 MB a frame).
            shape = min(SHADE_ROWS, -(-count // SHADE_ROW_STEP) * SHADE_ROW_STEP)
            padded = torch.cat([rows, rows[-1:].expand(shape - count)]) if shape > count else rows
            t = torch.cat([t, t[-1:].expand(shape - count)]) if shape > count else t
            positions = o[padded] + d[padded] * t[:, None]
            colors = field_.inference_color(positions, d[padded], scale, kernels)[:count].to(compute)
            rgb.index_add_(0, rows, colors * fused.weights[first : first + SHADE_ROWS].to(compute)[:, None])
        sums[ids, 2:5] = rgb
        return _pixels(sums, segments, background, compute)
    # The groups of slots each ray marches: those that start inside its segment and can hold density (the
    # others add nothing to any sum), in order, packed to the front of ``order`` (``count`` per ray).
    num_groups = -(-num_samples // group)
    starts = torch.arange(num_groups, device=device) * group
    wanted = t_near[:, None] + (starts[None, :].to(compute) + 0.5) * step < t_far[:, None]
    if baked is not None:
        wanted &= baked.occupied_groups(o, d, t_near, step, num_samples, group)
    count = wanted.sum(dim=-1)
    order = torch.argsort((~wanted).to(torch.uint8), dim=-1, stable=True)
    marching = count > 0
    ids, o, d, t_near, t_far, count, order = (x[marching] for x in (ids, o, d, t_near, t_far, count, order))
    optical_sum = torch.zeros(ids.numel(), device=device, dtype=compute)  # -log transmittance so far
    # Per ray: accumulated weight, weighted t, colour, and the weight whose colour was left out.
    ray_sums = torch.zeros(ids.numel(), 6, device=device, dtype=compute)
    in_group = torch.arange(group, device=device)
    ranks = torch.arange(per_block, device=device)
    first = 0  # the rank (among a ray's marched groups) of this iteration's first group
    while ids.numel() > 0:
        groups = order[:, first : first + per_block]
        index = (groups[:, :, None] * group + in_group).reshape(ids.numel(), -1)
        marched = ((first + ranks[: groups.shape[1]])[None, :] < count[:, None]).repeat_interleave(group, dim=1)
        # The same arithmetic as march_steps (offset 0.5 without jitter), so the positions are the oracle's.
        t = t_near[:, None] + (index.to(compute) + 0.5) * step
        positions = o[:, None, :] + d[:, None, :] * t[..., None]
        density = field_.occupied_density(positions.view(-1, 3), scale).view_as(t).to(compute)
        in_segment = marched & (t < t_far[:, None]) & (index < num_samples)
        optical = torch.where(in_segment, (density * delta).clamp(0.0, MAX_OPTICAL_DEPTH), 0.0)
        # A ray ends at the slot where its transmittance falls below ``termination``: the slots after it add nothing.
        before = optical_sum[:, None] + optical.cumsum(dim=-1) - optical
        optical = torch.where(before < stop_optical, optical, 0.0)
        weights, optical_sum = transmittance_weights(optical, optical_sum)
        ray_sums[:, 0] += weights.sum(dim=-1)
        ray_sums[:, 1] += (weights * t).sum(dim=-1)
        shade = weights > weight_threshold
        if faint_budget > 0:
            left_out = faint_samples_left_out(weights, shade, ray_sums[:, 5], faint_budget)
            ray_sums[:, 5] += torch.where(left_out, weights, 0.0).sum(dim=-1)
            shade &= ~left_out
        rows, cols = torch.nonzero(shade, as_tuple=True)
        if rows.numel():
            colors = field_.inference_color(positions[rows, cols], d[rows], scale).to(compute)
            ray_sums[:, 2:5].index_add_(0, rows, colors * weights[rows, cols, None])
        first += per_block
        marching = (count > first) & (optical_sum < stop_optical)
        if not bool(marching.all()):
            left = ~marching
            sums[ids[left]] = ray_sums[left]
            ids, o, d, t_far, t_near, count, order, optical_sum, ray_sums = (
                x[marching] for x in (ids, o, d, t_far, t_near, count, order, optical_sum, ray_sums))
    sums[ids] = ray_sums
    return _pixels(sums, segments, background, compute)


def _pixels(sums: Tensor, segments: RaySegments, background: Tensor, compute: torch.dtype) -> PixelRender:
    """Pixels from each ray's accumulated weight, weighted t and colour (``sums``' first five columns)."""
    accumulation, weighted_t, rgb = sums[:, 0], sums[:, 1], sums[:, 2:5]
    eps = torch.finfo(compute).eps
    depth = weighted_t / (accumulation + eps)
    depth = torch.maximum(torch.minimum(depth, segments.t_far.to(compute)), segments.t_near.to(compute))
    rgb = rgb + (1.0 - accumulation[:, None]) * background.to(compute)
    return PixelRender(rgb, depth[:, None], accumulation[:, None])


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
    background_depth: Optional[Float[Tensor, " rays"]] = None
    """Metric distance along each ray to the far background's sphere (None: no sphere); L_sd composites it
    behind the field's depth (``depth_through_box``)."""
    outer_distortion: Optional[Tensor] = None
    """Mean distortion of the samples outside the box (``OuterRender.distortion``; None: no outer space)."""
