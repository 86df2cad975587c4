"""Checks of a run's options before anything is loaded: a bad value ends with one line naming the option,
its limit and the value, instead of a traceback (or a silently disabled loss) minutes into training.

Pure dataclass inspection: no data, no nerfstudio set-up, so the checks run as soon as ns-train has parsed
the command line.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Iterator, List, Tuple

from frugalnerf_ns.errors import UserError


class OptionError(UserError):
    """An option's value cannot work."""


def flag(path: str) -> str:
    """The command-line spelling of a dotted config path (pipeline.model.final_voxels ->
    --pipeline.model.final-voxels)."""
    return "--" + path.replace("_", "-")


def option_problems(config: Any) -> List[str]:
    """Every problem with the options of a FrugalNeRF TrainerConfig, as one sentence each (empty: fine)."""
    problems: List[str] = []
    model, dm = config.pipeline.model, config.pipeline.datamanager

    def need(ok: bool, path: str, limit: str, value: Any) -> None:
        if not ok:
            problems.append(f"{flag(path)} must be {limit}, got {value}")

    m, d = "pipeline.model", "pipeline.datamanager"
    need(config.max_num_iterations >= 0, "max_num_iterations", ">= 0", config.max_num_iterations)
    need(config.steps_per_save >= 1, "steps_per_save", ">= 1", config.steps_per_save)
    # Fewer than 8 voxels cannot span two voxels per axis (0 divides by zero when the grid is sized).
    need(model.initial_voxels >= 8, f"{m}.initial_voxels", ">= 8 (2^3)", model.initial_voxels)
    if not model.auto_grid:
        need(
            model.final_voxels >= max(model.initial_voxels, 8),
            f"{m}.final_voxels",
            f">= {flag(m + '.initial_voxels')} ({model.initial_voxels})",
            model.final_voxels,
        )
    schedule_steps = getattr(config, "schedule_steps", None)
    need(schedule_steps is None or schedule_steps >= 1, "schedule_steps", ">= 1 (or unset: the run's iterations)", schedule_steps)
    for name in ("upsample_at", "alpha_mask_at"):
        fractions = tuple(getattr(model, name))
        need(
            all(0 < f < 1 for f in fractions) and list(fractions) == sorted(set(fractions)),
            f"{m}.{name}",
            "increasing fractions of the schedule, each in (0, 1)",
            " ".join(map(str, fractions)) or "(none)",
        )
    need(model.num_lower_scales >= 0, f"{m}.num_lower_scales", ">= 0", model.num_lower_scales)
    need(model.downsample_ratio >= 1, f"{m}.downsample_ratio", ">= 1", model.downsample_ratio)
    need(_positive(model.step_ratio), f"{m}.step_ratio", "> 0", model.step_ratio)
    need(model.max_samples_per_ray >= 1, f"{m}.max_samples_per_ray", ">= 1", model.max_samples_per_ray)
    need(_positive(model.distance_scale), f"{m}.distance_scale", "> 0", model.distance_scale)
    need(_non_negative(model.near_plane), f"{m}.near_plane", ">= 0", model.near_plane)
    # Errors are >= 0, so a threshold <= 0 leaves every ray out and L_geo silently does nothing.
    need(
        _positive(model.reprojection_threshold),
        f"{m}.reprojection_threshold",
        "> 0 (errors are >= 0: every ray would be left out; --pipeline.model.geo-weight 0 turns L_geo off)",
        model.reprojection_threshold,
    )
    need(_positive(model.loss_weight_decay), f"{m}.loss_weight_decay", "> 0 (1 keeps the weights constant)", model.loss_weight_decay)
    for name, value in _fields_ending(model, "_weight"):
        need(_non_negative(value), f"{m}.{name}", ">= 0 and finite", value)
    k = dm.patch_size
    need(k >= 1 and k % 2 == 1, f"{d}.patch_size", "odd and >= 1 (a k x k patch centred on a pixel: paper 5, DTU 15)", k)
    if k >= 1:
        need(
            dm.train_num_rays_per_batch >= k * k,
            f"{d}.train_num_rays_per_batch",
            f">= one {k}x{k} patch ({k * k} rays)",
            dm.train_num_rays_per_batch,
        )
    need(dm.eval_num_rays_per_batch >= 1, f"{d}.eval_num_rays_per_batch", ">= 1", dm.eval_num_rays_per_batch)
    need(dm.num_novel_rays_per_batch >= 0, f"{d}.num_novel_rays_per_batch", ">= 0", dm.num_novel_rays_per_batch)
    need(dm.num_novel_poses >= 1, f"{d}.num_novel_poses", ">= 1", dm.num_novel_poses)
    need(dm.num_sparse_rays_per_batch >= 0, f"{d}.num_sparse_rays_per_batch", ">= 0", dm.num_sparse_rays_per_batch)
    need(dm.min_sparse_points >= 0, f"{d}.min_sparse_points", ">= 0", dm.min_sparse_points)
    upsample = dm.triangulation.sift_upsample
    need(isinstance(upsample, int) and upsample >= 1, f"{d}.triangulation.sift_upsample", "a whole number >= 1", upsample)
    need(dm.fit_box_min_views >= 1, f"{d}.fit_box_min_views", ">= 1", dm.fit_box_min_views)
    need(_non_negative(dm.fit_box_margin), f"{d}.fit_box_margin", ">= 0", dm.fit_box_margin)
    if model.mlp_implementation == "tcnn":
        from frugalnerf_ns.field.color_mlp import tcnn_available

        need(tcnn_available(), f"{m}.mlp_implementation", "auto or torch where tinycudann or CUDA is missing", "tcnn")
    need(model.eval_num_rays_per_chunk >= 1, f"{m}.eval_num_rays_per_chunk", ">= 1", model.eval_num_rays_per_chunk)
    return problems


def validate_options(config: Any) -> None:
    """Raise ``OptionError`` with the first problem (and how many more there are)."""
    problems = option_problems(config)
    if problems:
        more = f" (and {len(problems) - 1} more problem(s) with the options)" if len(problems) > 1 else ""
        raise OptionError(problems[0] + more)


def _positive(value: float) -> bool:
    return math.isfinite(value) and value > 0


def _non_negative(value: float) -> bool:
    return math.isfinite(value) and value >= 0


def _fields_ending(config: Any, suffix: str) -> Iterator[Tuple[str, float]]:
    for f in dataclasses.fields(config):
        value = getattr(config, f.name)
        if f.name.endswith(suffix) and isinstance(value, (int, float)) and not isinstance(value, bool):
            yield f.name, float(value)
