"""An ``ffmpeg`` for nerfstudio's video writing on machines that have none, without trusting shared folders.

``ns-render`` checks ``shutil.which("ffmpeg")``, runs some ``ffmpeg`` commands through the shell, and writes
videos with mediapy, which runs the ffmpeg its config names. imageio-ffmpeg (a dependency) ships a static
binary under a versioned name. Only in a command that writes video (``ns-render``, or a script that calls
``provide_ffmpeg``), and only when PATH finds no ffmpeg:
- mediapy is pointed at the binary by its absolute path;
- a new private folder (``tempfile.mkdtemp``: a fresh unique name, mode 0700, owned by this user, removed at
  exit) gets an ``ffmpeg`` link to it and is appended to the END of this process's PATH, so it can only add
  ``ffmpeg`` and never shadows a program PATH already finds.
No folder is reused, none with a predictable name is created, and other commands' PATH is left alone.
"""

from __future__ import annotations

import atexit
import os
import shutil
import sys
import tempfile
from pathlib import Path
from typing import Optional

# Console scripts (and module files run as scripts) that write videos.
VIDEO_COMMANDS = frozenset({"ns-render", "render.py"})


def bundled_ffmpeg() -> Optional[Path]:
    """Absolute path of imageio-ffmpeg's static ffmpeg, or None when it is not installed."""
    try:
        import imageio_ffmpeg

        return Path(imageio_ffmpeg.get_ffmpeg_exe()).resolve()
    except Exception:  # noqa: BLE001 - no bundled binary: nerfstudio's own message will say so
        return None


def provide_ffmpeg() -> Optional[str]:
    """Path of the ffmpeg that PATH now finds (adding the bundled one as described above), or None."""
    found = shutil.which("ffmpeg")
    if found:
        return found
    binary = bundled_ffmpeg()
    if binary is None:
        return None
    try:
        import mediapy

        mediapy.set_ffmpeg(str(binary))
    except ImportError:
        pass
    folder = Path(tempfile.mkdtemp(prefix="frugalnerf-ffmpeg-"))
    atexit.register(shutil.rmtree, folder, ignore_errors=True)
    link = folder / "ffmpeg"
    try:
        link.symlink_to(binary)
    except OSError:
        shutil.copy2(binary, link)  # filesystems without symlinks
    path = os.environ.get("PATH", "")
    os.environ["PATH"] = f"{path}{os.pathsep}{folder}" if path else str(folder)
    return shutil.which("ffmpeg")


def provide_ffmpeg_for_video_commands(argv0: Optional[str] = None) -> Optional[str]:
    """``provide_ffmpeg`` when this process is a command that writes video; otherwise nothing changes."""
    name = Path(argv0 if argv0 is not None else (sys.argv[0] if sys.argv else "")).name
    return provide_ffmpeg() if name in VIDEO_COMMANDS else None
