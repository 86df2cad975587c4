"""Dense two-view stereo by plane sweep (pure torch): the matches between two training views on every textured
pixel whose match is unambiguous, not only at SIFT's keypoints.

Every reference pixel is carried into the source view at depths uniform in inverse depth (z along the reference
camera's axis) between near and far bounds; the zero-mean normalised cross-correlation (NCC) of a square window of
grey levels scores each depth. A pixel keeps its best depth (refined by a parabola through the neighbouring planes'
scores) when the score is high, the window is textured, the score falls off around it (no depth half a pixel or
more away along the epipolar line scores nearly as well: blurred or repeated texture fails) and the source pixel's own best depth carries it back to where it came
from (the left-right check: occlusions and mismatches fail it). A kept pixel is a two-view match whose point lies on
both rays, the observation that L_sd reads from triangulated SIFT points (``data/sparse_points.py``).

Conventions are ``reprojection.py``'s: nerfstudio camera-to-world [3, 4] with OpenGL axes, intrinsics (fx, fy, cx,
cy), pixel (u, v) from the top-left corner with pixel centres at i + 0.5; images are grey levels [H, W].
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple, Optional, Tuple

import torch
import torch.nn.functional as F
from jaxtyping import Bool, Float
from torch import Tensor

from frugalnerf_ns.geometry.reprojection import project_to_camera

MAX_BAND_ENTRIES = 1 << 24
"""Planes x pixels scored at once: the sweep goes through the image in bands of rows below this (64 MB of scores)."""


@dataclass(frozen=True)
class StereoOptions:
    """Which plane-sweep matches are kept."""

    window: int = 7
    """Side of the NCC window in pixels (odd)."""
    min_ncc: float = 0.9
    """Lowest NCC of the best depth."""
    min_std: float = 0.02
    """Lowest standard deviation of the reference window's grey levels (0-1): flat windows match anywhere."""
    uniqueness: float = 0.7
    """The best depth's 1 - NCC at most this times that of the best depth ``uniqueness_pixels`` or more away: the
    score must fall off around the match (a sharp, single peak), not only beat the rest."""
    uniqueness_pixels: float = 0.5
    """How far (in source pixels along the epipolar line, in whole planes, at least one) the uniqueness check looks."""
    max_lr_pixels: float = 1.0
    """Largest distance in pixels at which the source pixel's own depth carries it back to the reference pixel."""
    plane_step_pixels: float = 0.5
    """Largest shift, in source pixels, between neighbouring planes' positions of a reference pixel."""
    max_planes: int = 1024

    @property
    def uniqueness_planes(self) -> int:
        return max(1, round(self.uniqueness_pixels / self.plane_step_pixels))


class PlaneScores(NamedTuple):
    depth: Float[Tensor, "height width"]
    """Best z-depth per reference pixel (parabola-refined in inverse depth)."""
    keep: Bool[Tensor, "height width"]
    """The best depth passes the score, texture and uniqueness checks (not yet the left-right check)."""


def pixel_rays(
    camera_to_world: Float[Tensor, "3 4"], intrinsics: Float[Tensor, "4"], height: int, width: int
) -> Tuple[Float[Tensor, "height width 3"], Float[Tensor, "height width 2"]]:
    """Per pixel centre: the world vector from the camera centre to the point at z-depth 1, and (u, v)."""
    fx, fy, cx, cy = intrinsics.unbind(-1)
    dtype, device = camera_to_world.dtype, camera_to_world.device
    v, u = torch.meshgrid(torch.arange(height, dtype=dtype, device=device) + 0.5,
                          torch.arange(width, dtype=dtype, device=device) + 0.5, indexing="ij")
    local = torch.stack([(u - cx) / fx, -(v - cy) / fy, -torch.ones_like(u)], -1)
    return local @ camera_to_world[:3, :3].T, torch.stack([u, v], -1)


def plane_inverse_depths(
    camera_to_worlds: Float[Tensor, "2 3 4"], intrinsics: Float[Tensor, "2 4"], height: int, width: int,
    near: float, far: float, options: StereoOptions,
) -> Float[Tensor, " planes"]:
    """Inverse depths from 1/near to 1/far, as many as keep neighbouring planes within ``plane_step_pixels`` of
    each other in the source view (measured at the image's corners and centre; at least 8, at most
    ``max_planes``)."""
    rays, _ = pixel_rays(camera_to_worlds[0], intrinsics[0], height, width)
    probe = rays[[0, 0, -1, -1, height // 2], [0, -1, 0, -1, width // 2]]
    ends = torch.stack([camera_to_worlds[0, :3, 3] + probe * near, camera_to_worlds[0, :3, 3] + probe * far])
    proj = project_to_camera(ends, camera_to_worlds[1].expand(2, 5, 3, 4), intrinsics[1].expand(2, 5, 4))
    span = float((proj.pixels[0] - proj.pixels[1]).norm(dim=-1).max())
    planes = int(min(max(math.ceil(span / options.plane_step_pixels) + 1, 8), options.max_planes))
    return torch.linspace(1.0 / near, 1.0 / far, planes, dtype=camera_to_worlds.dtype, device=camera_to_worlds.device)


def _box(x: Tensor, window: int) -> Tensor:
    return F.avg_pool2d(x, window, stride=1, padding=window // 2, count_include_pad=False)


def sweep_scores(
    reference: Float[Tensor, "height width"], source: Float[Tensor, "h2 w2"],
    camera_to_worlds: Float[Tensor, "2 3 4"], intrinsics: Float[Tensor, "2 4"],
    inverse_depths: Float[Tensor, " planes"], options: StereoOptions, rows: Tuple[int, int] = (0, -1),
) -> Tuple[Float[Tensor, "planes band width"], Float[Tensor, "band width"]]:
    """NCC of the reference windows of rows ``rows`` [start, stop) against the source image carried through each
    plane (-1 where the carried pixel leaves the source image or falls behind its camera), and the windows'
    grey-level standard deviation. Windows near the image border average the pixels inside it."""
    height, width = reference.shape
    start, stop = rows[0], height if rows[1] < 0 else rows[1]
    pad = options.window // 2
    lo, hi = max(start - pad, 0), min(stop + pad, height)
    rays, _ = pixel_rays(camera_to_worlds[0], intrinsics[0], height, width)
    rays = rays[lo:hi]
    a = reference[lo:hi][None, None]
    mean_a = _box(a, options.window)
    std_a = (_box(a * a, options.window) - mean_a**2).clamp_min(0).sqrt()
    src = source[None, None]
    src_h, src_w = source.shape
    cam = camera_to_worlds[1].expand(*rays.shape[:2], 3, 4)
    k = intrinsics[1].expand(*rays.shape[:2], 4)
    scores = []
    for inverse in inverse_depths:
        proj = project_to_camera(camera_to_worlds[0, :3, 3] + rays / inverse, cam, k)
        u, v = proj.pixels.unbind(-1)
        grid = torch.stack([u / src_w * 2 - 1, v / src_h * 2 - 1], -1).to(reference.dtype)
        b = F.grid_sample(src, grid[None], mode="bilinear", padding_mode="border", align_corners=False)
        mean_b = _box(b, options.window)
        var_b = (_box(b * b, options.window) - mean_b**2).clamp_min(0)
        ncc = (_box(a * b, options.window) - mean_a * mean_b) / (std_a * var_b.sqrt()).clamp_min(1e-6)
        inside = proj.in_front & (u >= 0) & (u <= src_w) & (v >= 0) & (v <= src_h)
        scores.append(torch.where(inside, ncc[0, 0], torch.full_like(ncc[0, 0], -1.0)))
    crop = slice(start - lo, stop - lo)
    return torch.stack(scores)[:, crop], std_a[0, 0, crop]


def best_plane(
    scores: Float[Tensor, " planes *pixels"], inverse_depths: Float[Tensor, " planes"], std: Float[Tensor, "*pixels"],
    options: StereoOptions,
) -> PlaneScores:
    """The best plane per pixel, its depth refined by a parabola through its neighbours' scores (in inverse depth),
    and whether it passes the score, texture and uniqueness checks (``StereoOptions``); a best plane at either end of the sweep fails
    (the true depth may lie beyond it)."""
    planes = scores.shape[0]
    best = scores.argmax(0)
    top = scores.gather(0, best[None])[0]
    index = torch.arange(planes, device=scores.device).view(-1, *([1] * (scores.ndim - 1)))
    second = torch.where((index - best[None]).abs() >= options.uniqueness_planes, scores, torch.full_like(scores, -1.0)).amax(0)
    before = scores.gather(0, (best - 1).clamp_min(0)[None])[0]
    after = scores.gather(0, (best + 1).clamp_max(planes - 1)[None])[0]
    interior = (best > 0) & (best < planes - 1)
    curvature = before - 2 * top + after
    offset = torch.where(interior & (curvature < -1e-6), 0.5 * (before - after) / curvature.clamp_max(-1e-6),
                         torch.zeros_like(top)).clamp(-0.5, 0.5)
    step = inverse_depths[1] - inverse_depths[0] if planes > 1 else inverse_depths.new_zeros(())
    inverse = inverse_depths[best] + offset.to(inverse_depths.dtype) * step
    keep = interior & (top >= options.min_ncc) & (std >= options.min_std)
    keep &= (1 - top) <= options.uniqueness * (1 - second)
    return PlaneScores(1.0 / inverse, keep)


def plane_sweep_depth(
    reference: Float[Tensor, "height width"], source: Float[Tensor, "h2 w2"],
    camera_to_worlds: Float[Tensor, "2 3 4"], intrinsics: Float[Tensor, "2 4"],
    inverse_depths: Float[Tensor, " planes"], options: StereoOptions, max_band_entries: int = MAX_BAND_ENTRIES,
) -> PlaneScores:
    """``best_plane`` of every reference pixel against the source view, swept in bands of rows so that at most
    ``max_band_entries`` scores are held at once (the result does not depend on the bands)."""
    height, width = reference.shape
    band = max(1, max_band_entries // max(1, inverse_depths.shape[0] * width))
    depths, keeps = [], []
    for start in range(0, height, band):
        scores, std = sweep_scores(reference, source, camera_to_worlds, intrinsics, inverse_depths, options,
                                   (start, min(start + band, height)))
        found = best_plane(scores, inverse_depths, std, options)
        depths.append(found.depth)
        keeps.append(found.keep)
    return PlaneScores(torch.cat(depths), torch.cat(keeps))


class StereoMatches(NamedTuple):
    points: Float[Tensor, "matches 3"]
    """World points, on the reference pixel's ray at its depth."""
    reference_pixels: Float[Tensor, "matches 2"]
    """(u, v) of the reference pixel centre."""
    source_pixels: Float[Tensor, "matches 2"]
    """(u, v) where the point projects in the source view (its ray passes through the point)."""


def stereo_matches(
    images: Tuple[Float[Tensor, "height width"], Float[Tensor, "h2 w2"]],
    camera_to_worlds: Float[Tensor, "2 3 4"], intrinsics: Float[Tensor, "2 4"], near: float, far: float,
    options: StereoOptions = StereoOptions(),
) -> StereoMatches:
    """Plane-sweep matches of view 0's pixels in view 1 that pass every check, the left-right check included
    (view 1 is swept against view 0 too). ``near`` and ``far`` bound the z-depth in both cameras."""
    reference, source = images
    height, width = reference.shape
    flipped = camera_to_worlds.flip(0), intrinsics.flip(0)
    forward = plane_sweep_depth(reference, source, camera_to_worlds, intrinsics,
                                plane_inverse_depths(camera_to_worlds, intrinsics, height, width, near, far, options), options)
    backward = plane_sweep_depth(source, reference, *flipped,
                                 plane_inverse_depths(*flipped, *source.shape, near, far, options), options)
    points, uv, source_uv, consistent = left_right_check(forward.depth, backward.depth, camera_to_worlds, intrinsics,
                                                         options.max_lr_pixels, backward.keep)
    keep = forward.keep & consistent
    return StereoMatches(points[keep], uv[keep], source_uv[keep])


def left_right_check(
    forward_depth: Float[Tensor, "height width"], backward_depth: Float[Tensor, "h2 w2"],
    camera_to_worlds: Float[Tensor, "2 3 4"], intrinsics: Float[Tensor, "2 4"], max_pixels: float,
    backward_keep: Optional[Bool[Tensor, "h2 w2"]] = None,
) -> Tuple[Float[Tensor, "height width 3"], Float[Tensor, "height width 2"], Float[Tensor, "height width 2"], Bool[Tensor, "height width"]]:
    """Per reference pixel: its point at ``forward_depth`` (z), its (u, v), where the point lands in the source view,
    and whether the source pixel it lands on (kept, when ``backward_keep`` is given) carries its own centre, at its
    ``backward_depth``, back within ``max_pixels`` of the reference pixel."""
    height, width = forward_depth.shape
    src_h, src_w = backward_depth.shape
    rays, uv = pixel_rays(camera_to_worlds[0], intrinsics[0], height, width)
    points = camera_to_worlds[0, :3, 3] + rays * forward_depth[..., None]
    proj = project_to_camera(points, camera_to_worlds[1].expand(height, width, 3, 4), intrinsics[1].expand(height, width, 4))
    u, v = proj.pixels.unbind(-1)
    landed = proj.in_front & (u >= 0) & (u < src_w) & (v >= 0) & (v < src_h)
    col, row = u.floor().long().clamp(0, src_w - 1), v.floor().long().clamp(0, src_h - 1)
    source_rays, _ = pixel_rays(camera_to_worlds[1], intrinsics[1], src_h, src_w)
    back_points = camera_to_worlds[1, :3, 3] + source_rays[row, col] * backward_depth[row, col][..., None]
    back = project_to_camera(back_points, camera_to_worlds[0].expand(height, width, 3, 4), intrinsics[0].expand(height, width, 4))
    consistent = landed & back.in_front & ((back.pixels - uv).norm(dim=-1) <= max_pixels)
    if backward_keep is not None:
        consistent &= backward_keep[row, col]
    return points, uv, proj.pixels, consistent

