"""``frugalnerf-bench gpu-check`` on a machine without a GPU: its one-line answer, and a dry run of its parts on the CPU."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from frugalnerf_ns.bench import gpu_check

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has CUDA")
def test_without_cuda_one_line_and_exit_zero(tmp_path, capsys):
    assert gpu_check.main(["--out", str(tmp_path)]) == 0  # the script exits with main's return value
    lines = capsys.readouterr().out.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("gpu_check: no CUDA device")
    assert not (tmp_path / "gpu_check.json").exists()


def test_misplaced_names_tensors_on_the_wrong_device_type():
    tensors = [("grid", torch.zeros(2)), ("note", "not a tensor")]
    assert gpu_check.misplaced(iter(tensors), torch.device("cuda")) == ["grid"]
    assert gpu_check.misplaced(iter(tensors), torch.device("cpu")) == []
    from dataclasses import dataclass

    @dataclass
    class Render:
        depth: torch.Tensor
        scales: list

    nested = {"rgb": [torch.zeros(1), {"depth": torch.ones(1)}], "n": 3, "step": Render(torch.ones(1), [torch.ones(2)])}
    assert [name for name, _ in gpu_check.walk("out", nested)] == ["out.rgb[0]", "out.rgb[1].depth", "out.step.depth",
                                                                   "out.step.scales[0]"]


def test_cpu_path_counter_sees_the_index_add_backward():
    from frugalnerf_ns.field.tensorial import sample_plane

    plane = torch.randn(1, 3, 8, 8, requires_grad=True)
    x, y = torch.rand(10) * 2 - 1, torch.rand(10) * 2 - 1
    with gpu_check.count_cpu_path_calls() as counts:
        sample_plane(plane, x, y).sum().backward()
        with torch.no_grad():
            sample_plane(plane, x, y)  # no gradient: grid_sample, not the CPU path
    assert counts == {"cpu": 1, "cuda": 0}
    assert plane.grad is not None and plane.grad.abs().sum() > 0


def test_quadratic_memory_fit_recovers_the_model():
    points = [(r, 500.0 + 0.003 * r * r) for r in (100, 300, 640, 900)]
    a, b = gpu_check.fit_quadratic(points)
    assert a == pytest.approx(500.0) and b == pytest.approx(0.003)


def test_tcnn_layout_reader_reproduces_a_bias_free_mlp():
    torch.manual_seed(0)
    in_dim, hidden = 27, 32
    w1, w2, w3 = torch.randn(hidden, 32), torch.randn(hidden, hidden) * 0.2, torch.randn(16, hidden) * 0.2
    params = torch.cat([w1.flatten(), w2.flatten(), w3.flatten()])
    forward, used = gpu_check.torch_mlp_from_tcnn(params, in_dim, hidden, row_major=True, pad_value=1.0)
    assert used == params.numel()
    x = torch.rand(5, in_dim)
    padded = torch.cat([x, torch.ones(5, 32 - in_dim)], dim=-1)
    expected = torch.sigmoid(torch.relu(torch.relu(padded @ w1.t()) @ w2.t()) @ w3.t())[:, :3]
    assert torch.allclose(forward(x), expected, atol=1e-5)
    other, _ = gpu_check.torch_mlp_from_tcnn(params, in_dim, hidden, row_major=False, pad_value=1.0)
    assert not torch.allclose(other(x), expected, atol=1e-3)


def test_dry_run_of_the_in_process_parts_writes_table_and_json(tmp_path, capsys):
    code = gpu_check.main(["--dry-run", "--parts", "presets", "grid_sample", "tcnn", "--presets", "frugalnerf-tiny",
                           "frugalnerf", "--scenes", "procedural", "--out", str(tmp_path)])
    assert code == 0
    summary = json.loads((tmp_path / "gpu_check.json").read_text())
    assert summary["dry_run"] and summary["machine"]["device"] == "cpu"
    rows = {(row["part"], row.get("preset")): row for row in summary["rows"]}
    for preset in ("frugalnerf-tiny", "frugalnerf"):
        row = rows[("presets", preset)]
        assert row["ok"] and row["losses_finite"] and row["cpu_path_calls_on_gpu"] == 0
        assert row["s_per_step"] > 0 and row["peak_mib"] > 0 and row["color_mlp"] == "torch"
        # parameters, buffers, every scale's render inside the step's StepRender, and the losses
        assert row["checked_tensors"] > 40 and row["misplaced_tensors"] == []
    sample = next(row for row in summary["rows"] if row["part"] == "grid_sample")
    assert sample["max_grad_difference"] < 1e-3 and sample["used"] == "index_add"
    assert rows[("tcnn", "colour MLP")]["skipped"] == "no CUDA device"
    printed = capsys.readouterr().out
    assert "| presets | frugalnerf-tiny | procedural |" in printed and f"{len(summary['rows'])}/{len(summary['rows'])} rows ok" in printed


def test_dry_run_of_the_kernels_part_compares_every_kernel_with_torch(tmp_path):
    pytest.importorskip("warp")
    assert gpu_check.main(["--dry-run", "--parts", "kernels", "--out", str(tmp_path)]) == 0
    rows = {row["preset"]: row for row in json.loads((tmp_path / "gpu_check.json").read_text())["rows"]}
    assert set(rows) == {"march", "reads", "outer"} and all(row["ok"] for row in rows.values())
    assert rows["march"]["max_difference"] < 1 / 255 and rows["outer"]["max_difference"] < 1 / 255
    assert rows["reads"]["max_relative_gradient_difference"] < 1e-4
    assert all(row["s_fused"] > 0 and row["s_torch"] > 0 for row in rows.values())


def test_the_kernels_part_without_warp_is_one_failed_row(monkeypatch):
    from frugalnerf_ns.bench import kernel_check
    from frugalnerf_ns.field import fused_kernels

    def unavailable(choice, say=print):
        say("frugalnerf: fused kernels unavailable (ImportError: no module named warp)")

    monkeypatch.setattr(fused_kernels, "warp_kernels", unavailable)
    (row,) = kernel_check.part_kernels(None, torch.device("cpu"), {})
    assert not row["ok"] and "no module named warp" in row["error"]


@pytest.mark.slow
def test_dry_run_of_every_part(tmp_path):
    # Through the path the device machine's instructions name (scripts/gpu_check.py -> frugalnerf-bench gpu-check).
    proc = subprocess.run([sys.executable, str(ROOT / "scripts" / "gpu_check.py"), "--dry-run", "--scenes", "procedural",
                           "--out", str(tmp_path)], capture_output=True, text=True, cwd=tmp_path)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
    parts = {row["part"] for row in json.loads((tmp_path / "gpu_check.json").read_text())["rows"]}
    assert parts == set(gpu_check.PARTS)


def load_script(name: str):
    import importlib.util

    spec = importlib.util.spec_from_file_location(name, ROOT / "scripts" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_grid_ratio_driver_reads_progress_and_checkpoints(tmp_path):
    """The GPU ablation driver scores a stopped run at its latest checkpoint and reads the step it reached."""
    driver = load_script("gpu_grid_ratio")
    log = tmp_path / "train.log"
    log.write_bytes(b"Step (% Done)       Train Iter (time)\n------\n990 (66.00%)        1 s, 2 ms   \x1b[0m\n"
                    b"1000 (66.67%)       994.320 ms          \x1b[0m\nfrugalnerf: stopped by SIGTERM after step 1003\n")
    assert driver.last_logged_step(log) == 1000
    assert driver.last_logged_step(tmp_path / "missing.log") is None
    models = tmp_path / "run" / "nerfstudio_models"
    assert driver.latest_checkpoint(tmp_path / "run") is None
    models.mkdir(parents=True)
    for step in (500, 1000, 999):
        (models / f"step-{step:09d}.ckpt").write_bytes(b"")
    assert driver.latest_checkpoint(tmp_path / "run").name == "step-000001000.ckpt"
    text = driver.table([{"scene": "fern", "variant": "nogeo", "seed": 42, "psnr": 18.214, "ssim": 0.4987,
                          "lpips": 0.5361, "train_s": 410.2, "checkpoint_step": 3500, "ran_beside": 1,
                          "stopped_at_budget": True}])
    assert "| fern | nogeo | 42 | 18.21 | 0.499 | 0.536 | 410.2 | 3500 | 1 | stopped at budget |" in text
    # Every variant's options exist in the model config (a typo would make every run of it fail on the GPU).
    from frugalnerf_ns.model.frugalnerf import FrugalNeRFModelConfig

    fields = set(FrugalNeRFModelConfig.__dataclass_fields__)
    for options in driver.VARIANTS.values():
        for option in options[::2]:
            assert option.removeprefix("--pipeline.model.").replace("-", "_") in fields
