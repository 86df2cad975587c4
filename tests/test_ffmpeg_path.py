"""The bundled ffmpeg is offered only to video commands, from a private folder appended to PATH: nothing
planted in the shared temp folder can run in place of a system program."""

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from frugalnerf_ns.ffmpeg_path import bundled_ffmpeg

PLANTED = "#!/bin/sh\necho planted > {marker}\n"


@pytest.fixture
def planted(tmp_path):
    """A shared temp folder where someone planted ``ls`` and ``ffmpeg`` in the folder name the plugin used
    to trust, plus a dangling ``ffmpeg`` link; and a PATH holding only a real ``ls``."""
    tmpdir = tmp_path / "shared-tmp"
    trap = tmpdir / f"frugalnerf-ffmpeg-{os.getuid()}"
    trap.mkdir(parents=True)
    marker = tmp_path / "planted-program-ran"
    for name in ("ls", "ffmpeg"):
        (trap / name).write_text(PLANTED.format(marker=marker))
        (trap / name).chmod(0o755)
    dangling = tmpdir / "frugalnerf-ffmpeg-other"
    dangling.mkdir()
    (dangling / "ffmpeg").symlink_to(tmp_path / "written-through-the-link")
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    (bin_dir / "ls").symlink_to(shutil.which("ls"))
    env = {"PATH": str(bin_dir), "TMPDIR": str(tmpdir), "HOME": str(tmp_path), "PYTHONWARNINGS": "ignore"}
    return env, marker, bin_dir, tmp_path / "written-through-the-link"


def run_python(code, env):
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=300)
    assert result.returncode == 0, result.stderr[-2000:]
    return result.stdout.strip().splitlines()


def test_importing_the_plugin_changes_no_path_and_runs_nothing_planted(planted):
    env, marker, bin_dir, _ = planted
    out = run_python(
        "import os, shutil, subprocess, frugalnerf_ns; subprocess.run(['ls', '/'], stdout=subprocess.DEVNULL); "
        "print(os.environ['PATH']); print(shutil.which('ffmpeg'))",
        env,
    )
    assert out == [str(bin_dir), "None"]
    assert not marker.exists()


@pytest.mark.skipif(bundled_ffmpeg() is None, reason="imageio-ffmpeg has no binary here")
def test_video_commands_get_the_bundled_ffmpeg_from_a_private_folder_at_the_end_of_path(planted):
    env, marker, bin_dir, link_target = planted
    out = run_python(
        "import os, shutil, subprocess, sys\n"
        "from frugalnerf_ns.ffmpeg_path import provide_ffmpeg_for_video_commands\n"
        "found = provide_ffmpeg_for_video_commands('ns-render')\n"
        "subprocess.run(['ls', '/'], stdout=subprocess.DEVNULL)\n"
        "subprocess.run(['ffmpeg', '-version'], stdout=subprocess.DEVNULL)\n"
        "import mediapy\n"
        "folder = os.path.dirname(found)\n"
        "print(found); print(os.path.realpath(found)); print(os.environ['PATH']); print(oct(os.stat(folder).st_mode & 0o777)); "
        "print(os.stat(folder).st_uid); print(mediapy._config.ffmpeg_name_or_path)",
        env,
    )
    found, real, path, mode, uid, mediapy_ffmpeg = out
    assert real == str(bundled_ffmpeg()) and mediapy_ffmpeg == str(bundled_ffmpeg())
    folder = Path(found).parent
    # Appended after everything the user had, in a fresh folder only this user can write.
    assert path.split(os.pathsep) == [str(bin_dir), str(folder)]
    assert folder.name.startswith("frugalnerf-ffmpeg-") and folder.name != f"frugalnerf-ffmpeg-{os.getuid()}"
    assert mode == "0o700" and int(uid) == os.getuid()
    assert not marker.exists() and not link_target.exists()
    assert not folder.exists()  # removed when the process ended


def test_other_commands_get_nothing(planted, monkeypatch):
    env, _, bin_dir, _ = planted
    from frugalnerf_ns.ffmpeg_path import provide_ffmpeg_for_video_commands

    for name, value in env.items():
        monkeypatch.setenv(name, value)
    assert provide_ffmpeg_for_video_commands("ns-train") is None
    assert os.environ["PATH"] == str(bin_dir)
