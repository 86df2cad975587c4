"""ns-viewer on a trained FrugalNeRF run: the page loads, a websocket client that sends a camera receives a
rendered frame, and the process stops by its own handle."""

import asyncio
import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

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


async def receive_frame(port: int, timeout: float = 180.0) -> bytes:
    """Send a viewer camera (viser's message, OpenCV pose) and return the first background image's bytes."""
    import msgspec
    import websockets

    camera = {
        "type": "ViewerCameraMessage", "wxyz": (1.0, 0.0, 0.0, 0.0), "position": (0.0, 0.0, -30.0),
        "fov": 0.9, "aspect": 4 / 3, "look_at": (0.0, 0.0, 0.0), "up_direction": (0.0, -1.0, 0.0),
    }
    async with websockets.connect(f"ws://127.0.0.1:{port}", max_size=None) as ws:
        await ws.send(msgspec.msgpack.encode(camera))
        deadline = time.time() + timeout
        while time.time() < deadline:
            raw = await asyncio.wait_for(ws.recv(), timeout=max(1.0, deadline - time.time()))
            decoded = msgspec.msgpack.decode(raw)
            for message in decoded if isinstance(decoded, list) else [decoded]:
                if isinstance(message, dict) and message.get("type") == "BackgroundImageMessage":
                    return message["rgb_bytes"]
    raise AssertionError("the viewer sent no rendered frame")


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
        frame = asyncio.run(receive_frame(port))
        assert frame[:3] == JPEG or frame[:4] == PNG
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
