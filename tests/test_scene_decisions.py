"""What the datamanager and model decide from the scene at start-up, and that the CLI overrides win."""

import torch

from frugalnerf_ns.geometry.scene_analysis import grid_side_for_pixels
from tests.helpers import manager_for, model_for


def test_procedural_object_scene_is_detected_and_published_to_the_model(procedural_scene, tmp_path):
    manager = manager_for(procedural_scene, sparse_cache_dir=tmp_path)
    assert manager.scene_type == "object"  # cameras circling an object on a plain white background
    scene = manager.train_dataset.metadata["frugalnerf_scene"]
    height, width = manager.warp_images.shape[1:3]
    assert scene == {"scene_type": "object", "num_train_pixels": len(manager.warp_images) * height * width}
    model = model_for(manager, occlusion_weight=0.1)
    assert model.scene_type == "object" and model.occlusion_active


def test_scene_type_override_wins_and_drives_novel_rays_and_occlusion(procedural_scene, tmp_path):
    manager = manager_for(procedural_scene, scene_type="360", sparse_cache_dir=tmp_path)
    assert manager.scene_type == "360" and manager.novel_cameras is None
    _, batch = manager.next_train(0)
    assert batch.num_novel == 0
    model = model_for(manager, occlusion_weight=0.1)
    assert not model.occlusion_active  # occlusion is for object scenes only
    forward = manager_for(procedural_scene, scene_type="forward-facing", sparse_cache_dir=tmp_path)
    assert forward.novel_cameras is not None and not model_for(forward, occlusion_weight=0.1).occlusion_active


def test_auto_grid_sizes_the_final_grid_from_the_training_pixels(procedural_scene, tmp_path):
    manager = manager_for(procedural_scene, sparse_cache_dir=tmp_path)
    pixels = manager.train_dataset.metadata["frugalnerf_scene"]["num_train_pixels"]
    fixed = model_for(manager)
    assert fixed.final_voxels == 24**3 and fixed.upsample_voxels[-1] == 24**3
    auto = model_for(manager, auto_grid=True)
    assert auto.final_voxels == grid_side_for_pixels(pixels) ** 3 != 24**3
    assert auto.upsample_voxels[-1] == auto.final_voxels


def test_the_start_up_summary_names_each_decision_and_its_override(procedural_scene, tmp_path):
    # What FrugalPipeline prints when ns-train sets up (the trained_run fixture's real ns-train prints it too).
    from frugalnerf_ns.run.pipeline import scene_summary

    manager = manager_for(procedural_scene, scene_type="360", sparse_cache_dir=tmp_path)
    summary = scene_summary(manager, model_for(manager, auto_grid=True))
    assert summary.startswith("frugalnerf scene: 360 (set by --pipeline.datamanager.scene-type")
    assert "(auto: " in summary and "training pixels)" in summary
    assert "novel rays off (360 scene)" in summary
    detected = scene_summary(auto := manager_for(procedural_scene, sparse_cache_dir=tmp_path), model_for(auto))
    assert detected.startswith("frugalnerf scene: object (detected") and "--pipeline.model.auto-grid sizes it" in detected
    assert "space: bounded box" in detected
    # The photos' coverage, from the cameras: the procedural scene's 3 photos stand 40 degrees apart on an arc.
    photos = next(line for line in detected.splitlines() if line.startswith("  photos:"))
    assert photos.startswith("  photos: 3 photos over 80 degrees around the subject, up to 40 degrees between neighbours: fair")
    # An LLFF-layout split modelled in NDC (the layout's space) is called forward-facing only when it is one.
    ndc = {"focal": 100.0, "width": 64.0, "height": 48.0, "near": 1.0}
    in_ndc = model_for(auto)
    in_ndc.ndc = ndc
    assert "space: NDC (the data's near/far bounds), although the split is not forward-facing" in scene_summary(auto, in_ndc)
    # A box holding only the near part of the scene says what lies beyond it, and how to turn that off.
    from frugalnerf_ns.field.far_background import FarBackground

    with_far = model_for(auto)
    with_far.far_background = FarBackground((8, 16))
    assert "around the training cameras' focus; beyond it a learned far background (8x16 colours by direction, infinitely far; " \
        "--pipeline.model.far-background False" in scene_summary(auto, with_far)
    with_far.far_background = FarBackground((8, 16), torch.zeros(3), 7.5)
    assert "(8x16 colours by direction, on a sphere of radius 7.5, where the sparse points beyond the box lie; " \
        in scene_summary(auto, with_far)
    assert "far background" not in detected
    # With the room beyond the box the summary names the split's warp regime, from the points' count, and the override.
    from frugalnerf_ns.model.objective import warp_regime

    assert "geometric adaptation on" in scene_summary(auto, with_far)
    with_far.warp_regime = warp_regime(with_far.config, True, (82, 111))
    plain = scene_summary(auto, with_far)
    assert "geometric adaptation off, the photometric warps too (plain fit of the photos: 82 of the 111 points" in plain
    assert "--pipeline.model.room-warp-losses on keeps them" in plain
    assert "the alpha mask empties what no training camera sees (--pipeline.model.carve-unseen off keeps it)" in plain
    with_far.warp_regime = warp_regime(with_far.config, True, (0, 22))
    assert "geometric adaptation on (geometric adaptation: 0 of the 22 points the training views triangulate lie " \
        "beyond the box; --pipeline.model.room-warp-losses off: a plain fit)" in scene_summary(auto, with_far)
    assert "alpha mask empties" not in scene_summary(auto, with_far)
    forward = manager_for(procedural_scene, scene_type="forward-facing", sparse_cache_dir=tmp_path)
    forward_model = model_for(forward)
    forward_model.ndc = ndc
    assert "space: NDC (forward-facing, the data's near/far bounds)" in scene_summary(forward, forward_model)


def test_metric_box_is_fitted_to_what_the_training_views_see(procedural_scene, tmp_path):
    manager = manager_for(procedural_scene, sparse_cache_dir=tmp_path)
    original = manager.train_dataparser_outputs.scene_box.aabb
    fitted = manager.train_dataset.scene_box.aabb
    assert manager.fitted_box is not None and torch.equal(manager.fitted_box, original)
    assert (fitted[0] >= original[0]).all() and (fitted[1] <= original[1]).all()
    assert float((fitted[1] - fitted[0]).prod()) < 0.9 * float((original[1] - original[0]).prod())
    if manager.sparse is not None:  # every sparse point stays inside the fitted box
        assert ((manager.sparse.points >= fitted[0]) & (manager.sparse.points <= fitted[1])).all()
    model = model_for(manager)
    assert torch.equal(model.field.aabb, fitted)  # the model is built in the fitted box
    kept = manager_for(procedural_scene, sparse_cache_dir=tmp_path, fit_scene_box=False)
    assert kept.fitted_box is None and torch.equal(kept.train_dataset.scene_box.aabb, original)
