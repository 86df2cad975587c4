"""Sweeps: grid expansion, the results file, the tables, and (on a local Ray instance) runs that finish, fail,
lose their worker, and are skipped the second time."""

from __future__ import annotations

import json
import os
import signal
import threading
import time
from pathlib import Path

import pytest
import yaml

from frugalnerf_ns.tools.sweep import report
from frugalnerf_ns.tools.sweep.grid import GridError, cli_option, expand, load_grid
from frugalnerf_ns.tools.sweep.store import ResultStore

ROOT = Path(__file__).resolve().parents[1]


def scenes_file(tmp_path: Path, data: Path, own_split: bool = False) -> Path:
    path = tmp_path / "scenes.yaml"
    path.write_text(yaml.safe_dump({
        "data_root": str(data.parent),
        "scenes": {"proc": {"data": data.name, "parser": ["frugal-nerfstudio", "--center-method", "focus"],
                            "views": {2: ["--num-train-views", "2"], 3: ["--num-train-views", "3"]} if not own_split
                            else {3: []},  # the procedural scene's transforms.json has its own 3-view split
                            "baseline_options": ["--auto-scale-poses", "True"], "preset": "frugalnerf-tiny"}},
        "baselines": {"tensorf": {"args": ["--max-num-iterations", "5"]}},
    }))
    return path


def grid_file(tmp_path: Path, scenes_path: Path, **grid) -> Path:
    path = tmp_path / "grid.yaml"
    path.write_text(yaml.safe_dump({"scenes_file": str(scenes_path), **grid}))
    return path


# ---- grid ------------------------------------------------------------------------------------------------
def test_grid_is_the_product_of_its_axes_and_baselines_ignore_option_sets(tmp_path):
    scenes = scenes_file(tmp_path, tmp_path / "data" / "scene")
    grid = grid_file(tmp_path, scenes, scenes=["proc"], views=[2, 3], methods=["scene-preset", "tensorf"],
                     options={"full": {}, "no-geo": {"pipeline.model.geo_weight": 0}}, seeds=[1, 2], max_iterations=7)
    specs = load_grid(grid)
    ours = [s for s in specs if s.method == "frugalnerf-tiny"]
    theirs = [s for s in specs if s.method == "tensorf"]
    assert len(ours) == 2 * 2 * 2 and len(theirs) == 2 * 2  # views x options x seeds; views x seeds
    assert len({s.key for s in specs}) == len(specs)
    no_geo = next(s for s in ours if s.option == "no-geo" and s.views == 3 and s.seed == 2)
    assert no_geo.label == "frugalnerf-tiny[no-geo]"
    assert no_geo.train_args == ["--pipeline.model.geo-weight", "0", "--max-num-iterations", "7", "--machine.seed", "2",
                                 "--pipeline.datamanager.seed", "2"]
    assert no_geo.parser_args == ["frugal-nerfstudio", "--center-method", "focus", "--num-train-views", "3"]
    assert theirs[0].parser_args[-2:] == ["--auto-scale-poses", "True"] and "--pipeline.datamanager.seed" not in theirs[0].train_args
    assert Path(no_geo.data) == (tmp_path / "data" / "scene").resolve()
    # The key names the run, not where its data lives: the same grid under another data root finds its runs.
    moved = load_grid(grid, data_root=tmp_path / "elsewhere")
    assert [s.key for s in moved] == [s.key for s in specs] and moved[0].data != specs[0].data


def test_cli_option_spelling():
    assert cli_option("pipeline.model.geo_weight", 0) == ["--pipeline.model.geo-weight", "0"]
    assert cli_option("pipeline.model.upsample_at", [0.1, 0.2]) == ["--pipeline.model.upsample-at", "0.1", "0.2"]
    assert cli_option("pipeline.datamanager.novel_views", False) == ["--pipeline.datamanager.novel-views", "False"]


@pytest.mark.parametrize("grid, message", [
    ({"scenes": ["nope"], "methods": ["scene-preset"]}, "unknown scene 'nope'"),
    ({"scenes": ["proc"], "views": [4], "methods": ["scene-preset"]}, "defines no 4-view split"),
    ({"scenes": ["proc"], "methods": ["nerfacto"]}, "neither a FrugalNeRF preset nor one of its baselines"),
    ({"scenes": ["proc"], "methods": ["scene-preset"], "option": {}}, "unknown keys ['option']"),
    ({"scenes": ["proc"], "methods": ["scene-preset"], "options": {"a": {}, "b": {}}}, "the same run twice"),
])
def test_bad_grids_name_the_problem(tmp_path, grid, message):
    scenes = scenes_file(tmp_path, tmp_path / "scene")
    with pytest.raises(GridError, match=None) as err:
        load_grid(grid_file(tmp_path, scenes, **grid))
    assert message in str(err.value)


def test_shipped_grids_expand_against_the_shipped_scenes():
    for path in sorted((ROOT / "configs" / "sweeps").glob("*.yaml")):
        specs = load_grid(path)
        assert specs, path
        assert all(Path(s.data).name in {"fern", "flower", "scan65"} for s in specs), path


# ---- store and report ------------------------------------------------------------------------------------
def test_store_skips_finished_runs_and_retries_a_failure_once(tmp_path):
    store = ResultStore(tmp_path / "results.jsonl")
    store.append({"key": "a", "status": "ok", "psnr": 20.0})
    store.append({"key": "b", "status": "failed"})
    store.append({"key": "c", "status": "failed"})
    store.append({"key": "c", "status": "failed"})
    with open(store.path, "a") as handle:
        handle.write('{"key": "d", "status": "o')  # a run killed mid-write
    assert store.to_run(["a", "b", "c", "d", "e"]) == ["b", "d", "e"]
    assert store.to_run(["a", "b", "c"], retry_failed=True) == ["b", "c"]
    store.append({"key": "b", "status": "ok", "psnr": 21.0})
    latest = store.latest(["a", "b", "c"])
    assert latest["b"]["psnr"] == 21.0 and latest["c"]["status"] == "failed"


def test_failure_table_names_the_log_and_error():
    text = report.failure_table([{"scene": "s", "views": 2, "method": "m", "label": "m[x]", "seed": 1, "status": "failed",
                                  "stage": "train", "error": "frugalnerf: bad | option", "log": "/logs/k.log"}])
    assert "| s (2v) | m[x] | 1 | train | frugalnerf: bad \\| option | /logs/k.log |" in text
    assert report.failure_table([{"status": "ok"}]) == ""


def _stub_checkout(tmp_path: Path) -> tuple:
    """A git checkout whose package holds only a stand-in for the training tools: it says which file ran, and
    leaves what the runner looks for (a checkpoint; a RESULT line). (checkout, package, its short commit)."""
    import subprocess

    checkout = tmp_path / "worktree"
    package = checkout / "frugalnerf_ns"
    (package / "tools").mkdir(parents=True)
    (package / "__init__.py").write_text("")
    (package / "tools" / "__init__.py").write_text("")
    (package / "tools" / "offline_tools.py").write_text(
        "import json, pathlib, sys\n"
        "args = sys.argv[1:]\n"
        "if args[0] == 'train':\n"
        "    out, exp, stamp = (args[args.index(k) + 1] for k in ('--output-dir', '--experiment-name', '--timestamp'))\n"
        "    run = pathlib.Path(out) / exp / args[1] / stamp / 'nerfstudio_models'\n"
        "    run.mkdir(parents=True)\n"
        "    (run / 'step-000000001.ckpt').write_text(__file__)\n"
        "else:\n"
        "    print('RESULT ' + json.dumps({'psnr': 12.5, 'ssim': 0.5, 'lpips': 0.25, 'num_test_views': 1, 'ran': __file__}))\n"
    )
    git = ["git", "-C", str(checkout), "-c", "user.name=t", "-c", "user.email=t@t"]
    subprocess.run([*git, "init", "-q"], check=True)
    subprocess.run([*git, "add", "-A"], check=True)
    subprocess.run([*git, "commit", "-qm", "worktree"], check=True)
    commit = subprocess.run([*git, "rev-parse", "--short", "HEAD"], capture_output=True, text=True).stdout.strip()
    return checkout, package, commit


def test_a_run_trains_and_scores_with_the_code_of_the_checkout_that_started_it(tmp_path):
    """A sweep or gate started from a git worktree must train that worktree's code (a Ray worker imports the
    installed copy first): ``execute`` runs its children from ``code_root`` and records that checkout's commit."""
    from frugalnerf_ns.tools.sweep.grid import RunSpec
    from frugalnerf_ns.tools.sweep.runner import execute

    checkout, package, commit = _stub_checkout(tmp_path)
    spec = RunSpec(scene="proc", views=2, method="frugalnerf-tiny", option="full", data=str(tmp_path), parser_args=[],
                   train_args=[])
    record = execute(spec, tmp_path / "out", threads=1, code_root=str(checkout))
    assert record["status"] == "ok", record
    assert record["psnr"] == 12.5 and record["commit"] == commit and record["code_root"] == str(checkout)
    ckpt = next((tmp_path / "out" / "runs").rglob("step-*.ckpt"))
    assert ckpt.read_text() == str(package / "tools" / "offline_tools.py")  # the worktree's code trained


# ---- on a local Ray instance -----------------------------------------------------------------------------
@pytest.fixture(scope="module")
def local_ray():
    ray = pytest.importorskip("ray")
    import logging

    ray.init(num_cpus=2, include_dashboard=False, logging_level=logging.WARNING, log_to_driver=False)
    yield ray
    ray.shutdown()


@pytest.mark.e2e
def test_sweep_reports_a_failed_run_finishes_the_others_and_skips_them_next_time(local_ray, procedural_scene, tmp_path):
    from frugalnerf_ns.tools.sweep.cli import run_sweep, write_report

    scenes = scenes_file(tmp_path, procedural_scene, own_split=True)
    # geo weight -1 is refused by the option check (one line, exit 1): a run that fails in its own process.
    specs = expand(scenes, ["proc"], [3], ["frugalnerf-tiny"],
                   {"full": [], "bad": ["--pipeline.model.geo-weight", "-1"]}, [None], max_iterations=6)
    out = tmp_path / "sweep"
    said = []
    records = run_sweep(specs, out, say=said.append)
    by_option = {r["option"]: r for r in records}
    assert by_option["full"]["status"] == "ok" and 0 < by_option["full"]["psnr"] < 60
    assert by_option["full"]["threads"] == 2 and by_option["full"]["commit"]
    bad = by_option["bad"]
    assert bad["status"] == "failed" and bad["stage"] == "train" and bad["exit_code"] == 1
    assert bad["error"] == "frugalnerf: error: --pipeline.model.geo-weight must be >= 0 and finite, got -1.0"
    assert Path(bad["log"]).is_file()
    assert any(line.startswith("sweep: FAILED proc 3v frugalnerf-tiny[bad]") for line in said)
    assert any(line.startswith("sweep: 2/2 done (1 failed)") for line in said)

    # The table is made of the records' own numbers.
    text = write_report(records, out)
    ok = by_option["full"]
    assert f"| proc (3v) | frugalnerf-tiny | {ok['psnr']:.2f} | {ok['ssim']:.3f} | {ok['lpips']:.3f} |" in text
    assert "Failed runs" in text and bad["log"] in text
    assert json.loads((out / "results.json").read_text()) == json.loads(json.dumps(records, default=str))

    # Second invocation: the finished run is skipped, the failed one is retried once (and fails again).
    said.clear()
    again = run_sweep(specs, out, say=said.append)
    assert said[0].startswith("sweep: 2 runs, 1 already finished (or failed twice), 1 to run")
    assert {r["key"]: r["status"] for r in again} == {r["key"]: r["status"] for r in records}
    said.clear()
    run_sweep(specs, out, say=said.append)  # failed twice now: reported, not re-run
    assert said == ["sweep: 2 runs, 2 already finished (or failed twice), 0 to run; results in "
                    f"{(out / 'results.jsonl').resolve()}"]
    assert len(ResultStore(out / "results.jsonl").records()) == 3


def _training_pid(marker: str, timeout: float = 120.0):
    """(pid, parent pid) of the training process whose command line holds ``marker``."""
    deadline = time.time() + timeout
    while time.time() < deadline:
        for entry in Path("/proc").iterdir():
            if not entry.name.isdigit():
                continue
            try:
                cmdline = (entry / "cmdline").read_bytes().split(b"\0")
                stat = (entry / "stat").read_text()
            except OSError:
                continue
            text = b" ".join(cmdline)
            if b"offline_tools train" in text and marker.encode() in text:
                return int(entry.name), int(stat.rsplit(")", 1)[1].split()[1])
        time.sleep(0.5)
    raise AssertionError(f"no training with {marker} appeared")


@pytest.mark.slow
def test_a_killed_worker_is_retried_and_its_training_dies_with_it(local_ray, procedural_scene, tmp_path):
    from frugalnerf_ns.tools.sweep.cli import run_sweep

    scenes = scenes_file(tmp_path, procedural_scene, own_split=True)
    specs = expand(scenes, ["proc"], [3], ["frugalnerf-tiny"], {"full": []}, [None], max_iterations=150)
    out = tmp_path / "sweep"
    killed = {}

    def kill_worker():
        pid, worker = _training_pid(str(out))
        killed.update(training=pid, worker=worker)
        os.kill(worker, signal.SIGKILL)

    thread = threading.Thread(target=kill_worker)
    thread.start()
    records = run_sweep(specs, out, say=lambda line: None)
    thread.join()
    assert killed, "the worker was not found"
    assert not Path(f"/proc/{killed['training']}").exists() or b"zombie" in Path(f"/proc/{killed['training']}/status").read_bytes().lower()
    assert records[0]["status"] == "ok"  # Ray ran the task again on a new worker
    assert len(ResultStore(out / "results.jsonl").records()) == 1


@pytest.mark.e2e
def test_a_sweep_trains_the_checkout_it_is_given(local_ray, tmp_path):
    """``frugalnerf-gate --against REV`` trains REV's worktree through ``run_sweep(code_root=...)``: the Ray task
    runs that checkout's tools and its record names that checkout and commit, and the machine it ran on."""
    from frugalnerf_ns.tools.sweep.cli import run_sweep
    from frugalnerf_ns.tools.sweep.grid import RunSpec
    from frugalnerf_ns.tools.sweep.runner import machine

    checkout, package, commit = _stub_checkout(tmp_path)
    spec = RunSpec(scene="proc", views=2, method="frugalnerf-tiny", option="full", data=str(tmp_path), parser_args=[],
                   train_args=[])
    (record,) = run_sweep([spec], tmp_path / "out", say=lambda line: None, code_root=checkout)
    assert record["status"] == "ok", record
    assert record["commit"] == commit and record["code_root"] == str(checkout) and record["psnr"] == 12.5
    assert next((tmp_path / "out" / "runs").rglob("step-*.ckpt")).read_text() == str(package / "tools" / "offline_tools.py")
    assert record["machine"]["cpu"] == machine()["cpu"] and record["machine"]["torch"] == machine()["torch"]


def test_a_runs_machine_names_what_decides_its_rounding():
    import torch

    from frugalnerf_ns.tools.sweep.gate import machine_name
    from frugalnerf_ns.tools.sweep.runner import machine

    info = machine()
    assert info["torch"] == torch.__version__ and info["cpu_capability"] == torch.backends.cpu.get_cpu_capability()
    assert isinstance(info["cpu"], str)
    assert machine_name({"machine": info}).endswith(f"{info['cpu_capability']}, torch {torch.__version__}")
    assert machine_name({}) == ""


@pytest.mark.slow
def test_a_two_by_two_grid_completes_with_a_table_per_option_and_seed(local_ray, procedural_scene, tmp_path):
    from frugalnerf_ns.tools.sweep.cli import main

    scenes = scenes_file(tmp_path, procedural_scene, own_split=True)
    grid = grid_file(tmp_path, scenes, scenes=["proc"], views=[3], methods=["frugalnerf-tiny"], seeds=[1, 2],
                     options={"full": {}, "no-tv": {"pipeline.model.appearance_tv_weight": 0}}, max_iterations=8)
    out = tmp_path / "sweep"
    assert main([str(grid), "--out", str(out)]) == 0
    records = json.loads((out / "results.json").read_text())
    assert len(records) == 4 and all(r["status"] == "ok" for r in records)
    table = (out / "results.md").read_text()
    for label in ("frugalnerf-tiny", "frugalnerf-tiny[no-tv]"):
        rows = [r for r in records if r["label"] == label]
        mean = sum(r["psnr"] for r in rows) / 2
        assert f"| proc (3v) | {label} | mean of 2 (spread) | {mean:.2f}" in table
    assert (out / "pareto.png").stat().st_size > 0


def test_command_refuses_a_bad_grid_or_missing_data_in_one_line(tmp_path, capsys):
    from frugalnerf_ns.tools.sweep.cli import main

    assert main([str(tmp_path / "missing.yaml")]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("frugalnerf-sweep: ") and "missing.yaml" in err[0]
    scenes = scenes_file(tmp_path, tmp_path / "absent", own_split=True)
    grid = grid_file(tmp_path, scenes, scenes=["proc"], views=[3], methods=["frugalnerf-tiny"])
    assert main([str(grid), "--out", str(tmp_path / "out")]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "scene data not found" in err[0] and str(tmp_path / "absent") in err[0]
    assert not (tmp_path / "out").exists()
