"""ns-viewer on a trained FrugalNeRF run: the page loads, a websocket client that sends a camera receives a
rendered frame, and the process stops by its own handle."""

import asyncio
import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path
from typing import List, Tuple

import pytest

BIN = Path(sys.executable).parent
JPEG, PNG = b"\xff\xd8\xff", b"\x89PNG"


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def wait_for_page(url: str, process: subprocess.Popen, timeout: float = 240.0) -> bytes:
    deadline = time.time() + timeout
    while time.time() < deadline:
        if process.poll() is not None:
            raise AssertionError(f"ns-viewer exited early: {process.stdout.read()[-3000:]}")
        try:
            with urllib.request.urlopen(url, timeout=5) as response:
                if response.status == 200:
                    return response.read()
        except OSError:
            time.sleep(1.0)
    raise AssertionError(f"no page at {url} after {timeout} s")


async def receive_frame(port: int, timeout: float = 180.0) -> Tuple[bytes, List[str], List[str]]:
    """Send a viewer camera (viser's message, OpenCV pose); return the first background image's bytes, the
    "Output type" dropdown's options once the viewer has set them from the model's outputs, and the labels
    of the checkboxes the viewer shows."""
    import msgspec
    import websockets

    camera = {
        "type": "ViewerCameraMessage", "wxyz": (1.0, 0.0, 0.0, 0.0), "position": (0.0, 0.0, -30.0),
        "fov": 0.9, "aspect": 4 / 3, "look_at": (0.0, 0.0, 0.0), "up_direction": (0.0, -1.0, 0.0),
    }
    frame, options, checkboxes, dropdown = None, [], [], None
    async with websockets.connect(f"ws://127.0.0.1:{port}", max_size=None) as ws:
        await ws.send(msgspec.msgpack.encode(camera))
        deadline = time.time() + timeout
        while time.time() < deadline and (frame is None or not options):
            raw = await asyncio.wait_for(ws.recv(), timeout=max(1.0, deadline - time.time()))
            decoded = msgspec.msgpack.decode(raw)
            for message in decoded if isinstance(decoded, list) else [decoded]:
                if not isinstance(message, dict):
                    continue
                kind = message.get("type")
                if kind == "BackgroundImageMessage" and frame is None:
                    frame = message["rgb_bytes"]
                elif kind == "GuiAddDropdownMessage" and message.get("label") == "Output type":
                    dropdown = message["id"]
                elif kind == "GuiAddCheckboxMessage":
                    checkboxes.append(message["label"])
                elif kind == "GuiUpdateMessage" and message.get("id") == dropdown:
                    options = list(message["updates"].get("options", options))
    if frame is None:
        raise AssertionError("the viewer sent no rendered frame")
    return frame, options, checkboxes


# The real ns-viewer in a child process (~20 s); test_viewer_outputs_offer_every_scale_... renders in this process.
@pytest.mark.e2e
def test_viewer_serves_the_page_and_renders_a_frame_for_a_websocket_client(trained_run):
    _, run_dir = trained_run
    port = free_port()
    process = subprocess.Popen(
        [str(BIN / "ns-viewer"), "--load-config", str(run_dir / "config.yml"), "--viewer.websocket-port", str(port),
         "--viewer.websocket-host", "127.0.0.1"],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )
    try:
        page = wait_for_page(f"http://127.0.0.1:{port}/", process)
        assert b"<html" in page.lower() or b"<!doctype html" in page.lower()
        frame, options, checkboxes = asyncio.run(receive_frame(port))
        assert frame[:3] == JPEG or frame[:4] == PNG
        # The render dropdown offers what the panel's checkboxes ask for: on a CPU they start off (the full
        # scale only, the fast frame), with CUDA on (every scale's rgb and depth and the pseudo-GT scale map).
        import torch

        lower = ("rgb_scale1", "depth_scale1", "rgb_scale2", "depth_scale2", "pseudo_gt_scale")
        assert {"rgb", "depth"} <= set(options), options
        assert all((name in options) is torch.cuda.is_available() for name in lower), options
        assert {"Render lower scales", "Pseudo-GT scale map"} <= set(checkboxes)
        # A real render of the scene, not a blank frame.
        import io

        import numpy as np
        from PIL import Image

        pixels = np.asarray(Image.open(io.BytesIO(frame)).convert("RGB"), dtype=np.float64)
        assert min(pixels.shape[:2]) >= 64 and pixels.std() > 5.0
    finally:
        process.terminate()
        try:
            process.wait(timeout=30)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait(timeout=30)
    assert process.returncode is not None


def test_without_a_terminal_the_viewer_lets_training_end(monkeypatch):
    """The decision the end-to-end test below checks in a real ns-train: nerfstudio's viewer keeps a finished
    run alive until ctrl+c, which nobody can press without a terminal (CI, nohup, a job queue)."""
    from frugalnerf_ns.run import presets

    class Stdin:
        def __init__(self, tty):
            self.tty = tty

        def isatty(self):
            return self.tty

    for tty, quits in ((False, True), (True, False)):
        monkeypatch.setattr(presets.sys, "stdin", Stdin(tty))
        assert presets.build_trainer_config("frugalnerf-tiny").viewer.quit_on_train_completion is quits
    monkeypatch.setattr(presets.sys, "stdin", None)
    assert presets.build_trainer_config("frugalnerf-tiny").viewer.quit_on_train_completion is True


@pytest.mark.e2e
def test_training_with_the_viewer_exits_when_run_without_a_terminal(procedural_scene, tmp_path):
    """ns-train's default viewer waits for ctrl+c after training; with no terminal attached it must not."""
    port = free_port()
    result = subprocess.run(
        [str(BIN / "ns-train"), "frugalnerf-tiny", "--data", str(procedural_scene), "--output-dir", str(tmp_path),
         "--vis", "viewer", "--viewer.websocket-port", str(port), "--viewer.websocket-host", "127.0.0.1",
         "--max-num-iterations", "3"],
        stdin=subprocess.DEVNULL, capture_output=True, text=True, timeout=300,
    )
    assert result.returncode == 0, result.stderr[-3000:]
    assert list(tmp_path.rglob("step-*.ckpt"))


def test_viewer_outputs_offer_every_scale_and_the_pseudo_gt_scale_map(trained_run):
    import torch
    from nerfstudio.utils.eval_utils import eval_setup

    from frugalnerf_ns.model.geometric_adaptation import LEFT_OUT_COLOR, SCALE_CHOICE_COLORS

    _, run_dir = trained_run
    _, pipeline, _, _ = eval_setup(run_dir / "config.yml", test_mode="test")  # what ns-viewer loads
    model = pipeline.model
    assert model.reference_views is not None
    # The panel's checkboxes start on only where CUDA is (on a CPU the lower scales cost most of a frame).
    assert model.viewer_lower_scales.value is model.viewer_scale_map.value is torch.cuda.is_available()
    with torch.no_grad():  # without a viewer attached (ns-eval) the map is not rendered
        assert "pseudo_gt_scale" not in model.get_outputs_for_camera(pipeline.datamanager.eval_dataset.cameras[0:1])
    model.render_scale_map = True
    camera = pipeline.datamanager.eval_dataset.cameras[0:1]
    with torch.no_grad():
        outputs = model.get_outputs_for_camera(camera)
    height, width = int(camera.height), int(camera.width)
    for name in ("rgb", "depth", "rgb_scale1", "depth_scale1", "rgb_scale2", "depth_scale2", "pseudo_gt_scale"):
        assert outputs[name].shape[:2] == (height, width), name
    colors = outputs["pseudo_gt_scale"].reshape(-1, 1, 3)
    palette = torch.tensor((LEFT_OUT_COLOR,) + SCALE_CHOICE_COLORS[:3])
    index = (colors - palette[None]).abs().sum(-1).argmin(-1)
    assert torch.allclose(colors[:, 0], palette[index])  # every pixel is a palette colour
    # A trained model's depths explain the nearest training view for most pixels, at more than one scale.
    fraction = torch.bincount(index, minlength=4).float() / len(index)
    assert fraction[0] < 0.5 and (fraction[1:] > 0.02).sum() >= 2

    # Map off; then the viewer panel's "Render lower scales" off: full scale only (faster).
    model.render_scale_map = False
    with torch.no_grad():
        assert "pseudo_gt_scale" not in model.get_outputs_for_camera(camera)
    model.viewer_lower_scales.value = False
    with torch.no_grad():
        assert sorted(model.get_outputs_for_camera(camera)) == ["accumulation", "depth", "rgb"]


def test_viewer_benchmark_script_times_every_render_mode(trained_run, tmp_path, capsys):
    import json

    from frugalnerf_ns.bench import viewer as script

    _, run_dir = trained_run
    out = tmp_path / "viewer.json"
    script.main([str(run_dir / "config.yml"), "--max-res", "64", "--repeats", "1", "--out", str(out)])
    rows = json.loads(out.read_text())
    assert [row["mode"] for row in rows] == ["all scales + scale map", "all scales", "full scale only"]
    for row in rows:
        assert row["frame"] == "64x48" and row["frame_seconds"] > 0 and row["rays_per_second"] > 0
        width, height = map(int, row["preview"].split("x"))
        assert height >= 30 and abs(width / height - 4 / 3) < 0.1
    assert "| full scale only | 64x48 |" in capsys.readouterr().out
    with pytest.raises(SystemExit) as missing:
        script.main([str(tmp_path / "nope.yml")])
    assert missing.value.code == 2 and "no config at" in capsys.readouterr().err
