"""ns-train frugalnerf-tiny on the procedural scene, ns-eval, then resume from the checkpoint."""

import json

import pytest
import torch

from frugalnerf_ns.data.procedural_scene import constant_color_psnr

# The tiny preset must beat predicting the best constant colour by at least this much on the test views.
PSNR_MARGIN_DB = 6.0


def test_trained_model_clearly_beats_a_constant_colour(trained_run, procedural_scene):
    results, _ = trained_run
    baseline = constant_color_psnr(procedural_scene)
    assert results["psnr"] > baseline + PSNR_MARGIN_DB, (results, baseline)
    assert 0.0 <= results["lpips"] < 0.5 and results["ssim"] > 0.3


def test_checkpoint_holds_the_grown_grid(trained_run):
    _, run_dir = trained_run
    ckpts = sorted((run_dir / "nerfstudio_models").glob("step-*.ckpt"))
    assert ckpts, "no checkpoint written"
    state = torch.load(ckpts[-1], map_location="cpu")  # needs the plugin's safe globals (imported above)
    density = [v for k, v in state["pipeline"].items() if "density_grid.planes.0" in k][0]
    # The tiny preset starts at 30^3 voxels and upsamples to 48^3 (then shrinks the box, keeping the count).
    assert density.shape[-1] * density.shape[-2] > 30 * 30


def test_training_logs_and_plots_the_scale_fractions(trained_run):
    _, run_dir = trained_run
    png = run_dir / "geometric_adaptation.png"
    assert png.is_file() and png.read_bytes()[:4] == b"\x89PNG"
    history = json.loads((run_dir / "geometric_adaptation.json").read_text())
    # One row per training step of the tiny preset (400), each a distribution over scales + left out.
    assert len(history["steps"]) == 400 and history["steps"][-1] == 399
    for row in history["stats"][::50]:
        assert sum(row.values()) == pytest.approx(1.0)
    # Geometric adaptation actually happens: most rays find a scale within the threshold by the end.
    assert history["stats"][-1]["geo_left_out_fraction"] < 0.5
