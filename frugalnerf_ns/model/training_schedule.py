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
from torch.optim.lr_scheduler import LambdaLR

from frugalnerf_ns.field.radiance_field import FrugalNeRFField
from frugalnerf_ns.field.tensorial import OptimizerState
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
    """Of the lower scales' colour, TV, occlusion, depth smoothness and monocular depth (loss_weight_decay)."""
    geo: float = 1.0
    """Of lambda_geo (geo_weight_decay)."""
    sparse: float = 1.0
    """Of lambda_sd (sparse_depth_weight_decay, else loss_weight_decay)."""


def schedule_factors(config: FrugalNeRFSettings, step: Optional[int], length: Optional[int]) -> ScheduleFactors:
    """The factors at ``step`` of a run whose schedule is ``length`` steps, from the absolute step (a resumed run
    continues the same curve); all 1 where there is no schedule (no trainer) or no step."""
    if length is None or step is None:
        return ScheduleFactors()
    sparse_decay = config.sparse_depth_weight_decay
    if sparse_decay is None:
        sparse_decay = config.loss_weight_decay
    return ScheduleFactors(
        losses.loss_weight_schedule(step, length, config.loss_weight_decay),
        losses.loss_weight_schedule(step, length, config.geo_weight_decay),
        losses.loss_weight_schedule(step, length, sparse_decay),
    )


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
        state = carried_grid_state(model, training_callback_attributes)
        model.field.upsample(model.grid_resolution(voxels), state)
        _restart_grid_optimizer(training_callback_attributes, state)

    def update_alpha_mask(step: int) -> None:
        occupied_box = model.field.update_alpha_mask(
            model.config.step_ratio, model.config.distance_scale, model.config.alpha_mask_threshold,
            seen=model.seen_by_training_views(),
        )
        if step == alpha_mask_steps[0]:
            # Keep the voxel count while the box shrinks: the freed voxels refine the occupied region.
            voxels = int(model.field.density_grid.resolution.prod())
            state = carried_grid_state(model, training_callback_attributes)
            model.field.shrink(occupied_box, state)
            model.field.upsample(model.grid_resolution(voxels), state)
            _restart_grid_optimizer(training_callback_attributes, state)

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


def carried_grid_state(model: ScheduledModel, attributes: TrainingCallbackAttributes) -> Optional[OptimizerState]:
    """The grid optimiser's state, for the resize to carry over (``carry_optimizer_state``); else None."""
    if not model.config.carry_optimizer_state or attributes.optimizers is None:
        return None
    optimizer = attributes.optimizers.optimizers.get("encodings")
    return None if optimizer is None else optimizer.state


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


def _restart_grid_optimizer(attributes: TrainingCallbackAttributes, carried: Optional[OptimizerState] = None) -> None:
    """Recreate the grid optimiser for the resized tensors; its lr restarts. ``carried``: the old optimiser's
    state re-keyed to the new tensors (``carried_grid_state``), which the new one continues from."""
    optimizers, pipeline = attributes.optimizers, attributes.pipeline
    if optimizers is None or pipeline is None:
        return
    config = optimizers.config["encodings"]
    params = pipeline.get_param_groups()["encodings"]
    old_scheduler = optimizers.schedulers.get("encodings")
    optimizers.optimizers["encodings"] = config["optimizer"].setup(params=params)
    if carried:
        for param in params:
            if param in carried:
                optimizers.optimizers["encodings"].state[param] = carried[param]
    optimizers.parameters["encodings"] = params
    if config.get("scheduler"):
        scheduler = config["scheduler"].setup().get_scheduler(optimizer=optimizers.optimizers["encodings"], lr_init=config["optimizer"].lr)
        if old_scheduler is not None and not pipeline.model.config.grid_lr_restarts:
            continue_decay(scheduler, old_scheduler.last_epoch)
        optimizers.schedulers["encodings"] = scheduler


def continue_decay(scheduler: LambdaLR, step: int) -> None:
    """Put a fresh scheduler (and its optimiser's learning rates) at ``step`` of its curve, as if it had run
    from the start (``grid_lr_restarts`` off)."""
    scheduler.last_epoch = step
    lrs = [base * fn(step) for base, fn in zip(scheduler.base_lrs, scheduler.lr_lambdas)]
    for group, lr in zip(scheduler.optimizer.param_groups, lrs):
        group["lr"] = lr
    scheduler._last_lr = lrs  # what get_last_lr() reports (nerfstudio logs it)
