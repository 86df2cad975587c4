"""Geometry of the cross-scale geometric adaptation (pure torch; one test checks nerfstudio's ray convention)."""

import pytest
import torch

from frugalnerf_ns.model.losses import depth_smoothness_loss, geometric_adaptation_loss
from frugalnerf_ns.geometry.reprojection import (
    MAX_PIXEL_ERROR,
    Warp,
    patch_reprojection_error,
    project_to_camera,
    sample_images,
    select_pseudo_depth,
    unproject_along_rays,
    warp_to_views,
)
from tests.helpers import (
    FOCAL,
    HEIGHT,
    INTRINSICS,
    WIDTH,
    camera,
    patch_pixels,
    pixel_rays,
    plane_depth,
    render_plane,
    texture,
)


@pytest.fixture(scope="module")
def two_views():
    cameras = torch.stack([camera(), camera(x=1.0)])  # ~1.7 px of parallax per 10% of depth
    images = torch.stack([render_plane(c) for c in cameras])
    return cameras, images


def patch_error(two_views, depth_factor):
    cameras, images = two_views
    pixels = patch_pixels()
    origins, directions = pixel_rays(cameras[0], pixels)
    depth = plane_depth(origins, directions) * depth_factor
    source = texture(unproject_along_rays(origins, directions, plane_depth(origins, directions)))
    target = torch.ones(len(pixels), dtype=torch.long)
    warp = warp_to_views(origins, directions, depth, target, images, cameras, INTRINSICS.expand(2, 4))
    assert warp.valid.all()
    return float(patch_reprojection_error(source[None], Warp(warp.colors[None], warp.valid[None]))[0])


def test_true_depth_explains_the_other_view_and_wrong_depths_do_not(two_views):
    exact = patch_error(two_views, 1.0)
    assert exact < 0.02
    for factor in (0.9, 1.1):
        assert patch_error(two_views, factor) > 5 * exact + 0.05


def test_warp_round_trips_a_point_between_two_cameras():
    source, target = camera(), camera(x=0.5, y=-0.2, yaw=0.3)
    point = torch.tensor([[0.3, 0.1, -4.0]])
    projection = project_to_camera(point, target, INTRINSICS)
    assert projection.in_front.all()
    origins, directions = pixel_rays(target, projection.pixels)
    back = unproject_along_rays(origins, directions, (point - origins).norm(dim=-1))
    assert torch.allclose(back, point, atol=1e-5)
    # The same point, reached on the source camera's own ray, lands on the same target pixel.
    src_pixels = project_to_camera(point, source, INTRINSICS).pixels
    o, d = pixel_rays(source, src_pixels)
    again = project_to_camera(unproject_along_rays(o, d, (point - o).norm(dim=-1)), target, INTRINSICS)
    assert torch.allclose(again.pixels, projection.pixels, atol=1e-3)


def test_projection_matches_nerfstudio_ray_generation():
    from nerfstudio.cameras.cameras import Cameras

    c2w = camera(x=0.2, yaw=-0.2)
    cams = Cameras(camera_to_worlds=c2w[None], fx=FOCAL, fy=FOCAL, cx=WIDTH / 2, cy=HEIGHT / 2, width=WIDTH, height=HEIGHT)
    bundle = cams.generate_rays(camera_indices=0)  # [H, W]
    for row, col in ((0, 0), (5, 40), (HEIGHT - 1, WIDTH - 1)):
        point = unproject_along_rays(bundle.origins[row, col], bundle.directions[row, col], torch.tensor(2.5))
        pixels = project_to_camera(point[None], c2w, INTRINSICS).pixels[0]
        assert torch.allclose(pixels, torch.tensor([col + 0.5, row + 0.5]), atol=1e-3)


def test_points_behind_or_off_image_are_masked_and_everything_stays_finite(two_views):
    cameras, images = two_views
    origins = torch.zeros(4, 3)
    directions = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0], [1.0, 0.0, -0.01], [0.0, 0.0, -1.0]])
    directions = torch.nn.functional.normalize(directions, dim=-1)
    depth = torch.tensor([2.0, 3.0, 3.0, 0.0])  # behind, visible, far off to the side, at the camera centre
    target = torch.zeros(4, dtype=torch.long)
    warp = warp_to_views(origins, directions, depth, target, images, cameras, INTRINSICS.expand(2, 4))
    assert warp.valid.tolist() == [False, True, False, False]
    assert torch.isfinite(warp.colors).all() and (warp.colors[~warp.valid] == 0).all()
    error = patch_reprojection_error(torch.full((1, 4, 3), 0.5), Warp(warp.colors[None], warp.valid[None]))
    # Three of four pixels are invalid and count with the maximal error (RMSE: at least sqrt(0.75)).
    assert float(error) >= 0.75**0.5 * MAX_PIXEL_ERROR
    # NaN pixel coordinates (e.g. from a NaN depth) are invalid, not propagated.
    sampled = sample_images(images, torch.zeros(1, dtype=torch.long), torch.tensor([[float("nan"), 3.0]]))
    assert not sampled.valid.any() and torch.isfinite(sampled.colors).all()


def test_bilinear_sampling_reads_pixel_centres_exactly(two_views):
    _, images = two_views
    pixels = torch.tensor([[0.5, 0.5], [10.5, 7.5], [WIDTH - 0.5, HEIGHT - 0.5]])
    warp = sample_images(images, torch.tensor([1, 0, 1]), pixels)
    expected = torch.stack([images[1, 0, 0], images[0, 7, 10], images[1, HEIGHT - 1, WIDTH - 1]])
    assert warp.valid.all() and torch.allclose(warp.colors, expected, atol=1e-6)


def test_the_patch_error_is_the_rmse_over_the_patch():
    source = torch.rand(2, 3, 25, 3, generator=torch.Generator().manual_seed(0))
    warped = Warp(torch.rand(2, 3, 25, 3, generator=torch.Generator().manual_seed(1)), torch.ones(2, 3, 25, dtype=torch.bool))
    rmse = patch_reprojection_error(source, warped)
    assert rmse.shape == (2, 3)
    assert torch.allclose(rmse, ((source - warped.colors) ** 2).mean(dim=(-1, -2)).sqrt())


def test_scale_selection_picks_the_scale_with_the_least_error_and_drops_unreliable_rays():
    depths = torch.tensor([[1.0, 2.0, 3.0, 4.0], [1.5, 2.5, 3.5, 4.5], [0.5, 2.2, 3.3, 4.4]])
    errors = torch.tensor([[0.30, 0.01, 0.9, 0.6], [0.05, 0.20, 0.8, 0.7], [0.40, 0.30, 0.1, 0.8]])
    pseudo = select_pseudo_depth(errors, depths, threshold=0.5)
    assert pseudo.scale.tolist() == [1, 0, 2, 0]
    assert torch.allclose(pseudo.depth, torch.tensor([1.5, 2.0, 3.3, 4.0]))
    assert pseudo.reliable.tolist() == [True, True, True, False]


def test_geometric_adaptation_loss_sends_gradient_to_every_scale_but_not_through_the_target():
    depths = torch.tensor([[1.0, 2.0, 3.0], [1.2, 2.5, 2.0], [0.7, 2.1, 3.5]], requires_grad=True)
    errors = torch.tensor([[0.1, 0.3, 0.2], [0.2, 0.1, 0.9], [0.3, 0.2, 0.1]])
    pseudo = select_pseudo_depth(errors, depths, threshold=0.5)
    assert not pseudo.depth.requires_grad
    loss = geometric_adaptation_loss(depths, pseudo)
    expected = ((depths.detach() - torch.tensor([1.0, 2.5, 3.5])) ** 2).sum() / 3
    assert torch.allclose(loss, expected)
    loss.backward()
    grad = depths.grad
    # d/dD^l (D^l - D')^2 / n with D' constant: zero exactly at the chosen scale, 2 (D^l - D') / n elsewhere.
    assert torch.allclose(grad, 2 * (depths.detach() - pseudo.depth) / 3)
    for scale in range(3):
        assert grad[scale].abs().sum() > 0


def test_geometric_adaptation_loss_is_zero_without_reliable_rays():
    depths = torch.rand(3, 5, requires_grad=True)
    pseudo = select_pseudo_depth(torch.ones(3, 5), depths, threshold=0.5)
    loss = geometric_adaptation_loss(depths, pseudo)
    assert float(loss) == 0.0
    loss.backward()
    assert torch.isfinite(depths.grad).all()


def test_depth_smoothness_on_2x2_patches():
    flat = torch.full((3, 2, 2), 2.0)
    assert float(depth_smoothness_loss(flat)) == 0.0
    ramp = torch.tensor([[[0.0, 1.0], [0.0, 1.0]]])  # two horizontal steps of 1, no vertical change
    assert float(depth_smoothness_loss(ramp)) == pytest.approx(2.0)
