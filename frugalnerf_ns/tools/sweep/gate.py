"""``frugalnerf-gate``: the quality gate. Trains each scene's CPU preset on the scenes of ``configs/gate.yaml``
with that scene's seeds, scores every run with the one evaluator (the sweep runner), and compares each scene's
mean over its seeds with the recorded baseline (``configs/gate_baseline.yaml``) within the scene's tolerance.

  frugalnerf-gate                       # every scene; prints a table, exits 1 on a regression
  frugalnerf-gate --scenes horns        # a subset (the verdict covers only these scenes)
  frugalnerf-gate --record              # write the baseline file from this run (say why in the commit; the
                                        # comment lines under its header are kept)
  frugalnerf-gate --list                # the runs and whether they are done
  frugalnerf-gate --against main        # the baseline trained here: the same runs with main's code (a git
                                        # worktree in outputs/gate/worktrees), this machine's numbers on both sides

Runs go to ``outputs/gate/<commit>`` (``<commit>-dirty-<hash of the diff>`` with uncommitted changes), so the
same code resumes its own runs and never reuses another commit's. A scene fails when its mean PSNR or SSIM
falls below the baseline's by more than the tolerance, or its LPIPS rises above it by more, or when its seeds
spread more than the scene's ``max_spread`` (dB) and more than the baseline's spread plus the PSNR tolerance
(a spread within that is shown as a missed target, not a regression).

The same code and seed train to different numbers on another processor or torch build (floating-point rounding
that training amplifies: juice box 3-view seed 43 gave 23.15 dB on one machine and 24.30 on another). The gate
says so when the baseline file's runs came from another machine, or do not name theirs; ``--against REV``
compares with REV's code trained on this machine instead of the file.
"""

from __future__ import annotations

import argparse
import datetime
import hashlib
import statistics
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Dict, List, Mapping, Optional, Sequence, Union

import yaml

from frugalnerf_ns.config_files import CheckoutRequired, checkout_root, config_path, outputs_dir, require_checkout
from frugalnerf_ns.tools.sweep.grid import SCENE_PRESET, GridError, RunSpec, expand

METRICS = ("psnr", "ssim", "lpips")
HIGHER_IS_BETTER = {"psnr": True, "ssim": True, "lpips": False}
GATE_FILE = config_path("gate.yaml")
BASELINE_FILE = config_path("gate_baseline.yaml")
# The checkout whose git history names the runs' code (None for an installed package: main() stops in one line).
ROOT = checkout_root()


class GateError(ValueError):
    """A gate or baseline file that cannot be used; the message names the file and the entry."""


@dataclass(frozen=True)
class GateScene:
    name: str  # scene name in the scenes file
    views: int
    seeds: List[int]
    tolerance: Dict[str, float]  # metric -> allowed worsening of the mean
    max_spread: Optional[float] = None  # target dB between the best and worst seed (scenes run with several)

    @property
    def label(self) -> str:
        return f"{self.name}-{self.views}v"


def _read_yaml(path: Path, what: str) -> Dict[str, Any]:
    try:
        data = yaml.safe_load(Path(path).read_text())
    except OSError as err:
        raise GateError(f"{path}: cannot read the {what} ({err.strerror or err})") from None
    except yaml.YAMLError as err:
        raise GateError(f"{path}: the {what} is not valid YAML ({str(err).splitlines()[0]})") from None
    if not isinstance(data, dict):
        raise GateError(f"{path}: the {what} must be a mapping")
    return data


def _is_int(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def load_gate(path: Path = GATE_FILE) -> tuple:
    """(scenes file, [GateScene]) of a gate file."""
    gate = _read_yaml(path, "gate file")
    scenes = gate.get("scenes")
    if not isinstance(scenes, dict) or not scenes:
        raise GateError(f"{path}: `scenes:` is empty or missing")
    out, labels = [], {}
    for key, entry in scenes.items():
        entry = entry or {}
        if not isinstance(entry, dict):
            raise GateError(f"{path}: scene {key!r} must map views / seeds / tolerance to values")
        # An entry's key is the scene's name in the scenes file unless it names one with `scene:`, so one scene
        # can be gated with several view counts (fern with 2 views and with 3).
        name = entry.get("scene", key)
        if not isinstance(name, str) or not name:
            raise GateError(f"{path}: entry {key!r}: `scene:` must name a scene of the scenes file, not {name!r}")
        seeds = entry.get("seeds")
        if not isinstance(seeds, list) or not seeds or not all(_is_int(s) for s in seeds):
            raise GateError(f"{path}: scene {key!r} needs `seeds:`, a list of integers")
        tolerance = entry.get("tolerance") or {}
        if not isinstance(tolerance, dict):
            raise GateError(f"{path}: scene {key!r}: `tolerance:` must map psnr / ssim / lpips to numbers")
        missing = [m for m in METRICS if not _is_number(tolerance.get(m))]
        if missing:
            raise GateError(f"{path}: scene {key!r} has no tolerance for {', '.join(missing)}")
        views, max_spread = entry.get("views", 2), entry.get("max_spread")
        if not _is_int(views) or views < 1:
            raise GateError(f"{path}: scene {key!r}: `views:` must be a positive integer, not {views!r}")
        if max_spread is not None and not _is_number(max_spread):
            raise GateError(f"{path}: scene {key!r}: `max_spread:` must be a number of dB, not {max_spread!r}")
        scene = GateScene(str(name), int(views), list(seeds), {m: float(tolerance[m]) for m in METRICS},
                          None if max_spread is None else float(max_spread))
        if scene.label in labels:
            raise GateError(f"{path}: entries {labels[scene.label]!r} and {key!r} both gate {scene.label}")
        labels[scene.label] = key
        out.append(scene)
    scenes_file = (Path(path).parent / gate.get("scenes_file", "benchmark_scenes.yaml")).resolve()
    return scenes_file, out


def gate_specs(scenes_file: Path, scenes: Sequence[GateScene], data_root: Optional[Path] = None,
               max_iterations: Optional[int] = None) -> Dict[str, List[RunSpec]]:
    """Scene label -> its runs (the scene's CPU preset, one per seed)."""
    try:
        return {s.label: expand(scenes_file, [s.name], [s.views], [SCENE_PRESET], {"full": []}, s.seeds,
                                max_iterations, data_root=data_root) for s in scenes}
    except GridError as err:
        raise GateError(str(err)) from None


def load_baseline(path: Path = BASELINE_FILE) -> Dict[str, Any]:
    baseline = _read_yaml(path, "baseline file")
    if not isinstance(baseline.get("scenes"), dict):
        raise GateError(f"{path}: no `scenes:` section (write one with `frugalnerf-gate --record`)")
    for label, entry in baseline["scenes"].items():
        if not isinstance(entry, dict) or not isinstance(entry.get("mean"), dict):
            raise GateError(f"{path}: scene {label!r} has no `mean:` mapping")
        mean = entry["mean"]
        missing = [m for m in METRICS if not _is_number(mean.get(m))]
        if missing:
            raise GateError(f"{path}: scene {label!r} has no mean {', '.join(missing)}")
    return baseline


def machine_name(record: Mapping[str, Any]) -> str:
    """What decides a run's floating-point rounding, from its record: processor, torch's vector instructions
    and build, GPU ("" for a record that does not say)."""
    info = record.get("machine") or {}
    parts = [info.get("cpu"), info.get("cpu_capability"), f"torch {info['torch']}" if info.get("torch") else None,
             info.get("gpu")]
    return ", ".join(str(p) for p in parts if p)


def summarise(records: Sequence[Mapping[str, Any]]) -> Dict[str, Any]:
    """Mean and spread (max - min) of each metric over a scene's ok runs, each seed's values, and the machines
    they trained on."""
    ok = [r for r in records if r.get("status") == "ok"]
    if not ok:
        return {"runs": 0}
    return {
        "runs": len(ok),
        "mean": {m: statistics.fmean(float(r[m]) for r in ok) for m in METRICS},
        "spread": {m: max(float(r[m]) for r in ok) - min(float(r[m]) for r in ok) for m in METRICS},
        "seeds": {int(r["seed"]): {m: round(float(r[m]), 4) for m in METRICS} for r in ok},
        "machine": "; ".join(sorted({machine_name(r) for r in ok})),
    }


def other_machines(scenes: Sequence["GateScene"], summaries: Mapping[str, Mapping[str, Any]],
                   baseline: Mapping[str, Any]) -> List[str]:
    """Labels of the scenes whose baseline was trained on another machine than this run's, or does not say
    where (entries recorded before the gate kept the machine)."""
    base_scenes = baseline.get("scenes") or {}
    return [s.label for s in scenes if summaries.get(s.label, {}).get("runs") and s.label in base_scenes
            and (base_scenes[s.label].get("machine") or "") != summaries[s.label]["machine"]]


def verdict(scene: GateScene, summary: Mapping[str, Any], baseline: Optional[Mapping[str, Any]]) -> List[str]:
    """The reasons this scene fails the gate (empty: it passes). A scene without a baseline entry, or with a
    run missing, fails: the gate cannot say it did not get worse."""
    if summary.get("runs", 0) < len(scene.seeds):
        return [f"{len(scene.seeds) - summary.get('runs', 0)} of {len(scene.seeds)} runs failed"]
    if baseline is None:
        return ["no baseline for this scene (record one with --record)"]
    reasons = []
    for metric in METRICS:
        new, old, tol = summary["mean"][metric], float(baseline["mean"][metric]), scene.tolerance[metric]
        worse = (old - new) if HIGHER_IS_BETTER[metric] else (new - old)
        if worse > tol:
            reasons.append(f"{metric} {new:.3f} vs baseline {old:.3f} (worse by {worse:.3f} > {tol:g})")
    spread = summary["spread"]["psnr"]
    if scene.max_spread is not None and spread > scene.max_spread:
        before = (baseline.get("spread") or {}).get("psnr")
        if before is None or spread > max(float(before) + scene.tolerance["psnr"], scene.max_spread):
            reasons.append(f"seed spread {spread:.2f} dB > {scene.max_spread:g}"
                           + (f" and > baseline {float(before):.2f} + {scene.tolerance['psnr']:g}" if before is not None else ""))
    return reasons


def table(scenes: Sequence[GateScene], summaries: Mapping[str, Mapping[str, Any]],
          baseline: Mapping[str, Any], failures: Mapping[str, List[str]]) -> str:
    base_scenes = baseline.get("scenes") or {}
    lines = [f"| scene | seeds | PSNR (spread) | SSIM | LPIPS | baseline {baseline.get('commit', '?')} "
             "PSNR / SSIM / LPIPS | tolerance | verdict |", "|---" * 8 + "|"]
    for s in scenes:
        summary, base = summaries.get(s.label, {}), base_scenes.get(s.label)
        if summary.get("runs"):
            mean, spread = summary["mean"], summary["spread"]
            ours = f"{mean['psnr']:.2f} ({spread['psnr']:.2f}) | {mean['ssim']:.3f} | {mean['lpips']:.3f}"
        else:
            ours = "- | - | -"
        theirs = (f"{base['mean']['psnr']:.2f} / {base['mean']['ssim']:.3f} / {base['mean']['lpips']:.3f}"
                  if base else "-")
        tol = f"{s.tolerance['psnr']:g} / {s.tolerance['ssim']:g} / {s.tolerance['lpips']:g}"
        result = "FAIL: " + "; ".join(failures[s.label]) if failures.get(s.label) else "ok"
        if not failures.get(s.label) and s.max_spread is not None and summary.get("runs") \
                and summary["spread"]["psnr"] > s.max_spread:
            before = ((base or {}).get("spread") or {}).get("psnr")
            result += (f" (target missed: seed spread {summary['spread']['psnr']:.2f} dB > {s.max_spread:g}"
                       + (f"; baseline {float(before):.2f})" if before is not None else ")"))
        lines.append(f"| {s.label} | {' '.join(map(str, s.seeds))} | {ours} | {theirs} | {tol} | {result} |")
    return "\n".join(lines)


def baseline_document(scenes: Sequence[GateScene], summaries: Mapping[str, Mapping[str, Any]],
                      commit: Union[str, Mapping[str, str]],
                      previous: Optional[Mapping[str, Any]] = None) -> Dict[str, Any]:
    """The baseline file's content from this run's summaries; scenes not run keep their previous entry.
    ``commit``: the commit the runs were trained at, or per scene label (``a+b`` when its seeds' runs differ)."""
    entries = dict((previous or {}).get("scenes") or {})
    for s in scenes:
        summary = summaries[s.label]
        entries[s.label] = {"commit": commit if isinstance(commit, str) else commit[s.label], "seeds": summary["seeds"],
                            "mean": {m: round(v, 4) for m, v in summary["mean"].items()},
                            "spread": {m: round(v, 4) for m, v in summary["spread"].items()},
                            "machine": summary["machine"]}
    # The file's commit names every commit its scenes were recorded at (a subset recorded later adds its own).
    commits = sorted({c for e in entries.values() if e.get("commit") for c in str(e["commit"]).split("+")})
    return {"commit": "+".join(commits or [str(commit)]), "recorded": datetime.date.today().isoformat(), "scenes": entries}


def resolve_commit(rev: str, root: Path = ROOT) -> str:
    """``rev``'s short commit hash in the repository at ``root`` (GateError in one line when it names none)."""
    try:
        out = subprocess.run(["git", "-C", str(root), "rev-parse", "--short", "--verify", "--quiet", f"{rev}^{{commit}}"],
                             capture_output=True, text=True, timeout=30)
    except (OSError, subprocess.TimeoutExpired) as err:
        raise GateError(f"--against {rev}: cannot run git in {root} ({err})") from None
    if out.returncode != 0 or not out.stdout.strip():
        raise GateError(f"--against {rev}: not a commit of the repository at {root}")
    return out.stdout.strip()


def checkout(commit: str, root: Path = ROOT) -> Path:
    """A detached git worktree of ``commit`` in ``<root>/outputs/gate/worktrees/<commit>`` (reused when it is
    there): the code the ``--against`` runs train with."""
    dest = Path(root) / "outputs" / "gate" / "worktrees" / commit
    if (dest / ".git").exists():
        return dest
    dest.parent.mkdir(parents=True, exist_ok=True)
    made = subprocess.run(["git", "-C", str(root), "worktree", "add", "--detach", str(dest), commit],
                          capture_output=True, text=True, timeout=300)
    if made.returncode != 0:
        reason = (made.stderr.strip().splitlines() or ["git worktree add failed"])[-1]
        raise GateError(f"--against {commit}: cannot check it out in {dest} ({reason})")
    return dest


# What a run computes depends on these; the gate's own files, docs and tests do not change it.
TRAINING_PATHS = ("frugalnerf_ns", "configs", "pyproject.toml", "constraints.txt", ":(exclude)configs/gate*.yaml",
                  ":(exclude)frugalnerf_ns/tools/sweep/gate.py")


def code_version(root: Path = ROOT) -> str:
    """The commit, with ``-dirty-<hash>`` of the uncommitted diff when the code or configs have one (docs and
    tests do not change what a run computes)."""
    def git(*args: str) -> str:
        return subprocess.run(["git", *args], capture_output=True, text=True, cwd=root, timeout=30).stdout

    try:
        commit = git("rev-parse", "--short", "HEAD").strip() or "unknown"
        diff = git("diff", "--binary", "HEAD", "--", *TRAINING_PATHS)
        # New files git does not track yet (and does not ignore) change the code as much as edits do.
        for name in sorted(git("ls-files", "--others", "--exclude-standard", "--", *TRAINING_PATHS).splitlines()):
            try:
                diff += f"\nnew file {name}\n" + hashlib.sha1((Path(root) / name).read_bytes()).hexdigest()
            except OSError:
                diff += f"\nnew file {name} (unreadable)\n"
    except (OSError, subprocess.TimeoutExpired):
        return "unknown"
    return f"{commit}-dirty-{hashlib.sha1(diff.encode()).hexdigest()[:8]}" if diff else commit


BASELINE_HEADER = ("# Quality gate baseline: each scene's mean over its seeds, written by `frugalnerf-gate --record`.\n"
                   "# Update it only in a commit that means to move the numbers, and say why there.\n")


def kept_comments(path: Path) -> str:
    """The comment lines at the top of an existing baseline file, less the header ``--record`` writes itself: what
    someone wrote there about the runs (which commit trained which entry, why) survives the next recording."""
    try:
        lines = Path(path).read_text().splitlines()
    except (OSError, UnicodeDecodeError):
        return ""
    own = set(BASELINE_HEADER.splitlines())
    kept = []
    for line in lines:
        if not line.startswith("#"):
            break
        if line not in own:
            kept.append(line + "\n")
    return "".join(kept)


def against_baseline(commit: str, every: Sequence[RunSpec], specs: Mapping[str, Sequence[RunSpec]],
                     out: Optional[Path], cpus_per_run: Optional[int]) -> Dict[str, Any]:
    """The baseline of ``--against``: the same runs trained on this machine with ``commit``'s code (checked out
    only when some run is not finished in ``out``), summarised like the baseline file's entries."""
    from frugalnerf_ns.tools.sweep.cli import run_sweep
    from frugalnerf_ns.tools.sweep.store import ResultStore

    out = (out or outputs_dir("gate", commit)).resolve()
    done = ResultStore(out / "results.jsonl").latest([s.key for s in every])
    todo = [s for s in every if done.get(s.key, {}).get("status") != "ok"]
    code_root = checkout(commit) if todo else None
    print(f"frugalnerf-gate: the baseline: {len(every)} runs with the code of {commit} in {out}, {len(todo)} to train")
    records = {r["key"]: r for r in run_sweep(every, out, cpus_per_run=cpus_per_run, code_root=code_root)}
    scenes = {label: summarise([records[s.key] for s in group if s.key in records]) for label, group in specs.items()}
    return {"commit": f"{commit} (trained here)", "scenes": {label: v for label, v in scenes.items() if v.get("runs")}}


def main(argv: Optional[List[str]] = None) -> int:
    parser = argparse.ArgumentParser(prog="frugalnerf-gate", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--gate", type=Path, default=GATE_FILE, help="gate file (default configs/gate.yaml)")
    parser.add_argument("--baseline", type=Path, default=BASELINE_FILE,
                        help="baseline file (default configs/gate_baseline.yaml)")
    parser.add_argument("--scenes", nargs="*", help="scene labels or names to run (default: all)")
    parser.add_argument("--out", type=Path, help="runs folder (default outputs/gate/<commit>)")
    parser.add_argument("--data-root", type=Path, help="where the scenes file's data paths start")
    parser.add_argument("--cpus-per-run", type=int, help="cores per run (default 2: one training at a time)")
    parser.add_argument("--max-iterations", type=int, help="every run's budget (a smoke test; never --record it)")
    parser.add_argument("--record", action="store_true", help="write the baseline file from this run's results")
    parser.add_argument("--list", action="store_true", help="print the runs and whether they are done, then exit")
    parser.add_argument("--against", metavar="REV", help="compare with the same runs trained here with REV's code "
                        "(a git worktree) instead of the baseline file: both sides on this machine")
    parser.add_argument("--against-out", type=Path, help="runs folder of --against (default outputs/gate/<REV's commit>)")
    args = parser.parse_args(argv)
    try:
        require_checkout("frugalnerf-gate", "its git history names the code each run trained")
    except CheckoutRequired as err:
        print(f"frugalnerf-gate: {err}", file=sys.stderr)
        return 2
    if args.against and args.record:
        print("frugalnerf-gate: --record writes this code's runs into the baseline file and --against compares with "
              "another commit's runs: use one of them", file=sys.stderr)
        return 2

    from frugalnerf_ns.tools.sweep.cli import run_sweep
    from frugalnerf_ns.tools.sweep.store import ResultStore

    try:
        scenes_file, scenes = load_gate(args.gate)
        if args.scenes:
            unknown = sorted(set(args.scenes) - {s.label for s in scenes} - {s.name for s in scenes})
            if unknown:
                raise GateError(f"{args.gate}: no scene {unknown[0]!r} (it has {', '.join(s.label for s in scenes)})")
            scenes = [s for s in scenes if s.label in args.scenes or s.name in args.scenes]
        specs = gate_specs(scenes_file, scenes, args.data_root, args.max_iterations)
        baseline = {}
        if args.record and args.baseline.exists():
            try:  # scenes this run does not record keep their entries; an unreadable file is replaced
                baseline = load_baseline(args.baseline)
            except GateError as err:
                print(f"frugalnerf-gate: replacing the unreadable baseline: {err}", file=sys.stderr)
        elif not args.record and not args.list and not args.against:
            baseline = load_baseline(args.baseline)
        against = resolve_commit(args.against) if args.against else None
    except GateError as err:
        print(f"frugalnerf-gate: {err}", file=sys.stderr)
        return 2
    if args.record and args.max_iterations:
        print("frugalnerf-gate: --record with --max-iterations would record a shortened run as the baseline",
              file=sys.stderr)
        return 2
    version = code_version()
    out = (args.out or outputs_dir("gate", version)).resolve()
    every = [spec for group in specs.values() for spec in group]
    if args.list:
        latest = ResultStore(out / "results.jsonl").latest([s.key for s in every])
        for label, group in specs.items():
            for spec in group:
                status = latest.get(spec.key, {}).get("status")
                state = "done" if status == "ok" else "failed before" if status else "todo"
                print(f"{label} seed {spec.seed}: {state} ({spec.key})")
        print(f"runs folder: {out}")
        return 0
    missing = sorted({s.data for s in every if not Path(s.data).is_dir()})
    if missing:
        print(f"frugalnerf-gate: scene data not found: {', '.join(missing)} (--data-root)", file=sys.stderr)
        return 2
    print(f"frugalnerf-gate: code {version}, {len(every)} runs in {out}")
    records = {r["key"]: r for r in run_sweep(every, out, cpus_per_run=args.cpus_per_run)}
    summaries = {label: summarise([records[s.key] for s in group if s.key in records])
                 for label, group in specs.items()}
    if against:
        try:
            baseline = against_baseline(against, every, specs, args.against_out, args.cpus_per_run)
        except GateError as err:
            print(f"frugalnerf-gate: {err}", file=sys.stderr)
            return 2
    failures = {s.label: verdict(s, summaries[s.label], (baseline.get("scenes") or {}).get(s.label))
                for s in scenes}
    text = table(scenes, summaries, baseline, failures)
    elsewhere = other_machines(scenes, summaries, baseline)
    if elsewhere:
        here = next(summaries[label]["machine"] for label in elsewhere)
        text += (f"\n\nNote: the baseline of {', '.join(elsewhere)} was trained on another machine than these runs "
                 f"({here or 'a machine the records do not name'}), or its entry does not say on which: the same code "
                 "trains to different numbers on another processor or torch build; `--against <commit>` trains the "
                 "baseline's code here.")
    (out / "gate.md").write_text(f"code {version}\n\n{text}\n")
    print()
    print(text)
    if args.record:
        broken = [s.label for s in scenes if summaries[s.label].get("runs", 0) < len(s.seeds)]
        if broken:
            print(f"frugalnerf-gate: not recording: runs failed on {', '.join(broken)}", file=sys.stderr)
            return 1
        # The commit the runs were trained at (a resumed or --out folder may hold another commit's runs).
        trained_at = {label: "+".join(sorted({str(records[spec.key].get("commit") or version)
                                              for spec in group if spec.key in records}))
                      for label, group in specs.items()}
        document = baseline_document(scenes, summaries, trained_at, baseline)
        args.baseline.write_text(BASELINE_HEADER + kept_comments(args.baseline) + yaml.safe_dump(document, sort_keys=False))
        print(f"\nfrugalnerf-gate: recorded the baseline of {document['commit']} in {args.baseline}")
        return 0
    failed = [label for label, reasons in failures.items() if reasons]
    print(f"\nfrugalnerf-gate: {'FAILED on ' + ', '.join(failed) if failed else 'passed'} ({out / 'gate.md'})")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
