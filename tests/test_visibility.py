"""geometry/visibility.py and scoring/coverage.py (scripts/diagnostics/error_by_coverage.py): which training
cameras see a point, and the test error split by it."""

import math

import torch

from frugalnerf_ns.geometry.visibility import training_view_coverage
from frugalnerf_ns.scoring.coverage import summarise_coverage

WIDTH, HEIGHT = 40, 30
INTRINSICS = torch.tensor([30.0, 30.0, WIDTH / 2, HEIGHT / 2])


def camera_at(x: float) -> torch.Tensor:
    """An OpenGL camera at (x, 0, 0) looking down -z."""
    c2w = torch.eye(4)[:3]
    c2w[0, 3] = x
    return c2w


def depth_of_wall(c2w: torch.Tensor, wall_z: float) -> torch.Tensor:
    """Distances along each pixel's unit ray to the plane z = wall_z."""
    u = torch.arange(WIDTH) + 0.5
    v = torch.arange(HEIGHT) + 0.5
    vv, uu = torch.meshgrid(v, u, indexing="ij")
    fx, fy, cx, cy = INTRINSICS
    directions = torch.stack([(uu - cx) / fx, -(vv - cy) / fy, -torch.ones_like(uu)], dim=-1)
    directions = directions / directions.norm(dim=-1, keepdim=True)
    return (wall_z - c2w[2, 3]) / directions[..., 2]


def test_points_on_the_wall_are_seen_points_behind_it_and_outside_the_image_are_not():
    cameras = [camera_at(0.0), camera_at(1.0)]
    depths = [depth_of_wall(c, -2.0) for c in cameras]
    images = [torch.full((HEIGHT, WIDTH, 3), 0.25), torch.full((HEIGHT, WIDTH, 3), 0.75)]
    points = torch.tensor([
        [0.5, 0.0, -2.0],    # on the wall between the cameras: both see it
        [-1.2, 0.0, -2.0],   # on the wall, inside the first camera's image only (its half-width at z=-2 is 1.33)
        [0.5, 0.0, -3.0],    # behind the wall: inside both images, hidden in both
        [5.0, 0.0, -2.0],    # far to the side: inside neither image
        [0.5, 0.0, 1.0],     # behind the cameras
    ])
    coverage = training_view_coverage(points, cameras, [INTRINSICS] * 2, depths, images, tolerance=0.05)
    assert coverage.seen_by.tolist() == [2, 1, 0, 0, 0]
    assert coverage.in_frustum.tolist() == [True, True, True, False, False]
    # The first seeing camera gives the colour; unseen points get none.
    assert torch.allclose(coverage.colors[:, 0], torch.tensor([0.25, 0.25, 0.0, 0.0, 0.0]))


def test_a_point_just_off_the_wall_is_seen_within_the_tolerance_only():
    cameras = [camera_at(0.0)]
    depths = [depth_of_wall(cameras[0], -2.0)]
    images = [torch.zeros(HEIGHT, WIDTH, 3)]
    points = torch.tensor([[0.0, 0.0, -2.08], [0.0, 0.0, -2.2]])  # 4 % and 10 % behind the wall
    loose = training_view_coverage(points, cameras, [INTRINSICS], depths, images, tolerance=0.05)
    strict = training_view_coverage(points, cameras, [INTRINSICS], depths, images, tolerance=0.01)
    assert loose.seen_by.tolist() == [1, 0]
    assert strict.seen_by.tolist() == [0, 0]


def test_the_error_split_adds_up_and_removing_the_unseen_error_gives_the_seen_only_psnr():
    seen_by = torch.tensor([0, 0, 1, 2, 2, 2, 2, 2])
    in_frustum = torch.tensor([False, True, True, True, True, True, True, True])
    squared = torch.tensor([0.09, 0.09, 0.04, 0.01, 0.01, 0.01, 0.01, 0.01])[:, None].expand(8, 3)
    warp_squared = torch.full((8, 3), 0.04)
    summary = summarise_coverage(seen_by, in_frustum, squared, warp_squared)
    total = 0.09 * 2 + 0.04 + 0.01 * 5
    assert math.isclose(summary["psnr"], -10 * math.log10(total / 8), rel_tol=1e-6)
    assert math.isclose(summary["unseen"]["fraction"], 0.25)
    assert math.isclose(summary["unseen"]["error_share"], 0.18 / total, rel_tol=1e-6)
    assert math.isclose(summary["seen_by_1"]["psnr"], -10 * math.log10(0.04), rel_tol=1e-6)
    assert math.isclose(sum(summary[g]["error_share"] for g in ("unseen", "seen_by_1", "seen_by_2_or_more")), 1.0, rel_tol=1e-6)
    assert math.isclose(summary["psnr_if_unseen_were_perfect"], -10 * math.log10((0.04 + 0.05) / 8), rel_tol=1e-6)
    assert summary["psnr_if_unseen_were_perfect"] > summary["psnr"]
    assert math.isclose(summary["seen_psnr"], -10 * math.log10((0.04 + 0.05) / 6), rel_tol=1e-6)
    assert math.isclose(summary["seen_psnr_of_warped_training_colour"], -10 * math.log10(0.04), rel_tol=1e-6)
    assert math.isclose(summary["in_any_frustum_fraction"], 7 / 8)
