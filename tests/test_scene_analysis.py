"""Scene-type detection on synthetic camera layouts, and the pixel-scaled grid size (pure torch)."""

import math

import pytest
import torch

from frugalnerf_ns.geometry.scene_analysis import (
    PAPER_GRID_SIDE_PER_PIXEL_ROOT,
    classify_camera_layout,
    fit_scene_box,
    focus_point,
    grid_side_for_pixels,
    has_plain_background,
    seen_region_box,
)


def look_at(center, target, up=(0.0, 1.0, 0.0)):
    """OpenGL camera-to-world (looks down -z) at ``center`` looking at ``target``."""
    center, target, up = (torch.tensor(v, dtype=torch.float64) for v in (center, target, up))
    forward = torch.nn.functional.normalize(target - center, dim=0)
    right = torch.nn.functional.normalize(torch.linalg.cross(forward, up), dim=0)
    true_up = torch.linalg.cross(right, forward)
    return torch.stack([right, true_up, -forward, center], dim=1).float()


def forward_facing(views=4, baseline=0.2):
    """A handheld grid of cameras looking at a wall 4 units away (LLFF-like)."""
    centers = [(baseline * (i % 2), baseline * (i // 2), 0.0) for i in range(views)]
    return torch.stack([look_at(c, (0.1, 0.1, -4.0)) for c in centers])


def ring(views, arc_degrees, radius=3.0):
    """Cameras on an arc of ``arc_degrees`` around the origin, looking at it (object rig / 360 capture)."""
    angles = [math.radians(arc_degrees) * i / max(1, views - (0 if arc_degrees >= 360 else 1)) for i in range(views)]
    return torch.stack([look_at((radius * math.sin(a), 0.5, radius * math.cos(a)), (0.0, 0.0, 0.0)) for a in angles])


@pytest.mark.parametrize("views", [2, 3, 8])
def test_forward_facing_layouts(views):
    layout = classify_camera_layout(forward_facing(views))
    assert layout.scene_type == "forward-facing"
    assert layout.spread_degrees < 5.0


@pytest.mark.parametrize("views,arc", [(2, 40), (3, 60), (5, 90)])
def test_object_rigs_converge_on_the_object(views, arc):
    layout = classify_camera_layout(ring(views, arc))
    assert layout.scene_type == "object"
    assert torch.allclose(layout.focus, torch.zeros(3), atol=0.15)  # the cameras look at the origin


@pytest.mark.parametrize("views", [4, 8, 20])
def test_full_circles_are_360(views):
    layout = classify_camera_layout(ring(views, 360))
    assert layout.scene_type == "360"
    assert layout.coverage_degrees >= 180.0


def test_two_cameras_facing_each_other_are_360():
    cameras = torch.stack([look_at((0.0, 0.0, 3.0), (0.0, 0.0, 0.0)), look_at((0.0, 0.0, -3.0), (0.0, 0.0, 0.0))])
    assert classify_camera_layout(cameras).scene_type == "360"


def test_a_mask_or_plain_background_turns_a_narrow_rig_into_an_object_scene():
    narrow = ring(2, 10)  # two object views 10 degrees apart look forward-facing by layout alone
    assert classify_camera_layout(narrow).scene_type == "forward-facing"
    assert classify_camera_layout(narrow, has_object_mask=True).scene_type == "object"


def test_single_view_is_classified_and_finite():
    layout = classify_camera_layout(forward_facing(1))
    assert layout.scene_type == "forward-facing" and layout.coverage_degrees == 0.0
    assert torch.isfinite(layout.focus).all()


def test_focus_of_parallel_cameras_is_finite_and_ahead_of_them():
    cameras = forward_facing(4)
    cameras[:, :3, :3] = torch.eye(3)  # exactly parallel axes: the plain least squares is singular
    focus = focus_point(cameras)
    assert torch.isfinite(focus).all() and float(focus[2]) < 0.0


def test_plain_background_detection():
    white = torch.ones(2, 20, 30, 3)
    white[:, 5:15, 8:22] = torch.rand(2, 10, 14, 3)  # an object in the middle
    assert has_plain_background(white)
    assert not has_plain_background(torch.rand(2, 20, 30, 3))


def test_grid_side_scales_with_the_square_root_of_the_training_pixels():
    assert grid_side_for_pixels(2 * 1008 * 756) == 640  # the paper's LLFF input gets the paper's grid
    fern_eighth = grid_side_for_pixels(2 * 504 * 378)
    assert fern_eighth == round(PAPER_GRID_SIDE_PER_PIXEL_ROOT * math.sqrt(2 * 504 * 378)) == 320
    assert grid_side_for_pixels(4 * 504 * 378) > fern_eighth
    assert grid_side_for_pixels(10) == 32 and grid_side_for_pixels(10**9) == 640  # clamped


# A camera at z = 3 looking down -z with a 100 x 100 image and focal 400: half-width 0.125 per unit depth.
BOX = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
K = torch.tensor([[400.0, 400.0, 50.0, 50.0]])


def camera_at(x, z=3.0):
    return look_at((x, 0.0, z), (x, 0.0, z - 1.0))[None, :3].float()


def test_seen_region_is_the_frustum_inside_the_box():
    box = seen_region_box(BOX, camera_at(0.0), K, (100, 100), samples_per_axis=64)
    cell = 2.0 / 64
    # The frustum is widest at the far face of the box (depth 4): x, y within +-0.5.
    assert torch.allclose(box[:, :2], torch.tensor([[-0.5, -0.5], [0.5, 0.5]]), atol=cell)
    assert torch.allclose(box[:, 2], BOX[:, 2])
    near_far = seen_region_box(BOX, camera_at(0.0), K, (100, 100), near_far=(2.5, 3.5))
    assert torch.allclose(near_far[:, 2], torch.tensor([-0.5, 0.5]), atol=cell)
    assert float(near_far[1, 0]) < float(box[1, 0])  # nearer far bound: narrower frustum


def test_min_views_keeps_the_union_or_the_overlap():
    cameras = torch.cat([camera_at(-0.4), camera_at(0.4)])
    intrinsics = K.expand(2, 4)
    union = seen_region_box(BOX, cameras, intrinsics, (100, 100), min_views=1)
    overlap = seen_region_box(BOX, cameras, intrinsics, (100, 100), min_views=2)
    cell = 2.0 / 64
    assert torch.allclose(union[:, 0], torch.tensor([-0.9, 0.9]), atol=cell)
    assert torch.allclose(overlap[:, 0], torch.tensor([-0.1, 0.1]), atol=cell)
    # More views asked than exist: every camera must see it.
    assert torch.equal(seen_region_box(BOX, cameras, intrinsics, (100, 100), min_views=5), overlap)


def test_cameras_looking_away_leave_the_box_alone():
    away = look_at((0.0, 0.0, 3.0), (0.0, 0.0, 4.0))[None, :3].float()
    assert seen_region_box(BOX, away, K, (100, 100)) is None
    assert torch.equal(fit_scene_box(BOX, None), BOX)


def test_fitted_box_joins_points_adds_margin_and_stays_in_the_box():
    seen = torch.tensor([[-0.5, -0.5, -1.0], [0.5, 0.5, 1.0]])
    assert torch.allclose(fit_scene_box(BOX, seen, margin=0.0), seen)
    widened = fit_scene_box(BOX, seen, margin=0.1)
    assert torch.allclose(widened[:, 0], torch.tensor([-0.6, 0.6])) and torch.equal(widened[:, 2], BOX[:, 2])
    points = torch.tensor([[0.8, 0.0, 0.0], [5.0, 5.0, 5.0]])  # the second lies outside the box: ignored
    joined = fit_scene_box(BOX, seen, points, margin=0.0)
    assert torch.allclose(joined[1], torch.tensor([0.8, 0.5, 1.0]))
    only_points = fit_scene_box(BOX, None, torch.tensor([[0.1, 0.2, 0.3], [0.2, 0.3, 0.4]]), margin=0.0)
    assert torch.allclose(only_points, torch.tensor([[0.1, 0.2, 0.3], [0.2, 0.3, 0.4]]))


def test_uninformative_views_are_named():
    from frugalnerf_ns.geometry.scene_analysis import uninformative_view_notes

    c2w = torch.eye(4)[:3].expand(3, 3, 4).clone()
    c2w[1, 0, 3] = 0.5
    c2w[2, 0, 3] = 0.5 + 1e-7  # the same position as view b, up to float noise
    images = torch.rand(3, 8, 8, 3)
    images[0] = 0.004  # 1/255 and below: black with sensor noise
    notes = uninformative_view_notes(images, c2w, ["a.png", "b.png", "c.png"])
    assert len(notes) == 2
    assert "a.png are entirely black" in notes[0] and "b.png" not in notes[0]
    assert "b.png and c.png were taken from the same position" in notes[1]
    c2w[2, 0, 3] = 1.0
    assert uninformative_view_notes(torch.rand(3, 8, 8, 3), c2w, ["a", "b", "c"]) == []


def test_the_focus_box_is_a_cube_on_the_focus_that_holds_every_training_camera():
    from frugalnerf_ns.geometry.scene_analysis import FOCUS_BOX_SCALE, focus_box

    focus = torch.tensor([0.5, -1.0, 2.0])
    centres = focus + torch.tensor([[3.0, 0.0, 0.0], [0.0, 0.0, -4.0], [2.0, 1.0, 2.0]])
    c2w = torch.zeros(3, 3, 4)
    c2w[:, :3, :3] = torch.eye(3)
    c2w[:, :3, 3] = centres
    box = focus_box(c2w, focus)
    assert torch.allclose((box[0] + box[1]) / 2, focus)
    assert torch.allclose(box[1] - box[0], torch.full((3,), 2 * FOCUS_BOX_SCALE * 4.0))  # the farthest camera: 4
    assert ((centres > box[0]) & (centres < box[1])).all()
