"""One run of a sweep: ``ns-train`` (through offline_tools, so baselines need no network) then the one
evaluator, each in a child process, with a log file; returns the run's record.

Runs in a Ray worker (or in the calling process): a crash, NaN or out-of-memory in the training is a failed
record with the log's path and last error line, never an exception that ends the sweep. The children are
killed with the worker (PR_SET_PDEATHSIG), so a worker that dies leaves no training running on its cores.

The children run the code of the checkout that started the sweep (``code_root``: first on their PYTHONPATH,
their working folder), not whichever copy a Ray worker happens to import: a sweep or gate started from a git
worktree trains that worktree's code, and the record's commit is that checkout's.
"""

from __future__ import annotations

import ctypes
import json
import os
import platform
import re
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import Any, Dict, List, Optional

from frugalnerf_ns.config_files import code_root as package_parent
from frugalnerf_ns.tools.sweep.grid import RunSpec

QUIET = ["--vis", "tensorboard", "--steps-per-eval-image", "1000000", "--steps-per-eval-batch", "1000000",
         "--steps-per-eval-all-images", "1000000"]


def _die_with_parent() -> None:  # preexec_fn: runs in the child between fork and exec
    try:
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    except OSError:
        pass


def _run(command: List[str], log: Path, env: Dict[str, str], capture: bool = False, cwd: Optional[Path] = None) -> tuple:
    """(exit status, peak RSS MiB of that child, stdout if ``capture``) of one child process. Its output goes
    to ``log`` (stdout and stderr interleaved as printed; a captured stdout is appended after it ends)."""
    with open(log, "a") as handle:
        handle.write(f"$ {' '.join(command)}\n")
        handle.flush()
        proc = subprocess.Popen(command, stdout=subprocess.PIPE if capture else handle, stderr=handle, text=True,
                                env=env, cwd=cwd, preexec_fn=_die_with_parent if sys.platform.startswith("linux") else None)
        stdout = proc.stdout.read() if capture else ""  # type: ignore[union-attr]
        _, status, usage = os.wait4(proc.pid, 0)
        proc.returncode = os.waitstatus_to_exitcode(status)
        handle.write(stdout)
    return proc.returncode, usage.ru_maxrss / 1024.0, stdout


_EXCEPTION = re.compile(r"^[A-Za-z_.]*(Error|Exception|Interrupt)\b.*")


def last_error_line(log: Path) -> str:
    """The line that says why a run failed: the last Python exception line, else our own one-line error
    ("frugalnerf: ..."), else the log's last non-empty line."""
    try:
        lines = [line.strip() for line in log.read_text(errors="replace").splitlines() if line.strip()]
    except OSError:
        return "no log"
    for pattern in (_EXCEPTION, re.compile(r"^frugalnerf: .*"), re.compile(r".*(Killed|out of memory).*")):
        for line in reversed(lines):
            if pattern.match(line):
                return line[:300]
    return lines[-1][:300] if lines else "empty log"


def git_commit(root: Optional[Path] = None) -> Optional[str]:
    """The short commit of the checkout at ``root`` (default: the one this code runs from); None when ``root`` is no
    checkout's root (an installed package: a git repository around site-packages is not its code's commit)."""
    root = Path(root or package_parent())
    if not (root / ".git").exists():  # a folder for a clone, a file for a worktree
        return None
    try:
        out = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, cwd=root, timeout=10)
        return out.stdout.strip() or None
    except (OSError, subprocess.TimeoutExpired):
        return None


def cpu_model() -> str:
    """The processor's name (Linux's /proc/cpuinfo; elsewhere what the platform module says, maybe empty)."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.lower().startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor()


def machine() -> Dict[str, Any]:
    """Where a run trained. The processor, torch's build and the vector instructions torch dispatches to decide
    the floating-point rounding: the same code and seed train to different numbers on machines that differ in
    them (juice box 3-view by up to 1.15 dB; docs/notes/quality-gate.md), so the gate compares runs of one machine."""
    info: Dict[str, Any] = {"host": socket.gethostname(), "cpus": os.cpu_count(), "python": platform.python_version(),
                            "cpu": cpu_model()}
    try:
        import torch

        info["torch"] = torch.__version__
        capability = getattr(torch.backends.cpu, "get_cpu_capability", None)
        if capability is not None:
            info["cpu_capability"] = capability()
        if torch.cuda.is_available():
            info["gpu"] = torch.cuda.get_device_name(0)
    except ImportError:
        pass
    return info


def device_args() -> List[str]:
    """nerfstudio's methods default to CUDA; use the CPU where this worker has no GPU."""
    import torch

    return [] if torch.cuda.is_available() else ["--machine.device-type", "cpu"]


def run_location(spec: RunSpec, out: Path) -> tuple:
    """(experiment name, run folder): nerfstudio writes <out>/runs/<experiment>/<method>/<timestamp>, and
    ns-eval / eval_setup look the method part up, so it stays the registered name; the key keeps runs apart."""
    experiment = f"{spec.scene}-{spec.views}v"
    return experiment, Path(out) / "runs" / experiment / spec.method / spec.key


def python_path_first(code_root: Path) -> str:
    """This process's PYTHONPATH with ``code_root`` in front (``python -m frugalnerf_ns...`` runs that checkout)."""
    return os.pathsep.join([str(code_root), *filter(None, [os.environ.get("PYTHONPATH")])])


def code_env(code_root: Path, threads: Optional[int] = None) -> Dict[str, str]:
    """The children's environment: ``code_root`` first on PYTHONPATH, and the thread count Ray gave the run."""
    env = dict(os.environ)
    env["PYTHONPATH"] = python_path_first(code_root)
    if threads:  # a CPU run uses the cores Ray gave it, not every core of the machine
        env.update({"OMP_NUM_THREADS": str(threads), "MKL_NUM_THREADS": str(threads)})
    return env


def execute(spec: RunSpec, out: Path, threads: Optional[int] = None, code_root: Optional[str] = None) -> Dict[str, Any]:
    """Train and score one run with the code of ``code_root`` (default: this module's checkout); its record
    (status "ok" with metrics, or "failed" with the error)."""
    out = Path(out)
    root = Path(code_root) if code_root else package_parent()
    logs = out / "logs"
    logs.mkdir(parents=True, exist_ok=True)
    log = logs / f"{spec.key}.log"
    experiment, run_dir = run_location(spec, out)
    env = code_env(root, threads)
    record: Dict[str, Any] = {**spec.to_dict(), "log": str(log), "run_dir": str(run_dir), "commit": git_commit(root),
                              "code_root": str(root), "machine": machine(), "threads": threads,
                              "started_at": time.time()}
    train = [sys.executable, "-m", "frugalnerf_ns.tools.offline_tools", "train", spec.method, "--data", spec.data,
             "--output-dir", str(out / "runs"), "--experiment-name", experiment, "--timestamp", spec.key,
             *QUIET, *device_args(), *spec.train_args, *spec.parser_args]
    start = time.time()
    status, peak, _ = _run(train, log, env, cwd=root)
    record["train_seconds"] = time.time() - start
    record["peak_rss_mib"] = peak
    checkpoints = sorted((run_dir / "nerfstudio_models").glob("step-*.ckpt"))
    if status != 0 or not checkpoints:
        return {**record, "status": "failed", "stage": "train", "exit_code": status, "error": last_error_line(log),
                "finished_at": time.time()}
    steps = [int(p.stem.split("-")[1]) for p in checkpoints] if spec.anytime_every else []
    start_eval = time.time()
    status, _, stdout = _run([sys.executable, "-m", "frugalnerf_ns.tools.offline_tools", "eval", str(run_dir / "config.yml"),
                              *map(str, steps)], log, env, capture=True, cwd=root)
    record["eval_seconds"] = time.time() - start_eval
    results = [json.loads(line[len("RESULT "):]) for line in stdout.splitlines() if line.startswith("RESULT ")]
    if status != 0 or not results:
        return {**record, "status": "failed", "stage": "eval", "exit_code": status, "error": last_error_line(log),
                "finished_at": time.time()}
    final = results[-1]
    record.update({k: v for k, v in final.items() if k != "step"})
    record["checkpoint_mb"] = checkpoints[-1].stat().st_size / 1e6
    if spec.anytime_every:
        times = {int(p.stem.split("-")[1]): (p.stat().st_mtime - start, p.stat().st_size / 1e6) for p in checkpoints}
        record["anytime"] = [{**{k: v for k, v in r.items()}, "seconds": times[r["step"]][0],
                              "checkpoint_mb": times[r["step"]][1]} for r in results]
    return {**record, "status": "ok", "finished_at": time.time()}
