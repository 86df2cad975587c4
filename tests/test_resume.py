"""A run resumed from a checkpoint follows the same schedules as the uninterrupted run: compared at the
same step (loss weights, learning rates, grid upsampling, alpha-mask box)."""

import pytest

from frugalnerf_ns.model import losses, objective
from tests.training_helpers import preset_config, train

SCHEDULE = dict(
    pipeline__model__upsample_at=(2 / 12, 8 / 12),  # steps 2 and 8 of the 12-step run
    pipeline__model__alpha_mask_at=(3 / 12,),
    pipeline__datamanager__dataparser__center_method="focus",
    steps_per_save=5,
    save_only_latest_checkpoint=False,
)


def snapshot(trainer):
    model = trainer.pipeline.model
    return {
        "step": trainer.step,
        "loss_weight_factor": model.schedule(trainer.step).loss,
        "lr": {name: opt.param_groups[0]["lr"] for name, opt in trainer.optimizers.optimizers.items()},
        "resolution": model.field.density_grid.resolution.tolist(),
        "box": model.field.aabb.flatten().tolist(),
        "lower_scale_weight": objective.scale_color_weights(model.config, model.field.num_scales, model.schedule(trainer.step).loss)[1],
    }


def test_resumed_run_follows_the_uninterrupted_schedules(procedural_scene, tmp_path):
    full = train(preset_config("frugalnerf-tiny", procedural_scene, tmp_path / "full", max_num_iterations=12, **SCHEDULE))
    # nerfstudio resumes at the checkpoint's step + 1 and counts --max-num-iterations from there: 6 .. 11.
    resumed = train(preset_config(
        "frugalnerf-tiny", procedural_scene, tmp_path / "resumed", max_num_iterations=6,
        load_dir=full.checkpoint_dir, load_step=5, **SCHEDULE,
    ))
    a, b = snapshot(full), snapshot(resumed)
    assert a["step"] == b["step"] == 11
    # The resumed run (6 iterations) keeps the schedule length of the run it continues, from its checkpoint.
    assert full.schedule_steps == resumed.schedule_steps == 12
    assert resumed.optimizers.config["encodings"]["scheduler"].max_steps == 12
    # The decaying weights follow the schedule length (12 steps), not the steps of this run.
    assert a["loss_weight_factor"] == pytest.approx(losses.loss_weight_schedule(11, 12, 0.025))
    assert b["loss_weight_factor"] == pytest.approx(a["loss_weight_factor"])
    assert b["lower_scale_weight"] == pytest.approx(a["lower_scale_weight"])
    assert b["lr"] == pytest.approx(a["lr"])
    # Upsampled at step 8 (after the resume point) from the same box as the uninterrupted run.
    assert b["resolution"] == a["resolution"] and b["box"] == pytest.approx(a["box"])
    assert a["resolution"] != [30, 30, 30]
