"""FrugalNeRF's trainer: nerfstudio's, made safe to interrupt and clear about what a user can fix.

- Options are checked before anything is loaded (``options.validate_options``).
- Checkpoints are written atomically (``checkpoints.write_checkpoint``); resuming from a folder loads the
  newest checkpoint that reads back whole, saying which newer one it skipped.
- Running out of memory in a step ends with one line naming the batch options, after saving the last
  completed step when it is newer than the last checkpoint.
- A start that fails before training (bad data, bad options) removes the run folder when it holds nothing
  but the config.yml nerfstudio wrote before setting up.
- Ctrl-C or SIGTERM (a cluster's preemption) during training finishes the step under way, saves the steps done
  (atomically, as every checkpoint) and exits non-zero (130 / 143, the shells' codes for those signals) with
  one line naming the checkpoint folder and how to resume; a second Ctrl-C exits at once.

``--max-num-iterations`` keeps nerfstudio's meaning (steps to run in this invocation, also when resuming);
every schedule (learning rate, loss weights, upsampling, alpha mask) follows the absolute step, so a
resumed run continues exactly where the interrupted one was.
"""

from __future__ import annotations

import os
import re
import signal
import sys
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path
from typing import Any, Dict, List, Literal, Optional, Tuple, Type

import torch
import tyro
from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackLocation
from nerfstudio.engine.trainer import Trainer, TrainerConfig
from nerfstudio.utils.decorators import check_main_thread
from nerfstudio.utils.rich_utils import CONSOLE

from frugalnerf_ns.run.checkpoints import (
    checkpoint_file_name,
    newest_intact_checkpoint,
    read_checkpoint_or_exit,
    write_checkpoint,
)
from frugalnerf_ns.errors import one_line_errors
from frugalnerf_ns.run.options import OptionError, flag, validate_options


@dataclass
class FrugalTrainerConfig(TrainerConfig):
    """nerfstudio's trainer settings; the trainer adds atomic checkpoints and checked options."""

    _target: Type = field(default_factory=lambda: FrugalTrainer)
    prompt: tyro.conf.Suppress[Optional[str]] = None
    """nerfstudio's alias of --pipeline.model.prompt, which no part of FrugalNeRF reads: left out of --help with it."""
    schedule_steps: Optional[int] = None
    """Steps every schedule spans: the learning rates' and loss weights' decay, grid upsampling and the alpha
    mask (--pipeline.model.upsample-at / alpha-mask-at are fractions of it). None: --max-num-iterations of a run
    started from scratch; a resumed run keeps the one stored in its checkpoint."""
    suggest_next_view: bool = True
    """At the end of a training on photos without cameras or a capture around a subject (a room beyond the box),
    rank where the next photo would help most (``frugalnerf-next-view``, 10-20 s on 2 cores) and print one line."""

    def set_timestamp(self) -> None:
        """nerfstudio's timestamp (to the second), made unique: the run folder is claimed here, before ns-train
        writes config.yml into it. Two ns-train started in the same second on one scene (a script with ``&``, two
        terminals) would otherwise share one folder and overwrite each other's config and checkpoints; the second
        gets ``<timestamp>_2``. A timestamp given with --timestamp is kept as given."""
        if self.timestamp != "{timestamp}":
            return
        stamp = datetime.now().strftime("%Y-%m-%d_%H%M%S")
        for attempt in range(1, 1000):
            self.timestamp = stamp if attempt == 1 else f"{stamp}_{attempt}"
            base = self.get_base_dir()
            base.parent.mkdir(parents=True, exist_ok=True)
            try:
                base.mkdir()  # atomic: exactly one process creates a given folder
                return
            except FileExistsError:
                continue


def is_out_of_memory(err: BaseException) -> bool:
    """torch's CUDA OOM, or the CPU allocator's failure (a RuntimeError naming the allocation)."""
    if isinstance(err, getattr(torch, "OutOfMemoryError", ())):
        return True
    text = str(err)
    return isinstance(err, RuntimeError) and ("can't allocate memory" in text or "out of memory" in text)


def resolve_schedule_steps(config: FrugalTrainerConfig, resumed: Optional[Dict[str, Any]]) -> int:
    """The run's schedule length: --schedule-steps when given; else a resumed checkpoint's (checkpoints
    written before it was stored: where a run of --max-num-iterations from that step ends); else
    --max-num-iterations of a fresh run."""
    if config.schedule_steps:
        return int(config.schedule_steps)
    if resumed is not None:
        return int(resumed.get("schedule_steps") or int(resumed["step"]) + 1 + config.max_num_iterations)
    return int(config.max_num_iterations)


def memory_shortfall(err: BaseException, device: str) -> str:
    """'asked for X GB, Y GB free' from the allocator's message and the device (what is known of each)."""
    cpu = re.search(r"allocate (\d+) bytes", str(err))  # torch's CPU allocator
    cuda = re.search(r"Tried to allocate ([\d.]+) GiB", str(err))  # torch's CUDA allocator
    if cpu:
        asked_gb = f"asked for {int(cpu.group(1)) / 1e9:.1f} GB"
    elif cuda:
        asked_gb = f"asked for {float(cuda.group(1)) * 2**30 / 1e9:.1f} GB"
    else:
        asked_gb = "an allocation failed"
    if str(device).startswith("cuda") and torch.cuda.is_available():
        free, _ = torch.cuda.mem_get_info()
    else:
        import psutil

        free = psutil.virtual_memory().available
    return f"{asked_gb}, {free / 1e9:.1f} GB free"


def remove_config_only_run_folder(run_dir: Path, output_dir: Path) -> bool:
    """Delete ``run_dir`` when it holds only config.yml, then its parents up to ``output_dir`` while they are
    empty. Returns whether the run folder went."""
    if not run_dir.is_dir() or any(p.name != "config.yml" for p in run_dir.iterdir()):
        return False
    (run_dir / "config.yml").unlink(missing_ok=True)
    run_dir.rmdir()
    stop = output_dir.resolve()
    parent = run_dir.parent
    while parent.resolve() != stop and stop in parent.resolve().parents and not any(parent.iterdir()):
        parent.rmdir()
        parent = parent.parent
    return True


def with_new_parameters(saved: Dict[str, Any], optimizers: Dict[str, Any]) -> Dict[str, Any]:
    """The optimisers' saved state, made loadable where this version added parameters at the end of a group (a run
    trained before the space beyond its box was modelled has no outer grids): the new ones start with fresh Adam
    moments (torch would refuse a group of another size). A group that lost parameters is left to torch's error."""
    fixed = {}
    for name, state in saved.items():
        optimizer = optimizers.get(name)
        groups = state.get("param_groups", []) if isinstance(state, dict) else []
        if optimizer is None or len(groups) != len(optimizer.param_groups):
            fixed[name] = state
            continue
        new_groups, next_id, added = [], 1 + max((i for g in groups for i in g["params"]), default=-1), 0
        for group, current in zip(groups, optimizer.param_groups):
            missing = len(current["params"]) - len(group["params"])
            if missing > 0:
                group = {**group, "params": list(group["params"]) + list(range(next_id, next_id + missing))}
                next_id, added = next_id + missing, added + missing
            new_groups.append(group)
        if added:
            CONSOLE.print(f"frugalnerf: the checkpoint's {name!r} optimiser has {added} parameter tensors fewer than this "
                          "version's model (made since it was saved): they start with fresh optimiser state")
        fixed[name] = {**state, "param_groups": new_groups}
    return fixed


class FrugalTrainer(Trainer):
    config: FrugalTrainerConfig

    def __init__(self, config: FrugalTrainerConfig, local_rank: int = 0, world_size: int = 1) -> None:
        # nerfstudio defaults to CUDA and fails on a machine without it; train on the CPU there. Probed here,
        # when a FrugalNeRF run starts, not when the presets are built (every nerfstudio command builds them).
        if config.machine.device_type == "cuda" and not torch.cuda.is_available():
            CONSOLE.print("frugalnerf: no CUDA device: training on the CPU (--machine.device-type cpu says so).")
            config.machine.device_type = "cpu"
        super().__init__(config, local_rank, world_size)
        self.last_saved_step = -1  # the newest step whose state is on disk (saved or loaded)
        self.completed_step = -1  # the newest step whose iteration and callbacks have run
        self.interrupted_by: Optional[int] = None  # the signal that asked the run to stop

    def setup(self, test_mode: Literal["test", "val", "inference"] = "val") -> None:
        try:
            with one_line_errors():
                validate_options(self.config)
                # The checkpoint is read before nerfstudio builds the optimisers: it holds the schedule length
                # their learning-rate schedulers must be built with.
                self._resume = self._read_checkpoint_to_resume()
                self.schedule_steps = resolve_schedule_steps(self.config, None if self._resume is None else self._resume[1])
                for group in self.config.optimizers.values():
                    if group.get("scheduler") is not None and hasattr(group["scheduler"], "max_steps"):
                        group["scheduler"].max_steps = self.schedule_steps
                super().setup(test_mode)
            # Last of the step's callbacks (after the model's upsampling and alpha mask): from here on a
            # checkpoint of this step holds what nerfstudio's own save at this step would.
            self.callbacks.append(TrainingCallback([TrainingCallbackLocation.AFTER_TRAIN_ITERATION], self._mark_completed))
            if getattr(self.config, "suggest_next_view", False):
                self.callbacks.append(TrainingCallback([TrainingCallbackLocation.AFTER_TRAIN], self._suggest_next_view))
        except BaseException:
            # nerfstudio wrote config.yml before calling us: a run that never started leaves no folder.
            remove_config_only_run_folder(self.base_dir, Path(self.config.output_dir))
            raise

    # ---- checkpoints ------------------------------------------------------------------------------------
    def checkpoint_state(self, step: int) -> Dict[str, Any]:
        """What nerfstudio's save_checkpoint stores, under the same keys (its loaders read ours)."""
        pipeline = self.pipeline.module if hasattr(self.pipeline, "module") else self.pipeline
        return {
            "step": step,
            "schedule_steps": self.schedule_steps,
            "pipeline": pipeline.state_dict(),
            "optimizers": {k: v.state_dict() for (k, v) in self.optimizers.optimizers.items()},
            "schedulers": {k: v.state_dict() for (k, v) in self.optimizers.schedulers.items()},
            "scalers": self.grad_scaler.state_dict(),
        }

    @check_main_thread
    def save_checkpoint(self, step: int) -> None:
        path = self.checkpoint_dir / checkpoint_file_name(step)
        write_checkpoint(self.checkpoint_state(step), path, keep_only_this=self.config.save_only_latest_checkpoint)
        self.last_saved_step = step

    def _read_checkpoint_to_resume(self) -> Optional[Tuple[Path, Dict[str, Any]]]:
        cfg = self.config
        if cfg.load_dir is not None and cfg.load_step is None:
            return newest_intact_checkpoint(Path(cfg.load_dir))
        if cfg.load_dir is not None:
            path = Path(cfg.load_dir) / checkpoint_file_name(cfg.load_step)
            return path, read_checkpoint_or_exit(path)
        if cfg.load_checkpoint is not None:
            path = Path(cfg.load_checkpoint)
            return path, read_checkpoint_or_exit(path)
        return None

    def _load_checkpoint(self) -> None:
        cfg = self.config
        if self._resume is None:
            CONSOLE.print("No Nerfstudio checkpoint to load, so training from scratch.")
            return
        path, state = self._resume
        self._resume = None  # loaded once; the state is not kept around
        self._start_step = state["step"] + 1
        self.pipeline.load_pipeline(state["pipeline"], state["step"])
        self.optimizers.load_optimizers(with_new_parameters(state["optimizers"], self.optimizers.optimizers))
        if "schedulers" in state and cfg.load_scheduler:
            self.optimizers.load_schedulers(state["schedulers"])
        self.grad_scaler.load_state_dict(state["scalers"])
        self.last_saved_step = self.completed_step = state["step"]
        CONSOLE.print(f"Done loading Nerfstudio checkpoint from {path}")

    # ---- training ---------------------------------------------------------------------------------------
    def train(self) -> None:
        previous = self._catch_stop_signals()
        try:
            with one_line_errors():  # out of memory, a checkpoint that cannot be written
                super().train()
        finally:
            for signum, handler in previous.items():
                signal.signal(signum, handler)

    def _mark_completed(self, step: int) -> None:
        self.completed_step = step

    def _suggest_next_view(self, step: int) -> None:
        """The end-of-training line of a photo-only or capture scene: where the next photo would help most (the
        files go into the run folder). A failure here costs the user the suggestion, never the run."""
        from frugalnerf_ns.tools.next_view import suggest, wants_next_view

        pipeline = self.pipeline.module if hasattr(self.pipeline, "module") else self.pipeline
        if self.interrupted_by is not None or not wants_next_view(pipeline):
            return
        pipeline.eval()
        try:
            suggest(self.base_dir / "config.yml", pipeline=pipeline, print_fn=CONSOLE.print)
        except Exception as err:  # noqa: BLE001 - the run is saved; only the suggestion is lost
            CONSOLE.print(f"[bold yellow]frugalnerf: no next-photo suggestion ({type(err).__name__}: {err}); "
                          f"frugalnerf-next-view --load-config {self.base_dir / 'config.yml'} retries it")
        finally:
            pipeline.train()

    def _catch_stop_signals(self) -> Dict[int, Any]:
        """Handle SIGINT and SIGTERM by asking the loop to stop after the step under way (nerfstudio's
        ``stop_training``); returns the handlers they replaced. Only the main thread may install them."""
        import threading

        if threading.current_thread() is not threading.main_thread():
            return {}

        def stop(signum: int, _frame: Any) -> None:
            if self.interrupted_by is not None and signum == signal.SIGINT:
                # The second Ctrl-C: exit now. Checkpoints are written to a staging file and renamed, so the
                # newest one on disk stays whole even if this lands during a save.
                print(f"frugalnerf: quit at once; the last checkpoint (step {self.last_saved_step}) is in {self.checkpoint_dir}",
                      file=sys.stderr, flush=True)
                os._exit(128 + signum)
            self.interrupted_by = signum
            self.stop_training = True
            CONSOLE.print(f"frugalnerf: {signal.Signals(signum).name}: saving after step {self.step} (Ctrl-C again to quit at once)")

        stop_signals: List[int] = [signal.SIGINT, signal.SIGTERM]
        return {signum: signal.signal(signum, stop) for signum in stop_signals}

    def _after_train(self) -> None:
        if self.interrupted_by is None:
            super()._after_train()
            return
        from nerfstudio.utils import writer

        # nerfstudio's loop breaks at the top of the step after the signal, so ``self.step`` was never trained.
        step = self.completed_step
        if step > self.last_saved_step:
            self.save_checkpoint(step)
        writer.write_out_storage()
        self.shutdown()  # the viewer's server, so the process can end
        name = signal.Signals(self.interrupted_by).name
        if step < 0:
            print(f"frugalnerf: {name} before the first step ended: nothing to save", file=sys.stderr)
        else:
            # nerfstudio counts --max-num-iterations from the loaded step: the same command alone would train the
            # whole run's steps again after this one, so the line names the steps this run had left.
            left = self._start_step + self.config.max_num_iterations - (step + 1)
            print(
                f"frugalnerf: stopped by {name} after step {step}: saved in {self.checkpoint_dir}; resume with the same "
                f"command and --load-dir {self.checkpoint_dir} --max-num-iterations {left} (the steps left)",
                file=sys.stderr,
            )
        raise SystemExit(128 + self.interrupted_by)

    def train_iteration(self, step: int):
        try:
            return super().train_iteration(step)
        except Exception as err:  # noqa: BLE001 - only out-of-memory is handled; the rest re-raises as is
            if not is_out_of_memory(err):
                raise
            message = self._out_of_memory_message(step, err)
        # Outside the except block, so the failed step's tensors (held by the traceback) are freed first.
        self.optimizers.zero_grad_all()
        if torch.cuda.is_available():
            torch.cuda.empty_cache()
        if step - 1 > self.last_saved_step:  # steps trained since the last (or loaded) checkpoint
            self.save_checkpoint(step - 1)
            message += f"; steps up to {step - 1} are saved in {self.checkpoint_dir}"
        raise OptionError(message)

    def _out_of_memory_message(self, step: int, err: BaseException) -> str:
        dm = self.config.pipeline.datamanager
        rays = f"{dm.train_num_rays_per_batch} training + {getattr(dm, 'num_novel_rays_per_batch', 0)} novel rays"
        model = self.pipeline.model
        grid = ""
        if hasattr(model, "field"):
            side = round(float(model.field.density_grid.resolution.prod()) ** (1 / 3))
            grid = f", grid ~{side}^3"
        return (
            f"out of memory at step {step} ({rays} per step{grid} on {self.device}; {memory_shortfall(err, self.device)}): lower "
            f"{flag('pipeline.datamanager.train_num_rays_per_batch')}, "
            f"{flag('pipeline.datamanager.num_novel_rays_per_batch')} or {flag('pipeline.model.final_voxels')}"
        )

