"""Run the reliability trials of a new user's bad input and interrupted runs; print a table, write JSON.

  python scripts/diagnostics/bad_input_trials.py [--out outputs/bad_input_trials]

Each trial is a real command (ns-train, ns-eval, ns-render, or python importing the plugin) on a small
fixture this script writes (the procedural scene and variants of it, a short trained run, copies of its
checkpoint cut short). For each: the exit code, the line a user reads (the last line of stderr for
failures; the warning for runs that go on), the seconds until the command ended, and what it left in its
output folder. Run it alone: the seconds are wall time on this machine, and most of them are nerfstudio's
imports (the first row measures that alone).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path
from typing import Dict, List, Optional, Sequence

import numpy as np
from PIL import Image

BIN = Path(sys.executable).parent
QUIET = ["--vis", "tensorboard", "--logging.local-writer.enable", "False"]


def run(cmd: Sequence[object], env: Optional[Dict[str, str]] = None, timeout: int = 900):
    start = time.time()
    proc = subprocess.run([str(c) for c in cmd], capture_output=True, text=True, env=env, timeout=timeout)
    return proc, time.time() - start


def left_on_disk(folder: Path) -> str:
    if not folder.exists():
        return "nothing"
    files = sorted(str(p.relative_to(folder)) for p in folder.rglob("*") if p.is_file())
    if not files:
        return "nothing"
    names = sorted({Path(f).name if "step-" not in f else "step-*.ckpt" for f in files})
    return f"{len(files)} file(s): " + ", ".join(names[:6]) + (" ..." if len(names) > 6 else "")


def user_line(proc: subprocess.CompletedProcess, needle: Optional[str]) -> str:
    """The line a user reads: the one holding ``needle`` (a warning) or the last line of stderr."""
    text = proc.stdout + proc.stderr
    if needle:
        joined = " ".join(text.split())  # rich wraps long lines: search the text unwrapped
        at = joined.find(needle)
        if at < 0:
            return f"(no line with {needle!r})"
        start = joined.rfind("frugalnerf:", max(0, at - 250), at)
        start = at if start < 0 else start
        end = joined.find("frugalnerf:", at)  # up to the next message
        return joined[start : end if end > 0 else start + 260][:260].strip()
    if proc.returncode == 0:
        return "ok"
    lines = [line for line in proc.stderr.strip().splitlines() if line.strip()]
    return lines[-1][:260] if lines else "(nothing on stderr)"


def fixtures(root: Path) -> Dict[str, Path]:
    from frugalnerf_ns.data.procedural_scene import write_procedural_scene

    scene = write_procedural_scene(root / "scene")
    out: Dict[str, Path] = {"scene": scene}
    # One RGBA training image and one RGBA test image among RGB images.
    mixed = root / "mixed-rgba"
    shutil.copytree(scene, mixed)
    for name in ("frame_000.png", "frame_002.png"):
        rgb = np.asarray(Image.open(mixed / "images" / name).convert("RGB"))
        alpha = np.full(rgb.shape[:2] + (1,), 255, np.uint8)
        alpha[:10, :10] = 0
        Image.fromarray(np.concatenate([rgb, alpha], -1), "RGBA").save(mixed / "images" / name)
    out["mixed-rgba"] = mixed
    # All training images black.
    black = root / "black"
    shutil.copytree(scene, black)
    meta = json.loads((black / "transforms.json").read_text())
    for name in meta["train_filenames"]:
        image = Image.open(black / name)
        Image.fromarray(np.zeros_like(np.asarray(image))).save(black / name)
    out["black"] = black
    # Two training views from the same camera.
    same = root / "same-camera"
    shutil.copytree(scene, same)
    meta = json.loads((same / "transforms.json").read_text())
    train = meta["train_filenames"]
    frames = {f["file_path"]: f for f in meta["frames"]}
    frames[train[1]]["transform_matrix"] = frames[train[0]]["transform_matrix"]
    (same / "transforms.json").write_text(json.dumps(meta))
    out["same-camera"] = same
    return out


def trained_run(scene: Path, out: Path) -> Path:
    proc, _ = run([BIN / "ns-train", "frugalnerf-tiny", "--data", scene, "--output-dir", out, "--timestamp", "run",
                   "--max-num-iterations", "30", "--steps-per-save", "10", "--save-only-latest-checkpoint", "False", *QUIET])
    if proc.returncode != 0:
        sys.exit(f"bad_input_trials: the fixture run failed:\n{proc.stderr[-2000:]}")
    return next(out.rglob("config.yml")).parent


def copy_run(run_dir: Path, dest: Path, damage: str) -> Path:
    """A copy of the run whose newest checkpoint is damaged (its config points at the copy)."""
    import yaml

    import frugalnerf_ns  # noqa: F401 - registers the plugin's classes for yaml

    config = yaml.load((run_dir / "config.yml").read_text(), Loader=yaml.Loader)
    config.output_dir = dest
    copy = config.get_base_dir()
    shutil.copytree(run_dir, copy)
    config.save_config()
    newest = sorted((copy / "nerfstudio_models").glob("step-*.ckpt"))[-1]
    data = newest.read_bytes()
    newest.write_bytes(b"" if damage == "empty" else data[: len(data) // 3])
    return copy


def main(argv: Optional[Sequence[str]] = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, default=Path("outputs/bad_input_trials"))
    args = parser.parse_args(argv)
    root = args.out.resolve()
    shutil.rmtree(root, ignore_errors=True)
    root.mkdir(parents=True)
    fx = fixtures(root / "data")
    run_dir = trained_run(fx["scene"], root / "fixture-run")
    rows: List[Dict] = []

    def trial(name: str, cmd: Sequence[object], out: Optional[Path] = None, needle: Optional[str] = None,
              env: Optional[Dict[str, str]] = None) -> None:
        print(f"bad_input_trials: {name} ...", flush=True)
        proc, seconds = run(cmd, env=env)
        rows.append({
            "trial": name, "exit": proc.returncode, "message": user_line(proc, needle), "seconds": round(seconds, 1),
            "left": left_on_disk(out) if out is not None else "-",
            "traceback": "Traceback" in proc.stderr,
        })

    def train(name, data, *extra, needle=None):
        out = root / "runs" / name.replace(" ", "-")
        trial(name, [BIN / "ns-train", "frugalnerf-tiny", "--data", data, "--output-dir", out, *QUIET, *extra], out, needle)

    trial("imports only (python -c 'import nerfstudio.scripts.train')", [sys.executable, "-c", "import nerfstudio.scripts.train"])
    train("final-voxels 0", fx["scene"], "--pipeline.model.final-voxels", "0")
    train("final-voxels -8", fx["scene"], "--pipeline.model.final-voxels", "-8")
    train("initial-voxels 0", fx["scene"], "--pipeline.model.initial-voxels", "0")
    train("reprojection-threshold -1", fx["scene"], "--pipeline.model.reprojection-threshold", "-1")
    train("patch-size 4 (even)", fx["scene"], "--pipeline.datamanager.patch-size", "4")
    train("train rays 10^12 (memory)", fx["scene"], "--pipeline.datamanager.train-num-rays-per-batch", str(10**12))
    train("missing --data folder", root / "data" / "no-such-scene")
    train("one RGBA image among RGB (5 steps)", fx["mixed-rgba"], "--max-num-iterations", "5", needle="Training Finished")
    train("all-black training images (5 steps)", fx["black"], "--max-num-iterations", "5", needle="entirely black")
    train("two training views, one camera (5 steps)", fx["same-camera"], "--max-num-iterations", "5", needle="same position")
    out = root / "runs" / "paper-eval"
    trial("paper preset, --vis tensorboard, eval batch/image/all at step 20 (22 steps)",
          [BIN / "ns-train", "frugalnerf", "--data", fx["scene"], "--output-dir", out, *QUIET, "--max-num-iterations", "22",
           "--schedule-steps", "5000",
           "--steps-per-eval-batch", "20", "--steps-per-eval-image", "20", "--steps-per-eval-all-images", "21",
           "frugal-auto", "--center-method", "focus"], out, needle="Training Finished")
    for damage in ("truncated", "empty"):
        copy = copy_run(run_dir, root / f"cut-{damage}", damage)
        trial(f"ns-eval, newest checkpoint {damage}", [BIN / "ns-eval", "--load-config", copy / "config.yml",
              "--output-path", copy / "eval.json"], needle="unreadable")
        trial(f"ns-render spiral, newest checkpoint {damage}", [BIN / "ns-render", "spiral", "--load-config",
              copy / "config.yml", "--output-path", copy / "spiral.mp4", "--seconds", "0.5", "--frame-rate", "4"],
              needle="unreadable")
        out = root / "runs" / f"resume-{damage}"
        trial(f"resume (--load-dir), newest checkpoint {damage}", [BIN / "ns-train", "frugalnerf-tiny", "--data", fx["scene"],
              "--output-dir", out, *QUIET, "--load-dir", copy / "nerfstudio_models", "--max-num-iterations", "2"], out,
              needle="unreadable")
    # A planted `ls` in the temp folder the plugin used to put first on PATH.
    tmpdir = root / "shared-tmp"
    trap = tmpdir / f"frugalnerf-ffmpeg-{os.getuid()}"
    trap.mkdir(parents=True)
    marker = root / "planted-ls-ran"
    (trap / "ls").write_text(f"#!/bin/sh\necho planted > {marker}\n")
    (trap / "ls").chmod(0o755)
    env = {"PATH": "/usr/bin:/bin", "TMPDIR": str(tmpdir), "HOME": str(root)}
    trial("planted $TMPDIR/frugalnerf-ffmpeg-<uid>/ls, then import plugin and run ls",
          [sys.executable, "-c", "import frugalnerf_ns, subprocess; subprocess.run(['ls', '/'], stdout=subprocess.DEVNULL); "
           f"import os; print('ls ran: ' + ('the planted one' if os.path.exists({str(marker)!r}) else 'the system one'))"],
          env=env, needle="ls ran")

    (root / "trials.json").write_text(json.dumps(rows, indent=2))
    lines = ["| trial | exit | what the user reads | s | left in the output folder |", "|---|---|---|---|---|"]
    for r in rows:
        message = r["message"].replace("|", "\\|") + (" (TRACEBACK)" if r["traceback"] else "")
        lines.append(f"| {r['trial']} | {r['exit']} | {message} | {r['seconds']} | {r['left']} |")
    table = "\n".join(lines)
    (root / "trials.md").write_text(table + "\n")
    print(table)
    print(f"bad_input_trials: wrote {root / 'trials.md'} and trials.json")


if __name__ == "__main__":
    main()
