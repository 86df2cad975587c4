"""Options checked before training: one line naming the option, its limit and the value; a start that fails
leaves no run folder behind; running out of memory is one line too."""

import math

import pytest

from frugalnerf_ns.run.options import OptionError, option_problems, validate_options
from frugalnerf_ns.run.presets import apply_override, build_trainer_config, load_preset_table
from tests.training_helpers import ns_train_main, preset_config


@pytest.mark.parametrize("preset", sorted(load_preset_table()))
def test_every_preset_passes_the_checks(preset):
    assert option_problems(build_trainer_config(preset)) == []


@pytest.mark.parametrize(
    "path, value, expected",
    [
        ("pipeline.model.final_voxels", 0, "--pipeline.model.final-voxels must be >= --pipeline.model.initial-voxels (262144), got 0"),
        ("pipeline.model.final_voxels", -8, "got -8"),
        ("pipeline.model.initial_voxels", 0, "--pipeline.model.initial-voxels must be >= 8 (2^3), got 0"),
        ("pipeline.model.reprojection_threshold", -1.0, "--pipeline.model.reprojection-threshold must be > 0"),
        ("pipeline.model.reprojection_threshold", 0.0, "every ray would be left out"),
        ("pipeline.datamanager.patch_size", 4, "--pipeline.datamanager.patch-size must be odd and >= 1"),
        ("pipeline.datamanager.patch_size", 0, "got 0"),
        ("pipeline.datamanager.train_num_rays_per_batch", 24, ">= one 5x5 patch (25 rays), got 24"),
        ("pipeline.model.geo_weight", -0.01, "--pipeline.model.geo-weight must be >= 0 and finite, got -0.01"),
        ("pipeline.model.distortion_weight", math.nan, "--pipeline.model.distortion-weight must be >= 0 and finite"),
        ("pipeline.model.upsample_at", (0.5, 0.1), "--pipeline.model.upsample-at must be increasing fractions of the schedule, each in (0, 1), got 0.5 0.1"),
        ("pipeline.model.alpha_mask_at", (0.2, 1.0), "got 0.2 1.0"),
        ("schedule_steps", 0, "--schedule-steps must be >= 1 (or unset: the run's iterations), got 0"),
        ("pipeline.model.loss_weight_decay", 0.0, "--pipeline.model.loss-weight-decay must be > 0"),
        ("pipeline.model.geo_novel_weight", -0.1, "--pipeline.model.geo-novel-weight must be >= 0 and finite, got -0.1"),
        ("pipeline.datamanager.num_novel_rays_per_batch", -1, "got -1"),
        ("pipeline.datamanager.triangulation.sift_upsample", 0, "--pipeline.datamanager.triangulation.sift-upsample must be a whole number >= 1, got 0"),
    ],
)
def test_a_bad_value_is_one_line_naming_the_option_and_limit(path, value, expected):
    config = build_trainer_config("frugalnerf")
    apply_override(config, path, value)
    with pytest.raises(OptionError) as err:
        validate_options(config)
    message = str(err.value)
    assert message.startswith("frugalnerf: error: ") and expected in message and "\n" not in message


def test_auto_grid_ignores_final_voxels_and_several_problems_are_counted():
    config = build_trainer_config("frugalnerf")
    apply_override(config, "pipeline.model.auto_grid", True)
    apply_override(config, "pipeline.model.final_voxels", 0)
    assert option_problems(config) == []
    apply_override(config, "pipeline.datamanager.patch_size", 6)
    apply_override(config, "pipeline.model.geo_weight", -1.0)
    with pytest.raises(OptionError, match=r"\(and 1 more problem"):
        validate_options(config)


def test_bad_option_and_bad_data_stop_before_training_and_leave_no_run_folder(procedural_scene, tmp_path):
    out = tmp_path / "outputs"
    said = ns_train_main(preset_config("frugalnerf-tiny", procedural_scene, out, pipeline__model__final_voxels=0))
    assert said.startswith("frugalnerf: error: --pipeline.model.final-voxels must be >=") and said.endswith("got 0")
    said = ns_train_main(preset_config("frugalnerf-tiny", tmp_path / "no-such-scene", out))
    assert said.startswith("frugalnerf: error:")
    # nerfstudio wrote config.yml before set-up: nothing of either run is left.
    assert not out.exists() or not any(out.rglob("*")), sorted(out.rglob("*"))


def test_a_batch_larger_than_memory_is_one_line(procedural_scene, tmp_path):
    # 10^12 rays: the first allocation (the patch indices, 320 GB) fails at once, before any page is touched.
    said = ns_train_main(preset_config("frugalnerf-tiny", procedural_scene, tmp_path,
                                       pipeline__datamanager__train_num_rays_per_batch=10**12))
    assert said.startswith("frugalnerf: error: out of memory at step 0 (1000000000000 training + 256 novel rays per step")
    assert "--pipeline.datamanager.train-num-rays-per-batch" in said
    assert "asked for 320.0 GB" in said and "GB free" in said  # 4e10 patches x 8-byte indices, and the limit


def test_out_of_memory_is_recognised_from_both_allocators():
    import torch

    from frugalnerf_ns.run.trainer import is_out_of_memory, memory_shortfall

    cpu = RuntimeError("[enforce fail at alloc_cpu.cpp:127] err == 0. DefaultCPUAllocator: can't allocate memory: "
                       "you tried to allocate 320000000000 bytes. Error code 12 (Cannot allocate memory)")
    assert is_out_of_memory(cpu) and memory_shortfall(cpu, "cpu").startswith("asked for 320.0 GB, ")
    cuda = torch.OutOfMemoryError("CUDA out of memory. Tried to allocate 2.00 GiB. GPU 0 has a total capacity of 79 GiB")
    assert is_out_of_memory(cuda) and memory_shortfall(cuda, "cpu").startswith("asked for 2.1 GB, ")
    assert not is_out_of_memory(RuntimeError("The size of tensor a (3) must match the size of tensor b (4)"))
    assert not is_out_of_memory(ValueError("out of memory"))  # only the allocators' errors
