"""Cameras of a few photos without poses (issue 33): pycolmap verification, relative and absolute pose, bundle
adjustment, test-photo registration, one-line errors; on a rendered two-depth scene with known cameras and on
LLFF fern against its published poses."""

import math
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from frugalnerf_ns.data.input_checks import DataError
from frugalnerf_ns.data.photo_poses import (
    FEATURE_ATTEMPTS,
    PoseEstimationOptions,
    estimate_cameras,
    focal_from_35mm,
    focal_from_field_of_view,
)
from frugalnerf_ns.data.photo_geometry import opengl_to_world_to_camera, world_to_camera_to_opengl
from frugalnerf_ns.data.sparse_points import extract_sift
from frugalnerf_ns.geometry.camera_conventions import llff_to_opengl
from frugalnerf_ns.geometry.reprojection import project_to_camera
from tests.photo_scene import FOCAL, HEIGHT, TRUE, WIDTH, camera, render

FERN = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "llff" / "fern"
def rotation_angle(a, b):
    """Degrees of the rotation between two 3x3 rotations."""
    cos = (np.trace(a.T @ b) - 1.0) / 2.0
    return math.degrees(math.acos(np.clip(cos, -1.0, 1.0)))


def relative(c2w_a, c2w_b):
    """(rotation of b in a's frame, unit direction of b's centre in a's frame)."""
    rotation = c2w_a[:3, :3].T @ c2w_b[:3, :3]
    offset = c2w_a[:3, :3].T @ (c2w_b[:3, 3] - c2w_a[:3, 3])
    return rotation, offset / np.linalg.norm(offset)


def direction_error(a, b):
    return math.degrees(math.acos(np.clip(float(a @ b), -1.0, 1.0)))




def test_conventions_round_trip_and_agree_with_project_to_camera():
    c2w = TRUE[1].numpy()
    rotation, translation = opengl_to_world_to_camera(c2w)
    assert np.allclose(world_to_camera_to_opengl(rotation, translation), c2w)
    # COLMAP's x_cam = R X + t with OpenCV axes projects where our OpenGL camera does.
    point = np.array([0.2, -0.1, -2.5])
    cam = rotation @ point + translation
    uv = FOCAL * cam[:2] / cam[2] + np.array([WIDTH / 2, HEIGHT / 2])
    ours = project_to_camera(torch.tensor(point)[None], torch.tensor(c2w)[None],
                             torch.tensor([[FOCAL, FOCAL, WIDTH / 2, HEIGHT / 2]], dtype=torch.float64))
    assert np.allclose(ours.pixels[0].numpy(), uv)
    assert math.isclose(focal_from_field_of_view(640, 480, 90.0), 320.0)
    assert math.isclose(focal_from_35mm(4032, 3024, 26.0), 26.0 * 4032 / 36.0)


def test_two_photos_give_the_relative_pose_and_points_that_reproject():
    images = [render(c) for c in TRUE[:2]]
    est = estimate_cameras(images, ["a.png", "b.png"], FOCAL, PoseEstimationOptions())
    assert est.focal == FOCAL  # two views: the given focal length is kept
    true_rotation, true_direction = relative(TRUE[0].numpy(), TRUE[1].numpy())
    rotation, direction = relative(est.camera_to_worlds[0].numpy(), est.camera_to_worlds[1].numpy())
    assert rotation_angle(true_rotation, rotation) < 0.3
    assert direction_error(true_direction, direction) < 1.0
    points = est.points
    assert points.num_points > 150
    proj = project_to_camera(points.points[points.point], est.camera_to_worlds[points.view], est.intrinsics[points.view])
    assert torch.allclose(proj.pixels, points.pixels, atol=1e-6)
    assert torch.allclose(points.depth, (points.points[points.point] - est.camera_to_worlds[points.view, :, 3]).norm(dim=-1))
    # Up to the gauge (a similarity), the points lie on the scene's surfaces: moved into the true first camera's
    # frame at the true baseline, each is within ~1-2 texels (0.012) of the wall or the card (1.6 and 3 units away).
    world = in_true_frame(points.points.numpy(), est.camera_to_worlds.numpy(), TRUE)
    x, y, z = world.T
    off_surface = np.minimum(np.abs(z - (-3.0 + 0.2 * y)), np.abs(z - (-1.6 - 0.15 * x)))
    assert np.median(off_surface) < 0.02 and np.percentile(off_surface, 90) < 0.05


def in_true_frame(points, c2w, truth):
    """Estimated points moved by the similarity that puts the estimate's first camera on the true first camera
    and its first baseline at the true length."""
    scale = np.linalg.norm(truth[1][:3, 3].numpy() - truth[0][:3, 3].numpy()) / np.linalg.norm(c2w[1, :3, 3] - c2w[0, :3, 3])
    local = (points - c2w[0, :3, 3]) @ c2w[0, :3, :3] * scale
    return local @ truth[0][:3, :3].numpy().T + truth[0][:3, 3].numpy()


def test_three_photos_refine_a_wrong_focal_length_and_register_a_test_photo():
    images = [render(c) for c in TRUE[:3]]
    refine = PoseEstimationOptions(refine_focal_length=True)
    est = estimate_cameras(images, ["a", "b", "c"], FOCAL * 1.12, refine, [render(TRUE[3])], ["test"])
    assert abs(est.focal / FOCAL - 1.0) < 0.03
    for a, b in ((0, 1), (0, 2), (1, 2)):
        true_rotation, true_direction = relative(TRUE[a].numpy(), TRUE[b].numpy())
        rotation, direction = relative(est.camera_to_worlds[a].numpy(), est.camera_to_worlds[b].numpy())
        assert rotation_angle(true_rotation, rotation) < 0.3 and direction_error(true_direction, direction) < 1.0
    true_rotation, true_direction = relative(TRUE[0].numpy(), TRUE[3].numpy())
    rotation, direction = relative(est.camera_to_worlds[0].numpy(), est.test_camera_to_worlds[0].numpy())
    assert rotation_angle(true_rotation, rotation) < 0.3 and direction_error(true_direction, direction) < 1.5
    # A test photo never changes the training reconstruction.
    alone = estimate_cameras(images, ["a", "b", "c"], FOCAL * 1.12, refine)
    assert estimate_cameras(images, ["a", "b", "c"], FOCAL * 1.12, PoseEstimationOptions()).focal == FOCAL * 1.12
    assert torch.equal(alone.camera_to_worlds, est.camera_to_worlds) and alone.focal == est.focal
    assert torch.equal(alone.points.points, est.points.points)


def test_the_focal_length_is_refined_through_lens_distortion():
    # A phone-like lens (k = 0.04) and a 65-degree guess 10 % short of the truth: refined with the distortion
    # term, the focal length comes out +1.1 % off; as a pure pinhole it absorbs the distortion (+2.3 %).
    images = [render(c, radial=0.04) for c in TRUE[:3]]
    est = estimate_cameras(images, ["a", "b", "c"], None, PoseEstimationOptions())
    assert focal_from_field_of_view(WIDTH, HEIGHT, 65.0) < 0.92 * FOCAL
    assert abs(est.focal / FOCAL - 1.0) < 0.017


def test_bad_photos_get_one_line_naming_them():
    good = [render(c) for c in TRUE[:2]]
    with pytest.raises(DataError, match=r"photo blank.png has 0 SIFT features"):
        estimate_cameras([good[0], np.full_like(good[0], 128)], ["a.png", "blank.png"], None, PoseEstimationOptions())
    with pytest.raises(DataError, match=r"photo other.png shares at most \d+ verified matches .*at least 30 needed"):
        estimate_cameras(good + [render(TRUE[2], seed=7)], ["a", "b", "other.png"], None, PoseEstimationOptions())
    with pytest.raises(DataError, match="at least 2 photos"):
        estimate_cameras(good[:1], ["a"], None, PoseEstimationOptions())
    # Turning on the spot: no baseline, nothing to triangulate.
    turned = [render(camera((0.0, 0.0, 0.0), (x, 0.0, -2.0))) for x in (-0.15, 0.15)]
    with pytest.raises(DataError, match="from \\(almost\\) one place"):
        estimate_cameras(turned, ["left", "right"], FOCAL, PoseEstimationOptions())
    with pytest.raises(DataError, match="test photo far could not be registered"):
        estimate_cameras(good, ["a", "b"], FOCAL, PoseEstimationOptions(), [render(TRUE[2], seed=7)], ["far"])


def low_contrast(image, contrast):
    """The photo's grey levels squeezed around mid-grey (a dim room, a hazy day)."""
    return np.clip(128 + contrast * (image.astype(np.float32) - 128), 0, 255).astype(np.uint8)


def test_low_contrast_photos_register_with_more_features_and_failures_say_what_was_tried():
    dim = [low_contrast(render(c), 0.12) for c in TRUE[:3]]
    # COLMAP's SIFT settings find nothing in these photos; the second setting finds a few hundred features.
    assert max(len(k) for k in extract_sift(dim, 8192, progress=False)[0]) < 30
    second = FEATURE_ATTEMPTS[1]
    assert min(len(k) for k in extract_sift(dim, 8192, progress=False, peak_threshold=second.peak_threshold)[0]) > 200
    est = estimate_cameras(dim, ["a", "b", "c"], None, PoseEstimationOptions(), [low_contrast(render(TRUE[3]), 0.12)],
                           ["test"])
    assert abs(est.focal / FOCAL - 1.0) < 0.03
    for a, b in ((0, 1), (0, 2), (1, 2)):
        true_rotation, true_direction = relative(TRUE[a].numpy(), TRUE[b].numpy())
        rotation, direction = relative(est.camera_to_worlds[a].numpy(), est.camera_to_worlds[b].numpy())
        assert rotation_angle(true_rotation, rotation) < 0.5 and direction_error(true_direction, direction) < 2.0
    true_rotation, _ = relative(TRUE[0].numpy(), TRUE[3].numpy())
    rotation, _ = relative(est.camera_to_worlds[0].numpy(), est.test_camera_to_worlds[0].numpy())
    assert rotation_angle(true_rotation, rotation) < 0.5  # the test photo matched with the same setting
    darker = [low_contrast(render(c), 0.03) for c in TRUE[:3]]
    with pytest.raises(DataError) as failure:
        estimate_cameras(darker, ["a.png", "b.png", "c.png"], None, PoseEstimationOptions())
    line = str(failure.value)
    assert "\n" not in line and line.count("frugalnerf: error:") == 1
    assert "photo a.png has 0 SIFT features" in line and f"also tried with {second.describe()}: photo " in line


@pytest.mark.skipif(not FERN.exists(), reason="../shared/data is absent")
@pytest.mark.parametrize("views", [(6, 13), (1, 10, 19)])
def test_fern_cameras_agree_with_llffs_published_poses(views):
    files = sorted((FERN / "images_8").iterdir())
    images = [np.asarray(Image.open(files[v]).convert("RGB")) for v in views]
    poses = np.load(FERN / "poses_bounds.npy")[:, :15].reshape(-1, 3, 5)
    truth = llff_to_opengl(poses[:, :, :4])[list(views)]
    est = estimate_cameras(images, [files[v].name for v in views], None, PoseEstimationOptions())
    c2w = est.camera_to_worlds.numpy()
    for a in range(len(views)):
        for b in range(a + 1, len(views)):
            true_rotation, true_direction = relative(truth[a], truth[b])
            rotation, direction = relative(c2w[a], c2w[b])
            # Measured: 0.93 / 1.89 deg (6, 13), <= 0.82 / 1.41 deg (1, 10, 19).
            assert rotation_angle(true_rotation, rotation) < 1.5 and direction_error(true_direction, direction) < 3.0
    true_focal = poses[0, 2, 4] * images[0].shape[1] / poses[0, 1, 4]
    # Two views: the assumed 65 degrees (LLFF's phone: 64); three: refined from it (measured +0.1 % on an AMD EPYC,
    # +5.07 % on an Intel Xeon with AVX512-BF16, 2026-12-06: the features and the refinement differ by processor).
    assert abs(est.focal / true_focal - 1.0) < 0.06
    assert est.points.num_points > 200


def test_align_cameras_recovers_a_similarity_from_two_cameras():
    from frugalnerf_ns.geometry.camera_conventions import align_cameras, apply_similarity

    truth = np.stack([c.numpy() for c in TRUE])
    angle = 0.7
    rotation = np.array([[math.cos(angle), 0.0, math.sin(angle)], [0.0, 1.0, 0.0], [-math.sin(angle), 0.0, math.cos(angle)]])
    moved = apply_similarity(truth, rotation.T, 0.25, np.array([1.0, -2.0, 0.5]))
    r, s, t = align_cameras(moved[:2], truth[:2])  # two cameras determine it through their orientations
    assert np.allclose(apply_similarity(moved, r, s, t), truth, atol=1e-9)
    assert math.isclose(s, 4.0)
