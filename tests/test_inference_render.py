"""The inference marcher (blocks of samples, rays dropped when they leave the box or turn opaque) against the
training marcher it replaces outside training: same pixels, far fewer density lookups."""

import math

import pytest
import torch

from frugalnerf_ns.field.radiance_field import FrugalNeRFField
from frugalnerf_ns.geometry.raymarch import MAX_OPTICAL_DEPTH, intersect_aabb
from frugalnerf_ns.model.rendering import (
    FAINT_BUDGET,
    FAINT_WEIGHT,
    TERMINATION_TRANSMITTANCE,
    faint_samples_left_out,
    render_scale,
    render_scale_inference,
)
from tests.helpers import tiny_model
from tests.marching_scenes import AABB, SETTINGS, opaque_field, rays

def masked_slab_scene():
    """The slab field with its alpha mask, the test rays, their segments and a coloured background."""
    field = opaque_field(mask=True)
    origins, directions = rays()
    segments = intersect_aabb(origins, directions, field.aabb, 0.0)
    return field, origins, directions, segments, torch.tensor([0.2, 0.5, 1.0])


def both(field, scale, termination, background=torch.tensor([1.0, 1.0, 1.0])):
    """The oracle and the inference marcher; termination 0 also shades every faint sample (the exact mode)."""
    origins, directions = rays()
    segments = intersect_aabb(origins, directions, field.aabb, 0.0)
    with torch.no_grad():
        dense = render_scale(field, origins, directions, scale, background, segments, **SETTINGS, jitter=False)
        fast = render_scale_inference(field, origins, directions, scale, background, segments, **SETTINGS,
                                      termination=termination, faint_budget=0.0 if termination == 0 else FAINT_BUDGET)
    return dense, fast


@pytest.mark.parametrize("mask", [False, True])
@pytest.mark.parametrize("scale", [0, 1, 2])
def test_without_termination_the_blocks_give_the_dense_pixels(scale, mask):
    dense, fast = both(opaque_field(mask=mask), scale, termination=0.0)
    assert torch.allclose(fast.rgb, dense.rgb, atol=2e-6)
    assert torch.allclose(fast.accumulation, dense.accumulation, atol=2e-6)
    assert torch.allclose(fast.depth, dense.depth, atol=1e-5)
    assert dense.accumulation.max() > 0.999 and dense.accumulation[:20].abs().max() == 0  # opaque rays and misses


@pytest.mark.parametrize("scale", [0, 1, 2])
def test_early_termination_changes_no_pixel_by_a_level_and_skips_lookups(scale, monkeypatch):
    field, origins, directions, segments, background = masked_slab_scene()
    looked_up = []
    occupied_density = field.occupied_density

    def counting(positions, scale=0):
        looked_up.append(positions.shape[0])
        return occupied_density(positions, scale)

    monkeypatch.setattr(field, "occupied_density", counting)
    with torch.no_grad():
        dense = render_scale(field, origins, directions, scale, background, segments, **SETTINGS, jitter=False)
        # Blocks of 8 of the ~70 slots a ray has here (a 24^3 grid); real grids give hundreds of slots per ray.
        fast = render_scale_inference(field, origins, directions, scale, background, segments, **SETTINGS, block=8)
    assert (fast.rgb - dense.rgb).abs().max() < 1.0 / 255
    assert (fast.accumulation - dense.accumulation).abs().max() <= 1.1e-4
    assert (fast.depth - dense.depth).abs().max() < 1e-3 * float(segments.t_far.max())
    # The slab makes rays opaque half-way through the box: the slots behind it are never looked up (at the
    # full scale; the lower scales' few, long steps cross the box in two or three blocks), nor those of rays
    # that miss the box or have left it.
    # (The oracle marches only the slots some ray can reach, dense.t; the rule gives every ray dense.slots.)
    assert sum(looked_up) <= dense.t.shape[0] * dense.slots
    if scale == 0:
        assert sum(looked_up) < 0.3 * dense.t.numel()


def _kernels_if_any(name):
    if name == "torch":
        return None
    pytest.importorskip("warp")
    from frugalnerf_ns.field import fused_kernels

    return fused_kernels.warp_kernels("warp")


@pytest.mark.parametrize("marcher", ["torch", "warp"])
def test_a_ray_ends_at_the_slot_where_its_transmittance_falls_below_the_termination(marcher):
    # The accumulation of each ray is the sum of the dense weights of the slots marched before its optical depth
    # reached -log(termination): not one slot more, however the slots are blocked (blocks of 32 slots here).
    field, origins, directions, segments, background = masked_slab_scene()
    termination = TERMINATION_TRANSMITTANCE
    with torch.no_grad():
        dense = render_scale(field, origins, directions, 0, background, segments, **SETTINGS, jitter=False)
        fast = render_scale_inference(field, origins, directions, 0, background, segments, **SETTINGS, block=32,
                                      termination=termination, faint_budget=0.0, kernels=_kernels_if_any(marcher))
    delta = field.sample_step(0, SETTINGS["step_ratio"]) * SETTINGS["distance_scale"]
    optical = (dense.densities.double() * delta).clamp(0.0, MAX_OPTICAL_DEPTH)
    before = optical.cumsum(-1) - optical
    expected = torch.where(before < -math.log(termination), dense.weights.double(), 0.0).sum(-1)
    ended = expected > 1 - termination
    assert int(ended.sum()) > 100  # most rays turn opaque in the slab
    assert torch.allclose(fast.accumulation[:, 0].double(), expected, atol=2e-6)
    # Marching the rest of a block would have added up to ``termination`` more.
    assert float((dense.accumulation[ended, 0] - fast.accumulation[ended, 0]).max()) > 1e-5


def test_faint_samples_left_out_are_a_prefix_of_each_rays_faint_ones_within_the_budget():
    f = FAINT_WEIGHT
    weights = torch.tensor([
        [0.5 * f, 0.5, 0.9 * f, 0.5 * f, 0.5 * f, 3e-5],  # faint ones until the budget is spent; 3e-5: not shaded
        [f, 0.3, 0.2, 0.1, 0.0, 0.0],  # nothing below FAINT_WEIGHT: all shaded
        [0.9 * f, 0.95 * f, 0.1 * f, 0.0, 0.0, 0.0],  # 0.5 f already left out: the first fits, then the prefix ends
    ])
    shaded = weights > 1e-4
    left_so_far = torch.tensor([0.0, 0.0, 0.5 * f])
    left = faint_samples_left_out(weights, shaded, left_so_far, budget=1.6 * f)
    assert left.tolist() == [
        [True, False, True, False, False, False],
        [False] * 6,
        [True, False, False, False, False, False],
    ]
    assert not (left & ~shaded).any() and not (left & (weights >= FAINT_WEIGHT)).any()
    assert ((left_so_far + torch.where(left, weights, 0.0).sum(-1)) <= 1.6 * f + 1e-12).all()
    # Random weights: every ray's left-out weight within the budget, and the faint samples left out form a
    # prefix of its faint ones (a later faint sample is never left out while an earlier one is shaded).
    generator = torch.Generator().manual_seed(0)
    weights = torch.rand(500, 40, generator=generator) ** 4 * 0.02
    shaded = weights > 1e-4
    left = faint_samples_left_out(weights, shaded, torch.zeros(500), FAINT_BUDGET)
    assert (torch.where(left, weights, 0.0).sum(-1) <= FAINT_BUDGET + 1e-7).all() and left.any()
    faint = shaded & (weights < FAINT_WEIGHT)
    kept_faint = (faint & ~left).to(torch.int8)
    first_kept = torch.where(kept_faint.any(-1), kept_faint.argmax(-1), 40)
    assert not (left & (torch.arange(40)[None, :] > first_kept[:, None])).any()


def test_faint_samples_save_colour_reads_and_move_no_pixel_by_a_level(monkeypatch):
    field, origins, directions, segments, background = masked_slab_scene()
    shaded = []
    inference_color = field.inference_color

    def counting(positions, directions, scale=0):
        shaded.append(positions.shape[0])
        return inference_color(positions, directions, scale)

    monkeypatch.setattr(field, "inference_color", counting)
    with torch.no_grad():
        every = render_scale_inference(field, origins, directions, 0, background, segments, **SETTINGS, faint_budget=0.0)
        every_count, shaded[:] = sum(shaded), []
        faint = render_scale_inference(field, origins, directions, 0, background, segments, **SETTINGS)
    assert sum(shaded) < 0.95 * every_count
    assert (faint.rgb - every.rgb).abs().max() <= FAINT_BUDGET + 1e-6
    assert torch.equal(faint.accumulation, every.accumulation) and torch.equal(faint.depth, every.depth)
    assert FAINT_BUDGET + TERMINATION_TRANSMITTANCE < 1.0 / 255


def test_half_precision_inputs_composite_in_float32():
    field = opaque_field()
    origins, directions = rays()
    segments = intersect_aabb(origins, directions, field.aabb, 0.0)
    fast = render_scale_inference(field, origins.half().float(), directions, 0, torch.ones(3), segments, **SETTINGS)
    assert fast.rgb.dtype == torch.float32 and torch.isfinite(fast.rgb).all() and torch.isfinite(fast.depth).all()


def test_the_model_renders_outside_training_with_the_inference_marcher():
    model = tiny_model()
    model.eval()
    with torch.no_grad():
        for grid in (model.field.density_grid, model.field.appearance_grid):
            for tensor in (*grid.planes, *grid.lines):
                tensor.uniform_(0.0, 1.0)
    from nerfstudio.cameras.rays import RayBundle

    origins, directions = rays(200)
    bundle = RayBundle(origins=origins, directions=directions, pixel_area=torch.ones(200, 1))
    with torch.no_grad():
        fast = model.get_outputs(bundle)
        model.config.fast_inference = False
        dense = model.get_outputs(bundle)
    assert (fast["rgb"] - dense["rgb"]).abs().max() < 1.0 / 255
    assert (fast["accumulation"] - dense["accumulation"]).abs().max() <= 1.1e-4
    assert dense["accumulation"].max() > 0.99  # the test is about rays that do become opaque
    # With gradients on (nerfstudio's eval loss during training), the model keeps the training marcher.
    model.config.fast_inference = True
    with torch.enable_grad():
        assert model.get_outputs(bundle)["rgb"].requires_grad


def test_the_inference_marcher_renders_a_trained_run_as_the_training_marcher_does(trained_run):
    from nerfstudio.utils.eval_utils import eval_setup

    _, run_dir = trained_run
    _, pipeline, _, _ = eval_setup(run_dir / "config.yml", test_mode="test")
    model = pipeline.model
    model.num_rendered_scales = model.field.num_scales
    camera = pipeline.datamanager.eval_dataset.cameras[0:1]
    with torch.no_grad():
        fast = model.get_outputs_for_camera(camera)
        model.config.fast_inference = False
        dense = model.get_outputs_for_camera(camera)
    for suffix in ("", "_scale1", "_scale2"):
        difference = fast[f"rgb{suffix}"] - dense[f"rgb{suffix}"]
        assert -10 * torch.log10((difference**2).mean().clamp_min(1e-20)) > 50, suffix
        assert difference.abs().max() < 1.0 / 255, suffix
        assert torch.allclose(fast[f"depth{suffix}"], dense[f"depth{suffix}"], rtol=1e-3), suffix
    # The procedural object covers part of the view: rays that turn opaque (the ones stopped early) and rays
    # that cross the box to its end are both in the comparison.
    assert dense["accumulation"].max() > 0.999 and dense["accumulation"].min() < 0.01


def test_a_grid_too_large_to_bake_reads_its_planes_with_the_same_pixels(monkeypatch):
    import frugalnerf_ns.field.radiance_field as radiance_field

    field = opaque_field(mask=True)
    assert field.baked_density(0) is not None
    monkeypatch.setattr(radiance_field, "BAKED_DENSITY_MAX_ENTRIES", 1000)  # the paper preset's 640^3 case
    assert field.baked_density(0) is None
    for scale in (0, 2):
        dense, fast = both(field, scale, termination=0.0)
        assert torch.allclose(fast.rgb, dense.rgb, atol=2e-6)
        assert torch.allclose(fast.depth, dense.depth, atol=1e-5)


def hollow_field(activation: str, mask: bool) -> FrugalNeRFField:
    """A slab field on a grid fine along z with nothing in the front 40% of the box (the side the rays come
    from) nor in a gap in the middle: raw density below 0 there (ReLU: exactly 0; softplus: tiny, and the alpha
    mask leaves it out; ``mask``: build it)."""
    torch.manual_seed(3)
    field = FrugalNeRFField(AABB, (41, 49, 33), density_components=(4, 2, 2), appearance_components=(6, 2, 2),
                            mlp_hidden_dim=16, mlp_implementation="torch", density_activation=activation)
    with torch.no_grad():
        for plane in field.density_grid.planes:
            plane.uniform_(0.0, 0.3)
        for line in field.density_grid.lines:
            line.uniform_(0.0, 0.3)
            line[:, :, 6:9, :] += 6.0  # a slab across each axis, behind the empty front along z
        shift = 0.0 if activation == "relu" else 10.0  # softplus(x - 10): the slab must be dense there too
        field.density_grid.lines[0].add_(shift / 3)
        for empty in (slice(20, None), slice(10, 17)):  # z entries of the front 40% and of the gap
            field.density_grid.lines[0][:, :, empty, :] = -2.0  # the z line of the XY plane
            field.density_grid.planes[1][:, :, empty, :] = -2.0  # the XZ and YZ planes' z rows
            field.density_grid.planes[2][:, :, empty, :] = -2.0
        if mask:
            field.update_alpha_mask(SETTINGS["step_ratio"], SETTINGS["distance_scale"])
    return field


# ReLU without a mask: the grid's zero cells; with one on the grid's nodes: the cells in the mask; softplus:
# the mask alone.
@pytest.mark.parametrize("activation, mask", [("relu", False), ("relu", True), ("softplus", True)])
def test_rays_skip_the_groups_of_slots_that_cannot_hold_density_and_render_the_same_pixels(activation, mask):
    field = hollow_field(activation, mask)
    origins, directions = rays()
    segments = intersect_aabb(origins, directions, field.aabb, 0.0)
    with torch.no_grad():
        dense = render_scale(field, origins, directions, 0, torch.ones(3), segments, **SETTINGS, jitter=False)
    step, slots = field.sample_step(0, SETTINGS["step_ratio"]), dense.t.shape[1]
    hit = segments.hit
    dense_slot = dense.densities > 0
    assert dense_slot[hit].any(dim=-1).float().mean() > 0.6  # most rays do reach density
    empty = (~dense_slot) & (dense.t < segments.t_far[:, None])
    for group in (4, 8, 16):  # the marcher's 8, finer (a smaller dilation: more is skipped) and coarser groups
        groups = field.baked_density(0).occupied_groups(origins, directions, segments.t_near, step, slots, group)
        kept = groups.repeat_interleave(group, dim=1)[:, :slots]
        # Conservative: the oracle's density is exactly 0 at every skipped slot ...
        assert not (dense_slot & ~kept).any()
        if group == 4:
            # ... and not vacuous: most empty slots in front of the density are skipped, and (ReLU: its grid's
            # zero cells bound more tightly than the dilated mask) some of those behind a ray's first dense slot.
            before = torch.arange(slots)[None, :] < dense_slot.to(torch.uint8).argmax(dim=-1, keepdim=True)
            reach = dense_slot.any(dim=-1, keepdim=True)
            assert (~kept & empty & before & reach).sum() > 0.6 * (empty & before & reach).sum()
            if activation == "relu":
                assert (~kept & empty & ~before & reach).sum() > 0.2 * (empty & ~before & reach).sum() > 0
    for scale in (0, 1, 2):
        dense, fast = both(field, scale, termination=0.0)
        assert torch.allclose(fast.rgb, dense.rgb, atol=2e-6)
        assert torch.allclose(fast.accumulation, dense.accumulation, atol=2e-6)
        assert torch.allclose(fast.depth, dense.depth, atol=1e-5)


@pytest.mark.parametrize("scale", [0, 2])
def test_training_marcher_drops_only_slots_no_ray_reaches(scale, monkeypatch):
    from frugalnerf_ns.model import losses, rendering

    field = opaque_field(mask=True)
    origins, directions = rays()
    segments = intersect_aabb(origins, directions, field.aabb, 0.0)
    background = torch.tensor([0.2, 0.5, 1.0])

    def render_and_grads():
        torch.manual_seed(5)  # the same jitter for both
        render = render_scale(field, origins, directions, scale, background, segments, **SETTINGS, jitter=True)
        step = field.sample_step(scale, SETTINGS["step_ratio"])
        occlusion = losses.occlusion_loss(render.densities, render.colors, 4, 8, shaded=render.shaded, num_slots=render.slots)
        distortion = losses.distortion_loss(render.weights, render.t, step)
        field.zero_grad()
        (render.rgb.sum() + render.depth.sum() + occlusion + distortion).backward()
        grads = [p.grad.clone() for p in field.parameters() if p.grad is not None]
        return render, float(occlusion), float(distortion), grads

    cut, cut_occlusion, cut_distortion, cut_grads = render_and_grads()
    monkeypatch.setattr(rendering, "reachable_slots", lambda segments, step, num_samples: num_samples)
    full, full_occlusion, full_distortion, full_grads = render_and_grads()
    kept = cut.t.shape[1]
    assert cut.slots == full.slots == full.t.shape[1] > 1.3 * kept  # the box's diagonal is longer than any ray's path
    assert (full.weights[:, kept:] == 0).all() and (full.densities[:, kept:] == 0).all()
    assert torch.allclose(cut.weights, full.weights[:, :kept], rtol=1e-6, atol=1e-7)
    for name in ("rgb", "depth", "accumulation"):
        assert torch.allclose(getattr(cut, name), getattr(full, name), rtol=1e-6, atol=1e-6), name
    assert full_occlusion > 0 and cut_occlusion == pytest.approx(full_occlusion, rel=1e-6)
    assert full_distortion > 0 and cut_distortion == pytest.approx(full_distortion, rel=1e-5)
    assert len(cut_grads) == len(full_grads) > 0
    for a, b in zip(cut_grads, full_grads):
        assert torch.allclose(a, b, rtol=1e-5, atol=1e-6 * float(b.abs().max() or 1.0))


def test_the_group_bounds_volumes_are_the_max_pool_definitions():
    import torch.nn.functional as F

    from frugalnerf_ns.field import density

    generator = torch.Generator().manual_seed(31)
    nodes = torch.rand(9, 11, 13, generator=generator) > 0.93  # sparse: dilation changes many entries
    pooled = F.max_pool3d(nodes.float()[None, None], kernel_size=2, stride=1)[0, 0] > 0
    assert torch.equal(density.any_corner(nodes), pooled) and pooled.float().mean() < 0.6
    for axis in range(3):
        for radius in (0, 1, 3, 20):  # beyond the axis' length: every entry of a line that has one
            kernel, padding = [1, 1, 1], [0, 0, 0]
            kernel[axis], padding[axis] = 2 * min(radius, 6) + 1, min(radius, 6)  # max_pool3d's own limit
            expected = F.max_pool3d(nodes.float()[None, None], kernel_size=kernel, stride=1, padding=padding)[0, 0] > 0
            if radius <= 6:
                assert torch.equal(density.dilate_along(nodes, axis, radius), expected)
            else:
                whole_line = nodes.any(dim=axis, keepdim=True).expand_as(nodes)
                assert torch.equal(density.dilate_along(nodes, axis, radius), whole_line)
    # A baked field keeps its undilated volumes and the last few dilations.
    field = hollow_field("relu", True)
    baked = field.baked_density(0)
    first = baked._dilated_occupancy("cells in mask", (1, 1, 2))
    for r in range(2, density.DILATIONS_KEPT + 3):
        volume = baked._dilated_occupancy("cells in mask", (r, 1, 2))
        assert volume.dtype == torch.bool and volume.numel() == int(torch.tensor(baked.grid.shape[2:]).sub(1).prod())
        assert baked._dilated_occupancy("cells in mask", (1, 1, 2)) is first  # used each time: kept
    kept = [k for k in baked._dilated if k[0] != "base"]
    assert len(kept) == density.DILATIONS_KEPT and ("cells in mask", (2, 1, 2)) not in kept
    assert ("base", "cells in mask") in baked._dilated
