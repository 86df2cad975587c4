"""Turn the presets in ``configs/presets.yaml`` into nerfstudio MethodSpecifications.

The structure (pipeline, datamanager, model, optimiser groups) is built once here; every number lives in
the YAML, where each preset derives from another by overriding dotted paths.
"""

from __future__ import annotations

import copy
import dataclasses
import sys
from typing import Any, Dict, Mapping, Tuple

import torch
import yaml
from nerfstudio.configs.base_config import ViewerConfig
from nerfstudio.engine.optimizers import AdamOptimizerConfig
from nerfstudio.engine.schedulers import ExponentialDecaySchedulerConfig
from nerfstudio.engine.trainer import TrainerConfig
from nerfstudio.plugins.types import MethodSpecification

from frugalnerf_ns.config_files import config_text
from frugalnerf_ns.data.datamanager import FrugalDataManagerConfig
from frugalnerf_ns.data.dataparsers.auto import AutoDataParserConfig
from frugalnerf_ns.model.frugalnerf import FrugalNeRFModelConfig
from frugalnerf_ns.run.pipeline import FrugalPipelineConfig
from frugalnerf_ns.run.trainer import FrugalTrainerConfig


@dataclasses.dataclass
class AdamBetasOptimizerConfig(AdamOptimizerConfig):
    """Adam with configurable betas (nerfstudio's Adam config fixes them at torch's defaults)."""

    betas: Tuple[float, float] = (0.9, 0.99)
    """Adam's running-average coefficients; TensoRF and FrugalNeRF use (0.9, 0.99)."""
    fused: bool = True
    """Adam's update as one fused kernel per tensor (torch's ``fused=True``) where torch has one for the parameters'
    device, else torch's default: the same update to float rounding, in one pass over each grid plane instead of a
    dozen (on 2 CPU cores ~8 ms instead of ~40 ms a step for the CPU presets' final grids)."""

    def setup(self, params) -> torch.optim.Optimizer:
        kwargs = vars(self).copy()
        for name in ("_target", "max_norm", "fused"):
            kwargs.pop(name, None)  # a config saved before a field existed lacks it
        params = list(params)
        if self.fused:
            try:
                return self._target(params, fused=True, **kwargs)
            except (RuntimeError, ValueError, TypeError):  # no fused kernel for this device or torch version
                pass
        return self._target(params, **kwargs)


def load_preset_table() -> Dict[str, Dict[str, Any]]:
    """The raw YAML table: name -> {description, inherits?, overrides}."""
    text = config_text("presets.yaml")
    return yaml.safe_load(text)


def resolved_overrides(name: str, table: Mapping[str, Mapping[str, Any]]) -> Dict[str, Any]:
    """Overrides of ``name`` merged over those of every preset it inherits from (root first)."""
    chain, seen = [], set()
    current: str | None = name
    while current is not None:
        if current in seen:
            raise ValueError(f"preset inheritance loops through {current!r}")
        if current not in table:
            raise KeyError(f"unknown preset {current!r}; known: {sorted(table)}")
        seen.add(current)
        chain.append(table[current])
        current = table[current].get("inherits")
    merged: Dict[str, Any] = {}
    for entry in reversed(chain):
        merged.update(entry.get("overrides") or {})
    return merged


def _interactive() -> bool:
    return sys.stdin is not None and sys.stdin.isatty()


def base_trainer_config(method_name: str) -> FrugalTrainerConfig:
    """The paper's run (LLFF 2-view, Sec. 4 "Implementation details"): the root preset ``frugalnerf``.

    The paper's settings live once each: the model's and the datamanager's as the defaults of
    FrugalNeRFModelConfig and FrugalDataManagerConfig, the schedule, batch and learning rates here. Every other
    preset in ``configs/presets.yaml`` derives from this one by overrides."""
    return FrugalTrainerConfig(
        method_name=method_name,
        max_num_iterations=5000,
        # Our choices (the paper names none), stated here rather than left to nerfstudio's defaults.
        steps_per_eval_batch=500,
        steps_per_eval_image=500,
        steps_per_eval_all_images=5000,
        steps_per_save=1000,
        mixed_precision=False,
        pipeline=FrugalPipelineConfig(
            # 4096 rays per step (the reference's batch_size); evaluation batches of the same size.
            datamanager=FrugalDataManagerConfig(dataparser=AutoDataParserConfig(), train_num_rays_per_batch=4096,
                                                eval_num_rays_per_batch=4096),
            model=FrugalNeRFModelConfig(),
        ),
        optimizers={
            "encodings": {
                "optimizer": AdamBetasOptimizerConfig(lr=0.08),
                # max_steps: set by FrugalTrainer to the run's schedule length (--schedule-steps).
                "scheduler": ExponentialDecaySchedulerConfig(lr_final=0.002, max_steps=5000),
            },
            "fields": {
                "optimizer": AdamBetasOptimizerConfig(lr=4e-3),
                "scheduler": ExponentialDecaySchedulerConfig(lr_final=1e-4, max_steps=5000),
            },
        },
        # Without a terminal (CI, nohup, a job queue) nobody can press ctrl+c, so the viewer must not keep
        # the process alive after training; interactive runs keep nerfstudio's behaviour.
        viewer=ViewerConfig(num_rays_per_chunk=1 << 14, quit_on_train_completion=not _interactive()),
        vis="viewer",
    )


def apply_override(config: Any, dotted: str, value: Any) -> None:
    """Set ``config.a.b.c = value``; dict keys and dataclass fields both count as path segments."""
    *parents, leaf = dotted.split(".")
    target = config
    for part in parents:
        target = target[part] if isinstance(target, dict) else getattr(target, part)
    if isinstance(target, dict):
        if leaf not in target:
            raise KeyError(f"preset override {dotted!r}: no key {leaf!r}")
        target[leaf] = value
        return
    if not dataclasses.is_dataclass(target) or leaf not in {f.name for f in dataclasses.fields(target)}:
        raise KeyError(f"preset override {dotted!r}: {type(target).__name__} has no field {leaf!r}")
    current = getattr(target, leaf)
    if isinstance(current, tuple) and isinstance(value, list):
        value = tuple(value)
    setattr(target, leaf, value)


def build_trainer_config(name: str, table: Mapping[str, Mapping[str, Any]] | None = None) -> TrainerConfig:
    table = table if table is not None else load_preset_table()
    config = base_trainer_config(name)
    for dotted, value in resolved_overrides(name, table).items():
        apply_override(config, dotted, copy.deepcopy(value))
    return config


def method_specification(name: str) -> MethodSpecification:
    table = load_preset_table()
    return MethodSpecification(config=build_trainer_config(name, table), description=table[name]["description"])


# Entry points (pyproject.toml, group nerfstudio.method_configs) point at these.
frugalnerf = method_specification("frugalnerf")
frugalnerf_fast = method_specification("frugalnerf-fast")
frugalnerf_quality = method_specification("frugalnerf-quality")
frugalnerf_tiny = method_specification("frugalnerf-tiny")
frugalnerf_dtu = method_specification("frugalnerf-dtu")
frugalnerf_cpu = method_specification("frugalnerf-cpu")
frugalnerf_dtu_cpu = method_specification("frugalnerf-dtu-cpu")
frugalnerf_blender_cpu = method_specification("frugalnerf-blender-cpu")
