"""The geometry of cross-scale geometric adaptation as pure torch functions (paper Sec. 3.4-3.5, Eq. 2-4 and
6-8, supp. Sec. B): the warp, the reprojection error and the pseudo depth; the loss (Eq. 5, 9) is in losses.py.

A pixel of one view is lifted to 3D with its own ray and a rendered depth, projected into its nearest
training view and compared with that view's colour there. The scale whose depth explains the other view
best becomes the pseudo ground truth depth of every scale.

Conventions: cameras are nerfstudio's (camera-to-world [3, 4], OpenGL axes: x right, y up, the camera looks
down -z; pixel (u, v) is measured from the image's top-left corner with pixel centres at i + 0.5). Depths
are metric distances along the (unit) world ray; NDC scenes convert before calling (see ``ndc.py``).
Colours are in [0, 1].
"""

from __future__ import annotations

from typing import NamedTuple, Tuple

import torch
import torch.nn.functional as F
from jaxtyping import Bool, Float, Int
from torch import Tensor

# Points closer than this (in front of the camera, metric units) are treated as behind it: projecting
# them divides by ~0 and throws them arbitrarily far across the image.
MIN_CAMERA_DEPTH = 1e-4
# A pixel whose warp is invalid (behind the camera, outside the image) counts with the largest possible
# colour error: per-channel differences of colours in [0, 1] are at most 1.
MAX_PIXEL_ERROR = 1.0


class Projection(NamedTuple):
    pixels: Float[Tensor, "*bs 2"]
    """(u, v) pixel coordinates in the target image."""
    depth: Float[Tensor, "*bs"]
    """Distance in front of the target camera along its optical axis (> 0 when visible)."""
    in_front: Bool[Tensor, "*bs"]
    """The point lies in front of the target camera (depth above MIN_CAMERA_DEPTH)."""


class Warp(NamedTuple):
    colors: Float[Tensor, "*bs 3"]
    """Target image sampled where the points land (bilinear; 0 where invalid)."""
    valid: Bool[Tensor, "*bs"]
    """The point is in front of the target camera and lands inside its image."""


def unproject_along_rays(
    origins: Float[Tensor, "*bs 3"], directions: Float[Tensor, "*bs 3"], depth: Float[Tensor, "*bs"]
) -> Float[Tensor, "*bs 3"]:
    """Supp. Eq. "x^l = o_i(p_i) + D_i^l(p_i) v_i(p_i)": the 3D point of a pixel at a rendered depth, on the
    pixel's own ray (the reference code pairs patch pixels with other rays' depths; we do not)."""
    return origins + directions * depth[..., None]


def project_to_camera(
    points: Float[Tensor, "*bs 3"],
    camera_to_world: Float[Tensor, "*bs 3 4"],
    intrinsics: Float[Tensor, "*bs 4"],
) -> Projection:
    """Supp. Eq. "x_{i->j} = R_j^T (x - t_j)" and "p_{i->j} = pi(K_j x_{i->j})" for OpenGL-style cameras.

    ``intrinsics`` holds (fx, fy, cx, cy). The camera looks down -z and its y axis points up while image
    rows grow downwards, hence the two sign flips.
    """
    rotation, translation = camera_to_world[..., :3, :3], camera_to_world[..., :3, 3]
    local = torch.einsum("...ji,...j->...i", rotation, points - translation)  # R^T (x - t)
    depth = -local[..., 2]
    in_front = depth > MIN_CAMERA_DEPTH
    safe_depth = torch.where(in_front, depth, torch.ones_like(depth))
    fx, fy, cx, cy = intrinsics.unbind(-1)
    u = cx + fx * local[..., 0] / safe_depth
    v = cy - fy * local[..., 1] / safe_depth
    return Projection(torch.stack([u, v], dim=-1), depth, in_front)


def sample_images(
    images: Float[Tensor, "views height width 3"],
    view_index: Int[Tensor, " points"],
    pixels: Float[Tensor, "points 2"],
) -> Warp:
    """Bilinearly sample ``images[view_index]`` at continuous pixel coordinates (pixel centres at i + 0.5).

    Points outside [0, W] x [0, H] are invalid; inside, border padding keeps the half pixel at the edge
    from blending with zeros.
    """
    num_views, height, width, _ = images.shape
    colors = torch.zeros(pixels.shape[0], 3, dtype=images.dtype, device=images.device)
    finite = torch.isfinite(pixels).all(dim=-1)
    u, v = pixels.unbind(-1)
    inside = finite & (u >= 0) & (u <= width) & (v >= 0) & (v <= height)
    # align_corners=False: normalised -1 / 1 are the outer edges of the image, i.e. pixel coordinate 0 / W.
    grid = torch.where(finite[:, None], pixels, torch.zeros_like(pixels))
    grid = torch.stack([2.0 * grid[:, 0] / width - 1.0, 2.0 * grid[:, 1] / height - 1.0], dim=-1)
    chw = images.permute(0, 3, 1, 2)
    for view in range(num_views):
        rows = (view_index == view).nonzero(as_tuple=True)[0]
        if rows.numel() == 0:
            continue
        sampled = F.grid_sample(
            chw[view : view + 1], grid[rows][None, :, None, :], mode="bilinear", padding_mode="border",
            align_corners=False,
        )  # [1, 3, n, 1]
        colors[rows] = sampled[0, :, :, 0].T
    colors = torch.where(inside[:, None], colors, torch.zeros_like(colors))
    return Warp(colors, inside)


def warp_to_views(
    origins: Float[Tensor, "points 3"],
    directions: Float[Tensor, "points 3"],
    depth: Float[Tensor, " points"],
    target_view: Int[Tensor, " points"],
    images: Float[Tensor, "views height width 3"],
    camera_to_worlds: Float[Tensor, "views 3 4"],
    intrinsics: Float[Tensor, "views 4"],
) -> Warp:
    """Colour each point's target view shows where the point (at ``depth`` on its own ray) lands."""
    points = unproject_along_rays(origins, directions, depth)
    projection = project_to_camera(points, camera_to_worlds[target_view], intrinsics[target_view])
    warp = sample_images(images, target_view, projection.pixels)
    valid = warp.valid & projection.in_front
    return Warp(torch.where(valid[:, None], warp.colors, torch.zeros_like(warp.colors)), valid)


def downsample_views(
    images: Float[Tensor, "views height width 3"], intrinsics: Float[Tensor, "views 4"], factor: int
) -> Tuple[Float[Tensor, "views h w 3"], Float[Tensor, "views 4"]]:
    """The views averaged over ``factor`` x ``factor`` blocks and their intrinsics for that size: a pixel
    coordinate u of the full image is u / factor there (pixel centres at i + 0.5 in both), so warps into the
    smaller image land where they would in the full one, blurred over the block. Rows and columns beyond the
    last whole block are dropped (the intrinsics do not move: the image's top-left corner stays put)."""
    if factor == 1:
        return images, intrinsics
    small = F.avg_pool2d(images.permute(0, 3, 1, 2), factor).permute(0, 2, 3, 1).contiguous()
    return small, intrinsics / factor


def patch_reprojection_error(
    source_colors: Float[Tensor, "*scales patches pixels 3"],
    warped: Warp,
) -> Float[Tensor, "*scales patches"]:
    """Eq. 2 over a k x k patch (supp. Sec. B): the colour difference between each pixel of a view and
    where its warp lands in the nearest training view, aggregated over the patch.

    ``warped`` has colours [*scales, patches, pixels, 3] and validity [*scales, patches, pixels].
    Per pixel the error is the mean over RGB of the squared difference (in [0, 1]); an invalid warp counts
    as MAX_PIXEL_ERROR. The error is the RMSE over the patch (the reference code's choice): the square root of
    the mean, so it reads in colour units: 0.5 means the warped patch is off by half the colour range on
    average. It is in [0, 1], and a patch with more than a quarter of its pixels landing outside the other view
    has RMSE >= 0.5.
    """
    per_pixel = ((source_colors - warped.colors) ** 2).mean(dim=-1)
    per_pixel = torch.where(warped.valid, per_pixel, torch.full_like(per_pixel, MAX_PIXEL_ERROR))
    mse = per_pixel.mean(dim=-1)
    return mse.clamp_min(0).sqrt()


class PseudoDepth(NamedTuple):
    depth: Float[Tensor, " rays"]
    """Pseudo ground truth depth D' (detached)."""
    scale: Int[Tensor, " rays"]
    """Scale l' whose depth was chosen."""
    reliable: Bool[Tensor, " rays"]
    """The chosen scale's error is at most the threshold (the ray takes part in L_geo)."""


def select_pseudo_depth(
    errors: Float[Tensor, "scales rays"], depths: Float[Tensor, "scales rays"], threshold: float
) -> PseudoDepth:
    """Eq. 3-4 (train rays) and Eq. 7-8 (novel rays): l' = argmin_l e^l, D' = D^{l'} (no gradient); rays
    whose least error exceeds ``threshold`` are flagged unreliable and left out of the loss."""
    best_error, scale = errors.detach().min(dim=0)
    depth = depths.detach().gather(0, scale[None])[0]
    return PseudoDepth(depth, scale, best_error <= threshold)


