"""The training schedule of a FrugalNeRF model: what happens at given steps (TensoRF's grid upsampling and
alpha mask, FrugalNeRF's loss-weight decay, the record of the geometric adaptation's scale fractions) and the
grid optimiser that each resize recreates. The steps are fractions of the run's schedule length
(``--schedule-steps``), so a resumed or shortened run keeps the same curve."""

from __future__ import annotations

from pathlib import Path
from typing import Callable, List, NamedTuple, Optional, Protocol, Tuple

from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackAttributes, TrainingCallbackLocation
from nerfstudio.utils.rich_utils import CONSOLE
from torch import Tensor

from frugalnerf_ns.field.radiance_field import FrugalNeRFField
from frugalnerf_ns.model import losses
from frugalnerf_ns.model.config import FrugalNeRFSettings
from frugalnerf_ns.model.geometric_adaptation import ScaleFractionHistory


class ScheduledModel(Protocol):
    """What the schedule reads and sets on the model (FrugalNeRFModel; named by its parts, not its module, which
    imports this one)."""

    config: FrugalNeRFSettings
    field: FrugalNeRFField
    upsample_voxels: List[int]
    scale_history: ScaleFractionHistory

    def grid_resolution(self, num_voxels: int) -> Tuple[int, int, int]: ...

    def seen_by_training_views(self) -> Optional[Callable[[Tensor], Tensor]]: ...


class ScheduleFactors(NamedTuple):
    """The decaying loss weights' factors at one step (``losses.loss_weight_schedule``)."""

    loss: float = 1.0
    """Of the lower scales' colour, TV, occlusion, depth smoothness, sparse and monocular depth
    (loss_weight_decay)."""


def schedule_factors(config: FrugalNeRFSettings, step: Optional[int], length: Optional[int]) -> ScheduleFactors:
    """The factors at ``step`` of a run whose schedule is ``length`` steps, from the absolute step (a resumed run
    continues the same curve); all 1 where there is no schedule (no trainer) or no step."""
    if length is None or step is None:
        return ScheduleFactors()
    return ScheduleFactors(losses.loss_weight_schedule(step, length, config.loss_weight_decay))


def training_callbacks(model: ScheduledModel, training_callback_attributes: TrainingCallbackAttributes) -> List[TrainingCallback]:
    """What happens at given steps of training, in the order nerfstudio runs them: after a step, the grid
    upsampling, the alpha mask (and the box shrink the first time) and, at checkpoints, the plot of the geometric
    adaptation's scale fractions (and at the end). The loss weights' decay is no callback: the losses compute it
    from their batch's step (``schedule_factors``)."""
    length = schedule_length(training_callback_attributes)
    upsample_steps = steps_at(model.config.upsample_at, length)
    alpha_mask_steps = steps_at(model.config.alpha_mask_at, length)

    def upsample(step: int) -> None:
        # Fractions that round to the same step (a very short run) upsample once, to the later size.
        voxels = model.upsample_voxels[max(i for i, s in enumerate(upsample_steps) if s == step)]
        model.field.upsample(model.grid_resolution(voxels))
        _restart_grid_optimizer(training_callback_attributes)

    def update_alpha_mask(step: int) -> None:
        occupied_box = model.field.update_alpha_mask(
            model.config.step_ratio, model.config.distance_scale, model.config.alpha_mask_threshold,
            seen=model.seen_by_training_views(),
        )
        if step == alpha_mask_steps[0]:
            # Keep the voxel count while the box shrinks: the freed voxels refine the occupied region.
            voxels = int(model.field.density_grid.resolution.prod())
            model.field.shrink(occupied_box)
            model.field.upsample(model.grid_resolution(voxels))
            _restart_grid_optimizer(training_callback_attributes)

    def save_scale_fractions(step: int) -> None:
        # Written at every checkpoint too, so an interrupted run still has its plot.
        trainer = training_callback_attributes.trainer
        if trainer is not None and model.scale_history.steps and step % trainer.config.steps_per_save == 0:
            model.scale_history.write(Path(trainer.base_dir))

    def plot_scale_fractions(step: int) -> None:
        trainer = training_callback_attributes.trainer
        if trainer is not None and model.scale_history.steps:
            path = model.scale_history.write(Path(trainer.base_dir))
            CONSOLE.print(f"frugalnerf: pseudo-depth scale fractions over training plotted in {path}")

    return [
        TrainingCallback([TrainingCallbackLocation.AFTER_TRAIN_ITERATION], upsample, iters=tuple(sorted(set(upsample_steps)))),
        TrainingCallback(
            [TrainingCallbackLocation.AFTER_TRAIN_ITERATION], update_alpha_mask, iters=tuple(sorted(set(alpha_mask_steps)))
        ),
        TrainingCallback([TrainingCallbackLocation.AFTER_TRAIN_ITERATION], save_scale_fractions),
        TrainingCallback([TrainingCallbackLocation.AFTER_TRAIN], plot_scale_fractions),
    ]


def schedule_length(attributes: TrainingCallbackAttributes) -> Optional[int]:
    """Steps every schedule spans (upsampling, alpha mask, the decaying loss weights, the learning rates):
    FrugalTrainer resolves it once per run (``trainer.schedule_steps``: the run's iterations, or the
    checkpoint's when resuming); another trainer's run length; None without a trainer (no schedules)."""
    trainer = attributes.trainer
    if trainer is None:
        return None
    resolved = getattr(trainer, "schedule_steps", None)
    return int(resolved) if resolved else int(trainer.config.max_num_iterations)


def steps_at(fractions: Tuple[float, ...], length: Optional[int]) -> List[int]:
    """The steps at ``fractions`` of a schedule of ``length`` steps (one per fraction, inside the run)."""
    if not length:
        return []
    return [min(length - 1, max(1, round(f * length))) for f in fractions]


def _restart_grid_optimizer(attributes: TrainingCallbackAttributes) -> None:
    """Recreate the grid optimiser for the resized tensors (a fresh Adam, as the reference code); its lr restarts
    at its first value and decays again over the schedule's length (TensoRF's lr_upsample_reset)."""
    optimizers, pipeline = attributes.optimizers, attributes.pipeline
    if optimizers is None or pipeline is None:
        return
    config = optimizers.config["encodings"]
    params = pipeline.get_param_groups()["encodings"]
    optimizers.optimizers["encodings"] = config["optimizer"].setup(params=params)
    optimizers.parameters["encodings"] = params
    if config.get("scheduler"):
        scheduler = config["scheduler"].setup().get_scheduler(optimizer=optimizers.optimizers["encodings"], lr_init=config["optimizer"].lr)
        optimizers.schedulers["encodings"] = scheduler
