"""nerfstudio's render tools on a trained FrugalNeRF run: ns-render spiral / interpolate / dataset / camera-path
and the one-line spiral script, with no ffmpeg on the system PATH. The real ns-render binary runs once;
ns-export and the other renders call nerfstudio's own classes in this process."""

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from tests.helpers import load_script

BIN = Path(sys.executable).parent
ROOT = Path(__file__).resolve().parents[1]


def no_system_ffmpeg_env():
    """A PATH that finds no program at all (so no system ffmpeg, and not the venv's link setup_venv.sh
    made): the tools run by absolute path and must bring their own ffmpeg."""
    return {**os.environ, "PATH": str(ROOT / "no-programs-here"), "PYTHONWARNINGS": "ignore"}


def run(cmd, timeout=600):
    result = subprocess.run([str(c) for c in cmd], capture_output=True, text=True, timeout=timeout, env=no_system_ffmpeg_env())
    assert result.returncode == 0, (result.stdout[-2000:], result.stderr[-3000:])
    return result


def video_frames(path):
    """(frame count, width, height) read back from the file."""
    import av

    with av.open(str(path)) as container:
        frames = [frame for frame in container.decode(video=0)]
    return len(frames), frames[0].width, frames[0].height


def camera_size(scene):
    transforms = json.loads((scene / "transforms.json").read_text())
    return int(transforms["w"]), int(transforms["h"])


@pytest.fixture
def bundled_ffmpeg_only(monkeypatch):
    """In this process, what a video command gets from the plugin: the bundled ffmpeg, none from the system."""
    from nerfstudio.scripts import render  # noqa: F401  (imported as ns-render does, before any pipeline)

    from frugalnerf_ns.ffmpeg_path import provide_ffmpeg

    monkeypatch.setenv("PATH", str(ROOT / "no-programs-here"))  # restored after the test
    assert provide_ffmpeg() is not None


# The real ns-render binary (~19 s); test_render_spiral_script_prints_where_the_video_is renders a spiral with the
# bundled ffmpeg in this process.
@pytest.mark.e2e
def test_ns_render_spiral_without_a_system_ffmpeg(trained_run, procedural_scene, tmp_path):
    _, run_dir = trained_run
    config = run_dir / "config.yml"
    width, height = camera_size(procedural_scene)
    spiral = tmp_path / "spiral.mp4"
    result = run([BIN / "ns-render", "spiral", "--load-config", config, "--output-path", spiral, "--seconds", "1", "--frame-rate", "6"])
    assert video_frames(spiral) == (6, width, height)
    # The real ns-render used the scene's path (video.py) and printed progress lines.
    assert "frugalnerf render: spiral of 6 frames" in result.stdout and "frame 6/6" in result.stdout, result.stdout[-2000:]


def test_interpolated_depth_video(trained_run, procedural_scene, tmp_path, bundled_ffmpeg_only):
    from nerfstudio.scripts.render import RenderInterpolated

    _, run_dir = trained_run
    depth = tmp_path / "interp-depth.mp4"
    RenderInterpolated(load_config=run_dir / "config.yml", output_path=depth, interpolation_steps=4, frame_rate=8,
                       rendered_output_names=["depth"]).main()
    # Two evaluation cameras: one transition of 4 steps.
    assert video_frames(depth) == (4, *camera_size(procedural_scene))


def test_render_spiral_script_prints_where_the_video_is(trained_run, procedural_scene, tmp_path, monkeypatch, capsys):
    _, run_dir = trained_run
    monkeypatch.setenv("PATH", str(ROOT / "no-programs-here"))  # the script brings the bundled ffmpeg itself
    out = tmp_path / "one-line.mp4"
    load_script("render_spiral").main([str(run_dir / "config.yml"), "--output", str(out), "--seconds", "0.5",
                                       "--frame-rate", "8"])
    assert f"wrote {out.resolve()}" in capsys.readouterr().out
    width, height = camera_size(procedural_scene)
    assert video_frames(out) == (4, width, height)


def test_render_spiral_script_rejects_a_missing_config(tmp_path):
    with pytest.raises(SystemExit, match="is not a file"):
        load_script("render_spiral").main([str(tmp_path / "nope.yml")])


def test_dataset_render_matches_ns_eval_psnr(trained_run, tmp_path):
    results, run_dir = trained_run
    out = tmp_path / "dataset"
    from nerfstudio.scripts.render import DatasetRender

    DatasetRender(load_config=run_dir / "config.yml", output_path=out, split="test",
                  rendered_output_names=["rgb", "gt-rgb"], image_format="png").main()
    rendered = sorted((out / "test" / "rgb").rglob("*.png"))
    truth = sorted((out / "test" / "gt-rgb").rglob("*.png"))
    assert len(rendered) == len(truth) >= 2

    def load(path):
        image = np.asarray(Image.open(path), dtype=np.float64) / 255.0
        if image.shape[-1] == 4:  # composited on white, as the model's metrics do
            image = image[..., :3] * image[..., 3:] + (1.0 - image[..., 3:])
        return image

    psnrs = [-10 * np.log10(np.mean((load(r) - load(t)) ** 2)) for r, t in zip(rendered, truth)]
    # 8-bit files against ns-eval's float images: the same numbers up to quantisation.
    assert np.mean(psnrs) == pytest.approx(results["psnr"], abs=0.2)


def test_ns_export_pointcloud_writes_a_ply(trained_run, tmp_path):
    """ns-export's own command line and main, in this process (the real binaries' start-up is tested with
    ns-render above; a second nerfstudio import in a child would cost ~20 s for nothing more)."""
    import tyro

    try:
        from nerfstudio.scripts import exporter  # imports open3d
    except OSError as err:
        if "libusb" in str(err):
            pytest.fail("open3d cannot load libusb-1.0.so.0: scripts/setup_venv.sh should have provided it")
        raise

    _, run_dir = trained_run
    out = tmp_path / "pc"
    args = ["pointcloud", "--load-config", str(run_dir / "config.yml"), "--output-dir", str(out),
            "--num-points", "2000", "--normal-method", "open3d"]
    tyro.cli(exporter.Commands, args=args).main()  # what ns-export runs
    header = (out / "point_cloud.ply").read_bytes()[:400].split(b"end_header")[0].decode()
    vertices = int(header.split("element vertex ")[1].split()[0])
    assert vertices >= 1000 and "property uchar red" in header


def test_camera_path_render_of_a_viewer_style_path(trained_run, procedural_scene, tmp_path, bundled_ffmpeg_only):
    """A camera path in the format the viewer saves (4x4 camera-to-world rows, vertical fov in degrees)."""
    import torch
    from nerfstudio.utils.eval_utils import eval_setup

    _, run_dir = trained_run
    _, pipeline, _, _ = eval_setup(run_dir / "config.yml", test_mode="test")
    poses = pipeline.datamanager.train_dataset.cameras.camera_to_worlds[:2]
    frames = []
    for t in torch.linspace(0.0, 1.0, 5):
        c2w = torch.eye(4)
        c2w[:3] = poses[0] * (1 - t) + poses[1] * t  # positions blend; rotations stay near-orthonormal here
        frames.append({"camera_to_world": c2w.flatten().tolist(), "fov": 50.0, "aspect": 4 / 3})
    path = tmp_path / "camera_path.json"
    path.write_text(json.dumps({
        "camera_type": "perspective", "render_height": 48, "render_width": 64, "fps": 5, "seconds": 1.0,
        "camera_path": frames,
    }))
    video = tmp_path / "path.mp4"
    from nerfstudio.scripts.render import RenderCameraPath

    RenderCameraPath(load_config=run_dir / "config.yml", camera_path_filename=path, output_path=video).main()
    assert video_frames(video) == (5, 64, 48)
