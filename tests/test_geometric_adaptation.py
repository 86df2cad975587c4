"""L_geo on a real FrugalDataManager batch: the model's losses, statistics and the training plot."""

import dataclasses
import json
from contextlib import contextmanager

import pytest
import torch

from frugalnerf_ns.model.geometric_adaptation import (
    LEFT_OUT_COLOR,
    SCALE_CHOICE_COLORS,
    AdaptationRays,
    ReferenceViews,
    ScaleFractionHistory,
    cross_scale_geometric_adaptation,
    pseudo_ground_truth_scale,
    scale_choice_colors,
    scale_statistics,
)
from frugalnerf_ns.model.frugalnerf import FrugalNeRFModelConfig
from frugalnerf_ns.geometry.novel_views import nearest_other_view
from frugalnerf_ns.geometry.reprojection import unproject_along_rays
from tests.helpers import INTRINSICS, camera, manager_for, patch_pixels, pixel_rays, plane_depth, render_plane, texture


@pytest.fixture(scope="module")
def model_and_batch(procedural_scene, tmp_path_factory):
    # The procedural scene triangulates only a few points, on its backdrop outside the scene box: let them
    # all count, so the batch has sparse rays.
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr("frugalnerf_ns.data.training_points.points_inside_box", lambda sparse, aabb: sparse)
        manager = manager_for(
            procedural_scene, train_num_rays_per_batch=225, num_novel_rays_per_batch=64, patch_size=5,
            min_sparse_points=1, sparse_cache_dir=tmp_path_factory.mktemp("sparse"),
        )
    config = FrugalNeRFModelConfig(
        initial_voxels=24**3, final_voxels=24**3, upsample_at=(), alpha_mask_at=(),
        density_components=(4, 2, 2), appearance_components=(8, 2, 2), mlp_hidden_dim=16, background="white",
        density_activation="softplus", depth_smoothness_weight=1.0, reprojection_threshold=1.0,
    )
    torch.manual_seed(0)
    model = config.setup(scene_box=manager.train_dataset.scene_box, num_train_data=len(manager.train_dataset), metadata={})
    model.set_reference_views(manager.warp_images, manager.warp_camera_to_worlds, manager.warp_intrinsics)
    model.train()
    bundle, batch = manager.next_train(0)
    return model, bundle, batch


def test_losses_include_geometric_adaptation_and_smoothness_with_gradients(model_and_batch):
    model, bundle, batch = model_and_batch
    outputs = model(bundle)
    metrics = model.get_metrics_dict(outputs, batch)
    loss_dict = model.get_loss_dict(outputs, batch, metrics)
    assert {"rgb_loss", "geo_loss", "depth_smoothness", "sparse_depth"} <= set(loss_dict)
    for value in loss_dict.values():
        assert torch.isfinite(value)
    assert float(loss_dict["geo_loss"]) > 0
    fractions = [float(metrics[f"geo_scale{s}_fraction"]) for s in range(3)] + [float(metrics["geo_left_out_fraction"])]
    assert sum(fractions) == pytest.approx(1.0)
    # Only the training rays enter the colour loss: the batch's image has exactly that many rows.
    assert batch.image.shape[0] == batch.num_train < outputs["rgb"].shape[0]
    model.zero_grad()
    loss_dict["geo_loss"].backward()
    grads = [p.grad for p in model.field.grid_parameters() if p.grad is not None]
    assert grads and any(float(g.abs().sum()) > 0 for g in grads)


def test_sparse_depth_loss_reads_the_trailing_rays_at_every_scale(model_and_batch):
    from frugalnerf_ns.model.losses import inverse_depth_loss

    model, bundle, batch = model_and_batch
    outputs = model(bundle)
    loss_dict = model.get_loss_dict(outputs, batch, model.get_metrics_dict(outputs, batch))
    n = batch.sparse_depth.shape[0]
    assert n > 0 and outputs["rgb"].shape[0] == batch.num_train + batch.num_novel + n
    expected = sum(inverse_depth_loss(outputs[k][-n:, 0], batch.sparse_depth) for k in ("depth", "depth_scale1", "depth_scale2"))
    assert float(loss_dict["sparse_depth"]) == pytest.approx(model.config.sparse_depth_weight * float(expected), rel=1e-5)
    model.zero_grad()
    loss_dict["sparse_depth"].backward()
    grads = [p.grad for p in model.field.grid_parameters() if p.grad is not None]
    assert grads and all(torch.isfinite(g).all() for g in grads) and any(float(g.abs().sum()) > 0 for g in grads)
    from frugalnerf_ns.model.losses import relative_disparity_loss

    model.config.sparse_depth_error = "relative"
    try:
        outputs = model(bundle)
        loss_dict = model.get_loss_dict(outputs, batch, model.get_metrics_dict(outputs, batch))
        expected = sum(relative_disparity_loss(outputs[k][-n:, 0], batch.sparse_depth)
                       for k in ("depth", "depth_scale1", "depth_scale2"))
        assert float(loss_dict["sparse_depth"]) == pytest.approx(model.config.sparse_depth_weight * float(expected), rel=1e-5)
    finally:
        model.config.sparse_depth_error = "inverse"
    model.config.sparse_depth_weight = 0.0
    try:
        outputs = model(bundle)
        assert "sparse_depth" not in model.get_loss_dict(outputs, batch, model.get_metrics_dict(outputs, batch))
    finally:
        model.config.sparse_depth_weight = 0.5


def _seeded_step(model, ray_bundle, batch):
    """One training step's render, losses and gradients, with the same jitter every call."""
    torch.manual_seed(3)
    outputs = model(ray_bundle)
    loss_dict = model.get_loss_dict(outputs, batch, model.get_metrics_dict(outputs, batch))
    model.zero_grad()
    sum(loss_dict.values()).backward()
    grads = {name: p.grad.clone() for name, p in model.named_parameters() if p.grad is not None}
    return outputs["step"], {k: float(v.detach()) for k, v in loss_dict.items()}, grads


def test_colours_no_loss_reads_are_not_shaded_and_no_loss_or_gradient_changes(model_and_batch):
    import copy

    from frugalnerf_ns.batch import RAY_GROUP

    model, bundle, batch = model_and_batch

    def step(ray_bundle):
        return _seeded_step(model, ray_bundle, batch)

    assert RAY_GROUP in bundle.metadata
    ungrouped = copy.copy(bundle)
    ungrouped.metadata = {k: v for k, v in bundle.metadata.items() if k != RAY_GROUP}
    # The untrained field's weights are mostly below the shading threshold: shade every sample with weight.
    threshold, model.config.weight_threshold = model.config.weight_threshold, 0.0
    color = model.field.color
    shaded_with_gradient = []

    def counting_color(positions, directions, scale=0):
        if torch.is_grad_enabled():
            shaded_with_gradient.append(positions.shape[0])
        return color(positions, directions, scale)

    try:
        model.field.color = counting_color
        skipped, skipped_losses, skipped_grads = step(bundle)
        with_gradient, shaded_with_gradient = sum(shaded_with_gradient), []
        every, every_losses, every_grads = step(ungrouped)
    finally:
        model.config.weight_threshold = threshold
        del model.field.color
    # Only the training rays' colours carry gradient (the novel rays' full-scale colour is read detached).
    assert with_gradient == sum(int(s.shaded[batch.train].sum()) for s in skipped.scales)
    assert sum(shaded_with_gradient) == sum(int(s.shaded.sum()) for s in every.scales) > with_gradient
    novel, sparse = batch.novel, batch.sparse
    assert sparse.stop > sparse.start and novel.stop > novel.start
    for scale, (fast, full) in enumerate(zip(skipped.scales, every.scales)):
        # Without the groups the novel and sparse-depth rays are shaded at every scale (the test can fail);
        # with them the novel rays only at the full scale, the sparse-depth rays at none.
        assert full.shaded[novel].any() and full.shaded[sparse].any()
        assert fast.shaded[novel].any() == (scale == 0)
        assert not fast.shaded[sparse].any()
        assert torch.equal(fast.shaded[batch.train], full.shaded[batch.train])
        assert torch.equal(fast.weights, full.weights)
    assert set(skipped_losses) == set(every_losses) >= {"rgb_loss", "geo_loss", "sparse_depth", "depth_smoothness"}
    for name, value in every_losses.items():
        assert skipped_losses[name] == pytest.approx(value, rel=1e-6, abs=1e-9), name
    assert set(skipped_grads) == set(every_grads)
    for name, grad in every_grads.items():
        scale = float(grad.abs().max()) or 1.0
        assert torch.allclose(skipped_grads[name], grad, rtol=1e-4, atol=1e-5 * scale), name


def test_density_read_from_shared_nodes_gives_the_planes_losses_and_gradients(model_and_batch, monkeypatch):
    """The nodes and the planes read by the fused kernels (density and colour) against the planes read by torch."""
    from frugalnerf_ns.field import fused_training_reads

    model, bundle, batch = model_and_batch
    field = model.field
    node_sums, fused_reads = [], []
    fused_read = fused_training_reads.StepReads.read
    monkeypatch.setattr(fused_training_reads.StepReads, "read",
                        lambda self, grid, *a: fused_reads.append(grid) or fused_read(self, grid, *a))
    assert not field.fused_reads_pay()  # a small grid reads the nodes (or the planes with torch) ...
    monkeypatch.setattr("frugalnerf_ns.field.radiance_field.FUSED_READ_MIN_ENTRIES", 0)  # ... here, the kernels too
    node_sum = field.density_grid.node_sum

    def counting_node_sum():
        node_sums.append(1)
        return node_sum()

    def step(read, kernels="torch"):
        model.config.training_density_read, model.config.kernels = read, kernels
        return _seeded_step(model, bundle, batch)

    try:
        field.density_grid.node_sum = counting_node_sum
        nodes, node_losses, node_grads = step("nodes")
        assert len(node_sums) == 1  # one node tensor for the step's three scales
        planes, plane_losses, plane_grads = step("planes")  # the torch reads of the planes: the reference
        assert len(node_sums) == 1
        assert not fused_reads
        # The planes read by the kernels: asked for, and in place of the nodes where the kernels compile.
        fast_reads = [step("planes", "warp"), step("nodes", "warp")] if fused_kernels_compile() else []
        density_reads = [grid for grid in fused_reads if grid is field.density_grid]
        assert len(density_reads) == (6 if fast_reads else 0) and len(node_sums) == 1  # every scale's read, no nodes
        assert (len(fused_reads) > 9) == bool(fast_reads)  # and each scale's colour
    finally:
        model.config.training_density_read, model.config.kernels = "nodes", "auto"
        del field.density_grid.node_sum
    assert field._shared_nodes is None and field._step_reads is None  # nothing kept after the step
    for (fast, fast_losses, fast_grads) in [(nodes, node_losses, node_grads), *fast_reads]:
        for ours, reference in zip(fast.scales, planes.scales):
            assert (reference.densities > 0).any()
            assert torch.allclose(ours.densities, reference.densities, rtol=1e-5, atol=1e-6)
            assert torch.allclose(ours.weights, reference.weights, rtol=1e-4, atol=1e-6)
        for name, value in plane_losses.items():
            assert fast_losses[name] == pytest.approx(value, rel=1e-5, abs=1e-8), name
        density_names = {name for name in plane_grads if "density_grid" in name}
        assert len(density_names) == 6 and set(fast_grads) == set(plane_grads)
        for name, grad in plane_grads.items():
            scale = float(grad.abs().max()) or 1.0
            assert torch.allclose(fast_grads[name], grad, rtol=1e-4, atol=1e-5 * scale), name


def fused_kernels_compile() -> bool:
    """Warp is installed here (a dependency; where it is, its kernels must compile: an error fails the test)."""
    try:
        import warp  # noqa: F401
    except ImportError:
        return False
    return True


def test_geo_loss_off_when_its_weight_is_zero(model_and_batch):
    model, bundle, batch = model_and_batch
    model.config.geo_weight = 0.0
    try:
        outputs = model(bundle)
        loss_dict = model.get_loss_dict(outputs, batch, model.get_metrics_dict(outputs, batch))
        assert "geo_loss" not in loss_dict
    finally:
        model.config.geo_weight = 0.01


@contextmanager
def loss_along_the_schedule(model_and_batch, term):
    """A function of the step giving one loss term, the batch at that step of a 10-step run's schedule; the
    batch's step and the model's schedule are set back afterwards."""
    from types import SimpleNamespace

    from nerfstudio.engine.callbacks import TrainingCallbackAttributes

    model, bundle, batch = model_and_batch
    trainer = SimpleNamespace(config=SimpleNamespace(max_num_iterations=10, steps_per_save=1000), base_dir=".")
    attrs = TrainingCallbackAttributes(optimizers=None, grad_scaler=None, pipeline=None, trainer=trainer)
    model.get_training_callbacks(attrs)

    def set_step(step):
        batch.step = step

    def loss_at(step):
        set_step(step)
        torch.manual_seed(0)
        outputs = model(bundle)
        return float(model.get_loss_dict(outputs, batch, model.get_metrics_dict(outputs, batch))[term])

    try:
        yield loss_at
    finally:
        batch.step, model.schedule_length = None, None


def test_lambda_sd_falls_with_the_other_regularisers(model_and_batch):
    model = model_and_batch[0]
    decay = model.config.loss_weight_decay
    with loss_along_the_schedule(model_and_batch, "sparse_depth") as sparse_loss_at:
        start = sparse_loss_at(0)
        assert start > 0
        assert sparse_loss_at(10) == pytest.approx(decay * start, rel=1e-4)
        assert model.schedule(10).loss == pytest.approx(decay)


def test_geo_novel_weight_weighs_the_novel_rays_term_alone(model_and_batch):
    model, bundle, batch = model_and_batch

    def geo_loss(weight, novel_weight):
        model.config.geo_weight, model.config.geo_novel_weight = weight, novel_weight
        torch.manual_seed(0)
        outputs = model(bundle)
        return model.get_loss_dict(outputs, batch, model.get_metrics_dict(outputs, batch)).get("geo_loss")

    try:
        both = float(geo_loss(1.0, None))
        train_only = float(geo_loss(1.0, 0.0))
        novel_only = geo_loss(0.0, 1.0)  # the adaptation still runs with lambda_geo 0 on the training patches
        assert novel_only is not None and float(novel_only) > 0 and train_only > 0
        assert both == pytest.approx(train_only + float(novel_only), rel=1e-4)
        assert float(geo_loss(1.0, 3.0)) == pytest.approx(train_only + 3 * float(novel_only), rel=1e-4)
        assert geo_loss(0.0, 0.0) is None
    finally:
        model.config.geo_weight, model.config.geo_novel_weight = 0.01, None


def test_the_training_patches_photometric_term_reads_the_training_rows_and_sends_gradients(model_and_batch):
    from frugalnerf_ns.model.geometric_adaptation import photometric_consistency

    model, bundle, batch = model_and_batch
    views = model.reference_views
    try:
        model.config.photometric_weight = 0.5
        model.config.photometric_max_error = 1.0  # an untrained field: keep every patch inside the other image
        rows = batch.train
        torch.manual_seed(0)
        outputs = model(bundle)
        render = outputs["step"]
        # An untrained field's depth lies just in front of its camera, outside the other views: read it at the
        # distance to the scene's centre instead (the same value, the field's gradient).
        depth = render.metric_depths[0]
        render.metric_depths[0] = depth - depth.detach() + render.origins.detach().norm(dim=-1)
        term = model.get_loss_dict(outputs, batch, model.get_metrics_dict(outputs, batch))["photometric"]
        indices = batch.indices.to(render.origins.device)
        expected = photometric_consistency(
            render.origins[rows], render.directions[rows], render.metric_depths[0][rows], indices[:, 0].long(),
            indices[:, [2, 1]].float() + 0.5, batch.nearest_view[rows], batch.patch_size,
            views, 3, 1.0)
        assert float(term) == pytest.approx(0.5 * float(expected), rel=1e-5)
        assert float(term) > 0
        model.zero_grad()
        term.backward()
        grads = [p.grad for p in model.field.grid_parameters() if p.grad is not None]
        assert grads and all(torch.isfinite(g).all() for g in grads) and any(float(g.abs().sum()) > 0 for g in grads)
    finally:
        model.config.photometric_weight, model.config.photometric_max_error = 0.0, 0.2


def test_rays_without_another_view_are_left_out():
    # One camera at the origin looking down -z; rays whose nearest view is -1 (a single training view).
    images = torch.rand(1, 8, 8, 3)
    c2w = torch.eye(4)[:3][None]
    intrinsics = torch.tensor([[8.0, 8.0, 4.0, 4.0]])
    origins = torch.zeros(4, 3)
    directions = torch.tensor([0.0, 0.0, -1.0]).expand(4, 3)
    depths = torch.full((3, 4), 2.0, requires_grad=True)
    rays = AdaptationRays(origins, directions, depths, depths, torch.rand(4, 3), torch.full((4,), -1), 4, 2)
    result = cross_scale_geometric_adaptation(rays, ReferenceViews(images, c2w, intrinsics), 0.5)
    assert (result.chosen_scale == -1).all()
    assert float(result.loss_train) == 0.0 and float(result.loss_novel) == 0.0
    assert scale_statistics(result.chosen_scale, 3)["geo_left_out_fraction"] == 1.0


def test_scale_history_writes_json_and_png(tmp_path):
    history = ScaleFractionHistory()
    for step in range(5):
        history.record(step, {"geo_scale0_fraction": 0.2, "geo_scale1_fraction": 0.3, "geo_scale2_fraction": 0.4,
                              "geo_left_out_fraction": 0.1})
    png = history.write(tmp_path)
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    data = json.loads((tmp_path / "geometric_adaptation.json").read_text())
    assert data["steps"] == list(range(5)) and data["stats"][0]["geo_scale2_fraction"] == 0.4


def test_viewer_rays_warp_into_the_nearest_camera_they_do_not_start_in():
    c2w = torch.stack([camera(), camera(x=1.0), camera(x=5.0)])
    origins = torch.tensor([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.3, 0.0, 0.0], [4.0, 0.0, 0.0], [1.0 + 1e-5, 0.0, 0.0]])
    assert nearest_other_view(origins, c2w[:, :3, 3], same_position_fraction=1e-3).tolist() == [1, 0, 0, 2, 0]
    # A single training view: a ray from it has nowhere to warp; a ray from elsewhere warps into it.
    assert nearest_other_view(origins[:2], c2w[:1, :3, 3], same_position_fraction=1e-3).tolist() == [-1, 0]


@pytest.mark.parametrize("true_scale", [0, 1, 2])
def test_pseudo_gt_scale_map_picks_the_scale_whose_depth_explains_the_nearest_view(true_scale):
    cameras = torch.stack([camera(), camera(x=1.0)])
    images = torch.stack([render_plane(c) for c in cameras])
    viewer = camera(x=0.3)  # a novel camera: nearest training view is camera 0
    pixels = patch_pixels(top=14, left=20, k=16)
    origins, directions = pixel_rays(viewer, pixels)
    true_depth = plane_depth(origins, directions)
    factors = torch.tensor([1.15, 0.85, 1.3])
    factors[true_scale] = 1.0
    depths = factors[:, None] * true_depth[None]
    colors = texture(unproject_along_rays(origins, directions, true_depth))
    chosen = pseudo_ground_truth_scale(
        origins, directions, depths, colors, ReferenceViews(images, cameras, INTRINSICS.expand(2, 4)), threshold=0.5
    )
    assert chosen.shape == (len(pixels),)
    assert (chosen == true_scale).float().mean() > 0.9
    # With a threshold below every error, every ray is left out.
    wrong = pseudo_ground_truth_scale(
        origins, directions, depths * 1.5, colors, ReferenceViews(images, cameras, INTRINSICS.expand(2, 4)), threshold=1e-4
    )
    assert (wrong == -1).all()


def test_scale_choice_colors_use_one_colour_per_scale_and_grey_for_left_out():
    colors = scale_choice_colors(torch.tensor([[-1, 0], [1, 2]]))
    assert colors.shape == (2, 2, 3)
    assert torch.allclose(colors[0, 0], torch.tensor(LEFT_OUT_COLOR))
    for scale, pixel in ((0, colors[0, 1]), (1, colors[1, 0]), (2, colors[1, 1])):
        assert torch.allclose(pixel, torch.tensor(SCALE_CHOICE_COLORS[scale]))


def _variant(model, metadata, **fields):
    """``model``'s set-up with other settings or scene metadata, warping into the same training views."""
    import dataclasses

    config = dataclasses.replace(model.config, **fields)
    torch.manual_seed(0)
    variant = config.setup(scene_box=model.scene_box, num_train_data=model.num_train_data, metadata=metadata)
    variant.reference_views = model.reference_views
    variant.train()
    return variant


def test_a_room_beyond_the_box_drops_the_warp_losses_and_weighs_sparse_depth_relatively(model_and_batch):
    from frugalnerf_ns.model.losses import inverse_depth_loss, relative_disparity_loss

    model, bundle, batch = model_and_batch
    n = batch.sparse_depth.shape[0]
    scales = ("depth", "depth_scale1", "depth_scale2")

    def losses(variant):
        torch.manual_seed(1)
        outputs = variant(bundle)
        return outputs, variant.get_loss_dict(outputs, batch, variant.get_metrics_dict(outputs, batch))

    settings = dict(room_warp_losses=False, sparse_depth_error="auto", photometric_weight=0.1)
    # No room (LLFF, DTU, Blender): the settings change nothing; the warp losses act, L_sd is Eq. 11's.
    outputs, terms = losses(_variant(model, {}, **settings))
    assert {"geo_loss", "photometric"} <= set(terms) and float(terms["geo_loss"]) > 0
    expected = sum(inverse_depth_loss(outputs[k][-n:, 0], batch.sparse_depth) for k in scales)
    assert float(terms["sparse_depth"]) == pytest.approx(model.config.sparse_depth_weight * float(expected), rel=1e-5)
    # An object with the room beyond its box: no L_geo, no photometric term, L_sd relative to each point's depth.
    room = _variant(model, {"far_background": True}, **settings)
    assert room.has_room
    outputs, terms = losses(room)
    assert "geo_loss" not in terms and "photometric" not in terms and "geo_scale0_fraction" not in terms
    expected = sum(relative_disparity_loss(outputs[k][-n:, 0], batch.sparse_depth) for k in scales)
    assert float(terms["sparse_depth"]) == pytest.approx(model.config.sparse_depth_weight * float(expected), rel=1e-5)
    # The paper's defaults keep both in such a scene.
    _, terms = losses(_variant(model, {"far_background": True}, photometric_weight=0.1))
    assert {"geo_loss", "photometric"} <= set(terms) and float(terms["geo_loss"]) > 0


def test_the_warp_regime_follows_where_the_training_views_points_lie():
    """``room_warp_losses`` "auto": a plain fit where most triangulated points lie beyond the box, adaptation where
    they stand in it or are too few to say; "on"/"off" (and a saved bool) force it; no room, always the warps."""
    from frugalnerf_ns.model.objective import PLAIN_FIT_MIN_POINTS, geo_weights, warp_regime

    auto = FrugalNeRFModelConfig(geo_weight=0.1, geo_novel_weight=0.01)
    assert auto.room_warp_losses == "auto"
    # The measured splits: the juice box's wide (82 of 111 beyond) and 40-degree (54 of 75) splits, the bird (0 of 22).
    assert not warp_regime(auto, True, (82, 111)).warps and not warp_regime(auto, True, (54, 75)).warps
    assert warp_regime(auto, True, (0, 22)).warps
    assert "82 of the 111" in warp_regime(auto, True, (82, 111)).reason
    # The boundary: half the points beyond is a plain fit, one fewer is not.
    assert not warp_regime(auto, True, (10, 20)).warps and warp_regime(auto, True, (9, 20)).warps
    # Too few points, or none counted (sparse depth off): the warps act.
    few = PLAIN_FIT_MIN_POINTS - 1
    assert warp_regime(auto, True, (few, few)).warps and warp_regime(auto, True, None).warps
    # No room (NDC, DTU, Blender): the warps act whatever the option and the points say.
    for mode in ("auto", "off", False):
        assert warp_regime(dataclasses.replace(auto, room_warp_losses=mode), False, (100, 100)) == (True, "")
    for mode, warps in (("on", True), (True, True), ("off", False), (False, False)):
        assert warp_regime(dataclasses.replace(auto, room_warp_losses=mode), True, (100, 100)).warps is warps
        assert warp_regime(dataclasses.replace(auto, room_warp_losses=mode), True, (0, 100)).warps is warps
    assert geo_weights(auto, True) == (0.1, 0.01) and geo_weights(auto, False) == (0.0, 0.0)


def test_space_no_photo_sees_is_carved_where_the_split_is_fitted_plainly():
    from frugalnerf_ns.model.objective import WarpRegime, carve_unseen_space

    auto = FrugalNeRFModelConfig()
    plain, adapted = WarpRegime(False, ""), WarpRegime(True, "")
    assert carve_unseen_space(auto, False, plain) and not carve_unseen_space(auto, False, adapted)
    assert not carve_unseen_space(auto, True, plain)  # NDC: the box is the training frusta
    on, off = dataclasses.replace(auto, carve_unseen="on"), dataclasses.replace(auto, carve_unseen="off")
    assert carve_unseen_space(on, False, adapted) and not carve_unseen_space(off, False, plain)


def test_a_room_whose_points_lie_beyond_the_box_trains_without_the_warp_losses(model_and_batch):
    """Through the model: the datamanager's count in the scene metadata decides."""
    model, bundle, batch = model_and_batch

    def terms(variant):
        torch.manual_seed(1)
        outputs = variant(bundle)
        return variant.get_loss_dict(outputs, batch, variant.get_metrics_dict(outputs, batch))

    settings = dict(photometric_weight=0.1)
    plain = _variant(model, {"far_background": True, "frugalnerf_scene": {"points_beyond_box": [82, 111]}}, **settings)
    assert not plain.warp_regime.warps
    found = terms(plain)
    assert "geo_loss" not in found and "photometric" not in found and "sparse_depth" in found
    kept = _variant(model, {"far_background": True, "frugalnerf_scene": {"points_beyond_box": [0, 22]}}, **settings)
    assert kept.warp_regime.warps
    found = terms(kept)
    assert {"geo_loss", "photometric"} <= set(found) and float(found["geo_loss"]) > 0
    # The plain fit's alpha mask empties what no training camera sees; with the warps the mask is TensoRF's.
    assert kept.seen_by_training_views() is None
    seen = plain.seen_by_training_views()
    views = plain.reference_views
    centres = views.camera_to_worlds[:, :3, 3]
    forward = centres - 0.5 * views.camera_to_worlds[:, :3, 2]  # half a unit along each camera's viewing axis
    assert seen(forward).all() and not seen(centres + 0.5 * views.camera_to_worlds[:, :3, 2]).any()


def test_in_a_room_l_geo_compares_the_boxs_own_depths(model_and_batch):
    model, bundle, batch = model_and_batch
    box = _variant(model, {"far_background": True})
    torch.manual_seed(1)
    outputs = box(bundle)
    box_loss = box.get_loss_dict(outputs, batch, box.get_metrics_dict(outputs, batch))["geo_loss"]
    # The box's own depths (the paper's rendered depth): nothing beyond the box moves L_geo.
    outer = [p for p in box.outer_space.parameters() if p.requires_grad]
    grads = torch.autograd.grad(box_loss, outer, allow_unused=True)
    assert all(g is None or float(g.abs().max()) == 0.0 for g in grads)
