"""Real captures written in NeRF-synthetic's file names (``transforms_train.json`` / ``transforms_test.json``), as
instant-ngp's ``colmap2nerf.py`` and TensoRF's custom-data scripts write them: the file states its own intrinsics
(``fl_x``, ``fl_y``, ``cx``, ``cy``, ``w``, ``h``) and OpenCV distortion (``k1``, ``k2``, ``k3``, ``p1``, ``p2``),
the frames are photos without alpha, and the cameras stand wherever the capture put them.

Read as NeRF-synthetic, such a scene loses its principal point and distortion and is cut to a 3-unit box on white
(a room then renders as the box's faces). Here it is read as a capture: the file's intrinsics, the frames undistorted
into the scene's cache (the pinhole model every other part of the method assumes), and the scene modelled as posed
LLFF captures are (``llff.scene_space``): a box around the training cameras' focus with the space beyond it, or NDC
when the training cameras are forward-facing; near and far from the training views' triangulated points.
"""

from __future__ import annotations

import hashlib
import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Dict, List, Optional, Sequence, Tuple

import numpy as np
import torch
from nerfstudio.data.dataparsers.base_dataparser import DataparserOutputs
from PIL import Image, UnidentifiedImageError

from frugalnerf_ns.cache import scene_cache_dir, write_atomically
from frugalnerf_ns.data.dataparsers.llff import forward_facing_outputs, scene_space
from frugalnerf_ns.data.downscaled_images import area_downscale, factor_for_long_side
from frugalnerf_ns.data.input_checks import DataError
from frugalnerf_ns.data.scene_bounds import FAR_OVER_NEAR, near_far_from_points, training_points
from frugalnerf_ns.geometry.camera_conventions import average_pose

INTRINSIC_KEYS = ("fl_x", "fl_y", "cx", "cy")
DISTORTION_KEYS = ("k1", "k2", "p1", "p2", "k3")
"""OpenCV's order (cv2.undistort's distCoeffs: k1, k2, p1, p2, k3)."""
COPIES_VERSION = 1
BD_FACTOR = 0.75
"""The nearest point lands at 1 / BD_FACTOR from the cameras (NeRF's LLFF loader, as photos without cameras)."""


@dataclass(frozen=True)
class FileCamera:
    """The pinhole camera and distortion a transforms file states for its frames, at ``width`` x ``height``."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    distortion: Tuple[float, float, float, float, float]

    def downscaled(self, factor: int) -> "FileCamera":
        """The camera of the frames area-downscaled by ``factor`` (``area_downscale`` drops the last partial blocks:
        the scale is exactly 1 / factor)."""
        return FileCamera(self.fx / factor, self.fy / factor, self.cx / factor, self.cy / factor,
                          self.width // factor, self.height // factor, self.distortion)

    @property
    def distorted(self) -> bool:
        return any(abs(k) > 0.0 for k in self.distortion)

    def matrix(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])


def capture_reasons(meta: Dict, first_frame: Path, centres: np.ndarray, box_radius: float, far: float) -> List[str]:
    """Why a scene in NeRF-synthetic's file names is a real capture (empty: it is NeRF-synthetic): frames without
    alpha, intrinsics or distortion stated in the file, a camera that NeRF-synthetic's modelling cannot hold (inside
    the ``box_radius`` box's sphere, or beyond the ``far`` bound from the origin; NeRF-synthetic's stand at 4.03)."""
    reasons = []
    with Image.open(first_frame) as img:
        if img.mode not in ("RGBA", "LA", "PA") and not (img.mode == "P" and "transparency" in img.info):
            reasons.append(f"its frames have no alpha ({first_frame.name}: {img.mode})")
    stated = [k for k in INTRINSIC_KEYS + DISTORTION_KEYS if k in meta]
    if stated:
        reasons.append(f"the file states {', '.join(stated)}")
    distance = np.linalg.norm(centres, axis=-1)
    if distance.size and (distance.min() < box_radius or distance.max() > far):
        reasons.append(f"its cameras stand {distance.min():.2f}-{distance.max():.2f} from the origin "
                       f"(NeRF-synthetic's: 4.03, within the box's {box_radius:g} and the far bound {far:g})")
    return reasons


def per_frame_intrinsics(frames: List[Dict], path: Path) -> None:
    """One camera per file: a frame stating its own intrinsics or distortion stops with one line."""
    for index, frame in enumerate(frames):
        own = [k for k in INTRINSIC_KEYS + DISTORTION_KEYS + ("w", "h") if k in frame]
        if own:
            raise DataError(f"{path}: frame {index} states its own {', '.join(own)}; one camera per file is read "
                            "(the nerfstudio layout, transforms.json, reads a camera per frame)")


def file_camera(meta: Dict, image_size: Tuple[int, int], path: Path) -> FileCamera:
    """The file's camera (instant-ngp's keys; a field of view where no focal length is given), at the size it
    states (``w``, ``h``), else the frames' size."""
    width, height = int(meta.get("w", image_size[0])), int(meta.get("h", image_size[1]))

    def number(key: str, default: Optional[float]) -> float:
        value = meta.get(key, default)
        if not isinstance(value, (int, float)) or not math.isfinite(value):
            raise DataError(f"{path}: {key} must be a number (got {value!r})")
        return float(value)

    if "fl_x" in meta:
        fx = number("fl_x", None)
    elif "camera_angle_x" in meta:
        fx = 0.5 * width / math.tan(0.5 * number("camera_angle_x", None))
    else:
        raise DataError(f"{path}: neither fl_x nor camera_angle_x gives the focal length")
    if "fl_y" in meta:
        fy = number("fl_y", None)
    elif "camera_angle_y" in meta:
        fy = 0.5 * height / math.tan(0.5 * number("camera_angle_y", None))
    else:
        fy = fx
    camera = FileCamera(fx, fy, number("cx", width / 2.0), number("cy", height / 2.0), width, height,
                        tuple(number(k, 0.0) for k in DISTORTION_KEYS))  # type: ignore[arg-type]
    if fx <= 0 or fy <= 0 or width <= 0 or height <= 0:
        raise DataError(f"{path}: focal lengths and image size must be positive (fl_x {fx}, fl_y {fy}, {width}x{height})")
    if meta.get("is_fisheye") or float(meta.get("k4", 0.0) or 0.0) != 0.0:
        raise DataError(f"{path}: a fisheye camera (is_fisheye / k4) is not read (pinhole and OpenCV distortion are)")
    if meta.get("camera_model", "OPENCV") not in ("OPENCV", "PINHOLE", "SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL"):
        raise DataError(f"{path}: camera_model {meta['camera_model']!r} is not read (pinhole and OpenCV distortion are)")
    return camera


def working_copies(
    files: Sequence[Path], camera: FileCamera, factor: int, data: Path, say: Callable[[str], None]
) -> List[Path]:
    """Each frame as RGB, undistorted with the file's OpenCV distortion (the same pinhole matrix after) and then
    area-downscaled by ``factor``: written once into the scene's cache, reused while newer than the frame."""
    key = hashlib.sha256(json.dumps([COPIES_VERSION, factor, camera.matrix().round(6).tolist(),
                                     [round(k, 9) for k in camera.distortion]]).encode()).hexdigest()[:12]
    folder = scene_cache_dir(data, say) / f"capture_frames_{key}"
    out = []
    for path in files:
        target = folder / path.resolve().relative_to(data.resolve()).with_suffix(".png") \
            if path.resolve().is_relative_to(data.resolve()) else folder / (path.stem + ".png")
        if not (target.is_file() and target.stat().st_mtime >= path.stat().st_mtime):
            try:
                with Image.open(path) as img:
                    pixels = np.asarray(img.convert("RGB"))
            except (UnidentifiedImageError, SyntaxError, OSError) as err:
                raise DataError(f"image file {path} is unreadable or corrupt ({err})") from None
            if (pixels.shape[1], pixels.shape[0]) != (camera.width, camera.height):
                raise DataError(f"{path} is {pixels.shape[1]}x{pixels.shape[0]}; its transforms file says "
                                f"{camera.width}x{camera.height}")
            if camera.distorted:
                import cv2  # nerfstudio's dependency; only distorted captures need it

                # OpenCV puts pixel centres at integers, the file (COLMAP's, nerfstudio's) at +0.5: half a pixel off.
                opencv = camera.matrix()
                opencv[:2, 2] -= 0.5
                pixels = cv2.undistort(pixels, opencv, np.asarray(camera.distortion))
            small = Image.fromarray(area_downscale(pixels, factor) if factor > 1 else pixels)
            target.parent.mkdir(parents=True, exist_ok=True)
            write_atomically(target, lambda f: small.save(f, format="PNG"))
        out.append(target)
    return out


def capture_outputs(
    config, data: Path, split: str, train: Tuple[List[Path], np.ndarray], test: Tuple[List[Path], np.ndarray],
    camera: FileCamera, reasons: List[str], say: Callable[[str], None],
) -> DataparserOutputs:
    """The outputs of a real capture in NeRF-synthetic's files: ``train`` / ``test`` are (frames, OpenGL
    camera-to-worlds) of each split; ``camera`` the file's (for both files: one camera)."""
    factor = config.downscale_factor or factor_for_long_side(camera.width, camera.height)
    if factor < 1:
        raise DataError(f"--downscale-factor must be >= 1 (got {factor})")
    if config.focus_box_scale <= 0:
        raise DataError(f"--focus-box-scale must be positive (got {config.focus_box_scale})")
    work = camera.downscaled(factor)
    train_files = working_copies(train[0], camera, factor, data, say)
    c2w_train = train[1][:, :3, :4].astype(np.float64)
    # For near and far only: training triangulates again with its own options in the model's frame, and checks the
    # cameras there.
    sparse = training_points(train_files, c2w_train, [(work.fx, work.fy, work.cx, work.cy)] * len(train_files),
                             scene_cache_dir(data, say) / "capture_points.npz", say)
    bounds = near_far_from_points(sparse, c2w_train)
    if bounds is None:
        # Too few points to say: a tenth of the cameras' spread.
        spread = float(np.linalg.norm(c2w_train[:, :3, 3] - c2w_train[:, :3, 3].mean(0), axis=-1).max()) or 1.0
        bounds = (0.1 * spread, FAR_OVER_NEAR * 0.1 * spread)
    near, far = bounds[0], max(bounds[1], FAR_OVER_NEAR * bounds[0])
    scale = 1.0 / (near * BD_FACTOR)
    frame = np.eye(4)
    frame[:3] = average_pose(c2w_train)
    to_frame = np.linalg.inv(frame)

    def moved(c2w: np.ndarray) -> np.ndarray:
        out = to_frame[None, :3, :3] @ c2w[:, :3, :4]
        out[:, :, 3] = (out[:, :, 3] + to_frame[:3, 3]) * scale
        return out

    c2w_model = moved(c2w_train)
    ndc, box = scene_space(c2w_model, config.ndc, config.focus_box_scale)
    if split == "train":
        where = "in NDC (forward-facing)" if ndc else "in a box around the training cameras' focus with the space beyond it"
        undistorted = f"undistorted (k1 k2 p1 p2 k3 = {' '.join(f'{k:.4g}' for k in camera.distortion)})" \
            if camera.distorted else "no distortion"
        say(f"frugalnerf: {data}: a real capture in NeRF-synthetic's file names ({'; '.join(reasons)}): read with the "
            f"file's intrinsics (fl {camera.fx:.1f} {camera.fy:.1f}, principal point {camera.cx:.1f} {camera.cy:.1f} at "
            f"{camera.width}x{camera.height}), {undistorted}, {len(train_files)} views at {work.width}x{work.height}, "
            f"{sparse.num_points} points, modelled {where}; `frugal-blender --capture False` reads it as NeRF-synthetic")
        files, c2w = train_files, c2w_model
    else:
        files, c2w = working_copies(test[0], camera, factor, data, say), moved(test[1])
    transform = torch.from_numpy(to_frame[:3]).float()  # model = scale x (transform @ data)
    outputs = forward_facing_outputs(files, c2w, c2w_model, (work.fx, work.fy, work.cx, work.cy),
                                     (work.width, work.height), (near * scale, far * scale), ndc, float(scale), box,
                                     transform)
    return outputs
