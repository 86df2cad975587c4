"""Run a registered preset through nerfstudio's real Trainer in this process (no ns-train start-up cost)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from frugalnerf_ns.run.presets import apply_override, build_trainer_config


def preset_config(preset: str, data: Path, output_dir: Path, **overrides: Any):
    """The preset's config for ``data`` (tensorboard logging: evaluation during training is on), with
    ``overrides`` by dotted path (``pipeline__model__geo_weight=0`` style keys, ``__`` for ``.``)."""
    config = build_trainer_config(preset)
    config.pipeline.datamanager.data = Path(data)
    config.output_dir = Path(output_dir)
    config.vis = "tensorboard"
    config.timestamp = "run"
    config.logging.local_writer.enable = False
    for key, value in overrides.items():
        apply_override(config, key.replace("__", "."), value)
    return config


def train(config):
    """Set up and train ``config`` with nerfstudio's trainer loop; returns the trainer."""
    from nerfstudio.utils import writer  # after nerfstudio's configs (importing it first is circular)

    # nerfstudio's writers are module globals: start each run with none from an earlier one.
    writer.EVENT_WRITERS.clear()
    writer.EVENT_STORAGE.clear()
    config.save_config()
    trainer = config.setup(local_rank=0, world_size=1)
    trainer.setup()
    trainer.train()
    return trainer


def ns_train_main(config) -> str:
    """``ns-train``'s own main (config.yml written, then set-up and training) in this process, for a run that
    must stop with one line: returns that line (the SystemExit's message, what ns-train prints with status 1).
    The real binary's exit status and stderr are tested once (tests/test_data_errors.py)."""
    import pytest
    from nerfstudio.scripts import train as ns_train
    from nerfstudio.utils import writer

    writer.EVENT_WRITERS.clear()
    writer.EVENT_STORAGE.clear()
    with pytest.raises(SystemExit) as stopped:
        ns_train.main(config)
    message = stopped.value.code
    assert isinstance(message, str) and "\n" not in message, message
    return message
