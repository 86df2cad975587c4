"""NeRF-synthetic (Blender) scenes: ``transforms_{train,val,test}.json`` with RGBA ``.png`` frames.

The few-shot protocol is DietNeRF's, which FreeNeRF reuses for its Blender numbers (both in
``DietNeRF-pytorch/dietnerf/`` of github.com/Jiawei-Yang/FreeNeRF: ``run_nerf.py``, ``load_blender.py`` and
``configs/freenerf_8v/``):
- training views: ``np.random.seed(0)`` then ``np.random.choice(train frames, max_train_views, replace=False)``;
  for 8 views that is train frames 26, 86, 2, 55, 75, 93, 16, 73 (``configs/splits.yaml``);
- test views: every 8th frame of ``transforms_test.json`` (``testskip`` 8): 25 views;
- images at half resolution (``half_res``: 800x800 -> 400x400 by area averaging, straight alpha), composited
  on white (``white_bkgd``) for the metrics; near / far 2 / 6.

View indices are positions in the JSON's ``frames`` list (frame i is ``r_i``; filename order would put r_10
before r_2). Training keeps the alpha channel: the model composites it on its own background, and the
datamanager marks the scene as an object with a plain background.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Optional, Tuple, Type

import numpy as np
import torch
from nerfstudio.cameras.cameras import Cameras, CameraType
from nerfstudio.data.dataparsers.base_dataparser import DataParser, DataparserOutputs
from nerfstudio.data.scene_box import SceneBox
from nerfstudio.utils.rich_utils import CONSOLE
from PIL import Image

from frugalnerf_ns.data.downscaled_images import downscaled_all
from frugalnerf_ns.data.input_checks import DataError
from frugalnerf_ns.data.dataparsers.common import FewShotDataParserConfig, check_images
from frugalnerf_ns.data.dataparsers.transforms_capture import (
    capture_outputs,
    capture_reasons,
    file_camera,
    per_frame_intrinsics,
)
from frugalnerf_ns.data.splits import check_indices, dietnerf_train_views, load_split_table
from frugalnerf_ns.geometry.scene_analysis import FOCUS_BOX_SCALE

SPLIT_FILES = {"train": "transforms_train.json", "val": "transforms_val.json", "test": "transforms_test.json"}
PROTOCOL_WIDTH = 400
"""The few-shot protocol's image width (half of the 800x800 originals)."""


@dataclass
class BlenderDataParserConfig(FewShotDataParserConfig):
    """NeRF-synthetic layout: transforms_train.json / transforms_test.json (camera_angle_x, frames with
    file_path and a camera-to-world transform_matrix), RGBA .png frames. Indices count in each JSON's frame
    order: --train-views in transforms_train.json, --test-views in transforms_test.json."""

    _target: Type = field(default_factory=lambda: Blender)
    downscale_factor: Optional[int] = None
    """Image downscale (area average). Default: to the protocol's 400 pixels wide (2 for the 800x800
    originals; 1 for images already that small)."""
    test_every: Optional[int] = None
    """Test on every n-th frame of transforms_test.json when --test-views is empty (default: the protocol's 8)."""
    near: float = 2.0
    """Nearest distance from a camera to the object (Blender convention)."""
    far: float = 6.0
    """Farthest distance from a camera to the object (Blender convention)."""
    scene_radius: float = 1.5
    """Half-size of the modelled box around the origin (TensoRF's and nerfstudio's box for these scenes)."""
    capture: Optional[bool] = None
    """Read the scene as a real capture (instant-ngp's and TensoRF's custom-data files): the file's intrinsics and
    distortion, a box around the cameras' focus with the space beyond it, no white background. Default: a capture
    when its frames have no alpha, the file states fl_x / cx / distortion, or a camera stands off NeRF-synthetic's
    4-unit sphere; False reads it as NeRF-synthetic."""
    ndc: Optional[bool] = None
    """A capture only: model it in NDC (default: when its training cameras are forward-facing, as LLFF)."""
    focus_box_scale: float = FOCUS_BOX_SCALE
    """A capture only: half the side of the box around the training cameras' focus, in farthest-camera distances."""


class Blender(DataParser):
    config: BlenderDataParserConfig

    def _generate_dataparser_outputs(self, split: str = "train", **kwargs) -> DataparserOutputs:
        data = Path(self.config.data)
        table = load_split_table()["blender"]
        source = "train" if split == "train" else "test"
        meta, frames = read_transforms(data / SPLIT_FILES[source])
        indices = self._indices(source, len(frames), table)
        files = [frame_image(data, frames[i], data / SPLIT_FILES[source], i) for i in indices]
        check_images(files)
        capture = self._capture(data, table)
        if capture is not None:
            say = CONSOLE.print if split == "train" else (lambda _: None)
            return capture_outputs(self.config, data, split, *capture, say)
        with Image.open(files[0]) as img:
            full_width, full_height = img.size
        factor = self.config.downscale_factor or max(1, full_width // PROTOCOL_WIDTH)
        if factor < 1:
            raise DataError(f"--downscale-factor must be >= 1 (got {factor})")
        files = downscaled_all(files, factor, data, CONSOLE.print) if factor > 1 else files
        width, height = full_width // factor, full_height // factor
        focal = 0.5 * width / math.tan(0.5 * camera_angle(meta, data / SPLIT_FILES[source]))
        c2w = torch.tensor(np.stack([pose_of(frames[i], data / SPLIT_FILES[source], i) for i in indices]))
        cameras = Cameras(
            camera_to_worlds=c2w[:, :3, :4].float(),
            fx=focal,
            fy=focal,
            cx=width / 2.0,
            cy=height / 2.0,
            width=width,
            height=height,
            camera_type=CameraType.PERSPECTIVE,
        )
        r = self.config.scene_radius
        if split == "train":
            CONSOLE.print(
                f"frugalnerf: Blender scene, {len(indices)} training views {indices} of {len(frames)} in "
                f"{SPLIT_FILES['train']}, {width}x{height} (downscale {factor}); {self._synthetic_why}"
                + ("" if self.config.capture is False else " (`frugal-blender --capture True` reads it as a real capture)")
            )
        return DataparserOutputs(
            image_filenames=files,
            cameras=cameras,
            scene_box=SceneBox(aabb=torch.tensor([[-r, -r, -r], [r, r, r]], dtype=torch.float32)),
            metadata={"near_far": (self.config.near, self.config.far)},
        )

    def _capture(self, data: Path, table: Dict):
        """(train frames and poses, test frames and poses, the file's camera, why) when the scene is a real
        capture (``capture_reasons``, or --capture True), else None."""
        path = data / SPLIT_FILES["train"]
        meta, frames = read_transforms(path)
        centres = np.stack([pose_of(frame, path, i)[:3, 3] for i, frame in enumerate(frames)])
        first = frame_image(data, frames[0], path, 0)
        check_images([first])
        reasons = capture_reasons(meta, first, centres, self.config.scene_radius, self.config.far)
        wanted = self.config.capture if self.config.capture is not None else bool(reasons)
        if not wanted:
            distance = np.linalg.norm(centres, axis=-1)
            self._synthetic_why = (
                "NeRF-synthetic: RGBA frames, camera_angle_x only, cameras "
                f"{distance.min():.2f}-{distance.max():.2f} from the origin" if not reasons else
                f"read as NeRF-synthetic (`frugal-blender --capture False`) though {'; '.join(reasons)}")
            return None
        reasons = reasons or ["`frugal-blender --capture True`"]
        splits, metas = {}, {}
        for source in ("train", "test"):
            path = data / SPLIT_FILES[source]
            meta, frames = read_transforms(path)
            indices = self._indices(source, len(frames), table)
            files = [frame_image(data, frames[i], path, i) for i in indices]
            check_images(files)
            poses = np.stack([pose_of(frames[i], path, i) for i in indices])
            splits[source], metas[source] = (files, poses), (meta, frames, path)
        with Image.open(splits["train"][0][0]) as img:
            size = img.size
        cameras = []
        for meta, frames, path in metas.values():
            per_frame_intrinsics(frames, path)
            cameras.append(file_camera(meta, size, path))
        if cameras[0] != cameras[1]:
            raise DataError(f"{data}: {SPLIT_FILES['train']} and {SPLIT_FILES['test']} state different cameras "
                            f"({cameras[0]} / {cameras[1]}); one camera is read for both")
        return splits["train"], splits["test"], cameras[0], reasons

    def _indices(self, source: str, num_frames: int, table: Dict) -> List[int]:
        what = str(Path(self.config.data) / SPLIT_FILES[source])
        if source == "test":
            every = self.config.test_every or int(table["test_every"])
            indices = list(self.config.test_views) or list(range(0, num_frames, every))
            check_indices(indices, num_frames, "test", what)
            return indices
        if self.config.train_views:
            indices = list(self.config.train_views)
        else:
            count = int(table["num_train_views"]) if self.config.num_train_views is None else self.config.num_train_views
            if not 1 <= count <= num_frames:
                raise DataError(f"{what}: --num-train-views {count} must be between 1 and its {num_frames} frames")
            known = {int(k): v for k, v in table["train_views"].items()}
            indices = list(known[count]) if count in known and num_frames == 100 else dietnerf_train_views(num_frames, count)
        check_indices(indices, num_frames, "train", what)
        return indices


def read_transforms(path: Path) -> Tuple[Dict, List[Dict]]:
    if not path.is_file():
        raise DataError(f"{path} not found (Blender layout: transforms_train.json and transforms_test.json)")
    try:
        meta = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as err:
        raise DataError(f"{path} is not valid JSON ({err})") from None
    frames = meta.get("frames") if isinstance(meta, dict) else None
    if not isinstance(frames, list) or not frames:
        raise DataError(f"{path} has no frames")
    return meta, frames


def camera_angle(meta: Dict, path: Path) -> float:
    angle = meta.get("camera_angle_x")
    if not isinstance(angle, (int, float)) or not 0 < angle < math.pi:
        raise DataError(f"{path}: camera_angle_x must be a horizontal field of view in radians (got {angle!r})")
    return float(angle)


def pose_of(frame: Dict, path: Path, index: int) -> np.ndarray:
    try:
        pose = np.asarray(frame["transform_matrix"], dtype=np.float64)
    except (KeyError, TypeError, ValueError):
        pose = None
    if pose is None or pose.shape != (4, 4) or not np.isfinite(pose).all():
        raise DataError(f"{path}: frame {index} needs a finite 4x4 transform_matrix")
    return pose


def frame_image(data: Path, frame: Dict, path: Path, index: int) -> Path:
    """The frame's image: file_path relative to the scene, '.png' appended when it has no suffix."""
    name = frame.get("file_path")
    if not isinstance(name, str):
        raise DataError(f"{path}: frame {index} has no file_path")
    file = (data / name).resolve()
    return file if file.suffix else file.with_name(file.name + ".png")


def is_blender_layout(data: Path) -> bool:
    return all((data / SPLIT_FILES[s]).is_file() for s in ("train", "test"))
