"""The video camera path (pure torch): upright against the training cameras, aimed at the focus, inside the
region the cameras span, closing its loop. On the procedural scene (known world up: z) and on real fern and
DTU scan65 cameras (skipped where ../shared/data is absent)."""

from pathlib import Path

import pytest
import torch

from frugalnerf_ns.geometry.novel_views import spiral_focus_depth
from frugalnerf_ns.data.procedural_scene import SceneSpec, camera_poses
from frugalnerf_ns.geometry.scene_analysis import classify_camera_layout
from frugalnerf_ns.geometry.video_path import orbit_poses, roll_degrees, video_poses, world_up

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
FERN, FLOWER, SCAN65 = DATA / "llff" / "fern", DATA / "llff" / "flower", DATA / "dtu" / "scan65"


def procedural_training_cameras() -> torch.Tensor:
    spec = SceneSpec()
    poses = camera_poses(spec)
    return torch.stack([poses[i][:3] for i in spec.train_ids])


def assert_closed_loop(poses: torch.Tensor) -> None:
    """The step from the last frame back to frame 0 is no longer than the longest step between frames."""
    centres = poses[:, :, 3].double()
    steps = (centres[1:] - centres[:-1]).norm(dim=-1)
    closing = float((centres[0] - centres[-1]).norm())
    assert closing <= 1.01 * float(steps.max()) + 1e-9
    assert float(steps.max()) > 0  # the camera moves


def assert_looks_at(poses: torch.Tensor, point: torch.Tensor, degrees: float = 0.5) -> None:
    to_point = torch.nn.functional.normalize(point.double() - poses[:, :, 3].double(), dim=-1)
    cosines = (to_point * -poses[:, :, 2].double()).sum(-1)
    assert float(torch.rad2deg(torch.acos(cosines.clamp(max=1.0))).max()) < degrees


def test_world_up_is_the_direction_no_training_camera_is_rolled_against():
    cameras = procedural_training_cameras()  # look-at cameras built with world up +z, looking down 28 deg
    up = world_up(cameras)
    assert torch.allclose(up, torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64), atol=1e-6)
    # The cameras' mean up vector is tilted ~20 deg from it (they look down): not what upright means.
    mean_up = torch.nn.functional.normalize(cameras[:, :, 1].double().mean(0), dim=0)
    assert float(torch.rad2deg(torch.acos(mean_up @ up))) > 15
    # Parallel x axes (one camera) leave the up direction to the camera's own up.
    single = world_up(cameras[:1])
    assert torch.allclose(single, cameras[0, :, 1].double(), atol=1e-6)


def test_object_orbit_is_upright_aimed_and_starts_at_the_first_training_camera():
    cameras = procedural_training_cameras()
    layout = classify_camera_layout(cameras)
    assert layout.scene_type == "object"
    poses = video_poses(cameras, layout.scene_type, 48, focus=layout.focus, coverage_degrees=layout.coverage_degrees)
    assert poses.shape == (48, 3, 4)
    rotations = poses[:, :, :3].double()
    assert torch.allclose(rotations.transpose(1, 2) @ rotations, torch.eye(3, dtype=torch.float64).expand(48, 3, 3), atol=1e-5)
    assert float(roll_degrees(poses, world_up(cameras)).max()) < 0.5
    assert_looks_at(poses, layout.focus)
    assert_closed_loop(poses)
    # Every training camera is at the same distance and height: frame 0 is camera 0's position.
    assert float((poses[0, :, 3] - cameras[0, :, 3]).norm()) < 1e-3
    # An arc through the cameras' azimuths (they span 80 of 360 degrees), not a circle round the back.
    az = torch.atan2(poses[:, 1, 3].double(), poses[:, 0, 3].double()).rad2deg()
    assert float(az.min()) > -40.5 and float(az.max()) < 40.5 and float(az.max() - az.min()) > 79


def test_full_orbit_for_surrounding_cameras():
    spec = SceneSpec(azimuths_deg=tuple(range(0, 360, 45)))
    poses_list = camera_poses(spec)
    cameras = torch.stack([p[:3] for p in poses_list])
    focus = torch.tensor([0.0, 0.0, 0.25])
    poses = orbit_poses(cameras, focus, 36, full_circle=True)
    az = torch.atan2(poses[:, 1, 3].double(), poses[:, 0, 3].double())
    steps = torch.remainder(az[1:] - az[:-1], 2 * torch.pi)
    assert torch.allclose(steps, torch.full_like(steps, 2 * torch.pi / 36), atol=1e-6)  # one even turn
    assert float(roll_degrees(poses, world_up(cameras)).max()) < 0.5
    assert_closed_loop(poses)


def forward_facing_check(scene: Path):
    from frugalnerf_ns.data.dataparsers.llff import LLFFDataParserConfig

    outputs = LLFFDataParserConfig(data=scene).setup().get_dataparser_outputs("train")
    cameras = outputs.cameras.camera_to_worlds
    layout = classify_camera_layout(cameras)
    assert layout.scene_type == "forward-facing"
    depth = spiral_focus_depth(cameras, near_far=outputs.metadata["near_far"])
    radius = 1.0
    poses = video_poses(cameras, layout.scene_type, 72, focus_depth=depth, radius_scale=radius)
    up = world_up(cameras)
    assert float(roll_degrees(cameras, up).max()) < 2.0  # the training cameras are upright against it
    assert float(roll_degrees(poses, up).max()) < 2.0
    mean_centre = cameras[:, :, 3].double().mean(0)
    mean_back = torch.nn.functional.normalize(cameras[:, :, 2].double().sum(0), dim=0)
    assert_looks_at(poses, mean_centre - depth * mean_back)
    # Inside the training cameras' spread (largest offset from their mean centre) times the radius.
    spread = float((cameras[:, :, 3].double() - mean_centre).norm(dim=-1).max())
    assert float((poses[:, :, 3].double() - mean_centre).norm(dim=-1).max()) <= 1.01 * radius * spread
    assert_closed_loop(poses)
    # nerfstudio's spiral from the first camera rolls its frames by tens of degrees (the bug this replaces).
    from nerfstudio.cameras.camera_paths import get_spiral_path

    theirs = get_spiral_path(outputs.cameras[0:1], steps=24, radius=0.1).camera_to_worlds
    assert float(roll_degrees(theirs, up).max()) > 30


@pytest.mark.skipif(not FERN.is_dir(), reason=f"real LLFF scene not present at {FERN}")
def test_fern_spiral_is_upright_around_the_training_cameras():
    forward_facing_check(FERN)


@pytest.mark.skipif(not FLOWER.is_dir(), reason=f"real LLFF scene not present at {FLOWER}")
def test_flower_spiral_is_upright_around_the_training_cameras():
    forward_facing_check(FLOWER)


@pytest.mark.skipif(not SCAN65.is_dir(), reason=f"real DTU scene not present at {SCAN65}")
def test_dtu_orbit_stays_between_the_training_cameras():
    from frugalnerf_ns.data.dataparsers.dtu import DTUDataParserConfig

    cameras = DTUDataParserConfig(data=SCAN65).setup().get_dataparser_outputs("train").cameras.camera_to_worlds
    layout = classify_camera_layout(cameras, has_object_mask=True)
    assert layout.scene_type == "object"
    poses = video_poses(cameras, "object", 48, focus=layout.focus, coverage_degrees=layout.coverage_degrees)
    up = world_up(cameras)
    assert float(roll_degrees(poses, up).max()) < 0.5
    assert_looks_at(poses, layout.focus)
    assert_closed_loop(poses)
    # Frame 0 is near camera 0 (mean distance and height of the two), and no frame is farther from either
    # camera than the two are from each other.
    baseline = float((cameras[0, :, 3] - cameras[1, :, 3]).norm())
    assert float((poses[0, :, 3] - cameras[0, :, 3]).norm()) < 0.1 * baseline
    distance = torch.cdist(poses[:, :, 3].double(), cameras[:, :, 3].double())
    assert float(distance.min(dim=-1).values.max()) <= 0.6 * baseline


def test_the_one_look_at_frame_aims_at_the_target_without_roll():
    from frugalnerf_ns.geometry.camera_conventions import look_at_poses
    from frugalnerf_ns.data.procedural_scene import look_at

    generator = torch.Generator().manual_seed(0)
    positions = torch.randn(50, 3, generator=generator, dtype=torch.float64) * 3
    target, up = torch.tensor([0.2, -0.1, 0.3], dtype=torch.float64), torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    poses = look_at_poses(positions, target, up)
    rotation = poses[:, :, :3]
    assert torch.allclose(rotation.transpose(1, 2) @ rotation, torch.eye(3, dtype=torch.float64).expand(50, 3, 3), atol=1e-12)
    assert torch.allclose(torch.linalg.det(rotation), torch.ones(50, dtype=torch.float64))
    # OpenGL: the camera looks down -z, so -back points from the camera to the target.
    to_target = torch.nn.functional.normalize(target - positions, dim=-1)
    assert torch.allclose(-rotation[:, :, 2], to_target, atol=1e-12)
    # No roll: the right axis is level (perpendicular to up) and the camera's up leans towards the world's up.
    assert torch.allclose(rotation[:, :, 0] @ up, torch.zeros(50, dtype=torch.float64), atol=1e-12)
    assert (rotation[:, :, 1] @ up > 0).all()
    assert torch.equal(poses[:, :, 3], positions)
    # The procedural scene's 4x4 cameras are the same frame.
    c2w = look_at(positions[0].float(), target.float(), up.float())
    assert torch.allclose(c2w[:3], poses[0].float(), atol=1e-6) and c2w[3].tolist() == [0.0, 0.0, 0.0, 1.0]
