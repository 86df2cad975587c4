"""The renderer, geometry and losses at the extremes: finite values and gradients, and the right limits.

Property-based (hypothesis) where inputs range over orders of magnitude; plain tests for the
model-level cases (autocast, one training view, long training).
"""

import json
import math
import shutil

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from frugalnerf_ns.field.radiance_field import FrugalNeRFField
from frugalnerf_ns.model.geometric_adaptation import ADAPTATION_METRIC, ReferenceViews, pseudo_ground_truth_scale
from frugalnerf_ns.geometry.novel_views import nearest_other_view, spiral_poses
from frugalnerf_ns.geometry.raymarch import composite_rgb, composite_weights, intersect_aabb, march_steps
from frugalnerf_ns.geometry.reprojection import project_to_camera, unproject_along_rays, warp_to_views
from frugalnerf_ns.geometry.scene_analysis import classify_camera_layout
from frugalnerf_ns.data.sparse_points import TriangulationOptions, triangulate_tracks
from tests.helpers import INTRINSICS, camera, pixel_rays, plane_depth, render_plane

FAST = settings(max_examples=60, deadline=None)
magnitudes = st.floats(min_value=-3.0, max_value=3.0)  # log10 of a scene scale: 1e-3 .. 1e3


def finite(*tensors):
    return all(bool(torch.isfinite(t).all()) for t in tensors)


# ---- compositing -------------------------------------------------------------------------------------------
@FAST
@given(
    log_density=st.lists(st.floats(min_value=-8.0, max_value=6.0), min_size=1, max_size=64),
    zero_mask=st.lists(st.booleans(), min_size=64, max_size=64),
    step=st.floats(min_value=1e-4, max_value=10.0),
    dtype=st.sampled_from([torch.float32, torch.float64, torch.float16, torch.bfloat16]),
)
def test_compositing_is_finite_and_bounded_for_densities_from_0_to_1e6(log_density, zero_mask, step, dtype):
    raw = torch.tensor([10.0**v for v in log_density])
    raw = torch.where(torch.tensor(zero_mask[: len(raw)]), torch.zeros_like(raw), raw)  # exact zeros too
    densities = raw[None].to(dtype).requires_grad_(True)
    n = densities.shape[1]
    t = (torch.arange(n, dtype=torch.float32)[None] + 0.5) * step
    t_near, t_far = torch.zeros(1), torch.full((1,), n * step)
    comp = composite_weights(densities, t.to(dtype), step, 25.0, t_near.to(dtype), t_far.to(dtype))
    assert finite(comp.weights, comp.accumulation, comp.depth)
    tolerance = 1e-2 if dtype in (torch.float16, torch.bfloat16) else 1e-5
    assert float(comp.weights.min()) >= 0.0 and float(comp.accumulation.max()) <= 1.0 + tolerance
    assert 0.0 <= float(comp.depth) <= float(t_far[0]) * (1 + tolerance)
    (comp.depth.sum() + comp.accumulation.sum()).float().backward()
    if dtype == torch.float16:
        # A near-empty ray's depth gradient (~ t / eps) is finite in the float32 compositing but can
        # exceed float16's range once it reaches float16 densities: nerfstudio's GradScaler skips such
        # steps. It must never be NaN.
        assert not bool(torch.isnan(densities.grad).any())
    else:
        assert finite(densities.grad)


def test_opaque_first_sample_takes_everything_even_at_1e6():
    densities = torch.tensor([[1e6, 1e6, 0.0]], requires_grad=True)
    t = torch.tensor([[1.0, 2.0, 3.0]])
    comp = composite_weights(densities, t, 1.0, 25.0)
    assert torch.allclose(comp.weights, torch.tensor([[1.0, 0.0, 0.0]]))
    assert float(comp.depth) == pytest.approx(1.0)
    comp.depth.sum().backward()
    assert finite(densities.grad)


def test_rays_that_hit_nothing_report_the_background_and_a_depth_inside_their_segment():
    densities = torch.zeros(4, 16, requires_grad=True)
    t = torch.linspace(2.0, 5.0, 16).expand(4, 16)
    comp = composite_weights(densities, t, 0.2, 25.0, torch.full((4,), 2.0), torch.full((4,), 5.0))
    assert float(comp.accumulation.abs().max()) == 0.0
    assert torch.all((comp.depth >= 2.0) & (comp.depth <= 5.0))  # no 0/0: clamped into the segment
    rgb = composite_rgb(comp.weights, torch.rand(4, 16, 3), torch.tensor([1.0, 0.5, 0.0]))
    assert torch.allclose(rgb, torch.tensor([1.0, 0.5, 0.0]).expand(4, 3))
    comp.depth.sum().backward()
    assert finite(densities.grad)


@FAST
@given(log_scale=magnitudes, seed=st.integers(0, 1000))
def test_compositing_is_scale_invariant(log_scale, seed):
    """A scene scaled by s with densities scaled by 1/s renders the same weights and depth times s."""
    s = 10.0**log_scale
    generator = torch.Generator().manual_seed(seed)
    densities = torch.rand(3, 32, generator=generator, dtype=torch.float64) * 5
    t = torch.linspace(1.0, 4.0, 32, dtype=torch.float64).expand(3, 32)
    step = 3.0 / 31
    base = composite_weights(densities, t, step, 25.0)
    scaled = composite_weights(densities / s, t * s, step * s, 25.0)
    assert torch.allclose(scaled.weights, base.weights, atol=1e-9)
    assert torch.allclose(scaled.depth, base.depth * s, rtol=1e-9)


# ---- box intersection and sampling -----------------------------------------------------------------------
unit_components = st.floats(min_value=-1.0, max_value=1.0)


@FAST
@given(
    origin=st.tuples(*[st.floats(min_value=-2.0, max_value=2.0)] * 3),
    direction=st.tuples(unit_components, unit_components, unit_components),
    axis_aligned=st.booleans(),
    log_scale=magnitudes,
)
def test_box_intersection_is_ordered_and_finite_at_every_scale(origin, direction, axis_aligned, log_scale):
    s = 10.0**log_scale
    d = torch.tensor(direction, dtype=torch.float32)
    if axis_aligned:
        d = torch.zeros(3)
        d[int(torch.tensor(direction).abs().argmax())] = 1.0  # exact zeros in two components
    if float(d.norm()) < 1e-6:
        d = torch.tensor([0.0, 0.0, 1.0])
    d = torch.nn.functional.normalize(d, dim=0)[None]
    o = torch.tensor(origin, dtype=torch.float32)[None] * s
    aabb = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]]) * s
    seg = intersect_aabb(o, d, aabb, near_plane=0.0)
    assert finite(seg.t_near, seg.t_far)
    assert float(seg.t_far) >= float(seg.t_near) >= 0.0
    if bool(seg.hit):
        # Both ends lie on (or in) the box, up to float32 rounding at this scale.
        for t in (seg.t_near, seg.t_far):
            point = o + d * t[:, None]
            assert bool((point.abs() <= s * (1 + 1e-4)).all())


def test_origins_exactly_on_the_box_faces_and_rays_inside_the_faces_plane():
    aabb = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
    origins = torch.tensor([[-1.0, 0.0, 0.0], [1.0, 1.0, 1.0], [0.0, -1.0, 0.5]])
    directions = torch.tensor([[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0], [1.0, 0.0, 0.0]])  # the last slides along a face
    seg = intersect_aabb(origins, directions, aabb)
    assert finite(seg.t_near, seg.t_far)
    assert seg.t_far[0] == pytest.approx(2.0) and seg.t_near[0] == pytest.approx(0.0)


def test_samples_from_the_near_to_the_far_plane_and_on_voxel_borders_stay_finite():
    field = FrugalNeRFField(
        aabb=torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]]), resolution=(8, 8, 8), density_components=(2, 2, 2),
        appearance_components=(2, 2, 2), appearance_dim=6, mlp_hidden_dim=8, density_activation="softplus",
    )
    # Every voxel border and both box faces along each axis (the grid's nodes sit on the borders).
    ticks = torch.linspace(-1.0, 1.0, 9)
    points = torch.cartesian_prod(ticks, ticks, ticks)
    for scale in range(field.num_scales):
        field.zero_grad()
        density = field.density(points, scale)
        color = field.color(points, torch.nn.functional.normalize(torch.ones_like(points), dim=-1), scale)
        assert finite(density, color) and bool((density >= 0).all())
        (density.sum() + color.sum()).backward()
        grads = [p.grad for p in field.parameters() if p.grad is not None]
        assert grads and all(finite(g) for g in grads)
    # March from exactly the near plane to exactly the far plane.
    seg = intersect_aabb(torch.tensor([[0.0, 0.0, -3.0]]), torch.tensor([[0.0, 0.0, 1.0]]), field.aabb)
    t, valid = march_steps(seg, 0.25, 9, jitter=False)
    assert float(t[0, 0]) == pytest.approx(2.125) and bool(valid[0, :8].all()) and not bool(valid[0, 8])


# ---- warps -----------------------------------------------------------------------------------------------
@FAST
@given(
    depth_exponent=st.floats(min_value=-12.0, max_value=8.0),
    negative=st.booleans(),
    pixel=st.tuples(st.floats(min_value=-5.0, max_value=70.0), st.floats(min_value=-5.0, max_value=55.0)),
    yaw=st.floats(min_value=-1.55, max_value=1.55),
)
def test_warps_behind_the_camera_on_the_border_and_at_grazing_angles_are_finite(depth_exponent, negative, pixel, yaw):
    cameras = torch.stack([camera(), camera(x=1.0, yaw=yaw)])  # up to ~89 degrees: grazing views
    images = torch.rand(2, 48, 64, 3)
    origins, directions = pixel_rays(cameras[0], torch.tensor([pixel]))
    depth = torch.tensor([(-1.0 if negative else 1.0) * 10.0**depth_exponent], requires_grad=True)
    warp = warp_to_views(origins, directions, depth, torch.ones(1, dtype=torch.long), images, cameras, INTRINSICS.expand(2, 4))
    assert finite(warp.colors)
    projection = project_to_camera(unproject_along_rays(origins, directions, depth.detach()), cameras[1], INTRINSICS)
    assert finite(projection.pixels)
    if bool(warp.valid):
        assert bool(projection.in_front) and 0.0 <= float(projection.pixels[0, 0]) <= 64 and 0.0 <= float(projection.pixels[0, 1]) <= 48
    warp.colors.sum().backward()
    assert finite(depth.grad)


@FAST
@given(log_scale=magnitudes)
def test_pseudo_depth_selection_works_at_every_scene_scale(log_scale):
    """The same two-view scene scaled by s: the right scale wins at every s (no absolute epsilon bites)."""
    s = 10.0**log_scale
    cameras = torch.stack([camera(), camera(x=1.0)])
    images = torch.stack([render_plane(c) for c in cameras])  # images do not change with the scale
    scaled = cameras.clone()
    scaled[:, :, 3] *= s
    rows, cols = torch.meshgrid(torch.arange(16, 32) + 0.5, torch.arange(20, 44) + 0.5, indexing="ij")
    origins, directions = pixel_rays(camera(x=0.3), torch.stack([cols.flatten(), rows.flatten()], -1))
    true_depth = plane_depth(origins, directions)
    colors = warp_to_views(origins, directions, true_depth, torch.zeros(len(origins), dtype=torch.long), images,
                           cameras, INTRINSICS.expand(2, 4)).colors
    depths = torch.stack([true_depth * 1.2, true_depth, true_depth * 0.8]) * s
    chosen = pseudo_ground_truth_scale(origins * s, directions, depths, colors, ReferenceViews(images, scaled, INTRINSICS.expand(2, 4)), 0.5)
    assert (chosen == 1).float().mean() > 0.9


# ---- camera layouts: baseline ~0 and very wide ------------------------------------------------------------
@pytest.mark.parametrize("baseline", [0.0, 1e-9, 1e-6])
def test_nearly_identical_training_cameras(baseline):
    cameras = torch.stack([camera(), camera(x=baseline)])
    centers = cameras[:, :3, 3]
    assert nearest_other_view(centers, centers, own_view=torch.arange(2)).tolist() == [1, 0]
    # A ray from each camera's own centre warps into the other camera, however small the (non-zero)
    # baseline: "the camera it starts in" is relative to the baseline. With no baseline at all both cameras
    # are the one the ray starts in, so there is no other view (-1) rather than a division by 0.
    nearest = nearest_other_view(centers.clone(), centers, same_position_fraction=1e-3)
    assert nearest.tolist() == ([-1, -1] if baseline == 0.0 else [1, 0])
    layout = classify_camera_layout(cameras)
    assert layout.scene_type == "forward-facing" and finite(layout.focus)
    poses = spiral_poses(cameras, focus_depth=3.0, num_poses=8, rotations=1.0, radius_scale=1.0, zrate=0.5)
    assert finite(poses)
    # Triangulating with (almost) no baseline: matches at and near the same pixel give points at infinity
    # or at no angle; the filters drop them all without NaN leaking out or an exception.
    keypoints = [torch.tensor([[32.0, 24.0], [10.0, 10.0]]), torch.tensor([[32.0, 24.0], [10.5, 10.0]])]
    sparse = triangulate_tracks([[(0, 0), (1, 0)], [(0, 1), (1, 1)]], keypoints, cameras.double(),
                                INTRINSICS.expand(2, 4).double(), TriangulationOptions())
    assert sparse.num_points == 0


def test_very_wide_baselines():
    cameras = torch.stack([camera(z=3.0), camera(x=3.0, yaw=math.pi / 2), camera(z=-3.0, yaw=math.pi)])
    layout = classify_camera_layout(cameras)
    assert layout.scene_type == "360" and finite(layout.focus)
    poses = spiral_poses(cameras, focus_depth=3.0, num_poses=8, rotations=1.0, radius_scale=1.0, zrate=0.5)
    assert finite(poses)


# ---- model level -----------------------------------------------------------------------------------------
def tiny_model(manager, **overrides):
    from frugalnerf_ns.model.frugalnerf import FrugalNeRFModelConfig

    fields = dict(
        initial_voxels=16**3, final_voxels=16**3, upsample_at=(), alpha_mask_at=(), density_components=(4, 2, 2),
        appearance_components=(8, 2, 2), mlp_hidden_dim=16, background="white", density_activation="softplus",
    )
    fields.update(overrides)
    dataset = manager.train_dataset
    torch.manual_seed(0)
    model = FrugalNeRFModelConfig(**fields).setup(scene_box=dataset.scene_box, num_train_data=len(dataset), metadata=dataset.metadata)
    model.set_reference_views(manager.warp_images, manager.warp_camera_to_worlds, manager.warp_intrinsics)  # as the pipeline does
    return model


def total_loss(model, bundle, batch):
    outputs = model(bundle)
    metrics = model.get_metrics_dict(outputs, batch)
    loss_dict = model.get_loss_dict(outputs, batch, metrics)
    return loss_dict, sum(loss_dict.values())


@pytest.mark.parametrize("dtype", [torch.bfloat16, torch.float16])
def test_a_training_step_under_cpu_autocast_is_finite(procedural_scene, tmp_path, dtype):
    from tests.helpers import manager_for

    manager = manager_for(procedural_scene, sparse_cache_dir=tmp_path)
    model = tiny_model(manager)
    model.train()
    bundle, batch = manager.next_train(0)
    with torch.autocast("cpu", dtype=dtype):
        loss_dict, loss = total_loss(model, bundle, batch)
    assert all(bool(torch.isfinite(v)) for v in loss_dict.values()), loss_dict
    loss.backward()
    grads = [p.grad for p in model.parameters() if p.grad is not None]
    assert grads and all(finite(g) for g in grads)
    with torch.no_grad(), torch.autocast("cpu", dtype=dtype):
        model.eval()
        outputs = model.get_outputs_for_camera(manager.train_dataset.cameras[0:1])
    assert finite(outputs["rgb"], outputs["depth"])


def test_one_training_view_trains_without_geometric_adaptation_and_says_why(procedural_scene, tmp_path, capsys):
    from tests.helpers import manager_for

    scene = tmp_path / "one-view"
    shutil.copytree(procedural_scene, scene)
    meta = json.loads((scene / "transforms.json").read_text())
    meta["train_filenames"] = meta["train_filenames"][:1]
    (scene / "transforms.json").write_text(json.dumps(meta))
    manager = manager_for(scene, sparse_cache_dir=tmp_path)
    printed = " ".join(capsys.readouterr().out.split())  # rich wraps long lines
    assert "one training view" in printed and "novel-view rays only" in printed
    model = tiny_model(manager)
    model.train()
    bundle, batch = manager.next_train(0)
    outputs = model(bundle)
    metrics = model.get_metrics_dict(outputs, batch)
    loss_dict = model.get_loss_dict(outputs, batch, metrics)
    loss = sum(loss_dict.values())
    assert all(bool(torch.isfinite(v)) for v in loss_dict.values())
    # Training rays are all left out of L_geo; novel rays still warp into the one view.
    chosen = metrics[ADAPTATION_METRIC].chosen_scale
    assert (chosen[batch.train] == -1).all()
    assert float(metrics["geo_left_out_fraction"]) >= batch.num_train / len(chosen)
    loss.backward()
    assert all(finite(p.grad) for p in model.parameters() if p.grad is not None)


@pytest.mark.slow
def test_ten_thousand_iterations_do_not_drift_to_nan(procedural_scene, tmp_path):
    from tests.helpers import manager_for

    manager = manager_for(procedural_scene, sparse_cache_dir=tmp_path, train_num_rays_per_batch=72,
                          num_novel_rays_per_batch=16, num_sparse_rays_per_batch=0)
    model = tiny_model(manager, initial_voxels=12**3, final_voxels=12**3, appearance_components=(4, 2, 2),
                       lower_scale_color_weight=1.0)
    model.train()
    optimizer = torch.optim.Adam(model.parameters(), lr=0.02, betas=(0.9, 0.99))
    history = []
    for step in range(10_000):
        bundle, batch = manager.next_train(step)
        loss_dict, loss = total_loss(model, bundle, batch)
        assert bool(torch.isfinite(loss)), (step, {k: float(v) for k, v in loss_dict.items()})
        history.append(float(loss_dict["rgb_loss"]))
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    assert all(finite(p) for p in model.parameters())
    # It learned and stayed learned: the colour loss of the last 500 steps is below that of the first 100
    # and no worse than around step 2000 (no slow divergence). Batches of 72 rays are noisy: averages.
    first, middle, last = (sum(history[a:b]) / (b - a) for a, b in ((0, 100), (1750, 2250), (9500, 10_000)))
    assert last < 0.8 * first and last <= 1.1 * middle, (first, middle, last)
