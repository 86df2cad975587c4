"""The signals a candidate viewpoint is scored by (pure torch, no nerfstudio)."""

from __future__ import annotations

import torch

from frugalnerf_ns.geometry.camera_conventions import look_at_poses
from frugalnerf_ns.geometry.reprojection import project_to_camera
from frugalnerf_ns.scoring.next_view import SCORES, pixel_signals, scale_depth_disagreement

UP = torch.tensor([0.0, 1.0, 0.0])
SIZE = 32
INTRINSICS = torch.tensor([30.0, 30.0, SIZE / 2, SIZE / 2])


def wall_depth(c2w: torch.Tensor, wall_z: float = -3.0) -> torch.Tensor:
    """Depth (distance along unit rays) of the plane z = wall_z seen by a camera, [SIZE, SIZE]."""
    j, i = torch.meshgrid(torch.arange(SIZE) + 0.5, torch.arange(SIZE) + 0.5, indexing="ij")
    local = torch.stack([(i - INTRINSICS[2]) / INTRINSICS[0], -(j - INTRINSICS[3]) / INTRINSICS[1], -torch.ones_like(i)], -1)
    directions = torch.nn.functional.normalize(local @ c2w[:3, :3].T, dim=-1)
    distance = (wall_z - c2w[2, 3]) / directions[..., 2]
    return distance, directions


def camera(x: float) -> torch.Tensor:
    return look_at_poses(torch.tensor([[x, 0.0, 0.0]]), torch.tensor([x, 0.0, -3.0]), UP)[0]


def signals_of(candidate_x: float, photo_xs, accumulation: float = 1.0, has_room: bool = False, lower_scale_shift: float = 0.0):
    c2w = camera(candidate_x)
    depth, directions = wall_depth(c2w)
    origins = c2w[:3, 3].expand(SIZE * SIZE, 3)
    photos = [camera(x) for x in photo_xs]
    depths = [depth.reshape(-1), depth.reshape(-1) + lower_scale_shift]
    return pixel_signals(origins, directions.reshape(-1, 3), depths, torch.full((SIZE * SIZE,), accumulation),
                         photos, [INTRINSICS] * len(photos), [wall_depth(p)[0] for p in photos], has_room=has_room)


def test_a_viewpoint_over_the_photos_is_seen_and_one_beside_them_is_not():
    photos = [-0.5, 0.5]
    over = signals_of(0.0, photos).summary()
    beside = signals_of(6.0, photos).summary()
    assert over.unseen == 0.0 and over.single < 0.6  # the middle of the wall: both photos see it
    assert beside.unseen == 1.0  # the photos' frusta end ~1.6 units either side of x = 0 on the wall
    assert SCORES["unseen_or_single"](beside) > SCORES["unseen_or_single"](over)


def test_half_overlap_counts_single_views():
    one = signals_of(1.6, [0.0]).summary()  # the photo sees x in [-1.6, 1.6] of the wall, this view [0, 3.2]
    assert 0.4 < one.single < 0.6 and abs(one.single + one.unseen - 1.0) < 1e-6


def test_an_occluded_point_is_not_seen():
    c2w = camera(0.0)
    depth, directions = wall_depth(c2w)
    origins = c2w[:3, 3].expand(SIZE * SIZE, 3)
    # The photo sees something 1 unit in front of the wall everywhere: the wall behind it is hidden.
    hidden = wall_depth(camera(0.1), wall_z=-2.0)[0]
    signals = pixel_signals(origins, directions.reshape(-1, 3), [depth.reshape(-1)], torch.ones(SIZE * SIZE),
                            [camera(0.1)], [INTRINSICS], [hidden])
    assert signals.summary().unseen == 1.0
    point = origins[:1] + directions.reshape(-1, 3)[:1] * depth.reshape(-1)[:1]
    assert bool(project_to_camera(point, camera(0.1), INTRINSICS).in_front[0])  # in front, in view: only hidden


def test_depth_disagreement_and_light_beyond_the_box():
    agreeing = signals_of(0.0, [-0.5, 0.5]).summary()
    apart = signals_of(0.0, [-0.5, 0.5], lower_scale_shift=10.0).summary()
    assert agreeing.disagreement == 0.0 and apart.disagreement == 1.0  # 10 units off a ~3-unit depth: clipped
    assert signals_of(0.0, [0.0], accumulation=0.25).summary().beyond == 0.0  # no room: background colour
    assert abs(signals_of(0.0, [0.0], accumulation=0.25, has_room=True).summary().beyond - 0.75) < 1e-6
    spread = scale_depth_disagreement([torch.tensor([2.0, 4.0]), torch.tensor([2.5, 4.0]), torch.tensor([1.0, 3.0])])
    assert torch.allclose(spread, torch.tensor([0.5, 0.25]))
