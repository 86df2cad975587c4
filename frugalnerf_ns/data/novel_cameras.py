"""The novel cameras training samples rays from (paper Sec. 3.5 "novel pose sampling"), and nerfstudio
``Cameras`` at any poses (the novel-view rays and the videos share them). The poses themselves are pure
geometry (``novel_views.py``, ``video_path.py``); this module picks the path and gives the poses intrinsics."""

from __future__ import annotations

from typing import Callable, Tuple

from jaxtyping import Float
from nerfstudio.cameras.cameras import Cameras
from torch import Tensor

from frugalnerf_ns.geometry.novel_views import spiral_poses
from frugalnerf_ns.geometry.scene_analysis import SURROUND_MIN_COVERAGE, CameraLayout
from frugalnerf_ns.geometry.video_path import orbit_poses


def cameras_at(poses: Float[Tensor, "n 3 4"], camera) -> Cameras:
    """nerfstudio Cameras at ``poses`` with the pinhole intrinsics and image size of the first camera of
    ``camera`` (novel-view rays, videos)."""
    one = camera.reshape(-1)[:1].to("cpu")
    n = poses.shape[0]
    return Cameras(
        camera_to_worlds=poses, fx=one.fx.expand(n, 1), fy=one.fy.expand(n, 1), cx=one.cx.expand(n, 1),
        cy=one.cy.expand(n, 1), width=one.width.expand(n, 1), height=one.height.expand(n, 1),
        camera_type=one.camera_type.expand(n, 1),
    )


def novel_view_poses(
    camera_to_worlds: Float[Tensor, "views 3 4"],
    scene_type: str,
    layout: CameraLayout,
    focus_depth: Callable[[], float],
    num_poses: int,
    rotations: float,
    radius_scale: float,
    zrate: float,
) -> Tuple[Float[Tensor, "poses 3 4"], str]:
    """(poses, path name): the paper's spiral around the mean training pose, looking at ``focus_depth()`` in
    front of it; or, for an object the training cameras surround (NeRF-synthetic), where a mean pose would sit
    inside the object, one turn around it at the cameras' mean distance and height ("orbit")."""
    if scene_type == "object" and layout.coverage_degrees >= SURROUND_MIN_COVERAGE:
        return orbit_poses(camera_to_worlds, layout.focus, num_poses, full_circle=True), "orbit"
    return spiral_poses(camera_to_worlds, focus_depth(), num_poses, rotations, radius_scale, zrate), "spiral"
