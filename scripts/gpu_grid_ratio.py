"""Issue 32's ablation at the paper preset's grid on one CUDA machine: ``frugalnerf`` (640^3 full scale, 5000
steps, 4096 + 4096 rays) with and without L_geo on fern and flower 2-view at 1/8 resolution, several runs at once
on the one GPU, each scored by the offline evaluator, with the pseudo-depth check and a picture of test view 1.

  python scripts/gpu_grid_ratio.py --data-root ../shared/data/llff --out outputs/gpu_grid_ratio [--budget 430]

Runs wait in a queue (seed 42 of every cell first, then seed 43). Up to --parallel train at once: on a GPU a
training step of this package is mostly kernel launches from one Python thread, so runs side by side fill the
GPU's idle time (their step times are then not single-run speeds; the table says how many ran at once). A run
starts only while the time left under --budget exceeds the longest finished run's training time (or, before
any has finished, only in the first wave). A run still training when the budget ends is stopped and its latest
checkpoint is scored, marked with its step: such a row is not the preset's result.

Writes results.json and results.md (the table) in --out (rows.json as it goes), and pictures.tar (diagnose_views.py's strip of test
view 1 per run: ground truth, each scale, depths) and logs.tar.

On a CPU, ``--preset frugalnerf-cpu --extra --max-num-iterations 20 --machine.device-type cpu`` runs the same
driver in a minute (what the tests of this script would do; it needs no GPU).
"""

from __future__ import annotations

import argparse
import json
import re
import subprocess
import sys
import tarfile
import threading
import time
from pathlib import Path
from typing import Dict, List, Optional

CELLS = {"fern": ("6", "13"), "flower": ("11", "22"), "horns": ("20", "42")}
VARIANTS = {"full": [], "nogeo": ["--pipeline.model.geo-weight", "0"], "one-scale": ["--pipeline.model.num-lower-scales", "0"]}
PYTHON = sys.executable


def latest_checkpoint(run_dir: Path) -> Optional[Path]:
    checkpoints = sorted((run_dir / "nerfstudio_models").glob("step-*.ckpt"))
    return checkpoints[-1] if checkpoints else None


def last_logged_step(log: Path) -> Optional[int]:
    """The last "NNNN (xx.xx%)" progress line of nerfstudio's trainer log."""
    steps = re.findall(rb"^(\d+) \(\s*[\d.]+%\)", log.read_bytes(), flags=re.M) if log.exists() else []
    return int(steps[-1]) if steps else None


class Job:
    def __init__(self, scene: str, variant: str, seed: int, args) -> None:
        self.scene, self.variant, self.seed, self.args = scene, variant, seed, args
        self.name = f"{scene}-{variant}"
        self.run_dir = args.work / "runs" / self.name / args.preset / f"s{seed}"
        self.log = args.work / "logs" / f"{self.name}.s{seed}.train.log"
        self.row: Dict = {"scene": scene, "variant": variant, "seed": seed, "preset": args.preset}
        self.thread: Optional[threading.Thread] = None

    def train_command(self) -> List[str]:
        a = self.args
        return [PYTHON, "-m", "frugalnerf_ns.tools.offline_tools", "train", a.preset, "--data", str(a.data_root / self.scene),
                "--output-dir", str(a.work / "runs"), "--experiment-name", self.name, "--timestamp", f"s{self.seed}",
                "--vis", "tensorboard", "--steps-per-eval-image", "1000000", "--steps-per-eval-batch", "1000000",
                "--steps-per-eval-all-images", "1000000", "--steps-per-save", str(a.save_every),
                "--machine.seed", str(self.seed), "--pipeline.datamanager.seed", str(self.seed),
                *VARIANTS[self.variant], *a.extra, "frugal-llff", "--downscale-factor", "8",
                "--train-views", *CELLS[self.scene]]

    def run(self, deadline: float, concurrent: int) -> None:
        self.log.parent.mkdir(parents=True, exist_ok=True)
        start = time.time()
        self.row["ran_beside"] = concurrent - 1
        with self.log.open("wb") as log:
            proc = subprocess.Popen(self.train_command(), stdout=log, stderr=subprocess.STDOUT)
            try:
                proc.wait(timeout=max(deadline - time.time(), 1))
                self.row["stopped_at_budget"] = False
            except subprocess.TimeoutExpired:
                proc.terminate()
                try:
                    proc.wait(timeout=20)
                except subprocess.TimeoutExpired:
                    proc.kill()
                    proc.wait()
                self.row["stopped_at_budget"] = True
        self.row["train_s"] = round(time.time() - start, 1)
        self.row["exit"] = proc.returncode
        self.row["last_logged_step"] = last_logged_step(self.log)
        checkpoint = latest_checkpoint(self.run_dir)
        if checkpoint is None:
            self.row["error"] = f"no checkpoint (log {self.log.name}: {tail(self.log)})"
            return
        self.row["checkpoint_step"] = int(checkpoint.stem.split("-")[1])
        self.score()

    def score(self) -> None:
        config = self.run_dir / "config.yml"
        result = run_logged([PYTHON, "-m", "frugalnerf_ns.tools.offline_tools", "eval", str(config)],
                            self.args.work / "logs" / f"{self.name}.s{self.seed}.eval.log", timeout=self.args.eval_timeout)
        match = re.findall(r"^RESULT (\{.*\})$", result, flags=re.M)
        if match:
            scores = json.loads(match[-1])
            self.row.update({k: scores[k] for k in ("psnr", "ssim", "lpips") if k in scores})
        else:
            self.row["error"] = f"eval: {result.strip().splitlines()[-1][:200] if result.strip() else 'no output'}"
        if self.args.pictures:
            run_logged([PYTHON, "scripts/diagnostics/diagnose_views.py", str(config), "--test", "1", "--train",
                        "--out", str(self.args.work / "pictures" / f"{self.name}.s{self.seed}")],
                       self.args.work / "logs" / f"{self.name}.s{self.seed}.pictures.log", timeout=self.args.eval_timeout)
        if self.args.pseudo_depth and self.variant == "full":
            run_logged([PYTHON, "scripts/diagnostics/check_pseudo_depth.py", str(config)],
                       self.args.work / "logs" / f"{self.name}.s{self.seed}.pseudo_depth.log", timeout=self.args.eval_timeout)


def tail(path: Path) -> str:
    lines = [line for line in path.read_text(errors="replace").splitlines() if line.strip()] if path.exists() else []
    return lines[-1][:200] if lines else "empty"


END = [float("inf")]
"""Wall-clock time (time.time()) by which every scoring subprocess must have ended (--end)."""


def run_logged(command: List[str], log: Path, timeout: float) -> str:
    log.parent.mkdir(parents=True, exist_ok=True)
    timeout = min(timeout, END[0] - time.time())
    if timeout < 15:
        log.write_text("skipped: no time left under --end")
        return "skipped: no time left under --end"
    try:
        proc = subprocess.run(command, capture_output=True, text=True, timeout=timeout)
        text = proc.stdout + proc.stderr
    except subprocess.TimeoutExpired as err:
        text = f"{err.stdout or ''}{err.stderr or ''}\ntimed out after {timeout} s"
    log.write_text(text)
    return text


def table(rows: List[Dict]) -> str:
    lines = ["| scene | variant | seed | PSNR | SSIM | LPIPS | train s | step scored | runs beside | note |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        note = "stopped at budget" if r.get("stopped_at_budget") else ""
        note = "; ".join(x for x in (note, r.get("error", "")) if x)
        fmt = lambda k, p: f"{r[k]:.{p}f}" if isinstance(r.get(k), float) else ""  # noqa: E731
        lines.append(f"| {r['scene']} | {r['variant']} | {r['seed']} | {fmt('psnr', 2)} | {fmt('ssim', 3)} | "
                     f"{fmt('lpips', 3)} | {r.get('train_s', '')} | {r.get('checkpoint_step', '')} | "
                     f"{r.get('ran_beside', '')} | {note} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data-root", type=Path, default=Path("../shared/data/llff"))
    parser.add_argument("--out", type=Path, default=Path("outputs/gpu_grid_ratio"))
    parser.add_argument("--preset", default="frugalnerf")
    parser.add_argument("--scenes", nargs="+", default=["fern", "flower"], choices=sorted(CELLS))
    parser.add_argument("--variants", nargs="+", default=["full", "nogeo"], choices=sorted(VARIANTS))
    parser.add_argument("--seeds", nargs="+", type=int, default=[42, 43])
    parser.add_argument("--parallel", type=int, default=4, help="runs training at once")
    parser.add_argument("--budget", type=float, default=430.0, help="seconds from start after which training stops")
    parser.add_argument("--end", type=float, default=None, help="seconds from start by which scoring stops too")
    parser.add_argument("--eval-timeout", type=float, default=120.0)
    parser.add_argument("--work", type=Path, default=None, help="runs, logs and pictures (default: --out)")
    parser.add_argument("--save-every", type=int, default=500, help="checkpoint interval (a stopped run is scored there)")
    parser.add_argument("--no-pictures", dest="pictures", action="store_false")
    parser.add_argument("--no-pseudo-depth", dest="pseudo_depth", action="store_false")
    parser.add_argument("--extra", nargs=argparse.REMAINDER, default=[], help="more ns-train options (last)")
    args = parser.parse_args(argv)
    for scene in args.scenes:
        if not (args.data_root / scene / "poses_bounds.npy").is_file():
            raise SystemExit(f"gpu_grid_ratio: error: no LLFF scene at {args.data_root / scene} (--data-root)")
    args.work = args.work or args.out
    args.out.mkdir(parents=True, exist_ok=True)
    started = time.time()
    deadline = started + args.budget
    if args.end is not None:
        END[0] = started + args.end
    queue = [Job(scene, variant, seed, args) for seed in args.seeds for scene in args.scenes for variant in args.variants]
    first_wave = min(args.parallel, len(queue))
    started_jobs: List[Job] = []
    last_report = time.time()
    while queue or any(j.thread.is_alive() for j in started_jobs):
        running = [j for j in started_jobs if j.thread.is_alive()]
        finished = [j for j in started_jobs if not j.thread.is_alive() and not j.row.get("stopped_at_budget")
                    and "train_s" in j.row]
        longest = max((j.row["train_s"] for j in finished), default=None)
        while queue and len(running) < args.parallel:
            in_first_wave = len(started_jobs) < first_wave
            if not in_first_wave and (longest is None or time.time() + longest > deadline):
                break
            job = queue.pop(0)
            job.thread = threading.Thread(target=job.run, args=(deadline, min(args.parallel, len(running) + 1 + len(queue))))
            job.thread.start()
            started_jobs.append(job)
            running.append(job)
            print(f"gpu_grid_ratio: {time.time() - started:6.0f} s: started {job.name} seed {job.seed}", flush=True)
        if queue and not running and (longest is None or time.time() + longest > deadline):
            break
        time.sleep(2)
        if time.time() - last_report > 60:  # step progress of each run, so a stopped call still shows the rates
            last_report = time.time()
            progress = ", ".join(f"{j.name} s{j.seed}: {last_logged_step(j.log)}" for j in running)
            print(f"gpu_grid_ratio: {time.time() - started:6.0f} s: steps {progress}", flush=True)
        (args.out / "rows.json").write_text(json.dumps([j.row for j in started_jobs], indent=1))
    rows = [j.row for j in started_jobs]
    summary = {"preset": args.preset, "extra": args.extra, "parallel": args.parallel, "budget_s": args.budget,
               "seconds": round(time.time() - started, 1), "not_started": [f"{j.name} s{j.seed}" for j in queue],
               "rows": rows}
    (args.out / "results.json").write_text(json.dumps(summary, indent=1))
    text = table(rows)
    (args.out / "results.md").write_text(text + "\n")
    for name in ("pictures", "logs"):
        folder = args.work / name
        if folder.exists():
            with tarfile.open(args.out / f"{name}.tar", "w") as tar:
                tar.add(folder, arcname=name)
    for job in started_jobs:
        if "error" in job.row and job.log.exists():  # the end of a failed run's log, where it is read
            print(f"--- {job.log.name} (last lines)")
            print("\n".join(job.log.read_text(errors="replace").splitlines()[-15:]))
    print(text)
    print(f"gpu_grid_ratio: {len(rows)} runs in {summary['seconds']} s; not started: {summary['not_started']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
