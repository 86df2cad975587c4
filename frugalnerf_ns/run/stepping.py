"""Training steps outside nerfstudio's Trainer, for benchmarks and machine checks: the same calls, in the
same order, as ``Trainer.train_iteration`` (callbacks, zero_grad, loss, backward, optimiser and scheduler
steps), timed per step and synchronised on CUDA so a step's time is the GPU's too."""

from __future__ import annotations

import time
from typing import Any, Dict, List, Tuple

import torch


def optimizers_and_callbacks(config, pipeline) -> Tuple[Any, List[Any]]:
    """nerfstudio's optimisers for ``config.optimizers`` and the pipeline's training callbacks."""
    from nerfstudio.engine.callbacks import TrainingCallbackAttributes
    from nerfstudio.engine.optimizers import Optimizers

    optimizers = Optimizers(dict(config.optimizers), pipeline.get_param_groups())
    callbacks = pipeline.get_training_callbacks(
        TrainingCallbackAttributes(optimizers=optimizers, grad_scaler=None, pipeline=pipeline, trainer=None)
    )
    return optimizers, callbacks


def run_steps(pipeline, optimizers, callbacks, steps: int, start: int = 0) -> Tuple[List[float], Dict, Dict]:
    """Train ``steps`` steps from step ``start``; (seconds per step, last loss dict, last model outputs)."""
    from nerfstudio.engine.callbacks import TrainingCallbackLocation

    cuda = next(pipeline.model.parameters()).is_cuda
    times: List[float] = []
    losses: Dict[str, Any] = {}
    outputs: Dict[str, Any] = {}
    for step in range(start, start + steps):
        begin = time.perf_counter()
        for callback in callbacks:
            callback.run_callback_at_location(step, TrainingCallbackLocation.BEFORE_TRAIN_ITERATION)
        optimizers.zero_grad_all()
        outputs, losses, _ = pipeline.get_train_loss_dict(step=step)
        sum(losses.values()).backward()  # type: ignore[union-attr]
        optimizers.optimizer_step_all()
        optimizers.scheduler_step_all(step)
        for callback in callbacks:
            callback.run_callback_at_location(step, TrainingCallbackLocation.AFTER_TRAIN_ITERATION)
        if cuda:
            torch.cuda.synchronize()
        times.append(time.perf_counter() - begin)
    return times, losses, outputs
