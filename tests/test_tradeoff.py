"""The speed/accuracy measurements end to end on the procedural scene, through the installed ``frugalnerf-bench``:
``tradeoff`` (table, JSON, both plots) and ``model-size``."""

import json
import subprocess
import sys
from pathlib import Path

import pytest

from frugalnerf_ns.bench import tradeoff

BENCH = str(Path(sys.executable).parent / "frugalnerf-bench")  # the console script pyproject.toml installs


def test_a_budget_is_only_the_iterations_and_the_schedule_follows():
    from frugalnerf_ns.run.presets import build_trainer_config
    from frugalnerf_ns.model.training_schedule import steps_at

    assert tradeoff.budget_args("frugalnerf-cpu", 500) == ["--max-num-iterations", "500"]  # preset: 1500
    model = build_trainer_config("frugalnerf-cpu").pipeline.model
    # What the tradeoff script used to pass by hand, now derived from the run's length.
    assert steps_at(model.upsample_at, 500) == [50, 100, 150, 200, 250]
    assert steps_at(model.alpha_mask_at, 500) == [167, 333]
    assert steps_at(model.upsample_at, 1500) == [150, 300, 450, 600, 750] and steps_at(model.alpha_mask_at, 1500) == [500, 1000]


def test_pareto_front_keeps_only_undominated_runs():
    points = [{"run": "a", "seconds": 1, "psnr": 10, "lpips": 0.5}, {"run": "b", "seconds": 2, "psnr": 9, "lpips": 0.4},
              {"run": "c", "seconds": 3, "psnr": 12, "lpips": 0.6}]
    assert [p["run"] for p in tradeoff.pareto_front(points, "psnr", True)] == ["a", "c"]
    assert [p["run"] for p in tradeoff.pareto_front(points, "lpips", False)] == ["a", "b"]


def test_the_plan_has_every_budget_each_lower_scale_count_each_grid_and_tensorf(tmp_path):
    args = tradeoff.build_parser().parse_args(
        ["--presets", "frugalnerf-tiny", "--budgets", "20", "40", "--scales", "0", "2", "--scales-budget", "20",
         "--grid-sides", "24", "auto", "--seed", "3", "--anytime-every", "10", "--tensorf-iterations", "10"])
    runs = tradeoff.plan_runs(args, "proc", 0, tmp_path, ["frugal-nerfstudio"], ["nerfstudio-data"], ["frugalnerf-tiny"])
    by_label = {run.extra["run"]: run for run in runs}
    # frugalnerf-tiny has L = 2 of its own: that run at the L-sweep's budget is the preset's own 20-step run.
    assert list(by_label) == ["frugalnerf-tiny/20", "frugalnerf-tiny/40", "frugalnerf-tiny/20/L=0",
                              "frugalnerf-tiny/20/grid=24", "frugalnerf-tiny/20/grid=auto", "tensorf/10"]

    def option(run, name):
        return run.train_args[run.train_args.index(name) + 1]

    assert option(by_label["frugalnerf-tiny/40"], "--max-num-iterations") == "40"
    assert option(by_label["frugalnerf-tiny/40"], "--steps-per-save") == "10"  # scored every 10 steps
    assert option(by_label["frugalnerf-tiny/20/L=0"], "--pipeline.model.num-lower-scales") == "0"
    grid = by_label["frugalnerf-tiny/20/grid=24"]
    # 24^3 is below the preset's 30^3 start: the run starts at its final size (the grid never shrinks).
    assert option(grid, "--pipeline.model.final-voxels") == str(24**3) == option(grid, "--pipeline.model.initial-voxels")
    assert option(by_label["frugalnerf-tiny/20/grid=auto"], "--pipeline.model.auto-grid") == "True"
    reference = by_label["tensorf/10"]
    assert reference.method == "tensorf" and reference.parser_args == ["nerfstudio-data"]
    assert option(reference, "--pipeline.datamanager.train-num-rays-per-batch") == "1024"
    assert all(option(run, "--machine.seed") == "3" for run in runs)


@pytest.mark.e2e
def test_tradeoff_script_end_to_end_on_the_procedural_scene(procedural_scene, tmp_path):
    out = tmp_path / "tradeoff"
    result = subprocess.run(
        [BENCH, "tradeoff", "--data", str(procedural_scene), "--parser", "frugal-nerfstudio --center-method focus",
         "--presets", "frugalnerf-tiny", "--budgets", "20", "--scales", "--grid-sides", "24", "--scales-budget", "20",
         "--seed", "3", "--anytime-every", "10", "--tensorf-iterations", "10", "--out", str(out)],
        capture_output=True, text=True, timeout=900,
    )
    assert result.returncode == 0, result.stderr[-3000:]
    rows = json.loads((out / "tradeoff.json").read_text())
    runs = {row["run"] for row in rows}
    assert runs == {"frugalnerf-tiny/20", "frugalnerf-tiny/20/grid=24", "tensorf/10"}  # the L sweep: test above
    # The grid sweep's run really trained at that grid: its config asks for 24^3 final voxels.
    run_dir = next(row["run_dir"] for row in rows if row["run"] == "frugalnerf-tiny/20/grid=24")
    config = (Path(run_dir) / "config.yml").read_text()
    assert f"final_voxels: {24 ** 3}" in config and "seed: 3" in config
    anytime = sorted(row["step"] for row in rows if row["run"] == "frugalnerf-tiny/20")
    assert anytime == [11, 20]  # a checkpoint every 10 steps and the last one
    for row in rows:
        assert 0 < row["seconds"] < 900 and 0 < row["psnr"] < 60 and 0 <= row["lpips"] <= 1 and row["checkpoint_mb"] > 0
    times = [row["seconds"] for row in rows if row["run"] == "frugalnerf-tiny/20"]
    assert times == sorted(times)  # later checkpoints come later
    table = (out / "tradeoff.md").read_text().splitlines()
    assert table[0].startswith("| run | step | wall time | PSNR") and len(table) == 2 + len(rows)
    for name in ("pareto.png", "anytime.png"):
        from PIL import Image

        with Image.open(out / name) as image:
            assert image.format == "PNG" and min(image.size) > 300


@pytest.mark.e2e
def test_model_size_script_measures_fixed_and_auto_grids(procedural_scene, tmp_path):
    out = tmp_path / "sizes.json"
    result = subprocess.run(
        [BENCH, "model-size", "--data", str(procedural_scene), "--parser",
         "frugal-nerfstudio --center-method focus", "--presets", "frugalnerf-tiny", "--auto-grid", "--out", str(out)],
        capture_output=True, text=True, timeout=600,
    )
    assert result.returncode == 0, result.stderr[-3000:]
    fixed, auto = json.loads(out.read_text())
    assert fixed["preset"] == "frugalnerf-tiny" and auto["preset"] == "frugalnerf-tiny + auto-grid"
    # The preset's 48^3 voxels, shaped to the (fitted, not cubic) scene box.
    sides = [int(v) for v in fixed["grid"].split("x")]
    assert abs(sides[0] * sides[1] * sides[2] / 48**3 - 1) < 0.1 and len(set(sides)) > 1
    assert fixed["grid"] != auto["grid"]
    for row in (fixed, auto):
        # The field is what grows with the grid; the checkpoint holds it plus nerfstudio's bookkeeping.
        assert 0 < row["field_mb"] < row["checkpoint_mb"] and row["peak_rss_mib"] > 100 and row["rays"] > 0
    assert "| frugalnerf-tiny + auto-grid | " in result.stdout
