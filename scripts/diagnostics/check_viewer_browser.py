"""Check the viewer in a real browser: headless Chromium opens ns-viewer's page and saves a screenshot.

  python scripts/diagnostics/check_viewer_browser.py [--load-config <run>/config.yml] [--screenshot viewer.png]

Without --load-config it first trains frugalnerf-tiny on the procedural scene (a few minutes on a CPU).
Chromium comes from Debian (``apt-get install chromium``, run by this script when it is missing). The
browser is driven over the Chrome DevTools Protocol: the page loads, the viewer's client sends its camera,
the server renders, and once the canvas shows the render the screenshot is saved. Exits non-zero when the
page shows no rendered image within the time limit.
"""

from __future__ import annotations

import argparse
import asyncio
import base64
import io
import json
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import time
import urllib.request
from pathlib import Path
from typing import Optional

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
BIN = Path(sys.executable).parent


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def find_or_install_chromium() -> str:
    for name in ("chromium", "chromium-browser", "google-chrome"):
        if shutil.which(name):
            return shutil.which(name)  # type: ignore[return-value]
    print("check_viewer_browser: installing Debian's chromium with apt-get ...", flush=True)
    sudo = [] if os.geteuid() == 0 else ["sudo"]
    env = {**os.environ, "DEBIAN_FRONTEND": "noninteractive"}
    subprocess.run([*sudo, "apt-get", "update", "-q"], check=False, env=env)
    result = subprocess.run([*sudo, "apt-get", "install", "-y", "-q", "chromium"], env=env)
    if result.returncode != 0 or not shutil.which("chromium"):
        sys.exit("check_viewer_browser: error: could not install chromium with apt-get")
    return shutil.which("chromium")  # type: ignore[return-value]


def train_tiny_run(workdir: Path) -> Path:
    from frugalnerf_ns.tools.demo import train_and_eval
    from frugalnerf_ns.data.procedural_scene import write_procedural_scene

    scene = write_procedural_scene(workdir / "scene")
    results = train_and_eval(scene, workdir / "outputs")
    return Path(results["run_dir"]) / "config.yml"


def wait_http(url: str, timeout: float, process: Optional[subprocess.Popen] = None) -> bytes:
    deadline = time.time() + timeout
    while time.time() < deadline:
        if process is not None and process.poll() is not None:
            sys.exit(f"check_viewer_browser: error: {url}: the server exited early")
        try:
            with urllib.request.urlopen(url, timeout=5) as response:
                return response.read()
        except OSError:
            time.sleep(1.0)
    sys.exit(f"check_viewer_browser: error: nothing answered at {url} within {timeout:.0f} s")


def rendered_fraction(png: bytes) -> float:
    """Share of the canvas (left 60 % of the page; the control panel is on the right) whose pixels differ
    from the canvas's most common colour: the blank viewer is one flat colour plus a grid."""
    from PIL import Image

    image = np.asarray(Image.open(io.BytesIO(png)).convert("RGB"), dtype=np.int32)
    canvas = image[:, : int(image.shape[1] * 0.6)]
    flat = canvas.reshape(-1, 3)
    colours, counts = np.unique(flat // 8, axis=0, return_counts=True)
    background = colours[counts.argmax()] * 8 + 4
    differs = np.abs(flat - background).sum(axis=1) > 40
    # Colourful pixels (the scene), not the grey grid lines.
    saturated = (flat.max(axis=1) - flat.min(axis=1)) > 40
    return float((differs & saturated).mean())


async def screenshot_when_rendered(
    devtools_port: int, url: str, timeout: float, min_fraction: float, settle: float
) -> tuple:
    import websockets

    targets = json.loads(wait_http(f"http://127.0.0.1:{devtools_port}/json", 60))
    page = next(t for t in targets if t.get("type") == "page")
    async with websockets.connect(page["webSocketDebuggerUrl"], max_size=None) as ws:
        ids = iter(range(1, 1_000_000))

        async def call(method: str, **params):
            message_id = next(ids)
            await ws.send(json.dumps({"id": message_id, "method": method, "params": params}))
            while True:
                reply = json.loads(await ws.recv())
                if reply.get("id") == message_id:
                    return reply.get("result", {})

        await call("Emulation.setDeviceMetricsOverride", width=1280, height=800, deviceScaleFactor=1, mobile=False)
        await call("Page.navigate", url=url)
        deadline = time.time() + timeout
        png, fraction = b"", 0.0
        while time.time() < deadline:
            await asyncio.sleep(3.0)
            png = base64.b64decode((await call("Page.captureScreenshot", format="png"))["data"])
            fraction = rendered_fraction(png)
            if fraction >= min_fraction:
                # The first frames are low-resolution previews; the viewer refines once the camera rests.
                await asyncio.sleep(settle)
                png = base64.b64decode((await call("Page.captureScreenshot", format="png"))["data"])
                fraction = rendered_fraction(png)
                break
        return png, fraction


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--load-config", type=Path, default=None, help="config.yml of a trained run")
    parser.add_argument("--screenshot", type=Path, default=Path("outputs/viewer-screenshot.png"))
    parser.add_argument("--timeout", type=float, default=240.0, help="seconds to wait for a rendered image")
    parser.add_argument("--min-fraction", type=float, default=0.02, help="share of the canvas the render must cover")
    parser.add_argument("--settle", type=float, default=20.0, help="seconds to let the render refine before the shot")
    args = parser.parse_args(argv)

    chromium = find_or_install_chromium()
    config = args.load_config or train_tiny_run(Path(tempfile.mkdtemp(prefix="frugalnerf-viewer-")))
    if not config.is_file():
        sys.exit(f"check_viewer_browser: error: {config} is not a file")
    port, devtools = free_port(), free_port()
    viewer = subprocess.Popen(
        [str(BIN / "ns-viewer"), "--load-config", str(config), "--viewer.websocket-port", str(port),
         "--viewer.websocket-host", "127.0.0.1"],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
    )
    browser = None
    try:
        wait_http(f"http://127.0.0.1:{port}/", 240, viewer)
        profile = tempfile.mkdtemp(prefix="frugalnerf-chromium-")
        browser = subprocess.Popen(
            [chromium, "--headless=new", "--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
             "--ignore-gpu-blocklist", f"--remote-debugging-port={devtools}", f"--user-data-dir={profile}",
             "--no-first-run", "about:blank"],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
        )
        png, fraction = asyncio.run(
            screenshot_when_rendered(devtools, f"http://127.0.0.1:{port}/", args.timeout, args.min_fraction, args.settle)
        )
    finally:
        for process in (browser, viewer):
            if process is not None:
                process.terminate()
                try:
                    process.wait(timeout=20)
                except subprocess.TimeoutExpired:
                    process.kill()
    args.screenshot.parent.mkdir(parents=True, exist_ok=True)
    args.screenshot.write_bytes(png)
    print(f"check_viewer_browser: screenshot {args.screenshot.resolve()} (rendered share of the canvas {fraction:.3f})")
    if fraction < args.min_fraction:
        print("check_viewer_browser: error: the page shows no rendered image", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
