"""Atomic checkpoints and loading the newest intact one: unit level (no training) and through ns-eval's and
ns-train --load-dir's own code (in-process) on a trained run whose newest checkpoint is cut short."""

import shutil

import pytest
import torch

from frugalnerf_ns.run.checkpoints import (
    STAGING_NAME,
    CheckpointError,
    checkpoints_newest_first,
    newest_intact_checkpoint,
    write_checkpoint,
)
from tests.training_helpers import preset_config, train


def state(step):
    return {"step": step, "pipeline": {"w": torch.full((64, 64), float(step))}, "optimizers": {}, "scalers": {}}


def test_written_checkpoint_replaces_older_ones_only_once_whole(tmp_path):
    folder = tmp_path / "run" / "nerfstudio_models"
    write_checkpoint(state(10), folder / "step-000000010.ckpt", keep_only_this=True)
    write_checkpoint(state(20), folder / "step-000000020.ckpt", keep_only_this=True)
    assert [p.name for p in folder.iterdir()] == ["step-000000020.ckpt"]
    assert not (tmp_path / "run" / STAGING_NAME).exists()
    path, loaded = newest_intact_checkpoint(folder)
    assert path.name == "step-000000020.ckpt" and float(loaded["pipeline"]["w"][0, 0]) == 20.0


def test_a_kill_while_writing_leaves_the_previous_checkpoint_loadable(tmp_path, monkeypatch):
    folder = tmp_path / "run" / "nerfstudio_models"
    write_checkpoint(state(10), folder / "step-000000010.ckpt", keep_only_this=True)
    real_save = torch.save

    def killed_half_way(obj, f, *args, **kwargs):
        f.write(b"PK\x03\x04 partial")  # the start of a zip archive, then the process dies
        raise KeyboardInterrupt  # stands in for SIGKILL / ctrl+c: nothing after this line runs

    monkeypatch.setattr(torch, "save", killed_half_way)
    with pytest.raises(KeyboardInterrupt):
        write_checkpoint(state(20), folder / "step-000000020.ckpt", keep_only_this=True)
    monkeypatch.setattr(torch, "save", real_save)
    # The partial file is outside the checkpoint folder, where nerfstudio's name parsing never sees it.
    assert [p.name for p in folder.iterdir()] == ["step-000000010.ckpt"]
    path, loaded = newest_intact_checkpoint(folder)
    assert path.name == "step-000000010.ckpt" and loaded["step"] == 10


def test_a_full_disk_is_one_line_and_keeps_the_old_checkpoint(tmp_path, monkeypatch):
    folder = tmp_path / "run" / "nerfstudio_models"
    write_checkpoint(state(10), folder / "step-000000010.ckpt", keep_only_this=True)

    def disk_full(obj, f, *args, **kwargs):
        f.write(b"PK\x03\x04")
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(torch, "save", disk_full)
    with pytest.raises(CheckpointError) as err:
        write_checkpoint(state(20), folder / "step-000000020.ckpt", keep_only_this=True)
    message = str(err.value)
    assert message.startswith("frugalnerf: error:") and "step-000000020.ckpt" in message and "No space left" in message
    assert "\n" not in message
    assert [p.name for p in folder.iterdir()] == ["step-000000010.ckpt"]
    assert not (tmp_path / "run" / STAGING_NAME).exists()


@pytest.mark.parametrize("damage", ["truncated", "empty", "garbage"])
def test_newest_unreadable_checkpoint_is_named_and_skipped(tmp_path, damage, capsys):
    folder = tmp_path / "nerfstudio_models"
    write_checkpoint(state(10), folder / "step-000000010.ckpt", keep_only_this=False)
    write_checkpoint(state(20), folder / "step-000000020.ckpt", keep_only_this=False)
    newest = folder / "step-000000020.ckpt"
    data = newest.read_bytes()
    newest.write_bytes({"truncated": data[: len(data) // 2], "empty": b"", "garbage": b"not a checkpoint"}[damage])
    path, loaded = newest_intact_checkpoint(folder)
    assert path.name == "step-000000010.ckpt" and loaded["step"] == 10
    said = capsys.readouterr().out
    assert "step-000000020.ckpt" in said and "unreadable" in said


def test_no_readable_checkpoint_is_one_clear_error(tmp_path):
    folder = tmp_path / "nerfstudio_models"
    folder.mkdir()
    with pytest.raises(CheckpointError, match="holds no checkpoint"):
        newest_intact_checkpoint(folder)
    (folder / "step-000000005.ckpt").write_bytes(b"")
    with pytest.raises(CheckpointError, match="none of the 1 checkpoints"):
        newest_intact_checkpoint(folder)
    with pytest.raises(CheckpointError, match="does not exist"):
        newest_intact_checkpoint(tmp_path / "missing")
    (folder / "notes.txt").write_text("ignored")
    assert [s for s, _ in checkpoints_newest_first(folder)] == [5]


@pytest.fixture(scope="module")
def run_with_cut_checkpoint(trained_run, tmp_path_factory):
    """A copy of the trained run with a newer checkpoint cut short, as a kill during nerfstudio's in-place
    save left it (its name sorts last, so nerfstudio itself would load it)."""
    import yaml

    _, run_dir = trained_run
    config = yaml.load((run_dir / "config.yml").read_text(), Loader=yaml.Loader)
    config.output_dir = tmp_path_factory.mktemp("cut")
    copy = config.get_base_dir()
    shutil.copytree(run_dir, copy)
    config.save_config()  # the copy's config.yml names the copy's folder
    models = copy / "nerfstudio_models"
    intact = sorted(models.glob("step-*.ckpt"))[-1]
    cut = models / "step-000009999.ckpt"
    cut.write_bytes(intact.read_bytes()[: intact.stat().st_size // 3])
    return copy, intact, cut


def test_ns_eval_loads_the_newest_intact_checkpoint(run_with_cut_checkpoint, tmp_path, capsys):
    from nerfstudio.scripts.eval import ComputePSNR

    run_dir, intact, cut = run_with_cut_checkpoint
    out = tmp_path / "eval.json"
    ComputePSNR(load_config=run_dir / "config.yml", output_path=out).main()  # ns-eval's own main, in-process
    captured = capsys.readouterr()
    said = " ".join((captured.out + captured.err).split())
    assert f"{cut.name} is unreadable" in said
    assert out.is_file() and str(intact.name) in said


def test_resume_skips_a_cut_checkpoint(run_with_cut_checkpoint, procedural_scene, tmp_path, capsys):
    run_dir, intact, cut = run_with_cut_checkpoint
    # ns-train --load-dir, in-process: nerfstudio counts --max-num-iterations from the loaded step.
    train(preset_config("frugalnerf-tiny", procedural_scene, tmp_path, load_dir=run_dir / "nerfstudio_models",
                        max_num_iterations=2))
    captured = capsys.readouterr()
    said = " ".join((captured.out + captured.err).split())
    assert f"{cut.name} is unreadable" in said and "Done loading Nerfstudio checkpoint from" in said
    step = int(intact.stem.split("-")[1])
    resumed = sorted(tmp_path.rglob("step-*.ckpt"))
    assert [int(p.stem.split("-")[1]) for p in resumed] == [step + 2]
