"""The photometric consistency terms (``geometric_adaptation.photometric_consistency`` on training patches, on in the
CPU presets; ``novel_view_photometric_consistency`` on novel rays, off in every preset): the pyramid's pixel
coordinates, the losses' minimum and gradient at the true depth of a textured plane, and the patches they leave out."""

import numpy as np
import torch

from frugalnerf_ns.geometry.reprojection import downsample_views, project_to_camera, sample_images
from frugalnerf_ns.model import losses
from frugalnerf_ns.model.geometric_adaptation import ReferenceViews, novel_view_photometric_consistency, photometric_consistency
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


def novel_patch_rays(eye, corners):
    """Rays of 2x2 patches (top-left pixels ``corners``, patch-major) of a camera at ``eye`` that is no training view,
    and the metric distance along each unit ray to the plane."""
    c2w = camera(eye).float()
    dv, du = torch.meshgrid(torch.arange(2), torch.arange(2), indexing="ij")
    pixels = torch.cat([torch.stack([left + du.flatten(), top + dv.flatten()], -1) for top, left in corners]).float() + 0.5
    local = torch.stack([(pixels[:, 0] - WIDTH / 2) / FOCAL, -(pixels[:, 1] - HEIGHT / 2) / FOCAL, -torch.ones(len(pixels))], -1)
    directions = local @ c2w[:3, :3].T
    directions = directions / directions.norm(dim=-1, keepdim=True)
    origins = c2w[:3, 3].expand_as(directions)
    distance = (PLANE_Z - origins[:, 2] - 0.2 * origins[:, 0]) / (directions[:, 2] + 0.2 * directions[:, 0])
    return origins, directions, distance


NOVEL_EYE = (0.0, 0.03, 2.05)  # between the two views
NOVEL_CORNERS = [(60 + 13 * i, 90 + 17 * j) for i in range(6) for j in range(6)]


def novel_loss(depth, images, c2w, k, origins, directions, first=None, second=None, levels=3, max_error=0.3):
    rays = len(depth)
    first = torch.zeros(rays, dtype=torch.long) if first is None else first
    second = torch.ones(rays, dtype=torch.long) if second is None else second
    return novel_view_photometric_consistency(origins, directions, depth, first, second, 4, ReferenceViews(images, c2w, k), levels, max_error)


def test_novel_rays_see_one_colour_in_both_views_at_the_true_depth_and_descend_to_it():
    images, c2w, k = plane_views()
    origins, directions, distance = novel_patch_rays(NOVEL_EYE, NOVEL_CORNERS)
    at_truth = float(novel_loss(distance, images, c2w, k, origins, directions))
    for relative in (0.97, 0.99, 1.01, 1.03):
        depth = (distance * relative).requires_grad_(True)
        loss = novel_loss(depth, images, c2w, k, origins, directions)
        assert float(loss.detach()) > at_truth + 2e-4, relative
        loss.backward()
        assert float(depth.grad.sum()) * (relative - 1.0) > 0, relative
    # The two views swapped: the same comparison, the same loss.
    swapped = novel_loss(distance * 1.02, images, c2w, k, origins, directions, torch.ones(len(distance), dtype=torch.long),
                         torch.zeros(len(distance), dtype=torch.long))
    torch.testing.assert_close(swapped, novel_loss(distance * 1.02, images, c2w, k, origins, directions))


def test_novel_patches_without_a_second_view_or_off_an_image_get_no_gradient():
    images, c2w, k = plane_views()
    origins, directions, distance = novel_patch_rays(NOVEL_EYE, NOVEL_CORNERS[:4])
    second = torch.ones(len(distance), dtype=torch.long)
    second[4:8] = -1  # patch 1: one training view only
    depth = distance.clone()
    depth[:4] = 0.05  # patch 0: a hair in front of the camera, off both images
    depth.requires_grad_(True)
    novel_loss(depth * 1.01, images, c2w, k, origins, directions, second=second).backward()
    per_patch = depth.grad.abs().reshape(-1, 4).sum(-1)
    assert per_patch[0] == 0 and per_patch[1] == 0 and bool((per_patch[2:] > 0).all()), per_patch


def explicit_dissimilarity(x: torch.Tensor, y: torch.Tensor, window: int = 3) -> torch.Tensor:
    """(1 - SSIM) / 2 of one square patch (pixels x 3), written out block by block."""
    side = int(len(x) ** 0.5)
    x, y = x.reshape(side, side, 3).double(), y.reshape(side, side, 3).double()
    values = []
    for top in range(side - window + 1):
        for left in range(side - window + 1):
            for c in range(3):
                a = x[top:top + window, left:left + window, c].flatten()
                b = y[top:top + window, left:left + window, c].flatten()
                mu_a, mu_b = a.mean(), b.mean()
                var_a, var_b = (a * a).mean() - mu_a**2, (b * b).mean() - mu_b**2
                cov = (a * b).mean() - mu_a * mu_b
                ssim = ((2 * mu_a * mu_b + 1e-4) * (2 * cov + 9e-4)) / ((mu_a**2 + mu_b**2 + 1e-4) * (var_a + var_b + 9e-4))
                values.append(((1 - ssim) / 2).clamp(0, 1))
    return torch.stack(values).mean()


def test_patch_dissimilarity_is_ssim_over_3x3_blocks_and_ignores_exposure_more_than_structure():
    generator = torch.Generator().manual_seed(0)
    source = torch.rand(4, PATCH * PATCH, 3, generator=generator)
    warped = torch.rand(4, PATCH * PATCH, 3, generator=generator)
    ours = losses.patch_dissimilarity(source, warped)
    expected = torch.stack([explicit_dissimilarity(s, w) for s, w in zip(source, warped)]).float()
    torch.testing.assert_close(ours, expected, atol=1e-5, rtol=0)
    assert bool((losses.patch_dissimilarity(source, source) < 1e-6).all())
    # A darker, flatter exposure of the same patch against the patch shifted by a pixel: L1 calls the exposure
    # worse, SSIM the shift (the exposure keeps every block's structure).
    v, u = torch.meshgrid(torch.arange(PATCH + 1.0), torch.arange(PATCH + 1.0), indexing="ij")
    image = torch.stack([0.5 + 0.3 * torch.sin(u + c) * torch.cos(0.8 * v - c) for c in (0, 1, 2)], -1)
    patch = image[:PATCH, :PATCH].reshape(1, -1, 3)
    shifted = image[1:, 1:].reshape(1, -1, 3)
    exposed = 0.5 * patch + 0.05
    assert float((exposed - patch).abs().mean()) > float((shifted - patch).abs().mean())
    assert float(losses.patch_dissimilarity(patch, exposed)) < float(losses.patch_dissimilarity(patch, shifted))


def test_the_ssim_share_keeps_the_least_loss_at_the_true_depth_under_another_exposure():
    """The other view re-exposed (0.7 x + 0.1): the L1 term's minimum leaves the plane, the SSIM mix's stays, and its
    gradient still points to the plane."""
    images, c2w, k = plane_views()
    images[1] = 0.7 * images[1] + 0.1
    origins, directions, pixels, distance = patch_rays(c2w, CORNERS)
    rays = len(distance)

    def loss(depth, share):
        return photometric_consistency(
            origins, directions, depth, torch.zeros(rays, dtype=torch.long), pixels, torch.ones(rays, dtype=torch.long),
            PATCH, ReferenceViews(images, c2w, k), 3, 1.0, share,
        )

    assert float(loss(distance * 0.98, 0.0)) < float(loss(distance, 0.0))
    at_truth = float(loss(distance, 0.85))
    for relative in (0.98, 0.995, 1.005, 1.02):
        depth = (distance * relative).requires_grad_(True)
        value = loss(depth, 0.85)
        assert float(value.detach()) > at_truth + 1e-3, relative
        value.backward()
        assert float(depth.grad.sum()) * (relative - 1.0) > 0, relative


def test_patch_dissimilarity_needs_square_patches():
    import pytest

    with pytest.raises(ValueError, match="square"):
        losses.patch_dissimilarity(torch.rand(2, 6, 3), torch.rand(2, 6, 3))
