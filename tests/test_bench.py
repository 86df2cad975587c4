"""``frugalnerf-bench``: the installed command lists and dispatches its subcommands, the shared table-and-JSON
writer writes what it prints, and the shared pipeline builder sets a preset up at its final grid."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from frugalnerf_ns.bench import cli
from frugalnerf_ns.bench.report import markdown_table, write_report

BENCH = str(Path(sys.executable).parent / "frugalnerf-bench")  # the console script pyproject.toml installs


def test_installed_command_lists_every_subcommand_and_refuses_an_unknown_one():
    listed = subprocess.run([BENCH], capture_output=True, text=True)
    assert listed.returncode == 0
    names = [line.split()[0] for line in listed.stdout.splitlines() if line.startswith("  ")]
    assert names == list(cli.SUBCOMMANDS) == ["scenes", "tradeoff", "vs-tensorf", "render", "viewer", "next-view", "startup", "cameras",
                                              "model-size", "step", "profile", "gpu-check"]
    unknown = subprocess.run([BENCH, "bogus"], capture_output=True, text=True)
    assert unknown.returncode == 2 and unknown.stdout == ""
    assert unknown.stderr.strip().splitlines() == [
        "frugalnerf-bench: unknown subcommand 'bogus'; choose one of " + ", ".join(cli.SUBCOMMANDS)]


@pytest.mark.parametrize("name", list(cli.SUBCOMMANDS))
def test_every_subcommand_answers_help_under_its_own_name(name, capsys):
    with pytest.raises(SystemExit) as done:
        cli.main([name, "--help"])
    assert done.value.code == 0
    assert capsys.readouterr().out.startswith(f"usage: frugalnerf-bench {name} ")


def test_table_and_json_writer(tmp_path, capsys):
    rows = [{"scene": "fern", "psnr": 17.9812}, {"scene": "horns", "psnr": 17.0}]
    table = markdown_table(rows, [("scene", lambda r: r["scene"]), ("PSNR", lambda r: f"{r['psnr']:.2f}")])
    assert table.splitlines() == ["| scene | PSNR |", "|---|---|", "| fern | 17.98 |", "| horns | 17.00 |"]
    written = write_report("demo", table, {"rows": rows, "where": tmp_path}, tmp_path / "a" / "out.json",
                           tmp_path / "b" / "out.md")
    assert written == [tmp_path / "a" / "out.json", tmp_path / "b" / "out.md"]
    assert json.loads(written[0].read_text()) == {"rows": rows, "where": str(tmp_path)}  # paths as text
    assert written[1].read_text() == table + "\n"
    printed = capsys.readouterr().out.strip().splitlines()
    assert printed[:4] == table.splitlines() and printed[-1] == f"demo: wrote {written[0]} and {written[1]}"


def test_preset_pipeline_is_set_up_at_its_final_grid(procedural_scene):
    from frugalnerf_ns.bench.pipelines import preset_pipeline
    from frugalnerf_ns.field.grid_sizes import resolution_for_voxels

    def fewer_voxels(config) -> None:
        config.pipeline.model.final_voxels = 20**3

    config, pipeline = preset_pipeline("frugalnerf-tiny", procedural_scene, configure=fewer_voxels,
                                       parser_args=["frugal-nerfstudio", "--center-method", "focus"])
    model = pipeline.model
    box = (model.field.aabb[1] - model.field.aabb[0]).tolist()
    assert config.pipeline.model.final_voxels == 20**3 and config.pipeline.datamanager.dataparser.center_method == "focus"
    assert model.field.density_grid.resolution.tolist() == list(resolution_for_voxels(20**3, box))
    assert list(resolution_for_voxels(config.pipeline.model.initial_voxels, box)) != list(resolution_for_voxels(20**3, box))
    with pytest.raises(SystemExit) as bad:
        preset_pipeline("frugalnerf-tiny", procedural_scene, parser_args=["frugal-nope"])
    assert str(bad.value.code).startswith("frugalnerf-bench: unknown dataparser 'frugal-nope'")




def test_scenes_without_the_asked_split_sit_out_a_run_of_all_scenes(tmp_path, capsys):
    import yaml

    from frugalnerf_ns.bench import scenes as bench_scenes

    for name in ("paper", "capture"):
        (tmp_path / name).mkdir()
    config = {"data_root": str(tmp_path), "scenes": {
        "paper": {"data": "paper", "parser": ["frugal-llff"], "views": {2: ["--train-views", "0", "1"]}, "preset": "frugalnerf-cpu"},
        "capture": {"data": "capture", "parser": ["frugal-llff"], "views": {3: ["--train-views", "0", "1", "2"]},
                    "preset": "frugalnerf-cpu"}},
              "baselines": {"tensorf": {"args": ["--max-num-iterations", "1"]}}}
    (tmp_path / "scenes.yaml").write_text(yaml.safe_dump(config))
    # --only-baselines with no baselines: the plan is made (and checked), nothing trains.
    bench_scenes.main(["--config", str(tmp_path / "scenes.yaml"), "--only-baselines", "--out", str(tmp_path / "out")])
    assert "benchmark: skipping capture: it defines no 2-view split" in capsys.readouterr().out
    # Named: an error before anything trains, not a skip.
    with pytest.raises(SystemExit, match="scene 'capture' defines no 2-view split"):
        bench_scenes.main(["--config", str(tmp_path / "scenes.yaml"), "--scenes", "capture", "--only-baselines",
                           "--baselines", "tensorf", "--out", str(tmp_path / "out")])


SHARED_LLFF = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "llff"


@pytest.mark.skipif(not (SHARED_LLFF / "horns").exists(), reason="../shared/data is absent")
def test_cameras_bench_compares_estimated_cameras_with_published_poses(tmp_path, capsys):
    out = tmp_path / "cameras.json"
    startup = sorted((SHARED_LLFF / "horns" / "images_8").iterdir())[20:43:22]
    assert cli.main(["cameras", "--data-root", str(SHARED_LLFF.parent), "--cases", "horns-2v", "--out", str(out),
                     "--startup-photos", *map(str, startup)]) == 0
    report = json.loads(out.read_text())
    (row,) = report["cases"]
    assert len(row["train"]) == 2 and row["test_registered"] == row["test_count"] == 8
    # Measured 0.09 / 0.36 deg between the two views, test views 0.07 deg and 1 % of the spread (median) off.
    assert row["pair_rotation_deg"] < 0.5 and row["pair_direction_deg"] < 1.5
    assert row["test_rotation_deg_median"] < 0.5 and row["test_centre_median"] < 0.1
    assert report["startup"]["photos"] == 2 and report["startup"]["cached_s"] < report["startup"]["first_s"]
    assert "| horns-2v | DJI_" in capsys.readouterr().out
