"""The quality gate: its files, the verdict per scene, and the command end to end on recorded run results
(the runs themselves are the sweep runner's, tested in test_sweep.py)."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import pytest
import yaml

from frugalnerf_ns.tools.sweep import gate
from frugalnerf_ns.tools.sweep.store import ResultStore

ROOT = Path(__file__).resolve().parents[1]


def test_repository_gate_covers_every_scene_with_its_cpu_preset():
    scenes_file, scenes = gate.load_gate(ROOT / "configs" / "gate.yaml")
    by_label = {s.label: s for s in scenes}
    assert set(by_label) == {"fern-2v", "fern-3v", "flower-2v", "horns-2v", "dtu_scan65-2v", "juice_box-3v", "juice_box-4v",
                             "bird-3v", "fortress-2v", "re10k_5aca-2v"}
    assert len(by_label["horns-2v"].seeds) >= 2 and by_label["horns-2v"].max_spread is not None
    specs = gate.gate_specs(scenes_file, scenes)
    methods = {label: {s.method for s in group} for label, group in specs.items()}
    assert methods == {"fern-2v": {"frugalnerf-cpu"}, "fern-3v": {"frugalnerf-cpu"}, "flower-2v": {"frugalnerf-cpu"},
                       "horns-2v": {"frugalnerf-cpu"}, "dtu_scan65-2v": {"frugalnerf-dtu-cpu"},
                       "juice_box-3v": {"frugalnerf-cpu"}, "juice_box-4v": {"frugalnerf-cpu"},
                       "bird-3v": {"frugalnerf-cpu"}, "fortress-2v": {"frugalnerf-cpu"},
                       "re10k_5aca-2v": {"frugalnerf-cpu"}}
    # a scene the presets were not tuned on, with its own principal point; a RealEstate-10K clip
    assert specs["fortress-2v"][0].parser_args == ["frugal-llff", "--principal-point", "502.15", "381.09",
                                                   "--train-views", "13", "28"]
    assert specs["re10k_5aca-2v"][0].parser_args == ["frugal-realestate", "--num-train-views", "2"]
    assert specs["fern-3v"][0].parser_args[-2:] == ["--num-train-views", "3"]
    horns = specs["horns-2v"]
    assert [s.seed for s in horns] == by_label["horns-2v"].seeds
    assert horns[0].parser_args[-3:] == ["--train-views", "20", "42"]
    # each seed seeds both nerfstudio and our batch sampler
    assert horns[1].train_args[-4:] == ["--machine.seed", str(horns[1].seed), "--pipeline.datamanager.seed",
                                        str(horns[1].seed)]
    # two seeds on the juice box: one seed passed a lambda_geo that swings it by 3.5 dB with the seed
    assert len(by_label["juice_box-3v"].seeds) >= 2
    # the wide split: four frames from across the arc, the LLFF default test list
    assert specs["juice_box-4v"][0].parser_args[-5:] == ["--train-views", "45", "13", "29", "46"]
    # the full circle: frames between the training views as tests
    assert specs["bird-3v"][0].parser_args[-9:] == ["--train-views", "0", "23", "46", "--test-views", "8", "15", "31", "38"]
    assert len({s.key for group in specs.values() for s in group}) == 12


def _scene(max_spread=None, seeds=(1, 2)):
    return gate.GateScene("s", 2, list(seeds), {"psnr": 0.3, "ssim": 0.01, "lpips": 0.015}, max_spread)


def _records(psnrs, ssim=0.5, lpips=0.4):
    return [{"status": "ok", "seed": i, "psnr": p, "ssim": ssim, "lpips": lpips} for i, p in enumerate(psnrs)]


def test_verdict_flags_each_metric_beyond_its_tolerance_and_only_then():
    scene = _scene()
    base = {"mean": {"psnr": 17.0, "ssim": 0.5, "lpips": 0.4}}
    assert gate.verdict(scene, gate.summarise(_records([16.8, 16.9])), base) == []  # 0.15 dB lower: within
    assert gate.verdict(scene, gate.summarise(_records([18.0, 19.0])), base) == []  # better never fails
    worse = gate.verdict(scene, gate.summarise(_records([16.5, 16.8])), base)  # mean 16.65: 0.35 dB lower
    assert len(worse) == 1 and worse[0].startswith("psnr 16.650 vs baseline 17.000")
    worse = gate.verdict(scene, gate.summarise(_records([17.0, 17.0], ssim=0.48, lpips=0.42)), base)
    assert [r.split()[0] for r in worse] == ["ssim", "lpips"]


def test_verdict_demands_every_run_a_baseline_and_a_small_seed_spread():
    base = {"mean": {"psnr": 17.0, "ssim": 0.5, "lpips": 0.4}}
    summary = gate.summarise(_records([17.0, 18.0]))
    assert summary["spread"]["psnr"] == pytest.approx(1.0) and summary["mean"]["psnr"] == pytest.approx(17.5)
    assert gate.verdict(_scene(max_spread=0.5), summary, base) == ["seed spread 1.00 dB > 0.5"]
    assert gate.verdict(_scene(max_spread=1.5), summary, base) == []
    # A spread the baseline already had is a missed target, not a regression; a wider one fails.
    assert gate.verdict(_scene(max_spread=0.5), summary, {**base, "spread": {"psnr": 0.9}}) == []
    assert gate.verdict(_scene(max_spread=0.5), summary, {**base, "spread": {"psnr": 0.6}}) == [
        "seed spread 1.00 dB > 0.5 and > baseline 0.60 + 0.3"]
    one_failed = gate.summarise([*_records([17.0]), {"status": "failed", "seed": 2}])
    assert gate.verdict(_scene(), one_failed, base) == ["1 of 2 runs failed"]
    assert "no baseline" in gate.verdict(_scene(), summary, None)[0]


def _gate_files(tmp_path: Path) -> tuple:
    """A two-scene gate over folders that exist (no training happens: the tests pre-fill the results)."""
    for name in ("a", "b"):
        (tmp_path / "data" / name).mkdir(parents=True)
    scenes = {"data_root": str(tmp_path / "data"),
              "scenes": {n: {"data": n, "parser": ["frugal-llff"], "views": {2: ["--train-views", "0", "1"]},
                             "preset": "frugalnerf-tiny"} for n in ("a", "b")}}
    (tmp_path / "scenes.yaml").write_text(yaml.safe_dump(scenes))
    tol = {"psnr": 0.3, "ssim": 0.01, "lpips": 0.015}
    (tmp_path / "gate.yaml").write_text(yaml.safe_dump({
        "scenes_file": "scenes.yaml",
        "scenes": {"a": {"views": 2, "seeds": [1], "tolerance": tol},
                   "b": {"views": 2, "seeds": [1, 2], "tolerance": tol, "max_spread": 0.5}}}))
    return tmp_path / "gate.yaml", tmp_path / "out"


def _fill(out: Path, gate_file: Path, psnr: dict, commit: str = "c0ffee1", machine: Optional[dict] = None) -> None:
    """Finished-run records for the gate's runs named in ``psnr``, as the sweep runner appends them."""
    scenes_file, scenes = gate.load_gate(gate_file)
    store = ResultStore(out / "results.jsonl")
    for label, group in gate.gate_specs(scenes_file, scenes).items():
        for spec in group:
            if (label, spec.seed) in psnr:
                store.append({**spec.to_dict(), "status": "ok", "psnr": psnr[(label, spec.seed)], "ssim": 0.5,
                              "lpips": 0.4, "train_seconds": 60.0, "commit": commit,
                              **({"machine": machine} if machine else {})})


def test_gate_command_records_a_baseline_then_passes_and_fails_on_a_regression(tmp_path, capsys):
    gate_file, out = _gate_files(tmp_path)
    baseline = tmp_path / "baseline.yaml"
    _fill(out, gate_file, {("a-2v", 1): 17.0, ("b-2v", 1): 15.0, ("b-2v", 2): 15.4})
    args = ["--gate", str(gate_file), "--baseline", str(baseline), "--out", str(out)]

    assert gate.main([*args, "--record"]) == 0
    recorded = gate.load_baseline(baseline)
    assert recorded["scenes"]["b-2v"]["mean"]["psnr"] == pytest.approx(15.2)
    assert recorded["scenes"]["b-2v"]["seeds"] == {1: {"psnr": 15.0, "ssim": 0.5, "lpips": 0.4},
                                                   2: {"psnr": 15.4, "ssim": 0.5, "lpips": 0.4}}
    assert recorded["commit"] == "c0ffee1"  # the commit the runs trained at, from their records
    assert recorded["scenes"]["a-2v"]["commit"] == "c0ffee1"

    assert gate.main(args) == 0  # the same results against their own baseline
    assert "passed" in capsys.readouterr().out
    assert (out / "gate.md").read_text().count("| ok |") == 2

    # The same runs, scene a now 0.5 dB lower (a new commit's results in a fresh folder).
    out2 = tmp_path / "out2"
    _fill(out2, gate_file, {("a-2v", 1): 16.5, ("b-2v", 1): 15.0, ("b-2v", 2): 15.4})
    assert gate.main(["--gate", str(gate_file), "--baseline", str(baseline), "--out", str(out2)]) == 1
    text = capsys.readouterr().out
    assert "FAILED on a-2v" in text and "| a-2v | 1 | 16.50 (0.00) |" in text
    assert "| b-2v | 1 2 | 15.20 (0.40) |" in text

    # The same spread as at the baseline, over the 0.5 dB target: shown, not failed.
    out_same = tmp_path / "out_same"
    recorded["scenes"]["b-2v"]["spread"]["psnr"] = 0.8
    baseline.write_text(yaml.safe_dump(recorded))
    _fill(out_same, gate_file, {("a-2v", 1): 17.0, ("b-2v", 1): 14.8, ("b-2v", 2): 15.6})
    assert gate.main(["--gate", str(gate_file), "--baseline", str(baseline), "--out", str(out_same)]) == 0
    assert "| ok (target missed: seed spread 0.80 dB > 0.5; baseline 0.80) |" in capsys.readouterr().out
    recorded["scenes"]["b-2v"]["spread"]["psnr"] = 0.4
    baseline.write_text(yaml.safe_dump(recorded))

    # Scene b's seeds now 0.9 dB apart: over its 0.5 dB target and 0.5 dB wider than at the baseline.
    out3 = tmp_path / "out3"
    _fill(out3, gate_file, {("a-2v", 1): 17.0, ("b-2v", 1): 14.8, ("b-2v", 2): 15.7})
    assert gate.main(["--gate", str(gate_file), "--baseline", str(baseline), "--out", str(out3)]) == 1
    assert "FAILED on b-2v" in capsys.readouterr().out

    # Recording one scene later, at another commit, keeps the other scene's entry; the file names both commits,
    # and the comment lines someone wrote under the header survive (once, the header itself not doubled).
    baseline.write_text(gate.BASELINE_HEADER + "# scene b trained by hand at c0ffee1\n" + yaml.safe_dump(recorded))
    out4 = tmp_path / "out4"
    _fill(out4, gate_file, {("a-2v", 1): 17.3}, commit="beef002")
    assert gate.main(["--gate", str(gate_file), "--baseline", str(baseline), "--out", str(out4), "--scenes", "a", "--record"]) == 0
    both = gate.load_baseline(baseline)
    assert both["commit"] == "beef002+c0ffee1"
    assert both["scenes"]["a-2v"]["commit"] == "beef002" and both["scenes"]["a-2v"]["mean"]["psnr"] == pytest.approx(17.3)
    assert both["scenes"]["b-2v"] == recorded["scenes"]["b-2v"]
    text = baseline.read_text()
    assert text.startswith(gate.BASELINE_HEADER + "# scene b trained by hand at c0ffee1\n")
    assert text.count("# Quality gate baseline") == 1


def test_gate_command_refuses_bad_files_in_one_line(tmp_path, capsys):
    gate_file, out = _gate_files(tmp_path)
    missing = tmp_path / "nope.yaml"
    assert gate.main(["--gate", str(gate_file), "--baseline", str(missing), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and str(missing) in err and "cannot read the baseline file" in err
    bad = tmp_path / "bad_gate.yaml"
    bad.write_text(yaml.safe_dump({"scenes": {"a": {"views": 2, "seeds": [1]}}}))
    assert gate.main(["--gate", str(bad), "--list"]) == 2
    err = capsys.readouterr().err.strip()
    assert err == f"frugalnerf-gate: {bad}: scene 'a' has no tolerance for psnr, ssim, lpips"
    assert gate.main(["--gate", str(gate_file), "--scenes", "zzz", "--list"]) == 2
    assert "no scene 'zzz'" in capsys.readouterr().err
    scratch = tmp_path / "never_written.yaml"
    assert gate.main(["--gate", str(gate_file), "--baseline", str(scratch), "--record", "--max-iterations", "5",
                      "--out", str(out)]) == 2
    assert "--record with --max-iterations" in capsys.readouterr().err and not scratch.exists()
    bad_views = tmp_path / "bad_views.yaml"
    bad_views.write_text(yaml.safe_dump({"scenes": {"a": {"views": "two", "seeds": [1], "tolerance": {
        "psnr": 0.3, "ssim": 0.01, "lpips": 0.01}}}}))
    assert gate.main(["--gate", str(bad_views), "--list"]) == 2
    assert "`views:` must be a positive integer, not 'two'" in capsys.readouterr().err


def test_code_version_names_uncommitted_changes(tmp_path):
    import subprocess

    def git(*a):
        subprocess.run(["git", *a], cwd=tmp_path, check=True, capture_output=True)

    git("init", "-q")
    (tmp_path / "frugalnerf_ns").mkdir()
    (tmp_path / "frugalnerf_ns" / "f.py").write_text("x = 1\n")
    (tmp_path / "notes.md").write_text("a\n")
    git("add", "frugalnerf_ns/f.py", "notes.md")
    git("-c", "user.email=a@b", "-c", "user.name=a", "commit", "-qm", "c")
    clean = gate.code_version(tmp_path)
    assert "dirty" not in clean and len(clean) >= 7
    (tmp_path / "notes.md").write_text("b\n")  # documentation: the same code
    assert gate.code_version(tmp_path) == clean
    (tmp_path / "frugalnerf_ns" / "f.py").write_text("x = 2\n")
    dirty = gate.code_version(tmp_path)
    assert dirty.startswith(clean + "-dirty-")
    (tmp_path / "frugalnerf_ns" / "f.py").write_text("x = 3\n")
    assert gate.code_version(tmp_path) != dirty
    (tmp_path / "frugalnerf_ns" / "f.py").write_text("x = 1\n")
    # The gate's own files do not change what a run computes; a new, untracked module does.
    (tmp_path / "configs").mkdir()
    (tmp_path / "configs" / "gate.yaml").write_text("scenes: {}\n")
    assert gate.code_version(tmp_path) == clean
    (tmp_path / "frugalnerf_ns" / "new_loss.py").write_text("y = 1\n")
    untracked = gate.code_version(tmp_path)
    assert untracked.startswith(clean + "-dirty-")
    (tmp_path / "frugalnerf_ns" / "new_loss.py").write_text("y = 2\n")
    assert gate.code_version(tmp_path) not in (clean, untracked)



def test_committed_baseline_covers_the_gate_scenes_with_all_their_seeds():
    """The baseline in the repository names its commits and has every scene of the gate with all its seeds and
    means that match them."""
    path = ROOT / "configs" / "gate_baseline.yaml"
    if not path.exists():
        pytest.fail("configs/gate_baseline.yaml is missing: record it with `frugalnerf-gate --record`")
    baseline = gate.load_baseline(path)
    _, scenes = gate.load_gate(ROOT / "configs" / "gate.yaml")
    assert set(baseline["commit"].split("+")) == {c for e in baseline["scenes"].values() for c in e["commit"].split("+")}
    assert {s.label for s in scenes} <= set(baseline["scenes"])
    for scene in scenes:
        entry = baseline["scenes"][scene.label]
        if scene.max_spread is not None:  # the spread rule compares with the baseline's spread
            assert isinstance(entry["spread"]["psnr"], float), scene.label
        assert sorted(entry["seeds"]) == sorted(scene.seeds), scene.label
        for metric in gate.METRICS:
            values = [entry["seeds"][seed][metric] for seed in scene.seeds]
            assert entry["mean"][metric] == pytest.approx(sum(values) / len(values), abs=1e-3), (scene.label, metric)


def test_a_recorded_baseline_names_the_commit_each_scene_trained_at(tmp_path):
    # Runs resumed from a folder of another commit: each scene keeps its own commit, the file names all.
    gate_file, out = _gate_files(tmp_path)
    baseline = tmp_path / "baseline.yaml"
    _fill(out, gate_file, {("a-2v", 1): 17.0}, commit="aaaa111")
    _fill(out, gate_file, {("b-2v", 1): 15.0, ("b-2v", 2): 15.4}, commit="bbbb222")
    assert gate.main(["--gate", str(gate_file), "--baseline", str(baseline), "--out", str(out), "--record"]) == 0
    recorded = gate.load_baseline(baseline)
    assert recorded["scenes"]["a-2v"]["commit"] == "aaaa111" and recorded["scenes"]["b-2v"]["commit"] == "bbbb222"
    assert recorded["commit"] == "aaaa111+bbbb222"


def test_one_scene_can_be_gated_with_several_view_counts(tmp_path, capsys):
    """An entry names its scene with `scene:`: fern with 2 views and with 3 are two gate scenes with their own
    runs and labels; two entries for the same scene and view count are refused in one line."""
    scenes = {"data_root": ".", "scenes": {"a": {"data": "a", "parser": ["frugal-llff"], "preset": "frugalnerf-tiny",
                                                 "views": {2: ["--train-views", "0", "1"],
                                                           3: ["--num-train-views", "3"]}}}}
    (tmp_path / "scenes.yaml").write_text(yaml.safe_dump(scenes))
    tol = {"psnr": 0.3, "ssim": 0.01, "lpips": 0.015}
    gate_file = tmp_path / "gate.yaml"
    gate_file.write_text(yaml.safe_dump({"scenes_file": "scenes.yaml", "scenes": {
        "a": {"views": 2, "seeds": [1], "tolerance": tol},
        "a_3v": {"scene": "a", "views": 3, "seeds": [1, 2], "tolerance": tol}}}))
    scenes_file, gated = gate.load_gate(gate_file)
    assert [(s.name, s.label) for s in gated] == [("a", "a-2v"), ("a", "a-3v")]
    specs = gate.gate_specs(scenes_file, gated)
    assert specs["a-2v"][0].parser_args[-3:] == ["--train-views", "0", "1"]
    assert [s.parser_args[-2:] for s in specs["a-3v"]] == [["--num-train-views", "3"]] * 2
    assert len({s.key for group in specs.values() for s in group}) == 3
    gate_file.write_text(yaml.safe_dump({"scenes_file": "scenes.yaml", "scenes": {
        "a": {"views": 3, "seeds": [1], "tolerance": tol},
        "a_3v": {"scene": "a", "views": 3, "seeds": [2], "tolerance": tol}}}))
    assert gate.main(["--gate", str(gate_file), "--list"]) == 2
    assert capsys.readouterr().err.strip() == f"frugalnerf-gate: {gate_file}: entries 'a' and 'a_3v' both gate a-3v"


EPYC = {"host": "vm", "cpus": 2, "cpu": "AMD EPYC", "cpu_capability": "AVX512", "torch": "2.14.1"}
XEON = {"host": "vm", "cpus": 2, "cpu": "Intel Xeon", "cpu_capability": "AVX2", "torch": "2.14.1"}


def test_gate_says_when_the_baseline_trained_on_another_machine(tmp_path, capsys):
    """The same code trains to other numbers on another processor: a recorded entry keeps its runs' machine,
    and the gate names the scenes whose baseline came from elsewhere (or does not say), in its output and gate.md."""
    gate_file, out = _gate_files(tmp_path)
    baseline = tmp_path / "baseline.yaml"
    psnr = {("a-2v", 1): 17.0, ("b-2v", 1): 15.0, ("b-2v", 2): 15.4}
    _fill(out, gate_file, psnr, machine=EPYC)
    assert gate.main(["--gate", str(gate_file), "--baseline", str(baseline), "--out", str(out), "--record"]) == 0
    recorded = gate.load_baseline(baseline)
    assert recorded["scenes"]["a-2v"]["machine"] == "AMD EPYC, AVX512, torch 2.14.1"
    capsys.readouterr()
    assert gate.main(["--gate", str(gate_file), "--baseline", str(baseline), "--out", str(out)]) == 0
    assert "Note:" not in capsys.readouterr().out  # same machine: nothing to say

    elsewhere = tmp_path / "elsewhere"
    _fill(elsewhere, gate_file, psnr, machine=XEON)
    assert gate.main(["--gate", str(gate_file), "--baseline", str(baseline), "--out", str(elsewhere)]) == 0
    text = capsys.readouterr().out
    assert "Note: the baseline of a-2v, b-2v was trained on another machine than these runs (Intel Xeon, AVX2" in text
    assert "--against <commit>" in (elsewhere / "gate.md").read_text()

    # An entry recorded before the gate kept machines does not say where it trained: said too.
    del recorded["scenes"]["b-2v"]["machine"]
    baseline.write_text(yaml.safe_dump(recorded))
    assert gate.main(["--gate", str(gate_file), "--baseline", str(baseline), "--out", str(out)]) == 0
    assert "Note: the baseline of b-2v was trained" in capsys.readouterr().out


def test_gate_against_a_commit_compares_with_its_runs_on_this_machine(tmp_path, capsys):
    """--against REV: the baseline is REV's runs in their own folder (here finished already, so nothing is checked
    out or trained), not the baseline file; a bad REV, or --against with --record, is one line and exit 2."""
    gate_file, out = _gate_files(tmp_path)
    _fill(out, gate_file, {("a-2v", 1): 17.0, ("b-2v", 1): 15.0, ("b-2v", 2): 15.4}, machine=EPYC)
    theirs = tmp_path / "theirs"
    _fill(theirs, gate_file, {("a-2v", 1): 17.5, ("b-2v", 1): 15.1, ("b-2v", 2): 15.3}, commit="beef002", machine=EPYC)
    missing_file = tmp_path / "no_baseline.yaml"  # never read with --against
    args = ["--gate", str(gate_file), "--baseline", str(missing_file), "--out", str(out), "--against-out", str(theirs)]
    head = gate.resolve_commit("HEAD")
    assert gate.main([*args, "--against", "HEAD"]) == 1
    text = capsys.readouterr().out
    assert f"the baseline: 3 runs with the code of {head} in {theirs.resolve()}, 0 to train" in text
    assert f"baseline {head} (trained here) PSNR" in text
    assert "| a-2v | 1 | 17.00 (0.00) | 0.500 | 0.400 | 17.50 / 0.500 / 0.400 |" in text and "FAILED on a-2v" in text
    assert "Note:" not in text  # both sides trained on one machine

    theirs_close = tmp_path / "theirs_close"
    _fill(theirs_close, gate_file, {("a-2v", 1): 17.2, ("b-2v", 1): 15.1, ("b-2v", 2): 15.3}, machine=EPYC)
    assert gate.main([*args[:-2], "--against-out", str(theirs_close), "--against", "HEAD"]) == 0

    assert gate.main([*args, "--against", "no-such-rev"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"frugalnerf-gate: --against no-such-rev: not a commit of the repository at {gate.ROOT}"]
    assert gate.main([*args, "--against", "HEAD", "--record"]) == 2
    assert "use one of them" in capsys.readouterr().err


def test_checkout_makes_a_detached_worktree_of_the_commit(tmp_path):
    import subprocess

    repo = tmp_path / "repo"
    repo.mkdir()
    git = ["git", "-C", str(repo), "-c", "user.name=t", "-c", "user.email=t@t"]
    subprocess.run([*git, "init", "-q"], check=True)
    for value in ("1", "2"):
        (repo / "v.txt").write_text(value)
        subprocess.run([*git, "add", "-A"], check=True)
        subprocess.run([*git, "commit", "-qm", value], check=True)
    first = gate.resolve_commit("HEAD~1", repo)
    tree = gate.checkout(first, repo)
    assert tree == repo / "outputs" / "gate" / "worktrees" / first
    assert (tree / "v.txt").read_text() == "1" and (repo / "v.txt").read_text() == "2"
    assert gate.checkout(first, repo) == tree  # reused
    with pytest.raises(gate.GateError, match="not a commit"):
        gate.resolve_commit("HEAD~5", repo)
