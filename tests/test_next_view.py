"""``frugalnerf-next-view`` on a trained run: where it points, what it writes, and one line on bad input."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
import torch
import yaml


@pytest.fixture(scope="module")
def suggested(trained_run):
    """The tool run once on the session's trained run (the procedural scene: 3 photos on an 80-degree arc)."""
    from frugalnerf_ns.tools.next_view import load_pipeline, suggest

    _, run_dir = trained_run
    config = run_dir / "config.yml"
    pipeline = load_pipeline(config)
    lines = []
    record = suggest(config, count=3, viewer_copy=False, pipeline=pipeline, print_fn=lines.append)
    return pipeline, run_dir, record, lines


def test_the_suggestion_points_into_the_gap_and_a_duplicate_of_a_photo_ranks_last(suggested):
    from frugalnerf_ns.geometry.viewpoints import angle_difference, candidate_poses, subject_frame
    from frugalnerf_ns.scoring.next_view import SCORES
    from frugalnerf_ns.tools.next_view import Scorer

    pipeline, _, record, _ = suggested
    assert record["layout"] == "ring" and record["score"] == "largest_gap"  # the measured default around a subject
    photos = pipeline.datamanager.train_dataset.cameras.camera_to_worlds.cpu()
    frame = subject_frame(photos, pipeline.datamanager.scene_layout.focus)
    photo_azimuths = frame.azimuths(photos[:, :3, 3])
    best = torch.tensor(record["suggestions"][0]["camera_to_world"])
    away = angle_difference(frame.azimuths(best[None, :3, 3]), photo_azimuths).abs().min()
    assert float(away) >= 130.0  # the photos span 80 degrees; the middle of the other 280 is 140 from the nearest
    assert record["suggestions"][0]["signals"]["separation"] == pytest.approx(float(away) / 180.0, abs=1e-4)
    # The render-based score too sends the photo into the gap, and a duplicate of a photo ranks last by it.
    scorer = Scorer(pipeline)
    score = SCORES["unseen_or_single"]
    duplicate = score(scorer.render_signals(photos[1])[0].summary())  # the middle photo's own viewpoint
    poses = candidate_poses(photos, False, frame).camera_to_worlds
    ring = [score(scorer.render_signals(pose)[0].summary()) for pose in poses]
    # Last: the ring's candidate at the photo's own azimuth is the same viewpoint up to rounding (~0.001 apart).
    assert duplicate <= min(ring) + 0.005 and duplicate < 0.5 * sorted(ring)[len(ring) // 2]
    top = poses[max(range(len(ring)), key=ring.__getitem__)]
    assert float(angle_difference(frame.azimuths(top[None, :3, 3]), photo_azimuths).abs().min()) >= 40.0


def test_it_writes_the_json_the_camera_path_and_the_picture(suggested):
    from nerfstudio.cameras.camera_paths import get_path_from_json
    from PIL import Image

    pipeline, run_dir, record, lines = suggested
    saved = json.loads((run_dir / "next_view.json").read_text())
    assert [s["rank"] for s in saved["suggestions"]] == [1, 2, 3]
    scores = [s["score"] for s in saved["suggestions"]]
    assert scores == sorted(scores, reverse=True)
    assert all(s["description"].count("photo") >= 1 for s in saved["suggestions"])
    assert saved["largest_gap"]["degrees"] == pytest.approx(280.0, abs=2.0)
    # The data's own frame: nerfstudio-format data is only scaled/oriented by the parser; mapping back and forth agrees.
    outputs = pipeline.datamanager.train_dataparser_outputs
    data_pose = torch.tensor(saved["suggestions"][0]["camera_to_world_data_frame"])
    photo_data = outputs.transform_poses_to_original_space(outputs.cameras.camera_to_worlds, camera_convention="opengl")
    model_scale = float(torch.cdist(outputs.cameras.camera_to_worlds[:, :3, 3], outputs.cameras.camera_to_worlds[:, :3, 3]).max())
    data_scale = float(torch.cdist(photo_data[:, :3, 3], photo_data[:, :3, 3]).max())
    assert data_scale / model_scale == pytest.approx(1.0 / outputs.dataparser_scale, rel=1e-4)
    assert data_pose.shape == (3, 4)
    # ns-render camera-path reads the path: one camera per suggestion, at the suggested poses.
    path = json.loads((run_dir / "next_view_camera_path.json").read_text())
    cameras = get_path_from_json(path)
    assert len(cameras) == 3
    assert torch.allclose(cameras.camera_to_worlds[0], torch.tensor(record["suggestions"][0]["camera_to_world"]), atol=1e-5)
    assert len(path["keyframes"]) == 3 and len(path["keyframes"][0]["matrix"]) == 16  # the viewer's render panel
    with Image.open(run_dir / "next_view.png") as picture:
        width, height = picture.size
    assert width > 2 * 60 and height > 3 * 45  # three rows of render + map
    assert len(lines) == 1 and lines[0].startswith("frugalnerf: next photo: ")


def test_the_viewer_copy_lands_in_the_data_folders_camera_paths(suggested, tmp_path):
    from frugalnerf_ns.tools.next_view import suggest

    pipeline, run_dir, _, _ = suggested
    data = Path(pipeline.datamanager.config.dataparser.data)
    lines = []
    suggest(run_dir / "config.yml", count=1, viewer_copy=True, pipeline=pipeline, print_fn=lines.append)
    copied = data / "camera_paths" / "next_view.json"
    assert copied.is_file() and json.loads(copied.read_text())["keyframes"]
    assert str(copied) in lines[0]


def test_a_run_without_checkpoints_gets_one_line(trained_run, tmp_path):
    from frugalnerf_ns.tools.next_view import main

    _, run_dir = trained_run
    bare = tmp_path / "bare"
    bare.mkdir()
    shutil.copy(run_dir / "config.yml", bare / "config.yml")
    with pytest.raises(SystemExit) as stopped:
        main(["--load-config", str(bare / "config.yml"), "--no-viewer-copy"])
    message = str(stopped.value.code)
    assert message.startswith("frugalnerf: error: ") and "no checkpoint" in message and "\n" not in message
    with pytest.raises(SystemExit) as missing:
        main(["--load-config", str(tmp_path / "nothing" / "config.yml")])
    assert "is not a run's config.yml" in str(missing.value.code)


def test_a_run_whose_cameras_cannot_be_read_gets_one_line(trained_run, procedural_scene, tmp_path):
    from frugalnerf_ns.tools.next_view import main

    _, run_dir = trained_run
    scene = tmp_path / "scene"
    shutil.copytree(procedural_scene, scene)
    (scene / "transforms.json").write_text("{ not json")
    config = yaml.load((run_dir / "config.yml").read_text(), Loader=yaml.Loader)
    config.output_dir = tmp_path / "outputs"
    config.pipeline.datamanager.data = scene
    config.pipeline.datamanager.dataparser.data = scene
    copy = config.get_base_dir()
    shutil.copytree(run_dir, copy, ignore=shutil.ignore_patterns("next_view*"))
    config.save_config()  # the copy's config.yml names the broken scene
    with pytest.raises(SystemExit) as stopped:
        main(["--load-config", str(copy / "config.yml"), "--no-viewer-copy"])
    message = str(stopped.value.code)
    assert message.startswith("frugalnerf: error: ") and "transforms.json" in message and "\n" not in message


def test_the_benchmark_times_the_command_and_the_start_up_line(trained_run, tmp_path, capsys):
    from frugalnerf_ns.bench.next_view import main

    _, run_dir = trained_run
    out = tmp_path / "bench.json"
    rows = main([str(run_dir / "config.yml"), "--repeats", "1", "--out", str(out)])
    saved = json.loads(out.read_text())
    assert [row["what"] for row in saved["rows"]] == [row["what"] for row in rows] and len(rows) == 3
    assert all(row["seconds"] > 0 for row in rows) and saved["coverage_line"].startswith("3 photos over 80 degrees")
    assert "frugalnerf-next-view in all" in capsys.readouterr().out
