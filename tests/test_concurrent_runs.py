"""Two runs on one scene at once: cache files written by one process are never seen half-written by another, both
estimates of a photo folder's cameras succeed, and two ns-train started in the same second get their own folders."""

import multiprocessing
import subprocess
import sys
from datetime import datetime
from pathlib import Path

import numpy as np
import pytest
import torch

from frugalnerf_ns.cache import load_keyed_arrays, save_keyed_arrays, write_atomically
from frugalnerf_ns.run import trainer as trainer_module
from frugalnerf_ns.run.presets import build_trainer_config
from tests.photo_scene import TRUE, write_photos

WRITES = 60
SIZE = 400_000  # ~1.6 MB per file: a write takes long enough for two writers to overlap


def _write_many(path: str, value: int, start) -> None:
    start.wait()  # both writers and the reader begin together
    for _ in range(WRITES):
        save_keyed_arrays(Path(path), f"key-{value}", values=np.full(SIZE, value, np.float32))


def test_two_writers_of_one_cache_file_never_show_a_reader_a_part(tmp_path):
    path = tmp_path / "cache" / "sparse_depth_0-1_64x48.npz"
    context = multiprocessing.get_context("spawn")
    start = context.Barrier(3)
    writers = [context.Process(target=_write_many, args=(str(path), value, start)) for value in (1, 2)]
    for writer in writers:
        writer.start()
    start.wait(timeout=120)
    reads = 0
    while any(w.is_alive() for w in writers):
        for value in (1, 2):
            arrays, why = load_keyed_arrays(path, f"key-{value}")
            # Missing (not written yet) or the other writer's key are fine; a part of a file never is.
            assert "corrupt" not in why
            if arrays is not None:
                reads += 1
                assert arrays["values"].shape == (SIZE,) and np.all(arrays["values"] == value)
    for writer in writers:
        writer.join()
        assert writer.exitcode == 0  # neither writer's rename failed under the other
    assert reads > 0
    assert sorted(p.name for p in path.parent.iterdir()) == [path.name]  # no staging file left behind


def test_a_failed_write_leaves_the_old_file_and_no_staging_file(tmp_path):
    path = tmp_path / "image.png"
    path.write_bytes(b"old")

    def fails(f):
        f.write(b"half")
        raise OSError("disk full")

    with pytest.raises(OSError, match="disk full"):
        write_atomically(path, fails)
    assert path.read_bytes() == b"old" and sorted(tmp_path.iterdir()) == [path]


_ESTIMATE = """
import sys, torch
from pathlib import Path
from frugalnerf_ns.data.dataparsers.auto import AutoDataParserConfig
outputs = AutoDataParserConfig(data=Path(sys.argv[1]), test_views=(3,)).setup().get_dataparser_outputs("train")
torch.save(outputs.cameras.camera_to_worlds, sys.argv[2])
"""


def test_two_processes_estimate_one_photo_folder_at_once(tmp_path):
    data = write_photos(tmp_path / "scene", TRUE)
    root = Path(__file__).resolve().parents[1]
    runs = [
        subprocess.Popen([sys.executable, "-c", _ESTIMATE, str(data), str(tmp_path / f"c2w_{i}.pt")], cwd=root,
                         stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        for i in range(2)
    ]
    for run in runs:
        out, _ = run.communicate(timeout=300)
        assert run.returncode == 0, out[-2000:]
    first, second = (torch.load(tmp_path / f"c2w_{i}.pt") for i in range(2))
    assert torch.allclose(first, second, atol=1e-5)
    cache = data / "frugalnerf_cache"
    assert len(list(cache.glob("photo_cameras_*.npz"))) == 1
    assert not list(cache.rglob("*.partial"))


class _FixedClock:
    @staticmethod
    def now():
        return datetime(2026, 12, 5, 11, 30, 0)


def test_two_runs_started_in_one_second_get_their_own_folders(tmp_path, monkeypatch):
    monkeypatch.setattr(trainer_module, "datetime", _FixedClock)
    folders = []
    for _ in range(3):
        config = build_trainer_config("frugalnerf-tiny")
        config.output_dir, config.experiment_name = tmp_path, "scene"
        config.set_timestamp()
        folders.append(config.get_base_dir())
    assert [f.name for f in folders] == ["2026-12-05_113000", "2026-12-05_113000_2", "2026-12-05_113000_3"]
    assert all(f.is_dir() for f in folders)
    given = build_trainer_config("frugalnerf-tiny")
    given.output_dir, given.experiment_name, given.timestamp = tmp_path, "scene", "2026-12-05_113000"
    given.set_timestamp()  # a timestamp the user gave is kept
    assert given.get_base_dir() == folders[0]


@pytest.mark.e2e
def test_two_ns_train_on_one_photo_folder_at_once_both_train(tmp_path):
    data = write_photos(tmp_path / "scene", TRUE)
    runs = [
        subprocess.Popen([str(Path(sys.executable).with_name("ns-train")), "frugalnerf-tiny", "--data", str(data), "--output-dir", str(tmp_path / "out"),
                          "--max-num-iterations", "20", "--vis", "tensorboard"],
                         stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        for _ in range(2)
    ]
    for run in runs:
        out, _ = run.communicate(timeout=600)
        assert run.returncode == 0, out[-3000:]
    run_folders = sorted({p.parent.parent for p in (tmp_path / "out").rglob("step-*.ckpt")})
    assert len(run_folders) == 2
    assert not list(data.rglob("*.partial"))
