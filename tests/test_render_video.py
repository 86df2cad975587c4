"""`ns-render spiral` on a trained FrugalNeRF run: the scene's own path (video.py), full scale only, progress
lines, and frame 0 showing what the nearest training camera shows."""

import os
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from frugalnerf_ns.scoring.metrics import capped_psnr
from frugalnerf_ns.progress import FrameProgress, format_duration
from frugalnerf_ns.tools.video import scene_video_cameras
from frugalnerf_ns.geometry.video_path import roll_degrees, world_up


def test_frame_progress_lines_read_well_in_a_log():
    now = [0.0]
    lines = []
    progress = FrameProgress(10, every_seconds=5.0, write=lines.append, clock=lambda: now[0])
    for _ in range(10):
        now[0] += 2.0
        progress.tick()
    # Frame 1, then every 5 s (frames 4 and 7, at 8 and 14 s), then the last frame.
    assert [line.split("frame ")[1].split(",")[0] for line in lines] == ["1/10", "4/10", "7/10", "10/10"]
    assert lines[1] == "frugalnerf render: frame 4/10, 0.50 fps (2.0 s/frame), elapsed 0m08s, ETA 0m12s"
    assert format_duration(3725) == "1h02m"


def test_ns_render_spiral_renders_the_scene_path_upright_at_full_scale(trained_run, tmp_path, capsys, monkeypatch):
    from nerfstudio.scripts import render  # imported as ns-render does: FrugalPipeline then teaches it
    from nerfstudio.utils.eval_utils import eval_setup

    from frugalnerf_ns.ffmpeg_path import provide_ffmpeg

    monkeypatch.setenv("PATH", os.environ.get("PATH", ""))  # restored after the test
    provide_ffmpeg()  # what the ns-render command gets from the plugin (ns-render checks for ffmpeg first)
    _, run_dir = trained_run
    frames_dir = tmp_path / "spiral"
    render.SpiralRender(
        load_config=run_dir / "config.yml", output_path=frames_dir, seconds=2.0, frame_rate=6,
        output_format="images", image_format="png",
    ).main()
    frames = sorted(frames_dir.glob("*.png"))
    assert len(frames) == 12
    printed = capsys.readouterr().out
    assert "frugalnerf render: spiral of 12 frames" in printed and "frame 12/12" in printed

    _, pipeline, _, _ = eval_setup(run_dir / "config.yml", test_mode="test")
    model, datamanager = pipeline.model, pipeline.datamanager
    start = datamanager.eval_dataset.cameras[0:1]
    path = scene_video_cameras(datamanager, start, 12)
    train = datamanager.train_dataset.cameras
    assert float(roll_degrees(path.camera_to_worlds, world_up(train.camera_to_worlds)).max()) < 1.0
    with torch.no_grad():
        assert sorted(model.get_outputs_for_camera(path[0:1].to(model.device))) == ["accumulation", "depth", "rgb"]

    # Frame 0 against a render from the nearest training camera (same intrinsics as the video).
    nearest = int(torch.cdist(path.camera_to_worlds[:1, :, 3], train.camera_to_worlds[:, :, 3]).argmin())
    reference = path[0:1]
    reference.camera_to_worlds = train.camera_to_worlds[nearest : nearest + 1].clone()
    with torch.no_grad():
        expected = model.get_outputs_for_camera(reference.to(model.device))["rgb"].clamp(0, 1).cpu()
    frame0 = torch.from_numpy(np.asarray(Image.open(frames[0]).convert("RGB"), dtype=np.float32) / 255.0)
    ours = float(capped_psnr(frame0, expected))
    # nerfstudio's own spiral (radius 0.1 around the first test camera, its z axis as up) for comparison.
    theirs_camera = render.get_spiral_path.nerfstudio_original(start, steps=12, radius=0.1)[0:1]
    with torch.no_grad():
        theirs = float(capped_psnr(model.get_outputs_for_camera(theirs_camera.to(model.device))["rgb"].clamp(0, 1).cpu(), expected))
    # Frame 0 is the training camera's position aimed at the cameras' focus point (0.0015 units from its own aim):
    # the same picture up to 8-bit rounding, measured 52 dB on frugalnerf-tiny; nerfstudio's first frame,
    # rolled and beside the first test camera, measured 9 dB. 30 dB separates the two with a wide margin.
    print(f"frame 0 vs the nearest training camera: ours {ours:.1f} dB, nerfstudio spiral {theirs:.1f} dB")
    assert ours > 30.0, (ours, theirs)
    assert theirs < 30.0, (ours, theirs)


def test_render_benchmark_times_every_row_on_one_run(trained_run, tmp_path, capsys, monkeypatch):
    import json

    from frugalnerf_ns.bench import render

    _, run_dir = trained_run
    out = tmp_path / "render.json"
    # --before with this very tree: its marcher loaded from the file, timed beside the imported one.
    tree = Path(render.__file__).resolve().parents[2]
    # The same rows on every CPU: the float32 colour MLP (a CPU with bfloat16 hardware adds a row for it).
    monkeypatch.setattr("frugalnerf_ns.field.radiance_field.native_bfloat16", lambda: False)
    render.main([str(run_dir / "config.yml"), "--frames", "2", "--views", "1", "--out", str(out),
                 "--before", str(tree), "--repeats", "1"])
    records = json.loads(out.read_text())
    # The torch path and the fused kernels alternate first (where Warp compiles: always with the pinned set).
    # The torch path, the kernels on one core (as before they used every core) and the kernels.
    assert [r["row"].split(",")[0] for r in records] == (
        ["test view"] * 3 + ["spiral frame"] * 3
        + ["test view"] * 2 + ["spiral frame", "ns-eval per test view", "offline evaluator per test view"]
        + ["test view"] * 2)
    assert [r["row"].split(", ")[2] for r in records[:6]] == ["torch path", "fused kernels on one core in chunks of "
                                                             "eval_num_rays_per_chunk (before)", "fused kernels"] * 2
    assert records[0]["psnr_warp_vs_torch"] > 50 and records[0]["max_pixel_difference_warp_vs_torch"] < 1 / 255
    assert records[0]["max_pixel_difference_warp_vs_one_core"] < 1 / 255
    assert f"of {tree} (before)" in records[11]["row"] and records[0]["psnr_inference_vs_before"] > 100
    assert all(r["seconds"] > 0 for r in records) and "| test view, inference marcher (now)" in capsys.readouterr().out
    # The two marchers render the same test view (the inference one stops rays once opaque: < 1/255 apart).
    assert records[0]["psnr_inference_vs_training_marcher"] > 50 and records[0]["max_pixel_difference"] < 1 / 255
    with pytest.raises(SystemExit, match="no .*rendering.py"):
        render.main([str(run_dir / "config.yml"), "--before", str(tmp_path)])


# Two child processes each load the run and time steps (~30 s).
@pytest.mark.e2e
def test_step_benchmark_times_this_tree_beside_another_in_child_processes(trained_run, tmp_path, capsys):
    import json

    import torch

    from frugalnerf_ns.bench import step_time

    _, run_dir = trained_run
    out = tmp_path / "step.json"
    # --before with this very tree: both children must import the package from the tree they were given.
    tree = Path(step_time.__file__).resolve().parents[2]
    step_time.main([str(run_dir / "config.yml"), "--before", str(tree), "--torch-path", "--steps", "2", "--warmup", "1",
                    "--rounds", "1", "--out", str(out)])
    rows = json.loads(out.read_text())["rows"]
    checkpoint = torch.load(next((run_dir / "nerfstudio_models").glob("*.ckpt")), map_location="cpu", weights_only=False)
    grid = checkpoint["pipeline"]["_model.field.density_grid.resolution"].tolist()
    assert [r["tree"] for r in rows] == ["before", "now, torch path", "now"] and all(r["path"] == str(tree) for r in rows)
    assert [r["kernels"] for r in rows] == ["auto", "torch", "auto"]  # the run's setting, and the torch path asked for
    assert all(r["grid"] == grid and len(r["round_medians"]) == 1 and r["median_s_per_step"] > 0 for r in rows)
    assert all(r["peak_rss_mib"] > 100 for r in rows) and rows[2]["speedup_of_now"] == 1.0
    assert "| before (" in capsys.readouterr().out


def test_step_benchmark_refuses_a_before_tree_without_the_package(trained_run, tmp_path):
    from frugalnerf_ns.bench import step_time

    _, run_dir = trained_run
    with pytest.raises(SystemExit, match="no frugalnerf_ns package"):
        step_time.main([str(run_dir / "config.yml"), "--before", str(tmp_path)])
