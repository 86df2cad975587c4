"""Videos of a trained run: the scene's camera path as nerfstudio Cameras, ``ns-render spiral`` taught to use
it, and progress lines that read well in a log file.

``ns-render spiral`` builds its path with nerfstudio's ``get_spiral_path`` from the first test camera, with
that camera's z axis as "up" (rolled frames on forward-facing scenes) and a fixed radius in scene units; it
offers no hook for a method's own path. As with checkpoint loading (``checkpoints.py``), FrugalPipeline
replaces the function in ``nerfstudio.scripts.render`` when that module is running, and only for FrugalNeRF
pipelines; every other method keeps nerfstudio's path.
"""

from __future__ import annotations

import sys
import weakref
from typing import Optional

from nerfstudio.cameras.cameras import Cameras

from frugalnerf_ns.data.novel_cameras import cameras_at
from frugalnerf_ns.progress import FrameProgress
from frugalnerf_ns.geometry.video_path import video_poses


def scene_video_cameras(datamanager, intrinsics: Cameras, num_frames: int, radius_scale: float = 1.0,
                        rotations: float = 1.0) -> Cameras:
    """The scene's video path (``video_path.video_poses``) from a FrugalDataManager's training cameras and
    scene analysis, with the intrinsics (and image size) of the camera ``intrinsics``."""
    layout, scene_type = datamanager.scene_layout, datamanager.scene_type
    forward = scene_type == "forward-facing"
    poses = video_poses(
        datamanager.train_dataset.cameras.camera_to_worlds, scene_type, num_frames,
        focus_depth=datamanager.spiral_focus_depth() if forward else None, focus=None if forward else layout.focus,
        coverage_degrees=layout.coverage_degrees, radius_scale=radius_scale, rotations=rotations,
    ).float()
    return cameras_at(poses, intrinsics)


def teach_ns_render_spiral(pipeline) -> bool:
    """Inside ``ns-render`` (its module is loaded), make ``spiral`` use the scene's path for this pipeline and
    report progress per frame. Returns whether ns-render is running."""
    render = sys.modules.get("nerfstudio.scripts.render")
    if render is None or not hasattr(render, "get_spiral_path"):
        return False
    original = getattr(render.get_spiral_path, "nerfstudio_original", render.get_spiral_path)
    owner = weakref.ref(pipeline)

    def get_spiral_path(camera: Cameras, steps: int = 30, radius: Optional[float] = None, **kwargs) -> Cameras:
        active = owner()
        if active is None:
            return original(camera, steps=steps, radius=radius, **kwargs)
        print(
            f"frugalnerf render: spiral of {steps} frames fitted to the training cameras ({active.datamanager.scene_type} "
            "scene: the LLFF spiral for forward-facing scenes, an orbit around the focus for objects); ns-render's "
            "--radius is not used; only the full scale is rendered"
        )
        active.model.frame_progress = FrameProgress(steps)
        return scene_video_cameras(active.datamanager, camera, steps).to(camera.device)

    get_spiral_path.nerfstudio_original = original  # type: ignore[attr-defined]
    render.get_spiral_path = get_spiral_path
    return True

