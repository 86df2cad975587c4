"""Checkpoints that a kill or a full disk cannot break, and loading that falls back to the newest intact one.

nerfstudio 1.1.5 writes ``step-N.ckpt`` in place and, by default, then deletes every other checkpoint, so a
run killed while saving is left with one truncated file, which ns-eval, ns-render and resuming then fail on
with a deep traceback. Here a checkpoint is written in full to a staging file beside the checkpoint folder,
flushed to disk, and renamed into place (atomic within one filesystem); older ones are deleted only after.
The staging file lives outside ``nerfstudio_models`` because nerfstudio parses every name in that folder as
``step-<number>.ckpt``.
"""

from __future__ import annotations

import os
import re
from pathlib import Path
from typing import Any, Dict, List, Tuple

import torch
from nerfstudio.utils.rich_utils import CONSOLE

from frugalnerf_ns.errors import UserError, one_line_errors

CHECKPOINT_NAME = re.compile(r"^step-(\d+)\.ckpt$")
STAGING_NAME = ".checkpoint-being-written"  # in the run folder, next to nerfstudio_models


class CheckpointError(UserError):
    """No usable checkpoint where one was asked for."""


def checkpoint_file_name(step: int) -> str:
    """nerfstudio's name for the checkpoint of ``step``."""
    return f"step-{step:09d}.ckpt"


def checkpoints_newest_first(folder: Path) -> List[Tuple[int, Path]]:
    """(step, path) of the checkpoints in ``folder``, newest first; other files are ignored."""
    found = []
    for path in folder.iterdir():
        match = CHECKPOINT_NAME.match(path.name)
        if match and path.is_file():
            found.append((int(match.group(1)), path))
    return sorted(found, reverse=True)


def read_checkpoint(path: Path) -> Dict[str, Any]:
    """The checkpoint's contents; ``ValueError`` saying why when it cannot be read or is incomplete."""
    try:
        state = torch.load(path, map_location="cpu")
    except Exception as err:  # noqa: BLE001 - truncated zip, empty file, bad pickle: all mean "unreadable"
        # The first sentence only: torch appends advice about its internals to a truncated archive's error.
        first = (str(err).strip().splitlines() or [""])[0].split(". ")[0][:160]
        raise ValueError(f"{type(err).__name__}: {first}" if first else type(err).__name__) from None
    if not isinstance(state, dict) or not {"step", "pipeline"} <= set(state):
        raise ValueError("not a nerfstudio checkpoint (no step or pipeline)")
    return state


def read_checkpoint_or_exit(path: Path) -> Dict[str, Any]:
    """``read_checkpoint`` for a file the user named: a missing or unreadable one ends with one line."""
    if not path.is_file():
        raise CheckpointError(f"checkpoint {path} does not exist")
    try:
        return read_checkpoint(path)
    except ValueError as err:
        raise CheckpointError(f"checkpoint {path} is unreadable ({err})") from None


def newest_intact_checkpoint(folder: Path) -> Tuple[Path, Dict[str, Any]]:
    """The newest checkpoint in ``folder`` that reads back whole, and its contents. Each newer unreadable one
    is reported in one line; no readable checkpoint at all ends with one line."""
    if not folder.is_dir():
        raise CheckpointError(f"checkpoint folder {folder} does not exist")
    candidates = checkpoints_newest_first(folder)
    if not candidates:
        raise CheckpointError(f"{folder} holds no checkpoint (step-<number>.ckpt)")
    for _, path in candidates:
        try:
            state = read_checkpoint(path)
        except ValueError as err:
            CONSOLE.print(f"[bold yellow]frugalnerf: checkpoint {path} is unreadable ({err}); loading an older one.")
            continue
        return path, state
    raise CheckpointError(f"none of the {len(candidates)} checkpoints in {folder} is readable")


def load_for_evaluation(config: Any, pipeline: Any) -> Tuple[Path, int]:
    """nerfstudio's ``eval_utils.eval_load_checkpoint`` (ns-eval, ns-render, ns-viewer) with this module's
    reading: the newest intact checkpoint, or the step asked for with one clear line when it is unusable."""
    folder = Path(config.load_dir)
    if config.load_step is None:
        path, state = newest_intact_checkpoint(folder)
    else:
        path = folder / checkpoint_file_name(config.load_step)
        state = read_checkpoint_or_exit(path)
    pipeline.load_pipeline(state["pipeline"], state["step"])
    CONSOLE.print(f":white_check_mark: Done loading checkpoint from {path}")
    return path, int(state["step"])


def use_intact_checkpoints_in_eval_tools(pipeline_class: type) -> None:
    """Make nerfstudio's evaluation tools load checkpoints with ``load_for_evaluation``.

    ns-eval, ns-render and ns-viewer call ``eval_utils.eval_load_checkpoint`` right after building the
    pipeline and offer no hook for a method to load its own checkpoints, so FrugalPipeline calls this while
    it is built and hands in its class (this module does not import the pipeline). Other methods' pipelines
    keep nerfstudio's function."""
    from nerfstudio.utils import eval_utils

    original = eval_utils.eval_load_checkpoint
    if getattr(original, "frugalnerf_fallback", False):
        return

    def eval_load_checkpoint(config, pipeline):
        if isinstance(pipeline, pipeline_class):
            with one_line_errors():
                return load_for_evaluation(config, pipeline)
        return original(config, pipeline)

    eval_load_checkpoint.frugalnerf_fallback = True  # type: ignore[attr-defined]
    eval_utils.eval_load_checkpoint = eval_load_checkpoint


def write_checkpoint(state: Dict[str, Any], path: Path, keep_only_this: bool) -> None:
    """Write ``state`` to ``path`` atomically: a reader sees the previous file set or the new one, never a
    partial file. ``keep_only_this`` then deletes the folder's other checkpoints (nerfstudio's
    save_only_latest_checkpoint). A failed write (full disk) leaves the existing checkpoints untouched and
    raises ``CheckpointError`` naming the file."""
    path.parent.mkdir(parents=True, exist_ok=True)
    staging = path.parent.parent / STAGING_NAME
    try:
        with open(staging, "wb") as f:
            torch.save(state, f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(staging, path)
        _fsync_folder(path.parent)
    except OSError as err:
        staging.unlink(missing_ok=True)
        raise CheckpointError(
            f"could not write checkpoint {path} ({err.strerror or err}); the checkpoints already in {path.parent} "
            "are intact"
        ) from None
    if keep_only_this:
        for _, other in checkpoints_newest_first(path.parent):
            if other != path:
                other.unlink(missing_ok=True)


def _fsync_folder(folder: Path) -> None:
    """Make the rename itself durable (POSIX); a no-op where folders cannot be opened (Windows)."""
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)
