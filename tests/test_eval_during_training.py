"""Evaluation during training (what --vis tensorboard / wandb / comet turn on) with every registered preset:
an eval batch, one eval image and all eval images, for a few steps each, then a checkpoint.

nerfstudio evaluates before it saves, so a crash here used to take the run's first checkpoint with it."""

from pathlib import Path

import pytest
import torch

from frugalnerf_ns.run.presets import build_trainer_config, load_preset_table
from tests import layout_fixtures as fx
from tests.training_helpers import preset_config, train

PRESETS = sorted(load_preset_table())
#: Run by ``make test``: the paper's preset, the tiny one and the DTU CPU preset (the eval-mask path); the other
#: presets differ from these only in numbers and run with the end-to-end set (``make test-e2e``, CI).
QUICK = {"frugalnerf", "frugalnerf-tiny", "frugalnerf-dtu-cpu"}


@pytest.fixture(scope="module")
def masked_scene(tmp_path_factory) -> Path:
    """A DTU-layout scene with object masks (the eval-mask path of the DTU presets)."""
    root = tmp_path_factory.mktemp("dtu") / "scan"
    fx.write_dtu(root, count=8)
    return root


def test_every_preset_is_registered_here():
    assert {"frugalnerf", "frugalnerf-fast", "frugalnerf-quality", "frugalnerf-dtu", "frugalnerf-tiny",
            "frugalnerf-cpu", "frugalnerf-dtu-cpu"} <= set(PRESETS)


@pytest.mark.parametrize("preset", [p if p in QUICK else pytest.param(p, marks=pytest.mark.e2e) for p in PRESETS])
def test_preset_evaluates_during_training_and_saves(preset, procedural_scene, masked_scene, tmp_path, monkeypatch):
    dtu = "dtu" in preset
    data = masked_scene if dtu else procedural_scene
    parser = {"pipeline__datamanager__dataparser__train_views": (0, 3), "pipeline__datamanager__dataparser__test_views": (1, 5)} if dtu \
        else {"pipeline__datamanager__dataparser__center_method": "focus"}
    full_length = build_trainer_config(preset).max_num_iterations
    config = preset_config(
        preset, data, tmp_path,
        max_num_iterations=2, steps_per_eval_batch=1, steps_per_eval_image=1, steps_per_eval_all_images=1,
        steps_per_save=1000, **parser,
        # Two steps of the preset's own schedule (not the whole schedule squeezed into two steps, which
        # would upsample the paper presets to their 640^3 final grid at step 1).
        schedule_steps=full_length,
    )
    rays = config.pipeline.datamanager.eval_num_rays_per_batch
    k = config.pipeline.datamanager.patch_size
    seen = {}
    from nerfstudio.utils import writer

    real_put_dict = writer.put_dict

    def record(name, scalar_dict, step):
        seen[name] = dict(scalar_dict)
        real_put_dict(name=name, scalar_dict=scalar_dict, step=step)

    monkeypatch.setattr(writer, "put_dict", record)
    trainer = train(config)
    # The eval batch is scored pixel by pixel whatever the training patch (4096 rays are not a multiple of 25).
    assert rays % (k * k) != 0 or preset == "frugalnerf-tiny"
    eval_loss = seen["Eval Loss Dict"]
    assert torch.isfinite(eval_loss["rgb_loss"]) and float(eval_loss["rgb_loss"]) >= 0
    assert 0 < float(seen["Eval Metrics Dict"]["psnr"]) <= 100
    one_image = seen["Eval Images Metrics"]
    assert 0 < one_image["psnr"] <= 100 and 0 <= one_image["ssim"] <= 1
    # The 40x30 masked fixture is below LPIPS' 31-pixel minimum: the metric is left out, not a crash.
    with_lpips = {"psnr", "ssim"} | (set() if dtu else {"lpips"})
    assert set(one_image) & {"psnr", "ssim", "lpips"} == with_lpips and one_image.get("lpips", 0) >= 0
    all_images = seen["Eval Images Metrics Dict (all images)"]
    assert set(all_images) & {"psnr", "ssim", "lpips"} == with_lpips
    # The final checkpoint is written after the evaluations.
    assert (trainer.checkpoint_dir / "step-000000001.ckpt").is_file()
    if preset == "frugalnerf":  # the GPU preset itself trains on a CPU: the paper's 16 XY density components
        assert trainer.pipeline.model.field.density_grid.planes[0].shape[1] == 16
