"""The shared scorer of ``frugalnerf-bench scenes`` and the sweep runner: masked rendering is exact, full scale only is the same."""

import pytest
import torch
from nerfstudio.cameras.cameras import Cameras, CameraType

from frugalnerf_ns.tools.offline_tools import render_test_rgb
from tests.helpers import tiny_model


def small_camera(height=12, width=16):
    # Looks down -z from z = 3 at the unit box (nerfstudio cameras are OpenGL-style).
    c2w = torch.tensor([[1.0, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 3]])[None]
    return Cameras(
        camera_to_worlds=c2w, fx=20.0, fy=20.0, cx=width / 2, cy=height / 2, width=width, height=height,
        camera_type=CameraType.PERSPECTIVE,
    )


def test_masked_render_equals_full_render_inside_the_mask_and_black_outside():
    model = tiny_model()
    model.eval()
    camera = small_camera()
    full = render_test_rgb(model, camera, None)
    assert full.shape == (12, 16, 3)
    mask = torch.zeros(12, 16, 1, dtype=torch.bool)
    mask[3:9, 4:11] = True
    masked = render_test_rgb(model, camera, mask)
    inside = mask[..., 0]
    assert torch.allclose(masked[inside], full[inside], atol=1e-5)
    assert (masked[~inside] == 0).all()
    # An empty mask renders nothing and returns black.
    assert (render_test_rgb(model, camera, torch.zeros_like(mask)) == 0).all()


def test_outside_training_only_the_full_scale_is_rendered_unless_asked():
    model = tiny_model()
    model.eval()
    bundle = small_camera().generate_rays(camera_indices=0)
    with torch.no_grad():
        default = model.get_outputs_for_camera_ray_bundle(bundle)  # ns-eval, ns-render, eval in training
        model.config.eval_all_scales = True
        everything = model.get_outputs_for_camera_ray_bundle(bundle)
        with model.full_scale_only():  # the offline evaluator's block wins over the option
            only_full = model.get_outputs_for_camera_ray_bundle(bundle)
    assert sorted(default) == ["accumulation", "depth", "rgb"]
    assert "rgb_scale1" in everything and "rgb_scale1" not in only_full
    assert torch.allclose(only_full["rgb"], everything["rgb"], atol=1e-6)
    assert torch.allclose(default["rgb"], everything["rgb"], atol=1e-6)
    assert model.num_rendered_scales is None  # restored after the block


def test_mean_scores_average_each_metric_over_the_views_that_have_it():
    from frugalnerf_ns.tools.offline_tools import mean_scores

    views = [{"psnr": 10.0, "ssim": 0.5, "lpips": 0.2}, {"psnr": 20.0, "ssim": 0.7}]
    assert mean_scores(views) == {"psnr": 15.0, "ssim": 0.6, "lpips": 0.2}


@pytest.mark.parametrize("args, words", [
    (["eval", "--help"], "usage: python -m frugalnerf_ns.tools.offline_tools eval"),
    (["eval", "--per-view"], "usage: python -m frugalnerf_ns.tools.offline_tools eval"),
    (["eval", "--per-view", __file__, "x"], "frugalnerf: error: steps must be whole numbers, got x"),
    (["eval", "no/such/config.yml"], "frugalnerf: error: no/such/config.yml is not a run's config.yml"),
    (["eval", __file__, "last"], "frugalnerf: error: steps must be whole numbers, got last"),
])
def test_eval_with_bad_arguments_is_one_line(args, words):
    import subprocess
    import sys

    done = subprocess.run([sys.executable, "-m", "frugalnerf_ns.tools.offline_tools", *args], capture_output=True, text=True)
    assert done.returncode == 1 and words in done.stderr and "Traceback" not in done.stderr
    assert len(done.stderr.strip().splitlines()) == 1
