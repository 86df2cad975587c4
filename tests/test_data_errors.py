"""Bad --data gets one clear line and exit code 1, never a traceback from deep inside nerfstudio/torch."""

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from frugalnerf_ns.data.input_checks import DataError, check_scene_folder
from tests.training_helpers import ns_train_main, preset_config


def ns_train(data: Path, tmp_path: Path) -> subprocess.CompletedProcess:
    exe = Path(sys.executable).parent / "ns-train"
    return subprocess.run(
        [str(exe), "frugalnerf-tiny", "--data", str(data), "--output-dir", str(tmp_path / "out"), "--vis", "tensorboard"],
        capture_output=True,
        text=True,
        timeout=300,
    )


def assert_one_line_error(result: subprocess.CompletedProcess, *needles: str) -> None:
    assert result.returncode == 1, result.stderr[-2000:]
    assert "Traceback" not in result.stderr, result.stderr[-2000:]
    lines = [line for line in result.stderr.splitlines() if line.startswith("frugalnerf: error:")]
    assert len(lines) == 1, result.stderr[-2000:]
    for needle in needles:
        assert needle in lines[0]


def test_missing_folder(tmp_path):
    # The real ns-train binary: exit status 1 and one line on stderr (the other bad-input tests run ns-train's
    # main in this process and read the same line).
    assert_one_line_error(ns_train(tmp_path / "nope", tmp_path), "does not exist", "nope")


def test_single_image(tmp_path, procedural_scene):
    scene = tmp_path / "single"
    shutil.copytree(procedural_scene, scene)
    meta = json.loads((scene / "transforms.json").read_text())
    meta["frames"] = meta["frames"][:1]
    for key in ("train_filenames", "val_filenames", "test_filenames"):
        meta.pop(key, None)
    (scene / "transforms.json").write_text(json.dumps(meta))
    said = ns_train_main(preset_config("frugalnerf-tiny", scene, tmp_path / "out"))
    assert said.startswith("frugalnerf: error:") and "1 image(s)" in said and "at least 2" in said


def _edited_scene(tmp_path, procedural_scene, edit):
    scene = tmp_path / "edited"
    shutil.copytree(procedural_scene, scene)
    meta = json.loads((scene / "transforms.json").read_text())
    edit(scene, meta)
    (scene / "transforms.json").write_text(json.dumps(meta))
    return scene


def test_nan_pose(tmp_path, procedural_scene):
    def edit(scene, meta):
        meta["frames"][2]["transform_matrix"][0][3] = float("nan")

    scene = _edited_scene(tmp_path, procedural_scene, edit)
    with pytest.raises(DataError, match="NaN or inf"):
        check_scene_folder(scene)


def test_wrong_pose_shape(tmp_path, procedural_scene):
    def edit(scene, meta):
        meta["frames"][0]["transform_matrix"] = [[1, 0, 0], [0, 1, 0]]

    with pytest.raises(DataError, match=r"shape \(2, 3\)"):
        check_scene_folder(_edited_scene(tmp_path, procedural_scene, edit))


def test_corrupt_and_missing_images(tmp_path, procedural_scene):
    def corrupt(scene, meta):
        (scene / meta["frames"][1]["file_path"]).write_bytes(b"\x89PNG\r\n\x1a\n garbage")

    with pytest.raises(DataError, match="unreadable or corrupt"):
        check_scene_folder(_edited_scene(tmp_path / "a", procedural_scene, corrupt))

    def missing(scene, meta):
        (scene / meta["frames"][1]["file_path"]).unlink()

    with pytest.raises(DataError, match="not found"):
        check_scene_folder(_edited_scene(tmp_path / "b", procedural_scene, missing))


def test_invalid_json(tmp_path, procedural_scene):
    def edit(scene, meta):
        pass

    scene = _edited_scene(tmp_path, procedural_scene, edit)
    (scene / "transforms.json").write_text("{not json")
    with pytest.raises(DataError, match="not valid JSON"):
        check_scene_folder(scene)


def test_good_scene_passes(procedural_scene):
    assert check_scene_folder(procedural_scene).name == "transforms.json"


def test_data_errors_are_ordinary_exceptions_for_library_callers(tmp_path):
    from frugalnerf_ns.errors import one_line_errors

    try:
        check_scene_folder(tmp_path / "missing")
    except Exception as err:  # noqa: BLE001 - what a library caller writes
        caught = err
    assert isinstance(caught, DataError) and not isinstance(caught, SystemExit)
    assert str(caught) == f"frugalnerf: error: --data {tmp_path / 'missing'} does not exist"
    # At a command boundary the same line becomes the exit message (status 1, no traceback).
    with pytest.raises(SystemExit) as exit_info:
        with one_line_errors():
            check_scene_folder(tmp_path / "missing")
    assert exit_info.value.code == str(caught)
