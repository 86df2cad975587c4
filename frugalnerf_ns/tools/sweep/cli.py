"""``frugalnerf-sweep``: run a grid of trainings as Ray tasks, durable and resumable, then the tables.

  frugalnerf-sweep configs/sweeps/llff_ablation.yaml [--out outputs/sweep/llff_ablation] [--address ADDR]
                   [--cpus-per-run 2] [--gpus-per-run 1] [--data-root DIR] [--max-iterations N] [--retry-failed]
                   [--list]

Local by default: Ray starts inside the command (no cluster to set up) with this machine's cores; each run
asks for ``--cpus-per-run`` cores (default 2: on a CPU machine one training per 2 cores, because parallel
trainings oversubscribe the cores) or, where the cluster has GPUs, one GPU. ``--address`` (or RAY_ADDRESS)
sends the same sweep to a running Ray cluster; its workers need this package installed and the scenes at
the same path (a shared filesystem) or under ``--data-root`` as the workers see it.

Every finished run appends a record to ``<out>/results.jsonl``; running the command again skips the runs
that finished and retries the failed ones once. Writes ``results.md`` (per scene, means over seeds with
their spread, the average over scenes, failures with their logs), ``results.json`` and ``pareto.png``.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import os
import sys
import time
from pathlib import Path
from typing import Any, Callable, Dict, List, Optional, Sequence

from frugalnerf_ns.tools.sweep import report
from frugalnerf_ns.config_files import code_root as package_parent, outputs_dir
from frugalnerf_ns.tools.sweep.grid import GridError, RunSpec, load_grid
from frugalnerf_ns.tools.sweep.runner import execute, python_path_first
from frugalnerf_ns.tools.sweep.store import ResultStore


def _failed(spec: RunSpec, stage: str, error: str, out: Path) -> Dict[str, Any]:
    return {**spec.to_dict(), "status": "failed", "stage": stage, "error": error[:300],
            "log": str(out / "logs" / f"{spec.key}.log"), "started_at": None, "finished_at": time.time()}


def _init_ray(address: Optional[str]):
    import ray

    if ray.is_initialized():
        return ray, False
    address = address or os.environ.get("RAY_ADDRESS")
    if address:
        ray.init(address=address, logging_level=logging.WARNING, log_to_driver=False)
    else:
        # Local workers import this checkout too (a sweep started from a git worktree runs the worktree's
        # runner; the runs' own code is pinned by ``execute``'s code_root either way).
        path = python_path_first(package_parent())
        ray.init(num_cpus=os.cpu_count() or 1, include_dashboard=False, logging_level=logging.WARNING,
                 log_to_driver=False, runtime_env={"env_vars": {"PYTHONPATH": path}})
    return ray, True


def run_sweep(
    specs: Sequence[RunSpec],
    out: Path,
    address: Optional[str] = None,
    cpus_per_run: Optional[int] = None,
    gpus_per_run: Optional[float] = None,
    retry_failed: bool = False,
    progress_every: float = 60.0,
    say: Callable[[str], None] = print,
    code_root: Optional[Path] = None,
) -> List[Dict[str, Any]]:
    """Run the specs not yet finished as Ray tasks; the records of every spec (finished before or now). The runs
    train the code of ``code_root`` (a checkout; default the one this module is imported from)."""
    out = Path(out).resolve()
    store = ResultStore(out / "results.jsonl")
    by_key = {spec.key: spec for spec in specs}
    todo = store.to_run(by_key, retry_failed)
    skipped = len(by_key) - len(todo)
    say(f"sweep: {len(by_key)} runs, {skipped} already finished (or failed twice), {len(todo)} to run; "
        f"results in {store.path}")
    if todo:
        ray, started = _init_ray(address)
        try:
            _schedule(ray, [by_key[k] for k in todo], out, store, cpus_per_run, gpus_per_run, progress_every, say,
                      Path(code_root or package_parent()))
        finally:
            if started:
                ray.shutdown()
    latest = store.latest(by_key)
    return [latest[k] for k in by_key if k in latest]


def _schedule(ray, specs, out, store, cpus_per_run, gpus_per_run, progress_every, say, code_root: Path) -> None:
    resources = ray.cluster_resources()
    total_cpus, total_gpus = int(resources.get("CPU", 1)), resources.get("GPU", 0)
    gpus = gpus_per_run if gpus_per_run is not None else (1 if total_gpus >= 1 else 0)
    cpus = cpus_per_run if cpus_per_run is not None else (1 if gpus else 2)
    cpus = max(1, min(cpus, total_cpus))  # a request larger than the cluster would wait forever
    slots = max(1, int(total_gpus // gpus) if gpus else total_cpus // cpus)
    say(f"sweep: {len(specs)} runs, {cpus} CPU" + (f" + {gpus} GPU" if gpus else "") + f" each, "
        f"{slots} at a time ({total_cpus} CPUs" + (f", {total_gpus:g} GPUs" if total_gpus else "") + ")")
    remote = ray.remote(execute).options(num_cpus=cpus, num_gpus=gpus, max_retries=1, retry_exceptions=False)
    threads = None if gpus else cpus
    # The checkout this sweep was started from (or the one asked for): its code trains, whatever copy a worker
    # imports first.
    pending = {remote.remote(spec, out, threads, str(code_root)): spec for spec in specs}
    done = failed = 0
    durations: List[float] = []
    last_report = time.time()
    while pending:
        ready, _ = ray.wait(list(pending), num_returns=1, timeout=progress_every)
        for ref in ready:
            spec = pending.pop(ref)
            try:
                record = ray.get(ref)
            except ray.exceptions.RayError as err:  # the worker died twice (Ray retried it once) or Ray failed
                record = _failed(spec, "worker", f"{type(err).__name__}: {str(err).strip().splitlines()[0]}", out)
            store.append(record)
            done += 1
            if record.get("started_at"):
                durations.append(record["finished_at"] - record["started_at"])
            if record["status"] == "ok":
                say(f"sweep: done {spec.scene} {spec.views}v {spec.label} seed {spec.seed}: PSNR {record['psnr']:.2f} "
                    f"SSIM {record['ssim']:.3f} LPIPS {record.get('lpips', float('nan')):.3f} "
                    f"({record['train_seconds'] / 60:.1f} min)")
            else:
                failed += 1
                say(f"sweep: FAILED {spec.scene} {spec.views}v {spec.label} seed {spec.seed} ({record.get('stage')}): "
                    f"{record.get('error')}; log {record.get('log')}")
        if ready or time.time() - last_report >= progress_every:
            last_report = time.time()
            running = min(len(pending), slots)
            eta = ""
            if durations and pending:
                eta = f"; ETA {statistics_eta(durations, len(pending), slots) / 60:.0f} min"
            say(f"sweep: {done}/{done + len(pending)} done ({failed} failed), {running} running, "
                f"{len(pending) - running} queued{eta}")


def statistics_eta(durations: Sequence[float], remaining: int, slots: int) -> float:
    """Seconds left: the mean run so far, times the rounds of ``slots`` parallel runs still to go."""
    return sum(durations) / len(durations) * math.ceil(remaining / max(1, slots))


def write_report(records: Sequence[Dict[str, Any]], out: Path) -> str:
    """results.md / results.json / pareto.png; the Markdown text."""
    out.mkdir(parents=True, exist_ok=True)
    text = report.scene_table(records)
    failures = report.failure_table(records)
    if failures:
        text += "\n\nFailed runs:\n\n" + failures
    (out / "results.md").write_text(text + "\n")
    (out / "results.json").write_text(json.dumps(list(records), indent=2, default=str))
    rows = report.anytime_rows(records)
    if rows:
        report.plot(rows, out)
    return text


def main(argv: Optional[List[str]] = None) -> int:
    parser = argparse.ArgumentParser(prog="frugalnerf-sweep", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("grid", type=Path, help="grid file (configs/sweeps/*.yaml)")
    parser.add_argument("--out", type=Path, help="results folder (default outputs/sweep/<grid name>)")
    parser.add_argument("--address", help="a running Ray cluster (default: RAY_ADDRESS, else Ray inside this command)")
    parser.add_argument("--cpus-per-run", type=int, help="cores per run (default 2; 1 with a GPU)")
    parser.add_argument("--gpus-per-run", type=float, help="GPUs per run (default 1 where the cluster has GPUs)")
    parser.add_argument("--data-root", type=Path, help="where the scenes file's data paths start, as workers see it")
    parser.add_argument("--max-iterations", type=int, help="every run's iteration budget (default: the grid's)")
    parser.add_argument("--retry-failed", action="store_true", help="re-run failed runs however often they failed")
    parser.add_argument("--list", action="store_true", help="print the runs and whether they are done, then exit")
    args = parser.parse_args(argv)

    try:
        specs = load_grid(args.grid, args.data_root, args.max_iterations)
    except GridError as err:
        print(f"frugalnerf-sweep: {err}", file=sys.stderr)
        return 1
    out = args.out or outputs_dir("sweep", args.grid.stem)
    if not (args.address or os.environ.get("RAY_ADDRESS")):
        missing = sorted({s.data for s in specs if not Path(s.data).is_dir()})
        if missing:
            print(f"frugalnerf-sweep: scene data not found: {', '.join(missing)} (--data-root, or the scenes file's "
                  "data paths)", file=sys.stderr)
            return 1
    if args.list:
        todo = set(ResultStore(out / "results.jsonl").to_run([s.key for s in specs], args.retry_failed))
        for spec in specs:
            print(f"{spec.key}  {'todo' if spec.key in todo else 'done'}  {spec.scene} {spec.views}v {spec.label} "
                  f"seed {spec.seed}")
        return 0
    records = run_sweep(specs, out, args.address, args.cpus_per_run, args.gpus_per_run, args.retry_failed)
    print()
    print(write_report(records, out))
    failed = [r for r in records if r.get("status") != "ok"]
    print(f"\nfrugalnerf-sweep: {len(records) - len(failed)}/{len(specs)} runs ok; wrote {out / 'results.md'}")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
