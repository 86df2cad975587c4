"""The photometric consistency term (``geometric_adaptation.photometric_consistency`` on training patches): the
pyramid's pixel coordinates, the loss's minimum and gradient at the true depth of a textured plane, and the patches
it leaves out."""

import numpy as np
import torch

from frugalnerf_ns.geometry.reprojection import downsample_views, project_to_camera, sample_images
from frugalnerf_ns.model import losses
from frugalnerf_ns.model.geometric_adaptation import ReferenceViews, photometric_consistency
from tests.photo_scene import texture
from tests.plane_scene import FOCAL, HEIGHT, PLANE_Z, WIDTH, camera, intrinsics, render_plane

PATCH = 5


def test_a_coarser_level_samples_where_the_full_image_would():
    """A ramp image stays a ramp under block averaging: sampled at u / factor with the intrinsics / factor, a
    coarser level reads the full image's value at u (a half-pixel slip in the convention would show here)."""
    height, width = 48, 64
    v, u = torch.meshgrid(torch.arange(height) + 0.5, torch.arange(width) + 0.5, indexing="ij")
    image = torch.stack([u / width, v / height, 0.5 * (u / width + v / height)], -1)[None].float()
    k = torch.tensor([[50.0, 50.0, width / 2, height / 2]])
    c2w = torch.eye(4)[:3][None]
    points = torch.tensor([[0.1, -0.2, -1.0], [-0.3, 0.25, -2.0], [0.02, 0.05, -0.7]])
    full = project_to_camera(points, c2w.expand(3, 3, 4), k.expand(3, 4)).pixels
    expected = torch.stack([full[:, 0] / width, full[:, 1] / height, 0.5 * (full[:, 0] / width + full[:, 1] / height)], -1)
    for factor in (1, 2, 4):
        small, small_k = downsample_views(image, k, factor)
        assert small.shape == (1, height // factor, width // factor, 3)
        pixels = project_to_camera(points, c2w.expand(3, 3, 4), small_k.expand(3, 4)).pixels
        torch.testing.assert_close(pixels, full / factor)
        sampled = sample_images(small, torch.zeros(3, dtype=torch.long), pixels).colors
        torch.testing.assert_close(sampled, expected, atol=1e-5, rtol=0)


def plane_views():
    """Two float views of the textured plane, their cameras and intrinsics."""
    c2w = torch.stack([camera((0.25, 0.1, 2.0)), camera((-0.25, -0.05, 2.1))]).float()
    tex = np.asarray(texture(), np.float32)
    images = torch.stack([torch.from_numpy(render_plane(c, tex)).float() / 255 for c in c2w.double()])
    images = images[..., None].expand(-1, -1, -1, 3).contiguous()
    return images, c2w, intrinsics(2).float()


def patch_rays(c2w, corners):
    """Rays of 5x5 patches of view 0 whose top-left pixels are ``corners`` (patch-major), their pixel centres and
    the metric distance along each unit ray to the plane."""
    rows, columns = [], []
    for top, left in corners:
        dv, du = torch.meshgrid(torch.arange(PATCH), torch.arange(PATCH), indexing="ij")
        rows.append((top + dv).flatten())
        columns.append((left + du).flatten())
    pixels = torch.stack([torch.cat(columns), torch.cat(rows)], -1).float() + 0.5
    local = torch.stack([(pixels[:, 0] - WIDTH / 2) / FOCAL, -(pixels[:, 1] - HEIGHT / 2) / FOCAL, -torch.ones(len(pixels))], -1)
    directions = local @ c2w[0, :3, :3].T
    directions = directions / directions.norm(dim=-1, keepdim=True)
    origins = c2w[0, :3, 3].expand_as(directions)
    distance = (PLANE_Z - origins[:, 2] - 0.2 * origins[:, 0]) / (directions[:, 2] + 0.2 * directions[:, 0])
    return origins, directions, pixels, distance


CORNERS = [(100, 140), (120, 170), (80, 120), (130, 150)]  # inside both views


def loss_at(depth, images, c2w, k, origins, directions, pixels, levels=3, max_error=0.3):
    rays = len(depth)
    return photometric_consistency(
        origins, directions, depth, torch.zeros(rays, dtype=torch.long), pixels, torch.ones(rays, dtype=torch.long),
        PATCH, ReferenceViews(images, c2w, k), levels, max_error,
    )


def test_the_loss_is_least_at_the_true_depth_and_its_gradient_points_to_it():
    images, c2w, k = plane_views()
    origins, directions, pixels, distance = patch_rays(c2w, CORNERS)
    at_truth = float(loss_at(distance, images, c2w, k, origins, directions, pixels))
    for relative in (0.98, 0.995, 1.005, 1.02):  # ~1.5 and 0.4 px of disparity either way
        depth = (distance * relative).requires_grad_(True)
        loss = loss_at(depth, images, c2w, k, origins, directions, pixels)
        assert float(loss.detach()) > at_truth + 2e-4, relative  # (the nearest-texel renders leave 0.012 at the truth)
        loss.backward()
        # Descent moves the depth toward the plane: the mean gradient has the sign of the depth's error.
        assert float(depth.grad.sum()) * (relative - 1.0) > 0, relative


def test_the_coarse_levels_reach_farther_than_the_full_image():
    """10 % off (~5 px of disparity, about the texture's largest blobs): the 3-level pyramid's gradient points toward
    the plane in more patches than the full image's alone."""
    images, c2w, k = plane_views()
    corners = [(60 + 9 * i, 100 + 11 * j) for i in range(8) for j in range(8)]
    origins, directions, pixels, distance = patch_rays(c2w, corners)
    right = {}
    for levels in (1, 3):
        agree = 0
        for relative in (0.9, 1.1):
            depth = (distance * relative).requires_grad_(True)
            loss_at(depth, images, c2w, k, origins, directions, pixels, levels, max_error=1.0).backward()
            per_patch = depth.grad.reshape(-1, PATCH * PATCH).sum(-1)
            agree += int((per_patch * (relative - 1.0) > 0).sum())
        right[levels] = agree / (2 * len(corners))
    assert right[3] > 0.7 and right[3] > right[1] + 0.05, right


def test_patches_off_the_other_image_or_badly_matched_are_left_out():
    images, c2w, k = plane_views()
    origins, directions, pixels, distance = patch_rays(c2w, CORNERS)
    rays = len(distance)
    # Patch 0 a hair in front of its camera lands outside the other image; patch 1 has no other view: neither counts,
    # and neither gets a gradient, while the others do.
    depth = distance.clone()
    depth[:PATCH * PATCH] = 0.05
    depth.requires_grad_(True)
    nearest = torch.ones(rays, dtype=torch.long)
    nearest[PATCH * PATCH:2 * PATCH * PATCH] = -1
    photometric_consistency(origins, directions, depth * 1.01, torch.zeros(rays, dtype=torch.long), pixels, nearest,
                            PATCH, ReferenceViews(images, c2w, k), 3, 0.3).backward()
    per_patch = depth.grad.abs().reshape(-1, PATCH * PATCH).sum(-1)
    assert per_patch[0] == 0 and per_patch[1] == 0 and bool((per_patch[2:] > 0).all()), per_patch
    # Every patch over the error bound: nothing is kept and the loss is 0.
    assert float(loss_at(distance * 1.3, images, c2w, k, origins, directions, pixels, max_error=0.0)) == 0.0


def test_the_loss_itself_averages_kept_patches_only():
    source = torch.zeros(3, 4, 3)
    warped = torch.stack([torch.full((4, 3), 0.1), torch.full((4, 3), 0.3), torch.full((4, 3), 0.9)])
    kept = torch.tensor([True, True, False])
    torch.testing.assert_close(losses.photometric_consistency_loss(source, warped, kept), torch.tensor(0.2))
    assert float(losses.photometric_consistency_loss(source, warped, torch.zeros(3, dtype=torch.bool))) == 0.0
