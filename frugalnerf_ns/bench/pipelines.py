"""The one pipeline builder of the measurements: a preset set up on a scene as ``ns-train`` sets it up, with its
grid at the size the run reaches (the steady state of most of training), so that a preset can be sized,
profiled or checked without training it."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Callable, Optional, Sequence, Tuple


def preset_pipeline(preset: str, data: Path, *, device: str = "cpu", parser_args: Sequence[str] = (),
                    train_views: Optional[Sequence[int]] = None, final_grid: bool = True,
                    configure: Optional[Callable] = None) -> Tuple[object, object]:
    """``(config, pipeline)`` of ``preset`` on ``data`` (training split; "val" sets the datamanager up for
    training: patches, novel and sparse-depth rays).

    ``parser_args`` picks the dataparser with ns-train's subcommand syntax (``["frugal-llff", "--train-views",
    "6", "13"]``); ``train_views`` sets the preset's own parser's training views; ``configure(config)`` changes
    the trainer config before set-up; ``final_grid`` upsamples the grid to the preset's final voxel count.
    """
    from frugalnerf_ns.run.presets import build_trainer_config

    config = build_trainer_config(preset)
    config.machine.device_type = "cuda" if str(device).startswith("cuda") else "cpu"
    if parser_args:
        import tyro
        from nerfstudio.configs.dataparser_configs import all_dataparsers

        name, rest = parser_args[0], list(parser_args[1:])
        if name not in all_dataparsers:
            sys.exit(f"frugalnerf-bench: unknown dataparser {name!r} (known: {', '.join(sorted(all_dataparsers))})")
        default = all_dataparsers[name]
        config.pipeline.datamanager.dataparser = tyro.cli(type(default), args=rest, default=default)
    config.pipeline.datamanager.data = data
    config.pipeline.datamanager.dataparser.data = data
    if train_views is not None:
        config.pipeline.datamanager.dataparser.train_views = tuple(train_views)
    if configure is not None:
        configure(config)
    pipeline = config.pipeline.setup(device=str(device), test_mode="val")
    if final_grid:
        model = pipeline.model
        model.field.upsample(model.grid_resolution(model.final_voxels))
    return config, pipeline
