"""Make an ``ffmpeg`` visible to nerfstudio's video tools on machines that have none.

``ns-render`` checks ``shutil.which("ffmpeg")`` and mediapy runs ``ffmpeg`` from PATH. imageio-ffmpeg (a
dependency) ships a static binary under a versioned name; when PATH has no ffmpeg, importing the plugin
(which every nerfstudio command does while reading a FrugalNeRF config) links that binary as ``ffmpeg`` in
a private folder and puts the folder on this process's PATH.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path
from typing import Optional


def ensure_ffmpeg_on_path() -> Optional[str]:
    """Path of the ffmpeg that PATH now finds, or None when there is none to offer."""
    found = shutil.which("ffmpeg")
    if found:
        return found
    try:
        import imageio_ffmpeg

        binary = Path(imageio_ffmpeg.get_ffmpeg_exe())
    except Exception:  # noqa: BLE001 - no bundled binary either: nerfstudio's own message will say so
        return None
    folder = Path(tempfile.gettempdir()) / f"frugalnerf-ffmpeg-{os.getuid() if hasattr(os, 'getuid') else 'user'}"
    link = folder / "ffmpeg"
    try:
        folder.mkdir(parents=True, exist_ok=True)
        if not link.exists():
            try:
                link.symlink_to(binary)
            except OSError:
                shutil.copy2(binary, link)  # filesystems without symlinks
    except OSError:
        return None
    os.environ["PATH"] = f"{folder}{os.pathsep}{os.environ.get('PATH', '')}"
    return shutil.which("ffmpeg")
