"""Where novel-view rays come from and which training view each view is compared with (paper Sec. 3.5).

Pure torch functions on nerfstudio camera-to-world matrices ([n, 3, 4], OpenGL axes: the camera looks down
-z, y up).
"""

from __future__ import annotations

import math
from typing import Optional

import torch
from jaxtyping import Float, Int
from torch import Tensor

from frugalnerf_ns.geometry.camera_conventions import average_pose, look_at_poses
from frugalnerf_ns.geometry.scene_analysis import axes_conditioning, focus_point


def spiral_poses(
    camera_to_worlds: Float[Tensor, "views 3 4"],
    focus_depth: float,
    num_poses: int,
    rotations: float,
    radius_scale: float,
    zrate: float,
    min_radius_ratio: float = 0.0,
) -> Float[Tensor, "num_poses 3 4"]:
    """TensoRF's spiral around the training cameras (supp. "Novel pose sampling"): positions circle the
    average camera with radii the 90th percentile of the cameras' offsets from it (times ``radius_scale``)
    per axis, moving in depth at ``zrate`` times the angular speed, and every pose looks at the point
    ``focus_depth`` in front of the average camera, with the average camera's up. ``min_radius_ratio`` raises
    every radius to at least that fraction of the largest (0: the paper's spiral)."""
    if num_poses < 1:
        raise ValueError(f"num_poses must be >= 1, got {num_poses}")
    poses = camera_to_worlds.detach().cpu().double()
    mean = torch.from_numpy(average_pose(poses.numpy()))  # [right, up, back, centre]
    rotation, centre = mean[:, :3], mean[:, 3]
    offsets = (poses[:, :, 3] - centre) @ rotation  # each camera's centre in the average camera's frame
    radii = torch.quantile(offsets.abs(), 0.9, dim=0) * radius_scale
    radii = radii.clamp(min=float(radii.max()) * min_radius_ratio)
    lookat = centre - rotation[:, 2] * focus_depth
    angles = torch.linspace(0.0, 2.0 * math.pi * rotations, num_poses + 1, dtype=torch.float64)[:-1]
    local = torch.stack([angles.cos(), -angles.sin(), -(angles * zrate).sin()], dim=-1) * radii
    positions = centre + local @ rotation.T
    return look_at_poses(positions, lookat, rotation[:, 1]).to(camera_to_worlds)


def optical_axes_focus(camera_to_worlds: Float[Tensor, "views 3 4"]) -> Optional[Float[Tensor, "3"]]:
    """Least-squares point closest to every camera's optical axis (where the cameras look together), or
    None when the axes are (nearly) parallel and the point is ill-defined."""
    # Two axes 2 degrees apart give a smallest eigenvalue ~ 1 - cos(2 deg) = 6e-4.
    if axes_conditioning(camera_to_worlds) < 5e-4:
        return None
    return focus_point(camera_to_worlds, ridge=0.0)


def spiral_focus_depth(
    camera_to_worlds: Float[Tensor, "views 3 4"],
    near_far: Optional[tuple] = None,
    scene_center: Optional[Float[Tensor, "3"]] = None,
) -> float:
    """Depth in front of the average camera that the spiral looks at.

    Forward-facing scenes with near/far bounds use TensoRF's (and LLFF's) choice, a disparity-weighted mix
    of 0.9 x near and 5 x far. Otherwise the spiral looks where the training cameras' optical axes meet
    (object-centric captures) or, failing that, at the scene centre.
    """
    if near_far is not None:
        close, far = 0.9 * float(near_far[0]), 5.0 * float(near_far[1])
        return 1.0 / (0.25 / close + 0.75 / far)
    mean = torch.from_numpy(average_pose(camera_to_worlds.detach().cpu().double().numpy()))
    candidates = [optical_axes_focus(camera_to_worlds), None if scene_center is None else scene_center.detach().cpu().double()]
    for point in candidates:
        if point is not None:
            depth = float(torch.dot(mean[:, 3] - point, mean[:, 2]))  # along the viewing axis (-back)
            if depth > 0:
                return depth
    raise ValueError(
        "cannot aim the novel-view spiral: the training cameras' axes do not meet in front of them and the scene "
        "centre is behind the average camera"
    )


def nearest_other_view(
    query_centers: Float[Tensor, "queries 3"],
    view_centers: Float[Tensor, "views 3"],
    own_view: Optional[Int[Tensor, " queries"]] = None,
    same_position_fraction: float = 0.0,
) -> Int[Tensor, " queries"]:
    """Index of the training view whose centre is closest to each query's centre (a camera or a ray origin),
    never the query's own view: -1 where no other view exists (a single training view).

    "Own" is ``own_view`` where a query is a training view itself (-1 for the others), and any view whose
    centre lies within ``same_position_fraction`` of the widest training baseline of the query (a ray cast
    from a training camera itself: warping into its own view gives every depth the same error)."""
    centers = view_centers.double()
    distance = torch.cdist(query_centers.double(), centers)
    if same_position_fraction > 0:
        baseline = torch.cdist(centers, centers).max() if len(centers) > 1 else centers.new_tensor(0.0)
        distance = torch.where(distance <= same_position_fraction * baseline, torch.full_like(distance, float("inf")), distance)
    if own_view is not None:
        own = own_view >= 0
        rows = own.nonzero(as_tuple=True)[0]
        distance[rows, own_view[own]] = float("inf")
    best = distance.argmin(dim=-1)
    return torch.where(torch.isfinite(distance.min(dim=-1).values), best, torch.full_like(best, -1))
