"""Spiral novel poses and nearest-training-view lookup (pure torch)."""

import math

import pytest
import torch

from frugalnerf_ns.geometry.novel_views import nearest_other_view, spiral_focus_depth, spiral_poses


def looking_down_minus_z(centers):
    rotation = torch.eye(3).expand(len(centers), 3, 3)
    return torch.cat([rotation, torch.as_tensor(centers, dtype=torch.float32)[:, :, None]], dim=-1)


def test_spiral_circles_the_training_cameras_and_looks_at_the_focus_point():
    cameras = looking_down_minus_z([[-0.5, 0.0, 0.0], [0.5, 0.0, 0.0], [0.0, 0.2, 0.0], [0.0, -0.2, 0.0]])
    poses = spiral_poses(cameras, focus_depth=4.0, num_poses=60, rotations=1, radius_scale=1.0, zrate=0.5)
    assert poses.shape == (60, 3, 4)
    rotations = poses[:, :, :3]
    assert torch.allclose(rotations.transpose(1, 2) @ rotations, torch.eye(3).expand(60, 3, 3), atol=1e-5)
    assert torch.allclose(torch.linalg.det(rotations), torch.ones(60), atol=1e-5)
    # Every pose's viewing axis (-z) passes through the focus point 4 units in front of the mean camera.
    focus = torch.tensor([0.0, 0.0, -4.0])
    to_focus = torch.nn.functional.normalize(focus - poses[:, :, 3], dim=-1)
    assert torch.allclose(to_focus, -poses[:, :, 2], atol=1e-5)
    # Radii: 90th percentile of |offset| per axis (x: 0.5, y: 0.2), z moves at half the angular speed.
    assert float(poses[:, 0, 3].abs().max()) == pytest.approx(0.5, rel=1e-3)
    assert float(poses[:, 1, 3].abs().max()) == pytest.approx(0.2, rel=0.02)
    assert torch.allclose(poses[0, :, 3], torch.tensor([0.5, 0.0, 0.0]), atol=1e-6)
    # Up stays close to the training cameras' up.
    assert float(poses[:, 1, 1].min()) > 0.9


def test_radius_scale_and_rotations():
    cameras = looking_down_minus_z([[-1.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    half = spiral_poses(cameras, 5.0, num_poses=8, rotations=2, radius_scale=0.5, zrate=0.0)
    angles = torch.atan2(-half[:, 1, 3], half[:, 0, 3])  # y radius is 0 for two cameras on the x axis
    assert float(half[:, 0, 3].abs().max()) == pytest.approx(0.5, rel=1e-4)
    # Two rotations in 8 poses: every 4th pose is back at the start.
    assert torch.allclose(half[0, :, 3], half[4, :, 3], atol=1e-5)
    assert torch.isfinite(angles).all()
    with pytest.raises(ValueError):
        spiral_poses(cameras, 5.0, num_poses=0, rotations=1, radius_scale=1.0, zrate=0.5)


def test_focus_depth_for_forward_facing_and_object_scenes():
    cameras = looking_down_minus_z([[-0.5, 0.0, 0.0], [0.5, 0.0, 0.0]])
    near, far = 1.0, 10.0
    expected = 1.0 / (0.25 / (0.9 * near) + 0.75 / (5 * far))
    assert spiral_focus_depth(cameras, near_far=(near, far)) == pytest.approx(expected)
    # Parallel axes: the scene centre decides.
    shifted = looking_down_minus_z([[-0.5, 0.0, 3.0], [0.5, 0.0, 3.0]])
    assert spiral_focus_depth(shifted, scene_center=torch.zeros(3)) == pytest.approx(3.0)
    with pytest.raises(ValueError, match="spiral"):
        spiral_focus_depth(looking_down_minus_z([[0.0, 0.0, -3.0]]), scene_center=torch.zeros(3))
    # Cameras on a circle looking at a point 2 units away: their axes meet there, whatever the scene centre.
    target = torch.tensor([0.3, 0.0, -2.0])
    poses = []
    for angle in (-0.4, 0.0, 0.4):
        center = target + 2.0 * torch.tensor([math.sin(angle), 0.0, math.cos(angle)])
        back = torch.nn.functional.normalize(center - target, dim=0)
        right = torch.nn.functional.normalize(torch.linalg.cross(torch.tensor([0.0, 1.0, 0.0]), back), dim=0)
        poses.append(torch.stack([right, torch.linalg.cross(back, right), back, center], dim=1))
    poses = torch.stack(poses)
    mean_center = poses[:, :, 3].mean(dim=0)
    expected = float((mean_center - target).norm())
    assert spiral_focus_depth(poses, scene_center=torch.tensor([0.0, 0.0, 50.0])) == pytest.approx(expected, rel=1e-4)


def test_nearest_training_view_never_picks_itself():
    train = torch.tensor([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [3.0, 0.0, 0.0], [0.0, 2.5, 0.0]])
    own = torch.arange(4)
    assert nearest_other_view(train, train, own_view=own).tolist() == [1, 0, 1, 0]
    novel = torch.tensor([[2.2, 0.0, 0.0], [0.1, 2.0, 0.0], [0.0, 0.0, 0.0]])
    assert nearest_other_view(novel, train, own_view=torch.full((3,), -1)).tolist() == [2, 3, 0]
    assert nearest_other_view(novel, train).tolist() == [2, 3, 0]


def test_a_single_training_view_has_no_nearest_other_view():
    single = torch.zeros(1, 3)
    assert nearest_other_view(single, single, own_view=torch.zeros(1, dtype=torch.long)).tolist() == [-1]
    assert nearest_other_view(torch.ones(2, 3), single).tolist() == [0, 0]
    assert math.isfinite(float(spiral_poses(looking_down_minus_z([[0.0, 0.0, 0.0]]), 2.0, 4, 1, 1.0, 0.5).sum()))
