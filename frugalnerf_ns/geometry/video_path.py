"""Camera paths for a scene's video: the LLFF spiral for forward-facing scenes, an orbit for objects and 360s.

Pure torch functions on nerfstudio camera-to-world matrices ([n, 3, 4], OpenGL axes: the camera looks down
-z, y up). nerfstudio's own ``get_spiral_path`` takes the start camera's z axis as "up": for a forward-facing
capture that is nearly the viewing direction, so every frame is rolled by an arbitrary angle. Here "up" is
the world up of the training cameras (``world_up``), so no frame is rolled against them.
"""

from __future__ import annotations

import math
from typing import Optional

import torch
from jaxtyping import Float
from torch import Tensor

from frugalnerf_ns.geometry.camera_conventions import look_at_poses
from frugalnerf_ns.geometry.novel_views import spiral_poses

# Training cameras spread over less than this azimuth (around the focus) get an arc through their region
# rather than a full circle: the far side of an object two views saw is unconstrained, and a video of it
# would show nothing the data supports.
FULL_ORBIT_MIN_COVERAGE = 180.0
# Each spiral radius is raised to at least this fraction of the largest: two training views side by side have
# no vertical spread, and the spiral would collapse onto a line.
MIN_RADIUS_RATIO = 0.5


def world_up(camera_to_worlds: Float[Tensor, "views 3 4"]) -> Float[Tensor, "3"]:
    """The up direction no training camera is rolled against (float64).

    Every camera of an upright capture has its x axis horizontal, so world up is the direction perpendicular
    to all x axes: the eigenvector of sum(x x^T) with the smallest eigenvalue, turned towards the cameras'
    mean up. When the x axes are (nearly) parallel (one camera, or a forward-facing capture) that direction
    is undetermined and the cameras' mean up, made perpendicular to their mean x axis, is used instead."""
    poses = camera_to_worlds.detach().cpu().double()
    rights, ups = poses[:, :, 0], poses[:, :, 1]
    mean_up = ups.mean(0)
    values, vectors = torch.linalg.eigh(rights.T @ rights / len(rights))
    # The two directions perpendicular to parallel x axes share eigenvalue ~0; a second eigenvalue above
    # 0.01 means the x axes differ by more than ~6 degrees and pin the up direction down.
    if float(values[1]) > 1e-2:
        up = vectors[:, 0]
        return up if float(up @ mean_up) >= 0 else -up
    mean_right = torch.nn.functional.normalize(rights.mean(0), dim=0)
    up = mean_up - (mean_up @ mean_right) * mean_right
    return torch.nn.functional.normalize(up, dim=0)


def orbit_poses(
    camera_to_worlds: Float[Tensor, "views 3 4"],
    center: Float[Tensor, "3"],
    num_poses: int,
    full_circle: bool,
    radius_scale: float = 1.0,
) -> Float[Tensor, "num_poses 3 4"]:
    """Cameras circling ``center`` about the training cameras' ``world_up``, at their mean distance and
    height, looking at ``center``, starting at the first training camera's azimuth.

    ``full_circle``: one turn. Otherwise a closed back-and-forth sweep over the azimuths the training cameras
    span (times ``radius_scale``), so the video stays where the views constrain the scene."""
    if num_poses < 1:
        raise ValueError(f"num_poses must be >= 1, got {num_poses}")
    poses = camera_to_worlds.detach().cpu().double()
    center = center.detach().cpu().double()
    up = world_up(poses)
    offsets = poses[:, :, 3] - center
    heights = offsets @ up
    flat = offsets - heights[:, None] * up
    radius = float(flat.norm(dim=-1).mean())
    if radius < 1e-9:
        raise ValueError("cannot orbit: the training cameras are on the up axis through the scene centre")
    # Azimuth frame: e1 towards the first camera, e2 = up x e1.
    e1 = torch.nn.functional.normalize(flat[0] if float(flat[0].norm()) > 1e-9 else flat.mean(0), dim=0)
    e2 = torch.linalg.cross(up, e1, dim=0)
    azimuths = torch.atan2(flat @ e2, flat @ e1)  # camera 0 at 0
    t = torch.arange(num_poses, dtype=torch.float64) / num_poses  # loop: the frame after the last is frame 0
    if full_circle:
        angles = 2.0 * math.pi * t
    else:
        low, high = float(azimuths.min()), float(azimuths.max())
        middle, half = 0.5 * (low + high), 0.5 * (high - low) * radius_scale
        if half < 1e-9:
            angles = torch.zeros_like(t)
        else:
            # Sinusoidal sweep through the span, phased so frame 0 is at camera 0's azimuth.
            phase = math.asin(max(-1.0, min(1.0, (0.0 - middle) / half)))
            angles = middle + half * torch.sin(2.0 * math.pi * t + phase)
    positions = center + radius * (angles.cos()[:, None] * e1 + angles.sin()[:, None] * e2) + heights.mean() * up
    return look_at_poses(positions, center, up).to(camera_to_worlds)


def roll_degrees(camera_to_worlds: Float[Tensor, "n 3 4"], up: Float[Tensor, "3"]) -> Float[Tensor, " n"]:
    """Roll of each camera against ``up``: the angle between its x axis and the plane perpendicular to up
    (0 for an upright camera), in degrees. A camera looking straight along ``up`` has no defined roll."""
    right = camera_to_worlds[:, :, 0].double()
    sines = (right @ up.double().to(right.device)).abs().clamp(max=1.0)
    return torch.rad2deg(torch.asin(sines))


def video_poses(
    camera_to_worlds: Float[Tensor, "views 3 4"],
    scene_type: str,
    num_poses: int,
    focus_depth: Optional[float] = None,
    focus: Optional[Float[Tensor, "3"]] = None,
    coverage_degrees: float = 0.0,
    radius_scale: float = 1.0,
    rotations: float = 1.0,
) -> Float[Tensor, "num_poses 3 4"]:
    """The video path a scene needs: forward-facing scenes the LLFF / TensoRF spiral of
    ``novel_views.spiral_poses`` (the novel-view rays' path) looking at ``focus_depth`` in front of them; object and 360 scenes an orbit around ``focus`` (a full circle when
    the training cameras cover at least ``FULL_ORBIT_MIN_COVERAGE`` degrees or the scene is 360)."""
    if scene_type == "forward-facing":
        if focus_depth is None:
            raise ValueError("a forward-facing video path needs the focus depth")
        return spiral_poses(
            camera_to_worlds, focus_depth, num_poses, rotations, radius_scale, zrate=0.5, min_radius_ratio=MIN_RADIUS_RATIO
        )
    if focus is None:
        raise ValueError(f"a video path around an {scene_type} scene needs its focus point")
    full = scene_type == "360" or coverage_degrees >= FULL_ORBIT_MIN_COVERAGE
    return orbit_poses(camera_to_worlds, focus, num_poses, full_circle=full, radius_scale=radius_scale)
