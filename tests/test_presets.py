import os
import shutil
import subprocess
import sys
from importlib.metadata import entry_points
from pathlib import Path

import pytest
import yaml

from frugalnerf_ns.run import presets


def test_entry_points_register_the_methods():
    names = {ep.name for ep in entry_points(group="nerfstudio.method_configs")}
    # Every preset in the YAML is a method nerfstudio can run.
    assert set(presets.load_preset_table()) <= names
    assert {"frugalnerf", "frugalnerf-fast", "frugalnerf-quality", "frugalnerf-tiny", "frugalnerf-dtu"} <= names
    parsers = {ep.name for ep in entry_points(group="nerfstudio.dataparser_configs")}
    assert {"frugal-auto", "frugal-llff", "frugal-dtu", "frugal-realestate", "frugal-nerfstudio", "frugal-colmap", "frugal-photos"} <= parsers


def test_nerfstudio_discovers_the_methods():
    from nerfstudio.plugins.registry import discover_methods

    methods, descriptions = discover_methods()
    assert methods["frugalnerf"].method_name == "frugalnerf"
    assert "paper" in descriptions["frugalnerf"]


def test_paper_preset_holds_the_paper_settings():
    # The paper's settings are stated once, as config defaults and in base_trainer_config; the root preset
    # repeats none of them (a second copy could drift from the first).
    assert presets.load_preset_table()["frugalnerf"]["overrides"] == {}
    config = presets.build_trainer_config("frugalnerf")
    model = config.pipeline.model
    assert config.max_num_iterations == 5000
    assert config.pipeline.datamanager.train_num_rays_per_batch == 4096
    assert config.pipeline.datamanager.patch_size == 5 and config.pipeline.datamanager.num_novel_rays_per_batch == 4096
    # Loss weights of the LLFF setting (Sec. 4, the supplementary "Losses" and the reference LLFF config).
    assert model.lower_scale_color_weight == 10.0 and model.geo_weight == 0.01 and model.sparse_depth_weight == 0.5
    assert model.appearance_tv_weight == model.density_tv_weight == 10.0 and model.distortion_weight == 5e-4
    assert model.depth_smoothness_weight == 5e-3 and model.reprojection_threshold == 0.5
    assert model.initial_voxels == 64**3 and model.final_voxels == 640**3
    assert model.density_components == (16, 4, 4) and model.appearance_components == (48, 12, 12)
    assert model.num_lower_scales == 2 and model.downsample_ratio == 4
    assert model.distance_scale == 25.0 and model.density_activation == "relu"
    assert model.step_ratio == 0.5
    # Not in the paper either: the grids beyond a capture's box; frugalnerf-cpu measured 256^3, the paper's keeps 128^3.
    assert model.outer_space_resolution == 128
    assert presets.build_trainer_config("frugalnerf-cpu").pipeline.model.outer_space_resolution == 256
    # Not a paper term: the CPU presets' photometric consistency is off here.
    assert model.photometric_weight == 0.0
    assert config.optimizers["encodings"]["optimizer"].lr == 0.08
    assert config.optimizers["encodings"]["optimizer"].betas == (0.9, 0.99)
    assert config.optimizers["fields"]["optimizer"].lr == 0.004


def flatten(config, prefix=""):
    """{dotted path: value} of every leaf of a config (dataclass fields and dict keys)."""
    import dataclasses

    if dataclasses.is_dataclass(config) and not isinstance(config, type):
        items = [(f.name, getattr(config, f.name)) for f in dataclasses.fields(config) if f.name != "_target"]
    elif isinstance(config, dict):
        items = list(config.items())
    else:
        return {prefix: config}
    out = {}
    for name, value in items:
        out.update(flatten(value, f"{prefix}{name}."))
    return {k.rstrip("."): v for k, v in out.items()}


@pytest.mark.parametrize("name", [n for n, entry in sorted(presets.load_preset_table().items()) if entry.get("inherits")])
def test_derived_presets_differ_from_their_parent_only_where_they_say(name):
    table = presets.load_preset_table()
    parent = table[name]["inherits"]
    child_values, parent_values = flatten(presets.build_trainer_config(name)), flatten(presets.build_trainer_config(parent))
    assert child_values.keys() == parent_values.keys()
    changed = {path for path in child_values if child_values[path] != parent_values[path]}
    said = set(table[name]["overrides"]) | {"method_name"}
    assert changed <= said, changed - said
    assert "method_name" in changed and len(changed) > 1


def test_bad_presets_fail_clearly():
    table = {
        "a": {"description": "", "overrides": {"pipeline.model.no_such_field": 1}},
        "b": {"description": "", "inherits": "c"},
        "c": {"description": "", "inherits": "b"},
        "d": {"description": "", "inherits": "missing"},
    }
    with pytest.raises(KeyError, match="no_such_field"):
        presets.build_trainer_config("a", table)
    with pytest.raises(ValueError, match="loops"):
        presets.resolved_overrides("b", table)
    with pytest.raises(KeyError, match="unknown preset 'missing'"):
        presets.resolved_overrides("d", table)


def test_list_values_become_tuples():
    table = {"x": {"description": "", "overrides": {"pipeline.model.upsample_at": [0.1, 0.2]}}}
    assert presets.build_trainer_config("x", table).pipeline.model.upsample_at == (0.1, 0.2)


@pytest.mark.parametrize("name", sorted(presets.load_preset_table()))
def test_every_preset_schedule_fits_its_iterations(name):
    config = presets.build_trainer_config(name)
    from frugalnerf_ns.model.training_schedule import steps_at

    total = config.max_num_iterations
    model = config.pipeline.model
    for fractions in (model.upsample_at, model.alpha_mask_at):
        steps = steps_at(fractions, total)
        assert all(0 < step < total for step in steps) and steps == sorted(set(steps)), name
    assert model.initial_voxels <= model.final_voxels


def test_paper_preset_schedule_is_the_papers_steps():
    from frugalnerf_ns.model.training_schedule import steps_at

    model = presets.build_trainer_config("frugalnerf").pipeline.model
    assert steps_at(model.upsample_at, 5000) == [500, 1000, 1500, 2000, 2500, 3000]
    assert steps_at(model.alpha_mask_at, 5000) == [1000, 2000]


def test_speed_presets_trade_iterations_and_grid_against_the_paper_preset():
    paper, fast, quality = (presets.build_trainer_config(n) for n in ("frugalnerf", "frugalnerf-fast", "frugalnerf-quality"))
    assert fast.max_num_iterations < paper.max_num_iterations < quality.max_num_iterations
    assert fast.pipeline.model.final_voxels < paper.pipeline.model.final_voxels == quality.pipeline.model.final_voxels
    assert quality.pipeline.datamanager.train_num_rays_per_batch > paper.pipeline.datamanager.train_num_rays_per_batch
    # Everything else stays the paper's (same losses and weights).
    assert fast.pipeline.model.geo_weight == paper.pipeline.model.geo_weight == quality.pipeline.model.geo_weight


def test_a_checkout_on_pythonpath_reads_its_own_configs(tmp_path):
    # A git worktree gated with main's editable install first put its code on PYTHONPATH, but
    # frugalnerf_ns.configs still resolved to the installed checkout: a preset change was trained as main's.
    root = Path(__file__).resolve().parent.parent
    copy = tmp_path / "checkout"
    shutil.copytree(root / "frugalnerf_ns", copy / "frugalnerf_ns", ignore=shutil.ignore_patterns("__pycache__"))
    shutil.copytree(root / "configs", copy / "configs")
    shutil.copy(root / "pyproject.toml", copy / "pyproject.toml")
    table = yaml.safe_load((copy / "configs" / "presets.yaml").read_text())
    table["frugalnerf-cpu"]["overrides"]["pipeline.model.initial_voxels"] = 12345
    (copy / "configs" / "presets.yaml").write_text(yaml.safe_dump(table))
    splits = yaml.safe_load((copy / "configs" / "splits.yaml").read_text())
    splits["checkout_marker"] = [7]
    (copy / "configs" / "splits.yaml").write_text(yaml.safe_dump(splits))
    probe = (
        "import frugalnerf_ns, frugalnerf_ns.run.presets as p, frugalnerf_ns.data.splits as s;"
        "print(frugalnerf_ns.__file__);"
        "print(p.resolved_overrides('frugalnerf-cpu', p.load_preset_table())['pipeline.model.initial_voxels']);"
        "print(s.load_split_table().get('checkout_marker'))"
    )
    env = {**os.environ, "PYTHONPATH": str(copy)}
    out = subprocess.run([sys.executable, "-c", probe], cwd=copy, env=env, capture_output=True, text=True, check=True)
    lines = out.stdout.strip().splitlines()
    assert lines[0] == str(copy / "frugalnerf_ns" / "__init__.py")
    assert lines[1:] == ["12345", "[7]"]
    # The checkout this test runs from reads its own file as well.
    assert presets.resolved_overrides("frugalnerf-cpu", presets.load_preset_table())[
        "pipeline.model.initial_voxels"] == yaml.safe_load((root / "configs" / "presets.yaml").read_text())[
        "frugalnerf-cpu"]["overrides"]["pipeline.model.initial_voxels"]


def test_adam_is_fused_where_torch_has_the_kernel_and_updates_as_the_unfused_one():
    """The presets' Adam runs torch's fused update on the CPU (one kernel per tensor): after 30 steps its parameters
    equal the per-operation update's to float rounding; a config saved before the option existed (no ``fused`` in its
    state) sets up the same way, and a device without the kernel gets torch's default update."""
    import torch

    from frugalnerf_ns.run.presets import AdamBetasOptimizerConfig

    torch.manual_seed(0)
    start = [torch.randn(1, 6, 17, 13), torch.randn(1, 6, 17, 1), torch.randn(40, 9)]
    finals, kinds = [], []
    for fused in (False, True):
        params = [torch.nn.Parameter(t.clone()) for t in start]
        optimizer = AdamBetasOptimizerConfig(lr=0.02, eps=1e-15, fused=fused).setup(params=params)
        kinds.append(bool(optimizer.defaults.get("fused")))
        generator = torch.Generator().manual_seed(1)
        for _ in range(30):
            for p in params:
                p.grad = torch.randn(p.shape, generator=generator)
            optimizer.step()
        finals.append([p.detach() for p in params])
    assert kinds == [False, True]
    for a, b, s in zip(*finals, start):
        assert float((a - b).abs().max()) <= 1e-6 * float((a - s).abs().max()) + 1e-7
        assert float((a - s).abs().max()) > 0.1  # the steps moved the parameters

    old = AdamBetasOptimizerConfig(lr=0.01)
    del old.__dict__["fused"]  # as PyYAML loads a config.yml written before the field
    assert old.setup(params=[torch.nn.Parameter(torch.ones(3))]).defaults.get("fused") is True

    class NoFusedKernel(torch.optim.Adam):  # torch's refusal on a device or version without the kernel
        def __init__(self, params, fused=None, **kwargs):
            if fused:
                raise RuntimeError("`fused=True` requires all the params to be floating point Tensors of supported devices")
            super().__init__(params, **kwargs)

    params = (p for p in [torch.nn.Parameter(torch.ones(3))])  # a generator: the retry must still see the parameters
    fallback = AdamBetasOptimizerConfig(_target=NoFusedKernel, lr=0.01).setup(params=params)
    assert not fallback.defaults.get("fused") and len(fallback.param_groups[0]["params"]) == 1
