"""A lean ``ns-train frugalnerf --help``: the model settings a user should not touch are gone from it (the 11
unadopted experiments deleted with their code, docs/notes/README.md "Settings removed from the model"; the settings
inherited from nerfstudio that the model never reads hidden), and a run's config.yml that still holds them loads."""

import contextlib
import dataclasses
import io
import re

import pytest
import torch
import tyro
import yaml

from frugalnerf_ns.run import presets

# Removed experiments, with a value other than their old default: what an old run's config.yml may hold.
REMOVED = {
    "carry_optimizer_state": "true",
    "grid_lr_restarts": "false",
    "scale_spanning_rounding": "up",
    "scale_spanning_scales": "1",
    "lower_scale_reading": "stretched",
    "reprojection_error": "mse",
    "geo_weight_decay": "0.5",
    "photometric_novel_weight": "0.1",
    "photometric_ssim_share": "0.85",
    "sparse_depth_weight_decay": "0.5",
    "room_geo_depth": "contracted",
}
# Inherited from nerfstudio's ModelConfig, read by no part of the model: hidden from --help, kept in the config.
HIDDEN = ("collider_params", "loss_coefficients", "prompt")
MAX_MODEL_OPTIONS = 61
"""--pipeline.model.* options in the help after the clean-up (76 before it)."""


def help_text(config) -> str:
    """``ns-train <method> --help`` for one method, in process: tyro on the registered config, marked as ns-train
    marks its union of methods (fixed fields suppressed, booleans as {True,False})."""
    out = io.StringIO()
    with contextlib.redirect_stdout(out), pytest.raises(SystemExit):
        tyro.cli(tyro.conf.SuppressFixed[tyro.conf.FlagConversionOff[type(config)]], default=config, args=["--help"])
    return out.getvalue()


def model_options(text: str):
    """The --pipeline.model.* options of a help text, one per option line (plain text: no terminal here)."""
    return re.findall(r"^[ │]{1,2}(--pipeline\.model\.[a-z0-9.-]+)", text, re.M)


def test_the_help_lists_no_removed_or_hidden_model_setting():
    text = help_text(presets.frugalnerf.config)
    options = model_options(text)
    assert len(options) == len(set(options))
    assert 40 <= len(options) <= MAX_MODEL_OPTIONS, options  # the lower bound: the help's format is still read
    assert "--pipeline.model.near-plane" in options and "--pipeline.model.geo-weight" in options
    for name in [*REMOVED, *HIDDEN]:
        flag = "--pipeline.model." + name.replace("_", "-")
        assert not any(o == flag or o.startswith(flag + ".") for o in options), flag
        assert flag not in text


def test_the_hidden_settings_keep_nerfstudios_defaults():
    model = presets.build_trainer_config("frugalnerf").pipeline.model
    assert model.collider_params == {"near_plane": 2.0, "far_plane": 6.0}
    assert model.loss_coefficients == {"rgb_loss_coarse": 1.0, "rgb_loss_fine": 1.0}
    assert model.prompt is None
    names = {f.name for f in dataclasses.fields(model)}
    assert set(HIDDEN) <= names and not set(REMOVED) & names


def test_a_config_yml_with_removed_settings_loads_and_its_model_works():
    from nerfstudio.data.scene_box import SceneBox
    from nerfstudio.cameras.rays import RayBundle

    from frugalnerf_ns.model.frugalnerf import FrugalNeRFModel, FrugalNeRFModelConfig
    from frugalnerf_ns.run.options import option_problems
    from frugalnerf_ns.run.trainer import FrugalTrainerConfig

    config = presets.build_trainer_config("frugalnerf-tiny")
    text = yaml.dump(config)  # what nerfstudio's save_config writes
    assert not any(f"\n    {name}:" in text for name in REMOVED)
    header = "  model: !!python/object:frugalnerf_ns.model.frugalnerf.FrugalNeRFModelConfig\n"
    assert text.count(header) == 1
    old = text.replace(header, header + "".join(f"    {name}: {value}\n" for name, value in REMOVED.items()))

    loaded = yaml.load(old, Loader=yaml.Loader)  # as nerfstudio's eval_setup and ns-train --load-config read it
    assert type(loaded) is FrugalTrainerConfig and type(loaded.pipeline.model) is FrugalNeRFModelConfig
    assert loaded.pipeline.model._target is FrugalNeRFModel
    # Every setting the model has is the saved one; the removed ones are left aside, read by nothing.
    for f in dataclasses.fields(config.pipeline.model):
        assert getattr(loaded.pipeline.model, f.name) == getattr(config.pipeline.model, f.name), f.name
    assert option_problems(loaded) == []

    torch.manual_seed(0)
    model = loaded.pipeline.model.setup(scene_box=SceneBox(aabb=torch.tensor([[-1.0] * 3, [1.0] * 3])),
                                        num_train_data=2, metadata={})
    model.eval()
    n = 16
    generator = torch.Generator().manual_seed(0)
    origins = torch.tensor([0.0, 0.0, -3.0]).expand(n, 3).clone()
    targets = (torch.rand(n, 3, generator=generator) - 0.5) * torch.tensor([1.0, 1.0, 0.0])
    bundle = RayBundle(origins=origins, directions=torch.nn.functional.normalize(targets - origins, dim=-1),
                       pixel_area=torch.ones(n, 1), camera_indices=torch.zeros(n, 1).long())
    with torch.no_grad():
        rgb = model.get_outputs(bundle)["rgb"]
    assert rgb.shape == (n, 3) and torch.isfinite(rgb).all()
