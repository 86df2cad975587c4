"""Runs trained before the package had rooms (issue 30) still load: their config.yml names the flat modules
(``frugalnerf_ns.trainer.FrugalTrainerConfig``, ``frugalnerf_ns.model.FrugalNeRFModel``, ...). The files in
``tests/data/before_rooms`` were written by the code of that time (commit cbedf10): the ``frugalnerf-tiny``
preset's config.yml, and every dataparser's config as ``ns-train`` would save it."""

import importlib
import re
import shutil
from pathlib import Path

import yaml

BEFORE = Path(__file__).resolve().parent / "data" / "before_rooms"
TAG = re.compile(r"!!python/(?:object|name):(frugalnerf_ns[\w.]*)")


def resolve(path: str):
    """What PyYAML's loader does with a tag's ``module.name``."""
    module, _, name = path.rpartition(".")
    return getattr(importlib.import_module(module), name)


def old_to_new(text: str) -> dict:
    """{old class path: today's class path} for every package class the old file names."""
    found = {}
    for old in sorted(set(TAG.findall(text))):
        obj = resolve(old)
        found[old] = f"{obj.__module__}.{obj.__qualname__}"
    return found


def test_the_old_files_name_the_flat_modules_and_every_name_resolves_to_todays_class():
    from frugalnerf_ns.data.dataparsers.llff import LLFFDataParserConfig
    from frugalnerf_ns.data.datamanager import FrugalDataManagerConfig
    from frugalnerf_ns.model.frugalnerf import FrugalNeRFModel
    from frugalnerf_ns.run.trainer import FrugalTrainerConfig

    config = yaml.load((BEFORE / "config.yml").read_text(), Loader=yaml.Loader)
    assert type(config) is FrugalTrainerConfig
    assert type(config.pipeline.datamanager) is FrugalDataManagerConfig
    assert config.pipeline.model._target is FrugalNeRFModel
    parsers = yaml.load((BEFORE / "dataparsers.yml").read_text(), Loader=yaml.Loader)
    assert type(parsers["frugal_llff"]) is LLFFDataParserConfig  # an old package's child: one module, one class
    moved = old_to_new((BEFORE / "config.yml").read_text() + (BEFORE / "dataparsers.yml").read_text())
    assert len(moved) >= 25
    assert all(old != new for old, new in moved.items()), "an old file names today's paths: not a test of old names"


def test_a_run_saved_before_the_rooms_evaluates_and_resumes(trained_run, tmp_path):
    from nerfstudio.utils.eval_utils import eval_setup

    from frugalnerf_ns.run.pipeline import FrugalPipeline
    from tests.training_helpers import train

    _, run_dir = trained_run
    config = yaml.load((run_dir / "config.yml").read_text(), Loader=yaml.Loader)
    config.output_dir = tmp_path / "old"
    copy = config.get_base_dir()
    shutil.copytree(run_dir, copy)
    config.save_config()
    # Today's config.yml, written back with the class paths of the time before the rooms.
    text = (copy / "config.yml").read_text()
    for old, new in old_to_new((BEFORE / "config.yml").read_text()).items():
        text = text.replace(f":{new} ", f":{old} ").replace(f":{new}\n", f":{old}\n")
    # Fields added since (the photos' pose options of frugal-auto) were not in those files: dropped, so the run
    # must also load without them.
    text, dropped = re.subn(r"\n( +)poses: !!python/object:frugalnerf_ns\.data\.photo_poses\.PoseEstimationOptions\n(?:\1 +.*\n)*",
                            "\n", text)
    assert dropped == 1
    assert not re.search(r"frugalnerf_ns\.(run|data|model|field|geometry|scoring|tools)\.\w+\.", text)
    (copy / "config.yml").write_text(text)

    # ns-eval, ns-render and ns-viewer load a run through eval_setup.
    _, pipeline, checkpoint, step = eval_setup(copy / "config.yml", test_mode="test")
    newest = sorted((copy / "nerfstudio_models").glob("step-*.ckpt"))[-1]
    assert type(pipeline) is FrugalPipeline and checkpoint == newest and step == int(newest.stem.split("-")[1])

    # ns-train --load-config <old config.yml> --load-dir <its checkpoints>: two more steps, saved.
    resumed = yaml.load(text, Loader=yaml.Loader)
    resumed.output_dir = tmp_path / "resumed"
    resumed.load_dir = copy / "nerfstudio_models"
    resumed.max_num_iterations = 2
    resumed.vis = "tensorboard"
    train(resumed)
    assert [p.name for p in (tmp_path / "resumed").rglob("step-*.ckpt")] == [f"step-{step + 2:09d}.ckpt"]
